"""The identification procedure end to end (paper section IV).

1. dark frame (mean of frames with no light);
2. PSF identification (averaged still-spot frames, 2-D Gaussian with full covariance);
3. saturation curve (peak intensity vs exposure) and a mask of unusable pixels;
4. trigger-to-exposure latency from laser pulses (measured, not assumed) and, for one axis
   and one spot, the actuator's direction in the image (``fit.axis=measure``: tracked frame
   by frame at the sweep's first frequency, :func:`torchblur.image.tracking.calibrate_axes`);
5. the sweep: for each frequency, drive ``A sin(w t)``, wait out the transients, capture
   every exposure (several images per point); the amplitude follows the response so the
   spot moves ``target_px`` (from the closed-form moments of the previous point);
6. magnitude and phase of every point with one batched fit; a FrequencyResponse with
   covariances (fit, trigger jitter and latency calibration included);
7. a transfer-function model fitted to it, weighted by the uncertainties.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from torchblur.identify.config import IdentifyConfig

__all__ = ["IdentificationResult", "Calibration", "identify", "calibrate", "fit_model", "build_simulated_rig", "build_rig", "plant_of", "calibrate_latency", "check_resume_config"]


@dataclass
class IdentificationResult:
    """What :func:`identify` measured. ``frf`` (FrequencyResponse), ``model``
    (TransferFunctionFit or None), ``direct_model`` (DirectModelFit with ``model.direct=true``,
    else None), ``psf`` (GaussianPSF per second at power 1; ``[K]`` with
    many spots), ``fit`` (SinusoidFit of all points), ``amplitude`` (input amplitude per
    point), ``latency_s`` and its std, ``saturation`` (SaturationCurve), ``images`` (dark
    subtracted, electrons), ``windows``, ``truth`` (the true response or None), ``log``
    (list of messages), ``timing`` (acquisition and fit seconds, and how much of the fit
    overlapped the acquisition), ``inputs`` (the excited inputs), ``spots`` (SpotPSFs or
    None), ``direction`` (one axis, one spot: the unit image direction (x, y) along which the
    motion was fitted; the response is the motion along it) and ``axis`` (the
    :class:`~torchblur.image.tracking.AxisCalibration` that measured it, with ``fit.axis=measure``).

    One axis, one spot (SISO): ``fit`` batch ``[F]``, ``images`` ``[F, E*R, H, W]``,
    ``windows`` ``[F, E*R]``, ``amplitude`` ``[F]``, ``truth`` complex ``[F]``.
    Otherwise (a 2x2 plant and/or K spots; P = K problems per point, or 1): ``fit`` batch
    ``[I*F, P]`` (input-major) with ``axes="xy"``, ``images`` ``[I, F, P, E*R, h, w]``
    (crops of ``h x w`` at ``spots.offset``, or the frame), ``windows`` ``[I, F, E*R]``,
    ``amplitude`` ``[I*F]``, ``truth`` complex ``[O, I, F]`` like ``frf.response``."""

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


def build_simulated_rig(cfg: IdentifyConfig):
    """The simulated rig of a config (plant, camera, timing, noise)."""
    from torchblur.render.camera import CameraModel
    from torchblur.rig.simulated import SimulatedRig

    c = cfg.camera
    camera = CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                         bit_depth=int(c.bit_depth))
    spots = cfg.spots.grid(c) if getattr(cfg, "spots", None) is not None else None
    direction = tuple(float(v) for v in cfg.plant.direction) if not cfg.plant.is_mimo else (1.0, 0.0)
    return SimulatedRig(plant=plant_of(cfg), camera=camera, frame_shape=(int(c.height), int(c.width)), psf_sigma_px=c.psf_sigma_px,
                        frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s, readout_s=c.readout_s,
                        max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s, seed=int(cfg.seed), spots=spots,
                        direction=direction)


def plant_of(cfg):
    """The plant of ``cfg.plant``: a :class:`~torchblur.systems.lti.Plant`, or a
    :class:`~torchblur.systems.mimo.PlantMatrix` for 2x2 nested ``num``/``den``."""
    from torchblur.systems.mimo import plant_from_coefficients

    return plant_from_coefficients(cfg.plant.num, cfg.plant.den, cfg.plant.delay_s)


def calibrate_latency(rig, *, dark, gain: float, exposure_s: float = 200e-6, pulse_width_s: float = 20e-6,
                      max_latency_s: float = 200e-6, step_s: float = 2e-6, repeats: int = 2, trigger_delay_s: float = 0.0,
                      power: float = 1.0):
    """Trigger-to-exposure latency from short laser pulses (mirror still).

    The laser is on only during ``[p, p + pulse_width]`` after the trigger command; the frame's
    light is the overlap of the pulse with ``[Td + latency, Td + latency + Te]``. Scanning ``p``
    gives a trapezoid; its rising edge is linear and reaches half height at
    ``p = Td + latency - pulse_width / 2``. Returns ``(latency_s, std_s)`` (std from the
    residual scatter of the edge fit).
    """
    from torchblur.image.preprocess import subtract_dark

    times = np.arange(-pulse_width_s, max_latency_s + trigger_delay_s + exposure_s / 2, step_s)
    light = []
    for p in times:
        cap = rig.pulse(exposure_s=exposure_s, trigger_offset_s=0.0, pulse_time_s=float(p), pulse_width_s=pulse_width_s, n=repeats,
                        power=power)
        light.append(float(subtract_dark(cap.frames, dark).sum((-1, -2)).mean()) * gain)
    light = np.asarray(light)
    top = np.median(np.sort(light)[-max(3, len(light) // 10):])
    # Points on the rising edge: strictly between 10% and 90% of the top.
    idx = np.nonzero((light > 0.1 * top) & (light < 0.9 * top))[0]
    first_top = np.nonzero(light >= 0.9 * top)[0]
    if first_top.size:
        idx = idx[idx < first_top[0]]
    if idx.size < 2:
        raise RuntimeError("latency calibration: the pulse scan found no rising edge; widen max_latency_s or the pulse")
    A = np.stack([times[idx], np.ones(idx.size)], 1)
    coef, res, *_ = np.linalg.lstsq(A, light[idx], rcond=None)
    slope, intercept = coef
    t_half = (0.5 * top - intercept) / slope
    latency = t_half + pulse_width_s / 2 - trigger_delay_s
    resid = light[idx] - A @ coef
    dof = max(1, idx.size - 2)
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.inv(A.T @ A)
    # std of t_half by linearisation (slope and intercept), plus the top level's scatter.
    g = np.array([-(0.5 * top - intercept) / slope**2, -1 / slope])
    std = math.sqrt(max(float(g @ cov @ g), 0.0) + (0.5 * math.sqrt(s2) / abs(slope)) ** 2 / max(1, len(light) // 10))
    return float(latency), float(std)


def build_rig(cfg: IdentifyConfig, *, log=None):
    """The rig of ``cfg.rig``: the simulated rig, or a :class:`~torchblur.hardware.SerialRig`
    on ``rig.port`` (controller) and ``rig.frames`` (camera). A camera whose frame shape
    differs from ``camera.height`` x ``camera.width`` is a :class:`ConfigError`."""
    from torchblur.errors import ConfigError

    if cfg.rig.kind == "simulated":
        return build_simulated_rig(cfg)
    from torchblur.hardware.serial_rig import SerialRig

    rig = SerialRig.open(cfg.rig.port, cfg.rig.frames, timeout_s=float(cfg.rig.timeout_s), retries=int(cfg.rig.retries), log=log)
    shape = (int(cfg.camera.height), int(cfg.camera.width))
    if tuple(rig.frame_shape) != shape:
        rig.close()
        raise ConfigError(f"camera.height: the camera on {cfg.rig.frames} delivers {rig.frame_shape[0]}x{rig.frame_shape[1]} "
                          f"frames, the config says {shape[0]}x{shape[1]} (camera.height x camera.width)")
    return rig


_RESUMABLE_SECTIONS = ("rig", "fit", "model")


def check_resume_config(recorded, cfg, *, allowed=_RESUMABLE_SECTIONS) -> None:
    """Raise :class:`~torchblur.hardware.errors.RecordingError` naming the first key where
    ``cfg`` differs from the ``recorded`` config outside the sections in ``allowed``."""
    from dataclasses import asdict

    from torchblur.hardware.errors import RecordingError

    def walk(a, b, prefix=""):
        for k in a:
            if not prefix and k in allowed:
                continue
            if isinstance(a[k], dict):
                walk(a[k], b[k], prefix + k + ".")
            elif a[k] != b[k]:
                raise RecordingError(f"{prefix}{k}: the recording was made with {a[k]!r}, got {b[k]!r}; only "
                                     f"{', '.join(s + '.*' for s in allowed)} may change")

    walk(asdict(recorded), asdict(cfg))


def _open_experiment(record, cfg, rig):
    """An :class:`~torchblur.hardware.Experiment` from ``record`` (None, a path or one)."""
    if record is None:
        return None
    from pathlib import Path

    from torchblur.identify.config import config_to_yaml, load_dataclass
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.recording import Experiment, camera_info_of

    if isinstance(record, Experiment):
        exp = record
    else:
        path = Path(record)
        if (path / "experiment.json").is_file():
            exp = Experiment.open(path)
        else:
            return Experiment.create(path, config_yaml=config_to_yaml(cfg), camera=camera_info_of(rig))
    recorded = load_dataclass(type(cfg), str(exp.path / "config.yaml"), trusted=False)
    check_resume_config(recorded, cfg)
    shape = tuple(exp.camera_info.frame_shape)
    if tuple(rig.frame_shape) != shape:
        raise RecordingError(f"{exp.path}: recorded with {shape[0]}x{shape[1]} frames, the rig delivers "
                             f"{rig.frame_shape[0]}x{rig.frame_shape[1]}")
    return exp


class _ChunkFitter:
    """Fits completed sweep points in chunks of ``chunk`` points on a background thread, so
    fitting overlaps the acquisition of the next points (``chunk`` 0: everything at the end,
    in the calling thread). Chunk boundaries depend only on the point index, so the result
    does not depend on timing."""

    def __init__(self, chunk: int, fit_fn):
        import threading
        import time

        self.chunk, self.fit_fn = int(chunk), fit_fn
        self.pending: list[int] = []
        self.jobs: list = []
        self.busy_s = 0.0
        self.spans: list[tuple[float, float]] = []  # (start, end) of each chunk's fit, perf_counter seconds
        self._lock = threading.Lock()
        self._time = time.perf_counter
        self._exec = None
        if self.chunk > 0:
            from concurrent.futures import ThreadPoolExecutor

            self._exec = ThreadPoolExecutor(max_workers=1, thread_name_prefix="torchblur-fit")

    def _timed(self, idx):
        t0 = self._time()
        try:
            return self.fit_fn(idx)
        finally:
            with self._lock:
                self.busy_s += self._time() - t0
                self.spans.append((t0, self._time()))

    def add(self, k: int) -> None:
        self.pending.append(k)
        if self.chunk > 0 and len(self.pending) >= self.chunk:
            idx, self.pending = self.pending, []
            self.jobs.append((idx, self._exec.submit(self._timed, idx)))

    def finish(self):
        """Fit what is left and return ``[(point indices, SinusoidFit), ...]`` in order."""
        if self.pending:
            idx, self.pending = self.pending, []
            self.jobs.append((idx, _Done(self._timed(idx))))
        out = [(idx, job.result()) for idx, job in self.jobs]
        self.close()
        return out

    def close(self):
        if self._exec is not None:
            self._exec.shutdown(wait=False, cancel_futures=True)
            self._exec = None


class _Done:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


def _concat_fits(parts):
    """One SinusoidFit from per-chunk fits (batch dims first), in point order."""
    from dataclasses import fields as dc_fields

    from torchblur.fit.sinusoid import SinusoidFit

    if len(parts) == 1:
        return parts[0]
    kw = {}
    for f in dc_fields(SinusoidFit):
        vals = [getattr(p, f.name) for p in parts]
        if isinstance(vals[0], torch.Tensor):
            kw[f.name] = torch.cat(vals, 0)
        elif f.name == "extras":
            kw[f.name] = {"chunks": [dict(v) for v in vals]}
        else:
            kw[f.name] = vals[0]
    return SinusoidFit(**kw)


def _log(res_log, msg, progress):
    res_log.append(msg)
    if progress:
        from tqdm.auto import tqdm

        tqdm.write(msg)


def identify(cfg: IdentifyConfig, rig=None, *, progress: bool = True, record=None) -> IdentificationResult:
    """Run the identification on ``rig`` (default: the rig of ``cfg.rig``: the simulated rig,
    or a :class:`~torchblur.hardware.SerialRig` on ``rig.port`` / ``rig.frames``).

    Args:
        cfg: the configuration.
        rig: a :class:`~torchblur.rig.base.Rig`, or None.
        progress: show a progress bar and log lines.
        record: None, a directory, or a :class:`~torchblur.hardware.Experiment`: the run is
            recorded there as it goes (TIFF frames, ``manifest.jsonl``). Groups already
            recorded (a resumed run) are taken from the recording instead of the rig; a
            read-only experiment with :class:`~torchblur.hardware.recording.ReplayRig`
            re-fits a recording offline.

    Raises:
        HardwareError: the rig failed (the recording so far is kept; resume it);
        KeyboardInterrupt: likewise.
    """
    from torchblur.errors import InputTypeError

    if not isinstance(cfg, IdentifyConfig):
        raise InputTypeError(f"cfg: expected an IdentifyConfig (see torchblur.identify.config.load_config), got {type(cfg).__name__}")
    if rig is not None and not all(hasattr(rig, a) for a in ("frame_shape", "dark", "still", "sine")):
        raise InputTypeError(f"rig: expected a torchblur Rig (frame_shape, dark, still, sine, ...) or None, got {type(rig).__name__}")
    log: list[str] = []
    own_rig = rig is None
    if own_rig:
        rig = build_rig(cfg, log=lambda m: _log(log, m, progress))
    elif hasattr(rig, "set_logger"):
        rig.set_logger(lambda m: _log(log, m, progress))
    exp = None
    try:
        exp = _open_experiment(record, cfg, rig)
        if exp is not None and exp.writable:
            exp.start_session({"kind": cfg.rig.kind, "port": cfg.rig.port, "frames": cfg.rig.frames, "rig": repr(rig)})
            if exp.meta["sessions"] and len(exp.groups):
                _log(log, f"resume: {len(exp.groups)} recorded group(s) in {exp.path} are reused", progress)
        result = _identify(cfg, rig, exp, log, progress)
    except KeyboardInterrupt:
        if exp is not None:
            exp.end_session("interrupted", "KeyboardInterrupt")
        raise
    except BaseException as exc:
        if exp is not None:
            from torchblur.hardware.errors import HardwareError

            exp.end_session("stopped" if isinstance(exc, HardwareError) else "failed", f"{type(exc).__name__}: {exc}")
        raise
    finally:
        if own_rig and hasattr(rig, "close"):
            rig.close()
    if exp is not None:
        exp.end_session("complete")
    return result


def _stage(exp, key, kind, rig, fn):
    if exp is None:
        return fn(rig)
    return exp.stage(key, kind, rig, fn)[0]


@dataclass
class Calibration:
    """What the calibration stages (1-4 of :func:`identify`) measured: ``dark``
    (:class:`~torchblur.image.preprocess.DarkFrame`), ``read_noise_e``, ``saturation``
    (SaturationCurve), ``full_adu`` (usable range above the dark level, ADU), ``psf``
    (GaussianPSF in electrons per second at power 1), ``peak_rate`` (its peak, e-/s),
    ``latency_s`` and ``latency_std_s``, ``gain`` (e-/ADU), and for one-axis runs the
    actuator's image ``direction``."""

    dark: object
    read_noise_e: float
    saturation: object
    full_adu: float
    psf: object
    peak_rate: float
    latency_s: float
    latency_std_s: float
    gain: float
    spots: object = None  # many spots: SpotPSFs (psf [K] per spot, crop offsets), else None
    # One-axis, one-spot runs: the unit image direction (x, y) of the motion that is fitted, the
    # AxisCalibration it was measured by (fit.axis=measure), and |H| (px per input unit) at the
    # calibration frequency (seeds the sweep's first amplitude); else None.
    direction: tuple | None = None
    axis: object = None
    axis_gain: float | None = None


