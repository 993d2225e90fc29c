"""Image losses, one value per batch item (a sum over the trailing pixel axes).

All take ``model`` and ``data`` of the same shape ``[..., R]`` (R: pixels, flattened over
exposures), an optional per-pixel ``weight`` (``1 / sigma^2`` for l2; a 0/1 mask for the
others) and return ``[...]``.

- ``l2``: ``sum w (data - model)^2`` (Frobenius; maximum likelihood under Gaussian noise).
- ``l1``: ``sum w |data - model|``.
- ``linf``: ``max w |data - model|``.
- ``poisson``: the deviance ``2 sum w (data log(data / model) - (data - model))`` (maximum
  likelihood under Poisson noise; data and model in counts).
"""
from __future__ import annotations

import torch

from torchblur.errors import ParameterError

__all__ = ["LOSSES", "image_loss", "irls_weights"]

LOSSES = ("l2", "l1", "linf", "poisson")


def _poisson_floor(model: torch.Tensor) -> torch.Tensor:
    # At least sqrt(tiny) (1e-19 in float32, 1.5e-154 in float64): below it 1 / model
    # overflows float32 and a finite deviance gets NaN gradients (an empty model, spot off frame).
    floor = max(1e-9 * float(model.detach().abs().max().clamp_min(1e-30)), torch.finfo(model.dtype).tiny ** 0.5)
    return model.clamp_min(floor)


def image_loss(model: torch.Tensor, data: torch.Tensor, *, loss: str = "l2", weight: torch.Tensor | None = None) -> torch.Tensor:
    """Per-item loss ``[...]`` between ``model`` and ``data`` ``[..., R]`` (see module doc)."""
    if loss not in LOSSES:
        raise ParameterError(f"loss: expected one of {LOSSES}, got {loss!r}")
    r = data - model
    w = torch.ones_like(r) if weight is None else weight
    if loss == "l2":
        return (w * r * r).sum(-1)
    if loss == "l1":
        return (w * r.abs()).sum(-1)
    if loss == "linf":
        return (w * r.abs()).amax(-1)
    lam = _poisson_floor(model)
    d = data.clamp_min(0)
    pos = d > 0
    # d log(d / lam) as d (log d - log lam), with log 1 where d = 0: the masked branch must not
    # be 0 * log(0) or 0 / lam^2 (NaN gradients for an all-zero observation).
    log_d = torch.log(torch.where(pos, d, torch.ones_like(d)))
    term = torch.where(pos, d * (log_d - torch.log(lam)), torch.zeros_like(d)) - (d - lam)
    return 2 * (w * term).sum(-1)


def irls_weights(model: torch.Tensor, data: torch.Tensor, *, loss: str, weight: torch.Tensor | None) -> torch.Tensor:
    """Gauss-Newton weights whose weighted least-squares step is the loss's Newton/Fisher
    step (iteratively reweighted least squares): l2: ``w``; poisson: ``w / model`` (Fisher
    scoring); l1: ``w / max(|r|, eps)``."""
    w = torch.ones_like(model) if weight is None else weight
    if loss == "l2":
        return w
    if loss == "poisson":
        return w / _poisson_floor(model.detach())
    if loss == "l1":
        r = (data - model).detach().abs()
        eps = 1e-6 * float(data.detach().abs().max().clamp_min(1e-30))
        return w / r.clamp_min(eps) / 2
    raise ParameterError(f"loss: {loss!r} is not a sum of per-pixel terms; use optimizer='adam' or 'lbfgs'")
