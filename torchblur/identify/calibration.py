"""The calibrate stage (stages 1-4 of the identification): dark frame, saturation curve,
PSF (one spot, or a grid of spots), trigger-to-exposure latency and, for one axis and one
spot, the actuator's direction in the image."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from torchblur.errors import ConfigError, ParameterError, as_unit_direction
from torchblur.config import LATENCY_SCAN, SATURATION_STEPS, latency_scan_times
from torchblur.identify.drive import DriveLimit, at_limit, check_recorded_drive, drive_limit
from torchblur.identify.record import LOGGER, run_stage
from torchblur.image.photon_transfer import photon_transfer
from torchblur.image.preprocess import dark_frame, saturation_curve, subtract_dark
from torchblur.image.psf_from_still import psf_from_still
from torchblur.image.spot_layout import layout_spots
from torchblur.image.spots import crop_spots, locate_spots
from torchblur.render.psf import KernelPSF
from torchblur.image.tracking import calibrate_axes
from torchblur.render.camera import CameraNoise, camera_noise_std

__all__ = ["Calibration", "MIN_INSIDE", "PTC_STEPS", "SpotKernels", "calibrate", "calibrate_latency", "check_latency_source", "choose_gain",
           "latency_from_scan", "latency_given", "measure_gain", "ptc_exposures", "spot_kernels", "spots_from_still",
           "still_rate"]

MIN_INSIDE = 0.5  # a spot with less of its still light in the frame is flagged, not fitted


@dataclass
class Calibration:
    """What the calibration stages (1-4 of :func:`identify`) measured: ``dark``
    (:class:`~torchblur.image.preprocess.DarkFrame`), ``read_noise_e``, ``saturation``
    (SaturationCurve), ``full_adu`` (usable range above the dark level, ADU), ``psf``
    (GaussianPSF in electrons per second at power 1: with one spot the point-sampled Gaussian
    of :func:`~torchblur.image.psf_from_still.psf_from_still`, the pixel model of every fit;
    with many spots one per spot), ``peak_rate`` (its peak, e-/s), ``latency_s`` and
    ``latency_std_s``, ``gain`` (e-/ADU), with one spot ``still_psf`` (the
    :class:`~torchblur.image.psf_from_still.StillPSF`: the PSF every fit of the run uses (sine
    sweep, multisine, direct model), ``still_psf.psf``, a KernelPSF or that Gaussian, and why),
    with many spots ``spot_kernels`` (:class:`SpotKernels`, or None: the Gaussians), and for one-axis runs the
    actuator's unit image ``direction`` (x, y), with ``fit.axis=measure`` the ``axis`` (AxisCalibration) that
    measured it and ``axis_gain`` (|H|, px per input unit, at that frequency: the sweep's first amplitude); ``noise``, the camera's
    :class:`~torchblur.render.camera.CameraNoise` (gain, mean dark level, read noise: the one noise
    model every fit of the run weighs its residuals with), is built from them."""

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
    direction: tuple | None = None
    axis: object = None
    axis_gain: float | None = None
    still_psf: object = None  # one spot: the StillPSF (fit.psf's choice and its evidence), else None
    spot_kernels: object = None
    drive: DriveLimit | None = None  # the run's input range (every command within drive.limit); None: no limit
    latency_source: str = "scanned"  # "scanned" (laser pulses, rig.pulse) or "given" (camera.latency_s, camera.latency_std_s)
    ptc: object = None  # the PhotonTransfer measured from the run's frames (None: not measured)
    gain_source: str = "camera.gain"  # where ``gain`` came from: "camera.gain" or "photon transfer"
    noise: CameraNoise | None = None  # None: built from gain, dark and read_noise_e
    # many spots: the mean still frame [H, W] (e-/s at power 1, dark subtracted, gain applied) and its variance (of the
    # mean, (e-/s)^2, the camera noise model): a DM run's static holds are compared with it (torchblur.identify.dm_ladder)
    still_rate: torch.Tensor | None = None
    still_rate_var: torch.Tensor | None = None

    def __post_init__(self):
        if self.noise is None:
            self.noise = CameraNoise(gain_e_per_adu=self.gain, offset_adu=float(self.dark.mean.mean()), read_noise_e=self.read_noise_e)

    @property
    def input_limit(self) -> float:
        """The largest |command| (input units) the run may ask for (inf without a ``drive``)."""
        return math.inf if self.drive is None else float(self.drive.limit)

    def limit_at(self, freq_hz: float) -> float:
        """The largest sine amplitude (input units) at ``freq_hz`` Hz: the range and the slew limit
        (:meth:`~torchblur.identify.drive.DriveLimit.at`; inf without a ``drive``)."""
        return math.inf if self.drive is None else self.drive.at(freq_hz)


#: dark frames of a calibration: the dark mean's noise is common to every frame and in no std (with
#: 16 the multisine config's still failed its Gaussian test at reduced chi2 1.67 and one group fitted
#: at 3.1, its points lost; with 256 the still passed at 1.14 and every group fitted at <= 1.04)
N_DARK = 256


def calibrate(cfg, rig, exp=None, *, n_dark: int = N_DARK, n_still: int = 16, spot_psfs: bool = True,
              spot_layout=None):
    """Stages 1-4 of :func:`identify`: dark frame, saturation curve, PSF, latency and, for a
    one-axis, one-spot run, the actuator's direction in the image (each taken from the
    recording ``exp`` when it holds it). ``n_dark`` dark frames (:data:`N_DARK`) and ``n_still``
    still frames: the PSF's own error and the dark mean's noise, common to every frame, are in no fitted point's std, so a
    run whose stds are small takes more. ``spot_psfs``: many spots' PSFs by :func:`spot_kernels` (False: the Gaussians).
    ``spot_layout``: the sensor's declared rest positions ``[M, 2]`` (x, y px): the spots are cropped there
    (:func:`_layout_spots`), not found by thresholding the frame."""
    c = cfg.camera
    dtype = torch.float64

    check_latency_source(cfg, rig)
    # 0. The input range, fixed before the first frame (a resumed recording must be within it).
    drive = drive_limit(rig, cfg.excitation.max_amplitude, exp, getattr(cfg.excitation, "max_slew", None))
    if exp is not None and exp.writable:
        check_recorded_drive(exp, drive.limit, drive.slew)
    LOGGER.info(drive.describe())

    # 1. Dark frame.
    dark_raw = run_stage(exp, "dark", "dark", rig, lambda r: r.dark(n=n_dark, exposure_s=min(0.01, c.max_exposure_s))).frames.to(dtype)
    dark = dark_frame(dark_raw)
    LOGGER.info(f"dark: level {float(dark.mean.mean()):.2f} ADU, read noise {float(dark.read_noise):.3g} ADU, "
                f"{int(dark.hot_pixels.sum())} hot pixels")

    # 3 (before 2, to choose the PSF exposure). Saturation curve of the still spot.
    ladder = np.geomspace(1e-4, c.max_exposure_s, SATURATION_STEPS)
    peaks = run_stage(exp, "saturation", "saturation", rig,
                   lambda r: [float(r.still(n=1, exposure_s=float(te)).frames.to(dtype).amax()) for te in ladder])
    sat = saturation_curve(torch.tensor(peaks, dtype=dtype), torch.tensor(ladder, dtype=dtype))
    full_adu = float(sat.saturation_adu) - float(dark.mean.mean())
    LOGGER.info(f"saturation: {float(sat.saturation_adu):.0f} ADU plateau, linear up to {float(sat.linear_limit_s) * 1e3:.3g} ms of still exposure")

    # 2. PSF: still frames at an exposure that fills peak_fraction of the range.
    te_psf = float(min(c.max_exposure_s, c.peak_fraction * float(sat.linear_limit_s)))
    still_raw = run_stage(exp, "psf", "psf", rig, lambda r: r.still(n=n_still, exposure_s=te_psf)).frames.to(dtype)
    # 2a. The gain: a photon transfer curve of the still frames (and of a ladder with camera.ptc_frames), checked against camera.gain.
    ptc, gain, gain_source = _gain_stage(cfg, rig, exp, dark_raw, dark, still_raw, sat)
    read_noise_e = float(dark.read_noise) * gain
    still_e = subtract_dark(still_raw, dark) * gain
    spots = still_psf = spot_kern = None
    if getattr(cfg, "spots", None) is not None and cfg.spots.enabled:
        spots, spot_kern = spots_from_still(cfg, still_e, te_psf, read_noise_e, spot_layout=spot_layout,
                                            spot_psfs=spot_psfs)
        psf = spots.psf  # [K], full-frame coordinates
        whole = spots.inside_fraction >= MIN_INSIDE  # an edge spot's peak is an extrapolation: not trusted here
        peak_rate = float(psf.amplitude[whole].max() if bool(whole.any()) else psf.amplitude.max())  # e-/s at power 1
    else:
        still_psf = _still_psf(cfg, still_e, te_psf, read_noise_e)
        psf = still_psf.gaussian.psf
        peak_rate = float(psf.amplitude)  # electrons per second at power 1

    # 4. Latency: given (camera.latency_s, camera.latency_std_s), or scanned with laser pulses.
    latency, latency_std, latency_source = _latency_stage(cfg, rig, exp, dark, gain, full_adu, peak_rate)
    cal = Calibration(dark=dark, read_noise_e=read_noise_e, saturation=sat, full_adu=full_adu, psf=psf, peak_rate=peak_rate,
                      latency_s=latency, latency_std_s=latency_std, gain=gain, spots=spots, still_psf=still_psf, drive=drive,
                      latency_source=latency_source, ptc=ptc, gain_source=gain_source, spot_kernels=spot_kern)
    if spots is not None:
        cal.still_rate, cal.still_rate_var = still_rate(still_e, te_psf, read_noise_e)

    # 4b. The actuator's direction in the image (one axis, one spot; a 2x2 plant or many spots
    # fit both image axes).
    if not cfg.plant.is_mimo and spots is None:
        _axis_stage(cfg, rig, exp, cal)
    return cal


def still_rate(frames_e, exposure_s: float, read_noise_e: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean of still frames ``frames_e [n, H, W]`` (e-, dark subtracted) per second and its
    variance (of the mean, from the camera noise model): ``([H, W], [H, W])``."""
    mean = frames_e.mean(0)
    return mean / exposure_s, camera_noise_std(mean, read_noise_e) ** 2 / (frames_e.shape[0] * exposure_s**2)