def calibrate(cfg, rig, exp=None, log=None, progress: bool = False) -> Calibration:
    """Stages 1-4 of :func:`identify`: dark frame, saturation curve, PSF, latency and, for a
    one-axis, one-spot run, the actuator's direction in the image (each taken from the
    recording ``exp`` when it holds it)."""
    from torchblur.image.preprocess import dark_frame, fit_gaussian_psf, saturation_curve, subtract_dark

    log = [] if log is None else log
    c = cfg.camera
    gain = float(c.gain)
    dtype = torch.float64

    # 1. Dark frame.
    dark = dark_frame(_stage(exp, "dark", "dark", rig, lambda r: r.dark(n=16, exposure_s=min(0.01, c.max_exposure_s))).frames.to(dtype))
    read_noise_e = float(dark.read_noise) * gain
    _log(log, f"dark: level {float(dark.mean.mean()):.2f} ADU, read noise {read_noise_e:.2f} e-, "
              f"{int(dark.hot_pixels.sum())} hot pixels", progress)

    # 3 (before 2, to choose the PSF exposure). Saturation curve of the still spot.
    ladder = np.geomspace(1e-4, c.max_exposure_s, 9)
    peaks = _stage(exp, "saturation", "saturation", rig,
                   lambda r: [float(r.still(n=1, exposure_s=float(te)).frames.to(dtype).amax()) for te in ladder])
    sat = saturation_curve(torch.tensor(peaks, dtype=dtype), torch.tensor(ladder, dtype=dtype))
    full_adu = float(sat.saturation_adu) - float(dark.mean.mean())
    _log(log, f"saturation: {float(sat.saturation_adu):.0f} ADU plateau, linear up to {float(sat.linear_limit_s) * 1e3:.3g} ms of still exposure", progress)

    # 2. PSF: still frames at an exposure that fills peak_fraction of the range.
    te_psf = float(min(c.max_exposure_s, c.peak_fraction * float(sat.linear_limit_s)))
    still = subtract_dark(_stage(exp, "psf", "psf", rig, lambda r: r.still(n=16, exposure_s=te_psf)).frames.to(dtype), dark).mean(0) * gain
    spots = None
    if getattr(cfg, "spots", None) is not None and cfg.spots.enabled:
        spots = _locate_spots(cfg, still, te_psf, read_noise_e, log, progress)
        psf = spots.psf  # [K], full-frame coordinates
        whole = spots.inside_fraction >= _MIN_INSIDE  # an edge spot's peak is an extrapolation: not trusted here
        peak_rate = float(psf.amplitude[whole].max() if bool(whole.any()) else psf.amplitude.max())  # e-/s at power 1
    else:
        psf_fit = fit_gaussian_psf(still, exposure_s=te_psf, noise_std=math.sqrt(read_noise_e**2 + float(still.max())) / 4)
        psf = psf_fit.psf
        _log(log, f"psf: centre ({float(psf.center[0]):.2f}, {float(psf.center[1]):.2f}) px, cov "
                  f"[[{float(psf.cov[0, 0]):.3f}, {float(psf.cov[0, 1]):.3f}], [., {float(psf.cov[1, 1]):.3f}]] px^2, "
                  f"relative residual {float(psf_fit.relative_residual):.2e}", progress)
        peak_rate = float(psf.amplitude)  # electrons per second at power 1

    # 4. Latency.
    pulse_w = 20e-6
    latency, latency_std = _stage(exp, "latency", "latency", rig, lambda r: calibrate_latency(
        r, dark=dark, gain=gain, trigger_delay_s=c.trigger_delay_s, pulse_width_s=pulse_w,
        power=c.peak_fraction * full_adu * gain / (peak_rate * pulse_w)))
    _log(log, f"latency: {latency * 1e6:.3f} +- {latency_std * 1e6:.3f} us", progress)
    cal = Calibration(dark=dark, read_noise_e=read_noise_e, saturation=sat, full_adu=full_adu, psf=psf, peak_rate=peak_rate,
                      latency_s=latency, latency_std_s=latency_std, gain=gain, spots=spots)

    # 4b. The actuator's direction in the image (one axis, one spot; a 2x2 plant or many spots
    # fit both image axes).
    if not cfg.plant.is_mimo and spots is None:
        mode = cfg.fit.axis
        if mode == "measure" and exp is not None and not exp.writable and "axis" not in exp.groups:
            cal.direction = (1.0, 0.0)
            _log(log, "axis: not in the recording (made before the axis calibration): the motion is fitted along x", progress)
        elif mode == "measure":
            axis, axis_gain = _stage(exp, "axis", "axis", rig, lambda r: _measure_axis(cfg, r, cal))
            u = np.asarray(axis.direction, dtype=float)
            if u[0] < 0 or (u[0] == 0 and u[1] < 0):  # the sign that points toward +x: the FRF keeps the x convention
                u = -u
            if not (np.isfinite(u).all() and axis.px_per_unit > 5 * axis.px_per_unit_std):
                cal.direction = (1.0, 0.0)  # no clear motion to take a direction from
                _log(log, f"axis: no clear motion in the tracking ({axis.px_per_unit:.3g} +- {axis.px_per_unit_std:.2g} px per "
                          f"input unit at {cfg.frequencies_hz()[0]:.4g} Hz): the motion is fitted along x", progress)
            else:
                cal.direction, cal.axis, cal.axis_gain = (float(u[0]), float(u[1])), axis, axis_gain
                _log(log, f"axis: {math.degrees(math.atan2(u[1], u[0])):.3f} +- {math.degrees(axis.angle_std_rad):.3f} deg from "
                          f"+x (tracked at {cfg.frequencies_hz()[0]:.4g} Hz, {axis.px_per_unit:.4g} px per input unit)", progress)
        else:
            from torchblur.errors import as_unit_direction

            u = as_unit_direction({"x": (1.0, 0.0), "y": (0.0, 1.0)}[mode] if isinstance(mode, str) else mode, "fit.axis",
                                  like=torch.zeros((), dtype=torch.float64))
            cal.direction = (float(u[0]), float(u[1]))
    return cal


