"""Pixel-level helpers of :func:`~torchblur.fit.sinusoid.fit_sinusoid`'s robust options.

Masked pixels inpainted for the starts (:func:`inpaint`), a robust noise scale
(:func:`robust_scale`), pixels no blurred Gaussian spot can produce (:func:`impulses`: hot
pixels, cosmic rays), and the stray-light plane of ``fit_gradient`` (:func:`plane_fit`,
:func:`plane_image`). Shapes: ``[n, E, H, W]`` images of ``n`` items.
"""
from __future__ import annotations

import torch

from torchblur._compat import median_along
from torchblur.render.psf import GaussianPSF

__all__ = ["inpaint", "robust_scale", "impulses", "plane_fit", "plane_image"]


def inpaint(data: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Masked pixels of ``data [n, E, H, W]`` replaced by the 3x3 median of their neighbourhood
    (kornia), so that the closed-form starts and the dark-frame test do not see them. Their
    fit weight is 0, so the cost does not change."""
    if bool(keep.all()):
        return data
    import kornia

    n, E, H, W = data.shape
    med = kornia.filters.median_blur(data.reshape(n * E, 1, H, W), 3, border_type="replicate").reshape(n, E, H, W)
    return torch.where(keep, data, med)


def robust_scale(r: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
    """``1.4826 MAD`` of the residuals ``r [n, E, H, W]`` over the used pixels, ``[n, 1, 1, 1]``."""
    x = torch.where(used, r, torch.full_like(r, float("nan"))).flatten(1)
    med = median_along(x, keepdim=True, ignore_nan=True)
    mad = median_along((x - med).abs(), ignore_nan=True) * 1.482602218505602
    return torch.nan_to_num(mad, nan=0.0).clamp_min(torch.finfo(r.dtype).tiny)[:, None, None, None]


def impulses(data: torch.Tensor, psf: GaussianPSF, noise: torch.Tensor, k: float) -> torch.Tensor:
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


def plane_fit(data: torch.Tensor, use: torch.Tensor) -> torch.Tensor:
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


def plane_image(coef: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """``[n, E, H, W]`` image of planes ``coef [n, E, 3]`` (see :func:`plane_fit`)."""
    y = torch.arange(H, dtype=coef.dtype, device=coef.device)[:, None] - (H - 1) / 2
    x = torch.arange(W, dtype=coef.dtype, device=coef.device)[None, :] - (W - 1) / 2
    return coef[..., 0, None, None] + coef[..., 1, None, None] * x + coef[..., 2, None, None] * y