def _axis_stage(cfg, rig, exp, cal: Calibration) -> None:
    """Stage 4b of :func:`calibrate` (one axis, one spot): ``cal.direction``, the actuator's
    direction in the image (measured by tracking with ``fit.axis=measure``, from the recording
    where it holds it, else x; or the configured axis), with ``cal.axis`` and ``cal.axis_gain`` where measured."""
    mode = cfg.fit.axis
    if mode == "measure" and exp is not None and not exp.writable and "axis" not in exp.groups:
        cal.direction = (1.0, 0.0)
        LOGGER.info("axis: not in the recording (made before the axis calibration): the motion is fitted along x")
    elif mode == "measure":
        axis, axis_gain = run_stage(exp, "axis", "axis", rig, lambda r: _measure_axis(cfg, r, cal))
        u = np.asarray(axis.direction, dtype=float)
        if u[0] < 0 or (u[0] == 0 and u[1] < 0):  # the sign that points toward +x: the FRF keeps the x convention
            u = -u
        if not (np.isfinite(u).all() and axis.px_per_unit > 5 * axis.px_per_unit_std):
            cal.direction = (1.0, 0.0)  # no clear motion to take a direction from
            LOGGER.info(f"axis: no clear motion in the tracking ({axis.px_per_unit:.3g} +- {axis.px_per_unit_std:.2g} px per "
                        f"input unit at {cfg.frequencies_hz()[0]:.4g} Hz): the motion is fitted along x")
        else:
            cal.direction, cal.axis, cal.axis_gain = (float(u[0]), float(u[1])), axis, axis_gain
            LOGGER.info(f"axis: {math.degrees(math.atan2(u[1], u[0])):.3f} +- {math.degrees(axis.angle_std_rad):.3f} deg from "
                        f"+x (tracked at {cfg.frequencies_hz()[0]:.4g} Hz, {axis.px_per_unit:.4g} px per input unit)")
    else:
        cal.direction = configured_direction(mode)