_AXIS_FRAMES = 24  # short exposures of the axis calibration, at phases spread over a period


def _measure_axis(cfg, rig, cal: Calibration):
    """Stage 4b: track the spot frame by frame (:func:`torchblur.image.tracking.calibrate_axes`) at the
    sweep's first frequency, the amplitude adapted (up to three tries, as the sweep does) so
    the spot moves about ``excitation.target_px``. Returns ``(AxisCalibration, px per input
    unit)``."""
    from torchblur.image.tracking import calibrate_axes

    c, x = cfg.camera, cfg.excitation
    f = cfg.frequencies_hz()[0]
    target = float(x.target_px)
    # Tracking exposures: 5 % of the period (shorter when the camera's longest exposure is).
    frac = min(0.05, 0.9 * min(float(c.max_exposure_s), float(getattr(rig, "max_exposure_s", c.max_exposure_s))) * f)
    te = frac / f
    power = c.peak_fraction * cal.full_adu * cal.gain / (cal.peak_rate * te)
    A = target / 10.0
    for attempt in range(3):
        if x.max_amplitude is not None:
            A = min(A, float(x.max_amplitude))
        axis = calibrate_axes(rig, freq_hz=f, amplitude=A, rest_px=cal.psf.center, dark=cal.dark, gain=cal.gain, n_frames=_AXIS_FRAMES,
                              latency_s=cal.latency_s, trigger_delay_s=c.trigger_delay_s, power=power, noise_e=cal.read_noise_e,
                              exposure_fraction=frac)
        moved = axis.px_per_unit * A
        if 0.5 * target <= moved <= 2 * target or (x.max_amplitude is not None and A >= x.max_amplitude and moved < 2 * target):
            break
        A = target / max(axis.px_per_unit, 1e-12)
    return axis, axis.px_per_unit


