"""What an identification gives back: :class:`IdentificationResult` (the report stage's
product; the multisine plan extends it in :mod:`torchblur.identify.multisine`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = ["IdentificationResult"]


@dataclass
class IdentificationResult:
    """What :func:`identify` measured. ``frf`` (FrequencyResponse), ``model``
    (TransferFunctionFit or None), ``direct_model`` (DirectModelFit with ``model.direct=true``,
    else None), ``psf`` (GaussianPSF per second at power 1; ``[K]`` with
    many spots), ``fit`` (SinusoidFit of all points), ``amplitude`` (input amplitude per
    point), ``latency_s`` and its std, ``saturation`` (SaturationCurve), ``images`` (dark
    subtracted, electrons), ``windows``, ``truth`` (the true response or None), ``log``
    (the run's messages in order, collected by :func:`~torchblur.identify.record.collect_log`), ``timing`` (acquisition and fit seconds, and how much of the fit
    overlapped the acquisition), ``inputs`` (the excited inputs), ``spots`` (SpotPSFs or
    None), ``direction`` (one axis, one spot: the unit image direction (x, y) along which the
    motion was fitted; the response is the motion along it) and ``axis`` (the
    :class:`~torchblur.image.tracking.AxisCalibration` that measured it, with ``fit.axis=measure``),
    ``limited`` (np.bool_ per point: driven at the input range's limit, the target motion not
    reached, fitted at the smaller motion; see :mod:`torchblur.identify.drive`) and ``moved_px``
    (float per point: the motion the point reached, px: the fitted amplitude, the largest over
    the spots and image axes, NaN where nothing was fitted; a multisine: each tone's expected
    motion at the amplitudes used, from its last pilot frame), ``noise`` (the calibration's
    :class:`~torchblur.render.camera.CameraNoise`, electrons).

    One axis, one spot (SISO): ``fit`` batch ``[F]``, ``images`` ``[F, E*R, H, W]``,
    ``windows`` ``[F, E*R]``, ``amplitude`` ``[F]``, ``truth`` complex ``[F]``.
    Otherwise (a 2x2 plant and/or K spots; P = K problems per point, or 1): ``fit`` batch
    ``[I*F, P]`` (input-major) with ``axes="xy"``, ``images`` ``[I, F, P, E*R, h, w]``
    (crops of ``h x w`` at ``spots.offset``, or the frame), ``windows`` ``[I, F, E*R]``,
    ``amplitude``, ``limited`` and ``moved_px`` ``[I*F]``, ``truth`` complex ``[O, I, F]`` like
    ``frf.response``. SISO: ``limited`` and ``moved_px`` ``[F]``."""

    frf: object
    model: object
    psf: object
    fit: object
    amplitude: np.ndarray
    latency_s: float
    latency_std_s: float
    saturation: object
    images: torch.Tensor
    windows: object
    power: torch.Tensor
    truth: np.ndarray | None = None
    log: list = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    inputs: tuple = ("x",)
    spots: object = None
    direct_model: object = None  # DirectModelFit (model.direct=true) or None
    direction: tuple | None = None
    axis: object = None
    limited: np.ndarray | None = None  # [F] or [I*F] bool: the point was limited by the input range
    moved_px: np.ndarray | None = None  # [F] or [I*F]: the motion the point reached (px)
    noise: object = None  # the calibration's CameraNoise (the residual figure's sigma), or None
    ptc: object = None  # the calibration's PhotonTransfer (torchblur.image.photon_transfer), or None