def configured_direction(axis) -> tuple[float, float]:
    """The unit image direction ``(x, y)`` of ``fit.axis`` given as ``"x"``, ``"y"`` or ``[x, y]``."""
    u = as_unit_direction({"x": (1.0, 0.0), "y": (0.0, 1.0)}[axis] if isinstance(axis, str) else axis, "fit.axis",
                          like=torch.zeros((), dtype=torch.float64))
    return float(u[0]), float(u[1])


def _latency_stage(cfg, rig, exp, dark, gain: float, full_adu: float, peak_rate: float):
    """Stage 4: ``(latency_s, std_s, "given" | "scanned")``: ``camera.latency_s`` +- ``camera.latency_std_s``
    where given, else :func:`calibrate_latency` with pulses that fill ``camera.peak_fraction`` of the range
    (``full_adu``) at the still spot's peak (``peak_rate`` e-/s)."""
    c = cfg.camera
    if latency_given(cfg):
        latency, std = float(c.latency_s), float(c.latency_std_s)
        LOGGER.info(f"latency: {latency * 1e6:.3f} +- {std * 1e6:.3f} us given (camera.latency_s, camera.latency_std_s; "
                    f"not scanned)")
        return latency, std, "given"
    pulse_w = LATENCY_SCAN["pulse_width_s"]
    latency, std = run_stage(exp, "latency", "latency", rig, lambda r: calibrate_latency(
        r, dark=dark, gain=gain, trigger_delay_s=c.trigger_delay_s, pulse_width_s=pulse_w,
        power=c.peak_fraction * full_adu * gain / (peak_rate * pulse_w)))
    LOGGER.info(f"latency: {latency * 1e6:.3f} +- {std * 1e6:.3f} us scanned with laser pulses")
    return latency, std, "scanned"


