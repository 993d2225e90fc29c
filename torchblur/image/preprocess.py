"""Image preprocessing: dark frames, thresholds, spot finding, crops, the still-spot PSF fit
and the saturation curve (paper Fig. 4).

Conventions (as everywhere in torchblur): ``image[..., i, j]`` is the pixel at row ``i``,
column ``j``, whose centre is at ``x = j``, ``y = i``; positions in pixels (px), covariances
in px^2; ``[...]`` are batch dims; ``K`` spots or samples; ``N`` frames; ``H, W`` pixels.
Frames are in the camera's units (ADU, or electrons after
:meth:`~torchblur.render.camera.CameraModel.to_electrons`); a PSF's ``amplitude`` is its peak
intensity per second of exposure, in those units.

Every function is pure: tensors in, new tensors out, dtype and device taken from the
inputs. Image filtering and connected components use kornia (imported by this module only;
the package's ``__init__`` does not import it).

Typical use on a still-spot recording::

    dark = dark_frame(dark_frames)                       # [N, H, W] -> DarkFrame
    still = subtract_dark(still_frames, dark).mean(-3)   # average of N still frames
    spots = find_spots(still, noise_std=dark.read_noise / N**0.5)[0]
    crops, offset = crop(still, spots.centroid[0], (32, 32))
    fit = fit_gaussian_psf(crops, exposure_s=Te, mask=curve.mask(crops + dark_level))
    psf_full_frame = GaussianPSF(fit.psf.center + offset, fit.psf.cov, fit.psf.amplitude)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
import torch.autograd.forward_ad as fwAD

from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, broadcast_batch, check_finite, check_positive, check_real_scalar
from torchblur.image.moments import image_moments
from torchblur.fit.optim import levenberg_marquardt
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import RenderSettings, render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

__all__ = [
    "DarkFrame",
    "dark_frame",
    "subtract_dark",
    "threshold_mask",
    "Spots",
    "find_spots",
    "crop",
    "PSFFit",
    "fit_gaussian_psf",
    "SaturationCurve",
    "saturation_curve",
]

_MAD_TO_STD = 1.482602218505602  # 1 / Phi^-1(3/4): MAD of a Gaussian times this is its std


# --------------------------------------------------------------------------- helpers


def _image(value, name: str, *, min_dim: int = 2, desc: str = "[..., H, W]") -> torch.Tensor:
    """A floating tensor of at least ``min_dim`` dims (shape error names ``name``)."""
    t = as_tensor(value, name)
    if t.dim() < min_dim:
        raise ShapeError(f"{name}: expected shape {desc}, got {tuple(t.shape)}")
    if t.shape[-1] < 1 or t.shape[-2] < 1:
        raise ShapeError(f"{name}: expected non-empty H and W in {desc}, got {tuple(t.shape)}")
    return t


def _robust_std(x: torch.Tensor, dim) -> torch.Tensor:
    """``1.4826 * median(|x - median(x)|)`` over the (flattened) trailing ``dim`` dims."""
    flat = x.flatten(-dim) if dim > 1 else x
    med = flat.median(-1, keepdim=True).values
    return _MAD_TO_STD * (flat - med).abs().median(-1).values


def _check_int(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputTypeError(f"{name}: expected an integer, got {type(value).__name__}")
    if value < low:
        raise ParameterError(f"{name}: expected an integer >= {low}, got {value}")
    return value


def _batch_std(noise_std, name: str, like: torch.Tensor) -> torch.Tensor:
    """A per-item noise std ``[...]`` (> 0) broadcastable against ``like.shape[:-2]``."""
    s = check_positive(as_tensor(noise_std, name, like=like), name)
    broadcast_batch({"image": like.shape[:-2], name: s.shape})
    return s


# --------------------------------------------------------------------------- dark frames


@dataclass
class DarkFrame:
    """The dark level of a sensor, measured from frames taken with no light.

    Attributes:
        mean: ``[..., H, W]``: ``mean[..., i, j]`` is the dark level of pixel (i, j), the
            mean over the frames (frame units, e.g. ADU).
        read_noise: ``[...]``: the frame-to-frame noise std of one pixel in one frame, a
            robust (MAD-based) estimate pooled over all pixels (frame units; includes the
            1/12 ADU^2 of quantization).
        hot_pixels: bool ``[..., H, W]``: pixels whose dark level lies more than ``k``
            robust standard deviations above the median dark level.
        n_frames: the number of frames ``N`` averaged into ``mean``.
    """

    mean: torch.Tensor
    read_noise: torch.Tensor
    hot_pixels: torch.Tensor
    n_frames: int


def dark_frame(frames, *, k: float = 8.0) -> DarkFrame:
    """Dark level, read noise and hot pixels from ``N`` dark frames.

    Args:
        frames: dark frames ``[..., N, H, W]`` (N >= 2), finite.
        k: a pixel is hot when its mean exceeds the median dark level by more than ``k``
            robust standard deviations of the per-pixel means (> 0, default 8).

    Returns:
        :class:`DarkFrame` with ``mean [..., H, W]``, ``read_noise [...]`` and
        ``hot_pixels [..., H, W]``.

    The read noise is ``1.4826 * MAD`` of the residuals ``frames - mean`` over all frames and
    pixels, times ``sqrt(N / (N - 1))`` (a residual from a mean of N has variance
    ``(N-1)/N sigma^2``); the MAD ignores the few hot pixels' large fluctuations. The
    spread of the means is ``1.4826 * MAD`` of ``mean`` over the pixels (it includes any
    fixed-pattern noise), at least ``read_noise / sqrt(N)``.

    Example:
        >>> d = dark_frame(100 + 5 * torch.randn(3, 16, 32, 32))
        >>> d.mean.shape, d.read_noise.shape, d.hot_pixels.shape
        (torch.Size([3, 32, 32]), torch.Size([3]), torch.Size([3, 32, 32]))
    """
    frames = _image(frames, "frames", min_dim=3, desc="[..., N, H, W]")
    check_finite(frames, "frames")
    k = check_real_scalar(k, "k", positive=True)
    N = frames.shape[-3]
    if N < 2:
        raise ShapeError(f"frames: expected at least 2 frames in [..., N, H, W], got N = {N} (shape {tuple(frames.shape)})")
    f = frames.detach()
    mean = f.mean(-3)
    resid = (f - mean[..., None, :, :]) * math.sqrt(N / (N - 1))
    read_noise = _robust_std(resid, 3)
    level = mean.flatten(-2).median(-1).values
    spread = torch.maximum(_robust_std(mean, 2), read_noise / math.sqrt(N))
    spread = spread.clamp_min(torch.finfo(f.dtype).eps * (level.abs() + 1))
    hot = mean > (level + k * spread)[..., None, None]
    return DarkFrame(mean=mean, read_noise=read_noise, hot_pixels=hot, n_frames=N)


def subtract_dark(frames, dark: DarkFrame, *, clip_negative: bool = False) -> torch.Tensor:
    """``frames - dark.mean``, optionally clipped at 0.

    Args:
        frames: ``[..., H, W]`` (any leading dims, e.g. ``[..., N, H, W]``).
        dark: a :class:`DarkFrame`; ``dark.mean`` broadcasts against ``frames`` from the
            right (a ``[H, W]`` dark level fits any stack of frames).
        clip_negative: set negative results to 0 (biases the mean of faint pixels; leave
            it off for fitting).

    Returns:
        Dark-subtracted frames, the broadcast shape, dtype of ``frames``. Hot pixels are
        not repaired: exclude them with ``~dark.hot_pixels`` as a fit mask.
    """
    frames = _image(frames, "frames")
    if not isinstance(dark, DarkFrame):
        raise InputTypeError(f"dark: expected a DarkFrame, got {type(dark).__name__}")
    try:
        torch.broadcast_shapes(frames.shape, dark.mean.shape)
    except RuntimeError:
        raise ShapeError(
            f"dark: dark.mean of shape {tuple(dark.mean.shape)} does not broadcast against frames of shape {tuple(frames.shape)}"
        ) from None
    out = frames - dark.mean.to(frames.dtype)
    return out.clamp_min(0) if clip_negative else out


# --------------------------------------------------------------------------- thresholds and spots


def _smooth(image: torch.Tensor, sigma_px: float) -> tuple[torch.Tensor, float]:
    """Gaussian smoothing (kornia) of ``[..., H, W]`` and the factor by which it scales white noise's std."""
    H, W = image.shape[-2:]
    ksize = 2 * int(math.ceil(3 * sigma_px)) + 1
    flat = image.reshape(-1, 1, H, W)
    border = "reflect" if min(H, W) > ksize // 2 else "replicate"
    out = kornia.filters.gaussian_blur2d(flat, (ksize, ksize), (sigma_px, sigma_px), border_type=border)
    k1 = kornia.filters.get_gaussian_kernel1d(ksize, sigma_px, device=image.device, dtype=image.dtype).reshape(-1)
    # 2-D kernel = outer(k1, k1): sqrt(sum of its squares) = sum k1^2 (the std factor)
    return out.reshape(image.shape), float(k1.square().sum())


