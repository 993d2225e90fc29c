"""The deformable mirror's plan of the identification (:class:`DMPlan`, ``dm.n_across`` > 0): the
calibration on the sensor's spot grid (:func:`sensor_spots`), the plan
(:func:`torchblur.dm.plans.choose_plan`), the sweep (one amplitude per frequency,
:func:`next_amplitude`; each frequency's spot fits on the run's executor while the next is
acquired) and :func:`estimate_mirror` (``Y``, ``D``, the actuators, the registration). Each step:
docs/deformable_mirrors.md, "The run".
"""
from __future__ import annotations

import contextlib
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields, replace
from typing import NamedTuple

import numpy as np
import torch

from torchblur.dm.actuator_fit import fit_actuators
from torchblur.dm.common_noise import common_noise_line, static_column_variance, with_common_variance
from torchblur.config.budget import DM_DARK_FRAMES, DM_STILL_FRAMES, dm_geometry, dm_ladder_plan, dm_plan, dm_still_frames, dm_sweep_size
from torchblur.dm.demux import demultiplex
from torchblur.dm.ladder_fit import PatternLadder, fit_ladder_problems
from torchblur.fit.status import NOT_FITTED, OUT_OF_LADDER
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.plans import SPARSE_MARGIN, driven_spots, static_motion_px
from torchblur.dm.registration import Registration, RegistrationFit, fully_lit, register_and_refit
from torchblur.dm.slope_gains import slope_gains, slope_gains_line, with_slope_gain_stds
from torchblur.dm.spot_fit import PerSpotPSF, crop_problems, fit_spot_problems, pattern_responses
from torchblur.errors import ConfigError, InputTypeError, ParameterError
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.recording import ReplayRig
from torchblur.hardware.serial_dm_rig import open_dm_rig
from torchblur.identify.assemble import timing_phase_std
from torchblur.identify.calibration import MIN_INSIDE, calibrate, check_latency_source
from torchblur.identify.dm_ladder import choose_spot_model, ladder_holds, pattern_ladder, slope_noise
from torchblur.config import IdentifyConfig
from torchblur.identify.dm_record import (SWEEP_KIND, TABLE_KEY, check_recorded_commands, recorded_labels, recorded_plan, resume_seed,
                                          same_table, simulated_frames, sweep_key, table_digest)
from torchblur.identify.record import HARDWARE_LOGGER, LOGGER, RunRecord, run_stage
from torchblur.identify.verdict import LADDER_ON_HADAMARD, ladder_on_hadamard
from torchblur.identify.rigs import open_experiment, session, session_info
from torchblur.image.dark import subtract_dark
from torchblur.image.spots import crop_spots
from torchblur.render.camera import camera_noise_std
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow
from torchblur.rig.dm import SimulatedDMRig
from torchblur.rig.dm_contract import check_dm_rig
from torchblur.rig.factory import build_dm

__all__ = ["DM_DARK_FRAMES", "DM_STILL_FRAMES", "DMPlan", "DMResult", "check_dm_config", "estimate_mirror", "match_spots", "next_amplitude",
           "nominal_growth", "registration_errors", "sensor_config", "sensor_spots", "truth_errors"]

_F64 = torch.float64


@dataclass
class DMResult:
    """What a DM run measured.

    Attributes:
        freq_hz: ``[F]``.
        plan: the :class:`~torchblur.dm.plans.Plan`; ``n_repeats`` frames per exposure and
            pattern; ``plan_info`` (:func:`~torchblur.dm.plans.choose_plan`'s comparison).
        amplitude: ``[F]`` command amplitude; ``power``: ``[F]`` laser power.
        Y, Y_cov: ``[P, 2M, F]`` pattern responses and ``[P, 2M, F, 2, 2]`` their (Re, Im) covariance.
        D, D_cov: ``[2M, N, F]`` and ``[2M, N, F, 2, 2]``.
        actuators: the :class:`~torchblur.dm.actuator_fit.ActuatorTable` (``dc_gain`` relative to ``G``).
        G: ``[2M, N]`` the geometry the actuators were fitted on (px per input unit): the fitted
            registration's (:mod:`torchblur.dm.registration`), the nominal one where that fit did not run.
        G_nominal: ``[2M, N]`` the nominal geometry (the plan's); registration: the
            :class:`~torchblur.dm.registration.RegistrationFit`; support_check: the plan's support
            against the fitted G (:func:`~torchblur.dm.registration.support_check`, None without a fit).
        actuator_xy: ``[N, 2]``.
        n_frames: sweep frames taken; ``n_failed``: spot problems whose fit failed.
        spot_reduced_chi2: ``[P, M, F]`` every spot fit's reduced chi2 (NaN where it failed): about
            1 where the spots' PSFs (Gaussians or measured kernels) and the camera's noise model explain the images.
        timing_s: seconds per stage (``calibration``, ``acquisition``, ``fit_wait``, ``estimation``).
        spot_model: the sweep's spot model (``shifted`` or ``ladder``, :mod:`torchblur.identify.dm_ladder`);
            n_out_of_ladder: spot fits whose motion left the ladder's levels (their responses left out of D, as a
                failed fit's; the verdict says so); slope_noise: the ladder's ``(slope [P, M, 2], slope_cov
                [P, M, 2, 2])`` stage 4 grew the static columns' stds by (:mod:`torchblur.dm.common_noise`), None
                for the shifted still.
        fit_s: ``[F]`` each frequency's spot-fit seconds on its worker (NaN where its task failed), or None;
            frame_rate_hz: the rig's camera frame rate (the recorded camera's on a re-fit; None for an outside
            recording, which does not give it): :mod:`torchblur.identify.keep_up` says from both whether the
            fitting keeps up with the camera.
        truth_D: ``[2M, N, F]`` the simulated rig's D (None on a real rig); ``mirror``: the
            simulated mirror (its true dynamics), or None; ``truth_G``, ``truth_registration``: its
            true geometry and registration, or None.
        log: the run's messages (collected by the runner, :func:`~torchblur.identify.record.collect_log`).
    """

    freq_hz: np.ndarray
    plan: object
    n_repeats: int
    plan_info: dict
    amplitude: np.ndarray
    power: np.ndarray
    Y: np.ndarray
    Y_cov: np.ndarray
    D: np.ndarray
    D_cov: np.ndarray
    actuators: object
    G: np.ndarray
    actuator_xy: np.ndarray
    n_frames: int
    n_failed: int
    timing_s: dict
    spot_reduced_chi2: np.ndarray | None = None
    truth_D: np.ndarray | None = None
    mirror: DeformableMirror | None = None
    log: list = field(default_factory=list)
    G_nominal: np.ndarray | None = None
    registration: RegistrationFit | None = None
    support_check: dict | None = None
    truth_G: np.ndarray | None = None
    truth_registration: Registration | None = None
    spot_model: str = "shifted"
    n_out_of_ladder: int = 0
    slope_noise: tuple | None = None
    fit_s: np.ndarray | None = None
    frame_rate_hz: float | None = None


