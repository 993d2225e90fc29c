"""The results of the sine fitters: :class:`ToneFit`, the fields every one has, and :class:`SinusoidFit`."""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch

__all__ = ["ToneFit", "SinusoidFit", "put_items"]


@dataclass(kw_only=True)
class ToneFit:
    """The fields of every sine fitter's result (:class:`SinusoidFit`,
    :class:`~torchblur.fit.multisine.MultisineFit`); batch ``[...]`` is the images' leading dims.

    Attributes:
        amplitude: M (px, >= 0), one per fitted axis or tone (the shapes: each subclass).
        phase: phi (rad, wrapped to (-pi, pi]), same shape.
        amplitude_std, phase_std: one standard deviation from the Fisher information at the
            solution (noise level given, or estimated from the residuals), same shape.
        covariance: ``[..., P, P]`` over every fitted parameter, in ``param_names`` order.
        param_names: names of the P parameters.
        cost: the loss at the solution, ``[...]``.
        converged: ``[...]`` bool, ``status == 0``.
        status: ``[...]`` int, see :data:`~torchblur.fit.status.STATUS`.
        noise_std: the pixel noise std used for the uncertainty, ``[...]``.
        n_iter: optimiser iterations, ``[...]``.
        scale: the fitted intensity scale ``[...]`` (None if not fitted).
        flags: ``[...]`` int, a bit field of :data:`~torchblur.fit.status.FLAGS`; test a bit with
            ``(fit.flags & PARTLY_OUT_OF_FRAME) != 0``.
        extras: the fitter's diagnostics (each subclass lists them).
    """

    amplitude: torch.Tensor
    phase: torch.Tensor
    amplitude_std: torch.Tensor
    phase_std: torch.Tensor
    covariance: torch.Tensor
    param_names: tuple
    cost: torch.Tensor
    converged: torch.Tensor
    status: torch.Tensor
    noise_std: torch.Tensor
    n_iter: torch.Tensor
    scale: torch.Tensor | None = None
    flags: torch.Tensor | None = None
    extras: dict = field(default_factory=dict)


@dataclass(kw_only=True)
class SinusoidFit(ToneFit):
    """Result of :func:`~torchblur.fit.sinusoid.fit_sinusoid`: the :class:`ToneFit` fields, with
    ``amplitude``, ``phase`` and their stds ``[...]`` (axes "x"/"y", or an image direction) or
    ``[..., 2]`` (axes "xy"); ``flags`` (:data:`~torchblur.fit.status.MASKED`,
    :data:`~torchblur.fit.status.SATURATED_MASKED`, :data:`~torchblur.fit.status.OUTLIERS_MASKED`,
    :data:`~torchblur.fit.status.PARTLY_OUT_OF_FRAME`, :data:`~torchblur.fit.status.NO_MOTION`, ...).

    Attributes:
        alias_phase: the other branch for the first exposure (renders the same image as
            ``phase`` in that exposure), same shape as ``phase``.
        alias_cost: the loss at ``(amplitude, alias_phase)`` over all exposures, ``[...]``:
            equal to ``cost`` with one exposure, larger when the exposures resolve the alias.
        background, center: fitted nuisance parameters (None if not fitted).
        n_masked: pixels excluded from the fit (every cause), ``[...]`` int.
        n_outliers: of which excluded by the robust pass (``outliers="reject"``), ``[...]`` int.
        background_plane: with ``fit_gradient``: the stray-light plane removed from each
            exposure, ``[..., E, 3]`` = (level at the frame centre, slope along x per px,
            slope along y per px), in image units; None otherwise.
        reduced_chi2: ``[...]`` the cost per degree of freedom (pixels used minus
            parameters) where the noise was given and the loss is l2 (poisson, l1: the l2 cost
            ``sum r^2 / sigma^2`` at their solution; linf: NaN): about 1 when the model
            explains the images; well above 1, the model does not, and the stds understate the
            error (a wrong PSF, stray light, a motion that is not a sine). NaN otherwise.
    """

    alias_phase: torch.Tensor
    alias_cost: torch.Tensor
    background: torch.Tensor | None = None
    center: torch.Tensor | None = None
    n_masked: torch.Tensor | None = None
    n_outliers: torch.Tensor | None = None
    background_plane: torch.Tensor | None = None
    reduced_chi2: torch.Tensor | None = None


def put_items(res: SinusoidFit, idx: torch.Tensor, sub: SinusoidFit) -> None:
    """Overwrite items ``idx [n]`` of a flat-batch ``res`` (batch ``[N]``) with those of ``sub`` (batch ``[n]``)."""
    for f in fields(SinusoidFit):
        v = getattr(res, f.name)
        if isinstance(v, torch.Tensor):
            v[idx] = getattr(sub, f.name)
