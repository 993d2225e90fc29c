"""Dark frames: the dark level, read noise and hot pixels of a sensor, and their subtraction.

Frames are in the camera's units (ADU, or electrons); ``[...]`` batch, ``N`` frames, ``H, W`` pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchblur._compat import median_along
from torchblur.errors import ShapeError, as_image, check_finite, check_real_scalar, check_type

__all__ = ["DarkFrame", "dark_frame", "subtract_dark", "robust_std"]

_MAD_TO_STD = 1.482602218505602  # 1 / Phi^-1(3/4): MAD of a Gaussian times this is its std


def robust_std(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``1.4826 * median(|x - median(x)|)`` over the (flattened) trailing ``dim`` dims: the
    std of Gaussian data, unmoved by a few outliers (hot pixels, the spot)."""
    flat = x.flatten(-dim) if dim > 1 else x
    med = median_along(flat, keepdim=True)
    return _MAD_TO_STD * median_along((flat - med).abs())


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
    frames = as_image(frames, "frames", min_dim=3, desc="[..., N, H, W]")
    check_finite(frames, "frames")
    k = check_real_scalar(k, "k", positive=True)
    N = frames.shape[-3]
    if N < 2:
        raise ShapeError(f"frames: expected at least 2 frames in [..., N, H, W], got N = {N} (shape {tuple(frames.shape)})")
    f = frames.detach()
    mean = f.mean(-3)
    resid = (f - mean[..., None, :, :]) * math.sqrt(N / (N - 1))
    read_noise = robust_std(resid, 3)
    level = median_along(mean.flatten(-2))
    spread = torch.maximum(robust_std(mean, 2), read_noise / math.sqrt(N))
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
    frames = as_image(frames, "frames")
    check_type(dark, "dark", DarkFrame, "a DarkFrame")
    try:
        torch.broadcast_shapes(frames.shape, dark.mean.shape)
    except RuntimeError:
        raise ShapeError(
            f"dark: dark.mean of shape {tuple(dark.mean.shape)} does not broadcast against frames of shape {tuple(frames.shape)}"
        ) from None
    out = frames - dark.mean.to(frames.dtype)
    return out.clamp_min(0) if clip_negative else out
