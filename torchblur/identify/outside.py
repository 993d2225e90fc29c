"""An outside recording (:mod:`torchblur.hardware.outside`) through the identification's own
stages (:func:`~torchblur.identify.pipeline.identify` with the plan :class:`OutsidePlan`): the
folder becomes the run record's calibration (:func:`outside_calibration`: the dark level and
read noise from the dark frames, the PSF from the still frames by the same
:mod:`~torchblur.identify.calibration` code as ``identify``, the timing) and its sweep (the sine
plan whose sweep stage reads the recorded points instead of driving a rig, and with
``fit.axis=measure`` fits them on both image axes for the motion's direction). The fit,
assemble, model and report stages are the sine plan's: no fitting logic here.

:func:`identify_outside` runs it; ``torchblur fit FOLDER`` runs it for a folder with a
``frames.csv`` (docs/outside_recordings.md).
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import replace
from functools import partial

import torch

from torchblur.design.windows import check_design
from torchblur.errors import ConfigError, InputTypeError, check_type
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.outside import YAML_NAME, OutsideRecording
from torchblur.identify.calibration import Calibration, _still_psf, configured_direction, measure_gain
from torchblur.config import IdentifyConfig, load_config
from torchblur.identify.fitting import ChunkFitter
from torchblur.identify.pipeline import identify
from torchblur.identify.record import LOGGER, RunRecord
from torchblur.identify.result import IdentificationResult
from torchblur.identify.sweep import SineAcquisition, SinePlan, fit_points, sweep_layout
from torchblur.image.preprocess import dark_frame, subtract_dark
from torchblur.image.saturation import SaturationCurve
from torchblur.render.window import ExposureWindow
from torchblur.sysid.frequency_response import FrequencyResponse

__all__ = ["OutsidePlan", "check_overrides", "fitted_direction", "identify_outside", "outside_calibration", "outside_config",
           "outside_record", "recording_levels"]

_F64 = torch.float64
DARKS_PER_STILL = 4  # fewer dark frames than this many per still frame: the dark's own noise shows in the errors (logged)
ALLOWED = ("fit.", "model.", "report.")  # what a user may set for an outside recording (the rest is the recording's)


def outside_config(rec: OutsideRecording, overrides=()) -> IdentifyConfig:
    """The configuration that fits ``rec``: the defaults with the ``fit.*`` / ``model.*``
    ``overrides`` (and ``seed``), the camera's gain and timing from ``recording.yaml``, the
    sweep's frequencies and frame shape from the recording, ``rig.kind = "outside"``.

    Raises:
        ConfigError: an override outside ``fit.*``, ``model.*`` and ``seed`` (named), or a bad value.
    """
    check_overrides(overrides)
    cfg = load_config(None, list(overrides), force=True)
    c = rec.camera
    H, W = rec.frame_shape
    camera = replace(cfg.camera, gain=float(c.gain_e_per_adu), jitter_s=float(c.jitter_s), trigger_delay_s=float(c.trigger_delay_s),
                     latency_s=float(c.latency_s), height=int(H), width=int(W))
    sweep = replace(cfg.sweep, freq_hz=[p.freq_hz for p in rec.points], images_per_point=int(rec.points[0].R))
    return replace(cfg, camera=camera, sweep=sweep, rig=replace(cfg.rig, kind="outside"))


def check_overrides(overrides, what: str = "an outside recording", source: str = "camera and sweep are in recording.yaml and frames.csv"):
    """ConfigError naming an override outside fit.*, model.*, report.*, seed and camera.gain_from (the rest is ``source``)."""
    for item in overrides:
        key = str(item).partition("=")[0]
        if not (key.startswith(ALLOWED) or key in ("seed", "camera.gain_from")):
            raise ConfigError(f"{key}: {what} takes only fit.*, model.*, report.* and seed overrides, and camera.gain_from (its "
                              f"{source})")


def fitted_direction(fit):
    """The motion's image direction from a fit of the points on both image axes (batch
    ``[J]``, ``axes="xy"``): with ``c[j] = (M_x e^{i phi_x}, M_y e^{i phi_y})`` a line motion
    has ``c[j]`` real up to one phase, and ``u`` is the leading eigenvector of
    ``sum_j Re(c[j] c[j]^H)`` (the converged points), pointed toward +x (as ``fit.axis=measure``:
    the FRF's phase carries the sign).

    Returns:
        ``(u (x, y) or None, angle std rad, across / along ratio)``: the std combines each
        point's ``hypot(M_x s_y, M_y s_x) / |M|^2`` (as :func:`~torchblur.image.tracking.calibrate_axes`);
        the ratio is the eigenvalues' (0 for a straight line). ``u`` is None without a
        converged point that moved.
    """
    ok = fit.converged.reshape(-1)
    amp, ph = fit.amplitude.reshape(-1, 2)[ok], fit.phase.reshape(-1, 2)[ok]
    std = fit.amplitude_std.reshape(-1, 2)[ok]
    c = torch.polar(amp, ph)  # [J, 2] complex
    Z = (c[:, :, None] * c[:, None, :].conj()).real.sum(0)
    if not bool(ok.any()) or not bool(torch.isfinite(Z).all()):
        return None, math.nan, math.nan
    lam, vec = torch.linalg.eigh(Z)
    if float(lam[1]) <= 0:
        return None, math.nan, math.nan
    u = vec[:, 1]
    if float(u[0]) < 0 or (float(u[0]) == 0 and float(u[1]) < 0):
        u = -u
    s_j = torch.hypot(amp[:, 0] * std[:, 1], amp[:, 1] * std[:, 0]) / (amp ** 2).sum(-1).clamp_min(1e-300)
    return (float(u[0]), float(u[1])), float((1 / s_j ** 2).sum() ** -0.5), float(lam[0].clamp_min(0) / lam[1])


def recording_levels(rec, cfg: IdentifyConfig) -> tuple[dict, torch.Tensor]:
    """``(levels, still_e)`` of an outside recording ``rec`` (one-spot or DM): ``levels`` the
    :class:`~torchblur.identify.calibration.Calibration` fields it gives (the dark frame,
    ``saturation_adu`` over its level, the gain: :func:`~torchblur.identify.calibration.measure_gain`
    of the still frames against ``gain_e_per_adu``, ``camera.gain_from``; the read noise:
    ``read_noise_e``, else the dark frames'; the latency ``recording.yaml`` gives), ``still_e``
    ``[N, H, W]`` the still frames dark subtracted, in electrons."""
    c = rec.camera
    dark_raw = torch.as_tensor(rec.dark, dtype=_F64)
    dark = dark_frame(dark_raw)
    sat_adu = math.inf if c.saturation_adu is None else float(c.saturation_adu)
    nan = torch.tensor(math.nan, dtype=_F64)
    sat = SaturationCurve(slope_adu_per_s=nan, offset_adu=dark.mean.mean(), saturation_adu=torch.tensor(sat_adu, dtype=_F64),
                          linear_limit_s=torch.tensor(math.inf, dtype=_F64), residual_rms_adu=nan, saturated_in_data=False)
    ptc, gain, gain_source = measure_gain([torch.as_tensor(rec.still, dtype=_F64)], dark_raw, dark, sat_adu, float(c.gain_e_per_adu),
                                          cfg.camera.gain_from, name=f"{YAML_NAME} gain_e_per_adu")
    read_noise_e = float(c.read_noise_e) if c.read_noise_e is not None else float(dark.read_noise) * gain
    full_adu = float(sat.saturation_adu - sat.offset_adu)
    levels = dict(dark=dark, read_noise_e=read_noise_e, saturation=sat, full_adu=full_adu, gain=gain, ptc=ptc,
                  gain_source=gain_source, latency_s=float(c.latency_s), latency_std_s=float(c.latency_std_s),
                  latency_source="given")
    return levels, subtract_dark(torch.as_tensor(rec.still, dtype=_F64), dark) * gain


def outside_calibration(rec: OutsideRecording, cfg: IdentifyConfig) -> Calibration:
    """The calibration of ``rec``: the dark frame and read noise (``recording.yaml``'s
    ``read_noise_e``, else measured), the saturation level, the PSF of the still frames
    (``fit.psf``, as ``identify``), the timing, and the motion's image direction
    (``fit.axis`` given; with ``measure`` it is left None for :class:`OutsidePlan`'s sweep)."""
    c = rec.camera
    levels, still_e = recording_levels(rec, cfg)
    dark, sat, read_noise_e = levels["dark"], levels["saturation"], levels["read_noise_e"]
    LOGGER.info(f"dark: level {float(sat.offset_adu):.2f} ADU, read noise {read_noise_e:.2f} e- "
                f"({'recording.yaml' if c.read_noise_e is not None else f'from {dark.n_frames} dark frames'}), "
                f"{int(dark.hot_pixels.sum())} hot pixels")
    n_still = len(rec.still)
    if dark.n_frames < DARKS_PER_STILL * n_still:
        LOGGER.info(f"dark: warning: {dark.n_frames} dark frames for {n_still} still frames: the dark level's own noise "
                    f"({read_noise_e / math.sqrt(dark.n_frames):.2g} e- per pixel) is subtracted from the PSF and from every frame "
                    f"and is in no std, so the stds may understate the errors (docs/outside_recordings.md); take at least "
                    f"{DARKS_PER_STILL * n_still} dark frames")
    LOGGER.info(f"saturation: {rec.saturation_source}")
    clipped = int((~sat.mask(torch.as_tensor(rec.still, dtype=_F64)) & ~dark.hot_pixels).sum())
    if clipped:
        raise RecordingError(f"{rec.path}: the still frames have {clipped} saturated pixel(s) (at or within 1% below "
                             f"saturation_adu {float(sat.saturation_adu):.6g}, hot pixels aside); the PSF needs "
                             f"unsaturated still frames: take them with a shorter exposure_s or less light")
    still_psf = _still_psf(cfg, still_e, float(rec.still_exposure_s), read_noise_e)
    psf = still_psf.gaussian.psf
    cal = Calibration(psf=psf, peak_rate=float(psf.amplitude), still_psf=still_psf, **levels)
    LOGGER.info(f"timing: latency {c.latency_s * 1e6:.3f} +- {c.latency_std_s * 1e6:.3f} us, jitter {c.jitter_s * 1e6:.3f} us "
                f"(recording.yaml)")
    if cfg.fit.axis != "measure":  # else the sweep stage measures it from the recorded points (fitted_direction)
        cal.direction = configured_direction(cfg.fit.axis)
    return cal


def check_no_rig(rig, what: str = "an outside recording") -> None:
    """Refuse any ``rig``: ``what`` is fitted without one (InputTypeError naming ``rig``)."""
    if rig is not None:
        raise InputTypeError(f"rig: {what} is fitted without a rig, got {type(rig).__name__}")


@contextlib.contextmanager
def outside_record(cfg, *, progress: bool, record, executor=None, what: str = "an outside recording"):
    """The run record of an outside recording's run (either plan's ``open``): no rig, nothing
    recorded (``record`` must be None)."""
    if record is not None:
        raise InputTypeError(f"record: {what} is not recorded again, got {type(record).__name__}")
    yield RunRecord(cfg=cfg, rig=None, progress=progress, executor=executor)


class OutsidePlan(SinePlan):
    """The sine plan over a recording made elsewhere: no rig, nothing recorded, the calibration
    of :func:`outside_calibration`, and a sweep stage that reads the points of ``rec`` (dark
    subtracted, in electrons, with the saturated pixels masked) into the same
    :class:`~torchblur.identify.sweep.SineAcquisition` a rig's sweep fills; fit, assemble,
    the direct model and the result are the sine plan's."""

    def __init__(self, rec: OutsideRecording):
        self.rec = rec

    def check(self, cfg, rig) -> None:
        """Refuse any ``rig``."""
        check_no_rig(rig)

    def open(self, cfg, rig, *, progress: bool, record, base_dir: str | None = None, executor=None):
        """The run record (:func:`outside_record`)."""
        return outside_record(cfg, progress=progress, record=record, executor=executor)

    def calibrate(self, run) -> None:
        """``run.cal``: :func:`outside_calibration`."""
        run.cal = outside_calibration(self.rec, run.cfg)

    def sweep(self, run) -> None:
        """The sweep stage: every recorded point into the acquisition (and, with
        ``fit.axis=measure``, the direction measured from them: :meth:`measure_axis`)."""
        rec, cal, cfg = self.rec, run.cal, run.cfg
        R = rec.points[0].R
        measure = cal.direction is None
        if measure:
            cal.direction = (1.0, 0.0)  # for the layout until it is measured
        lay = sweep_layout(cfg, cal, rec.frame_shape)
        lay = replace(lay, fracs=[float(d * rec.points[0].freq_hz) for d in rec.points[0].duration_s[::R]], R=R)
        acq = SineAcquisition(omega_job=torch.tensor([2 * math.pi * p.freq_hz for p in rec.points], dtype=_F64), layout=lay)
        run.acquisition, acq.t_sweep = acq, time.perf_counter()
        for p in rec.points:
            raw = torch.as_tensor(p.frames, dtype=_F64)  # [E*R, H, W] ADU
            acq.frames.append((subtract_dark(raw, cal.dark) * cal.gain)[None])  # [1, E*R, H, W] e-
            usable = cal.saturation.mask(raw)
            acq.n_saturated.append(int((~usable).sum()))
            acq.masks.append(usable[None])
            acq.windows.append(ExposureWindow(torch.as_tensor(p.start_s, dtype=_F64), torch.as_tensor(p.duration_s, dtype=_F64)))
            acq.amps.append(p.amplitude)
            acq.powers.append(p.power)
        if measure:
            lay = acq.layout = self.measure_axis(run, acq, lay)
        acq.fitter = ChunkFitter(int(cfg.fit.chunk_points), partial(fit_points, acq, lay, cfg, cal.noise))
        for k in range(len(rec.points)):
            acq.fitter.add(k)
        acq.t_acq_end = time.perf_counter()
        win = self.windows(acq)
        for msg in check_design(acq.omega_job, win[:, ::R] if R > 1 else win, warn=False):
            run.say(f"design: warning: {msg}")
        n_sat = sum(acq.n_saturated)
        if n_sat:
            run.say(f"saturation: {n_sat} saturated pixels masked out of the fit")
        run.say(f"recording: {len(rec.points)} point(s) of {lay.E} exposure(s) x {R} image(s), {rec.n_frames} frames, from {rec.path}")

    @staticmethod
    def measure_axis(run, acq: SineAcquisition, lay):
        """``fit.axis=measure``: fit every point on both image axes (the sweep's own fit,
        ``axes="xy"``), take :func:`fitted_direction`, set ``run.cal.direction`` and return
        the layout that fits along it (x, logged, where no motion is seen)."""
        cal = run.cal
        both = replace(lay, axes="xy", single=False)
        fit = fit_points(acq, both, run.cfg, cal.noise, list(range(len(acq.frames))))
        u, std, ratio = fitted_direction(fit)
        if u is None:
            run.say("axis: no converged point moved in the fit on both image axes: the motion is fitted along x")
            u = (1.0, 0.0)
        else:
            run.say(f"axis: {math.degrees(math.atan2(u[1], u[0])):.3f} +- {math.degrees(std):.3f} deg from +x (fitted on both image "
                    f"axes at {int(fit.converged.sum())} point(s); across / along {ratio:.2g})")
        cal.direction = u
        return replace(lay, axes=u, moment_dirs=[torch.tensor(u, dtype=_F64)])

    def assemble(self, run) -> None:
        """The sine plan's assemble stage; the FRF's meta says where the frames came from."""
        super().assemble(run)
        f = run.frf
        meta = {**f.meta, "recording": "outside", "source": str(self.rec.path), "input_unit": self.rec.camera.input_unit}
        run.frf = FrequencyResponse(f.omega, f.response, cov=f.cov, input_labels=f.input_labels, output_labels=f.output_labels, meta=meta)


def identify_outside(rec: OutsideRecording, cfg: IdentifyConfig | None = None, *, progress: bool = True) -> IdentificationResult:
    """Identify the response of the outside recording ``rec`` with the identification's
    stages (:func:`~torchblur.identify.pipeline.identify` with :class:`OutsidePlan`).

    Args:
        rec: from :func:`~torchblur.hardware.outside.read_outside_recording`.
        cfg: from :func:`outside_config` (default: its defaults).
        progress: show the messages (where nothing handles the ``torchblur`` logger) and bars.
    """
    check_type(rec, "rec", OutsideRecording, "an OutsideRecording (read_outside_recording)")
    cfg = outside_config(rec) if cfg is None else cfg
    check_type(cfg, "cfg", IdentifyConfig, "an IdentifyConfig (outside_config)")
    return identify(cfg, progress=progress, plan=OutsidePlan(rec))