def _locate_spots(cfg, still, exposure_s, read_noise_e, log, progress):
    """Stage 2 with many spots: find them in the still image and fit a PSF per spot (one
    batch, on crops); log how many of the expected grid were found."""
    from torchblur.image.spots import locate_spots

    sp = cfg.spots
    spots = locate_spots(still, exposure_s=exposure_s, noise_std=math.sqrt(read_noise_e**2 + float(still.max())) / 4,
                         pitch_px=float(sp.pitch_px), crop_px=None if sp.crop_px is None else int(sp.crop_px))
    K, expected = len(spots), int(sp.rows) * int(sp.cols)
    sd = torch.linalg.eigvalsh(spots.psf.cov).clamp_min(0).sqrt()
    _log(log, f"spots: {K} found (grid {sp.rows}x{sp.cols} = {expected}), crops {spots.size[0]}x{spots.size[1]} px, PSF sigma "
              f"{float(sd.min()):.2f}..{float(sd.max()):.2f} px, worst relative residual "
              f"{float(spots.fit.relative_residual.max()):.2e}", progress)
    if K < expected:
        _log(log, f"spots: {expected - K} of the {expected} expected spot(s) not found (missing or too dim); the others are fitted",
             progress)
    for k in torch.nonzero(spots.clipped).reshape(-1).tolist():
        c = spots.psf.center[k]
        frac = float(spots.inside_fraction[k])
        what = "flagged: not fitted" if frac < _MIN_INSIDE else "fitted on the pixels in the frame"
        _log(log, f"spots: s{k} at ({float(c[0]):.1f}, {float(c[1]):.1f}) px is at the frame edge, {frac * 100:.0f}% of its light "
                  f"in the frame ({what})", progress)
    return spots