def match_spots(found_xy: np.ndarray, rest_px: np.ndarray, pitch_px: float) -> np.ndarray:
    """For each of the M valid subapertures (rest positions ``[M, 2]`` px) the index of the
    found spot (``[K, 2]`` px) nearest its rest position; raises :class:`ParameterError`
    naming ``spots`` when one has none within ``pitch_px / 2`` or two share one."""
    d = np.hypot(*(np.asarray(found_xy)[None, :, :] - np.asarray(rest_px)[:, None, :]).transpose(2, 0, 1))  # [M, K]
    idx = d.argmin(1)
    far = np.flatnonzero(d[np.arange(len(idx)), idx] > pitch_px / 2)
    if far.size:
        raise ParameterError(f"spots: no spot found within half a pitch of valid subaperture(s) {far.tolist()} (found {len(found_xy)})")
    if len(set(idx.tolist())) != len(idx):
        raise ParameterError("spots: two valid subapertures share one found spot")
    return idx


def _second_order(f, mode_hz, damping):
    r = np.asarray(f, dtype=np.float64) / mode_hz
    return 1.0 / np.abs(1 - r * r + 2j * damping * r)


def nominal_growth(dm, f_hz: float, f_ref_hz: float | None) -> float:
    """The largest ratio ``|H(f)| / |H(f_ref)|`` (``|H(f)|`` itself when ``f_ref_hz`` is None)
    over the nominal resonances the ``dm`` config allows: mode ``mode_hz (1 + 3 k mode_spread)``,
    k in -1, 0, 1, damping ``damping (1 - 3 damping_spread)`` (the sharpest), gain ``gain (1 + 3
    gain_spread)`` (the prediction of :func:`next_amplitude`)."""
    zeta = dm.damping * max(0.05, 1 - 3 * dm.damping_spread)
    best = 0.0
    for k in (-1.0, 0.0, 1.0):
        mode = dm.mode_hz * (1 + 3 * k * dm.mode_spread)
        h = _second_order(f_hz, mode, zeta)
        best = max(best, h if f_ref_hz is None else h / _second_order(f_ref_hz, mode, zeta))
    return best * (dm.gain * (1 + 3 * dm.gain_spread) if f_ref_hz is None else 1.0)


def next_amplitude(*, target_px: float, motion_per_unit: float, input_limit: float, max_pattern: float) -> float:
    """The command amplitude that moves the largest spot ``target_px`` (``motion_per_unit``:
    the predicted largest spot motion per unit amplitude, px), at most ``input_limit /
    max_pattern``."""
    amp = target_px / motion_per_unit if motion_per_unit > 0 else math.inf
    return float(min(amp, input_limit / max_pattern))


# DM_DARK_FRAMES, dm_still_frames (torchblur.config.budget): the calibration's dark and still frames.

def sensor_config(cfg):
    """``cfg`` with its ``spots`` section on the sensor's grid (``wfs``): the spots the calibration crops."""
    n = int(cfg.wfs.n_across)
    spots = replace(cfg.spots, rows=n, cols=n, pitch_px=float(cfg.wfs.pitch_px), sigma_px=float(cfg.wfs.sigma_px))
    return replace(cfg, spots=spots)


def _calibrate(cfg, rig, wfs, exp=None):
    """Stage 1 (module docstring): the calibration on the sensor's spot grid (from the recording
    ``exp`` where it holds it); its spots in valid-subaperture order: :func:`sensor_spots`."""
    size = dm_sweep_size(cfg)
    n_still = dm_still_frames(size["frames"], size["frame_shape"])
    cal = calibrate(sensor_config(cfg), rig, exp, n_dark=DM_DARK_FRAMES, n_still=n_still,
                    spot_layout=wfs.rest_px)  # spots cropped on the sensor's layout; each spot's PSF (fit.psf) (issue 23)
    n = int(cfg.wfs.n_across)
    LOGGER.info(f"dm spots: {len(cal.spots)} found, matched to the {wfs.n_valid} valid subapertures (the other "
                f"{n * n - wfs.n_valid} cells of the {n}x{n} grid are outside the pupil)")
    return cal


def sensor_spots(cal, wfs):
    """``(order [M], psf, offset [M, 2], size)``: the calibration's spot matched to each valid subaperture
    (:func:`match_spots`), their PSFs (:func:`_spot_psf`) and crops in that order."""
    order = torch.as_tensor(match_spots(cal.spots.psf.center.numpy(), wfs.rest_px, wfs.pitch_px))
    return order, _spot_psf(cal, order), cal.spots.offset[order], cal.spots.size


