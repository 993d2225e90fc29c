"""The problems of a sinusoid fit as its steps see them: :func:`sine_problem` (pixel weights, noise
and background levels, the items that cannot be fitted), :func:`starting_points` (closed-form starts
from the image moments) and :func:`crop_to_reach` (the frames cut to where the model reaches).
"""
from __future__ import annotations

import dataclasses
import math
import statistics
from dataclasses import dataclass

import torch

from torchblur._compat import median_along
from torchblur.fit.sine_model import ParamLayout
from torchblur.image.moments import image_moments, moments_along, sinusoid_from_moments
from torchblur.losses import pixel_weights
from torchblur.render.alias import wrap_phase
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow

__all__ = ["SineProblem", "sine_problem", "starting_points", "crop_to_reach", "crop_box", "cut_sums", "dark_items",
           "matched_filter_peak", "DARK_FALSE_ALARM"]


@dataclass(frozen=True)
class SineProblem:
    """``N`` sinusoid-fit problems of ``E`` exposures (a flat batch), checked.

    Attributes:
        data: images ``[N, E, H, W]`` (dark level subtracted); after :func:`crop_to_reach`, the crop's.
        weight: fit weight of each pixel ``[N, E, H, W]`` (``1 / sigma^2``; 0 excludes the pixel;
            a broadcast view of ``row_weight`` where that is set).
        row_weight: ``[N]``: the one weight of every pixel of an item (the same noise on every
            pixel, nothing masked), else None.
        noise_given: whether the caller gave the pixel noise std.
        noise_level: pixel noise std per item ``[N]`` (given: its median over the pixels;
            else ``1.4826`` MAD of a strided subsample).
        level: the median pixel (the background level) per item ``[N]``.
        start, duration: exposure windows (s) ``[N, E]``; omega: rad/s ``[N]``.
        psf: ``[N]``, in the coordinates of ``data``.
        rest: the rest position ``[N, 2]`` (px, the PSF's centre or centroid, full frame);
            psf_cov: its covariance ``[N, 2, 2]`` (px^2).
        direction: unit image directions of the fitted axes ``[N, n_axes, 2]``.
        dark: ``[N]`` bool, no signal above the noise (:func:`dark_items`: a matched filter); outside: ``[N]`` bool, the rest
            position is out of the frame (3 PSF sigmas margin).
        dim: ``[N]`` bool or None: lit, but only the matched filter sees it (no pixel above 8
            noise stds); its starts come from the smoothed images.
        origin: ``(x0, y0)``, the crop's corner in the full frame (px).
        region: ``[N, 4]`` long or None: a measured kernel's own crop per item (``x0, y0, w, h``
            in the full frame, px; :func:`crop_to_reach`): item ``n``'s pixels are
            ``data[n, :, :h, :w]``, the rest of the frame ``data`` is zero-weighted padding.
        cut_cost, cut_sq, cut_n: ``[N]``, over the pixels the crop cut off: the weighted sum of
            squares, the plain sum of squares over the used pixels, the number of used pixels
            (the model is zero there, so they add a constant to the cost and to the residuals).
    """

    data: torch.Tensor
    weight: torch.Tensor
    row_weight: torch.Tensor | None
    noise_given: bool
    noise_level: torch.Tensor
    level: torch.Tensor
    start: torch.Tensor
    duration: torch.Tensor
    omega: torch.Tensor
    psf: GaussianPSF | KernelPSF
    rest: torch.Tensor
    psf_cov: torch.Tensor
    direction: torch.Tensor
    dark: torch.Tensor
    outside: torch.Tensor
    dim: torch.Tensor | None = None
    origin: tuple = (0, 0)
    cut_cost: torch.Tensor | None = None
    cut_sq: torch.Tensor | None = None
    cut_n: torch.Tensor | None = None
    region: torch.Tensor | None = None

    @property
    def live(self) -> torch.Tensor:
        """``[N]`` bool: the items to fit (neither dark nor out of frame)."""
        return ~self.dark & ~self.outside