def threshold_mask(image, noise_std, k: float = 3.0, *, sigma_px: float = 1.0) -> torch.Tensor:
    """Pixels significantly above zero, after Gaussian smoothing.

    The image is smoothed with ``kornia.filters.gaussian_blur2d`` (std ``sigma_px``), which
    scales white pixel noise of std ``noise_std`` to ``g * noise_std`` with
    ``g = sqrt(sum kernel^2)`` (about ``1 / (2 sqrt(pi) sigma_px)``); a pixel is kept where
    the smoothed value exceeds ``k * g * noise_std``.

    Args:
        image: dark-subtracted image ``[..., H, W]`` (background ~ 0), finite.
        noise_std: per-pixel noise std of ``image``: a number or ``[...]`` (> 0).
        k: significance in standard deviations of the smoothed noise (> 0). With k = 3
            about 0.1% of pure-noise pixels pass (in clumps); use 5 to find spots.
        sigma_px: smoothing std in px (> 0); 0 smoothing is not offered.

    Returns:
        bool mask ``[..., H, W]`` (broadcast of image and noise_std batch).
    """
    image = _image(image, "image")
    check_finite(image, "image")
    k = check_real_scalar(k, "k", positive=True)
    sigma_px = check_real_scalar(sigma_px, "sigma_px", positive=True)
    s = _batch_std(noise_std, "noise_std", image)
    smooth, gain = _smooth(image, sigma_px)
    return smooth > (k * gain * s)[..., None, None]