def _spot_psf(cal, order):
    """The PSF of every valid subaperture's spot (in ``order``): its Gaussian, or where the
    calibration measured kernels (``fit.psf`` kernel, or auto and a spot's Gaussian fails
    :func:`~torchblur.image.psf_from_still.psf_from_still`'s test) a
    :class:`~torchblur.dm.spot_fit.PerSpotPSF`: the kernel for each spot whose still chose it."""
    gauss = cal.spots.psf_in_crops()[order]
    sk = cal.spot_kernels
    if sk is None:
        return gauss
    use = torch.tensor([st is not None and st.kind == "kernel" for st in sk.still], dtype=torch.bool)[order]
    LOGGER.info(f"dm spots psf: the measured kernel for {int(use.sum())} of {len(use)} spots, the Gaussian for the others "
                f"(each spot's own still decides; the kernels' own noise is in the stds)")
    return PerSpotPSF(gauss, KernelPSF(sk.psf.kernel[order]), use)


#: px: a spot whose static motion under its pattern at the ladder's top level is below this barely
#: changes shape; where its ladder fit left the levels (its shape's command is then the data's noise,
#: often beyond the levels) it is fitted by its shifted still instead (:func:`_fit_frequency`)
STILL_ENOUGH_PX = 0.2


class FrequencyFit(NamedTuple):
    """One frequency's spot fits (:func:`_fit_frequency`): ``Y [P, 2M]``, ``Y_cov [P, 2M, 2, 2]``, the
    failed fits, every fit's reduced chi2 ``[P, M]``, the fits out of the ladder, those refitted by the
    shifted still, and the fit's wall seconds."""

    Y: np.ndarray
    Y_cov: np.ndarray
    failed: int
    chi2: np.ndarray
    out_of_ladder: int
    refitted: int
    seconds: float


def _fit_frequency(frames, window, omega, amplitude, power, cal, psf, offset, size, jitter_s, fit_options, ladder=None, driven=None):
    """One frequency's pattern responses: frames ``[P, E*R, H, W]`` ADU -> :class:`FrequencyFit` (``Y [P, 2M]``,
    ``Y_cov [P, 2M, 2, 2]``, failed, reduced chi2 ``[P, M]`` of every spot fit, out of the ladder, refitted, seconds). ``psf``: the spots'
    Gaussians or :class:`~torchblur.dm.spot_fit.PerSpotPSF` (:func:`_spot_psf`, at power 1); ``ladder``: the
    patterns' :class:`~torchblur.dm.ladder_fit.PatternLadder` (``dm_plan.spot_model`` ladder: the spots
    fitted with it, :func:`~torchblur.dm.ladder_fit.fit_ladder_problems`; ``out of the ladder`` counts
    the spot fits whose motion left its levels, their responses NaN: left out of D, except those of a
    spot that barely moves under the pattern (:data:`STILL_ENOUGH_PX`), ``refitted`` by the shifted
    ``psf``), or None (the shifted ``psf``; ``refitted`` 0). ``driven``: ``[P, M]`` bool, the (pattern, spot) problems
    the plan measures (:func:`~torchblur.dm.plans.driven_spots`; the others are not fitted, their responses NaN,
    neither failed nor in the chi2), or None (every one)."""
    t0 = time.perf_counter()
    e = subtract_dark(frames.to(_F64), cal.dark) * cal.gain
    crops, in_frame = crop_problems(e[:, None], offset, size)  # [P, 1, M, ER, h, w]
    mask = (in_frame & ~crop_spots(cal.dark.hot_pixels, offset, size))[:, None]  # the hot pixels of every crop left out
    n = window.shape[-1]
    phase_var = float(timing_phase_std(omega, jitter_s, cal.latency_std_s, n)) ** 2
    refit = 0
    only = None if driven is None else torch.as_tensor(np.asarray(driven, dtype=bool))[:, None, :]  # [P, 1, M]
    if ladder is None:
        fits = _shifted_fits(crops, window, omega, power, cal, psf, mask, fit_options, only)
    else:
        amp = torch.full((crops.shape[0], 1), float(amplitude), dtype=_F64)
        # pixel weights from the camera noise of each crop's 3 x 3 local mean (a pixel's own value would bias the amplitudes low)
        local = torch.nn.functional.avg_pool2d(crops.flatten(0, -3), 3, stride=1, padding=1, count_include_pad=False).reshape(crops.shape)
        fits = _fit_spots(crops, ladder, window, torch.tensor([omega], dtype=_F64), amp, fitter=fit_ladder_problems, power=float(power),
                          noise_std=camera_noise_std(local, cal.read_noise_e), mask=mask, device=fit_options["device"], only=only)
        fits, refit = _still_spots_refitted(fits, ladder, crops, window, omega, power, cal, psf, mask, fit_options)
    Y, Yc = pattern_responses(fits, amplitude, phase_var=phase_var)
    chi2 = fits.reduced_chi2.reshape(fits.reduced_chi2.shape[0], -1).numpy()  # [P, M] (F = 1)
    beyond = ((fits.flags & OUT_OF_LADDER) != 0).reshape(fits.flags.shape[0], -1).numpy()  # [P, M]
    # a motion beyond the ladder's levels is the end cubics extrapolated: no error model holds there, so its
    # responses are left out of D like a failed fit's (counted, and the verdict's ladder rule sees them)
    Y[np.concatenate([beyond, beyond], 1)] = np.nan
    Yc[np.concatenate([beyond, beyond], 1)] = np.nan
    failed = int(((fits.status != 0) & (fits.status != NOT_FITTED)).sum())
    return FrequencyFit(Y[..., 0], Yc[:, :, 0], failed, chi2, int(beyond.sum()), refit, time.perf_counter() - t0)


