"""An outside recording (:mod:`torchblur.hardware.outside`) through the identification's own
stages: the folder becomes the run record's calibration (:func:`outside_calibration`: the
dark level and read noise from the dark frames, the PSF from the still frames by the same
:func:`~torchblur.identify.calibration` code as ``identify``, the motion's image direction)
and its sweep (:class:`OutsidePlan`: the sine plan whose sweep stage reads the recorded
points instead of driving a rig). The fit, assemble, model and report stages are the sine
plan's (:func:`~torchblur.identify.stages.run_plan`): no fitting logic here.

:func:`identify_outside` runs it; ``torchblur fit FOLDER`` calls it for a folder with a
``frames.csv`` (docs/outside_recordings.md).
"""
from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import replace
from functools import partial

import numpy as np
import torch

from torchblur.design.windows import check_design
from torchblur.errors import ConfigError, InputTypeError, as_unit_direction
from torchblur.hardware.outside import OutsideRecording
from torchblur.identify.calibration import Calibration, _still_psf
from torchblur.identify.config import IdentifyConfig, load_config
from torchblur.identify.fitting import ChunkFitter
from torchblur.identify.record import RunRecord, console_logging, log_message
from torchblur.identify.result import IdentificationResult
from torchblur.identify.stages import run_plan
from torchblur.identify.sweep import SineAcquisition, SinePlan, fit_points, sweep_layout
from torchblur.image.moments import image_moments
from torchblur.image.preprocess import dark_frame, subtract_dark
from torchblur.image.saturation import SaturationCurve
from torchblur.render.window import ExposureWindow
from torchblur.sysid.frequency_response import FrequencyResponse

__all__ = ["OutsidePlan", "identify_outside", "moment_direction", "outside_calibration", "outside_config"]

_F64 = torch.float64
ALLOWED = ("fit.", "model.")  # what a user may set for an outside recording (the rest is the recording's)


def outside_config(rec: OutsideRecording, overrides=()) -> IdentifyConfig:
    """The configuration that fits ``rec``: the defaults with the ``fit.*`` / ``model.*``
    ``overrides`` (and ``seed``), the camera's gain and timing from ``recording.yaml``, the
    sweep's frequencies and frame shape from the recording, ``rig.kind = "outside"``.

    Raises:
        ConfigError: an override outside ``fit.*``, ``model.*`` and ``seed`` (named), or a bad value.
    """
    for item in overrides:
        key = str(item).partition("=")[0]
        if not (key.startswith(ALLOWED) or key == "seed"):
            raise ConfigError(f"{key}: an outside recording takes only fit.*, model.* and seed overrides (its camera and sweep "
                              f"are in recording.yaml and frames.csv)")
    cfg = load_config(None, list(overrides), force=True)
    c = rec.camera
    H, W = rec.frame_shape
    camera = replace(cfg.camera, gain=float(c.gain_e_per_adu), jitter_s=float(c.jitter_s), trigger_delay_s=float(c.trigger_delay_s),
                     latency_s=float(c.latency_s), height=int(H), width=int(W))
    sweep = replace(cfg.sweep, freq_hz=[p.freq_hz for p in rec.points], images_per_point=int(rec.points[0].R))
    return replace(cfg, camera=camera, sweep=sweep, rig=replace(cfg.rig, kind="outside"))