_MIN_INSIDE = 0.5  # a spot with less of its still light in the frame is flagged, not fitted


def fit_model(cfg, frf, log=None, progress: bool = False):
    """Stage 7 of :func:`identify`: the transfer-function model of ``frf`` under
    ``cfg.model`` (None, with the reason logged, when the fit fails)."""
    from torchblur.sysid.tf_fit import fit_transfer_function

    log = [] if log is None else log
    # Outputs with a channel that has no valid point at all (a spot flagged at every
    # frequency) are left out, so they do not take the other outputs' models with them.
    keep = frf.valid.any(-1).all(-1)  # [O]
    if not keep.any():
        _log(log, "model: fit failed: no output has a valid point in every channel", progress)
        return None
    if not keep.all():
        from torchblur.sysid.frequency_response import FrequencyResponse

        dropped = [lab for lab, k in zip(frf.output_labels, keep) if not k]
        _log(log, f"model: output(s) {', '.join(dropped)} have a channel with no valid point and are left out of the model", progress)
        frf = FrequencyResponse(frf.omega, frf.response[keep], cov=frf.cov[keep], input_labels=frf.input_labels,
                                output_labels=[lab for lab, k in zip(frf.output_labels, keep) if k], meta=frf.meta)
    try:
        model = fit_transfer_function(frf, n_poles=cfg.model.n_poles, n_zeros=cfg.model.n_zeros,
                                      delay_s=None if cfg.model.fit_delay else 0.0, max_order=int(cfg.model.max_order))
    except Exception as exc:  # the FRF is still a result; say why the model failed
        _log(log, f"model: fit failed: {exc}", progress)
        return None
    if model.is_siso:
        _log(log, f"model: {model.n_poles} poles, {model.n_zeros} zeros, delay {model.delay_s * 1e6:.2f} us, "
                  f"reduced chi2 {model.reduced_chi2:.3f}", progress)
    else:  # one model per channel (output o from input i)
        for o, out in enumerate(model.output_labels):
            for i, inp in enumerate(model.input_labels):
                _log(log, f"model {out} from {inp}: {model.n_poles[o][i]} poles, {model.n_zeros[o][i]} zeros, delay "
                          f"{model.delay_s[o][i] * 1e6:.2f} us, reduced chi2 {model.reduced_chi2[o][i]:.3f}", progress)
    return model