def _shifted_fits(crops, window, omega, power, cal, psf, mask, fit_options, only=None):
    """The shifted still's :class:`~torchblur.dm.spot_fit.SpotFits` of ``crops [P, 1, M, E*R, h, w]`` (electrons),
    ``window [P, 1, E*R]``: each spot its ``psf`` (Gaussian, or :class:`~torchblur.dm.spot_fit.PerSpotPSF` with the
    kernels' own noise in the stds) scaled to laser power ``power``, weights from the camera's noise model
    (``only``: ``[P, 1, M]`` bool, the problems fitted, None: every one)."""
    kernel_noise = None
    if isinstance(psf, PerSpotPSF):
        p = psf.scaled(power)
        # the kernels' own noise: the still frames' light against this point's (its exposures at laser power `power`)
        kernel_noise = cal.spot_kernels.kernel_noise_factor(window.duration.to(_F64) * power).reshape(-1, 1, 1)  # [P, 1, 1]
    else:
        p = GaussianPSF(psf.center, psf.cov, psf.amplitude * power)
    # weights from the camera's noise model: the fitter refits with the first fit's expected signal
    return _fit_spots(crops, p, window, torch.tensor([omega], dtype=_F64), noise=cal.noise, mask=mask, kernel_noise=kernel_noise,
                      only=only, **fit_options)


def _still_spots_refitted(fits, ladder, crops, window, omega, power, cal, psf, mask, fit_options):
    """``(fits, n)``: the ladder's ``fits`` with every fit that left the ladder on a spot whose static motion at the
    pattern's top level is below :data:`STILL_ENOUGH_PX` (``ladder.slope``) replaced by its shifted still's
    (:func:`_shifted_fits`, run on the patterns that have one), and how many. Such a spot barely changes shape, so
    its still describes it; its ladder fit's shape command is the data's noise (a spot of a dead actuator, or one
    at the edge of its actuators' reach on a sparse plan) and leaving it out would cost D the entry."""
    if ladder.slope is None:
        return fits, 0
    top = ladder.levels.abs().amax(-1).cpu()  # [P]
    still = ladder.slope.cpu().norm(dim=-1) * top[:, None] < STILL_ENOUGH_PX  # [P, M]
    redo = ((fits.flags[:, 0] & OUT_OF_LADDER) != 0) & still  # [P, M]
    if not bool(redo.any()):
        return fits, 0
    pp = torch.nonzero(redo.any(1)).reshape(-1)
    sh = _shifted_fits(crops[pp], window[pp], omega, power, cal, psf, mask, fit_options, redo[pp][:, None])
    take = redo[pp][:, None]  # [p', 1, M]

    def merged(a, b):
        out = a.clone()
        out[pp] = torch.where(take.reshape(take.shape + (1,) * (a.dim() - 3)), b.to(a.dtype), a[pp])
        return out
    return replace(fits, **{f.name: merged(getattr(fits, f.name), getattr(sh, f.name)) for f in fields(fits)
                            if isinstance(getattr(fits, f.name), torch.Tensor)}), int(redo.sum())


def _fit_spots(crops, psf, window, omega, *args, device: str = "cpu", fitter=fit_spot_problems, **kw):
    """``fitter`` (:func:`~torchblur.dm.spot_fit.fit_spot_problems`, or the ladder's
    :func:`~torchblur.dm.ladder_fit.fit_ladder_problems`) on ``device`` (``fit.device``): the crops,
    PSFs (or the ladder), window, omega, mask and kernel noise moved there, the
    :class:`~torchblur.dm.spot_fit.SpotFits` back on the CPU (``.to`` of a tensor already there is itself)."""
    dev = torch.device(device)

    def move(x):
        if isinstance(x, PerSpotPSF):
            return PerSpotPSF(move(x.gaussian), move(x.kernel), x.use_kernel.to(dev))
        if isinstance(x, PatternLadder):
            return replace(x, **{f.name: getattr(x, f.name).to(dev) for f in fields(x)})
        return x.to(dev) if isinstance(x, (torch.Tensor, GaussianPSF, KernelPSF, ExposureWindow)) else x

    fits = fitter(move(crops), move(psf), move(window), move(omega), *map(move, args), **{k: move(v) for k, v in kw.items()})
    return replace(fits, **{f.name: v.cpu() for f in fields(fits) if isinstance(v := getattr(fits, f.name), torch.Tensor)})


def _acquire_frequency(rig, plan, f, amp, te, offset_s, R, settle_s, power, latency_s, trigger_delay_s):
    """Every pattern at frequency ``f``: frames ``[P, E*R, H, W]`` and their windows ``[P, 1, E*R]``
    (a frame's exposure starts ``trigger_delay_s + latency_s`` after its trigger). The rig is
    called by keyword (a recording stores the arguments by name)."""
    frames, starts, durs = [], [], []
    for row in plan.patterns:
        cap = rig.pattern_sine(pattern=row, freq_hz=f, amplitude=amp, exposures_s=te, trigger_offset_s=offset_s, n_repeats=R,
                               settle_s=settle_s, power=power)
        frames.append(cap.frames.reshape((-1,) + tuple(cap.frames.shape[-2:])))
        starts.append(cap.trigger_time_s.reshape(-1) + trigger_delay_s + latency_s)
        durs.append(cap.exposure_s.reshape(-1))
    window = ExposureWindow(torch.stack(starts)[:, None], torch.stack(durs)[:, None])
    return torch.stack(frames), window


def _fit_options(cfg) -> dict:
    """The spot fits' options of ``cfg.fit`` (``device``: where :func:`_fit_spots` runs them)."""
    return {"optimizer": cfg.fit.optimizer, "loss": cfg.fit.loss, "fit_scale": bool(cfg.fit.fit_scale),
            "fit_background": bool(cfg.fit.fit_background), "device": cfg.fit.device}


#: the amplitude at frequency k is predicted from the fit of frequency k - AMPLITUDE_LAG (waited
#: for): one frequency's fit overlaps the next one's acquisition, and the run does not depend on
#: which fits happen to have finished (the same seed gives the same run).
AMPLITUDE_LAG = 2