def latency_given(cfg) -> bool:
    """Whether the run takes its trigger-to-exposure latency as given (``camera.latency_std_s`` set:
    ``camera.latency_s`` +- it) instead of scanning it with laser pulses."""
    return getattr(cfg.camera, "latency_std_s", None) is not None


def check_latency_source(cfg, rig) -> None:
    """Refuse, before any frame, a run that must scan its latency on a rig that cannot
    (no ``pulse()``: a gated laser the controller does not have).

    Raises:
        ConfigError: naming ``camera.latency_std_s``.
    """
    if not latency_given(cfg) and not callable(getattr(rig, "pulse", None)):
        raise ConfigError(f"camera.latency_std_s: the rig ({type(rig).__name__}) has no gated laser (pulse()) to scan the "
                          f"trigger-to-exposure latency; give camera.latency_s=... and camera.latency_std_s=... (s), the "
                          f"latency your camera's datasheet or your own measurement gives and its std")


PTC_STEPS = 8  # exposures of the photon transfer ladder (camera.ptc_frames frames each), 5 %..95 % of the linear range
WARN_Z = 3.0  # a configured gain this many stds from the measured one is named in a warning
AUTO_REL_STD = 0.01  # camera.gain_from=auto takes the measured gain when it is this precise (or the configured one is off)


def ptc_exposures(linear_limit_s: float, max_exposure_s: float) -> list[float]:
    """The exposures (s) of the photon transfer ladder: :data:`PTC_STEPS` from 5 % to 95 % of the
    still spot's linear range (its peak short of saturation), at most ``max_exposure_s``."""
    return [float(min(max_exposure_s, t)) for t in np.geomspace(0.05, 0.95, PTC_STEPS) * float(linear_limit_s)]


def choose_gain(ptc, configured: float, mode: str, name: str = "camera.gain") -> tuple[float, str, str]:
    """The gain a run uses: ``(gain e-/ADU, source, log line)``. ``mode`` (``camera.gain_from``):
    ``"measure"``: the photon transfer's; ``"config"``: ``configured`` (beyond :data:`WARN_Z` stds
    from the measured one with a warning); ``"auto"``: the measured one where it is
    within :data:`AUTO_REL_STD` relative std or the configured one lies more than :data:`WARN_Z`
    stds from it, else the configured one. The line names both, their distance in stds and, beyond
    :data:`WARN_Z`, warns that with the configured gain every std would be sqrt(true / configured) times the true error's.
    ``name``: where ``configured`` comes from (``camera.gain``; a recording's ``gain_e_per_adu``).
    """
    if ptc is None:
        return configured, name, f"gain: {configured:g} e-/ADU from {name} (given, not measured: every std scales with it)"
    z = ptc.gain_z(configured)
    measured = f"{ptc.gain_e_per_adu:.4g} +- {ptc.gain_std:.2g} e-/ADU measured (photon transfer)"
    off = abs(z) > WARN_Z
    use = mode == "measure" or (mode == "auto" and (ptc.relative_gain_std <= AUTO_REL_STD or off))
    gain, source = (ptc.gain_e_per_adu, "photon transfer") if use else (configured, name)
    line = f"gain: {gain:.4g} e-/ADU from {source} (camera.gain_from={mode}; {measured}; {name} {configured:g} is {z:+.1f} stds from it)"
    if off:
        line = (f"gain: warning: {name} {configured:g} e-/ADU is {z:+.1f} stds from the {measured}: with it every std would be "
                f"{math.sqrt(ptc.gain_e_per_adu / configured):.3g} times the true error's; the run uses {gain:.4g} e-/ADU from {source}")
    return gain, source, line


