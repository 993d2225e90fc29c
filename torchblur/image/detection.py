"""Spot detection in one frame: a significance threshold after smoothing, connected components
(kornia) and integer crops around spots. Conventions: x = column j, y = row i, px.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch

from torchblur.errors import InputTypeError, ParameterError, broadcast_batch, ShapeError, as_image, as_noise_std, as_tensor, check_finite, check_int, check_real_scalar

__all__ = ["threshold_mask", "Spots", "find_spots", "crop"]


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
    image = as_image(image, "image")
    check_finite(image, "image")
    k = check_real_scalar(k, "k", positive=True)
    sigma_px = check_real_scalar(sigma_px, "sigma_px", positive=True)
    s = as_noise_std(noise_std, "noise_std", image)
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
    image = as_image(image, "image")
    check_finite(image, "image")
    if max_spots is not None:
        max_spots = check_int(max_spots, "max_spots", low=0)
    min_area = check_int(min_area, "min_area", low=1)
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
    h = check_int(size[0], "size", low=1)
    w = check_int(size[1], "size", low=1)
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
