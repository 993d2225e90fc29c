"""Workarounds for torch behaviour that would give silently wrong numbers.

``Tensor.median(dim)`` and ``Tensor.nanmedian(dim)`` return garbage (denormals such as 4e-322,
measured with torch 2.13 on CPU, float64) along a dimension of stride 0, which an ``expand``-ed
tensor (a broadcast noise level, say) has and ``reshape`` keeps. :func:`median_along` reduces a
contiguous copy instead (no copy when the tensor is already contiguous)."""
from __future__ import annotations

import torch

__all__ = ["median_along"]


def median_along(x: torch.Tensor, dim: int = -1, *, keepdim: bool = False, ignore_nan: bool = False) -> torch.Tensor:
    """The median of ``x`` along ``dim`` (values only): ``x.median(dim)``, or ``x.nanmedian(dim)``
    with ``ignore_nan``, of ``x.contiguous()``. Shape: ``x``'s without ``dim`` (kept as 1 with
    ``keepdim``); dtype and device follow ``x``."""
    x = x.contiguous()
    return (x.nanmedian(dim, keepdim=keepdim) if ignore_nan else x.median(dim, keepdim=keepdim)).values
