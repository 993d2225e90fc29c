"""The identification procedure end to end (paper section IV).

1. dark frame (mean of frames with no light);
2. PSF identification (averaged still-spot frames, 2-D Gaussian with full covariance);
3. saturation curve (peak intensity vs exposure) and a mask of unusable pixels;
4. trigger-to-exposure latency from laser pulses (measured, not assumed);
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

from .config import IdentifyConfig

__all__ = ["IdentificationResult", "Calibration", "identify", "calibrate", "fit_model", "build_simulated_rig", "build_rig", "calibrate_latency", "check_resume_config"]


@dataclass
class IdentificationResult:
    """What :func:`identify` measured. ``frf`` (FrequencyResponse), ``model``
    (TransferFunctionFit or None), ``psf`` (GaussianPSF per second at power 1), ``fit``
    (SinusoidFit of all points), ``amplitude`` (input amplitude per point), ``latency_s``
    and its std, ``saturation`` (SaturationCurve), ``images`` [F, E*R, H, W] (dark
    subtracted, electrons), ``windows`` (ExposureWindow [F, E*R]), ``truth`` (complex [F] or
    None), ``log`` (list of messages), ``timing`` (acquisition and fit seconds, and how much
    of the fit overlapped the acquisition)."""

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


def build_simulated_rig(cfg: IdentifyConfig):
    """The simulated rig of a config (plant, camera, timing, noise)."""
    from .camera import CameraModel
    from .lti import Plant
    from .rig.simulated import SimulatedRig

    c = cfg.camera
    camera = CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                         bit_depth=int(c.bit_depth))
    plant = Plant(tuple(float(v) for v in cfg.plant.num), tuple(float(v) for v in cfg.plant.den), float(cfg.plant.delay_s))
    return SimulatedRig(plant=plant, camera=camera, frame_shape=(int(c.height), int(c.width)), psf_sigma_px=c.psf_sigma_px,
                        frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s, readout_s=c.readout_s,
                        max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s, seed=int(cfg.seed))


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
    from .preprocess import subtract_dark

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
    from .errors import ConfigError

    if cfg.rig.kind == "simulated":
        return build_simulated_rig(cfg)
    from .hardware.serial_rig import SerialRig

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

    from .hardware.errors import RecordingError

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

    from .config import config_to_yaml, load_dataclass
    from .hardware.errors import RecordingError
    from .hardware.recording import Experiment, camera_info_of

    if isinstance(record, Experiment):
        exp = record
    else:
        path = Path(record)
        if (path / "experiment.json").is_file():
            exp = Experiment.open(path)
        else:
            return Experiment.create(path, config_yaml=config_to_yaml(cfg), camera=camera_info_of(rig))
    recorded = load_dataclass(type(cfg), str(exp.path / "config.yaml"))
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

    from .fit import SinusoidFit

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
            from .hardware.errors import HardwareError

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
    (:class:`~torchblur.preprocess.DarkFrame`), ``read_noise_e``, ``saturation``
    (SaturationCurve), ``full_adu`` (usable range above the dark level, ADU), ``psf``
    (GaussianPSF in electrons per second at power 1), ``peak_rate`` (its peak, e-/s),
    ``latency_s`` and ``latency_std_s``, ``gain`` (e-/ADU)."""

    dark: object
    read_noise_e: float
    saturation: object
    full_adu: float
    psf: object
    peak_rate: float
    latency_s: float
    latency_std_s: float
    gain: float


def calibrate(cfg, rig, exp=None, log=None, progress: bool = False) -> Calibration:
    """Stages 1-4 of :func:`identify`: dark frame, saturation curve, PSF and latency (each
    taken from the recording ``exp`` when it holds it)."""
    from .preprocess import dark_frame, fit_gaussian_psf, saturation_curve, subtract_dark

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
    return Calibration(dark=dark, read_noise_e=read_noise_e, saturation=sat, full_adu=full_adu, psf=psf, peak_rate=peak_rate,
                       latency_s=latency, latency_std_s=latency_std, gain=gain)