def _gain_stage(cfg, rig, exp, dark_raw, dark, still_raw, sat):
    """Stage 2a: the photon transfer curve of the still frames (the spot's pixels span dark to its
    peak) and, with ``camera.ptc_frames`` > 0, of a ladder of :data:`PTC_STEPS` exposures of that
    many still frames each; the gain it gives is checked against ``camera.gain`` and chosen
    (:func:`choose_gain`). Returns ``(PhotonTransfer or None, gain, source)``."""
    c = cfg.camera
    mode, configured = getattr(c, "gain_from", "config"), float(c.gain)
    steps = [still_raw]
    n_ladder = int(getattr(c, "ptc_frames", 0) or 0)
    if n_ladder > 0:
        te = ptc_exposures(float(sat.linear_limit_s), float(c.max_exposure_s))
        steps += run_stage(exp, "ptc", "ptc", rig, lambda r: [r.still(n=n_ladder, exposure_s=t).frames.to(dark_raw.dtype) for t in te])
    return measure_gain(steps, dark_raw, dark, float(sat.saturation_adu), configured, mode)


def measure_gain(steps, dark_raw, dark, saturation_adu: float, configured: float, mode: str, *,
                 name: str = "camera.gain"):
    """The photon transfer curve of ``steps`` (raw frames, ADU: a list of ``[N, H, W]``) against the
    raw dark frames ``dark_raw`` ``[D, H, W]`` (``dark``: their DarkFrame, for the hot pixels), and
    the gain :func:`choose_gain` takes from it; both logged. Returns ``(PhotonTransfer or None, gain,
    source)``: None where the frames give no curve (then ``configured``, unless ``mode`` is measure).

    Raises:
        ConfigError: naming ``camera.gain_from`` (measure, and the frames give no curve).
    """
    ptc = None
    if all(s.shape[0] >= 2 for s in steps) and dark_raw.shape[0] >= 2:
        try:
            ptc = photon_transfer(steps, dark_raw, saturation_adu=saturation_adu, hot_pixels=dark.hot_pixels)
            LOGGER.info(f"photon transfer: {ptc.describe()}")
        except ParameterError as exc:
            LOGGER.info(f"photon transfer: not measured ({exc})")
    if ptc is None and mode == "measure":
        raise ConfigError("camera.gain_from: measure, but the frames give no photon transfer curve (see the log)")
    gain, source, line = choose_gain(ptc, configured, mode, name)
    LOGGER.info(line)
    return ptc, gain, source


_AXIS_FRAMES = 24  # short exposures of the axis calibration, at phases spread over a period


def _measure_axis(cfg, rig, cal: Calibration):
    """Stage 4b: track the spot frame by frame (:func:`torchblur.image.tracking.calibrate_axes`) at the
    sweep's first frequency, the amplitude adapted (up to three tries, as the sweep does) so
    the spot moves about ``excitation.target_px``. Returns ``(AxisCalibration, px per input
    unit)``."""
    c, x = cfg.camera, cfg.excitation
    f = cfg.frequencies_hz()[0]
    target, limit = float(x.target_px), cal.limit_at(f)
    # Tracking exposures: 5 % of the period (shorter when the camera's longest exposure is).
    frac = min(0.05, 0.9 * min(float(c.max_exposure_s), float(getattr(rig, "max_exposure_s", c.max_exposure_s))) * f)
    te = frac / f
    power = c.peak_fraction * cal.full_adu * cal.gain / (cal.peak_rate * te)
    A = target / 10.0
    for attempt in range(3):
        A = min(A, limit)
        axis = calibrate_axes(rig, freq_hz=f, amplitude=A, rest_px=cal.psf.center, dark=cal.dark, gain=cal.gain, n_frames=_AXIS_FRAMES,
                              latency_s=cal.latency_s, trigger_delay_s=c.trigger_delay_s, power=power, noise_e=cal.read_noise_e,
                              exposure_fraction=frac)
        moved = axis.px_per_unit * A
        if 0.5 * target <= moved <= 2 * target or (at_limit(A, limit) and moved < 2 * target):
            break
        A = target / max(axis.px_per_unit, 1e-12)
    return axis, axis.px_per_unit


