"""The checks and flattening every fitter's entry shares (:func:`~torchblur.fit.sinusoid.fit_sinusoid`,
:func:`~torchblur.fit.multisine.fit_multisine`, :func:`~torchblur.fit.coded.fit_sinusoid_coded`).

A fitter takes images ``[..., *frame]`` (``frame`` = ``E, H, W``, or ``H, W`` for one coded image), a
PSF, windows and frequencies batched over ``[...]``; these functions check them once, with errors that
name the argument, and flatten them to ``N = prod(...)`` items.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_tensor, as_unit_direction, check_finite,
                              check_positive, check_type)
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow

__all__ = ["fit_dtype", "check_data", "flat_window", "flat_omega", "flat_psf", "unit_direction", "flat_direction",
           "check_count", "flat_count"]


def fit_dtype(images: torch.Tensor, psf, window: ExposureWindow) -> torch.dtype:
    """The dtype a fit computes in and returns: the widest floating dtype of ``images``, the
    PSF and the window, at least float32 (integer images count as none; float16 and bfloat16
    are promoted: the model's sums and the normal equations need float32's precision)."""
    psf_t = psf.cov if isinstance(psf, GaussianPSF) else psf.kernel
    dtype = torch.float32
    for t in (images, psf_t, window.start, window.duration):
        if t.is_floating_point():
            dtype = torch.promote_types(dtype, t.dtype)
    return dtype


def _broadcasts_to(shape, target) -> bool:
    """Whether a tensor of ``shape`` can be expanded to ``target`` (broadcasting to a larger
    shape is not enough: a PSF batch of 2 does not fit images of batch 1)."""
    try:
        return torch.broadcast_shapes(tuple(shape), tuple(target)) == tuple(target)
    except RuntimeError:
        return False


def check_data(images, psf, window, *, frame_dims: int = 3):
    """Check a fitter's ``images [..., *frame]`` (a real, non-empty, finite tensor: floating or a
    camera's integer counts, dark level subtracted), ``psf`` (a GaussianPSF or a KernelPSF of the
    images' frame, batch broadcastable to ``[...]``) and ``window`` (an ExposureWindow) ->
    ``(images, psf, window)`` in one floating dtype (:func:`fit_dtype`)."""
    desc = f"[..., {', '.join('EHW'[-frame_dims:])}]"
    if not isinstance(images, torch.Tensor):
        raise InputTypeError(f"images: expected a tensor {desc}, got {type(images).__name__}")
    if images.is_complex() or images.dtype == torch.bool:
        raise InputTypeError(f"images: expected a real tensor {desc} (floating or integer counts) with the dark level "
                             f"subtracted (preprocess.subtract_dark), got dtype {images.dtype}")
    if images.dim() < frame_dims or images.numel() == 0:
        raise ShapeError(f"images: expected a non-empty tensor {desc}, got shape {tuple(images.shape)}")
    check_type(psf, "psf", (GaussianPSF, KernelPSF), "a GaussianPSF or KernelPSF")
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
    dtype = fit_dtype(images, psf, window)
    images, psf, window = images.to(dtype), psf.to(dtype), window.to(dtype)
    check_finite(images, "images")
    batch = images.shape[:-frame_dims]
    if not _broadcasts_to(psf.shape, batch):
        raise ShapeError(f"psf: expected a batch shape that broadcasts to the images' batch {tuple(batch)} "
                         f"(images {desc} = {tuple(images.shape)}), got {tuple(psf.shape)}")
    if isinstance(psf, KernelPSF) and psf.frame_shape != tuple(images.shape[-2:]):
        raise ShapeError(f"psf: expected a kernel of frame shape {tuple(images.shape[-2:])}, got {psf.frame_shape}")
    return images, psf, window


def flat_window(window: ExposureWindow, batch: tuple, N: int, E: int | None = None) -> ExposureWindow:
    """``window`` (batch broadcastable to the images' ``[...]``, or with ``E`` to ``[..., E]``: one
    window per exposure, or one for all) -> ``[N]``, or ``[N, E]`` with ``E``."""
    tail = () if E is None else (E,)
    lead = tuple(batch) + tail
    if not _broadcasts_to(window.shape, lead):
        raise ShapeError(f"window: expected a batch shape that broadcasts to the images' "
                         f"{'[..., E]' if tail else '[...]'} = {lead}, got {tuple(window.shape)}")
    w = window.expand(lead)
    return ExposureWindow(w.start.reshape((N,) + tail), w.duration.reshape((N,) + tail))


def flat_omega(omega, batch: tuple, N: int, like: torch.Tensor, *, tones: bool = False) -> torch.Tensor:
    """``omega`` (rad/s, > 0; ``[...]``, or with ``tones`` ``[..., n_tones]``, broadcastable to the
    images' batch ``[...]``) -> ``[N]`` or ``[N, n_tones]`` in ``like``'s dtype and device."""
    omega = check_positive(as_tensor(omega, "omega", dtype=like.dtype, device=like.device), "omega")
    if tones and omega.dim() == 0:
        raise ShapeError("omega: expected shape [..., N] (one value per tone), got a scalar")
    tail = tuple(omega.shape[-1:]) if tones else ()
    if not _broadcasts_to(omega.shape, tuple(batch) + tail):
        raise ShapeError(f"omega: expected a shape that broadcasts to the images' batch {tuple(batch)}"
                         f"{' + (n_tones,)' if tones else ''}, got {tuple(omega.shape)}")
    return omega.expand(tuple(batch) + tail).reshape((N,) + tail)


def flat_psf(psf, batch: tuple, N: int):
    """A PSF of batch broadcastable to ``[...]`` -> batch ``[N]`` (a KernelPSF's kernel ``[N, H, W]``)."""
    if isinstance(psf, GaussianPSF):
        return GaussianPSF(psf.center.expand(batch + (2,)).reshape(N, 2),
                           psf.cov.expand(batch + (2, 2)).reshape(N, 2, 2), psf.amplitude.expand(batch).reshape(N))
    H, W = psf.frame_shape
    return KernelPSF(psf.kernel.expand(batch + (H, W)).reshape(N, H, W))


def unit_direction(value, like: torch.Tensor, name: str = "direction") -> torch.Tensor:
    """An image direction ``(x, y)`` (a pair, or ``[2]`` / ``[..., 2]``) as a unit vector; None: +x."""
    if value is None:
        return torch.tensor([1.0, 0.0], dtype=like.dtype, device=like.device)
    return as_unit_direction(value, name, like=like)


def flat_direction(value, batch: tuple, N: int, like: torch.Tensor, name: str = "direction") -> torch.Tensor:
    """:func:`unit_direction` broadcast to the images' batch ``[...]`` -> ``[N, 2]``."""
    d = unit_direction(value, like, name)
    try:
        return d.expand(tuple(batch) + (2,)).reshape(N, 2)
    except RuntimeError:
        raise ShapeError(f"{name}: expected [2] or a shape that broadcasts to the images' batch {tuple(batch)} + (2,), "
                         f"got {tuple(d.shape)}") from None


def check_count(value, name: str, low: int = 1, *, optional: bool = False) -> None:
    """A fitter's count option (iterations, starts): an integer >= ``low`` (or None with ``optional``),
    else :class:`~torchblur.errors.ParameterError` naming ``name``."""
    if optional and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ParameterError(f"{name}: expected {'None or ' if optional else ''}an integer >= {low}, got {value!r}")


def flat_count(images: torch.Tensor, frame_dims: int = 3) -> int:
    """``N``, the number of items of ``images [..., *frame]`` (1 without batch dims)."""
    return max(1, math.prod(images.shape[:-frame_dims]))