def _amplitude_reference(futures, k: int, M: int):
    """``(i, largest |Y| per unit amplitude of frequency i)`` for the amplitude of frequency
    ``k``: the latest frequency ``i <= k - AMPLITUDE_LAG`` whose fit has a finite response
    (waiting for those fits), or None (then the nominal prediction)."""
    for i in range(min(k - AMPLITUDE_LAG, len(futures) - 1), -1, -1):
        done = _fit_outcome(futures[i])[0]
        if done is not None and np.isfinite(done[0]).any():
            Yi = done[0]
            return i, float(np.nanmax(np.hypot(np.abs(Yi[:, :M]), np.abs(Yi[:, M:]))))
    return None


def _fit_outcome(future):
    """``(result, None)`` of one frequency's fit (:func:`_fit_frequency`), or where its task
    raised (a lost worker, a failed task on a cluster) ``(None, message)``: reported, not lost."""
    try:
        return future.result(), None
    except Exception as exc:  # noqa: BLE001 - one frequency's failed task is flagged, the others kept
        return None, f"{type(exc).__name__}: {exc}"


def _failed_frequency(P: int, M2: int, n_fits: int):
    """A frequency whose fit task failed: NaN responses and covariances, its ``n_fits`` spot fits (the driven ones) failed."""
    return FrequencyFit(np.full((P, M2), np.nan + 0j), np.full((P, M2, 2, 2), np.nan), n_fits, np.full((P, M2 // 2), np.nan), 0, 0,
                        math.nan)


def _sweep(cfg, rig, plan, R, G, cal, psf, offset, size, exp=None, executor=None, ladder=None):
    """Stage 3 (module docstring): ``(amplitude [F], power [F], Y [P, 2M, F], Y_cov, failed, chi2, frames, out of the
    ladder, t_acq, t_wait, fit seconds [F])``; ``ladder``: the patterns' PatternLadder (the spot model ladder) or None.
    With a recording ``exp`` each frequency is one group (:mod:`torchblur.identify.dm_record`): taken from
    it, at its recorded amplitude, where it holds it, else acquired and recorded. Each frequency's
    spot fits go to ``executor`` (any :class:`concurrent.futures.Executor`, Dask's
    ``client.get_executor()`` included; default: one worker thread) while the next is acquired."""
    freqs = cfg.frequencies_hz()
    F, P, M2 = len(freqs), plan.n_patterns, G.shape[0]
    c, s = cfg.camera, cfg.sweep
    motion_static = static_motion_px(plan, G)
    limit = min(math.inf if cfg.dm.input_limit is None else float(cfg.dm.input_limit), cal.input_limit)  # and the rig's RANGE?
    amps, powers, futures = np.zeros(F), np.zeros(F), []
    driven = driven_spots(plan)  # [P, M]: the spot problems the plan measures, the same at every frequency
    t_acq = 0.0
    with fit_pool(executor) as pool:
        for k, f in enumerate(freqs):
            done_ref = _amplitude_reference(futures, k, M2 // 2)
            rec = recorded_labels(exp, sweep_key(k))
            if rec is not None:
                amps[k] = float(rec["amplitude"])
            else:
                if done_ref is None or not math.isfinite(done_ref[1]):
                    motion = motion_static * nominal_growth(cfg.dm, f, None)
                else:
                    motion = done_ref[1] * nominal_growth(cfg.dm, f, freqs[done_ref[0]])
                lim_f = min(limit, cal.limit_at(f))  # the range and, at f, the amplifier's slew limit
                amps[k] = next_amplitude(target_px=float(cfg.excitation.target_px), motion_per_unit=motion, input_limit=lim_f,
                                         max_pattern=float(np.abs(plan.patterns).max()))
                if lim_f < limit and amps[k] * float(np.abs(plan.patterns).max()) >= lim_f * (1 - 1e-9):
                    LOGGER.info(f"dm sweep: {f:.4g} Hz limited by the slew limit {cal.drive.slew:.6g} input units/s "
                                f"(largest command {lim_f:.4g} there)")
            te = [float(e) / f for e in s.exposures]
            powers[k] = c.peak_fraction * cal.full_adu * cal.gain / (cal.peak_rate * max(te))
            delay = float(rec["trigger_delay_s"]) if rec is not None else float(getattr(rig, "trigger_delay_s", c.trigger_delay_s))
            labels = {"freq_hz": float(f), "amplitude": float(amps[k]), "power": float(powers[k]), "point": k,
                      "trigger_delay_s": delay, "n_patterns": P, "n_repeats": R}
            t0 = time.perf_counter()
            frames, window = run_stage(exp, sweep_key(k), SWEEP_KIND, rig, lambda r: _acquire_frequency(
                r, plan, f, float(amps[k]), te, float(s.trigger_phase_rad) / (2 * math.pi * f), R, s.settle_s, float(powers[k]),
                cal.latency_s, delay), labels)
            t_acq += time.perf_counter() - t0
            futures.append(pool.submit(_fit_frequency, frames, window, 2 * math.pi * f, float(amps[k]), float(powers[k]), cal, psf,
                                       offset, size, float(c.jitter_s), _fit_options(cfg), ladder, driven))
            LOGGER.info(f"dm sweep: {f:.4g} Hz, amplitude {amps[k]:.4g}, power {powers[k]:.3g}, {P} patterns x "
                        f"{len(te)} exposures x {R} repeats ({k + 1}/{F}{', recorded' if rec is not None else ''})")
        t0 = time.perf_counter()
        Y, Y_cov, failed, chi2, out, fit_s = collect_fits(freqs, futures, P, M2, driven)
        t_wait = time.perf_counter() - t0
    return amps, powers, Y, Y_cov, failed, chi2, P * F * len(s.exposures) * R, out, t_acq, t_wait, fit_s


def fit_pool(executor=None):
    """``executor`` as a context (left open), or one worker thread (on a busy machine two OpenMP threads were 12x slower)."""
    return ThreadPoolExecutor(max_workers=1) if executor is None else contextlib.nullcontext(executor)


def collect_fits(freqs, futures, P: int, M2: int, driven=None):
    """The :func:`_fit_frequency` of every frequency (``futures``), waited for: ``(Y [P, 2M, F], Y_cov [P, 2M, F, 2, 2], failed,
    chi2 [P, M, F], out of the ladder, fit seconds [F])``; a task that raised: NaN responses and seconds, its spot fits counted
    failed (logged): the ``driven`` ``[P, M]`` ones the task was given (None: all ``P * M``), as the verdict counts them."""
    n_fits = P * (M2 // 2) if driven is None else int(np.count_nonzero(driven))
    outcomes = [_fit_outcome(fu) for fu in futures]
    for f, (_, why) in zip(freqs, outcomes):
        if why is not None:
            LOGGER.info(f"dm sweep: the spot fits of {f:.4g} Hz failed on the executor ({why}): its responses are NaN and "
                        f"its {n_fits} spot fits counted failed")
    results = [r if r is not None else _failed_frequency(P, M2, n_fits) for r, _ in outcomes]
    out, refit = sum(r.out_of_ladder for r in results), sum(r.refitted for r in results)
    if refit:
        LOGGER.info(f"dm spot model: {refit} spot fits that left the ladder's levels on spots barely moving under their pattern "
                    f"(under {STILL_ENOUGH_PX:g} px at its top level) fitted by the spot's shifted still instead")
    if out:
        LOGGER.info(f"dm spot model: {out} spot fits' motion left the ladder's levels (flagged; their responses extrapolate the "
                    f"static images: raise dm_plan.ladder_reach)")
    return (np.stack([r.Y for r in results], -1), np.stack([r.Y_cov for r in results], 2), sum(r.failed for r in results),
            np.stack([r.chi2 for r in results], -1), out, np.array([r.seconds for r in results]))


def check_dm_config(cfg) -> None:
    """Refuse a ``cfg`` that is not a DM run's :class:`~torchblur.config.IdentifyConfig`
    (InputTypeError naming ``cfg``; ConfigError naming ``dm.n_across`` when it is 0)."""
    if not isinstance(cfg, IdentifyConfig):
        raise InputTypeError(f"cfg: expected an IdentifyConfig (torchblur.load_config), got {type(cfg).__name__}")
    if not cfg.dm.enabled:
        raise ConfigError("dm.n_across: 0, not a DM config; set the mirror's dm section (configs/identify_dm.yaml)")


class DMPlan:
    """The deformable mirror's plan of the identification's stages (``dm.n_across`` > 0; module
    docstring), registered as ``"dm"`` in :data:`torchblur.identify.pipeline.PLANS`: :meth:`open`
    (the rig, the recording and its session), :meth:`calibrate` (stage 1), :meth:`sweep` (stages
    2 and 3: each frequency's spot fits submitted to ``run.executor``, default one worker thread,
    while the next frequency is acquired), :meth:`assemble` (stage 4, the actuators' models
    included, so the runner's model stages are not this plan's) and :meth:`result` (a :class:`DMResult`)."""

    kind = "dm"
    supports_direct = False
    model_stages = ()  # the actuators' models are fitted in assemble (estimate_mirror)
    slope_noise = None  # the ladder's (slope, slope_cov) once the sweep built one (stage 4's common error)
    fit_s = None  # each frequency's spot-fit seconds once the sweep is done

    @staticmethod
    def check(cfg, rig) -> None:
        """Refuse ``cfg`` that is not a DM run's (:func:`check_dm_config`) and a lab's ``rig``
        that breaks the contract (:func:`~torchblur.rig.dm_contract.check_dm_rig`) or has no
        latency source, before any frame (docs/dm_rig.md)."""
        check_dm_config(cfg)
        if rig is not None and not isinstance(rig, ReplayRig):
            check_dm_rig(rig, cfg)
            check_latency_source(cfg, rig)

    @contextlib.contextmanager
    def open(self, cfg, rig, *, progress: bool, record, base_dir: str | None = None, executor=None):
        """The :class:`~torchblur.identify.record.RunRecord` of a DM run on ``rig`` (None: the
        config's rig: the simulated DM rig, or with ``rig.kind=serial`` a
        :class:`~torchblur.hardware.serial_dm_rig.SerialDMRig` on ``rig.port`` and ``rig.frames``,
        closed after the run, its link's statistics logged) recorded in ``record``
        (:mod:`torchblur.identify.dm_record`), inside the recording's session."""
        own = rig is None and cfg.rig.kind == "serial"
        if own:
            rig = open_dm_rig(cfg, log=HARDWARE_LOGGER.info)
        try:
            if own:  # the config was checked before (identify), the rig's contract by open_dm_rig
                check_latency_source(cfg, rig)
            with self._session(cfg, rig, progress, record, base_dir) as run:
                run.executor = executor
                yield run
        finally:
            if own:
                rig.close()
        if own:
            st = rig.stats  # its events were logged as they came
            HARDWARE_LOGGER.info(f"serial link: {rig!r}: {st['calls']} calls, {st['retries']} retried, {st['resets']} controller resets, "
                                 f"{st['reconnects']} reconnects, {st['stale_discarded']} stale frames discarded")

    @contextlib.contextmanager
    def _session(self, cfg, rig, progress, record, base_dir):
        """:meth:`open` once the rig is open: the simulated mirror (the model's geometry, and the
        truth where every frame is simulated), the recording and its session."""
        self.model_mirror, self.wfs, sim = build_dm(cfg, base_dir=base_dir)
        exp = open_experiment(record, cfg, sim if rig is None else rig)
        resumed = exp is not None and exp.writable and bool(exp.meta["sessions"])
        if rig is None and resumed:
            sim = build_dm(cfg, base_dir=base_dir, rig_seed=resume_seed(int(cfg.seed), len(exp.meta["sessions"])))[2]
        rig = sim if rig is None else rig
        digest = table_digest(cfg, base_dir)
        simulated = simulated_frames(isinstance(rig, SimulatedDMRig), exp)
        if simulated and exp is not None and not same_table(exp, digest):
            if exp.writable:
                exp.close()
                raise RecordingError(f"dm.actuator_table: {cfg.dm.actuator_table} is not the file the recording {exp.path} was "
                                     f"simulated with (its SHA-256 differs); resume with that file, or record anew")
            simulated = False
            LOGGER.info(f"dm: no simulated truth: {cfg.dm.actuator_table} is not the actuator table the recording was simulated "
                        f"with (its SHA-256 differs)")
        self.truth_rig = (rig if isinstance(rig, SimulatedDMRig) else sim) if simulated else None
        with session(exp, session_info(cfg, rig, **{TABLE_KEY: digest})):
            yield RunRecord(cfg=cfg, rig=rig, exp=exp, progress=progress)

    def calibrate(self, run) -> None:
        """Stage 1: ``run.cal`` and every valid subaperture's spot PSF, crop offset and size."""
        t0 = time.perf_counter()
        run.cal = _calibrate(run.cfg, run.rig, self.wfs, run.exp)
        order, self.psf, self.offset, self.size = sensor_spots(run.cal, self.wfs)
        self.inside = (run.cal.spots.inside_fraction >= MIN_INSIDE)[order]  # [M] the spots mostly in the frame
        run.timing["calibration"] = time.perf_counter() - t0

    def sweep(self, run) -> None:
        """Stages 2 and 3: the plan (the recorded one where the recording holds it) and the sweep
        (``run.acquisition``: :func:`_sweep`'s amplitudes, powers, pattern responses and spot-fit counts)."""
        cfg, exp = run.cfg, run.exp
        self.G = dm_geometry(cfg)  # the geometry does not depend on the dynamics (nor on dm.actuator_table)
        freqs = np.asarray(cfg.frequencies_hz())
        plan, R, self.info = dm_plan(cfg)
        t0 = time.perf_counter()
        limit = min(math.inf if cfg.dm.input_limit is None else float(cfg.dm.input_limit), run.cal.input_limit)
        self.spot_model = choose_spot_model(cfg, run.rig, exp, plan.patterns, self.G, run.cal, self.offset, self.size, self.inside,
                                            limit)
        threshold = float(cfg.dm_plan.support_threshold)
        ladder_plan = dm_ladder_plan(cfg) if self.spot_model == "ladder" else None
        if ladder_plan is not None and ladder_plan[0].kind != plan.kind:  # auto's sparse plan for the ladder
            plan, R, self.info, threshold = ladder_plan
            LOGGER.info(f"dm plan: sparse, not hadamard (auto, and the spots change shape: on a pattern that moves several of the "
                        f"actuators a spot sees, the ladder ties the spot's shape to their common command and pulls each "
                        f"actuator's response toward its neighbours'; on a sparse plan a spot sees one; seen at {threshold:g} of the "
                        f"largest displacement, {SPARSE_MARGIN:g} x dm_plan.support_threshold, for a misregistered mirror; "
                        f"docs/deformable_mirrors.md, \"The plans\")")
        self.plan, self.R = recorded_plan(exp, plan, R, self.G, threshold)
        if exp is not None and exp.writable:
            check_recorded_commands(exp, math.inf if cfg.dm.input_limit is None else float(cfg.dm.input_limit))
        run.say(f"dm plan: {self.plan.kind}, {self.plan.n_patterns} patterns x {len(freqs)} frequencies x {len(cfg.sweep.exposures)} "
                f"exposures x {self.R} repeats = {self.plan.n_frames(len(freqs), len(cfg.sweep.exposures), self.R)} frames; frames for "
                f"the same accuracy vs one at a time: {self.info['cost_ratio_to_one_at_a_time']:.3f}")
        if ladder_on_hadamard(self.spot_model, self.plan.kind):  # said before the holds and the sweep, not only in the verdict
            LOGGER.warning(f"dm plan: hadamard with the ladder spot model (dm_plan.kind={cfg.dm_plan.kind}, or the recording's "
                           f"plan): this run will end exit 4, {LADDER_ON_HADAMARD}")
        ladder = None
        if self.spot_model == "ladder":
            holds = ladder_holds(cfg, run.rig, exp, self.plan.patterns, self.G, run.cal, self.offset, self.size, limit)
            ladder = pattern_ladder(holds, run.cal, self.offset, self.size)
        self.slope_noise = slope_noise(ladder)
        run.timing["calibration"] += time.perf_counter() - t0
        out = _sweep(cfg, run.rig, self.plan, self.R, self.G, run.cal, self.psf, self.offset, self.size, exp, executor=run.executor,
                     ladder=ladder)
        run.acquisition, (run.timing["acquisition"], run.timing["fit_wait"]), self.fit_s = out[:8], out[8:10], out[10]

    def fit(self, run) -> None:
        """Nothing left: every frequency's spot fits ran on the executor during :meth:`sweep`."""

    def assemble(self, run) -> None:
        """Stage 4: ``D (jw)``, the actuators' table, the registration and the support check
        (:func:`estimate_mirror`)."""
        t0 = time.perf_counter()
        Y, Y_cov = run.acquisition[2:4]
        self.estimate = estimate_mirror(run.cfg, np.asarray(run.cfg.frequencies_hz()), Y, Y_cov, self.plan, self.G, self.wfs,
                                        self.model_mirror.actuator_xy, slope_noise=self.slope_noise)
        run.timing["estimation"] = time.perf_counter() - t0
        if run.exp is not None:
            st = run.exp.stats
            run.say(f"recording: {st['groups_written']} group(s) written ({st['write_s']:.2f} s), {st['groups_reused']} reused, in "
                    f"{run.exp.path}")

    def result(self, run) -> DMResult:
        """The run's :class:`DMResult` (the simulated truth where every frame was simulated)."""
        freqs = np.asarray(run.cfg.frequencies_hz())
        amps, powers, Y, Y_cov, failed, chi2, n_frames, out = run.acquisition
        D, D_cov, table, reg, support = self.estimate
        truth = self.truth_rig
        return DMResult(freq_hz=freqs, plan=self.plan, n_repeats=self.R, plan_info=self.info, amplitude=amps, power=powers, Y=Y,
                        Y_cov=Y_cov, D=D, D_cov=D_cov, actuators=table, G=reg.G, actuator_xy=self.model_mirror.actuator_xy,
                        n_frames=n_frames, n_failed=failed, spot_reduced_chi2=chi2, timing_s=run.timing,
                        spot_model=self.spot_model, n_out_of_ladder=out, slope_noise=self.slope_noise, fit_s=self.fit_s,
                        frame_rate_hz=getattr(run.rig, "frame_rate_hz", None),
                        truth_D=truth.truth_D(freqs) if truth is not None else None, mirror=truth.mirror if truth is not None else None,
                        G_nominal=self.G, registration=reg, support_check=support,
                        truth_G=truth.geometry if truth is not None else None,
                        truth_registration=truth.registration if truth is not None else None)


def estimate_mirror(cfg, freqs, Y, Y_cov, plan, G, wfs, actuator_xy, slope_noise=None):
    """Stage 4 (module docstring), one function for a live run and an outside recording: the
    pattern responses ``Y [P, 2M, F]`` demultiplexed into ``D (jw)``, every actuator fitted on the
    nominal ``G``, the mirror's registration fitted to D0 and the actuators fitted again on the
    fitted G (:func:`~torchblur.dm.registration.register_and_refit`), their ``dc_gain`` stds grown by
    the slope rows' own gain scatter (:mod:`torchblur.dm.slope_gains`). ``slope_noise``: the ladder
    spot model's ``(slope [P, M, 2], slope_cov [P, M, 2, 2])``, whose error common to every frequency
    grows the static columns' and ``dc_gain``'s stds before the registration sees them
    (:mod:`torchblur.dm.common_noise`); None for the shifted still. Returns ``(D, D_cov, table,
    registration, support_check)``."""
    D, D_cov = demultiplex(Y, Y_cov, plan.patterns, plan.support)
    table = fit_actuators(freqs, D, D_cov, G, actuator_xy=actuator_xy)
    common = None
    if slope_noise is not None:
        common = static_column_variance(*slope_noise, plan.patterns, plan.support, table.static_column)
        table = with_common_variance(table, common, G)
        LOGGER.info(common_noise_line(common, table))
    table, reg, support = register_and_refit(freqs, D, D_cov, table, wfs, actuator_xy, float(cfg.dm.coupling),
                                             support=plan.support, threshold=float(cfg.dm_plan.support_threshold))
    if common is not None and reg.ok:
        table = with_common_variance(table, common, reg.G)
    gains = slope_gains(table.static_column, table.static_column_std, reg.G, table.dc_gain, np.tile(fully_lit(wfs), 2))
    LOGGER.info(slope_gains_line(gains))
    return D, D_cov, with_slope_gain_stds(table, gains), reg, support


def truth_errors(res: DMResult) -> dict | None:
    """The run's errors against the simulated mirror (None on a real rig): the largest relative
    error of every live actuator's ``mode_hz``, ``damping`` and ``dc_gain`` (and in stds:
    the largest ``*_max_z``, the rms ``*_rms_z``, about 1 where the stds hold), the rms error of the measured D0 over the largest |D0| element, and whether the
    dead actuators (and only they) are reported dead."""
    if res.mirror is None:
        return None
    m, a = res.mirror, res.actuators
    live = ~m.dead
    status = np.asarray(a.status)
    out = {}
    for name, est, std, true in (("mode_hz", a.mode_hz, a.mode_hz_std, m.mode_hz), ("damping", a.damping, a.damping_std, m.damping),
                                 ("dc_gain", a.dc_gain, a.dc_gain_std, m.gain)):
        out[f"{name}_max_rel_error"] = float(np.nanmax(np.abs(est[live] / true[live] - 1))) if np.isfinite(est[live]).all() else math.nan
        z = (est[live] - true[live]) / std[live]
        out[f"{name}_max_z"] = float(np.nanmax(np.abs(z)))
        out[f"{name}_rms_z"] = float(np.sqrt(np.nanmean(z**2)))  # about 1 where the stds hold
    D0 = (res.G if res.truth_G is None else res.truth_G) * m.gain
    out.update(registration_errors(res))
    out["D0_rms_error_over_max"] = float(np.sqrt(np.mean((a.static_column - D0) ** 2)) / np.abs(D0).max())
    out["dead_reported_dead"] = bool(np.all(status[m.dead] == "dead"))
    out["live_reported_dead"] = np.flatnonzero(live & (status == "dead")).tolist()
    return out


def registration_errors(res: DMResult) -> dict:
    """The fitted registration's errors against the simulated truth (``registration_*_error``:
    shift x/y in actuator pitches, rotation in degrees, magnification and coupling as differences;
    ``registration_*_z``: each over its std); empty without a truth or a fit."""
    fit, true = res.registration, res.truth_registration
    if fit is None or true is None or not fit.ok:
        return {}
    r = fit.registration
    c_true = float(res.mirror.coupling) if true.coupling is None else true.coupling
    errs = {"shift_x": r.shift_x - true.shift_x, "shift_y": r.shift_y - true.shift_y, "rotation_deg": r.rotation_deg - true.rotation_deg,
            "magnification": r.magnification - true.magnification, "coupling": r.coupling - c_true}
    out = {f"registration_{k}_error": float(v) for k, v in errs.items()}
    out.update({f"registration_{k}_z": float(v / fit.std[k]) for k, v in errs.items()})
    return out
