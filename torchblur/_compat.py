"""Workarounds for torch behaviour that would give silently wrong numbers.

``Tensor.median(dim)`` and ``Tensor.nanmedian(dim)`` return garbage (denormals such as 4e-322,
measured with torch 2.13 on CPU, float64) along a dimension of stride 0, which an ``expand``-ed
tensor (a broadcast noise level, say) has and ``reshape`` keeps. :func:`median_along` reduces a
contiguous copy instead (no copy when the tensor is already contiguous).

``torch.linalg.lstsq``'s default CPU driver, ``gelsy`` (MKL), gives results that differ in the
last bits from call to call on the same inputs, with the process's memory state (measured with
torch 2.13 on CPU, float64: 8 distinct solutions of one 12 x 6 problem in 300 calls; it made
configs/identify_multisine.yaml's outputs differ run to run). :func:`lstsq_solution` uses
``gelsd`` (SVD-based, also rank-revealing; 1 distinct solution in those 300 calls) on CPU."""
from __future__ import annotations

import torch

__all__ = ["lstsq_solution", "median_along"]


def median_along(x: torch.Tensor, dim: int = -1, *, keepdim: bool = False, ignore_nan: bool = False) -> torch.Tensor:
    """The median of ``x`` along ``dim`` (values only): ``x.median(dim)``, or ``x.nanmedian(dim)``
    with ``ignore_nan``, of ``x.contiguous()``. Shape: ``x``'s without ``dim`` (kept as 1 with
    ``keepdim``); dtype and device follow ``x``."""
    x = x.contiguous()
    return (x.nanmedian(dim, keepdim=keepdim) if ignore_nan else x.median(dim, keepdim=keepdim)).values


def lstsq_solution(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The least-squares solution ``x [..., N, K]`` of ``a [..., M, N] x = b [..., M, K]``:
    ``torch.linalg.lstsq(a, b).solution`` with the ``gelsd`` driver on CPU (reproducible, see
    the module docstring; minimum norm where ``a`` is rank-deficient), the device's only
    driver (``gels``) elsewhere. dtype and device follow the inputs."""
    driver = "gelsd" if a.device.type == "cpu" else None
    return torch.linalg.lstsq(a, b, driver=driver).solution