def _still_psf(cfg, still_e, exposure_s, read_noise_e):
    """Stage 2 with one spot: :func:`~torchblur.image.psf_from_still.psf_from_still` of the
    dark-subtracted still frames ``still_e`` ``[N, H, W]`` (electrons; one frame's noise from
    the camera model; background 0 after the dark subtraction, unless ``fit.fit_background``
    lets the sweep fit a level, when it is measured too) with ``kind = fit.psf``. Logs the
    choice, its reason (both reduced chi2) and the Gaussian;
    every route (sine sweep, multisine, direct model) fits with ``sp.psf``."""
    noise = camera_noise_std(still_e.mean(0), read_noise_e)  # one frame's noise [H, W], e-
    sp = psf_from_still(still_e, exposure_s, noise, kind=cfg.fit.psf, background=None if cfg.fit.fit_background else 0.0)
    if sp.gaussian is None:
        raise ParameterError(f"fit.psf: no Gaussian fits the still frame, and the centre, peak rate and axis calibration need "
                             f"one ({sp.reason})")
    g = sp.gaussian.psf
    LOGGER.info(f"psf: {sp.reason}")
    LOGGER.info(f"psf: Gaussian (point-sampled) centre ({float(g.center[0]):.2f}, {float(g.center[1]):.2f}) px, cov "
                f"[[{float(g.cov[0, 0]):.3f}, {float(g.cov[0, 1]):.3f}], [., {float(g.cov[1, 1]):.3f}]] px^2, relative "
                f"residual {float(sp.gaussian.relative_residual):.2e}")
    return sp


@dataclass(frozen=True)
class SpotKernels:
    """The measured kernels of many spots: ``psf`` (:class:`KernelPSF` ``[K, h, w]`` in the spots'
    crops, electrons per second at power 1), ``still`` (``[K]``, each spot's
    :class:`~torchblur.image.psf_from_still.StillPSF`, None for a spot not fitted) and ``rule``
    (one of them, kind ``kernel``: its :meth:`kernel_noise_factor` is every spot's)."""

    psf: KernelPSF
    still: list
    rule: object

    def kernel_noise_factor(self, exposures_s) -> torch.Tensor:
        """The kernels' own noise (every spot's still has the same frames and exposure)."""
        return self.rule.kernel_noise_factor(exposures_s)


def spots_from_still(cfg, still_e, exposure_s, read_noise_e, *, spot_layout=None, spot_psfs: bool = True):
    """Many spots from the still frames ``still_e [N, H, W]`` (electrons, dark subtracted):
    ``(spots, kernels)``, the :class:`~torchblur.image.spots.SpotPSFs` (found by thresholding, or
    with ``spot_layout`` ``[M, 2]`` cropped on the sensor's declared layout) and their
    :class:`SpotKernels` (:func:`spot_kernels`; None when ``spot_psfs`` is False). One function for
    a live calibration and for a recording's (``torchblur.identify.dm_outside``), so both take the same steps."""
    if spot_layout is None:
        spots = _locate_spots(cfg, still_e.mean(0), exposure_s, read_noise_e)
    else:
        spots = _layout_spots(cfg, still_e.mean(0), exposure_s, read_noise_e, spot_layout)
    kernels = spot_kernels(cfg, still_e, exposure_s, read_noise_e, spots) if spot_psfs else None
    return spots, kernels


