"""Does a shifted still explain a spot held still under a pattern? (the DM run's ``dm_plan.spot_model``
auto test, issue 23).

The run's shifted spot model says that under any command a spot is its still image moved by its
motion. :func:`fit_shifted_still` fits that model to static images of the spots (a pattern held at a
command, :meth:`torchblur.rig.dm_contract.DMRig` ``pattern_ladder``): per image the still ``K``
(``[M, h, w]``, e-/s) moved by ``(dx, dy)`` px (the renderer's Fourier shift of a kernel) and scaled by
``a``, ``model = a K(x - dx, y - dy)``, fitted by Gauss-Newton with the analytic derivatives of the
shift, weighted by the images' variance plus the still's (scaled as the model; shifted with it for
the final chi2). Where the
spots change shape as they move (a real lenslet under a curved surface), the reduced chi2 rises above
its noise-only spread, :func:`chi2_threshold`.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import ShapeError
from torchblur.image.moments import image_moments
from torchblur.losses import chi2_limit
from torchblur.render.splat import kernel_shift_with_jacobian

__all__ = ["fit_shifted_still", "chi2_threshold"]


def chi2_threshold(dof: int, n_tests: int, false_alarm: float = 0.01) -> float:
    """The largest reduced chi2 of ``dof`` degrees of freedom that passes when ``n_tests`` are made
    and the chance that any pure-noise one fails is ``false_alarm``: ``1 + z sqrt(2 / dof)``, ``z``
    the normal quantile of ``1 - false_alarm / n_tests`` (at least 4, ``psf_from_still``'s)."""
    p = torch.tensor(1.0 - false_alarm / max(1, int(n_tests)), dtype=torch.float64)
    z = max(4.0, float(torch.special.ndtri(p)))
    return chi2_limit(dof, z)


def _shifted(still, dx, dy, pad: int):
    """``still [M, h, w]`` moved by (``dx``, ``dy``) ``[..., M]`` px and its derivatives along x and y
    (:func:`~torchblur.render.splat.kernel_shift_with_jacobian`, one node): ``(image [..., M, h, w],
    d/dx, d/dy)``."""
    eye = torch.eye(2, dtype=dx.dtype, device=dx.device)
    img, jac = kernel_shift_with_jacobian(still, dx[..., None], dy[..., None], eye[None, :1], eye[None, 1:], torch.ones_like(dx)[..., None],
                                          pad=pad)
    return img, jac[..., 0, :, :], jac[..., 1, :, :]


def fit_shifted_still(images, variance, still, still_variance=None, *, mask=None, iterations: int = 5, pad: int = 6):
    """The best shifted still per image.

    Args:
        images: ``[..., M, h, w]`` static spot crops (e-/s, any common scale with ``still``).
        variance: their variance, broadcastable to ``images`` ((e-/s)^2, > 0 where used).
        still: ``[M, h, w]`` each spot's still image (same units).
        still_variance: its variance (default 0), broadcastable to ``still``.
        mask: bool broadcastable to ``images``, the pixels used (default all).
        iterations: Gauss-Newton steps.
        pad: zero padding (px) around the crop before the Fourier shift.

    Returns:
        ``(reduced_chi2 [..., M], shift [..., M, 2] (x, y px), scale [..., M], dof)``: ``dof`` the
        used pixels of the smallest mask less 3. NaN where an image has no used pixel.
    """
    if images.dim() < 3 or still.shape[-3:] != images.shape[-3:]:
        raise ShapeError(f"still: expected [M, h, w] = {tuple(images.shape[-3:])} (the images' last dims), got {tuple(still.shape)}")
    sv = torch.zeros_like(still) if still_variance is None else torch.as_tensor(still_variance, dtype=still.dtype).expand_as(still)
    use = torch.ones_like(images, dtype=torch.bool) if mask is None else torch.as_tensor(mask).expand_as(images)
    var = torch.as_tensor(variance, dtype=images.dtype, device=images.device).expand_as(images)
    use = use & (var > 0) & torch.isfinite(images)
    data = torch.where(use, images, torch.zeros_like(images))
    # start: the centroids' difference and the light's ratio
    (m_img, c_img, _), (m_st, c_st, _) = image_moments(data), image_moments(still)
    dx, dy = (c_img - c_st).unbind(-1)
    a = m_img / m_st.clamp_min(torch.finfo(still.dtype).tiny)
    for _ in range(iterations):
        S, Sx, Sy = _shifted(still, dx, dy, pad)
        wgt = torch.where(use, 1.0 / (var + a[..., None, None] ** 2 * sv).clamp_min(torch.finfo(images.dtype).tiny), 0.0)
        r = (data - a[..., None, None] * S) * wgt.sqrt()
        J = torch.stack([a[..., None, None] * Sx, a[..., None, None] * Sy, S], -1) * wgt.sqrt()[..., None]  # d model / d (dx, dy, a)
        J = J.flatten(-3, -2)
        JtJ = J.transpose(-1, -2) @ J
        step = torch.linalg.solve(JtJ + 1e-9 * torch.diag_embed(JtJ.diagonal(dim1=-2, dim2=-1)) + 1e-300 * torch.eye(3, dtype=J.dtype),
                                  (J.transpose(-1, -2) @ r.flatten(-2)[..., None]))[..., 0]
        dx, dy, a = dx + step[..., 0].clamp(-1, 1), dy + step[..., 1].clamp(-1, 1), a + step[..., 2]
    S = _shifted(still, dx, dy, pad)[0]
    Sv = _shifted(sv, dx, dy, pad)[0].clamp_min(0)  # the still's variance, moved as the model
    wgt = torch.where(use, 1.0 / (var + a[..., None, None] ** 2 * Sv).clamp_min(torch.finfo(images.dtype).tiny), 0.0)
    chi2 = ((data - a[..., None, None] * S) ** 2 * wgt).sum((-1, -2))
    n = use.sum((-1, -2))
    red = torch.where(n > 3, chi2 / (n - 3).clamp_min(1), torch.full_like(chi2, math.nan))
    dof = int(n.min()) - 3 if n.numel() else 0
    return red, torch.stack([dx, dy], -1), a, dof