def _identify(cfg, rig, exp, log, progress) -> IdentificationResult:
    import time

    from tqdm.auto import tqdm

    from torchblur.design.windows import check_design
    from torchblur.fit.sinusoid import fit_sinusoid
    from torchblur.sysid.frequency_response import FrequencyResponse
    from torchblur.image.moments import image_moments, moments_along, sinusoid_from_moments
    from torchblur.image.preprocess import subtract_dark
    from torchblur.render.psf import GaussianPSF
    from torchblur.render.window import ExposureWindow

    c = cfg.camera
    dtype = torch.float64
    H, W = rig.frame_shape
    freqs = np.asarray(cfg.frequencies_hz())
    F = len(freqs)
    fracs = [float(e) for e in cfg.sweep.exposures]
    E, R = len(fracs), int(cfg.sweep.images_per_point)
    b = float(cfg.sweep.trigger_phase_rad)
    mimo = bool(cfg.plant.is_mimo)
    inputs = ["x", "y"] if mimo else ["x"]
    I = len(inputs)

    t_start = time.perf_counter()
    cal = calibrate(cfg, rig, exp, log, progress)
    dark, read_noise_e, sat, full_adu = cal.dark, cal.read_noise_e, cal.saturation, cal.full_adu
    psf, peak_rate, latency, latency_std, gain = cal.psf, cal.peak_rate, cal.latency_s, cal.latency_std_s, cal.gain
    if cfg.excitation.kind == "multisine":
        from torchblur.identify.multisine import identify_multisine

        return identify_multisine(cfg, rig, exp, log, progress, cal, t_start)

    # Problems per sweep point: one (the spot, full frame) or K (one crop per spot).
    spots = cal.spots
    single = not mimo and spots is None  # the one-axis, one-spot identification: along cal.direction, shapes [F]
    axes = cal.direction if single else "xy"
    if spots is not None:
        P, (h, w) = len(spots), spots.size
        psf_p = spots.psf_in_crops()  # [K] in crop coordinates
        # the dominant motion is measured on spots whose crop is whole (an edge spot's moments are biased)
        use_p = ~spots.clipped if bool((~spots.clipped).any()) else torch.ones(P, dtype=torch.bool)
    else:
        P, (h, w) = 1, (H, W)
        psf_p = GaussianPSF(psf.center[None], psf.cov[None], psf.amplitude[None])
        use_p = torch.ones(1, dtype=torch.bool)
    # Directions along which the sweep's amplitude adaptation measures the motion.
    moment_dirs = [torch.tensor(cal.direction, dtype=dtype)] if single else [torch.tensor([1.0, 0.0], dtype=dtype),
                                                                             torch.tensor([0.0, 1.0], dtype=dtype)]

    def pieces_of(frames):
        """``[E, R, H, W]`` -> ``[E, R, P, h, w]`` (the spots' crops, or the frame)."""
        if spots is None:
            return frames[:, :, None]
        from torchblur.image.spots import crop_spots

        return crop_spots(frames, spots.offset, spots.size)

    if spots is not None:
        from torchblur.image.spots import crop_valid

        in_frame = crop_valid((H, W), spots.offset, spots.size)  # [P, h, w] pixels of each crop in the frame
        flagged = spots.inside_fraction < _MIN_INSIDE  # [P] spots mostly outside the frame: not fitted
        use_p = use_p & ~flagged if bool((use_p & ~flagged).any()) else use_p

    # 5. Sweep: each input in turn, every frequency. Every completed point goes to the chunked
    # background fit (6.) at once; job j = input index * F + point index.
    target = float(cfg.excitation.target_px)
    amax = cfg.excitation.max_amplitude
    frames_all, masks_all, windows_start, windows_dur, amps, powers, n_saturated = [], [], [], [], [], [], []
    omega_job = torch.tensor(np.tile(2 * math.pi * freqs, I), dtype=dtype)

    def fit_points(idx):
        imgs = torch.stack([frames_all[j] for j in idx])  # [n, P, E*R, h, w]
        pw = torch.tensor([powers[j] for j in idx], dtype=dtype)
        n = len(idx)
        psf_b = GaussianPSF(psf_p.center.expand(n, P, 2), psf_p.cov.expand(n, P, 2, 2), psf_p.amplitude[None, :] * pw[:, None])
        win = ExposureWindow(torch.stack([windows_start[j] for j in idx])[:, None], torch.stack([windows_dur[j] for j in idx])[:, None])
        noise = torch.sqrt(read_noise_e**2 + imgs.clamp_min(0))  # shot + read noise (e-), per pixel
        fit = fit_sinusoid(imgs, psf_b, win, omega_job[list(idx)][:, None], axes=axes, optimizer=cfg.fit.optimizer,
                           loss=cfg.fit.loss, noise_std=noise, mask=torch.stack([masks_all[j] for j in idx]),
                           fit_scale=cfg.fit.fit_scale, fit_background=cfg.fit.fit_background, fit_gradient=cfg.fit.fit_gradient,
                           outliers=cfg.fit.outliers, outlier_sigma=float(cfg.fit.outlier_sigma))
        return _squeeze_problems(fit) if single else fit

    fitter = _ChunkFitter(int(cfg.fit.chunk_points), fit_points)
    t_sweep = time.perf_counter()
    bar = tqdm(total=I * F, desc="sweep", unit="pt", disable=not progress)
    try:
        for ii, inp in enumerate(inputs):
            gain_est = cal.axis_gain  # |H| estimate of the dominant motion (px per input unit) from the previous point
            for k, f in enumerate(freqs):
                om = 2 * math.pi * f
                period = 1 / f
                te = [fr * period for fr in fracs]
                A = target / gain_est if gain_est else target / 10.0
                if amax is not None:
                    A = min(A, float(amax))
                # Laser power: a still spot over the longest exposure would reach peak_fraction of the range.
                power = c.peak_fraction * full_adu * gain / (peak_rate * max(te))
                offset = (b / om - c.trigger_delay_s - latency) % period
                start0 = torch.tensor(offset + c.trigger_delay_s + latency, dtype=dtype)

                def moved_px(cap_frames):
                    """Dark-subtracted electrons ``[E, R, P, h, w]`` and the closed-form amplitude
                    (px) of the first exposure: how far did the spot (the farthest spot, on the
                    axis that moves most) move?"""
                    img_ = pieces_of(subtract_dark(cap_frames.to(dtype), dark) * gain)
                    _, cen, cov_ = image_moments(img_[0].mean(0), threshold=3 * read_noise_e)  # [P, 2], [P, 2, 2]
                    Ms = []
                    for u in moment_dirs:
                        mu1, vex = moments_along(cen - psf_p.center, cov_ - psf_p.cov, u)
                        M, _ = sinusoid_from_moments(mu1, vex, torch.tensor(om, dtype=dtype), start0, torch.tensor(te[0], dtype=dtype))
                        Ms.append(M)
                    M = torch.stack(Ms, -1)[use_p]
                    M = M[torch.isfinite(M)]
                    return img_, float(M.max()) if M.numel() else 0.0

                key = f"sweep/{inp}/{k:03d}"
                if exp is not None and exp.has(key):
                    rec = exp.groups[key][0]
                    if not (math.isclose(rec["freq_hz"], f, rel_tol=1e-12) and math.isclose(rec["power"], power, rel_tol=1e-9)):
                        from torchblur.hardware.errors import RecordingError

                        raise RecordingError(f"{key}: recorded at {rec['freq_hz']} Hz, power {rec['power']}; this run asks "
                                             f"{f} Hz, power {power}")
                    (_, _, cap), = exp.load_calls(key)
                    A = float(rec["amplitude"])
                    img, M_est = moved_px(cap.frames)
                    gain_new = max(M_est, 1e-3) / A
                else:
                    for attempt in range(3):
                        kw = dict(freq_hz=float(f), amplitude=float(A), exposures_s=te, trigger_offset_s=float(offset), n_repeats=R,
                                  settle_s=cfg.sweep.settle_s, power=float(power))
                        if mimo:
                            kw["input"] = inp
                        cap = rig.sine(**kw)
                        img, M_est = moved_px(cap.frames)  # [E, R, P, h, w] electrons
                        ok = 0.75 * target <= M_est <= 1.33 * target or (amax is not None and A >= amax and M_est < 1.33 * target)
                        gain_new = max(M_est, 1e-3) / A
                        if ok or attempt == 2:
                            break
                        A = target / gain_new
                        if amax is not None:
                            A = min(A, float(amax))
                    if exp is not None and exp.writable:
                        from torchblur.hardware.recording import _bind

                        exp.record(key, "sweep", [("sine", _bind("sine", (), kw), cap)],
                                   labels={"input": inp, "freq_hz": float(f), "amplitude": float(A), "power": float(power),
                                           "point": k, "attempts": attempt + 1})
                gain_est = gain_new
                if spots is not None and bool(flagged.any()):
                    img = img * ~flagged[:, None, None]  # a flagged spot is left dark: the fit marks it "no signal"
                frames_all.append(img.permute(2, 0, 1, 3, 4).reshape(P, E * R, h, w))
                usable = pieces_of(sat.mask(cap.frames.to(dtype)))  # [E, R, P, h, w]
                if spots is not None:
                    n_saturated.append(int((~usable & in_frame).sum()))
                    usable = usable & in_frame & ~flagged[:, None, None]
                else:
                    n_saturated.append(int((~usable).sum()))
                masks_all.append(usable.permute(2, 0, 1, 3, 4).reshape(P, E * R, h, w))
                windows_start.append(torch.tensor([offset + c.trigger_delay_s + latency] * (E * R), dtype=dtype))
                windows_dur.append(torch.tensor([t for t in te for _ in range(R)], dtype=dtype))
                amps.append(A)
                powers.append(power)
                fitter.add(ii * F + k)
                bar.update(1)
                bar.set_postfix(input=inp, f_hz=f"{f:.4g}", amplitude=f"{A:.3g}")
        bar.close()
        t_acq_end = time.perf_counter()

        images = torch.stack(frames_all)  # [J, P, E*R, h, w]
        windows = ExposureWindow(torch.stack(windows_start), torch.stack(windows_dur))  # [J, E*R]
        power_t = torch.tensor(powers, dtype=dtype)
        check_design(omega_job, windows[:, ::R] if R > 1 else windows, warn=progress)
        n_sat = sum(n_saturated)
        if n_sat:
            _log(log, f"saturation: {n_sat} saturated pixels masked out of the fit", progress)

        # 6. The batched fit of every point (chunks fitted while the sweep went on, the rest now).
        parts = fitter.finish()
    finally:
        fitter.close()
    t_fit_end = time.perf_counter()
    fit = _concat_fits([p for _, p in parts])
    spans = fitter.spans
    overlapped = sum(max(0.0, min(e, t_acq_end) - s0) for s0, e in spans)
    timing = {"calibration_s": t_sweep - t_start, "sweep_s": t_acq_end - t_sweep, "fit_s": fitter.busy_s,
              "fit_overlapped_s": overlapped, "after_sweep_s": t_fit_end - t_acq_end, "fit_chunks": len(parts),
              "total_s": t_fit_end - t_start}
    if exp is not None:
        timing["recording_write_s"] = exp.stats["write_s"]
        _log(log, f"recording: {exp.stats['groups_written']} group(s) written ({exp.stats['write_s']:.2f} s), "
                  f"{exp.stats['groups_reused']} reused, in {exp.path}", progress)
    _log(log, f"fit: {len(parts)} chunk(s), {fitter.busy_s:.2f} s of fitting, {overlapped:.2f} s of it during the sweep; "
              f"{t_fit_end - t_acq_end:.2f} s from the last frame to the last fit", progress)
    meta = {"seed": int(cfg.seed)}
    if single:
        meta["direction"] = list(cal.direction)  # the image direction of the fitted motion (x, y)
        images = images[:, 0]  # [F, E*R, H, W]
        frf = _assemble_siso(fit, amps, omega_job, c, latency_std, E * R, meta)
    else:
        images = images.reshape((I, F) + tuple(images.shape[1:]))  # [I, F, P, E*R, h, w]
        windows = ExposureWindow(windows.start.reshape(I, F, E * R), windows.duration.reshape(I, F, E * R))
        if spots is not None:
            meta["spot_centers_px"] = spots.psf.center.tolist()
        frf = _assemble_mimo(fit, amps, omega_job, c, latency_std, E * R, inputs, P, spots is not None, meta)
    n_bad = int((~np.isfinite(frf.response)).sum())
    n_all = frf.response.size
    _log(log, f"fit: {n_all - n_bad} of {n_all} {'points' if single else 'channel points'} converged", progress)
    if spots is not None:
        bad_spots = [k for k in range(P) if not np.isfinite(frf.response[2 * k:2 * k + 2]).any()]
        for k in bad_spots:
            st = fit.status.reshape(I * F, P)[:, k]
            from torchblur.fit.sinusoid import STATUS

            why = "mostly outside the frame" if bool(flagged[k]) else STATUS.get(int(st.mode().values), "?")
            _log(log, f"spots: s{k} flagged at every point ({why}); its channels are NaN, the other spots are fitted", progress)

    # 7. Parametric model; with model.direct, the model fitted to every image at once from it.
    model = fit_model(cfg, frf, log, progress)
    direct_model = None
    if cfg.model.direct and model is None:
        _log(log, "direct: skipped (no two-step model to start from)", progress)
    elif cfg.model.direct:
        direct_model = _fit_direct_model(cfg, model, images, windows, omega_job, amps, psf, power_t, read_noise_e,
                                         torch.stack(masks_all)[:, 0], fit, log, progress, cal.direction)
    truth = _truth_of(rig, freqs, frf, spots, single)
    return IdentificationResult(frf=frf, model=model, psf=psf, fit=fit, amplitude=np.asarray(amps), latency_s=latency,
                                latency_std_s=latency_std, saturation=sat, images=images, windows=windows, power=power_t,
                                truth=truth, log=log, timing=timing, inputs=tuple(inputs), spots=spots, direct_model=direct_model,
                                direction=cal.direction, axis=cal.axis)


