"""Image moments and the closed-form sinusoid starts (PHYSICS.md section 2, "Moments").

Along a motion axis, with the window's phase at its centre ``c = omega (tcam + Te/2)``, the
exposure angle ``p = omega Te`` and ``psi = c + phi``:

    mu1 = centroid - rest = M alpha sin(psi),          alpha = 2 sin(p/2) / p
    mu2 = var(image) - Sigma + mu1^2 = (M^2/2) (1 - beta cos(2 psi)),   beta = sin(p) / p

so ``M^2 = 2 (mu2 - beta mu1^2 / alpha^2) / (1 - beta)`` and ``sin(psi) = mu1 / (M alpha)``:
two roots, ``psi`` and ``pi - psi``, which are exactly the alias pair.
"""
from __future__ import annotations

import math

import torch

from torchblur.render.alias import wrap_phase
from torchblur.errors import InputTypeError, ShapeError

__all__ = ["image_moments", "moments_along", "sinusoid_from_moments"]


def image_moments(images: torch.Tensor, *, threshold: torch.Tensor | float | None = None):
    """Total, centroid and covariance of images.

    Args:
        images: ``[..., H, W]``; pixel (i, j) at x = j, y = i.
        threshold: pixels at or below it count as zero (suppresses background noise in the
            second moments); ``[...]`` or a number; default: none (negative values clipped).

    Returns:
        ``(total [...], centroid [..., 2] (x, y px), cov [..., 2, 2] (px^2))``.
    """
    if not isinstance(images, torch.Tensor) or not images.is_floating_point():
        got = f"dtype {images.dtype}" if isinstance(images, torch.Tensor) else type(images).__name__
        raise InputTypeError(f"images: expected a real floating tensor [..., H, W], got {got}")
    if images.dim() < 2:
        raise ShapeError(f"images: expected shape [..., H, W], got {tuple(images.shape)}")
    img = images
    zero = torch.zeros((), dtype=img.dtype, device=img.device)
    if threshold is not None:
        thr = torch.as_tensor(threshold, dtype=img.dtype, device=img.device).clamp_min(0)
        while thr.dim() < img.dim():
            thr = thr[..., None]
        img = torch.where(img > thr, img, zero)
    else:
        img = img.clamp_min(0)
    H, W = img.shape[-2:]
    # Coordinates about the frame centre (less cancellation in the second moments); every
    # moment from the row sums and two matrix-vector products (no [..., H, W] temporaries).
    oy, ox = (H - 1) / 2, (W - 1) / 2
    y = torch.arange(H, dtype=img.dtype, device=img.device) - oy
    x = torch.arange(W, dtype=img.dtype, device=img.device) - ox
    sx = img @ torch.stack([torch.ones_like(x), x, x * x], -1)  # [..., H, 3]: row sums of img, img x, img x^2
    yy = torch.stack([torch.ones_like(y), y, y * y], -1)  # [H, 3]
    r0, r1 = sx[..., 0], sx[..., 1]
    m0 = r0.sum(-1)
    safe = m0.clamp_min(torch.finfo(img.dtype).tiny)
    ey = (r0[..., None, :] @ yy)[..., 0, :] / safe[..., None]  # E[1], E[y], E[y^2]
    cx = r1.sum(-1) / safe
    cy = ey[..., 1]
    sxx = (sx[..., 2].sum(-1) / safe - cx * cx).clamp_min(0)
    syy = (ey[..., 2] - cy * cy).clamp_min(0)
    sxy = (r1 * y).sum(-1) / safe - cx * cy
    cx, cy = cx + ox, cy + oy
    cov = torch.stack([torch.stack([sxx, sxy], -1), torch.stack([sxy, syy], -1)], -2)
    return m0, torch.stack([cx, cy], -1), cov


def moments_along(offset: torch.Tensor, excess_cov: torch.Tensor, direction: torch.Tensor):
    """The image moments of a spot moving along the unit ``direction`` (x, y), projected on it:
    ``offset [..., 2]`` (centroid less the rest position) and ``excess_cov [..., 2, 2]`` (image
    covariance less the PSF's) give the mean displacement ``u . offset`` and its variance
    ``u^T excess_cov u`` along it, ``[...]`` (px, px^2): the ``mu1`` and ``var_excess`` of
    :func:`sinusoid_from_moments`. ``direction`` broadcasts as ``[..., 2]``."""
    u = direction
    return (offset * u).sum(-1), (u[..., None, :] @ excess_cov @ u[..., None])[..., 0, 0]


def sinusoid_from_moments(mu1: torch.Tensor, var_excess: torch.Tensor, omega: torch.Tensor, start: torch.Tensor, duration: torch.Tensor):
    """Solve the moment equations for (M, phi) along one axis.

    Args:
        mu1: centroid offset from the rest position (px), ``[...]``.
        var_excess: ``var(image) - Sigma_axis`` (px^2), ``[...]``; then ``mu2 = var_excess + mu1^2``.
        omega: rad/s; start, duration: the window (s); all broadcast to ``[...]``.

    Returns:
        ``(M [...], phi [..., 2])``: the amplitude (>= 0) and both phase roots (the alias
        pair), wrapped to (-pi, pi]. Where ``p`` is a whole number of periods the phase is
        unidentifiable and both roots are NaN.
    """
    p = omega * duration
    c = omega * (start + duration / 2)
    alpha = torch.where(p.abs() > 1e-12, 2 * torch.sin(p / 2) / p, torch.ones_like(p))
    beta = torch.where(p.abs() > 1e-12, torch.sin(p) / p, torch.ones_like(p))
    mu2 = var_excess + mu1 * mu1
    m2 = 2 * (mu2 - beta * mu1 * mu1 / (alpha * alpha)) / (1 - beta)
    M = m2.clamp_min(0).sqrt()
    # M from the centroid alone is a lower bound: keep the larger (noise shrinks mu2 estimates).
    M = torch.maximum(M, mu1.abs() / alpha.abs().clamp_min(1e-12))
    s = (mu1 / (M * alpha).clamp_min(1e-30)).clamp(-1, 1)
    psi = torch.asin(s)
    phi = torch.stack([wrap_phase(psi - c), wrap_phase(math.pi - psi - c)], -1)
    bad = alpha.abs() < 1e-9
    phi = torch.where(bad[..., None], torch.full_like(phi, float("nan")), phi)
    return M, phi