def spot_kernels(cfg, still_e, exposure_s, read_noise_e, spots):
    """Stage 2 with many spots and ``fit.psf`` auto or kernel: :func:`~torchblur.image.psf_from_still.psf_from_still`
    on every spot's crop of the dark-subtracted still frames ``still_e [N, H, W]`` (e-). Every spot is
    fitted with its measured kernel when ``fit.psf=kernel`` or, with ``auto``, when any fitted spot's
    Gaussian fails its test (one PSF type per batch; a spot whose Gaussian passes is as well
    described by its kernel); else (or with ``fit.psf=gaussian``) None: the Gaussians. A spot mostly
    outside the frame (not fitted) keeps its Gaussian's image as a placeholder kernel."""
    if cfg.fit.psf == "gaussian":
        return None
    crops = crop_spots(still_e, spots.offset, spots.size)  # [N, K, h, w]
    h, w = spots.size
    inside = spots.inside_fraction >= MIN_INSIDE
    psf_c = spots.psf_in_crops()
    yy, xx = torch.meshgrid(torch.arange(h, dtype=still_e.dtype), torch.arange(w, dtype=still_e.dtype), indexing="ij")
    kern, still = [], []
    for k in range(len(spots)):
        sp = None
        if bool(inside[k]):
            c = crops[:, k]
            try:
                sp = psf_from_still(c, exposure_s, camera_noise_std(c.mean(0), read_noise_e), kind=cfg.fit.psf,
                                    background=None if cfg.fit.fit_background else 0.0)
            except ParameterError:
                sp = None
        still.append(sp)
        kern.append(sp.kernel.kernel if sp is not None else psf_c[k].evaluate(xx, yy))
    fitted = [sp for sp in still if sp is not None]
    failing = [sp for sp in fitted if sp.kind == "kernel"]
    if not fitted or not failing:
        if fitted:
            LOGGER.info(f"spots psf: Gaussian per spot (each of the {len(fitted)} spots' Gaussians explains its still: worst "
                        f"reduced chi2 {max(float(sp.chi2_gaussian) for sp in fitted):.3g})")
        return None
    worst = max(failing, key=lambda sp: float(sp.chi2_gaussian))
    why = "fit.psf=kernel" if cfg.fit.psf == "kernel" else (f"{len(failing)} of {len(fitted)} spots' Gaussians do not explain "
                                                            f"their still, worst reduced chi2 {float(worst.chi2_gaussian):.3g} > "
                                                            f"{worst.chi2_threshold:.3g}")
    LOGGER.info(f"spots psf: the measured kernel of every spot ({why})")
    return SpotKernels(psf=KernelPSF(torch.stack(kern)), still=still, rule=replace(fitted[0], kind="kernel", psf=fitted[0].kernel))


def _locate_spots(cfg, still, exposure_s, read_noise_e):
    """Stage 2 with many spots: find them in the still image and fit a PSF per spot (one
    batch, on crops); log how many of the expected grid were found."""
    sp = cfg.spots
    spots = locate_spots(still, exposure_s=exposure_s, noise_std=camera_noise_std(float(still.max()), read_noise_e) / 4,
                         pitch_px=float(sp.pitch_px), crop_px=None if sp.crop_px is None else int(sp.crop_px))
    K, expected = len(spots), int(sp.rows) * int(sp.cols)
    sd = torch.linalg.eigvalsh(spots.psf.cov).clamp_min(0).sqrt()
    LOGGER.info(f"spots: {K} found (grid {sp.rows}x{sp.cols} = {expected}), crops {spots.size[0]}x{spots.size[1]} px, PSF sigma "
                f"{float(sd.min()):.2f}..{float(sd.max()):.2f} px, worst relative residual "
                f"{float(spots.fit.relative_residual.max()):.2e}")
    if K < expected:
        LOGGER.info(f"spots: {expected - K} of the {expected} expected spot(s) not found (missing or too dim); the others are fitted")
    for k in torch.nonzero(spots.clipped).reshape(-1).tolist():
        c = spots.psf.center[k]
        frac = float(spots.inside_fraction[k])
        what = "flagged: not fitted" if frac < MIN_INSIDE else "fitted on the pixels in the frame"
        LOGGER.info(f"spots: s{k} at ({float(c[0]):.1f}, {float(c[1]):.1f}) px is at the frame edge, {frac * 100:.0f}% of its light "
                    f"in the frame ({what})")
    return spots


def _layout_spots(cfg, still, exposure_s, read_noise_e, rest_px):
    """Stage 2 on a sensor's known layout: the declared spots ``rest_px [M, 2]`` registered to the
    still image and fitted (:func:`~torchblur.image.spot_layout.layout_spots`, one batch, in the
    declared order); logs the registration and names every flagged spot (its fit goes on)."""

    sp = cfg.spots
    spots, reg, flags = layout_spots(still, exposure_s=exposure_s, noise_std=camera_noise_std(float(still.max()), read_noise_e) / 4,
                                     rest_px=rest_px, pitch_px=float(sp.pitch_px), sigma_px=float(sp.sigma_px),
                                     crop_px=None if sp.crop_px is None else int(sp.crop_px))
    LOGGER.info(f"spots: {reg.describe()}")
    sd = torch.linalg.eigvalsh(spots.psf.cov).clamp_min(0).sqrt()
    LOGGER.info(f"spots: {len(spots)} declared spots cropped {spots.size[0]}x{spots.size[1]} px, Gaussian PSF sigma "
                f"{float(sd.min()):.2f}..{float(sd.max()):.2f} px, worst relative residual "
                f"{float(spots.fit.relative_residual.max()):.2e}")
    for k, f in enumerate(flags):
        if f != "ok":
            LOGGER.info(f"spots: s{k} flagged {f} (its Gaussian PSF is kept; its fits are judged by their own chi2)")
    return spots