@dataclass
class Spots:
    """Spots found in one image, brightest first; ``K`` spots.

    Attributes:
        centroid: ``[K, 2]`` (x, y px): intensity-weighted centroid of the spot's pixels.
        box: ``[K, 4]`` long ``(x0, y0, x1, y1)``: the spot's pixels lie in
            ``image[y0:y1, x0:x1]`` (end exclusive).
        total: ``[K]``: sum of the image over the spot's pixels.
        area: ``[K]`` long: number of pixels in the spot.
    """

    centroid: torch.Tensor
    box: torch.Tensor
    total: torch.Tensor
    area: torch.Tensor

    def __len__(self) -> int:
        return int(self.total.shape[0])


def find_spots(
    image,
    *,
    noise_std,
    max_spots: int | None = None,
    min_area: int = 4,
    k: float = 5.0,
    sigma_px: float = 1.0,
) -> list[Spots]:
    """Find bright spots (e.g. the many spots of a Shack-Hartmann frame).

    The pixels of :func:`threshold_mask` (smoothed image above ``k`` noise stds) are
    grouped into 8-connected components with ``kornia.contrib.connected_components_union_find``;
    components smaller than ``min_area`` pixels or with a non-positive total are dropped.
    Each spot's centroid and total come from the raw (unsmoothed) pixels of its component.

    Args:
        image: dark-subtracted image ``[H, W]`` or ``[..., H, W]`` (background ~ 0; repair
            or zero hot pixels first: a bright hot pixel smoothed is a small spot).
        noise_std: pixel noise std, a number or ``[...]`` (> 0).
        max_spots: keep at most this many, the brightest (None: all).
        min_area: smallest spot in pixels (>= 1).
        k: detection threshold in smoothed-noise standard deviations (default 5: a
            96x96 frame of pure noise gives no spot).
        sigma_px: smoothing std in px before thresholding.

    Returns:
        A list of :class:`Spots`, one per image over the flattened batch (row-major);
        a single ``[H, W]`` image gives a list of one.

    Example:
        >>> img = torch.zeros(32, 32); img[10:13, 20:23] = 100.0
        >>> s = find_spots(img, noise_std=1.0)[0]
        >>> s.centroid
        tensor([[21., 11.]])
    """
    image = _image(image, "image")
    check_finite(image, "image")
    if max_spots is not None:
        max_spots = _check_int(max_spots, "max_spots", 0)
    min_area = _check_int(min_area, "min_area", 1)
    mask = threshold_mask(image, noise_std, k, sigma_px=sigma_px)
    H, W = image.shape[-2:]
    img = image.detach().expand(mask.shape).reshape(-1, H * W)
    B = img.shape[0]
    dtype, device = img.dtype, img.device
    labels = kornia.contrib.connected_components_union_find(mask.reshape(B, 1, H, W)).reshape(B, H * W)
    b_idx, p_idx = (labels > 0).nonzero(as_tuple=True)
    uniq, inv = torch.unique(labels[b_idx, p_idx], return_inverse=True)
    L = uniq.numel()
    v = img[b_idx, p_idx]
    xs = p_idx % W
    ys = torch.div(p_idx, W, rounding_mode="floor")
    zeros = torch.zeros(L, dtype=dtype, device=device)
    total = zeros.index_add(0, inv, v)
    sx = zeros.index_add(0, inv, v * xs.to(dtype))
    sy = zeros.index_add(0, inv, v * ys.to(dtype))
    area = torch.zeros(L, dtype=torch.long, device=device).index_add(0, inv, torch.ones_like(inv))
    big = torch.full((L,), max(H, W), dtype=torch.long, device=device)
    x0 = big.scatter_reduce(0, inv, xs, "amin")
    y0 = big.scatter_reduce(0, inv, ys, "amin")
    x1 = torch.zeros_like(big).scatter_reduce(0, inv, xs, "amax") + 1
    y1 = torch.zeros_like(big).scatter_reduce(0, inv, ys, "amax") + 1
    owner = torch.zeros_like(big).scatter_reduce(0, inv, b_idx, "amax")
    keep = (area >= min_area) & (total > 0)
    centroid = torch.stack([sx, sy], -1) / total.clamp_min(torch.finfo(dtype).tiny)[:, None]
    box = torch.stack([x0, y0, x1, y1], -1)
    out = []
    for b in range(B):
        sel = (keep & (owner == b)).nonzero(as_tuple=True)[0]
        sel = sel[torch.argsort(total[sel], descending=True, stable=True)]
        if max_spots is not None:
            sel = sel[:max_spots]
        out.append(Spots(centroid=centroid[sel], box=box[sel], total=total[sel], area=area[sel]))
    return out


# --------------------------------------------------------------------------- crops


