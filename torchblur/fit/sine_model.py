"""The model a sinusoid fit compares with the images: for rows ``theta [n, P]`` (laid out by
:class:`ParamLayout`) of problems ``n [n]``, :class:`SineModel` gives the model images
``[n, E * H * W]`` and their Jacobian ``[n, E * H * W, P]``, the two calls the optimiser sees. Three
paths: analytic (a Gaussian PSF, point-sampled pixels: image and Jacobian from one splat of
:func:`torchblur.render.splat.sine_blur_with_jacobian`, frames of equal node count together), a
measured kernel (its Fourier shift, each item on its own crop, rules and FFT grid, so a batch gives
each item what a fit of it alone gives), and generic (pixel integration, ``normalize``:
:func:`~torchblur.render.blur.render_blur` and forward-mode AD).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from torchblur.optim import model_jacobian
from torchblur.render.blur import RenderSettings, _kernel_fourier, choose_node_count, panel_count, quadrature_nodes, render_blur
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.splat import sine_blur_with_jacobian, window_nodes
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

__all__ = ["ParamLayout", "SineModel", "sine_model"]

# One splat call's fixed cost (Python and per-operation overheads) in nodes x pixels of frame
# work: measured on a 2-core CPU, 1.8 ms per call against 0.84 us per node of a 22x54 frame.
_CALL_NODE_PIXELS = 2.5e6
# Kernel path: a row's FFT grid is padded by its largest displacement plus 2 px, rounded up to
# a multiple of this (px), so rows of similar reach are rendered by one call.
_PAD_STEP = 8


@dataclass(frozen=True)
class ParamLayout:
    """Where each parameter sits in ``theta [..., P]``: the amplitudes of the fitted axes, their
    phases, then ``scale``, ``background``, ``center_x, center_y`` where fitted.

    ``labels``: one name per fitted axis (``("x",)``, ``("y",)``, ``("x", "y")``, ``("u",)``
    for an image direction); the parameters are named ``amplitude_<label>``, ``phase_<label>``.
    """

    labels: tuple
    fit_scale: bool = False
    fit_background: bool = False
    fit_center: bool = False

    @property
    def n_axes(self) -> int:
        return len(self.labels)

    @property
    def names(self) -> tuple:
        """The P parameter names in ``theta`` order."""
        return tuple([f"amplitude_{a}" for a in self.labels] + [f"phase_{a}" for a in self.labels]
                     + ["scale"] * self.fit_scale + ["background"] * self.fit_background + ["center_x", "center_y"] * self.fit_center)

    @property
    def size(self) -> int:
        """P, the number of parameters."""
        return 2 * self.n_axes + int(self.fit_scale) + int(self.fit_background) + 2 * int(self.fit_center)

    @property
    def scale(self) -> int:
        """Column of the intensity scale (meaningful with ``fit_scale``)."""
        return 2 * self.n_axes

    @property
    def background(self) -> int:
        """Column of the background (meaningful with ``fit_background``)."""
        return 2 * self.n_axes + int(self.fit_scale)

    @property
    def center(self) -> int:
        """First of the two rest-position columns (meaningful with ``fit_center``)."""
        return 2 * self.n_axes + int(self.fit_scale) + int(self.fit_background)

    def amplitudes(self, theta: torch.Tensor) -> torch.Tensor:
        """``theta [..., P]`` -> amplitudes ``[..., n_axes]`` (px)."""
        return theta[..., :self.n_axes]

    def phases(self, theta: torch.Tensor) -> torch.Tensor:
        """``theta [..., P]`` -> phases ``[..., n_axes]`` (rad)."""
        return theta[..., self.n_axes:2 * self.n_axes]


@dataclass(frozen=True, eq=False)
class SineModel:
    """Model images of ``N`` sinusoid-fit problems and their Jacobian (see the module docstring).

    Attributes:
        layout: the parameters' layout.
        psf: ``[N]``, in the coordinates of the (possibly cropped) frame.
        start, duration: exposure windows (s) ``[N, E]``; omega: rad/s ``[N]``.
        direction: unit image directions of the fitted axes ``[N, n_axes, 2]``.
        height, width: the frame H, W (px).
        settings: renderer settings with the node count fixed (``settings.nodes``).
        normalize: images divided by their Frobenius norms (generic path only).
        panels: analytic path: the panel count of each frame's rule ``[N, E]`` (long); None: generic.
        nodes_per_panel: Gauss-Legendre nodes per panel of those rules.
        precision: analytic path: the PSF's ``(A, B, C)``, each ``[N]`` (``cov^-1 = [[A, B], [B, C]]``).
        kernel_rule: kernel path: each frame's quadrature rule on [0, 1], ``(tau, weights)`` each
            ``[N, E, S]`` (a frame's ``S_f <= S`` nodes first, then weight 0); None otherwise.
        regions: kernel path: ``[N, 2]`` long, ``(h, w)`` of each item's own crop, the frame's
            top-left (the rest is zero-weighted padding); None: the whole frame.
    """

    layout: ParamLayout
    psf: GaussianPSF | KernelPSF
    start: torch.Tensor
    duration: torch.Tensor
    omega: torch.Tensor
    direction: torch.Tensor
    height: int
    width: int
    settings: RenderSettings
    normalize: bool = False
    panels: torch.Tensor | None = None
    nodes_per_panel: int = 0
    precision: tuple | None = None
    kernel_rule: tuple | None = None
    regions: torch.Tensor | None = None

    @property
    def kernel_jacobian(self) -> bool:
        """True on the kernel path when the Jacobian comes in one pass with the image
        (:meth:`_kernel_image_and_jacobian`; not with ``normalize`` or a fitted rest position)."""
        return self.kernel_rule is not None and not self.normalize and not self.layout.fit_center

    @property
    def analytic(self) -> bool:
        """True when the Jacobian comes from the splat (cheap: evaluated with every trial point)."""
        return self.panels is not None

    def rendered(self, theta: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """Model ``[m, E * H * W]`` of rows ``theta [m, P]`` of problems ``n [m]`` by
        :func:`~torchblur.render.blur.render_blur` (differentiable by autograd and forward AD)."""
        L = self.layout
        amp, ph = L.amplitudes(theta), L.phases(theta)
        if L.n_axes == 2:
            amp_xy, ph_xy = amp, ph
        else:  # a motion along the direction D[n, 0]
            amp_xy, ph_xy = amp * self.direction[n, 0], torch.cat([ph, ph], -1)
        if self.kernel_rule is not None:
            img = self._kernel_images(amp, ph, n)
        else:
            c = theta[:, L.center:L.center + 2] if L.fit_center else self.psf.center[n]
            psf_n = GaussianPSF(c[:, None, :], self.psf.cov[n][:, None], self.psf.amplitude[n][:, None])
            traj = Sinusoid(amp_xy[:, None, :], ph_xy[:, None, :], self.omega[n][:, None])
            img = render_blur(traj, psf_n, ExposureWindow(self.start[n], self.duration[n]), height=self.height, width=self.width,
                              settings=self.settings)
        img = self._nuisance(img, theta)
        if self.normalize:
            img = img / img.square().sum((-1, -2), keepdim=True).sqrt().clamp_min(1e-30)
        return img.reshape(img.shape[0], -1)

    def _kernel_nodes(self, amp: torch.Tensor, ph: torch.Tensor, n: torch.Tensor):
        """Kernel path, amplitudes and phases ``[m, n_axes]`` of problems ``n [m]``: ``(t, w, disp, groups)``:
        each frame's nodes (s) and weights ``[m, E, S]``, the spot's displacement at each node ``[m, E, S, 2]``
        (0 past a frame's own nodes), and the rows grouped by crop and FFT grid, ``[(rows, h, w, pad, S)]``: the
        crop ``h x w`` (kernel ``[:h, :w]``), the grid padded by the rows' largest displacement, S the nodes."""
        tau, wq = (v[n] for v in self.kernel_rule)  # [m, E, S]
        live = wq > 0
        t = self.start[n][..., None] + self.duration[n][..., None] * tau
        w = self.duration[n][..., None] * wq
        s = torch.sin(self.omega[n][:, None, None, None] * t[..., None] + ph[:, None, None, :]) * amp[:, None, None, :]
        disp = (s[..., None] * self.direction[n][:, None, None]).sum(-2)  # [m, E, S, 2]
        disp = torch.where(live[..., None], disp, torch.zeros((), dtype=disp.dtype, device=disp.device))
        m, H, W = n.shape[0], self.height, self.width
        hw = self.regions[n] if self.regions is not None else torch.tensor([[H, W]], device=n.device).expand(m, 2)
        reach = disp.detach().abs().flatten(1).amax(-1).ceil().long() + 2 if disp.numel() else torch.full((m,), 2, dtype=torch.long)
        pad = -(-reach // _PAD_STEP) * _PAD_STEP  # [m]: rows of similar reach share a grid
        keys = torch.stack([hw[:, 0].to(pad.device), hw[:, 1].to(pad.device), pad], -1)
        uniq, group = torch.unique(keys, dim=0, return_inverse=True)
        groups = []
        for g, (h, wd, pd) in enumerate(uniq.tolist()):
            rows = (group == g).nonzero(as_tuple=True)[0].to(n.device)
            groups.append((rows, h, wd, pd, max(int(live[rows].sum(-1).max()), 1)))
        return t, w, disp, groups

    def _kernel_images(self, amp: torch.Tensor, ph: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """Kernel path: images ``[m, E, H, W]`` of amplitudes and phases ``[m, n_axes]`` of problems
        ``n [m]``, each row on its own crop, rules and FFT grid (:meth:`_kernel_nodes`)."""
        t, w, disp, groups = self._kernel_nodes(amp, ph, n)
        parts, order = [], []
        for rows, h, wd, pd, S in groups:
            kern = self.psf.kernel[n[rows], :h, :wd][:, None].expand(-1, t.shape[1], h, wd)
            img = _kernel_fourier(kern, disp[rows, :, :S, 0], disp[rows, :, :S, 1], w[rows, :, :S], pad=pd)
            parts.append(torch.nn.functional.pad(img, (0, self.width - wd, 0, self.height - h)))
            order.append(rows)
        img = torch.cat(parts) if len(parts) > 1 else parts[0]
        return img if len(parts) == 1 else img.index_select(0, torch.argsort(torch.cat(order)))

    def _kernel_image_and_jacobian(self, theta: torch.Tensor, n: torch.Tensor):
        """Kernel path: :meth:`image_and_jacobian` in one pass of
        :func:`~torchblur.render.splat.kernel_shift_with_jacobian` (exact, about 3 times faster than
        forward AD through :meth:`_kernel_images`; the same rows, crops, rules and FFT grids, so the
        same image to round-off)."""
        L, H, W = self.layout, self.height, self.width
        amp, ph = L.amplitudes(theta), L.phases(theta)  # [m, n_axes]
        m, E, K = n.shape[0], self.start.shape[1], amp.shape[-1]
        with torch.no_grad():  # the FFT grid per row, as _kernel_images chooses it
            t, w, _, groups = self._kernel_nodes(amp, ph, n)
        img = theta.new_zeros(m, E, H, W)
        J = theta.new_zeros(m, theta.shape[1], E, H, W)
        for r, h, wd, pd, S in groups:
            i, dj = sine_blur_with_jacobian(t[r, :, :S], w[r, :, :S], amp[r, None].expand(-1, E, K), ph[r, None].expand(-1, E, K),
                                            self.omega[n[r], None, None].expand(-1, E, K), self.direction[n[r], None].expand(-1, E, K, 2),
                                            theta.new_zeros(r.numel(), E, 2), None, h, wd,
                                            kernel=self.psf.kernel[n[r], :h, :wd][:, None].expand(-1, E, h, wd), pad=pd)
            img[r, :, :h, :wd] = i
            J[r, :2 * K, :, :h, :wd] = dj.transpose(1, 2)  # [rows, 2K, E, h, w]: amplitudes then phases, as theta
        return self._nuisance_with_jacobian(img, J, theta)

    def image(self, theta: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """Model ``[m, E * H * W]`` of rows ``theta [m, P]`` of problems ``n [m]`` (the splat's
        image alone on the analytic path, else :meth:`rendered`)."""
        if not self.analytic:
            return self.rendered(theta, n)
        rows = theta.shape[0]
        pc = self.panels[n]  # [rows, E]
        img = theta.new_empty(rows, pc.shape[-1], self.height, self.width)
        for u in torch.unique(pc).tolist():
            r_f, e_f = (pc == u).nonzero(as_tuple=True)
            img[r_f, e_f] = self.frames(theta[r_f], n[r_f], e_f, u, jacobian=False)[0]
        return self._nuisance(img, theta).reshape(rows, -1)

    def image_and_jacobian(self, theta: torch.Tensor, n: torch.Tensor):
        """``(model [m, R], J [m, R, P])``, ``R = E * H * W``, of rows ``theta [m, P]`` of problems
        ``n [m]``: from the splat (frames grouped by their node count), else by forward AD."""
        if self.kernel_jacobian:
            return self._kernel_image_and_jacobian(theta, n)
        if not self.analytic:
            return model_jacobian(self.rendered, theta, n)
        H, W = self.height, self.width
        rows, P = theta.shape
        pc = self.panels[n]  # [rows, E]
        E = pc.shape[-1]
        counts = torch.unique(pc).tolist()
        J = theta.new_empty(rows, P, E, H, W)  # parameter-major: the normal equations are then plain GEMMs
        if len(counts) == 1:
            r_f = torch.arange(rows, device=theta.device).repeat_interleave(E)
            e_f = torch.arange(E, device=theta.device).repeat(rows)
            img, dimg = self.frames(theta[r_f], n[r_f], e_f, counts[0])
            img = img.reshape(rows, E, H, W)
            dimg = dimg.reshape(rows, E, -1, H, W).transpose(1, 2)
            for j_theta, j_splat in self._splat_columns():
                J[:, j_theta].copy_(dimg[:, j_splat])
        else:
            img = theta.new_empty(rows, E, H, W)
            for u in counts:
                r_f, e_f = (pc == u).nonzero(as_tuple=True)
                img[r_f, e_f], dimg = self.frames(theta[r_f], n[r_f], e_f, u)
                for j_theta, j_splat in self._splat_columns():
                    J[r_f, j_theta, e_f] = dimg[:, j_splat]
        return self._nuisance_with_jacobian(img, J, theta)

    def frames(self, theta_f: torch.Tensor, n_f: torch.Tensor, e_f: torch.Tensor, n_panels: int, *, jacobian: bool = True):
        """Image ``[m, H, W]`` and splat Jacobian ``[m, Q, H, W]`` (``Q = 2 n_axes (+ 2)``: the
        amplitude, phase (and rest position) columns; ``Q = 0`` without ``jacobian``) of ``m``
        frames: problem ``n_f [m]``, exposure ``e_f [m]``, parameters ``theta_f [m, P]``, on a
        rule of ``n_panels`` panels. Analytic path only."""
        tau, wq = quadrature_nodes(n_panels, self.nodes_per_panel, dtype=theta_f.dtype, device=theta_f.device)  # a few us
        L = self.layout
        t, w = window_nodes(self.start[n_f, e_f], self.duration[n_f, e_f], tau, wq, self.psf.amplitude[n_f])
        centre = theta_f[:, L.center:L.center + 2] if L.fit_center else self.psf.center[n_f]
        precision = tuple(v[n_f] for v in self.precision)
        return sine_blur_with_jacobian(t, w, L.amplitudes(theta_f), L.phases(theta_f), self.omega[n_f, None].expand(-1, L.n_axes),
                                       self.direction[n_f], centre, precision, self.height, self.width,
                                       center_jacobian=L.fit_center, jacobian=jacobian)

    def _splat_columns(self):
        """Pairs ``(theta columns, splat Jacobian columns)`` as slices: the splat's amplitude and
        phase columns, then its rest-position columns, which follow the scale and background in theta."""
        L = self.layout
        k2 = 2 * L.n_axes
        if L.center == k2:  # nothing between: one block
            q = k2 + 2 * int(L.fit_center)
            return [(slice(0, q), slice(0, q))]
        out = [(slice(0, k2), slice(0, k2))]
        if L.fit_center:
            out.append((slice(L.center, L.center + 2), slice(k2, k2 + 2)))
        return out

    def _nuisance_with_jacobian(self, img: torch.Tensor, J: torch.Tensor, theta: torch.Tensor):
        """:meth:`_nuisance` with its Jacobian: ``img [m, E, H, W]`` and the splat's ``J [m, P,
        E, H, W]`` (its scale and background columns filled here, in place) -> ``(model [m, R],
        J [m, R, P])``."""
        L = self.layout
        m, P = J.shape[:2]
        if L.fit_scale:
            J.mul_(theta[:, L.scale, None, None, None, None])
            J[:, L.scale] = img
        if L.fit_background:
            J[:, L.background] = 1
        return self._nuisance(img, theta).reshape(m, -1), J.reshape(m, P, -1).transpose(1, 2)

    def _nuisance(self, img: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """``img [m, E, H, W]`` times the fitted scale, plus the fitted background."""
        L = self.layout
        if L.fit_scale:
            img = img * theta[:, L.scale, None, None, None]
        if L.fit_background:
            img = img + theta[:, L.background, None, None, None]
        return img


def sine_model(layout: ParamLayout, psf, start, duration, omega, direction, height: int, width: int, *, amplitude_bound,
               settings: RenderSettings | None = None, normalize: bool = False, region=None) -> SineModel:
    """The :class:`SineModel` of ``N`` problems, its node counts fixed for the whole fit.

    Args:
        layout, psf ``[N]``, start, duration ``[N, E]``, omega ``[N]``, direction ``[N, n_axes, 2]``,
            height, width, normalize: as in :class:`SineModel`.
        amplitude_bound: ``[N, n_axes]`` px, a generous bound on the fitted amplitudes.
        settings: renderer settings (None: panels of 3.5 PSF widths). Without a node count, one
            count for the rendered model (``settings.nodes``) and, on the analytic path, one per
            frame (``panels [N, E]``) come from the motion bound: a short exposure or a small
            motion needs far fewer nodes than the batch's longest streak, and the splat's cost
            is proportional to them. A fit needs the model far below the noise, not to
            round-off: panels of 3.5 PSF widths (quadrature error < 1e-6 of the peak; estimates
            move < 2e-7 of their std vs 2.5).
        region: a kernel's per-item crops ``[N, 4]`` long (``x0, y0, w, h``; the crop at the
            frame's top-left: :attr:`~torchblur.fit.problem.SineProblem.region`), or None (the
            whole frame).
    """
    settings = settings or RenderSettings(panel_path_sigmas=3.5)
    panels = None
    N, E = duration.shape
    if settings.nodes is None:
        amp_xy = (direction.abs() * amplitude_bound[..., None]).sum(1)
        path = Sinusoid(amp_xy[:, None, :], torch.zeros_like(amp_xy)[:, None, :], omega[:, None]).path_length(
            ExposureWindow(torch.zeros_like(duration), duration))
        smin = psf.sigma_min()[:, None]
        span = omega[:, None] * duration  # [N, E]
        S = choose_node_count(path, smin, settings, span)
        panels = panel_count(path, smin, settings, span)
        settings = dataclasses.replace(settings, nodes=S)
    model = dict(layout=layout, psf=psf, start=start, duration=duration, omega=omega, direction=direction, height=height,
                 width=width, settings=settings, normalize=normalize)
    if isinstance(psf, KernelPSF):
        return SineModel(**model, kernel_rule=_frame_rules(panels, settings, N, E, duration),
                         regions=None if region is None else region[:, [3, 2]])
    if normalize or settings.pixel_integration:
        return SineModel(**model)
    m_nodes = settings.nodes_per_panel
    if panels is None or settings.nodes % m_nodes:  # nodes given by the caller: one rule for every frame
        m_nodes = settings.nodes if settings.nodes % m_nodes else m_nodes
        panels = torch.full((N, E), settings.nodes // m_nodes, dtype=torch.long, device=duration.device)
    else:
        panels = _merge_panel_groups(panels, m_nodes, _CALL_NODE_PIXELS / (height * width))
    return SineModel(**model, panels=panels, nodes_per_panel=m_nodes, precision=psf.precision())


def _frame_rules(panels, settings: RenderSettings, N: int, E: int, like: torch.Tensor):
    """Each frame's own quadrature rule ``(tau, weights)``, each ``[N, E, S]`` (``S`` the most
    nodes any frame has; a frame's nodes first, then zero weights): ``panels [N, E]`` panels of
    ``settings.nodes_per_panel`` nodes, or (``panels`` None) ``settings.nodes`` nodes for every
    frame, as :func:`~torchblur.render.blur.render_blur` lays them out."""
    m = settings.nodes_per_panel
    if panels is None:
        S = settings.nodes
        m = m if S % m == 0 else S
        panels = torch.full((N, E), S // m, dtype=torch.long, device=like.device)
    S = int(panels.max()) * m
    tau = torch.zeros(N, E, S, dtype=like.dtype, device=like.device)
    wq = torch.zeros_like(tau)
    for u in torch.unique(panels).tolist():
        r, e = (panels == u).nonzero(as_tuple=True)
        t_u, w_u = quadrature_nodes(u, m, dtype=like.dtype, device=like.device)
        tau[r, e, :u * m], wq[r, e, :u * m] = t_u, w_u
    return tau, wq


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