def calibrate_latency(rig, *, dark, gain: float, exposure_s: float = LATENCY_SCAN["exposure_s"],
                      pulse_width_s: float = LATENCY_SCAN["pulse_width_s"], max_latency_s: float = LATENCY_SCAN["max_latency_s"],
                      step_s: float = LATENCY_SCAN["step_s"], repeats: int = LATENCY_SCAN["repeats"], trigger_delay_s: float = 0.0,
                      power: float = 1.0):
    """Trigger-to-exposure latency from short laser pulses (mirror still).

    The laser is on only during ``[p, p + pulse_width]`` after the trigger command; the frame's
    light is the overlap of the pulse with ``[Td + latency, Td + latency + Te]``. Scanning ``p``
    gives a trapezoid; its rising edge is linear and reaches half height at
    ``p = Td + latency - pulse_width / 2``. Returns ``(latency_s, std_s)`` (std from the
    residual scatter of the edge fit).
    """
    times = latency_scan_times(trigger_delay_s, exposure_s=exposure_s, pulse_width_s=pulse_width_s, max_latency_s=max_latency_s,
                               step_s=step_s)
    light = []
    for p in times:
        cap = rig.pulse(exposure_s=exposure_s, trigger_offset_s=0.0, pulse_time_s=float(p), pulse_width_s=pulse_width_s, n=repeats,
                        power=power)
        light.append(float(subtract_dark(cap.frames, dark).sum((-1, -2)).mean()) * gain)
    return latency_from_scan(times, np.asarray(light), pulse_width_s=pulse_width_s, trigger_delay_s=trigger_delay_s)


def latency_from_scan(times, light, *, pulse_width_s: float, trigger_delay_s: float = 0.0):
    """``(latency_s, std_s)`` from a pulse scan's ``light [n]`` (e-, per frame) at pulse times
    ``times [n]`` (s after the trigger): :func:`calibrate_latency`'s estimate.

    The plateau's level ``top`` is the median of every point above 90 % of a first guess (the
    median of the highest tenth), not of the highest points alone: those are the ones the noise
    pushed up, and their median (about 1.3 noise stds high on a 90-point plateau) moved the half
    height, hence the latency, late by a bias larger than its std. The rising edge (points
    strictly between 10 % and 90 % of ``top`` before the first plateau point) is fitted by a line;
    the latency is where it reaches ``top / 2``, plus half the pulse, minus the trigger delay.
    The std: the line's covariance (its residual scatter) and the plateau median's
    (``1.2533 std / sqrt(n)``), carried to the half-height time by linearisation.
    """
    light = np.asarray(light, dtype=np.float64)
    guess = np.median(np.sort(light)[-max(3, len(light) // 10):])
    plateau = light[light >= 0.9 * guess]
    top = float(np.median(plateau))
    top_var = 1.2533 ** 2 * float(np.var(plateau, ddof=1)) / plateau.size if plateau.size > 1 else 0.0
    # Points on the rising edge: strictly between 10% and 90% of the top.
    idx = np.nonzero((light > 0.1 * top) & (light < 0.9 * top))[0]
    first_top = np.nonzero(light >= 0.9 * top)[0]
    if first_top.size:
        idx = idx[idx < first_top[0]]
    if idx.size < 2:
        raise RuntimeError("latency calibration: the pulse scan found no rising edge; widen max_latency_s or the pulse")
    A = np.stack([times[idx], np.ones(idx.size)], 1)
    coef, *_ = np.linalg.lstsq(A, light[idx], rcond=None)
    slope, intercept = coef
    t_half = (0.5 * top - intercept) / slope
    latency = t_half + pulse_width_s / 2 - trigger_delay_s
    resid = light[idx] - A @ coef
    s2 = float(resid @ resid) / max(1, idx.size - 2)
    cov = s2 * np.linalg.inv(A.T @ A)
    g = np.array([-(0.5 * top - intercept) / slope**2, -1 / slope])  # d t_half / d (slope, intercept)
    std = math.sqrt(max(float(g @ cov @ g), 0.0) + 0.25 * top_var / slope**2)
    return float(latency), float(std)
