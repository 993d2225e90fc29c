"""Coded exposure: one image that tells the direction of time (issue 6 part 5).

A plain exposure integrates the spot over ``[t0, t0 + Te]``; the time reversal about the window
centre maps ``M sin(omega t + phi)`` to ``M sin(omega t + pi - 2c - phi)`` (c: the phase at the
centre) and gives exactly the same image (PHYSICS.md section 2, Proposition 3), so one image has
two phase branches. A *coded* exposure opens the shutter (or pulses the laser) only during an
asymmetric set of sub-intervals of the window, ``code = [(a_1, b_1), ..., (a_K, b_K)]`` as
fractions of ``Te``: the image is the sum of the sub-windows' images,

    Y = sum_k integral_{t0 + a_k Te}^{t0 + b_k Te} Psi(eta - y(t)) dt,

and the time reversal maps the code to its mirror ``(1 - b_k, 1 - a_k)``, which is a different
code unless the code is symmetric: the alias no longer renders the same image, and one image
identifies the phase. (A rolling shutter, rows exposed at staggered times, breaks the symmetry the
same way along the rows.)

:func:`render_coded` is the image model (the differentiable renderer on the sub-windows),
:func:`fit_sinusoid_coded` fits ``(M, phi[, scale])`` to single coded images by batched
Levenberg-Marquardt from a grid of phase starts (no alias pair to choose from: the best start
wins), with Fisher-information stds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchblur.render.alias import wrap_phase
from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_finite, check_positive
from torchblur.fit.losses import image_loss
from torchblur.fit.optim import levenberg_marquardt
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import RenderSettings, choose_node_count, render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

__all__ = ["check_code", "mirror_code", "coded_windows", "render_coded", "CodedFit", "fit_sinusoid_coded"]


def check_code(code, *, like: torch.Tensor | None = None) -> torch.Tensor:
    """A code as a ``[K, 2]`` tensor of open intervals ``(a_k, b_k)``, fractions of the
    exposure, ``0 <= a_1 < b_1 <= a_2 < ... <= 1``; :class:`ParameterError` naming ``code``
    otherwise."""
    c = as_tensor(code, "code", like=like) if like is not None else as_tensor(code, "code", dtype=torch.float64)
    if c.dim() != 2 or c.shape[-1] != 2 or c.shape[0] < 1:
        raise ShapeError(f"code: expected shape [K, 2] (open intervals as fractions of the exposure), got {tuple(c.shape)}")
    check_finite(c, "code")
    flat = c.reshape(-1)
    if bool((flat < 0).any()) or bool((flat > 1).any()) or bool((c[:, 1] <= c[:, 0]).any()) or bool((flat.diff() < 0).any()):
        raise ParameterError(f"code: expected increasing, non-overlapping intervals in [0, 1], got {c.tolist()}")
    return c


def mirror_code(code) -> torch.Tensor:
    """The time-reversed code ``(1 - b_k, 1 - a_k)`` (in increasing order)."""
    c = check_code(code)
    return torch.flip(1 - c, dims=(0, 1))


def coded_windows(window: ExposureWindow, code) -> ExposureWindow:
    """The open sub-windows of coded exposures: batch ``[..., K]`` from ``window`` ``[...]``."""
    c = check_code(code, like=window.start)
    te = window.duration[..., None]
    return ExposureWindow(window.start[..., None] + c[:, 0] * te, (c[:, 1] - c[:, 0]) * te)


def render_coded(trajectory, psf, window: ExposureWindow, code, *, height: int, width: int,
                 settings: RenderSettings | None = None) -> torch.Tensor:
    """The image of a coded exposure: the sum over the code's sub-windows of
    :func:`~torchblur.render.blur.render_blur`.

    Args:
        trajectory, psf: as :func:`render_blur`, batch ``[...]``.
        window: the whole exposures ``[...]`` (s).
        code: ``[K, 2]`` open intervals as fractions of the exposure (:func:`check_code`).
        height, width, settings: as :func:`render_blur`.

    Returns:
        ``[..., H, W]``. Differentiable in every parameter.
    """
    sub = coded_windows(window, code)
    traj_b = trajectory
    shape = torch.broadcast_shapes(trajectory.shape, psf.shape, window.shape)
    sub = sub.expand(shape + sub.shape[-1:])
    if isinstance(trajectory, Sinusoid):
        traj_b = Sinusoid(trajectory.amplitude[..., None, :], trajectory.phase[..., None, :], trajectory.omega[..., None, :])
    else:
        raise InputTypeError(f"trajectory: expected a Sinusoid, got {type(trajectory).__name__}")
    if isinstance(psf, GaussianPSF):
        psf_b = GaussianPSF(psf.center[..., None, :], psf.cov[..., None, :, :], psf.amplitude[..., None])
    else:
        raise InputTypeError(f"psf: expected a GaussianPSF, got {type(psf).__name__}")
    return render_blur(traj_b, psf_b, sub, height=height, width=width, settings=settings).sum(-3)


@dataclass
class CodedFit:
    """Result of :func:`fit_sinusoid_coded`, batch ``[...]``: ``amplitude`` (px), ``phase``
    (rad), their stds, ``cost``, ``alias_cost`` (the cost at the plain window's alias phase
    ``pi - 2c - phi``, same amplitude; equal to ``cost`` when the code does not break the alias),
    ``converged``, ``covariance`` ``[..., P, P]``, ``scale`` (or None)."""

    amplitude: torch.Tensor
    phase: torch.Tensor
    amplitude_std: torch.Tensor
    phase_std: torch.Tensor
    cost: torch.Tensor
    alias_cost: torch.Tensor
    converged: torch.Tensor
    covariance: torch.Tensor
    scale: torch.Tensor | None = None


def fit_sinusoid_coded(images, psf: GaussianPSF, window: ExposureWindow, code, omega, *, noise_std=None, amplitude_guess=None,
                       fit_scale: bool = False, n_phases: int = 12, max_iter: int = 60, tol: float = 1e-10) -> CodedFit:
    """Fit ``y(t) = M sin(omega t + phi)`` along x to single coded images.

    Args:
        images: ``[..., H, W]``, one coded exposure each (dark subtracted).
        psf: :class:`GaussianPSF`, batch ``[...]``.
        window: the whole exposures ``[...]`` (s, command clock).
        code: ``[K, 2]`` open intervals (fractions of the exposure).
        omega: rad/s, ``[...]``.
        noise_std: pixel noise std (number, ``[...]`` or ``[..., H, W]``); None: unweighted,
            noise from the residuals.
        amplitude_guess: M start (px), ``[...]``; default from the image's second moment.
        fit_scale: also fit an intensity scale.
        n_phases: phase starts on a grid over the circle (all refined, the best kept).

    Returns:
        :class:`CodedFit`.
    """
    if not isinstance(images, torch.Tensor) or images.dim() < 2:
        raise ShapeError("images: expected a tensor [..., H, W]")
    if not isinstance(psf, GaussianPSF):
        raise InputTypeError(f"psf: expected a GaussianPSF, got {type(psf).__name__}")
    if isinstance(n_phases, bool) or not isinstance(n_phases, int) or n_phases < 1:
        raise ParameterError(f"n_phases: expected an integer >= 1, got {n_phases!r}")
    check_finite(images, "images")
    dtype, device = images.dtype, images.device
    batch = images.shape[:-2]
    H, W = images.shape[-2:]
    B = max(1, math.prod(batch))
    code = check_code(code, like=images)
    om = check_positive(as_tensor(omega, "omega", like=images), "omega").expand(batch).reshape(B)
    win = window.to(dtype).expand(batch)
    start, dur = win.start.reshape(B), win.duration.reshape(B)
    p = psf.to(dtype)
    center = p.center.expand(batch + (2,)).reshape(B, 2)
    cov = p.cov.expand(batch + (2, 2)).reshape(B, 2, 2)
    amp = p.amplitude.expand(batch).reshape(B)
    data = images.reshape(B, H * W)
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=images), "noise_std")
        s = s.expand(batch + (H, W)) if s.dim() >= 2 and tuple(s.shape[-2:]) == (H, W) else s.expand(batch)[..., None, None].expand(batch + (H, W))
        weight = 1 / s.reshape(B, H * W) ** 2
    else:
        weight = torch.ones_like(data)
    if amplitude_guess is None:
        from torchblur.image.moments import image_moments

        flat = data
        thr = flat.median(-1).values + 3 * (flat - flat.median(-1).values[:, None]).abs().median(-1).values * 1.4826
        _, cen, icov = image_moments(images.reshape(B, H, W), threshold=thr)
        ms = (icov[:, 0, 0] - cov[:, 0, 0] + (cen[:, 0] - center[:, 0]) ** 2).clamp_min(0.25)
        M0 = (2 * ms).sqrt()
    else:
        M0 = as_tensor(amplitude_guess, "amplitude_guess", like=images).expand(batch).reshape(B).abs().clamp_min(1e-3)
    K = n_phases
    ph0 = torch.arange(K, dtype=dtype, device=device) * (2 * math.pi / K) - math.pi
    theta0 = torch.stack([M0[:, None].expand(B, K), ph0.expand(B, K)], -1)
    if fit_scale:
        theta0 = torch.cat([theta0, torch.ones(B, K, 1, dtype=dtype, device=device)], -1)
    P = theta0.shape[-1]
    theta0 = theta0.reshape(B * K, P)
    item = torch.arange(B, device=device).repeat_interleave(K)
    settings = RenderSettings(panel_path_sigmas=3.5)
    bound = Sinusoid(torch.stack([M0 * 1.5 + 0.5, torch.zeros_like(M0)], -1), torch.zeros(B, 2, dtype=dtype, device=device), om)
    S = choose_node_count(bound.path_length(ExposureWindow(torch.zeros_like(dur), dur)), p.sigma_min().expand(batch).reshape(B),
                          settings)
    settings = RenderSettings(panel_path_sigmas=3.5, nodes=S)

    def model_fn(theta, it):
        M, ph = theta[:, 0], theta[:, 1]
        traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([ph, ph], -1), om[it])
        img = render_coded(traj, GaussianPSF(center[it], cov[it], amp[it]), ExposureWindow(start[it], dur[it]), code, height=H,
                           width=W, settings=settings)
        if fit_scale:
            img = img * theta[:, 2, None, None]
        return img.reshape(theta.shape[0], -1)

    from torchblur.render.blur import quadrature_nodes
    from torchblur.render.splat import gaussian_splat_with_jacobian

    m = settings.nodes_per_panel
    tau, wq = quadrature_nodes(S // m, m, dtype=dtype, device=device)
    frac0, width = code[:, 0], code[:, 1] - code[:, 0]  # [K]
    A_p, B_p, C_p = GaussianPSF(center, cov, amp).precision()

    def jac_fn(theta, it):
        """Model [n, H W] and Jacobian [n, H W, P] from one splat over the nodes of every open interval."""
        n = theta.shape[0]
        te = dur[it][:, None, None]
        t = (start[it][:, None, None] + te * (frac0[:, None] + width[:, None] * tau)).reshape(n, -1)  # [n, K S]
        w = (te * width[:, None] * wq).reshape(n, -1) * amp[it][:, None]
        arg = om[it][:, None] * t + theta[:, 1, None]
        sn, cs = torch.sin(arg), torch.cos(arg)
        px = center[it][:, 0, None] + theta[:, 0, None] * sn
        py = center[it][:, 1, None].expand(px.shape)
        dpx = torch.stack([sn, theta[:, 0, None] * cs], -1)
        img, dimg = gaussian_splat_with_jacobian(px, py, dpx, torch.zeros_like(dpx), w, A_p[it], B_p[it], C_p[it], H, W)
        J = dimg.movedim(1, -1).reshape(n, H * W, 2)
        model = img.reshape(n, -1)
        if fit_scale:
            J = torch.cat([J * theta[:, 2, None, None], model[..., None]], -1)
            model = model * theta[:, 2, None]
        return model, J

    res = levenberg_marquardt(lambda th, i: model_fn(th, item[i]), theta0, data[item], weight=weight[item], max_iter=max_iter, tol=tol,
                              jacobian_fn=lambda th, i: jac_fn(th, item[i]))
    cost = torch.nan_to_num(res.cost, nan=float("inf")).reshape(B, K)
    best = cost.argmin(-1)
    ar = torch.arange(B, device=device)
    theta = res.theta.reshape(B, K, P)[ar, best].clone()
    neg = theta[:, 0] < 0
    theta[:, 0] = theta[:, 0].abs()
    theta[:, 1] = wrap_phase(theta[:, 1] + math.pi * neg)
    # The plain window's alias branch: the code breaks the alias when its cost is higher there.
    c_mid = om * (start + dur / 2)
    ta = theta.clone()
    ta[:, 1] = wrap_phase(math.pi - 2 * c_mid - theta[:, 1])
    model, J = jac_fn(theta, ar)
    if noise_std is None:
        sig2 = ((data - model) ** 2).sum(-1) / max(1, H * W - P)
        fw = weight / sig2[:, None]
    else:
        fw = weight
    F = (J * fw[..., None]).transpose(-1, -2) @ J
    covm, _ = torch.linalg.inv_ex(F)
    std = torch.diagonal(covm, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    conv = res.converged.reshape(B, K)[ar, best]
    out = lambda x, tail=(): x.reshape(batch + tail)  # noqa: E731
    return CodedFit(amplitude=out(theta[:, 0]), phase=out(theta[:, 1]), amplitude_std=out(std[:, 0]), phase_std=out(std[:, 1]),
                    cost=out(cost[ar, best]), alias_cost=out(image_loss(model_fn(ta, ar).detach(), data, weight=weight)),
                    converged=out(conv), covariance=out(covm, (P, P)), scale=out(theta[:, 2]) if fit_scale else None)