def modes_outside_band(modes, f_lo_hz: float, f_hi_hz: float, factor: float = 3.0) -> list:
    """The modes (dicts with ``freq_hz``, as ``modal_parameters()`` gives) more than ``factor``
    beyond the swept band ``[f_lo_hz, f_hi_hz]``: the images cannot constrain them (a fitted
    mode there may run away while the fit reports convergence)."""
    return [m for m in modes if not (f_lo_hz / factor <= m["freq_hz"] <= factor * f_hi_hz)]


def _fit_direct_model(cfg, model, images, windows, omega, amps, psf, power_t, read_noise_e, mask, fit, log, progress, direction):
    """The direct model (one axis, one spot): every image at once, with the sweep's noise
    model and mask; dark or out-of-frame points are left out. None, logged, if it fails."""
    import time

    from torchblur.sysid.direct import fit_direct
    from torchblur.render.psf import GaussianPSF

    F = images.shape[0]
    t_direct = time.perf_counter()
    psf_pts = GaussianPSF(psf.center.expand(F, 2), psf.cov.expand(F, 2, 2), psf.amplitude * power_t)
    A_t = torch.tensor(amps, dtype=torch.float64)
    try:
        d = fit_direct(images, psf_pts, windows, omega, A_t, model, form=cfg.model.direct_form, fit_delay=bool(cfg.model.fit_delay),
                       axis=direction,
                       noise_std=torch.sqrt(read_noise_e**2 + images.clamp_min(0)), mask=mask,
                       valid=(fit.status != 1) & (fit.status != 3), fit_scale=cfg.fit.fit_scale,
                       fit_background=cfg.fit.fit_background, max_iter=int(cfg.model.direct_max_iter))
    except Exception as exc:  # the two-step model is still a result; say why the direct fit failed
        _log(log, f"direct: fit failed: {exc}", progress)
        return None
    modal = d.modal_parameters()
    modes = ", ".join(f"{m['freq_hz']:.3f} +- {m['freq_hz_std']:.3f} Hz (zeta {m['zeta']:.4f} +- {m['zeta_std']:.4f})"
                      for m in modal)
    f_lo, f_hi = float(omega.min()) / (2 * math.pi), float(omega.max()) / (2 * math.pi)
    for m in modes_outside_band(modal, f_lo, f_hi):
        _log(log, f"direct: warning: a mode at {m['freq_hz']:.4g} Hz lies far outside the swept band "
                  f"({f_lo:.4g}-{f_hi:.4g} Hz); the images do not constrain it (std {m['freq_hz_std']:.3g} Hz)", progress)
    _log(log, f"direct: {d.form} model from {int(d.used.sum())} points ({d.n_excluded} excluded), {d.n_iter} iterations, "
              f"converged {d.converged}, reduced chi2 {d.reduced_chi2:.3f}, {time.perf_counter() - t_direct:.2f} s; "
              f"modes: {modes or 'none'}", progress)
    return d


