"""Image losses, one value per batch item (a sum over the trailing pixel axes), and what each
needs from the camera's noise model to be a likelihood.

All take ``model`` and ``data`` of the same shape ``[..., R]`` (R: pixels, flattened over
exposures), an optional per-pixel ``weight`` ``[..., R]`` (0 excludes a pixel) and return ``[...]``.

- ``l2``: ``sum w (data - model)^2`` (Frobenius; maximum likelihood under Gaussian noise with
  ``w = 1 / sigma^2``).
- ``l1``: ``sum w |data - model|`` (least absolute deviations; with ``w = 1 / sigma`` the
  residuals are scaled by their noise).
- ``linf``: ``max w |data - model|`` (no likelihood: no covariance).
- ``poisson``: the deviance ``2 sum w (y log(y / lam) - (y - lam))`` with ``y = max(data + s, 0)``
  and ``lam = model + s``, ``s`` the ``shift`` (default 0): maximum likelihood under Poisson
  noise (data and model in counts), and with ``s = read_noise_e**2`` the shifted Poisson of
  Poisson-plus-Gaussian read noise (:class:`~torchblur.render.camera.CameraNoise`); ``w`` a 0/1 mask.

:func:`loss_weight` gives each loss its weight from the l2 weights ``1 / sigma^2`` (the one
noise model), and :func:`covariance_factor` what its covariance is in units of the l2 Fisher
inverse.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import ParameterError, check_choice, flat_noise_and_mask

__all__ = ["LOSSES", "LIKELIHOOD_LOSSES", "chi2_limit", "covariance_factor", "fisher_covariance", "gauss_newton_terms",
           "image_loss", "irls_weights", "loss_weight", "pixel_weights", "residual_weights", "singular_covariance"]

LOSSES = ("l2", "l1", "linf", "poisson")
# The losses whose estimates come with a covariance that holds (identify accepts these).
LIKELIHOOD_LOSSES = ("l2", "l1", "poisson")


def chi2_limit(dof, z: float) -> float:
    """``1 + z sqrt(2 / dof)``: the largest reduced chi2 of ``dof`` (>= 1 counted) degrees of freedom
    that passes a test at ``z`` of its stds (a right model's reduced chi2 has std ``sqrt(2 / dof)``)."""
    return 1.0 + z * math.sqrt(2.0 / max(1, int(dof)))


def loss_weight(loss: str, inverse_variance: torch.Tensor) -> torch.Tensor:
    """Each loss's per-pixel weight ``[...]`` from the l2 weights ``inverse_variance = 1 / sigma^2``
    ``[...]`` (0 excludes a pixel): l2 ``1 / sigma^2``; l1 and linf ``1 / sigma`` (the residual
    in noise stds); poisson the 0/1 mask (the deviance carries its own variance, ``lam``).

    Example:
        >>> loss_weight("l1", torch.tensor([0.25, 0.0]))
        tensor([0.5000, 0.0000])
    """
    check_choice(loss, "loss", LOSSES)
    if loss == "l2":
        return inverse_variance
    if loss == "poisson":
        return (inverse_variance > 0).to(inverse_variance.dtype)
    return inverse_variance.clamp_min(0).sqrt()


def pixel_weights(noise_std, mask, images: torch.Tensor, frame_dims: int = 3):
    """A fitter's l2 pixel weights of ``images [..., *frame]`` (``frame``: the last ``frame_dims``
    dims): ``(weight [N, *frame], std)``, ``weight = 1 / std^2`` (ones without ``noise_std``) and 0
    where ``mask`` is False; ``std`` None, ``[N]`` or ``[N, *frame]``, the checked ``noise_std`` of
    :func:`~torchblur.errors.flat_noise_and_mask`. With one weight per item and nothing masked,
    ``weight`` is a broadcast view of ``N`` values, not a copy."""
    std, keep = flat_noise_and_mask(noise_std, mask, images, frame_dims)
    shape = (max(1, math.prod(images.shape[:-frame_dims])),) + tuple(images.shape[-frame_dims:])
    if std is None:
        weight = torch.ones(shape[0], dtype=images.dtype, device=images.device)
    else:
        weight = 1 / std**2
    if weight.dim() == 1:
        weight = weight.reshape(shape[:1] + (1,) * frame_dims).expand(shape)
    if keep is not None:
        weight = weight * keep.to(images.dtype)
    return weight, std

def covariance_factor(loss: str) -> float:
    """The covariance of the loss's estimate in units of the l2 Fisher inverse
    ``(J^T diag(1 / sigma^2) J)^-1``, under Gaussian noise of std ``sigma``: l2 and poisson 1
    (maximum likelihood: poisson's own Fisher information ``J^T diag(1 / lam) J`` is the l2 one
    with ``sigma^2 = lam``); l1 ``pi / 2`` (least absolute deviations on residuals scaled by
    ``sigma``: ``1 / (4 f(0)^2)`` for the standard normal density ``f``, Koenker & Bassett
    1978; a std ``sqrt(pi / 2) = 1.25`` times l2's); linf NaN (no likelihood)."""
    check_choice(loss, "loss", LOSSES)
    return {"l2": 1.0, "poisson": 1.0, "l1": math.pi / 2, "linf": float("nan")}[loss]


def residual_weights(resid: torch.Tensor, weight: torch.Tensor, n_params: int, *, cut_sq=0.0, cut_n=0.0):
    """The Fisher weights of a fit whose noise is estimated from its residuals: ``(fisher_weight [N, R],
    sigma^2 [N])``, one variance per item ``sum r^2 / (n_used - P)`` over the used pixels
    (``weight [N, R] > 0``) of ``resid [N, R]``, plus the pixels a crop cut off (``cut_sq [N]`` their
    sum of squares, ``cut_n [N]`` their count: the model is 0 there), and ``(weight > 0) / sigma^2``."""
    used = weight > 0
    n_used = used.sum(-1).to(resid.dtype) + cut_n
    sig2 = (((resid * resid) * used).sum(-1) + cut_sq) / (n_used - n_params).clamp_min(1)
    return used.to(resid.dtype) / sig2[:, None].clamp_min(torch.finfo(resid.dtype).tiny), sig2


def fisher_covariance(jac: torch.Tensor, fisher_weight: torch.Tensor):
    """The inverse Fisher information ``(J^T diag(w) J)^-1`` of ``jac [N, R, P]`` with the pixel
    weights ``fisher_weight [N, R]`` (``1 / sigma^2``) -> ``(covariance [N, P, P], info [N])``
    (``info`` non-zero where the inversion failed: :func:`singular_covariance`)."""
    return torch.linalg.inv_ex((jac * fisher_weight[..., None]).transpose(-1, -2) @ jac)


def singular_covariance(cov: torch.Tensor, info: torch.Tensor) -> torch.Tensor:
    """``[N]`` bool: the parameters are not identifiable: the inversion failed (``info``), or a
    covariance ``[N, P, P]`` is not finite or has a variance <= 0."""
    bad = (info != 0) | ~torch.isfinite(cov).all(-1).all(-1)
    return bad | (torch.diagonal(cov, dim1=-2, dim2=-1) <= 0).any(-1)


def _poisson_floor(model: torch.Tensor) -> torch.Tensor:
    # At least sqrt(tiny) (1e-19 in float32, 1.5e-154 in float64): below it 1 / model
    # overflows float32 and a finite deviance gets NaN gradients (an empty model, spot off frame).
    floor = max(1e-9 * float(model.detach().abs().max().clamp_min(1e-30)), torch.finfo(model.dtype).tiny ** 0.5)
    return model.clamp_min(floor)


def image_loss(model: torch.Tensor, data: torch.Tensor, *, loss: str = "l2", weight: torch.Tensor | None = None,
               shift: float = 0.0) -> torch.Tensor:
    """Per-item loss ``[...]`` between ``model`` and ``data`` ``[..., R]`` (see module doc);
    ``shift`` (>= 0, counts) is poisson's read-noise shift, ignored by the others."""
    check_choice(loss, "loss", LOSSES)
    r = data - model
    w = torch.ones_like(r) if weight is None else weight
    if loss == "l2":
        return (w * r * r).sum(-1)
    if loss == "l1":
        return (w * r.abs()).sum(-1)
    if loss == "linf":
        return (w * r.abs()).amax(-1)
    lam = _poisson_floor(model + shift)
    d = (data + shift).clamp_min(0)
    pos = d > 0
    # d log(d / lam) as d (log d - log lam), with log 1 where d = 0: the masked branch must not
    # be 0 * log(0) or 0 / lam^2 (NaN gradients for an all-zero observation).
    log_d = torch.log(torch.where(pos, d, torch.ones_like(d)))
    term = torch.where(pos, d * (log_d - torch.log(lam)), torch.zeros_like(d)) - (d - lam)
    return 2 * (w * term).sum(-1)


def irls_weights(model: torch.Tensor, data: torch.Tensor, *, loss: str, weight: torch.Tensor | None, shift: float = 0.0) -> torch.Tensor:
    """Gauss-Newton weights whose weighted least-squares step is the loss's Newton/Fisher
    step (iteratively reweighted least squares): l2: ``w``; poisson: ``w / (model + shift)``
    (Fisher scoring; the Fisher information's weights); l1: ``w / max(|r|, eps) / 2``."""
    w = torch.ones_like(model) if weight is None else weight
    if loss == "l2":
        return w
    if loss == "poisson":
        return w / _poisson_floor(model.detach() + shift)
    if loss == "l1":
        r = (data - model).detach().abs()
        eps = 1e-6 * float(data.detach().abs().max().clamp_min(1e-30))
        return w / r.clamp_min(eps) / 2
    raise ParameterError(f"loss: {loss!r} is not a sum of per-pixel terms; use optimizer='adam' or 'lbfgs'")


def gauss_newton_terms(model: torch.Tensor, data: torch.Tensor, *, loss: str, weight: torch.Tensor | None, shift: float = 0.0):
    """The terms of the loss's Gauss-Newton (Fisher scoring) step: ``(curvature [..., R],
    gradient [..., R])``; the step is ``(J^T diag(curvature) J)^-1 J^T gradient`` (``J`` the
    model's Jacobian ``[..., R, P]``), and ``g^T A^-1 g`` (``A = J^T diag(curvature) J``,
    ``g = J^T gradient``) over the cost per degree of freedom is the step's squared length in
    noise stds (what ``levenberg_marquardt``'s ``gn_tol`` measures).

    l2 and poisson: ``curvature`` = :func:`irls_weights`, ``gradient = curvature * r`` (``r`` the
    residual; ``A`` and ``g`` are half the cost's Hessian and minus half its gradient).
    l1 (``w`` the weights ``1 / sigma``): the cost ``C = sum w |r|`` is not smooth, and
    reweighting by ``1 / |r|`` converges slowly on noisy images (the pixels whose residual is
    near 0 dominate), so its step is Newton's on the expected cost under Gaussian noise:
    ``gradient = w sign(r)`` (minus the cost's gradient) and ``curvature = 2 n w^2 / (pi C)``
    (the expected Hessian ``sqrt(2 / pi) J^T diag(w^2) J / s``, ``n`` the pixels used and the
    scaled residuals' std ``s = sqrt(pi / 2) C / n`` estimated from the cost: 1 where ``w`` is
    the true ``1 / sigma``). Its fixed point is the l1 optimum (``sum w sign(r) J = 0``).

    Example:
        >>> c, g = gauss_newton_terms(torch.zeros(4), torch.tensor([1.0, -1.0, 2.0, -2.0]), loss="l1", weight=None)
        >>> g
        tensor([ 1., -1.,  1., -1.])
    """
    if loss != "l1":
        W = irls_weights(model, data, loss=loss, weight=weight, shift=shift)
        return W, W * (data - model)
    r = (data - model).detach()
    w = torch.ones_like(r) if weight is None else weight
    cost = (w * r.abs()).sum(-1, keepdim=True)
    n = (w > 0).sum(-1, keepdim=True).to(r.dtype)
    curvature = 2 * w * w * n / (math.pi * cost.clamp_min(torch.finfo(r.dtype).tiny))
    return curvature, w * torch.sign(r)