def fit_model(cfg, frf, log=None, progress: bool = False):
    """Stage 7 of :func:`identify`: the transfer-function model of ``frf`` under
    ``cfg.model`` (None, with the reason logged, when the fit fails)."""
    from .model_fit import fit_transfer_function

    log = [] if log is None else log
    try:
        model = fit_transfer_function(frf, n_poles=cfg.model.n_poles, n_zeros=cfg.model.n_zeros,
                                      delay_s=None if cfg.model.fit_delay else 0.0, max_order=int(cfg.model.max_order))
    except Exception as exc:  # the FRF is still a result; say why the model failed
        _log(log, f"model: fit failed: {exc}", progress)
        return None
    _log(log, f"model: {model.n_poles} poles, {model.n_zeros} zeros, delay {model.delay_s * 1e6:.2f} us, "
              f"reduced chi2 {model.reduced_chi2:.3f}", progress)
    return model


def _identify(cfg, rig, exp, log, progress) -> IdentificationResult:
    import time

    from tqdm.auto import tqdm

    from .design import check_design
    from .fit import fit_sinusoid
    from .frequency_response import FrequencyResponse
    from .moments import image_moments, sinusoid_from_moments
    from .preprocess import subtract_dark
    from .psf import GaussianPSF
    from .timing import ExposureWindow

    c = cfg.camera
    dtype = torch.float64
    H, W = rig.frame_shape
    freqs = np.asarray(cfg.frequencies_hz())
    fracs = [float(e) for e in cfg.sweep.exposures]
    E, R = len(fracs), int(cfg.sweep.images_per_point)
    b = float(cfg.sweep.trigger_phase_rad)

    t_start = time.perf_counter()
    cal = calibrate(cfg, rig, exp, log, progress)
    dark, read_noise_e, sat, full_adu = cal.dark, cal.read_noise_e, cal.saturation, cal.full_adu
    psf, peak_rate, latency, latency_std, gain = cal.psf, cal.peak_rate, cal.latency_s, cal.latency_std_s, cal.gain
    if cfg.excitation.kind == "multisine":
        from .identify_multisine import identify_multisine

        return identify_multisine(cfg, rig, exp, log, progress, cal, t_start)

    # 5. Sweep. Every completed point goes to the chunked background fit (6.) at once.
    target = float(cfg.excitation.target_px)
    amax = cfg.excitation.max_amplitude
    frames_all, masks_all, windows_start, windows_dur, amps, powers = [], [], [], [], [], []
    omega_all = torch.tensor(2 * math.pi * freqs, dtype=dtype)

    def fit_points(idx):
        imgs = torch.stack([frames_all[k] for k in idx])  # [n, E*R, H, W]
        pw = torch.tensor([powers[k] for k in idx], dtype=dtype)
        n = len(idx)
        psf_b = GaussianPSF(psf.center.expand(n, 2), psf.cov.expand(n, 2, 2), psf.amplitude * pw)
        win = ExposureWindow(torch.stack([windows_start[k] for k in idx]), torch.stack([windows_dur[k] for k in idx]))
        noise = torch.sqrt(read_noise_e**2 + imgs.clamp_min(0))  # shot + read noise (e-), per pixel
        return fit_sinusoid(imgs, psf_b, win, omega_all[list(idx)], axes="x", optimizer=cfg.fit.optimizer, loss=cfg.fit.loss,
                            noise_std=noise, mask=torch.stack([masks_all[k] for k in idx]), fit_scale=cfg.fit.fit_scale,
                            fit_background=cfg.fit.fit_background)

    fitter = _ChunkFitter(int(cfg.fit.chunk_points), fit_points)
    t_sweep = time.perf_counter()
    gain_est = None  # |H| estimate (px per input unit) from the previous point
    bar = tqdm(total=len(freqs), desc="sweep", unit="pt", disable=not progress)
    try:
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
                """Dark-subtracted electrons [E, R, H, W] and the closed-form amplitude (px) of
                the first exposure: how far did the spot move?"""
                img_ = subtract_dark(cap_frames.to(dtype), dark) * gain
                _, cen, cov_ = image_moments(img_.mean(1), threshold=3 * read_noise_e)
                mu1 = cen[0, 0] - psf.center[0]
                vex = cov_[0, 0, 0] - psf.cov[0, 0]
                M, _ = sinusoid_from_moments(mu1, vex, torch.tensor(om, dtype=dtype), start0, torch.tensor(te[0], dtype=dtype))
                return img_, float(M)

            key = f"sweep/x/{k:03d}"
            if exp is not None and exp.has(key):
                rec = exp.groups[key][0]
                if not (math.isclose(rec["freq_hz"], f, rel_tol=1e-12) and math.isclose(rec["power"], power, rel_tol=1e-9)):
                    from .hardware.errors import RecordingError

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
                    cap = rig.sine(**kw)
                    img, M_est = moved_px(cap.frames)  # [E, R, H, W] electrons
                    ok = 0.75 * target <= M_est <= 1.33 * target or (amax is not None and A >= amax and M_est < 1.33 * target)
                    gain_new = max(M_est, 1e-3) / A
                    if ok or attempt == 2:
                        break
                    A = target / gain_new
                    if amax is not None:
                        A = min(A, float(amax))
                if exp is not None and exp.writable:
                    from .hardware.recording import _bind

                    exp.record(key, "sweep", [("sine", _bind("sine", (), kw), cap)],
                               labels={"input": "x", "freq_hz": float(f), "amplitude": float(A), "power": float(power),
                                       "point": k, "attempts": attempt + 1})
            gain_est = gain_new
            frames_all.append(img.reshape(E * R, H, W))
            masks_all.append(sat.mask(cap.frames.to(dtype)).reshape(E * R, H, W))
            windows_start.append(torch.tensor([offset + c.trigger_delay_s + latency] * (E * R), dtype=dtype))
            windows_dur.append(torch.tensor([t for t in te for _ in range(R)], dtype=dtype))
            amps.append(A)
            powers.append(power)
            fitter.add(k)
            bar.update(1)
            bar.set_postfix(f_hz=f"{f:.4g}", amplitude=f"{A:.3g}")
        bar.close()
        t_acq_end = time.perf_counter()

        images = torch.stack(frames_all)  # [F, E*R, H, W]
        windows = ExposureWindow(torch.stack(windows_start), torch.stack(windows_dur))
        omega = omega_all
        power_t = torch.tensor(powers, dtype=dtype)
        check_design(omega, windows[:, ::R] if R > 1 else windows, warn=progress)
        mask = torch.stack(masks_all)  # usable (unsaturated) pixels
        n_sat = int((~mask).sum())
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
    A_t = torch.tensor(amps, dtype=dtype)
    mag = (fit.amplitude / A_t).numpy()
    phase = fit.phase.numpy()
    mag_std = (fit.amplitude_std / A_t).numpy()
    n_frames = E * R
    # Phase std: the fit, the trigger jitter (per frame, averaged) and the latency calibration.
    ph_std = np.sqrt(fit.phase_std.numpy() ** 2 + (omega.numpy() * c.jitter_s) ** 2 / n_frames + (omega.numpy() * latency_std) ** 2)
    i_m = fit.param_names.index("amplitude_x")
    i_p = fit.param_names.index("phase_x")
    corr = (fit.covariance[:, i_m, i_p] / (fit.amplitude_std * fit.phase_std).clamp_min(1e-300)).numpy()
    cov = np.zeros((len(freqs), 2, 2))
    cov[:, 0, 0] = mag_std**2
    cov[:, 1, 1] = ph_std**2
    cov[:, 0, 1] = cov[:, 1, 0] = corr * mag_std * fit.phase_std.numpy()
    response = mag * np.exp(1j * phase)
    bad = ~fit.converged.numpy()
    response[bad] = np.nan
    cov[bad] = np.nan
    frf = FrequencyResponse(omega.numpy(), response, cov=cov, input_labels=["x"], output_labels=["x"],
                            meta={"seed": int(cfg.seed)})
    n_bad = int(bad.sum())
    _log(log, f"fit: {len(freqs) - n_bad} of {len(freqs)} points converged", progress)

    # 7. Parametric model.
    model = fit_model(cfg, frf, log, progress)
    truth = None
    if hasattr(rig, "truth"):
        truth = np.asarray([rig.truth(float(f)) for f in freqs])
    return IdentificationResult(frf=frf, model=model, psf=psf, fit=fit, amplitude=np.asarray(amps), latency_s=latency,
                                latency_std_s=latency_std, saturation=sat, images=images, windows=windows, power=power_t,
                                truth=truth, log=log, timing=timing)
