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

__all__ = ["IdentificationResult", "identify", "build_simulated_rig", "calibrate_latency"]


@dataclass
class IdentificationResult:
    """What :func:`identify` measured. ``frf`` (FrequencyResponse), ``model``
    (TransferFunctionFit or None), ``psf`` (GaussianPSF per second at power 1), ``fit``
    (SinusoidFit of all points), ``amplitude`` (input amplitude per point), ``latency_s``
    and its std, ``saturation`` (SaturationCurve), ``images`` [F, E*R, H, W] (dark
    subtracted, electrons), ``windows`` (ExposureWindow [F, E*R]), ``truth`` (complex [F] or
    None), ``log`` (list of messages)."""

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


def _log(res_log, msg, progress):
    res_log.append(msg)
    if progress:
        from tqdm.auto import tqdm

        tqdm.write(msg)


def identify(cfg: IdentifyConfig, rig=None, *, progress: bool = True) -> IdentificationResult:
    """Run the identification on ``rig`` (default: the config's simulated rig)."""
    from tqdm.auto import tqdm

    from .design import check_design
    from .fit import fit_sinusoid
    from .frequency_response import FrequencyResponse
    from .model_fit import fit_transfer_function
    from .moments import image_moments, sinusoid_from_moments
    from .preprocess import dark_frame, fit_gaussian_psf, saturation_curve, subtract_dark
    from .psf import GaussianPSF
    from .timing import ExposureWindow

    log: list[str] = []
    rig = rig if rig is not None else build_simulated_rig(cfg)
    c = cfg.camera
    gain = float(c.gain)
    dtype = torch.float64
    H, W = rig.frame_shape
    freqs = np.asarray(cfg.frequencies_hz())
    fracs = [float(e) for e in cfg.sweep.exposures]
    E, R = len(fracs), int(cfg.sweep.images_per_point)
    b = float(cfg.sweep.trigger_phase_rad)

    # 1. Dark frame.
    dark = dark_frame(rig.dark(n=16, exposure_s=min(0.01, c.max_exposure_s)).frames.to(dtype))
    read_noise_e = float(dark.read_noise) * gain
    _log(log, f"dark: level {float(dark.mean.mean()):.2f} ADU, read noise {read_noise_e:.2f} e-, "
              f"{int(dark.hot_pixels.sum())} hot pixels", progress)

    # 3 (before 2, to choose the PSF exposure). Saturation curve of the still spot.
    ladder = np.geomspace(1e-4, c.max_exposure_s, 9)
    peaks = []
    for te in ladder:
        peaks.append(float(rig.still(n=1, exposure_s=float(te)).frames.to(dtype).amax()))
    sat = saturation_curve(torch.tensor(peaks, dtype=dtype), torch.tensor(ladder, dtype=dtype))
    full_adu = float(sat.saturation_adu) - float(dark.mean.mean())
    _log(log, f"saturation: {float(sat.saturation_adu):.0f} ADU plateau, linear up to {float(sat.linear_limit_s) * 1e3:.3g} ms of still exposure", progress)

    # 2. PSF: still frames at an exposure that fills peak_fraction of the range.
    te_psf = float(min(c.max_exposure_s, c.peak_fraction * float(sat.linear_limit_s)))
    still = subtract_dark(rig.still(n=16, exposure_s=te_psf).frames.to(dtype), dark).mean(0) * gain
    psf_fit = fit_gaussian_psf(still, exposure_s=te_psf, noise_std=math.sqrt(read_noise_e**2 + float(still.max())) / 4)
    psf = psf_fit.psf
    _log(log, f"psf: centre ({float(psf.center[0]):.2f}, {float(psf.center[1]):.2f}) px, cov "
              f"[[{float(psf.cov[0, 0]):.3f}, {float(psf.cov[0, 1]):.3f}], [., {float(psf.cov[1, 1]):.3f}]] px^2, "
              f"relative residual {float(psf_fit.relative_residual):.2e}", progress)
    peak_rate = float(psf.amplitude)  # electrons per second at power 1

    # 4. Latency.
    pulse_w = 20e-6
    latency, latency_std = calibrate_latency(rig, dark=dark, gain=gain, trigger_delay_s=c.trigger_delay_s, pulse_width_s=pulse_w,
                                             power=c.peak_fraction * full_adu * gain / (peak_rate * pulse_w))
    _log(log, f"latency: {latency * 1e6:.3f} +- {latency_std * 1e6:.3f} us", progress)

    # 5. Sweep.
    target = float(cfg.excitation.target_px)
    amax = cfg.excitation.max_amplitude
    frames_all, masks_all, windows_start, windows_dur, amps, powers = [], [], [], [], [], []
    gain_est = None  # |H| estimate (px per input unit) from the previous point
    bar = tqdm(total=len(freqs), desc="sweep", unit="pt", disable=not progress)
    for f in freqs:
        om = 2 * math.pi * f
        period = 1 / f
        te = [fr * period for fr in fracs]
        A = target / gain_est if gain_est else target / 10.0
        if amax is not None:
            A = min(A, float(amax))
        # Laser power: a still spot over the longest exposure would reach peak_fraction of the range.
        power = c.peak_fraction * full_adu * gain / (peak_rate * max(te))
        offset = (b / om - c.trigger_delay_s - latency) % period
        for attempt in range(3):
            cap = rig.sine(freq_hz=float(f), amplitude=float(A), exposures_s=te, trigger_offset_s=float(offset), n_repeats=R,
                           settle_s=cfg.sweep.settle_s, power=float(power))
            img = subtract_dark(cap.frames.to(dtype), dark) * gain  # [E, R, H, W] electrons
            # closed-form moments of the first exposure: how far did the spot move?
            _, cen, cov = image_moments(img.mean(1), threshold=3 * read_noise_e)
            mu1 = cen[0, 0] - psf.center[0]
            vex = cov[0, 0, 0] - psf.cov[0, 0]
            start0 = torch.tensor(offset + c.trigger_delay_s + latency, dtype=dtype)
            M_est, _ = sinusoid_from_moments(mu1, vex, torch.tensor(om, dtype=dtype), start0, torch.tensor(te[0], dtype=dtype))
            M_est = float(M_est)
            ok = 0.75 * target <= M_est <= 1.33 * target or (amax is not None and A >= amax and M_est < 1.33 * target)
            gain_new = max(M_est, 1e-3) / A
            if ok or attempt == 2:
                break
            A = target / gain_new
            if amax is not None:
                A = min(A, float(amax))
        gain_est = gain_new
        frames_all.append(img.reshape(E * R, H, W))
        masks_all.append(sat.mask(cap.frames.to(dtype)).reshape(E * R, H, W))
        start = torch.tensor([offset + c.trigger_delay_s + latency] * (E * R), dtype=dtype)
        windows_start.append(start)
        windows_dur.append(torch.tensor([t for t in te for _ in range(R)], dtype=dtype))
        amps.append(A)
        powers.append(power)
        bar.update(1)
        bar.set_postfix(f_hz=f"{f:.4g}", amplitude=f"{A:.3g}")
    bar.close()

    images = torch.stack(frames_all)  # [F, E*R, H, W]
    windows = ExposureWindow(torch.stack(windows_start), torch.stack(windows_dur))
    omega = torch.tensor(2 * math.pi * freqs, dtype=dtype)
    power_t = torch.tensor(powers, dtype=dtype)
    check_design(omega, windows[:, ::R] if R > 1 else windows, warn=progress)

    # 6. One batched fit of every point.
    psf_b = GaussianPSF(psf.center.expand(len(freqs), 2), psf.cov.expand(len(freqs), 2, 2), psf.amplitude * power_t)
    mask = torch.stack(masks_all)  # usable (unsaturated) pixels
    n_sat = int((~mask).sum())
    if n_sat:
        _log(log, f"saturation: {n_sat} saturated pixels masked out of the fit", progress)
    noise = torch.sqrt(read_noise_e**2 + images.clamp_min(0))  # shot + read noise (e-), per pixel
    fit = fit_sinusoid(images, psf_b, windows, omega, axes="x", optimizer=cfg.fit.optimizer, loss=cfg.fit.loss,
                       noise_std=noise, mask=mask, fit_scale=cfg.fit.fit_scale, fit_background=cfg.fit.fit_background)
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
    model = None
    try:
        model = fit_transfer_function(frf, n_poles=cfg.model.n_poles, n_zeros=cfg.model.n_zeros,
                                      delay_s=None if cfg.model.fit_delay else 0.0, max_order=int(cfg.model.max_order))
        _log(log, f"model: {model.n_poles} poles, {model.n_zeros} zeros, delay {model.delay_s * 1e6:.2f} us, "
                  f"reduced chi2 {model.reduced_chi2:.3f}", progress)
    except Exception as exc:  # the FRF is still a result; say why the model failed
        _log(log, f"model: fit failed: {exc}", progress)
    truth = None
    if hasattr(rig, "truth"):
        truth = np.asarray([rig.truth(float(f)) for f in freqs])
    return IdentificationResult(frf=frf, model=model, psf=psf, fit=fit, amplitude=np.asarray(amps), latency_s=latency,
                                latency_std_s=latency_std, saturation=sat, images=images, windows=windows, power=power_t,
                                truth=truth, log=log)