def moment_direction(still_e: torch.Tensor, points_e: list, R: int, read_noise_e: float):
    """The motion's image direction from the blur's second moments: each exposure's (its
    repeats averaged) covariance minus the still spot's is ``var(s) u u^T`` for a motion
    ``s(t) u``; ``u`` is the leading eigenvector of their sum, pointed toward +x (as
    ``fit.axis=measure``: the FRF's phase carries the sign).

    Args:
        still_e: the mean still frame ``[H, W]`` (dark subtracted, electrons).
        points_e: per point, frames ``[E*R, H, W]`` (dark subtracted, electrons, exposure-major).
        R: images per exposure.
        read_noise_e: the moments count pixels above 3 read-noise stds.

    Returns:
        ``(u (x, y) or None, angle std rad, minor / major eigenvalue ratio)``; ``u`` is None
        when the excess has no positive leading eigenvalue (no motion seen).
    """
    thr = 3 * float(read_noise_e)
    _, _, cov0 = image_moments(still_e, threshold=thr)
    per_point = []
    for fr in points_e:
        mean = fr.reshape(fr.shape[0] // R, R, *fr.shape[-2:]).mean(1)
        _, _, cov = image_moments(mean, threshold=thr)  # [E, 2, 2]
        per_point.append((cov - cov0).sum(0))
    S = torch.stack(per_point).sum(0)
    lam, vec = torch.linalg.eigh(S)
    if not (torch.isfinite(lam).all() and float(lam[1]) > 0):
        return None, math.nan, math.nan
    u = vec[:, 1]
    if float(u[0]) < 0 or (float(u[0]) == 0 and float(u[1]) < 0):
        u = -u
    ang = math.atan2(float(u[1]), float(u[0]))
    # scatter of the points' own directions (mod pi) about the common one
    devs = []
    for Sk in per_point:
        lk, vk = torch.linalg.eigh(Sk)
        if float(lk[1]) > 0:
            d = math.atan2(float(vk[1, 1]), float(vk[0, 1])) - ang
            devs.append((d + math.pi / 2) % math.pi - math.pi / 2)
    std = float(np.std(devs, ddof=1) / math.sqrt(len(devs))) if len(devs) > 1 else math.nan
    return (float(u[0]), float(u[1])), std, float(lam[0] / lam[1])


def outside_calibration(rec: OutsideRecording, cfg: IdentifyConfig, log: list, progress: bool = False) -> Calibration:
    """The calibration of ``rec``: the dark frame and read noise (``recording.yaml``'s
    ``read_noise_e``, else measured), the saturation level, the PSF of the still frames
    (``fit.psf``, as ``identify``), the timing, and the motion's image direction
    (``fit.axis``: given, or ``measure``: :func:`moment_direction` of the sweep frames)."""
    c = rec.camera
    gain = float(c.gain_e_per_adu)
    dark = dark_frame(torch.as_tensor(rec.dark, dtype=_F64))
    read_noise_e = float(c.read_noise_e) if c.read_noise_e is not None else float(dark.read_noise) * gain
    level = dark.mean.mean()
    log_message(log, f"dark: level {float(level):.2f} ADU, read noise {read_noise_e:.2f} e- "
                     f"({'recording.yaml' if c.read_noise_e is not None else f'from {dark.n_frames} dark frames'}), "
                     f"{int(dark.hot_pixels.sum())} hot pixels", progress)
    sat_adu = torch.tensor(math.inf if c.saturation_adu is None else float(c.saturation_adu), dtype=_F64)
    nan = torch.tensor(math.nan, dtype=_F64)
    sat = SaturationCurve(slope_adu_per_s=nan, offset_adu=level, saturation_adu=sat_adu, linear_limit_s=torch.tensor(math.inf, dtype=_F64),
                          residual_rms_adu=nan, saturated_in_data=False)
    log_message(log, f"saturation: {float(sat_adu):.0f} ADU " + ("(recording.yaml)" if c.saturation_adu is not None else
                                                                  "(none given for float frames: no pixel is masked)"), progress)
    still_e = subtract_dark(torch.as_tensor(rec.still, dtype=_F64), dark) * gain
    still_psf = _still_psf(cfg, still_e, float(rec.still_exposure_s), read_noise_e, log, progress)
    psf = still_psf.gaussian.psf
    cal = Calibration(dark=dark, read_noise_e=read_noise_e, saturation=sat, full_adu=float(sat_adu - level), psf=psf,
                      peak_rate=float(psf.amplitude), latency_s=float(c.latency_s), latency_std_s=float(c.latency_std_s), gain=gain,
                      still_psf=still_psf)
    log_message(log, f"timing: latency {c.latency_s * 1e6:.3f} +- {c.latency_std_s * 1e6:.3f} us, jitter {c.jitter_s * 1e6:.3f} us "
                     f"(recording.yaml)", progress)
    mode = cfg.fit.axis
    if mode == "measure":
        pts = [subtract_dark(torch.as_tensor(p.frames, dtype=_F64), dark) * gain for p in rec.points]
        u, std, ratio = moment_direction(still_e.mean(0), pts, rec.points[0].R, read_noise_e)
        if u is None:
            cal.direction = (1.0, 0.0)
            log_message(log, "axis: no motion in the sweep frames' second moments: the motion is fitted along x", progress)
        else:
            cal.direction = u
            log_message(log, f"axis: {math.degrees(math.atan2(u[1], u[0])):.3f} +- {math.degrees(std):.3f} deg from +x (the sweep "
                             f"frames' second moments, {len(pts)} point(s); across / along {ratio:.2g})", progress)
    else:
        d = as_unit_direction({"x": (1.0, 0.0), "y": (0.0, 1.0)}[mode] if isinstance(mode, str) else mode, "fit.axis",
                              like=torch.zeros((), dtype=_F64))
        cal.direction = (float(d[0]), float(d[1]))
    return cal


class OutsidePlan(SinePlan):
    """The sine plan over a recording made elsewhere: its sweep stage reads the points of
    ``rec`` (dark subtracted, in electrons, with the saturated pixels masked) into the same
    :class:`~torchblur.identify.sweep.SineAcquisition` a rig's sweep fills; fit, assemble,
    the direct model and the result are the sine plan's."""

    def __init__(self, rec: OutsideRecording):
        self.rec = rec

    def sweep(self, run) -> None:
        rec, cal, cfg = self.rec, run.cal, run.cfg
        R = rec.points[0].R
        lay = sweep_layout(cfg, cal, rec.frame_shape)
        lay = replace(lay, fracs=[float(d * rec.points[0].freq_hz) for d in rec.points[0].duration_s[::R]], R=R)
        acq = SineAcquisition(omega_job=torch.tensor([2 * math.pi * p.freq_hz for p in rec.points], dtype=_F64), layout=lay)
        acq.fitter = ChunkFitter(int(cfg.fit.chunk_points), partial(fit_points, acq, lay, cfg, cal.read_noise_e))
        run.acquisition, acq.t_sweep = acq, time.perf_counter()
        try:
            for k, p in enumerate(rec.points):
                raw = torch.as_tensor(p.frames, dtype=_F64)  # [E*R, H, W] ADU
                acq.frames.append((subtract_dark(raw, cal.dark) * cal.gain)[None])  # [1, E*R, H, W] e-
                usable = cal.saturation.mask(raw)
                acq.n_saturated.append(int((~usable).sum()))
                acq.masks.append(usable[None])
                acq.windows.append(ExposureWindow(torch.as_tensor(p.start_s, dtype=_F64), torch.as_tensor(p.duration_s, dtype=_F64)))
                acq.amps.append(p.amplitude)
                acq.powers.append(p.power)
                acq.fitter.add(k)
            acq.t_acq_end = time.perf_counter()
            win = self.windows(acq)
            for msg in check_design(acq.omega_job, win[:, ::R] if R > 1 else win, warn=False):
                run.say(f"design: warning: {msg}")
            n_sat = sum(acq.n_saturated)
            if n_sat:
                run.say(f"saturation: {n_sat} saturated pixels masked out of the fit")
            run.say(f"recording: {len(rec.points)} point(s) of {lay.E} exposure(s) x {R} image(s), {rec.n_frames} frames, from {rec.path}")
        except BaseException:
            acq.fitter.close()
            raise

    def assemble(self, run) -> None:
        """The sine plan's assemble stage; the FRF's meta says where the frames came from."""
        super().assemble(run)
        f = run.frf
        meta = {**f.meta, "recording": "outside", "source": str(self.rec.path), "input_unit": self.rec.camera.input_unit}
        run.frf = FrequencyResponse(f.omega, f.response, cov=f.cov, input_labels=f.input_labels, output_labels=f.output_labels, meta=meta)


def identify_outside(rec: OutsideRecording, cfg: IdentifyConfig | None = None, *, progress: bool = True) -> IdentificationResult:
    """Identify the response of the outside recording ``rec`` with the identification's
    stages: :func:`outside_calibration`, then :class:`OutsidePlan`'s sweep, the fit,
    assemble, model and report (:func:`~torchblur.identify.stages.run_plan`).

    Args:
        rec: from :func:`~torchblur.hardware.outside.read_outside_recording`.
        cfg: from :func:`outside_config` (default: its defaults).
        progress: show the messages (where nothing handles the ``torchblur`` logger) and bars.
    """
    if not isinstance(rec, OutsideRecording):
        raise InputTypeError(f"rec: expected an OutsideRecording (read_outside_recording), got {type(rec).__name__}")
    cfg = outside_config(rec) if cfg is None else cfg
    if not isinstance(cfg, IdentifyConfig):
        raise InputTypeError(f"cfg: expected an IdentifyConfig (outside_config), got {type(cfg).__name__}")
    shown = progress and not logging.getLogger("torchblur").hasHandlers()
    with console_logging() if shown else contextlib.nullcontext():
        run = RunRecord(cfg=cfg, rig=None, progress=progress, t_start=time.perf_counter())
        run.cal = outside_calibration(rec, cfg, run.log, progress)
        run.plan = OutsidePlan(rec)
        return run_plan(run)