def sine_problem(data, psf, window: ExposureWindow, omega, direction, *, noise_std=None, use=None) -> SineProblem:
    """A :class:`SineProblem` from checked, flat inputs.

    Args:
        data: ``[N, E, H, W]`` floating images; psf: ``[N]``; window: ``[N, E]``; omega: ``[N]`` rad/s.
        direction: ``[N, n_axes, 2]`` unit image directions of the fitted axes.
        noise_std: None, ``[N]`` or ``[N, E, H, W]`` (positive, data's dtype).
        use: None or bool ``[N, E, H, W]``: False excludes a pixel.
    """
    dtype, device = data.dtype, data.device
    N, E, H, W = data.shape
    win = window.to(dtype).expand((N, E))
    if isinstance(psf, GaussianPSF):
        psf = psf.to(dtype)
    rest, cov_psf = psf.moments()
    weight, std = pixel_weights(noise_std, use, data)
    # one weight per item, nothing masked: weight is a view of row_weight (see SineProblem)
    row_weight = weight[:, 0, 0, 0] if use is None and (std is None or std.dim() == 1) else None
    sigma_level = None if std is None else median_along(std.reshape(N, -1))
    # Background and noise level from ~1024-2048 pixels per item (a strided subsample: the
    # median of 1024 noise samples is within 0.04 std of the level, and a median costs a
    # selection per item).
    flat = data.reshape(N, -1)
    sub = flat[:, ::max(1, flat.shape[-1] // 1024)]
    med = median_along(sub)
    noise_level = sigma_level if sigma_level is not None else median_along((sub - med[:, None]).abs()) * 1.4826
    peak = (flat - med[:, None]).amax(-1)
    dark = dark_items(data, med, noise_level, cov_psf, noise_given=noise_std is not None, peak=peak)
    dim = ~dark & ~(peak > 8 * noise_level.clamp_min(torch.finfo(dtype).tiny))
    # The rest position must be in the frame (3 sigma margin): otherwise flag, do not fit.
    sd = torch.diagonal(cov_psf, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    outside = ((rest < -3 * sd) | (rest > torch.tensor([W - 1, H - 1], dtype=dtype, device=device) + 3 * sd)).any(-1)
    zero = torch.zeros(N, dtype=dtype, device=device)
    return SineProblem(data=data, weight=weight, row_weight=row_weight, noise_given=noise_std is not None, noise_level=noise_level,
                       level=med, start=win.start.reshape(N, E), duration=win.duration.reshape(N, E), omega=omega, psf=psf,
                       rest=rest, psf_cov=cov_psf, direction=direction, dark=dark, outside=outside, dim=dim, cut_cost=zero, cut_sq=zero,
                       cut_n=zero.clone())


DARK_FALSE_ALARM = 1e-3  # the matched filter's false-alarm rate per item on white Gaussian noise (a bound)


def dark_items(data, level, noise_level, psf_cov, *, noise_given: bool = True, peak=None,
               false_alarm: float = DARK_FALSE_ALARM) -> torch.Tensor:
    """Which items ``[N]`` (bool) hold no signal above the noise: "dark", decided on the total
    signal of the spot by a matched filter, not on the brightest pixel (docs/reliability.md,
    "Degenerate frames are flagged per item, never raised", has the rule's false-alarm rate and gain).

    Each exposure is correlated with the zero-mean, unit-norm template of the still spot (a
    Gaussian of covariance ``psf_cov``) and divided by the pixel noise std ``noise_level``; an item
    is dark when the largest value over every pixel and exposure stays below
    ``t = Phi^-1(1 - false_alarm / n)`` (``n = E H W``, ``Phi`` the normal CDF). Where the noise std
    is estimated (``noise_given`` False) it is estimated again for the candidates from every pixel
    (``1.4826`` MAD). An item whose brightest pixel is above 8 noise stds is lit without the
    filter, and one whose brightest pixel is not above the level (an empty frame) is dark.

    Args:
        data: ``[N, E, H, W]``; level, noise_level: ``[N]`` (background and pixel noise std);
        noise_given: whether ``noise_level`` is the caller's (else estimated);
        psf_cov: ``[N, 2, 2]`` px^2; peak: optional ``[N]``, the brightest pixel less the level.
        false_alarm: the per-item false-alarm bound, in (0, 1).

    Returns:
        ``[N]`` bool, True for a dark item.
    """
    N, E, H, W = data.shape
    tiny = torch.finfo(data.dtype).tiny
    if peak is None:
        peak = (data.reshape(N, -1) - level[:, None]).amax(-1)
    dark = ~(peak > 8 * noise_level.clamp_min(tiny)) | (peak <= 0)
    idx = torch.arange(N, device=data.device)[dark & (peak > 0)]
    if idx.numel():
        noise = noise_level[idx]
        if not noise_given:  # the candidates' noise again, from every pixel (a finer estimate)
            flat = data[idx].reshape(idx.numel(), -1)
            noise = median_along((flat - median_along(flat, keepdim=True)).abs()) * 1.4826
        snr = matched_filter_peak(data[idx], psf_cov[idx]) / noise.clamp_min(tiny)
        t = statistics.NormalDist().inv_cdf(1 - false_alarm / (E * H * W))
        dark[idx] = ~(snr > t)
    return dark


def matched_filter_peak(data, psf_cov) -> torch.Tensor:
    """The largest value ``[N]`` over pixels and exposures of ``data [N, E, H, W]`` correlated
    with the zero-mean, unit-norm template of a Gaussian spot of covariance ``psf_cov [N, 2, 2]``
    (px^2; circular, by FFT). A constant background adds nothing; for white noise of std ``s``
    each value has std ``s``."""
    g, _ = _template(psf_cov, *data.shape[-2:], data.dtype)
    g = g - g.mean((-1, -2), keepdim=True)  # zero mean: blind to the background level
    return _correlate(data, g / g.square().sum((-1, -2), keepdim=True).sqrt()).flatten(1).amax(-1)


def _template(psf_cov, H: int, W: int, dtype):
    """The still spot's template ``g [N, H, W]`` (a Gaussian of covariance ``psf_cov [N, 2, 2]``
    plus 0.05 px^2, peak 1, centred on pixel (0, 0), circular) and that covariance ``[N, 2, 2]``."""
    device = psf_cov.device

    def offsets(n):  # pixel offsets 0, 1, ..., -1 in FFT order
        return (torch.arange(n, device=device, dtype=dtype) + n // 2) % n - n // 2

    dy, dx = offsets(H)[:, None], offsets(W)[None, :]
    cov = psf_cov.to(dtype) + 0.05 * torch.eye(2, dtype=dtype, device=device)  # a point PSF still spans a pixel
    prec = torch.linalg.inv(cov)[:, None, None]  # [N, 1, 1, 2, 2]
    q = prec[..., 0, 0] * dx * dx + 2 * prec[..., 0, 1] * dx * dy + prec[..., 1, 1] * dy * dy
    return torch.exp(-0.5 * q), cov


def _correlate(data, g):
    """``data [N, E, H, W]`` correlated with the centred, symmetric ``g [N, H, W]`` (circular, by FFT)."""
    H, W = data.shape[-2:]
    return torch.fft.irfft2(torch.fft.rfft2(data) * torch.fft.rfft2(g)[:, None], s=(H, W))


def smoothed_for_moments(data, level, noise_level, psf_cov):
    """For the starts of a dim item: ``(smoothed [N, E, H, W], threshold [N], cov [N, 2, 2])``:
    the background-subtracted images blurred by the spot's template (unit sum, so the light
    is kept and its covariance ``cov`` adds to the image's), and 3 noise stds of the result."""
    g, cov = _template(psf_cov, *data.shape[-2:], data.dtype)
    g = g / g.sum((-1, -2), keepdim=True)
    smooth = _correlate(data - level[:, None, None, None], g)
    return smooth, 3 * noise_level * g.square().sum((-1, -2)).sqrt(), cov


def starting_points(problem: SineProblem, layout: ParamLayout):
    """Starts ``(theta0 [N * K, P], amplitude0 [N, K, n_axes])``, ``K`` candidates per item.

    The closed-form starts come from the moments of every exposure (both roots). Candidates:
    the roots of the first exposure (the alias pair; four combinations for a Lissajous motion).
    With two or more exposures the true root is the one the exposures share (the aliases move
    with the window centre), so the single consensus root is the start (amplitude: the mean
    over the exposures). Nuisance starts: the scale from the total light, the background from
    the median pixel, the rest position from the PSF. Amplitudes are capped at the frame
    diagonal (a larger motion cannot be measured) and floored at 1e-3 px.
    """
    p = problem
    N, E, H, W = p.data.shape
    n_axes = layout.n_axes
    thr = p.level[:, None] + 3 * p.noise_level[:, None]
    _, centroid, icov = image_moments(p.data, threshold=thr)  # [N, E, 2], [N, E, 2, 2]
    icov = icov - p.psf_cov[:, None]
    if p.dim is not None and bool(p.dim.any()):
        i = torch.arange(N, device=p.data.device)[p.dim]
        smooth, s_thr, s_cov = smoothed_for_moments(p.data[i], p.level[i], p.noise_level[i], p.psf_cov[i])
        _, centroid[i], s_icov = image_moments(smooth, threshold=s_thr[:, None])
        icov[i] = s_icov - p.psf_cov[i][:, None] - s_cov[:, None]
    M_c, phi_c = [], []
    for k in range(n_axes):
        mu1, vex = moments_along(centroid - p.rest[:, None], icov, p.direction[:, None, k])
        M, phi = sinusoid_from_moments(mu1, vex, p.omega[:, None], p.start, p.duration)  # [N, E], [N, E, 2]
        M_c.append(M.clamp(max=math.hypot(H, W)))
        phi_c.append(torch.nan_to_num(phi, nan=0.0))
    roots = [(r,) for r in range(2)] if n_axes == 1 else [(r0, r1) for r0 in range(2) for r1 in range(2)]

    def root_phases(phi, rs):  # phi: per axis [N, 2] -> [N, n_axes]
        return torch.stack([phi[k][:, rs[k]] for k in range(n_axes)], -1)

    first = [c[:, 0] for c in phi_c]
    cands = [torch.cat([torch.stack([M_c[k][:, 0] for k in range(n_axes)], -1), root_phases(first, rs)], -1) for rs in roots]
    if E >= 2:
        # Compare with the exposure whose window centre best separates the alias (repeats of
        # the same window share the alias and would tell nothing).
        centre = p.omega[:, None] * (p.start + p.duration / 2)
        other = (centre - centre[:, :1]).sin().abs().argmax(-1)  # [N]
        ar = torch.arange(N, device=p.data.device)
        phi_other = [c[ar, other] for c in phi_c]  # [N, 2] per axis
        dist = torch.stack([
            torch.stack([wrap_phase(root_phases(first, rs) - root_phases(phi_other, r2)).abs().sum(-1) for r2 in roots], -1).amin(-1)
            for rs in roots], -1)  # [N, n_roots]
        cands = [torch.stack(cands, 1)[ar, dist.argmin(-1)]]
        cands[0][:, :n_axes] = torch.stack([M_c[k].mean(-1) for k in range(n_axes)], -1)
    K = len(cands)
    theta_core = torch.stack(cands, 1)  # [N, K, 2 n_axes]
    theta_core[..., :n_axes] = theta_core[..., :n_axes].clamp_min(1e-3)
    extra = _nuisance_starts(problem, layout)
    theta0 = theta_core
    if extra:
        theta0 = torch.cat([theta_core, torch.stack(extra, -1)[:, None, :].expand(N, K, len(extra))], -1)
    return theta0.reshape(N * K, layout.size).detach(), theta_core[..., :n_axes]


def _nuisance_starts(problem: SineProblem, layout: ParamLayout) -> list:
    """The starts ``[N]`` of the fitted nuisance parameters, in ``theta`` order."""
    p = problem
    extra = []
    if layout.fit_scale:
        expected = (p.psf.total_light()[:, None] * p.duration).sum(-1)
        extra.append((p.data.sum((-1, -2, -3)) / expected.clamp_min(1e-30)).clamp_min(1e-3))
    if layout.fit_background:
        extra.append(p.level)
    if layout.fit_center:
        extra += [p.rest[:, 0], p.rest[:, 1]]
    return extra


KERNEL_CROP_STEP = 8  #: px: a kernel item's own crop is rounded up to a multiple of this, so items of similar reach share a shape


def crop_to_reach(problem: SineProblem, amplitude_bound: torch.Tensor, *, fit_center: bool) -> SineProblem:
    """The problem cut to the region the model can reach (an l2 fit), or the problem itself.

    Outside it (5.5 PSF sigmas, or a kernel's non-zero pixels, beyond the largest motion,
    ``amplitude_bound [N, n_axes]`` px times 1.25 plus 0.5 px, and 2 px more with ``fit_center``)
    the model and its Jacobian are below 3e-7 of the peak (a kernel: zero), so those pixels change nothing in
    the normal equations; their constant contribution to the cost and to the noise estimate is
    kept in ``cut_cost``, ``cut_sq``, ``cut_n``. A crop is skipped unless it is at least 4x4 and
    under 90% of the frame.

    A Gaussian PSF's crop is shared by the batch (the union over the live items): the model
    there is the Gaussian's, wherever the crop ends. A measured kernel is cut with the frame,
    so each item gets its own crop (a function of that item alone, its size rounded up to
    :data:`KERNEL_CROP_STEP` px): a batch gives each item what a fit of it alone gives.
    """
    p = problem
    if not bool(p.live.any()):
        return p
    lo, hi = _reach_bounds(p, amplitude_bound, fit_center)
    if isinstance(p.psf, KernelPSF):
        return _crop_items(p, lo, hi)
    N, E, H, W = p.data.shape
    live = p.live
    lo, hi = lo[live].amin(0), hi[live].amax(0)
    box = crop_box(lo, hi, H, W)
    if box is None:
        return p
    cx0, cy0, cx1, cy1 = box
    cut_cost, cut_sq, cut_n = cut_sums(p.data, p.weight, (cy0, cy1, cx0, cx1), p.row_weight)
    return dataclasses.replace(p, data=p.data[..., cy0:cy1, cx0:cx1], weight=p.weight[..., cy0:cy1, cx0:cx1],
                               psf=p.psf.cropped(cx0, cy0, cx1, cy1),
                               origin=(cx0, cy0), cut_cost=cut_cost, cut_sq=cut_sq, cut_n=cut_n)


def cut_sums(data, weight, box, row_weight=None):
    """Over the pixels of ``data [N, E, H, W]`` outside the crop ``box = (y0, y1, x0, x1)`` (px), where
    every model is 0: ``(cost, sq, n)``, each ``[N]``: the weighted sum of squares (``weight [N, E, H,
    W]``, or one weight per item ``row_weight [N]``, nothing masked), the plain sum of squares and the
    count of the used pixels (weight > 0)."""
    N, E, H, W = data.shape
    y0, y1, x0, x1 = box
    bands = ((slice(None, y0), slice(None)), (slice(y1, None), slice(None)),
             (slice(y0, y1), slice(None, x0)), (slice(y0, y1), slice(x1, None)))

    def cut_sum(f):  # f(band) -> [N, E, h, w]: summed over the pixels the crop cuts off -> [N]
        return sum(f(b).sum((-1, -2, -3)) for b in bands)

    def sq(b):
        d = data[(..., *b)]
        return d * d

    if row_weight is not None:
        cut_sq = cut_sum(sq)
        return row_weight * cut_sq, cut_sq, torch.full_like(cut_sq, float(E * (H * W - (y1 - y0) * (x1 - x0))))
    used = weight > 0
    return (cut_sum(lambda b: weight[(..., *b)] * sq(b)), cut_sum(lambda b: used[(..., *b)] * sq(b)),
            cut_sum(lambda b: used[(..., *b)].to(data.dtype)))


def _reach_bounds(p: SineProblem, amplitude_bound: torch.Tensor, fit_center: bool):
    """``(lo [N, 2], hi [N, 2])`` (x, y px): each item's reach (see :func:`crop_to_reach`): the
    spot (a Gaussian: 5.5 sigmas about its centre; a kernel: wherever it is not zero, its
    faint wings included) widened by the motion."""
    reach = (p.direction.abs() * (amplitude_bound * 1.25 + 0.5)[..., None]).sum(1)  # [N, 2] px
    margin = 2.0 if fit_center else 0.0
    lo, hi = p.psf.footprint(5.5)
    return lo - reach - margin, hi + reach + margin


def crop_box(lo, hi, H: int, W: int) -> tuple[int, int, int, int] | None:
    """The crop ``(x0, y0, x1, y1)`` (px, the frame's ``[y0:y1, x0:x1]``) of an ``H x W`` frame
    that holds ``[lo, hi]`` (``[2]`` each, (x, y) px at pixel centres), kept inside the frame;
    None where it is not worth it (:func:`_worth_cropping`)."""
    x0, y0 = max(0, int(math.floor(float(lo[0])))), max(0, int(math.floor(float(lo[1]))))
    x1, y1 = min(W, int(math.ceil(float(hi[0]))) + 1), min(H, int(math.ceil(float(hi[1]))) + 1)
    return (x0, y0, x1, y1) if _worth_cropping(x1 - x0, y1 - y0, H, W) else None


def _worth_cropping(w: int, h: int, H: int, W: int) -> bool:
    """A crop of ``w x h`` px of an ``H x W`` frame is worth it: at least 4x4, under 90%."""
    return w >= 4 and h >= 4 and w * h < 0.9 * H * W


def _item_span(lo: float, hi: float, n: int) -> tuple[int, int]:
    """One item's crop ``(start, length)`` along an axis of ``n`` px: ``[lo, hi]`` (px, pixel
    centres) in whole pixels, the length rounded up to :data:`KERNEL_CROP_STEP` (grown about
    its middle, kept inside the frame)."""
    lo = lo if math.isfinite(lo) else 0.0
    hi = hi if math.isfinite(hi) else n - 1.0
    a, b = max(0, int(math.floor(lo))), min(n, int(math.ceil(hi)) + 1)
    length = min(n, max(b - a, 1))
    rounded = min(n, -(-length // KERNEL_CROP_STEP) * KERNEL_CROP_STEP)
    start = min(max(0, a - (rounded - length) // 2), n - rounded)
    return start, rounded


def _crop_items(p: SineProblem, lo: torch.Tensor, hi: torch.Tensor) -> SineProblem:
    """The kernel problem cut to each item's own crop (:func:`crop_to_reach`): item ``n``'s
    pixels at the top-left ``[:h_n, :w_n]`` of a frame of the largest crop's size, the rest of
    it zero (data, weight and kernel), ``region [N, 4]`` saying where each crop was."""
    N, E, H, W = p.data.shape
    dev = p.data.device
    spans = []
    for n in range(N):
        x0, w = _item_span(float(lo[n, 0]), float(hi[n, 0]), W)
        y0, h = _item_span(float(lo[n, 1]), float(hi[n, 1]), H)
        spans.append((x0, y0, w, h) if _worth_cropping(w, h, H, W) else (0, 0, W, H))
    region = torch.tensor(spans, dtype=torch.long, device=dev)  # [N, 4]
    wc, hc = int(region[:, 2].max()), int(region[:, 3].max())
    if (wc, hc) == (W, H) and bool((region[:, 2:] == region.new_tensor([W, H])).all()):
        return p
    ys = (region[:, 1, None] + torch.arange(hc, device=dev)).clamp_max(H - 1)  # [N, hc]
    xs = (region[:, 0, None] + torch.arange(wc, device=dev)).clamp_max(W - 1)  # [N, wc]
    inside = (torch.arange(hc, device=dev) < region[:, 3, None])[:, :, None] & (torch.arange(wc, device=dev) < region[:, 2, None])[:, None, :]
    n_i = torch.arange(N, device=dev)

    def cut(t):  # [N, ..., H, W] -> [N, ..., hc, wc]: each item's crop at the top-left, zero beyond
        c = t[n_i[:, None, None], ..., ys[:, :, None], xs[:, None, :]]  # [N, hc, wc, ...]
        c = c.movedim((1, 2), (-2, -1))
        return torch.where(inside.view((N,) + (1,) * (c.dim() - 3) + (hc, wc)), c, torch.zeros((), dtype=c.dtype, device=dev))

    full = torch.zeros(N, H, W, dtype=torch.bool, device=dev)
    for n, (x0, y0, w, h) in enumerate(spans):
        full[n, y0:y0 + h, x0:x0 + w] = True
    out = (~full)[:, None]  # [N, 1, H, W]: the pixels each item's crop cuts off
    sq = p.data * p.data
    used = (p.weight > 0).to(p.data.dtype)
    cut_cost = (p.weight * sq * out).sum((-1, -2, -3))
    cut_sq = (used * sq * out).sum((-1, -2, -3))
    cut_n = (used * out).sum((-1, -2, -3))
    same = bool((region[:, 2] == wc).all() and (region[:, 3] == hc).all())
    return dataclasses.replace(p, data=cut(p.data), weight=cut(p.weight), row_weight=p.row_weight if same else None,
                               psf=KernelPSF(cut(p.psf.kernel)), cut_cost=cut_cost, cut_sq=cut_sq, cut_n=cut_n, region=region)