def crop(images, center_xy, size) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer crops around given centres, shifted to stay inside the frame (no interpolation).

    The crop's top-left pixel is ``x0 = floor(cx - (w - 1)/2 + 1/2)`` (so an odd-sized
    crop is centred on the pixel nearest ``cx``), then clamped to ``[0, W - w]``; the same
    for y.

    Args:
        images: ``[..., H, W]``.
        center_xy: ``[..., 2]`` (x, y px), finite; batch broadcasts against the images'.
        size: ``(h, w)`` in pixels (or one int for a square), ``1 <= h <= H``, ``1 <= w <= W``.

    Returns:
        ``(crops [..., h, w], offset [..., 2])``: ``crops[..., i, j] = images[..., y0 + i,
        x0 + j]`` and ``offset = (x0, y0)`` (long): a position in the crop plus ``offset``
        is the position in the full frame.

    Example:
        >>> c, off = crop(torch.arange(100.0).reshape(10, 10), torch.tensor([1.0, 8.0]), (3, 3))
        >>> off
        tensor([0, 7])
    """
    images = as_tensor(images, "images") if not isinstance(images, torch.Tensor) else images
    if images.dim() < 2:
        raise ShapeError(f"images: expected shape [..., H, W], got {tuple(images.shape)}")
    center = as_tensor(center_xy, "center_xy", like=images if images.is_floating_point() else None)
    if center.dim() < 1 or center.shape[-1] != 2:
        raise ShapeError(f"center_xy: expected shape [..., 2] (x, y px), got {tuple(center.shape)}")
    check_finite(center, "center_xy")
    if isinstance(size, int) and not isinstance(size, bool):
        size = (size, size)
    if not isinstance(size, (tuple, list)) or len(size) != 2:
        raise InputTypeError(f"size: expected (h, w) or an int, got {size!r}")
    H, W = images.shape[-2:]
    h = _check_int(size[0], "size", 1)
    w = _check_int(size[1], "size", 1)
    if h > H or w > W:
        raise ParameterError(f"size: expected a crop no larger than the frame ({H}, {W}), got ({h}, {w})")
    batch = broadcast_batch({"images": images.shape[:-2], "center_xy": center.shape[:-1]})
    imgs = images.expand(batch + (H, W))
    c = center.detach().expand(batch + (2,))
    x0 = torch.floor(c[..., 0] - (w - 1) / 2 + 0.5).clamp(0, W - w).long()
    y0 = torch.floor(c[..., 1] - (h - 1) / 2 + 0.5).clamp(0, H - h).long()
    rows = y0[..., None] + torch.arange(h, device=images.device)  # [..., h]
    cols = x0[..., None] + torch.arange(w, device=images.device)  # [..., w]
    out = torch.gather(imgs, -2, rows[..., :, None].expand(batch + (h, W)))
    out = torch.gather(out, -1, cols[..., None, :].expand(batch + (h, w)))
    return out, torch.stack([x0, y0], -1)


# --------------------------------------------------------------------------- PSF fit


@dataclass
class PSFFit:
    """Result of :func:`fit_gaussian_psf`, batch ``[...]``.

    Attributes:
        psf: the fitted :class:`~torchblur.render.psf.GaussianPSF` (center ``[..., 2]`` px, cov
            ``[..., 2, 2]`` px^2, amplitude ``[...]`` = peak intensity per second).
        background: ``[...]`` fitted constant offset (image units; 0 if not fitted).
        residual_rms: ``[...]`` rms of ``image - model`` over the fitted pixels.
        relative_residual: ``[...]`` ``residual_rms`` over the model's peak above background.
        cov_std: ``[..., 2, 2]`` one standard deviation of each covariance entry (px^2);
            NaN where the information matrix is singular (the same for the two below).
        center_std: ``[..., 2]`` one standard deviation of the centre (px).
        amplitude_std: ``[...]`` one standard deviation of the amplitude.
        converged: ``[...]`` bool: the Levenberg-Marquardt iteration converged.
        model: ``[..., H, W]`` the fitted image (renderer output plus background).
    """

    psf: GaussianPSF
    background: torch.Tensor
    residual_rms: torch.Tensor
    relative_residual: torch.Tensor
    cov_std: torch.Tensor
    center_std: torch.Tensor
    amplitude_std: torch.Tensor
    converged: torch.Tensor
    model: torch.Tensor


def _cholesky_cov(theta: torch.Tensor) -> torch.Tensor:
    """theta[:, 2:5] = (log L00, L10, log L11) -> cov [n, 2, 2] = L L^T."""
    L00 = torch.exp(theta[:, 2])
    L11 = torch.exp(theta[:, 4])
    L10 = theta[:, 3]
    # Exactly 0 would send the renderer down its axis-aligned path, which ignores the cross
    # term and so has no derivative in it; a relative eps keeps the tilted path.
    L10 = L10 + (L10 == 0).to(L10.dtype) * torch.finfo(L10.dtype).eps * L00
    sxx = L00 * L00
    sxy = L00 * L10
    syy = L10 * L10 + L11 * L11
    return torch.stack([torch.stack([sxx, sxy], -1), torch.stack([sxy, syy], -1)], -2)


def fit_gaussian_psf(
    image,
    *,
    exposure_s,
    noise_std=None,
    mask=None,
    fit_background: bool = True,
    pixel_integration: bool = True,
    max_iter: int = 100,
) -> PSFFit:
    """Fit a 2-D Gaussian PSF (full covariance), its amplitude and a background to a still spot.

    The model image is the library's renderer in still mode,
    ``render_blur(Sinusoid(0, 0, 1), GaussianPSF(c, cov, a), ExposureWindow(0, exposure_s),
    settings=RenderSettings(pixel_integration=...)) + background``, so the fitted PSF is
    exactly the one the renderer reproduces the image with: ``amplitude`` is per second of
    exposure and the pixel-integration setting matches. Parameters
    ``(cx, cy, log L00, L10, log L11, a[, b])`` with ``cov = L L^T`` (L lower triangular,
    positive diagonal) keep the covariance positive definite. The fit is a batched
    Levenberg-Marquardt (:func:`torchblur.fit.optim.levenberg_marquardt`) started from the image
    moments, computed in float64 (results cast back to the image's dtype).

    Args:
        image: still-spot image ``[..., H, W]`` (averaged still frames, dark-subtracted),
            finite where ``mask`` is True.
        exposure_s: exposure of ``image`` in seconds, a number or ``[...]`` (> 0).
        noise_std: pixel noise std of ``image``: a number, ``[...]`` or a per-pixel map
            ``[..., H, W]`` (recognised by its trailing ``(H, W)``); the fit is weighted by
            ``1 / noise_std^2`` and ``cov_std`` comes from the Fisher information. None: an
            unweighted fit whose uncertainty is the heteroscedasticity-consistent (sandwich)
            estimate ``(J^T J)^-1 J^T diag(r^2) J (J^T J)^-1`` from the residuals ``r``.
        mask: bool ``[..., H, W]`` (or ``[H, W]``), False excludes a pixel (saturated, hot).
        fit_background: fit a constant offset (else background 0).
        pixel_integration: the renderer's pixel-area integration (must match how the PSF
            will be rendered).
        max_iter: Levenberg-Marquardt iterations at most (>= 1).

    Returns:
        :class:`PSFFit`, batch ``[...]`` (the broadcast of image, exposure, noise and mask
        batches).

    Example:
        >>> psf = GaussianPSF.from_axes(torch.tensor([12.3, 11.6]), 2.4, 1.5, 0.6, amplitude=1e4)
        >>> img = render_blur(Sinusoid(torch.zeros(2), torch.zeros(2), 1.0), psf, ExposureWindow(0.0, 0.1),
        ...                   height=24, width=24, settings=RenderSettings(pixel_integration=True))
        >>> fit_gaussian_psf(img, exposure_s=0.1).psf.cov.shape
        torch.Size([2, 2])
    """
    image = _image(image, "image")
    H, W = image.shape[-2:]
    in_dtype, device = image.dtype, image.device
    dtype = torch.float64 if torch.finfo(in_dtype).bits < 64 else in_dtype
    if not isinstance(fit_background, bool):
        raise InputTypeError(f"fit_background: expected True or False, got {type(fit_background).__name__}")
    if not isinstance(pixel_integration, bool):
        raise InputTypeError(f"pixel_integration: expected True or False, got {type(pixel_integration).__name__}")
    max_iter = _check_int(max_iter, "max_iter", 1)
    exposure = check_positive(as_tensor(exposure_s, "exposure_s", like=image), "exposure_s")

    shapes = {"image": image.shape[:-2], "exposure_s": exposure.shape}
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError(f"mask: expected a bool tensor [..., H, W], got {type(mask).__name__}"
                                 f"{'' if not isinstance(mask, torch.Tensor) else ' of dtype ' + str(mask.dtype)}")
        if mask.dim() < 2 or tuple(mask.shape[-2:]) != (H, W):
            raise ShapeError(f"mask: expected shape [..., {H}, {W}] like image, got {tuple(mask.shape)}")
        shapes["mask"] = mask.shape[:-2]
    per_pixel = False
    if noise_std is not None:
        sigma = check_positive(as_tensor(noise_std, "noise_std", like=image), "noise_std")
        per_pixel = sigma.dim() >= 2 and tuple(sigma.shape[-2:]) == (H, W)
        shapes["noise_std"] = sigma.shape[:-2] if per_pixel else sigma.shape
    batch = broadcast_batch(shapes)
    N = math.prod(batch)

    data = image.detach().to(dtype).expand(batch + (H, W)).reshape(N, H * W)
    used = torch.ones(N, H * W, dtype=torch.bool, device=device)
    if mask is not None:
        used = mask.to(device).expand(batch + (H, W)).reshape(N, H * W).clone()
    bad = ~torch.isfinite(data) & used
    if bool(bad.any()):
        raise ParameterError(f"image: expected finite values where mask is True, got {int(bad.sum())} NaN/Inf entries")
    data = torch.where(used, data, torch.zeros_like(data))
    P = 6 + int(fit_background)
    n_used = used.sum(-1)
    if bool((n_used <= P).any()):
        raise ParameterError(f"mask: expected more than {P} usable pixels per image, got {int(n_used.min())}")
    weight = used.to(dtype)
    if noise_std is not None:
        s = sigma.detach().to(dtype)
        s = s.expand(batch + (H, W)) if per_pixel else s.expand(batch)[..., None, None].expand(batch + (H, W))
        weight = weight / s.reshape(N, H * W).square()
    expo = exposure.detach().to(dtype).expand(batch).reshape(N)

    theta0 = _psf_start(data, used, expo, H, W, fit_background)
    # Amplitude and background are fitted in units of their start's scale, so every Jacobian
    # column has a comparable size (the optimiser's small absolute regulariser then damps none).
    span = (torch.where(used, data, -torch.inf).amax(-1) - torch.where(used, data, torch.inf).amin(-1)).clamp_min(1e-30)
    a_scale = torch.where(theta0[:, 5] > 0, theta0[:, 5], span / expo)
    b_scale = span
    theta0[:, 5] = theta0[:, 5] / a_scale
    if fit_background:
        theta0[:, 6] = theta0[:, 6] / b_scale
    settings = RenderSettings(pixel_integration=pixel_integration, nodes=1)  # a still spot: one time node is exact
    zeros2 = torch.zeros(1, 2, dtype=dtype, device=device)

    def model_fn(theta, idx):
        n = theta.shape[0]
        psf = GaussianPSF(theta[:, 0:2], _cholesky_cov(theta), theta[:, 5] * a_scale[idx])
        still = Sinusoid(zeros2.expand(n, 2), zeros2.expand(n, 2), 1.0)
        img = render_blur(still, psf, ExposureWindow(0.0, expo[idx]), height=H, width=W, settings=settings)
        img = img.reshape(n, H * W)
        if fit_background:
            img = img + theta[:, 6:7] * b_scale[idx, None]
        return img

    def jac_fn(theta, idx):
        # All P Jacobian columns from ONE forward-AD pass: row (i, k) carries problem i with
        # the tangent e_k (fewer, larger renderer calls than P passes of model_jacobian).
        n = theta.shape[0]
        rep = theta.detach().repeat_interleave(P, 0)
        tangent = torch.eye(P, dtype=dtype, device=device).repeat(n, 1)
        with fwAD.dual_level():
            outd = fwAD.unpack_dual(model_fn(fwAD.make_dual(rep, tangent), idx.repeat_interleave(P)))
        primal = outd.primal.detach().reshape(n, P, -1)[:, 0]
        return primal, outd.tangent.reshape(n, P, -1).transpose(1, 2)

    log_lo, log_hi = math.log(0.05), math.log(4.0 * max(H, W))

    def project(theta):
        theta = theta.clone()
        theta[:, 2] = theta[:, 2].clamp(log_lo, log_hi)
        theta[:, 4] = theta[:, 4].clamp(log_lo, log_hi)
        theta[:, 3] = theta[:, 3].clamp(-4.0 * max(H, W), 4.0 * max(H, W))
        theta[:, 0] = theta[:, 0].clamp(-W, 2 * W)
        theta[:, 1] = theta[:, 1].clamp(-H, 2 * H)
        return theta

    res = levenberg_marquardt(model_fn, theta0, data, weight=weight, max_iter=max_iter, project=project, jacobian_fn=jac_fn)
    theta = res.theta
    all_idx = torch.arange(N, device=device)
    model, J = jac_fn(theta, all_idx)
    resid = (data - model) * used
    usedf = used.to(dtype)

    # Parameter covariance: Fisher information (noise given) or the sandwich estimate.
    if noise_std is not None:
        F = (J * weight[..., None]).transpose(-1, -2) @ J
        cov_theta, info = torch.linalg.inv_ex(F)
    else:
        Ju = J * usedf[..., None]
        bread, info = torch.linalg.inv_ex(Ju.transpose(-1, -2) @ Ju)
        # HC2: r^2 / (1 - h) with the leverages h = diag(J (J^T J)^-1 J^T) undoes the
        # shrinkage of the residuals of the few high-leverage (spot) pixels.
        lev = ((Ju @ bread) * Ju).sum(-1).clamp(0, 0.99)
        Jr = Ju * (resid / (1 - lev).sqrt())[..., None]
        meat = Jr.transpose(-1, -2) @ Jr
        cov_theta = bread @ meat @ bread
    # A singular information matrix (no spot, or a parameter the data cannot fix): NaN std.
    cov_theta = torch.where((info != 0)[:, None, None], torch.full_like(cov_theta, float("nan")), cov_theta)
    L00, L10, L11 = torch.exp(theta[:, 2]), theta[:, 3], torch.exp(theta[:, 4])
    G = torch.zeros(N, 3, P, dtype=dtype, device=device)  # d(sxx, sxy, syy) / d theta
    G[:, 0, 2] = 2 * L00 * L00
    G[:, 1, 2] = L00 * L10
    G[:, 1, 3] = L00
    G[:, 2, 3] = 2 * L10
    G[:, 2, 4] = 2 * L11 * L11
    var_c = torch.diagonal(G @ cov_theta @ G.transpose(-1, -2), dim1=-2, dim2=-1).clamp_min(0)
    std_c = var_c.sqrt()
    cov_std = torch.stack([torch.stack([std_c[:, 0], std_c[:, 1]], -1), torch.stack([std_c[:, 1], std_c[:, 2]], -1)], -2)
    std_theta = torch.diagonal(cov_theta, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    bg = theta[:, 6] * b_scale if fit_background else torch.zeros(N, dtype=dtype, device=device)
    rms = (resid.square().sum(-1) / n_used.to(dtype)).sqrt()
    peak = (model - bg[:, None]).amax(-1)
    rel = rms / peak.abs().clamp_min(torch.finfo(dtype).tiny)

    def out(x, tail=()):
        return x.detach().reshape(batch + tail).to(in_dtype)

    cov = _cholesky_cov(theta)
    psf = GaussianPSF(out(theta[:, 0:2], (2,)), out(cov, (2, 2)), out(theta[:, 5] * a_scale))
    return PSFFit(
        psf=psf,
        background=out(bg),
        residual_rms=out(rms),
        relative_residual=out(rel),
        cov_std=out(cov_std, (2, 2)),
        center_std=out(std_theta[:, 0:2], (2,)),
        amplitude_std=out(std_theta[:, 5] * a_scale),
        converged=res.converged.reshape(batch),
        model=out(model, (H, W)),
    )


def _psf_start(data, used, expo, H, W, fit_background):
    """Moment start ``[N, P]`` for the PSF fit from flattened data ``[N, H*W]``."""
    N = data.shape[0]
    dtype = data.dtype
    img = data.reshape(N, H, W)
    u = used.reshape(N, H, W)
    nan = torch.full_like(img, float("nan"))
    vals = torch.where(u, img, nan).reshape(N, -1)
    if fit_background:
        edge = torch.zeros(H, W, dtype=torch.bool, device=img.device)
        edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        ev = torch.where(u & edge, img, nan).reshape(N, -1)
        bg = torch.where(torch.isnan(ev).all(-1), vals.nanmedian(-1).values, ev.nanmedian(-1).values)
    else:
        bg = torch.zeros(N, dtype=dtype, device=img.device)
    sig = img - bg[:, None, None]
    noise = _MAD_TO_STD * (vals - bg[:, None]).abs().nanmedian(-1).values
    peak = torch.where(u, sig, torch.full_like(sig, -float("inf"))).amax((-1, -2))
    thr = torch.maximum(0.02 * peak, 3 * noise)
    total, centroid, cov = image_moments(torch.where(u, sig, torch.zeros_like(sig)), threshold=thr)
    good = (total > 0) & torch.isfinite(cov).all(-1).all(-1)
    sxx = torch.where(good, cov[:, 0, 0], torch.ones_like(total)).clamp_min(0.05)
    syy = torch.where(good, cov[:, 1, 1], torch.ones_like(total)).clamp_min(0.05)
    sxy = torch.where(good, cov[:, 0, 1], torch.zeros_like(total))
    sxy = sxy.clamp(-0.95 * (sxx * syy).sqrt(), 0.95 * (sxx * syy).sqrt())
    centre = torch.where(good[:, None], centroid, torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=dtype, device=img.device))
    L00 = sxx.sqrt()
    L10 = sxy / L00
    L11 = (syy - L10 * L10).clamp_min(0.0025).sqrt()
    det = (sxx * syy - sxy * sxy).clamp_min(1e-6)
    amp = torch.where(good, total / (2 * math.pi * det.sqrt()), peak.clamp_min(0)) / expo
    cols = [centre[:, 0], centre[:, 1], L00.log(), L10, L11.log(), amp]
    if fit_background:
        cols.append(bg)
    return torch.stack(cols, -1)


# --------------------------------------------------------------------------- saturation


@dataclass
class SaturationCurve:
    """Peak intensity versus exposure: ``min(offset_adu + slope_adu_per_s t, saturation_adu)``.

    Attributes (0-d tensors, the dtype of the peaks):
        slope_adu_per_s: the linear response (ADU per second of exposure).
        offset_adu: the line's value at t = 0 (the dark level plus any constant light).
        saturation_adu: the plateau; ``inf`` if no sample saturated and no full scale was given.
        linear_limit_s: the exposure where the line meets the plateau.
        residual_rms_adu: rms of the samples about the fitted curve.
        saturated_in_data: whether the samples themselves show the plateau.
    """

    slope_adu_per_s: torch.Tensor
    offset_adu: torch.Tensor
    saturation_adu: torch.Tensor
    linear_limit_s: torch.Tensor
    residual_rms_adu: torch.Tensor
    saturated_in_data: bool

    def __call__(self, exposure_s) -> torch.Tensor:
        """The curve at ``exposure_s`` (any shape), in ADU."""
        t = as_tensor(exposure_s, "exposure_s", like=self.slope_adu_per_s)
        return torch.minimum(self.offset_adu + self.slope_adu_per_s * t, self.saturation_adu)

    def mask(self, frames_adu, margin_adu: float | None = None) -> torch.Tensor:
        """Usable (unsaturated) pixels: ``frames_adu < saturation_adu - margin_adu``.

        Args:
            frames_adu: frames in ADU, any shape (raw, before dark subtraction: the same
                scale as the peaks the curve was fitted to).
            margin_adu: pixels within this distance below the plateau are excluded too
                (>= 0); default 1% of ``saturation_adu - offset_adu`` (the response bends
                before it clips).

        Returns:
            bool tensor, the shape of ``frames_adu``; NaN pixels are False.
        """
        frames = as_tensor(frames_adu, "frames_adu")
        if margin_adu is None:
            span = self.saturation_adu - self.offset_adu
            margin = torch.where(torch.isfinite(span), 0.01 * span, torch.zeros_like(span))
        else:
            margin = torch.tensor(check_real_scalar(margin_adu, "margin_adu", nonnegative=True), dtype=frames.dtype)
        level = (self.saturation_adu - margin).to(device=frames.device, dtype=frames.dtype)
        return frames < level

    def is_linear(self, exposure_s) -> torch.Tensor:
        """bool, the shape of ``exposure_s``: the peak is still on the line at that exposure."""
        t = as_tensor(exposure_s, "exposure_s", like=self.slope_adu_per_s)
        return t <= self.linear_limit_s.to(device=t.device, dtype=t.dtype)


def _hinge_fit(t: torch.Tensor, y: torch.Tensor, knots: torch.Tensor):
    """Least squares of ``y = a + b min(t, knot)`` for each knot: ``(a, b, sse)``, each ``[M]``."""
    u = torch.minimum(t[None, :], knots[:, None])  # [M, K]
    um = u.mean(-1, keepdim=True)
    ym = y.mean()
    du = u - um
    suu = du.square().sum(-1)
    b = (du * (y - ym)).sum(-1) / suu.clamp_min(torch.finfo(t.dtype).tiny)
    a = ym - b * um[:, 0]
    sse = (y - a[:, None] - b[:, None] * u).square().sum(-1)
    sse = torch.where((suu > 0) & (b > 0), sse, torch.full_like(sse, float("inf")))
    return a, b, sse


def saturation_curve(peak_adu, exposures_s, *, full_scale_adu: float | None = None, samples_per_interval: int = 64) -> SaturationCurve:
    """Fit the peak intensity versus exposure time (paper Fig. 4): linear, then flat.

    The model ``min(offset + slope t, plateau)`` is continuous, so with the knot
    ``t_k = (plateau - offset) / slope`` it is ``offset + slope min(t, t_k)``: linear in
    (offset, slope) for a fixed knot. The knot is scanned over ``samples_per_interval``
    candidates in each interval between sorted exposures (at least two samples on the line
    and two on the plateau), then once more on a finer grid around the best, and the least
    squares fit wins. The plateau is kept only if it lowers the squared error of the plain
    line by more than 9 residual variances (about a 3 sigma improvement); else the
    samples are all linear and the plateau is ``full_scale_adu`` (or ``inf``).

    Args:
        peak_adu: peak pixel values ``[K]`` (ADU, raw: the dark level included), finite.
        exposures_s: exposure times ``[K]`` (s, >= 0), at least 3 distinct values.
        full_scale_adu: the ADC's largest value (optional); used as the plateau when no
            sample saturates.
        samples_per_interval: knot candidates per interval between exposures (>= 2).

    Returns:
        :class:`SaturationCurve`.
    """
    y = as_tensor(peak_adu, "peak_adu")
    t = as_tensor(exposures_s, "exposures_s", like=y)
    if y.dim() != 1:
        raise ShapeError(f"peak_adu: expected shape [K], got {tuple(y.shape)}")
    if t.shape != y.shape:
        raise ShapeError(f"exposures_s: expected shape {tuple(y.shape)} like peak_adu, got {tuple(t.shape)}")
    check_finite(y, "peak_adu")
    check_positive(t, "exposures_s", strict=False)
    m = _check_int(samples_per_interval, "samples_per_interval", 2)
    if full_scale_adu is not None:
        full_scale_adu = check_real_scalar(full_scale_adu, "full_scale_adu", positive=True)
    t, order = t.detach().sort()
    y = y.detach()[order]
    tu = torch.unique(t)
    if tu.numel() < 3:
        raise ParameterError(f"exposures_s: expected at least 3 distinct exposures, got {tu.numel()}")
    K = t.numel()
    dtype, device = y.dtype, y.device

    a_lin, b_lin, sse_lin = _hinge_fit(t, y, t[-1:])
    best = (a_lin[0], b_lin[0], sse_lin[0], t[-1])
    saturated = False
    if tu.numel() >= 4:
        # knots between the 2nd and the 2nd-to-last distinct exposures
        frac = torch.linspace(0, 1, m + 1, dtype=dtype, device=device)[:-1]
        lo, hi = tu[1:-2], tu[2:-1]
        knots = torch.cat([(lo[:, None] + (hi - lo)[:, None] * frac).reshape(-1), tu[-2:-1]])
        a, b, sse = _hinge_fit(t, y, knots)
        i = int(torch.argmin(sse))
        if torch.isfinite(sse[i]):
            left = knots[max(i - 1, 0)]
            right = knots[min(i + 1, knots.numel() - 1)]
            fine = torch.linspace(float(left), float(right), 4 * m + 1, dtype=dtype, device=device)
            a2, b2, sse2 = _hinge_fit(t, y, fine)
            j = int(torch.argmin(sse2))
            cand = (a2[j], b2[j], sse2[j], fine[j]) if sse2[j] <= sse[i] else (a[i], b[i], sse[i], knots[i])
            dof = max(K - 3, 1)
            if not torch.isfinite(sse_lin[0]) or float(sse_lin[0] - cand[2]) > 9 * float(cand[2]) / dof:
                best = cand
                saturated = True
    a, b, sse, knot = best
    if not torch.isfinite(sse):
        raise ParameterError("peak_adu: expected peaks that rise with exposure (no positive slope fits)")
    if saturated:
        plateau = a + b * knot
        limit = knot
    elif full_scale_adu is not None:
        plateau = torch.tensor(full_scale_adu, dtype=dtype, device=device)
        limit = (plateau - a) / b
    else:
        plateau = torch.tensor(float("inf"), dtype=dtype, device=device)
        limit = torch.tensor(float("inf"), dtype=dtype, device=device)
    rms = (sse / K).sqrt()
    return SaturationCurve(
        slope_adu_per_s=b, offset_adu=a, saturation_adu=plateau, linear_limit_s=limit,
        residual_rms_adu=rms, saturated_in_data=saturated,
    )