def _squeeze_problems(fit):
    """A SinusoidFit of batch ``[n, 1]`` as batch ``[n]`` (one problem per point)."""
    from dataclasses import fields as dc_fields

    from torchblur.fit.sinusoid import SinusoidFit

    kw = {}
    for f in dc_fields(SinusoidFit):
        v = getattr(fit, f.name)
        kw[f.name] = v.squeeze(1) if isinstance(v, torch.Tensor) and v.dim() >= 2 and v.shape[1] == 1 else v
    return SinusoidFit(**kw)


def _phase_std(fit_phase_std, omega, camera, latency_std, n_frames):
    """Phase std (rad): the fit, the trigger jitter (per frame, averaged) and the latency calibration."""
    return np.sqrt(fit_phase_std ** 2 + (omega * camera.jitter_s) ** 2 / n_frames + (omega * latency_std) ** 2)


def _assemble_siso(fit, amps, omega, camera, latency_std, n_frames, meta):
    """The 1x1 FrequencyResponse of a one-axis, one-spot sweep (fit batch ``[F]``)."""
    from torchblur.sysid.frequency_response import FrequencyResponse

    A_t = torch.tensor(amps, dtype=torch.float64)
    mag = (fit.amplitude / A_t).numpy()
    phase = fit.phase.numpy()
    mag_std = (fit.amplitude_std / A_t).numpy()
    ph_std = _phase_std(fit.phase_std.numpy(), omega.numpy(), camera, latency_std, n_frames)
    i_m, i_p = 0, 1  # (amplitude, phase) of the one fitted axis
    corr = (fit.covariance[:, i_m, i_p] / (fit.amplitude_std * fit.phase_std).clamp_min(1e-300)).numpy()
    F = mag.shape[0]
    cov = np.zeros((F, 2, 2))
    cov[:, 0, 0] = mag_std**2
    cov[:, 1, 1] = ph_std**2
    cov[:, 0, 1] = cov[:, 1, 0] = corr * mag_std * fit.phase_std.numpy()
    response = mag * np.exp(1j * phase)
    bad = ~fit.converged.numpy()
    response[bad] = np.nan
    cov[bad] = np.nan
    return FrequencyResponse(omega.numpy(), response, cov=cov, input_labels=["x"], output_labels=["x"], meta=meta)


def _assemble_mimo(fit, amps, omega_job, camera, latency_std, n_frames, inputs, P, many_spots, meta):
    """The ``[O, I, F]`` FrequencyResponse from a fit of batch ``[I*F, P]`` with ``axes="xy"``:
    outputs x, y (one spot) or ``s{k}.x``, ``s{k}.y`` (K = P spots), with the (magnitude,
    phase) covariance of every channel point."""
    from torchblur.sysid.frequency_response import FrequencyResponse
    from torchblur.image.spots import spot_labels

    I = len(inputs)
    J = fit.amplitude.shape[0]
    F = J // I
    A_t = torch.tensor(amps, dtype=torch.float64)[:, None, None]  # [J, 1, 1]
    mag = (fit.amplitude / A_t).numpy()  # [J, P, 2]
    phase = fit.phase.numpy()
    mag_std = (fit.amplitude_std / A_t).numpy()
    fit_ph_std = fit.phase_std.numpy()
    om = omega_job.numpy()[:, None, None]
    ph_std = _phase_std(fit_ph_std, om, camera, latency_std, n_frames)
    names = fit.param_names
    corr = np.zeros_like(mag)
    for a, ax in enumerate("xy"):
        i_m, i_p = names.index(f"amplitude_{ax}"), names.index(f"phase_{ax}")
        corr[..., a] = (fit.covariance[..., i_m, i_p] / (fit.amplitude_std[..., a] * fit.phase_std[..., a]).clamp_min(1e-300)).numpy()
    cov = np.zeros(mag.shape + (2, 2))
    cov[..., 0, 0] = mag_std**2
    cov[..., 1, 1] = ph_std**2
    cov[..., 0, 1] = cov[..., 1, 0] = corr * mag_std * fit_ph_std
    response = mag * np.exp(1j * phase)
    bad = ~fit.converged.numpy()  # [J, P]
    response[bad] = np.nan
    cov[bad] = np.nan

    def arrange(x):  # [I*F, P, 2, ...] -> [P*2, I, F, ...]
        x = x.reshape((I, F, P, 2) + x.shape[3:])
        x = np.moveaxis(np.moveaxis(x, 2, 0), 3, 1)  # [P, 2, I, F, ...]
        return x.reshape((P * 2, I, F) + x.shape[4:])

    outputs = spot_labels(P) if many_spots else ["x", "y"]
    return FrequencyResponse(omega_job.numpy()[:F], arrange(response), cov=arrange(cov), input_labels=list(inputs),
                             output_labels=outputs, meta=meta)


def _truth_of(rig, freqs, frf, spots, single):
    """The true response where the rig knows it (simulated rigs): ``[F]`` for a one-spot SISO
    run, else ``[O, I, F]`` in the FRF's channel order (spots matched to the rig's layout by
    their rest position; NaN where none is within 3 px)."""
    if not hasattr(rig, "truth"):
        return None
    if single:
        return np.asarray([rig.truth(float(f)) for f in freqs])
    if spots is None:
        return np.asarray(rig.truth(np.asarray(freqs, dtype=np.float64)))
    if not hasattr(rig, "spot_truth") or getattr(rig, "spots", None) is None:
        return None
    t = np.asarray(rig.spot_truth(np.asarray(freqs, dtype=np.float64)))  # [Kt, 2, I, F]
    rest = rig.spots.rest_px.numpy()
    out = np.full((len(spots), 2) + t.shape[2:], np.nan + 0j)
    for k, cxy in enumerate(spots.psf.center.numpy()):
        d = np.hypot(*(rest - cxy).T)
        if d.min() < 3.0:
            out[k] = t[int(d.argmin())]
    return out.reshape((-1,) + t.shape[2:])
