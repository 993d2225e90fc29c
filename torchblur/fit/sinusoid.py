"""Batched sinusoid fitting: amplitude and phase of a spot's motion from blurred images.

Every problem (a frequency, a spot) of a batch is fitted at once. Starts come from the
closed-form moments (every root, the alias pair included), all refined together; with two
or more exposures of the same motion the fit is joint and the alias is gone. The result
carries the Fisher-information uncertainty of each estimate and a status per item, so a
dark frame or a spot out of frame is flagged and never stops or poisons the batch.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields

import torch

from torchblur.render.alias import alias_phase as _alias_phase
from torchblur.render.alias import wrap_phase
from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_tensor, as_unit_direction, check_choice, check_finite, check_positive,
                     check_real_scalar)
from torchblur.fit.losses import LOSSES, image_loss, irls_weights
from torchblur.image.moments import image_moments, moments_along, sinusoid_from_moments
from torchblur.fit.optim import levenberg_marquardt, model_jacobian
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.blur import RenderSettings, choose_node_count, panel_count, quadrature_nodes, render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

from torchblur.fit.status import (  # noqa: F401  (re-exported: torchblur.fit.sinusoid.STATUS, ...)
    FLAGS, MASKED, NO_MOTION, NO_PIXELS, OUT_OF_FRAME, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED, STATUS,
)

__all__ = ["SinusoidFit", "fit_sinusoid", "STATUS", "FLAGS", "MASKED", "SATURATED_MASKED", "OUTLIERS_MASKED", "PARTLY_OUT_OF_FRAME",
           "NO_MOTION"]

OPTIMIZERS = ("lm", "adam", "lbfgs")
AXES = ("x", "y", "xy")
OUTLIERS = ("none", "reject")


@dataclass
class SinusoidFit:
    """Result of :func:`fit_sinusoid`; batch ``[...]`` is the images' leading dims.

    Attributes:
        amplitude: M (px), ``[...]`` (axes "x"/"y") or ``[..., 2]`` (axes "xy"), >= 0.
        phase: phi (rad, wrapped to (-pi, pi]), same shape.
        amplitude_std, phase_std: one standard deviation from the Fisher information at the
            solution (noise level given, or estimated from the residuals).
        alias_phase: the other branch for the first exposure (renders the same image as
            ``phase`` in that exposure), same shape as ``phase``.
        alias_cost: the loss at ``(amplitude, alias_phase)`` over all exposures, ``[...]``:
            equal to ``cost`` with one exposure, larger when the exposures resolve the alias.
        cost: the loss at the solution, ``[...]``.
        converged: ``[...]`` bool, ``status == 0``.
        status: ``[...]`` int, see :data:`STATUS`.
        covariance: ``[..., P, P]`` over every fitted parameter, in ``param_names`` order.
        param_names: names of the P parameters.
        noise_std: the pixel noise std used for the uncertainty, ``[...]``.
        scale, background, center: fitted nuisance parameters (None if not fitted).
        n_iter: optimiser iterations, ``[...]``.
        flags: ``[...]`` int, a bit field of :data:`FLAGS` (:data:`MASKED`,
            :data:`SATURATED_MASKED`, :data:`OUTLIERS_MASKED`, :data:`PARTLY_OUT_OF_FRAME`,
            :data:`NO_MOTION`); test a bit with ``(fit.flags & PARTLY_OUT_OF_FRAME) != 0``.
        n_masked: pixels excluded from the fit (every cause), ``[...]`` int.
        n_outliers: of which excluded by the robust pass (``outliers="reject"``), ``[...]`` int.
        background_plane: with ``fit_gradient``: the stray-light plane removed from each
            exposure, ``[..., E, 3]`` = (level at the frame centre, slope along x per px,
            slope along y per px), in image units; None otherwise.
    """

    amplitude: torch.Tensor
    phase: torch.Tensor
    amplitude_std: torch.Tensor
    phase_std: torch.Tensor
    alias_phase: torch.Tensor
    alias_cost: torch.Tensor
    cost: torch.Tensor
    converged: torch.Tensor
    status: torch.Tensor
    covariance: torch.Tensor
    param_names: tuple
    noise_std: torch.Tensor
    n_iter: torch.Tensor
    scale: torch.Tensor | None = None
    background: torch.Tensor | None = None
    center: torch.Tensor | None = None
    extras: dict = field(default_factory=dict)
    flags: torch.Tensor | None = None
    n_masked: torch.Tensor | None = None
    n_outliers: torch.Tensor | None = None
    background_plane: torch.Tensor | None = None


def _flatten_psf(psf, batch, N):
    if isinstance(psf, GaussianPSF):
        return GaussianPSF(psf.center.expand(batch + (2,)).reshape(N, 2), psf.cov.expand(batch + (2, 2)).reshape(N, 2, 2),
                           psf.amplitude.expand(batch).reshape(N))
    H, W = psf.frame_shape
    return KernelPSF(psf.kernel.expand(batch + (H, W)).reshape(N, H, W))


def _validate(images, psf, window, omega, axes, optimizer, loss):
    if not isinstance(images, torch.Tensor):
        raise InputTypeError(f"images: expected a tensor [..., E, H, W], got {type(images).__name__}")
    if not images.is_floating_point():
        images = images.to(torch.get_default_dtype())
    if images.dim() < 3:
        raise ShapeError(f"images: expected shape [..., E, H, W], got {tuple(images.shape)}")
    if images.numel() == 0:
        raise ShapeError(f"images: expected a non-empty batch, got shape {tuple(images.shape)}")
    check_finite(images, "images")
    if not isinstance(psf, (GaussianPSF, KernelPSF)):
        raise InputTypeError(f"psf: expected GaussianPSF or KernelPSF, got {type(psf).__name__}")
    if not isinstance(window, ExposureWindow):
        raise InputTypeError(f"window: expected an ExposureWindow, got {type(window).__name__}")
    if isinstance(axes, str):
        check_choice(axes, "axes", AXES)
    check_choice(optimizer, "optimizer", OPTIMIZERS)
    check_choice(loss, "loss", LOSSES)
    if optimizer == "lm" and loss == "linf":
        raise ParameterError("loss: 'linf' is not a sum of squares; use optimizer='adam' or 'lbfgs' with it")
    batch_e = images.shape[:-2]
    E = batch_e[-1]
    if window.shape and window.shape[-1] not in (1, E):
        raise ShapeError(f"window: expected a last dim of 1 or E={E} (one window per exposure), got shape {tuple(window.shape)}")
    try:
        torch.broadcast_shapes(window.shape, batch_e)
    except RuntimeError:
        raise ShapeError(f"window: expected a batch shape that broadcasts to the images' [..., E] = {tuple(batch_e)}, got {tuple(window.shape)}") from None
    omega = check_positive(as_tensor(omega, "omega", like=images), "omega")
    batch = images.shape[:-3]
    try:
        torch.broadcast_shapes(omega.shape, batch)
    except RuntimeError:
        raise ShapeError(f"omega: expected a shape that broadcasts to the images' batch {tuple(batch)}, got {tuple(omega.shape)}") from None
    try:
        torch.broadcast_shapes(psf.shape, batch)
    except RuntimeError:
        raise ShapeError(f"psf: expected a batch shape that broadcasts to the images' batch {tuple(batch)}, got {tuple(psf.shape)}") from None
    if isinstance(psf, KernelPSF) and psf.frame_shape != tuple(images.shape[-2:]):
        raise ShapeError(f"psf: expected a kernel of frame shape {tuple(images.shape[-2:])}, got {psf.frame_shape}")
    return images, omega


def _fit_core(
    images,
    psf,
    window: ExposureWindow,
    omega,
    *,
    axes="x",
    optimizer: str = "lm",
    loss: str = "l2",
    noise_std=None,
    mask=None,
    fit_scale: bool = False,
    fit_background: bool = False,
    fit_center: bool = False,
    normalize: bool = False,
    max_iter: int | None = None,
    tol: float = 1e-9,
    render_settings: RenderSettings | None = None,
) -> SinusoidFit:
    """One pass of :func:`fit_sinusoid` (its arguments, already checked there, less the robust
    options; ``axes`` a name or unit directions ``[N, 2]``); flags are set there."""
    dtype, device = images.dtype, images.device
    batch = images.shape[:-3]
    E, H, W = images.shape[-3:]
    N = max(1, math.prod(batch))
    data = images.reshape(N, E, H, W)
    win = window.to(dtype).expand(batch + (E,))
    start = win.start.reshape(N, E)
    dur = win.duration.reshape(N, E)
    om = omega.expand(batch).reshape(N)
    p_flat = _flatten_psf(psf.to(dtype) if isinstance(psf, GaussianPSF) else psf, batch, N)
    if isinstance(p_flat, GaussianPSF):
        rest, cov_psf = p_flat.center, p_flat.cov
    else:
        rest, cov_psf = p_flat.moments()

    # Weights and the noise level. ``row_weight [N]``: one weight per item (the same noise on
    # every pixel, nothing masked), then ``weight`` is a broadcast view of it, not a copy.
    row_weight = torch.ones(N, dtype=dtype, device=device)
    weight = row_weight[:, None, None, None].expand(N, E, H, W)
    sigma_given = None
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=data), "noise_std")
        if s.dim() >= 3 and s.shape[-3:] == (E, H, W):
            s = s.expand(batch + (E, H, W)).reshape(N, E, H, W)
        else:
            try:
                s = s.expand(batch).reshape(N, 1, 1, 1)
            except RuntimeError:
                raise ShapeError(f"noise_std: expected a number, [...] or [..., E, H, W], got {tuple(s.shape)}") from None
        sigma_level = s.reshape(N, -1).contiguous().median(-1).values
        sigma_given = s.expand(N, E, H, W)
        if s.shape[-3:] == (1, 1, 1):
            row_weight = 1 / s.reshape(N) ** 2
            weight = row_weight[:, None, None, None].expand(N, E, H, W)
        else:
            row_weight, weight = None, 1 / sigma_given**2
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError("mask: expected a bool tensor [..., E, H, W] (True = use the pixel)")
        try:
            m = mask.expand(batch + (E, H, W)).reshape(N, E, H, W)
        except RuntimeError:
            raise ShapeError(f"mask: expected shape [..., E, H, W] = {tuple(images.shape)}, got {tuple(mask.shape)}") from None
        weight = weight * m.to(dtype)
        row_weight = None

    # Degenerate items: no signal above the noise.
    flat = data.reshape(N, -1)
    # Background and noise level from ~1024-2048 pixels per item (a strided subsample: the
    # median of 1024 noise samples is within 0.04 std of the level, and a median costs a
    # selection per item).
    sub = flat[:, ::max(1, flat.shape[-1] // 1024)]
    med = sub.median(-1).values
    noise_level = sigma_level if sigma_given is not None else (sub - med[:, None]).abs().median(-1).values * 1.4826
    peak = (flat - med[:, None]).amax(-1)
    dark = ~(peak > 8 * noise_level.clamp_min(torch.finfo(dtype).tiny)) | (peak <= 0)

    # Closed-form starts from the moments of every exposure (both roots).
    thr = med[:, None] + 3 * noise_level[:, None]
    _, centroid, icov = image_moments(data, threshold=thr)  # [N, E, 2], [N, E, 2, 2]
    # The image direction of each fitted axis: D [N, n_axes, 2] (unit vectors).
    D = _axis_directions(axes, N, dtype, device)
    n_axes = D.shape[1]
    M_c, phi_c = [], []
    for k in range(n_axes):
        d = D[:, None, k]  # [N, 1, 2]
        mu1, vex = moments_along(centroid - rest[:, None], icov - cov_psf[:, None], d)
        M, phi = sinusoid_from_moments(mu1, vex, om[:, None], start, dur)  # [N, E], [N, E, 2]
        M_c.append(M)
        phi_c.append(torch.nan_to_num(phi, nan=0.0))
    # A motion larger than the frame cannot be measured: cap the starts (keeps the node count sane).
    diag = math.hypot(H, W)
    M_c = [m.clamp(max=diag) for m in M_c]
    # The rest position must be in the frame (3 sigma margin): otherwise flag, do not fit.
    sd = torch.diagonal(cov_psf, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    outside = ((rest < -3 * sd) | (rest > torch.tensor([W - 1, H - 1], dtype=dtype, device=device) + 3 * sd)).any(-1)
    # Candidates: the roots of the first exposure (the alias pair; four combinations for a
    # Lissajous motion). With two or more exposures the true root is the one the exposures
    # share (the aliases move with the window centre), so the single consensus root is
    # refined; items whose alias then fits better are refitted from it below.
    roots = [(r,) for r in range(2)] if n_axes == 1 else [(r0, r1) for r0 in range(2) for r1 in range(2)]

    def root_phases(e, rs):
        return torch.stack([phi_c[k][:, e, rs[k]] for k in range(n_axes)], -1)  # [N, n_axes]

    cands = [torch.cat([torch.stack([M_c[k][:, 0] for k in range(n_axes)], -1), root_phases(0, rs)], -1) for rs in roots]
    if E >= 2:
        # Compare with the exposure whose window centre best separates the alias (repeats of
        # the same window share the alias and would tell nothing).
        centre = om[:, None] * (start + dur / 2)
        sep = (centre - centre[:, :1]).sin().abs()  # [N, E]
        other = sep.argmax(-1)  # [N]
        phi_other = [p[torch.arange(N, device=device), other] for p in phi_c]  # [N, 2] per axis

        def other_phases(rs):
            return torch.stack([phi_other[k][:, rs[k]] for k in range(n_axes)], -1)

        dist = torch.stack([
            torch.stack([wrap_phase(root_phases(0, rs) - other_phases(r2)).abs().sum(-1) for r2 in roots], -1).amin(-1)
            for rs in roots], -1)  # [N, n_roots]
        pick = dist.argmin(-1)
        stacked = torch.stack(cands, 1)
        cands = [stacked[torch.arange(N, device=device), pick]]
        M_mean = torch.stack([M_c[k].mean(-1) for k in range(n_axes)], -1)
        cands[0][:, :n_axes] = M_mean
    K = len(cands)
    theta_core = torch.stack(cands, 1)  # [N, K, 2 n_axes]
    theta_core[..., :n_axes] = theta_core[..., :n_axes].clamp_min(1e-3)

    labels = ["u"] if isinstance(axes, torch.Tensor) else list(axes)
    names = [f"amplitude_{a}" for a in labels] + [f"phase_{a}" for a in labels]
    extra = []
    if fit_scale:
        names.append("scale")
        if isinstance(p_flat, GaussianPSF):
            expected = (p_flat.total_light()[:, None] * dur).sum(-1)
        else:
            expected = (p_flat.kernel.sum((-1, -2))[:, None] * dur).sum(-1)
        extra.append((data.sum((-1, -2, -3)) / expected.clamp_min(1e-30)).clamp_min(1e-3))
    if fit_background:
        names.append("background")
        extra.append(med)
    if fit_center:
        names += ["center_x", "center_y"]
        extra += [rest[:, 0], rest[:, 1]]
    P = len(names)
    if extra:
        ex = torch.stack(extra, -1)[:, None, :].expand(N, K, len(extra))
        theta0 = torch.cat([theta_core, ex], -1)
    else:
        theta0 = theta_core
    theta0 = theta0.reshape(N * K, P).detach()

    # Crop to the region the model can reach (l2): outside it (5.5 PSF sigmas beyond the
    # largest motion) the model and its Jacobian are below 3e-7 of the peak, far below any
    # camera's noise, so those pixels change nothing in the normal equations; their
    # constant contribution to the cost (and the noise estimate) is added back at the end.
    x0 = y0 = 0
    outside_cost = torch.zeros(N, dtype=dtype, device=device)
    outside_sq = torch.zeros(N, dtype=dtype, device=device)
    outside_n = torch.zeros(N, dtype=dtype, device=device)
    live_items = ~dark & ~outside
    if loss == "l2" and not normalize and not fit_background and bool(live_items.any()):
        reach = (D.abs() * (theta_core[..., :n_axes].amax(1) * 1.25 + 0.5)[..., None]).sum(1)  # [N, 2] px
        sdv = torch.diagonal(cov_psf, dim1=-2, dim2=-1).clamp_min(0).sqrt()
        lo = (rest - reach - 5.5 * sdv - (2.0 if fit_center else 0.0))[live_items].amin(0)
        hi = (rest + reach + 5.5 * sdv + (2.0 if fit_center else 0.0))[live_items].amax(0)
        cx0, cy0 = max(0, int(math.floor(float(lo[0])))), max(0, int(math.floor(float(lo[1]))))
        cx1, cy1 = min(W, int(math.ceil(float(hi[0]))) + 1), min(H, int(math.ceil(float(hi[1]))) + 1)
        if cx1 - cx0 >= 4 and cy1 - cy0 >= 4 and (cx1 - cx0) * (cy1 - cy0) < 0.9 * H * W:
            bands = ((slice(None, cy0), slice(None)), (slice(cy1, None), slice(None)),
                     (slice(cy0, cy1), slice(None, cx0)), (slice(cy0, cy1), slice(cx1, None)))

            def out_sum(f):  # f(band index) -> [N, E, h, w]: summed over the pixels outside the crop -> [N]
                return sum(f(b).sum((-1, -2, -3)) for b in bands)

            def sq(b):
                d = data[(..., *b)]
                return d * d

            if row_weight is not None:
                outside_sq = out_sum(sq)
                outside_cost = row_weight * outside_sq
                outside_n.fill_(E * (H * W - (cy1 - cy0) * (cx1 - cx0)))
            else:
                outside_cost = out_sum(lambda b: weight[(..., *b)] * sq(b))
                outside_sq = out_sum(lambda b: (weight[(..., *b)] > 0) * sq(b))
                outside_n = out_sum(lambda b: (weight[(..., *b)] > 0).to(dtype))
            x0, y0 = cx0, cy0
            data = data[..., cy0:cy1, cx0:cx1]
            weight = weight[..., cy0:cy1, cx0:cx1]
            H, W = cy1 - cy0, cx1 - cx0
            shift = torch.tensor([x0, y0], dtype=dtype, device=device)
            if isinstance(p_flat, GaussianPSF):
                p_flat = GaussianPSF(p_flat.center - shift, p_flat.cov, p_flat.amplitude)
            else:
                p_flat = KernelPSF(p_flat.kernel[..., cy0:cy1, cx0:cx1])
            if fit_center:
                j_c = names.index("center_x")
                theta0 = theta0.clone()
                theta0[:, j_c:j_c + 2] -= shift

    # Node counts fixed for the whole fit, from a generous motion bound: one count for the
    # rendered model (``settings.nodes``) and, for the analytic Jacobian path, one per frame
    # (``panels [N, E]``): a short exposure or a small motion needs far fewer nodes than the
    # batch's longest streak, and the splat's cost is proportional to them.
    # A fit needs the model far below the noise, not to round-off: panels of 3.5 PSF widths
    # (quadrature error < 1e-6 of the peak; estimates move < 2e-7 of their std vs 2.5).
    settings = render_settings or RenderSettings(panel_path_sigmas=3.5)
    panels = None
    if settings.nodes is None:
        amp_bound = (theta_core[..., :n_axes].amax(1) * 1.2 + 0.5)  # [N, n_axes]
        amp_xy = (D.abs() * amp_bound[..., None]).sum(1)
        path = Sinusoid(amp_xy[:, None, :], torch.zeros(N, 1, 2, dtype=dtype, device=device), om[:, None]).path_length(
            ExposureWindow(torch.zeros_like(dur), dur))
        smin = p_flat.sigma_min()[:, None]
        span = om[:, None] * dur  # [N, E]
        S = choose_node_count(path, smin, settings, span)
        panels = panel_count(path, smin, settings, span)
        settings = dataclasses.replace(settings, nodes=S)

    prob_of = lambda idx: torch.div(idx, K, rounding_mode="floor")  # noqa: E731

    def model_fn(theta, idx, k_of=prob_of):
        n = k_of(idx)
        amp = theta[:, :n_axes]
        ph = theta[:, n_axes:2 * n_axes]
        if n_axes == 2:
            amp_xy, ph_xy = amp, ph
        else:  # a motion along the direction D[n, 0]
            amp_xy, ph_xy = amp * D[n, 0], torch.cat([ph, ph], -1)
        j = 2 * n_axes
        scale = theta[:, j] if fit_scale else None
        j += int(fit_scale)
        bg = theta[:, j] if fit_background else None
        j += int(fit_background)
        if isinstance(p_flat, GaussianPSF):
            c = theta[:, j:j + 2] if fit_center else p_flat.center[n]
            psf_n = GaussianPSF(c[:, None, :], p_flat.cov[n][:, None], p_flat.amplitude[n][:, None])
        else:
            psf_n = KernelPSF(p_flat.kernel[n][:, None])
        traj = Sinusoid(amp_xy[:, None, :], ph_xy[:, None, :], om[n][:, None])
        img = render_blur(traj, psf_n, ExposureWindow(start[n], dur[n]), height=H, width=W, settings=settings)
        if scale is not None:
            img = img * scale[:, None, None, None]
        if bg is not None:
            img = img + bg[:, None, None, None]
        if normalize:
            img = img / img.square().sum((-1, -2), keepdim=True).sqrt().clamp_min(1e-30)
        return img.reshape(img.shape[0], -1)

    analytic = isinstance(p_flat, GaussianPSF) and not normalize and not settings.pixel_integration
    if analytic:
        m_nodes = settings.nodes_per_panel
        if panels is None or settings.nodes % m_nodes:  # nodes given by the caller: one rule for every frame
            m_nodes = settings.nodes if settings.nodes % m_nodes else m_nodes
            panels = torch.full((N, E), settings.nodes // m_nodes, dtype=torch.long, device=device)
        else:
            panels = _merge_panel_groups(panels, m_nodes, _CALL_NODE_PIXELS / (H * W))
        rules = {}  # panel count -> (tau [S], weights [S])
        A_all, B_all, C_all = p_flat.precision()

    def splat_frames(theta_f, n_f, e_f, n_panels, with_jac=True):
        """Image ``[m, H, W]`` and Jacobian ``[m, P, H, W]`` (``[m, 0, H, W]`` without
        ``with_jac``) of ``m`` frames (problem ``n_f``, exposure ``e_f``, parameters
        ``theta_f [m, P]``) on a rule of ``n_panels`` panels."""
        from torchblur.render.splat import gaussian_splat_with_jacobian

        if n_panels not in rules:
            rules[n_panels] = quadrature_nodes(n_panels, m_nodes, dtype=dtype, device=device)
        tau, wq = rules[n_panels]
        t0, d0 = start[n_f, e_f], dur[n_f, e_f]
        t = t0[:, None] + d0[:, None] * tau  # [m, S]
        w = d0[:, None] * wq * p_flat.amplitude[n_f][:, None]
        j = 2 * n_axes + int(fit_scale) + int(fit_background)
        c = theta_f[:, j:j + 2] if fit_center else p_flat.center[n_f]
        arg = om[n_f][:, None, None] * t[..., None] + theta_f[:, None, n_axes:2 * n_axes]  # [m, S, n_axes]
        sn, cs = torch.sin(arg), torch.cos(arg)
        amp = theta_f[:, None, :n_axes]
        disp = amp * sn
        dpx = torch.zeros(t.shape + (P,), dtype=dtype, device=device)
        dpy = torch.zeros_like(dpx)
        px = c[:, 0, None].expand(t.shape)
        py = c[:, 1, None].expand(t.shape)
        for k in range(n_axes):  # each fitted axis moves the spot along its direction
            ux, uy = D[n_f, k, 0, None], D[n_f, k, 1, None]  # [m, 1]
            dpx[..., k], dpy[..., k] = ux * sn[..., k], uy * sn[..., k]
            dpx[..., n_axes + k], dpy[..., n_axes + k] = ux * (amp * cs)[..., k], uy * (amp * cs)[..., k]
            px = px + ux * disp[..., k]
            py = py + uy * disp[..., k]
        if fit_center:
            dpx[..., j] = 1
            dpy[..., j + 1] = 1
        if not with_jac:
            dpx, dpy = dpx[..., :0], dpy[..., :0]
        return gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A_all[n_f], B_all[n_f], C_all[n_f], H, W)

    def image_fn(theta, idx, k_of=prob_of):
        """Model ``[n, R]`` alone from the same splat as :func:`jac_fn`."""
        n = k_of(idx)
        rows = theta.shape[0]
        pc = panels[n]  # [rows, E]
        img = theta.new_empty(rows, E, H, W)
        for u in torch.unique(pc).tolist():
            r_f, e_f = (pc == u).nonzero(as_tuple=True)
            img[r_f, e_f] = splat_frames(theta[r_f], n[r_f], e_f, u, with_jac=False)[0]
        if fit_scale:
            img = img * theta[:, 2 * n_axes, None, None, None]
        if fit_background:
            img = img + theta[:, 2 * n_axes + int(fit_scale), None, None, None]
        return img.reshape(rows, -1)

    def jac_fn(theta, idx, k_of=prob_of):
        """Model ``[n, R]`` and its Jacobian ``[n, R, P]`` from the splat (Gaussian PSF),
        frames grouped by their node count."""
        n = k_of(idx)
        rows = theta.shape[0]
        pc = panels[n]  # [rows, E]
        counts = torch.unique(pc).tolist()
        J = theta.new_empty(rows, P, E, H, W)  # parameter-major: the normal equations are then plain GEMMs
        if len(counts) == 1:
            r_f = torch.arange(rows, device=device).repeat_interleave(E)
            e_f = torch.arange(E, device=device).repeat(rows)
            img, dimg = splat_frames(theta[r_f], n[r_f], e_f, counts[0])
            img = img.reshape(rows, E, H, W)
            J.copy_(dimg.reshape(rows, E, P, H, W).transpose(1, 2))
        else:
            img = theta.new_empty(rows, E, H, W)
            for u in counts:
                r_f, e_f = (pc == u).nonzero(as_tuple=True)
                img[r_f, e_f], J[r_f, :, e_f] = splat_frames(theta[r_f], n[r_f], e_f, u)
        model = img
        if fit_scale:
            j = 2 * n_axes
            J.mul_(theta[:, j, None, None, None, None])
            J[:, j] = img
            model = model * theta[:, j, None, None, None]
        if fit_background:
            model = model + theta[:, 2 * n_axes + int(fit_scale), None, None, None]
            J[:, 2 * n_axes + int(fit_scale)] = 1
        J = J.reshape(rows, P, E * H * W).transpose(1, 2)
        return model.reshape(rows, -1), J

    target = data
    if normalize:
        target = data / data.square().sum((-1, -2), keepdim=True).sqrt().clamp_min(1e-30)
    target_k = target.reshape(N, 1, -1).expand(N, K, E * H * W).reshape(N * K, -1)
    weight_k = weight.reshape(N, 1, -1).expand(N, K, E * H * W).reshape(N * K, -1)

    def project(theta):
        return theta

    live = (~dark & ~outside).repeat_interleave(K)
    live_idx = torch.arange(N * K, device=device)[live]
    theta = theta0.clone()
    cost = torch.full((N * K,), float("inf"), dtype=dtype, device=device)
    conv = torch.zeros(N * K, dtype=torch.bool, device=device)
    iters = torch.zeros(N * K, dtype=torch.long, device=device)
    if live_idx.numel():
        sub_model = lambda th, i: model_fn(th, live_idx[i])  # noqa: E731
        sub_jac = (lambda th, i: jac_fn(th, live_idx[i])) if analytic else None  # noqa: E731
        res = _optimise(sub_model, theta0[live_idx], target_k[live_idx], weight_k[live_idx], loss, optimizer, max_iter, tol, project,
                        jacobian_fn=sub_jac)
        theta[live_idx], cost[live_idx], conv[live_idx], iters[live_idx] = res.theta, res.cost, res.converged, res.n_iter
    # The optimiser's final J^T W J and model are the Fisher information's (l2 and Poisson).
    reuse = analytic and optimizer == "lm" and loss in ("l2", "poisson") and live_idx.numel() > 0
    if reuse:
        R_pix = target_k.shape[-1]
        jtj_all = torch.eye(P, dtype=dtype, device=device).repeat(N * K, 1, 1)
        model_all = torch.zeros(N * K, R_pix, dtype=dtype, device=device)
        jtj_all[live_idx], model_all[live_idx] = res.jtj, res.model

    # Canonical form: M >= 0, phases wrapped.
    def canonical(t):
        t = t.clone()
        neg = t[..., :n_axes] < 0
        t[..., :n_axes] = t[..., :n_axes].abs()
        t[..., n_axes:2 * n_axes] = wrap_phase(t[..., n_axes:2 * n_axes] + math.pi * neg)
        return t

    flipped = theta.reshape(N, K, P)[..., :n_axes] < 0  # (-M, phi) -> (M, phi + pi) flips J's M columns
    th = canonical(theta.reshape(N, K, P))
    cost = cost.reshape(N, K)
    best = torch.nan_to_num(cost, nan=float("inf")).argmin(1)
    ar = torch.arange(N, device=device)
    theta_best = th[ar, best]  # [N, P]
    cost_best = cost[ar, best]
    conv_best = conv.reshape(N, K)[ar, best]
    iters_best = iters.reshape(N, K)[ar, best]
    flip_best = flipped[ar, best]
    rows = ar * K  # model_fn rows that address problem n
    if reuse:
        jtj_best = jtj_all.reshape(N, K, P, P)[ar, best]
        model_best = model_all.reshape(N, K, -1)[ar, best]

    # The other branch (alias of the first exposure) and its cost over all exposures.
    first = ExposureWindow(start[:, :1], dur[:, :1])

    def alias_of(t, n=None):
        n = ar if n is None else n
        ta = t.clone()
        ta[:, n_axes:2 * n_axes] = _alias_phase(t[:, n_axes:2 * n_axes], om[n][:, None], first[n])
        return ta

    flat_target = target.reshape(N, -1)
    flat_weight = weight.reshape(N, -1)
    cheap_model = image_fn if analytic else model_fn  # the same model; the splat's per-frame node counts are cheaper
    theta_alias = alias_of(theta_best)
    with torch.no_grad():
        alias_cost = image_loss(cheap_model(theta_alias, rows), flat_target, loss=loss, weight=flat_weight)
    live_n = ~dark & ~outside
    if E >= 2:
        # Safety net: where the alias fits better than the consensus start, refit from it.
        r = ar[live_n & (alias_cost < cost_best)]
        if r.numel():
            res2 = _optimise(lambda t, i: model_fn(t, rows[r[i]]), theta_alias[r], flat_target[r], flat_weight[r], loss, optimizer,
                             max_iter, tol, project, jacobian_fn=(lambda t, i: jac_fn(t, rows[r[i]])) if analytic else None)
            better = res2.cost < cost_best[r]
            rb = r[better]
            theta_best[rb] = canonical(res2.theta[better])
            flip_best[rb] = res2.theta[better][:, :n_axes] < 0
            if reuse:
                jtj_best[rb], model_best[rb] = res2.jtj[better], res2.model[better]
            cost_best[rb] = res2.cost[better]
            conv_best[rb] = res2.converged[better]
            iters_best[rb] += res2.n_iter[better]
            theta_alias[rb] = alias_of(theta_best[rb], rb)
            with torch.no_grad():
                alias_cost[rb] = image_loss(cheap_model(theta_alias[rb], rows[rb]), flat_target[rb], loss=loss, weight=flat_weight[rb])

    # Uncertainty: the Fisher information at the solution.
    w = weight.reshape(N, -1)
    n_used = (torch.full((N,), float(w.shape[-1]), dtype=dtype, device=device) if row_weight is not None
              else (w > 0).sum(-1).to(dtype)) + outside_n
    if reuse:
        model = model_best
        sign = torch.ones(N, P, dtype=dtype, device=device)
        sign[:, :n_axes] = torch.where(flip_best, -1.0, 1.0)
        F = jtj_best * sign[:, :, None] * sign[:, None, :]
    else:
        model, J = jac_fn(theta_best, rows) if analytic else model_jacobian(lambda t, i: model_fn(t, i), theta_best, rows)
    resid = target.reshape(N, -1) - model
    if loss == "poisson":
        fisher_w = irls_weights(model, target.reshape(N, -1), loss="poisson", weight=(w > 0).to(dtype))
        sigma_used = torch.full((N,), float("nan"), dtype=dtype, device=device)
        scale2 = torch.ones(N, dtype=dtype, device=device)
    elif sigma_given is not None:
        fisher_w = w
        sigma_used = noise_level
        scale2 = torch.ones(N, dtype=dtype, device=device)
    else:
        sig2 = (((resid * resid) * (w > 0)).sum(-1) + outside_sq) / (n_used - P).clamp_min(1)
        fisher_w = (w > 0).to(dtype) / sig2[:, None].clamp_min(torch.finfo(dtype).tiny)
        sigma_used = sig2.sqrt()
        scale2 = 1 / sig2.clamp_min(torch.finfo(dtype).tiny)
    if reuse:
        F = F * scale2[:, None, None]
    else:
        JW = J * fisher_w[..., None]
        F = JW.transpose(-1, -2) @ J
    cov, info = torch.linalg.inv_ex(F)
    singular = (info != 0) | ~torch.isfinite(cov).all(-1).all(-1)
    diag = torch.diagonal(cov, dim1=-2, dim2=-1)
    singular = singular | (diag <= 0).any(-1)
    std = diag.clamp_min(0).sqrt()

    amp_b = theta_best[:, :n_axes]
    ph_b = theta_best[:, n_axes:2 * n_axes]
    alias = theta_alias[:, n_axes:2 * n_axes]

    # Status per item.
    status = torch.zeros(N, dtype=torch.long, device=device)
    status[~conv_best] = 2
    status[singular] = 4
    if isinstance(p_flat, GaussianPSF):
        with torch.no_grad():
            scale_b = theta_best[:, 2 * n_axes] if fit_scale else torch.ones(N, dtype=dtype, device=device)
            bg_b = theta_best[:, 2 * n_axes + int(fit_scale)] if fit_background else 0.0
            inside = (model - (bg_b[:, None] if fit_background else 0.0)).sum(-1)
            if normalize:
                inside = torch.full_like(inside, float("inf"))
            total = scale_b * (p_flat.total_light()[:, None] * dur).sum(-1)
            status[inside < 0.5 * total] = OUT_OF_FRAME
    status[outside] = 3
    status[dark] = 1
    bad = (status == 1) | outside
    nan = torch.tensor(float("nan"), dtype=dtype, device=device)

    def out(x, tail=()):
        return x.reshape(batch + tail)

    def core(v):
        v = torch.where(bad[:, None], nan, v)
        return out(v, (2,)) if n_axes == 2 else out(v[:, 0])

    res = SinusoidFit(
        amplitude=core(amp_b),
        phase=core(ph_b),
        amplitude_std=core(std[:, :n_axes]),
        phase_std=core(std[:, n_axes:2 * n_axes]),
        alias_phase=core(alias),
        alias_cost=out(torch.where(bad, nan, alias_cost + outside_cost)),
        cost=out(torch.where(bad, nan, cost_best + outside_cost)),
        converged=out(status == 0),
        status=out(status),
        covariance=out(torch.where(bad[:, None, None], nan, cov), (P, P)),
        param_names=tuple(names),
        noise_std=out(sigma_used),
        n_iter=out(iters_best),
    )
    j = 2 * n_axes
    if fit_scale:
        res.scale = out(theta_best[:, j])
        j += 1
    if fit_background:
        res.background = out(theta_best[:, j])
        j += 1
    if fit_center:
        res.center = out(theta_best[:, j:j + 2] + torch.tensor([x0, y0], dtype=dtype, device=device), (2,))
    res.extras["nodes"] = settings.nodes
    if analytic:
        res.extras["nodes_per_frame"] = out(panels * m_nodes, (E,))
    res.extras["candidates"] = K
    return res


GN_TOL = 1e-2  # squared Mahalanobis length (in std^2) of a final Gauss-Newton step taken unevaluated


def _optimise(model_fn, theta0, data, weight, loss, optimizer, max_iter, tol, project, jacobian_fn=None):
    """Run the chosen optimiser on ``[n, P]`` problems (see :func:`fit_sinusoid`)."""
    from torchblur.fit.optim import LMResult

    if optimizer == "lm":
        it = max_iter or 60
        # Converged once the next Gauss-Newton step is below 0.1 standard deviation (that
        # step is then taken unevaluated; the result is within ~0.01 std of the optimum).
        return levenberg_marquardt(model_fn, theta0, data, loss=loss, weight=weight, max_iter=it, tol=tol, project=project,
                                   jacobian_fn=jacobian_fn, gn_tol=GN_TOL if loss in ("l2", "poisson") else None)
    n = theta0.shape[0]
    idx = torch.arange(n, device=theta0.device)
    theta = theta0.clone().requires_grad_(True)
    scale = theta0.detach().abs().clamp_min(1.0)
    if optimizer == "adam":
        it = max_iter or 400
        u = torch.zeros_like(theta0, requires_grad=True)
        opt = torch.optim.Adam([u], lr=0.02)
        history = []
        for _ in range(it):
            opt.zero_grad()
            c = image_loss(model_fn(theta0 + u * scale, idx), data, loss=loss, weight=weight)
            c.sum().backward()
            opt.step()
            history.append(c.detach())
        with torch.no_grad():
            final = theta0 + u * scale
            cost = image_loss(model_fn(final, idx), data, loss=loss, weight=weight)
        prev = history[-20] if len(history) >= 20 else history[0]
        conv = (prev - cost).abs() <= 1e-4 * cost.abs().clamp_min(1e-30)
        return LMResult(final.detach(), cost, conv, torch.full((n,), it, dtype=torch.long, device=theta0.device))
    it = max_iter or 100
    u = torch.zeros_like(theta0, requires_grad=True)
    opt = torch.optim.LBFGS([u], lr=1.0, max_iter=it, line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-14)

    def closure():
        opt.zero_grad()
        c = image_loss(model_fn(theta0 + u * scale, idx), data, loss=loss, weight=weight).sum()
        c.backward()
        return c

    opt.step(closure)
    with torch.no_grad():
        final = theta0 + u * scale
        cost = image_loss(model_fn(final, idx), data, loss=loss, weight=weight)
    state = opt.state[opt._params[0]]
    n_it = int(state.get("n_iter", it))
    conv = torch.full((n,), n_it < it, dtype=torch.bool, device=theta0.device)
    return LMResult(final.detach(), cost, conv, torch.full((n,), n_it, dtype=torch.long, device=theta0.device))


# --------------------------------------------------------------------------- public entry: checks, masks, robust pass, flags


# One splat call's fixed cost (Python and per-operation overheads) in nodes x pixels of frame
# work: measured on a 2-core CPU, 1.8 ms per call against 0.84 us per node of a 22x54 frame.
_CALL_NODE_PIXELS = 2.5e6


def _merge_panel_groups(panels: torch.Tensor, m_nodes: int, call_nodes: float) -> torch.Tensor:
    """Panel counts ``[N, E]`` with groups of adjacent counts merged (their frames rounded up to
    the group's largest count) so as to minimise the splat's cost: frames of equal count are
    rendered by one call, which costs ``call_nodes`` node-frames of overhead, and a frame costs
    its nodes. An exact dynamic programme over the distinct counts (a handful)."""
    vals, counts = torch.unique(panels, return_counts=True)
    v, m = vals.tolist(), counts.tolist()
    K = len(v)
    if K <= 1:
        return panels
    best, cut = [0.0] + [math.inf] * K, [0] * (K + 1)
    for j in range(1, K + 1):  # best[j]: the cheapest grouping of the j smallest counts
        frames = 0
        for i in range(j, 0, -1):  # the last group: counts i..j, all at count j
            frames += m[i - 1]
            c = best[i - 1] + call_nodes + frames * v[j - 1] * m_nodes
            if c < best[j]:
                best[j], cut[j] = c, i
    out = panels.clone()
    j = K
    while j > 0:
        i = cut[j]
        for k in range(i, j):
            out[panels == v[k - 1]] = v[j - 1]
        j = i - 1
    return out


def _check_flag(value, name: str) -> bool:
    if not isinstance(value, bool):
        raise InputTypeError(f"{name}: expected True or False, got {type(value).__name__}")
    return value


def _take_psf(psf, idx):
    return psf[idx] if isinstance(psf, GaussianPSF) else KernelPSF(psf.kernel[idx])


def _inpaint(data: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Masked pixels of ``data [n, E, H, W]`` replaced by the 3x3 median of their neighbourhood
    (kornia), so that the closed-form starts and the dark-frame test do not see them. Their
    fit weight is 0, so the cost does not change."""
    if bool(keep.all()):
        return data
    import kornia

    n, E, H, W = data.shape
    med = kornia.filters.median_blur(data.reshape(n * E, 1, H, W), 3, border_type="replicate").reshape(n, E, H, W)
    return torch.where(keep, data, med)


def _axis_directions(axes, N: int, dtype, device) -> torch.Tensor:
    """The image directions ``[N, n_axes, 2]`` of the fitted axes: ``"x"``, ``"y"``, ``"xy"``,
    or a direction per item ``[N, 2]`` (unit vectors, see :func:`_as_direction`)."""
    if isinstance(axes, torch.Tensor):
        return axes.to(dtype=dtype, device=device).expand(N, 2)[:, None, :]
    eye = torch.eye(2, dtype=dtype, device=device)
    rows = {"x": eye[:1], "y": eye[1:], "xy": eye}[axes]
    return rows[None].expand(N, len(rows), 2)


def _as_direction(axes, batch, N: int, like: torch.Tensor) -> torch.Tensor:
    """``axes`` given as an image direction (a pair (x, y), or a tensor ``[2]`` or ``[..., 2]``
    broadcastable to the images' batch) -> unit vectors ``[N, 2]``."""
    d = as_unit_direction(axes, "axes", like=like)
    try:
        return d.expand(batch + (2,)).reshape(N, 2)
    except RuntimeError:
        raise ShapeError(f"axes: a direction [..., 2] must broadcast to the images' batch {tuple(batch)}, got {tuple(d.shape)}") from None


def _axes_xy(amplitude: torch.Tensor, phase: torch.Tensor, direction: torch.Tensor | None):
    """Per-axis ``(amplitude [n, 2], phase [n, 2])`` of a fit: ``direction [n, 2]`` the unit
    image direction of a one-axis fit, None for a Lissajous (``"xy"``) fit."""
    if direction is None:
        return amplitude, phase
    return amplitude[:, None] * direction, torch.stack([phase, phase], -1)


def _fitted_psf(res: SinusoidFit, psf, idx, fit_scale: bool, fit_center: bool):
    """The PSF of items ``idx`` with the fitted scale and rest position, batch ``[n, 1]``."""
    scale = res.scale[idx] if fit_scale else None
    if isinstance(psf, GaussianPSF):
        c = res.center[idx] if fit_center else psf.center[idx]
        a = psf.amplitude[idx] * (scale if scale is not None else 1.0)
        return GaussianPSF(c[:, None], psf.cov[idx][:, None], a[:, None])
    k = psf.kernel[idx]
    return KernelPSF((k * scale[:, None, None] if scale is not None else k)[:, None])


def _model_images(res, idx, psf, win, om, direction, H, W, fit_scale, fit_center, fit_background, settings):
    """The fitted model ``[n, E, H, W]`` of items ``idx`` (``direction [N, 2]`` or None, see :func:`_axes_xy`)."""
    amp, ph = _axes_xy(res.amplitude[idx], res.phase[idx], None if direction is None else direction[idx])
    traj = Sinusoid(amp[:, None, :], ph[:, None, :], om[idx][:, None])
    with torch.no_grad():
        img = render_blur(traj, _fitted_psf(res, psf, idx, fit_scale, fit_center), win[idx], height=H, width=W, settings=settings)
    if fit_background:
        img = img + res.background[idx][:, None, None, None]
    return img


def _light_in_frame(res, psf, win, om, direction, H, W, fit_center, n_t: int = 64) -> torch.Tensor:
    """Fraction ``[N]`` of the fitted spot's light that falls inside the frame
    ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (worst exposure), from the Gaussian marginals of the
    PSF along the fitted path (NaN where the fit has no estimate)."""
    amp, ph = _axes_xy(res.amplitude, res.phase, direction)
    if isinstance(psf, GaussianPSF):
        centre, cov = psf.center, psf.cov
    else:
        centre, cov = psf.moments()
    if fit_center and res.center is not None:
        centre = res.center
    dtype, device = amp.dtype, amp.device
    tau = (torch.arange(n_t, dtype=dtype, device=device) + 0.5) / n_t
    t = win.start[..., None] + win.duration[..., None] * tau  # [N, E, T]
    pos = centre[:, None, None, :] + amp[:, None, None, :] * torch.sin(om[:, None, None, None] * t[..., None] + ph[:, None, None, :])
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(1e-12).sqrt()[:, None, None, :]
    hi = torch.tensor([W - 0.5, H - 0.5], dtype=dtype, device=device)
    inside = torch.special.ndtr((hi - pos) / sd) - torch.special.ndtr((-0.5 - pos) / sd)  # [N, E, T, 2]
    return inside.prod(-1).mean(-1).amin(-1)


def _robust_scale(r: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
    """``1.4826 MAD`` of the residuals ``r [n, E, H, W]`` over the used pixels, ``[n, 1, 1, 1]``."""
    x = torch.where(used, r, torch.full_like(r, float("nan"))).flatten(1)
    med = x.nanmedian(-1, keepdim=True).values
    mad = (x - med).abs().nanmedian(-1).values * 1.482602218505602
    return torch.nan_to_num(mad, nan=0.0).clamp_min(torch.finfo(r.dtype).tiny)[:, None, None, None]


def _impulses(data: torch.Tensor, psf: GaussianPSF, noise: torch.Tensor, k: float) -> torch.Tensor:
    """Pixels ``[n, E, H, W]`` brighter than any blurred Gaussian spot allows: hot pixels and
    cosmic-ray hits, found before the fit so they cannot spoil its start.

    A positive sum of Gaussians of precision ``[[A, B], [B, C]]`` obeys
    ``f(x) <= exp(A / 2) (f(x - 1) + f(x + 1)) / 2`` along x (and likewise with C along y),
    since ``g(x + d) + g(x - d) >= 2 g(x) exp(-d^2 A / 2)`` for each of its terms. A pixel that
    exceeds either bound by ``k`` noise standard deviations cannot come from the spot.
    Interior pixels only. ``noise``: ``[n, 1, 1, 1]`` or ``[n, E, H, W]``.
    """
    A, _, C = psf.precision()
    out = torch.zeros_like(data, dtype=torch.bool)
    if data.shape[-1] < 3 and data.shape[-2] < 3:
        return out
    s = noise.expand_as(data)
    for dim, prec in ((-1, A), (-2, C)):
        if data.shape[dim] < 3:
            continue
        c = torch.exp(prec / 2)[:, None, None, None]
        mid = data.narrow(dim, 1, data.shape[dim] - 2)
        nb = 0.5 * (data.narrow(dim, 0, data.shape[dim] - 2) + data.narrow(dim, 2, data.shape[dim] - 2))
        sd = s.narrow(dim, 1, data.shape[dim] - 2) * torch.sqrt(1 + c * c / 2)
        out.narrow(dim, 1, data.shape[dim] - 2).logical_or_(mid - c * nb > k * sd)
    return out


def _plane_fit(data: torch.Tensor, use: torch.Tensor) -> torch.Tensor:
    """Least-squares plane ``a + b (x - xc) + c (y - yc)`` of each ``data [n, E, H, W]`` over
    the pixels ``use``; ``[n, E, 3]`` (centre level, x slope, y slope per px)."""
    n, E, H, W = data.shape
    y = torch.arange(H, dtype=data.dtype, device=data.device)[:, None].expand(H, W) - (H - 1) / 2
    x = torch.arange(W, dtype=data.dtype, device=data.device)[None, :].expand(H, W) - (W - 1) / 2
    basis = torch.stack([torch.ones_like(x), x, y], -1).reshape(H * W, 3)  # [HW, 3]
    w = use.reshape(n, E, H * W).to(data.dtype)
    A = torch.einsum("nep,pi,pj->neij", w, basis, basis)
    rhs = torch.einsum("nep,pi,nep->nei", w, basis, data.reshape(n, E, H * W))
    A = A + 1e-12 * A.diagonal(dim1=-2, dim2=-1).amax(-1)[..., None, None].clamp_min(1) * torch.eye(3, dtype=data.dtype, device=data.device)
    return torch.linalg.solve(A, rhs[..., None])[..., 0]


def _plane_image(coef: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """``[n, E, H, W]`` image of planes ``coef [n, E, 3]`` (see :func:`_plane_fit`)."""
    y = torch.arange(H, dtype=coef.dtype, device=coef.device)[:, None] - (H - 1) / 2
    x = torch.arange(W, dtype=coef.dtype, device=coef.device)[None, :] - (W - 1) / 2
    return coef[..., 0, None, None] + coef[..., 1, None, None] * x + coef[..., 2, None, None] * y


def _put(res: SinusoidFit, idx: torch.Tensor, sub: SinusoidFit) -> None:
    """Overwrite items ``idx`` of a flat-batch ``res`` with those of ``sub``."""
    for f in fields(SinusoidFit):
        v = getattr(res, f.name)
        if isinstance(v, torch.Tensor):
            v[idx] = getattr(sub, f.name)


def fit_sinusoid(
    images,
    psf,
    window: ExposureWindow,
    omega,
    *,
    axes="x",
    optimizer: str = "lm",
    loss: str = "l2",
    noise_std=None,
    mask=None,
    saturation_level=None,
    outliers: str = "none",
    outlier_sigma: float = 5.0,
    fit_scale: bool = False,
    fit_background: bool = False,
    fit_center: bool = False,
    fit_gradient: bool = False,
    normalize: bool = False,
    max_iter: int | None = None,
    tol: float = 1e-9,
    render_settings: RenderSettings | None = None,
) -> SinusoidFit:
    """Fit ``y(t) = M sin(omega t + phi)`` to blurred images of a moving spot.

    Args:
        images: ``[..., E, H, W]``: E exposures of the same motion (E = 1, 2 or more), dark
            level subtracted, in the units of the PSF times seconds; a real floating tensor
            (integer frames still hold the dark level: use ``preprocess.subtract_dark``).
        psf: ``GaussianPSF`` or ``KernelPSF``, batch ``[...]`` (shared by the E exposures).
        window: exposure windows, batch broadcastable to ``[..., E]``.
        omega: rad/s, ``[...]``.
        axes: ``"x"`` or ``"y"``: a motion along that axis (amplitude, phase ``[...]``);
            ``"xy"``: a 2-D Lissajous motion (amplitude, phase ``[..., 2]``); or an image
            direction ``(x, y)`` (a pair, or a tensor ``[2]`` or ``[..., 2]``, normalised): a
            motion along it, e.g. an actuator axis rotated in the camera's image
            (:func:`torchblur.image.tracking.calibrate_axes` measures it); the amplitude is then
            along that direction (``[...]``) and the parameters are named ``amplitude_u``,
            ``phase_u``.
        optimizer: ``"lm"`` (batched Levenberg-Marquardt, default), ``"adam"``, ``"lbfgs"``.
        loss: ``"l2"`` (default), ``"l1"``, ``"linf"`` (adam/lbfgs only), ``"poisson"``.
        noise_std: pixel noise std: a number, ``[...]`` or ``[..., E, H, W]``; None: the l2
            fit is unweighted and the noise is estimated from the residuals.
        mask: bool ``[..., E, H, W]``, False excludes a pixel (hot pixels from
            ``preprocess.dark_frame(...).hot_pixels``, saturated pixels from
            ``SaturationCurve.mask`` or ``CameraModel.saturated_mask`` of the raw frames).
            Sets :data:`MASKED`.
        saturation_level: pixels of ``images`` at or above it are excluded (the clipping level
            in the units of ``images``, i.e. less the dark level): a number or ``[...]``.
            Sets :data:`SATURATED_MASKED`. None (default): nothing is clipped.
        outliers: ``"none"`` (default) or ``"reject"``: after the fit, pixels whose residual
            exceeds ``outlier_sigma`` noise standard deviations (``noise_std``, else a robust
            MAD estimate from the residuals, which assumes the noise does not grow with the
            signal) are excluded and the item refitted, up to 3 passes; for hot pixels
            without a map and cosmic-ray hits. Sets :data:`OUTLIERS_MASKED` and ``n_outliers``.
        outlier_sigma: the rejection threshold in standard deviations (> 0, default 5: about
            6e-7 of clean Gaussian pixels are rejected).
        fit_scale, fit_background, fit_center: fit an intensity scale, a constant background
            (stray light), the rest position jointly (nuisance parameters).
        fit_gradient: remove a stray-light plane (level and slopes) from each exposure,
            fitted to the pixels the spot does not reach: first the frame's 2-px border,
            then every pixel where the fitted spot is below 1e-4 of its peak; the spot is
            refitted after each. Reported in ``background_plane``; its uncertainty (from
            many pixels) is not added to the estimates'.
        normalize: the paper's eq. 8: compare images divided by their Frobenius norms (an
            option; it weights the exposures unequally and loses precision).
        max_iter: optimiser iterations, an int >= 1 (default 60 for lm, 400 for adam, 100
            for lbfgs).
        tol: relative cost decrease that counts as converged (lm), >= 0.
        render_settings: renderer settings; the node count is fixed for the whole fit
            (default: panels of 3.5 PSF widths, model error < 1e-6 of the peak).

    Returns:
        :class:`SinusoidFit`. Degenerate items are flagged, never raised, and do not change
        the other items: ``status`` 1 (no signal), 3 (spot mostly outside the frame), 5 (no
        usable pixel) give NaN estimates; ``flags`` mark masked, saturated and outlier
        pixels, a spot partly out of the frame (fitted on what is visible) and a motion too
        small to measure.

    Example:
        >>> fit = fit_sinusoid(images, psf, window, omega, mask=~dark.hot_pixels, outliers="reject")
        >>> bad = (fit.flags & PARTLY_OUT_OF_FRAME) != 0
    """
    if isinstance(images, torch.Tensor) and not images.is_floating_point():
        raise InputTypeError(f"images: expected a real floating tensor [..., E, H, W] with the dark level subtracted "
                             f"(preprocess.subtract_dark), got dtype {images.dtype}")
    images, omega = _validate(images, psf, window, omega, axes, optimizer, loss)
    for name, v in (("fit_scale", fit_scale), ("fit_background", fit_background), ("fit_center", fit_center), ("fit_gradient", fit_gradient),
                    ("normalize", normalize)):
        _check_flag(v, name)
    check_choice(outliers, "outliers", OUTLIERS)
    outlier_sigma = check_real_scalar(outlier_sigma, "outlier_sigma", positive=True)
    if fit_gradient and normalize:
        raise ParameterError("fit_gradient: expected False with normalize=True (the plane is in image units), got True")
    if outliers == "reject" and normalize:
        raise ParameterError("outliers: expected 'none' with normalize=True (the robust pass compares data and model in image units), "
                             "got 'reject'")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ParameterError(f"max_iter: expected None or an integer >= 1, got {max_iter!r}")
    tol = check_real_scalar(tol, "tol", nonnegative=True)
    if render_settings is not None and not isinstance(render_settings, RenderSettings):
        raise InputTypeError(f"render_settings: expected a RenderSettings or None, got {type(render_settings).__name__}")

    dtype, device = images.dtype, images.device
    batch = images.shape[:-3]
    E, H, W = images.shape[-3:]
    N = max(1, math.prod(batch))
    data = images.reshape(N, E, H, W)
    # One-axis fits: the unit image direction of the motion per item [N, 2] (None: Lissajous).
    direction = None if isinstance(axes, str) and axes == "xy" else (_axis_directions(axes, N, dtype, device)[:, 0] if isinstance(axes, str)
                                          else _as_direction(axes, batch, N, data))
    w_full = window.to(dtype).expand(batch + (E,))
    win = ExposureWindow(w_full.start.reshape(N, E), w_full.duration.reshape(N, E))
    om = omega.expand(batch).reshape(N)
    psf_n = _flatten_psf(psf.to(dtype) if isinstance(psf, GaussianPSF) else psf, batch, N)
    sig = None
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=data), "noise_std")
        try:
            sig = s.expand(batch + (E, H, W)).reshape(N, E, H, W) if s.dim() >= 3 and s.shape[-3:] == (E, H, W) else s.expand(batch).reshape(N)
        except RuntimeError:
            raise ShapeError(f"noise_std: expected a number, [...] or [..., E, H, W], got {tuple(s.shape)}") from None

    keep = torch.ones(N, E, H, W, dtype=torch.bool, device=device)
    user_masked = torch.zeros(N, dtype=torch.bool, device=device)
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError(f"mask: expected a bool tensor [..., E, H, W] (True = use the pixel), got "
                                 f"{mask.dtype if isinstance(mask, torch.Tensor) else type(mask).__name__}")
        try:
            m = mask.to(device).expand(batch + (E, H, W)).reshape(N, E, H, W)
        except RuntimeError:
            raise ShapeError(f"mask: expected shape [..., E, H, W] = {tuple(images.shape)}, got {tuple(mask.shape)}") from None
        keep = keep & m
        user_masked = (~m).flatten(1).any(1)
    sat_masked = torch.zeros(N, dtype=torch.bool, device=device)
    if saturation_level is not None:
        lvl = check_finite(as_tensor(saturation_level, "saturation_level", like=data), "saturation_level")
        try:
            lvl = lvl.expand(batch).reshape(N)
        except RuntimeError:
            raise ShapeError(f"saturation_level: expected a number or the images' batch {tuple(batch)}, got {tuple(lvl.shape)}") from None
        sat = data >= lvl[:, None, None, None]
        sat_masked = (sat & keep).flatten(1).any(1)
        keep = keep & ~sat

    core_axes = direction if not isinstance(axes, str) else axes
    opts = dict(optimizer=optimizer, loss=loss, fit_scale=fit_scale, fit_background=fit_background, fit_center=fit_center,
                normalize=normalize, max_iter=max_iter, tol=tol, render_settings=render_settings)

    def run(idx, use):
        if idx.numel() == N:  # everything: no copies
            return _fit_core(_inpaint(data, use), psf_n, win, om, axes=core_axes, noise_std=sig, mask=None if bool(use.all()) else use,
                             **opts)
        return _fit_core(_inpaint(data[idx], use), _take_psf(psf_n, idx), win[idx], om[idx],
                         axes=core_axes if isinstance(core_axes, str) else core_axes[idx],
                         noise_std=None if sig is None else sig[idx], mask=None if bool(use.all()) else use, **opts)

    everything = torch.arange(N, device=device)
    rejected = torch.zeros_like(keep)
    if outliers == "reject" and isinstance(psf_n, GaussianPSF):
        if sig is not None:
            noise0 = sig if sig.dim() == 4 else sig[:, None, None, None]
        else:
            noise0 = _robust_scale(data, keep)
        rejected = _impulses(data, psf_n, noise0, outlier_sigma) & keep
    plane = None
    if fit_gradient:
        border = torch.ones(H, W, dtype=torch.bool, device=device)
        border[2:-2, 2:-2] = False
        plane = _plane_fit(data, keep & ~rejected & border)
        data_raw, data = data, data - _plane_image(plane, H, W)
    res = run(everything, keep & ~rejected)
    if fit_gradient:
        live = everything[torch.isfinite(res.cost)]
        if live.numel():
            spot = _model_images(res, live, psf_n, win, om, direction, H, W, fit_scale, fit_center, False, render_settings)
            far = spot < 1e-4 * spot.amax((-1, -2), keepdim=True)
            plane[live] = _plane_fit(data_raw[live], keep[live] & ~rejected[live] & far)
            data = data_raw - _plane_image(plane, H, W)
            _put(res, live, run(live, keep[live] & ~rejected[live]))
    passes = 0
    if outliers == "reject":
        for passes in range(1, 4):
            idx = everything[torch.isfinite(res.cost) & ((res.status == 0) | (res.status == 2) | (res.status == 4))]
            if idx.numel() == 0:
                break
            model = _model_images(res, idx, psf_n, win, om, direction, H, W, fit_scale, fit_center, fit_background, render_settings)
            r = data[idx] - model
            used = keep[idx]
            scale = sig[idx] if sig is not None and sig.dim() == 4 else (
                sig[idx][:, None, None, None] if sig is not None else _robust_scale(r, used))
            new = (r.abs() > outlier_sigma * scale) & used
            changed = (new != rejected[idx]).flatten(1).any(1)
            if not bool(changed.any()):
                break
            ci = idx[changed]
            rejected[ci] = new[changed]
            _put(res, ci, run(ci, keep[ci] & ~rejected[ci]))

    # Items with nothing left to fit.
    used_all = keep & ~rejected
    n_used = used_all.flatten(1).sum(1)
    P = len(res.param_names)
    empty = n_used <= P
    if bool(empty.any()):
        nan = float("nan")
        for name in ("amplitude", "phase", "amplitude_std", "phase_std", "alias_phase", "alias_cost", "cost", "covariance"):
            getattr(res, name)[empty] = nan
        res.status[empty] = NO_PIXELS
        res.converged[empty] = False

    n_out = rejected.flatten(1).sum(1)
    flags = torch.zeros(N, dtype=torch.long, device=device)
    flags |= MASKED * user_masked.long()
    flags |= SATURATED_MASKED * sat_masked.long()
    flags |= OUTLIERS_MASKED * (n_out > 0).long()
    with torch.no_grad():
        frac = _light_in_frame(res, psf_n, win, om, direction, H, W, fit_center)
    flags |= PARTLY_OUT_OF_FRAME * ((frac < 0.999) & (res.status != 3)).long()
    amp_z = res.amplitude / res.amplitude_std
    lissajous = direction is None
    weak = (amp_z < 3) if not lissajous else (amp_z < 3).any(-1)
    flags |= NO_MOTION * (weak & ~torch.isnan(res.amplitude) if not lissajous else weak & ~torch.isnan(res.amplitude).any(-1)).long()
    res.flags = flags
    res.n_masked = E * H * W - n_used
    res.n_outliers = n_out
    res.extras["outlier_passes"] = passes
    res.background_plane = plane

    for f in fields(SinusoidFit):
        v = getattr(res, f.name)
        if isinstance(v, torch.Tensor):
            setattr(res, f.name, v.reshape(batch + v.shape[1:]))
    return res
