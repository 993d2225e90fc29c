"""The sine plan (``excitation.kind=sine``): the sweep, fit and assemble stages of a run that
drives one sine per point.

For each input in turn and each frequency: drive ``A sin(w t)``, wait out the transients and
take every exposure of the point (``sweep.exposures`` fractions of the period from one
trigger phase, :func:`~torchblur.design.windows.dual_exposure_windows`; several images per
point). The amplitude follows the response so the spot moves ``excitation.target_px`` (from
the closed-form moments of the point's first exposure; up to three tries). Every completed
point goes to the chunked background fit at once (:class:`~torchblur.identify.fitting.ChunkFitter`);
the fit stage collects it and the assemble stage makes the FrequencyResponse.

Problems per point: one (the spot, the whole frame) or K (one crop per spot of a grid).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import torch

from torchblur.design.windows import check_design, dual_exposure_windows
from torchblur.fit.sinusoid import STATUS, fit_sinusoid
from torchblur.fit.status import NO_MOTION
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.recording import _bind
from torchblur.identify.assemble import assemble_mimo, assemble_siso, truth_of
from torchblur.identify.calibration import MIN_INSIDE
from torchblur.identify.drive import at_limit, is_limited, limited_summary
from torchblur.identify.fitting import ChunkFitter, concat_fits, squeeze_problems
from torchblur.identify.model import fit_direct_model
from torchblur.identify.record import progress_bar
from torchblur.identify.result import IdentificationResult
from torchblur.image.moments import image_moments, moments_along, sinusoid_from_moments
from torchblur.image.preprocess import subtract_dark
from torchblur.image.spots import crop_spots, crop_valid
from torchblur.render.camera import CameraNoise
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow
from torchblur.sysid.frequency_response_io import json_floats

__all__ = ["SinePlan", "SweepLayout", "point_windows", "sweep_layout"]

_F64 = torch.float64
# One fit at a time: the kernel model's Jacobian is by forward-mode AD, whose dual level is
# global to the process, and ChunkFitter.finish fits the last chunk while the background
# thread may still fit the one before.
_FIT_LOCK = threading.Lock()


@dataclass
class SweepLayout:
    """What every point of the sweep shares: ``inputs`` (driven in turn), ``freqs`` (Hz,
    ``[F]``), ``fracs`` (E exposure fractions of the period), ``R`` images per exposure,
    ``trigger_phase`` (rad), ``single`` (one axis, one spot: fits along the calibrated
    direction, shapes ``[F]``), ``axes`` (that direction, or ``"xy"``), ``P`` problems per
    point of ``h x w`` pixels (``psf_p`` ``[P]`` in their coordinates), ``use_p`` ``[P]``
    (problems whose motion steers the amplitude), ``moment_dirs`` (directions it is measured
    along), with one spot ``still_psf`` (the calibration's
    :class:`~torchblur.image.psf_from_still.StillPSF`: the points are fitted with
    ``still_psf.psf``), and with many spots ``spots``, ``in_frame`` ``[P, h, w]``,
    ``flagged`` ``[P]`` and ``spot_kernels`` (the calibration's
    :class:`~torchblur.identify.calibration.SpotKernels`: every spot fitted with its measured
    kernel; None: the Gaussians ``psf_p``)."""

    inputs: list
    freqs: np.ndarray
    fracs: list
    R: int
    trigger_phase: float
    single: bool
    axes: object
    P: int
    h: int
    w: int
    psf_p: GaussianPSF
    use_p: torch.Tensor
    moment_dirs: list
    still_psf: object = None
    spots: object = None
    in_frame: torch.Tensor | None = None
    flagged: torch.Tensor | None = None
    spot_kernels: object = None

    @property
    def E(self) -> int:
        return len(self.fracs)

    @property
    def uses_kernel(self) -> bool:
        """The points are fitted with the measured kernel (``still_psf.psf`` is a KernelPSF, or
        many spots' ``spot_kernels``)."""
        return self.spot_kernels is not None or (self.still_psf is not None and isinstance(self.still_psf.psf, KernelPSF))

    @property
    def kernel_rule(self):
        """What gives the kernel's own noise factor (``kernel_noise_factor``): the one spot's
        StillPSF or the spots' kernels."""
        return self.spot_kernels if self.spot_kernels is not None else self.still_psf

    def pieces_of(self, frames: torch.Tensor) -> torch.Tensor:
        """``[E, R, H, W]`` -> ``[E, R, P, h, w]`` (the spots' crops, or the frame)."""
        if self.spots is None:
            return frames[:, :, None]
        return crop_spots(frames, self.spots.offset, self.spots.size)


def sweep_layout(cfg, cal, frame_shape) -> SweepLayout:
    """The :class:`SweepLayout` of ``cfg`` after the calibration ``cal`` on frames ``(H, W)``."""
    mimo = bool(cfg.plant.is_mimo)
    spots = cal.spots
    single = not mimo and spots is None
    psf = cal.psf
    kw = {}
    if spots is not None:
        P, (h, w) = len(spots), spots.size
        psf_p = spots.psf_in_crops()  # [K] in crop coordinates
        # the dominant motion is measured on spots whose crop is whole (an edge spot's moments are biased)
        use_p = ~spots.clipped if bool((~spots.clipped).any()) else torch.ones(P, dtype=torch.bool)
        flagged = spots.inside_fraction < MIN_INSIDE  # [P] spots mostly outside the frame: not fitted
        use_p = use_p & ~flagged if bool((use_p & ~flagged).any()) else use_p
        kw = dict(spots=spots, in_frame=crop_valid(tuple(frame_shape), spots.offset, spots.size), flagged=flagged,
                  spot_kernels=getattr(cal, "spot_kernels", None))
    else:
        P, (h, w) = 1, tuple(frame_shape)
        psf_p = GaussianPSF(psf.center[None], psf.cov[None], psf.amplitude[None])
        use_p = torch.ones(1, dtype=torch.bool)
    dirs = [torch.tensor(cal.direction, dtype=_F64)] if single else [torch.tensor([1.0, 0.0], dtype=_F64),
                                                                      torch.tensor([0.0, 1.0], dtype=_F64)]
    return SweepLayout(inputs=["x", "y"] if mimo else ["x"], freqs=np.asarray(cfg.frequencies_hz()),
                       fracs=[float(e) for e in cfg.sweep.exposures], R=int(cfg.sweep.images_per_point),
                       trigger_phase=float(cfg.sweep.trigger_phase_rad), single=single, axes=cal.direction if single else "xy",
                       P=P, h=h, w=w, psf_p=psf_p, use_p=use_p, moment_dirs=dirs, still_psf=cal.still_psf, **kw)


def point_windows(freq_hz: float, fractions, trigger_phase: float, trigger_delay_s: float, latency_s: float):
    """The exposures of one sweep point: the windows of
    :func:`~torchblur.design.windows.dual_exposure_windows` (durations ``fractions`` of the
    period, one start at ``trigger_phase``) moved to the rig's clock, where the exposure
    begins ``trigger_delay_s + latency_s`` after the trigger.

    Returns ``(trigger_offset_s, window)``: the trigger time after a period start (s, in
    ``[0, 1 / freq_hz)``) and an :class:`ExposureWindow` ``[E]`` (float64, s) starting at
    ``trigger_offset_s + trigger_delay_s + latency_s``."""
    period = 1 / freq_hz
    design = dual_exposure_windows(torch.tensor(2 * math.pi * freq_hz, dtype=_F64), fractions=fractions, trigger_phase=trigger_phase)
    offset = (float(design.start[0]) - trigger_delay_s - latency_s) % period
    start = offset + trigger_delay_s + latency_s
    return offset, ExposureWindow(torch.full_like(design.duration, start), design.duration)


@dataclass
class SineAcquisition:
    """What the sweep collected, per job ``j = input index * F + point index``: ``frames``
    ``[P, E*R, h, w]`` electrons, ``masks`` (usable pixels, same shape), ``windows`` ``[E*R]``,
    ``amps`` (command amplitude), ``powers`` (laser), ``n_saturated`` (pixels masked),
    after the fit ``moved_px`` (the motion reached, px) and ``limited`` (at the input range's
    limit and short of the target, :func:`~torchblur.identify.drive.is_limited`);
    ``omega_job`` ``[J]`` rad/s; ``layout`` the sweep's :class:`SweepLayout`; ``fitter`` fits
    completed jobs as they come."""

    omega_job: torch.Tensor
    frames: list = field(default_factory=list)
    masks: list = field(default_factory=list)
    windows: list = field(default_factory=list)
    amps: list = field(default_factory=list)
    powers: list = field(default_factory=list)
    n_saturated: list = field(default_factory=list)
    moved_px: list = field(default_factory=list)
    limited: list = field(default_factory=list)
    layout: SweepLayout | None = None
    fitter: ChunkFitter | None = None
    t_sweep: float = 0.0
    t_acq_end: float = 0.0


def _point_psf(lay: SweepLayout, power: torch.Tensor):
    """The PSF of points of laser powers ``power`` ``[n]``, batch ``[n, P]``: the measured
    kernel where the calibration chose it (one spot), else the Gaussian(s) ``lay.psf_p``."""
    n, P, psf_p = power.shape[0], lay.P, lay.psf_p
    if lay.spot_kernels is not None:  # [P, h, w]: a kernel per spot
        return KernelPSF(lay.spot_kernels.psf.kernel.to(_F64).expand(n, P, lay.h, lay.w) * power[:, None, None, None])
    if lay.uses_kernel:
        return KernelPSF(lay.still_psf.psf.kernel.to(_F64).expand(n, P, lay.h, lay.w) * power[:, None, None, None])
    return GaussianPSF(psf_p.center.expand(n, P, 2), psf_p.cov.expand(n, P, 2, 2), psf_p.amplitude[None, :] * power[:, None])


def inflate_std(fit, factor: torch.Tensor):
    """``fit`` (a SinusoidFit of batch ``[...]``) with ``amplitude_std`` and ``phase_std``
    times ``factor`` ``[...]`` and ``covariance`` times ``factor**2`` (correlations kept)."""
    def per(v):
        return factor.to(v).reshape(tuple(factor.shape) + (1,) * (v.dim() - factor.dim()))
    return replace(fit, amplitude_std=fit.amplitude_std * per(fit.amplitude_std), phase_std=fit.phase_std * per(fit.phase_std),
                   covariance=fit.covariance * per(fit.covariance) ** 2)


def fit_points(acq: SineAcquisition, lay: SweepLayout, cfg, noise: CameraNoise, idx: list):
    """One batched :func:`~torchblur.fit.sinusoid.fit_sinusoid` of the jobs ``idx`` (batch
    ``[n]`` for a single-spot SISO run, else ``[n, P]``), weighted by the camera noise model
    ``noise`` (the calibration's; every ``fit.loss`` uses it).
    With the measured kernel the stds include its own noise: times
    :meth:`~torchblur.image.psf_from_still.StillPSF.kernel_noise_factor` of the point's
    exposures (all ``E*R`` of them, fitted together) times its laser power (the still frames
    are taken at power 1). A kernel fit gives each point its own crop and rules, so a point's
    values do not depend on the chunking."""
    imgs = torch.stack([acq.frames[j] for j in idx])  # [n, P, E*R, h, w]
    pw = torch.tensor([acq.powers[j] for j in idx], dtype=_F64)
    psf_b = _point_psf(lay, pw)
    win = ExposureWindow(torch.stack([acq.windows[j].start for j in idx])[:, None],
                         torch.stack([acq.windows[j].duration for j in idx])[:, None])
    f = cfg.fit
    with _FIT_LOCK:
        fit = fit_sinusoid(imgs, psf_b, win, acq.omega_job[list(idx)][:, None], axes=lay.axes, optimizer=f.optimizer, loss=f.loss,
                           noise=noise, mask=torch.stack([acq.masks[j] for j in idx]),
                           fit_scale=f.fit_scale, fit_background=f.fit_background, fit_gradient=f.fit_gradient,
                           outliers=f.outliers, outlier_sigma=float(f.outlier_sigma))
    if lay.uses_kernel:
        # the rule counts the light: a point's exposures at laser power p hold the light of p times them at power 1
        fit = inflate_std(fit, lay.kernel_rule.kernel_noise_factor(win.duration * pw[:, None, None]))  # [n, 1]
    return squeeze_problems(fit) if lay.single else fit


def _moved_px(frames, lay: SweepLayout, cal, omega: float, window: ExposureWindow):
    """Dark-subtracted electrons ``[E, R, P, h, w]`` and the closed-form amplitude (px) of the
    first exposure: how far did the spot (the farthest spot, on the axis that moves most)
    move?"""
    img = lay.pieces_of(subtract_dark(frames.to(_F64), cal.dark) * cal.gain)
    _, cen, cov = image_moments(img[0].mean(0), threshold=3 * cal.read_noise_e)  # [P, 2], [P, 2, 2]
    Ms = []
    for u in lay.moment_dirs:
        mu1, vex = moments_along(cen - lay.psf_p.center, cov - lay.psf_p.cov, u)
        M, _ = sinusoid_from_moments(mu1, vex, torch.tensor(omega, dtype=_F64), window.start[0], window.duration[0])
        Ms.append(M)
    M = torch.stack(Ms, -1)[lay.use_p]
    M = M[torch.isfinite(M)]
    return img, float(M.max()) if M.numel() else 0.0


def _recorded_point(run, key, f, A, power, moved):
    """A point the recording ``run.exp`` holds: ``(capture, amplitude, images, moved px)``."""
    rec = run.exp.groups[key][0]
    if not (math.isclose(rec["freq_hz"], f, rel_tol=1e-12) and math.isclose(rec["power"], power, rel_tol=1e-9)):
        raise RecordingError(f"{key}: recorded at {rec['freq_hz']} Hz, power {rec['power']}; this run asks {f} Hz, power {power}")
    (_, _, cap), = run.exp.load_calls(key)
    A = float(rec["amplitude"])
    img, M_est = moved(cap.frames)
    return cap, A, img, M_est


_MAX_ATTEMPTS = 6  # amplitudes tried per point: three, and up to three more for a point still short of its target


def _take_point(run, key, inp, k, f, A, power, offset, te, moved):
    """Drive one point (up to three amplitudes, each within the run's input range, until the
    spot moves about ``target_px``; a point still short of it goes on, up to
    :data:`_MAX_ATTEMPTS`, until it is at the limit, where the motion it gives is kept) and record it.
    Returns ``(capture, amplitude, images, moved px)``."""
    cfg = run.cfg
    target, limit = float(cfg.excitation.target_px), run.cal.limit_at(f)  # the range and, at f, the slew limit
    for attempt in range(_MAX_ATTEMPTS):
        kw = dict(freq_hz=float(f), amplitude=float(A), exposures_s=te, trigger_offset_s=float(offset),
                  n_repeats=int(cfg.sweep.images_per_point), settle_s=cfg.sweep.settle_s, power=float(power))
        if cfg.plant.is_mimo:
            kw["input"] = inp
        cap = run.rig.sine(**kw)
        img, M_est = moved(cap.frames)  # [E, R, P, h, w] electrons
        ok = 0.75 * target <= M_est <= 1.33 * target or (at_limit(A, limit) and M_est < 1.33 * target)
        # past three tries only a point still short of its target goes on, toward the limit (a small
        # motion's moment estimate has a floor of a few px, so each try gains only a few times)
        if ok or attempt == _MAX_ATTEMPTS - 1 or (attempt >= 2 and M_est >= 0.75 * target):
            break
        A = min(target / (max(M_est, 1e-3) / A), limit)
    if run.exp is not None and run.exp.writable:
        run.exp.record(key, "sweep", [("sine", _bind("sine", (), kw), cap)],
                       labels={"input": inp, "freq_hz": float(f), "amplitude": float(A), "power": float(power), "point": k,
                               "attempts": attempt + 1})
    return cap, A, img, M_est


def _sweep_point(run, lay: SweepLayout, acq: SineAcquisition, inp: str, k: int, f: float, gain_est):
    """Take point ``k`` (frequency ``f``) of input ``inp`` (or load it from the recording) and
    add it to ``acq``. Returns the new |H| estimate (px per input unit)."""
    c, cal, x = run.cfg.camera, run.cal, run.cfg.excitation
    om = 2 * math.pi * f
    offset, win = point_windows(f, lay.fracs, lay.trigger_phase, c.trigger_delay_s, cal.latency_s)
    te = win.duration.tolist()
    A = min(float(x.target_px) / gain_est if gain_est else float(x.target_px) / 10.0, cal.limit_at(f))
    # Laser power: a still spot over the longest exposure would reach peak_fraction of the range.
    power = c.peak_fraction * cal.full_adu * cal.gain / (cal.peak_rate * max(te))
    moved = partial(_moved_px, lay=lay, cal=cal, omega=om, window=win)
    key = f"sweep/{inp}/{k:03d}"
    if run.exp is not None and run.exp.has(key):
        cap, A, img, M_est = _recorded_point(run, key, f, A, power, moved)
    else:
        cap, A, img, M_est = _take_point(run, key, inp, k, f, A, power, offset, te, moved)
    P, E, R, h, w = lay.P, lay.E, lay.R, lay.h, lay.w
    if lay.spots is not None and bool(lay.flagged.any()):
        img = img * ~lay.flagged[:, None, None]  # a flagged spot is left dark: the fit marks it "no signal"
    acq.frames.append(img.permute(2, 0, 1, 3, 4).reshape(P, E * R, h, w))
    usable = lay.pieces_of(cal.saturation.mask(cap.frames.to(_F64)))  # [E, R, P, h, w]
    if lay.spots is not None:
        acq.n_saturated.append(int((~usable & lay.in_frame).sum()))
        usable = usable & lay.in_frame & ~lay.flagged[:, None, None]
    else:
        acq.n_saturated.append(int((~usable).sum()))
    acq.masks.append(usable.permute(2, 0, 1, 3, 4).reshape(P, E * R, h, w))
    acq.windows.append(ExposureWindow(win.start.repeat_interleave(R), win.duration.repeat_interleave(R)))
    acq.amps.append(A)
    acq.powers.append(power)
    return max(M_est, 1e-3) / A


def design_check(run, lay: SweepLayout) -> None:
    """The pre-run design check of a sine sweep (:func:`~torchblur.design.windows.check_design`
    on the designed windows of every frequency): its messages are logged (and, with progress
    shown, warned) before the first point is driven, e.g. one exposure per point (the alias)."""
    om = torch.tensor(2 * math.pi * lay.freqs, dtype=_F64)
    win = dual_exposure_windows(om, fractions=lay.fracs, trigger_phase=lay.trigger_phase)
    for msg in check_design(om, win, warn=run.progress):
        run.say(f"design: warning: {msg}")


def _drive_meta(run, lay: SweepLayout) -> dict:
    """Each point's reached motion (``acq.moved_px``: the fitted amplitude, px, the largest over
    the spots and image axes; NaN without a fit) and whether the input range limited it
    (``acq.limited``: at the limit and short of the target, or not fitted); the log line that
    names those points; the frequency response's entries ``input_limit`` (input units, None:
    none), ``slew_limit`` (input units/s, None: none) and ``limited_hz`` (the frequencies of the
    limited points, on any input)."""
    acq, limit, target = run.acquisition, run.cal.input_limit, float(run.cfg.excitation.target_px)
    slew = math.inf if run.cal.drive is None else run.cal.drive.slew
    freqs = np.tile(lay.freqs, len(lay.inputs))
    amp = run.fit.amplitude.detach().to(_F64).reshape(len(acq.amps), -1)
    amp = torch.where(torch.isfinite(amp), amp, torch.full_like(amp, -1.0)).amax(1)
    acq.moved_px = [float(m) if m >= 0 else float("nan") for m in amp.tolist()]
    acq.limited = [is_limited(A, m, target, run.cal.limit_at(f)) for A, m, f in zip(acq.amps, acq.moved_px, freqs)]
    flags = run.fit.flags
    no_motion = None if flags is None else ((flags.reshape(len(acq.amps), -1) & NO_MOTION) != 0).any(1).tolist()
    line = limited_summary(lay.freqs, acq.limited, acq.moved_px, target, limit, tuple(lay.inputs), no_motion, slew=slew)
    if line is not None:
        run.say(line)
    return {"input_limit": json_floats(limit), "slew_limit": json_floats(slew),
            "limited_hz": sorted({float(f) for f, lim in zip(freqs, acq.limited) if lim})}


class SinePlan:
    """One sine per point: the sweep, fit, assemble and report stages of ``excitation.kind=sine``."""

    kind = "sine"
    supports_direct = True

    def sweep(self, run) -> None:
        """The sweep stage: every input, every frequency; the chunked fits run while it goes on."""
        lay = sweep_layout(run.cfg, run.cal, run.rig.frame_shape)
        F, I = len(lay.freqs), len(lay.inputs)
        acq = SineAcquisition(omega_job=torch.tensor(np.tile(2 * math.pi * lay.freqs, I), dtype=_F64), layout=lay)
        acq.fitter = ChunkFitter(int(run.cfg.fit.chunk_points), partial(fit_points, acq, lay, run.cfg, run.cal.noise))
        run.acquisition = acq
        design_check(run, lay)
        acq.t_sweep = time.perf_counter()
        bar = progress_bar(run.progress, total=I * F, desc="sweep", unit="pt")
        try:
            for ii, inp in enumerate(lay.inputs):
                gain_est = run.cal.axis_gain  # |H| of the dominant motion (px per input unit) from the previous point
                for k, f in enumerate(lay.freqs):
                    gain_est = _sweep_point(run, lay, acq, inp, k, float(f), gain_est)
                    acq.fitter.add(ii * F + k)
                    bar.update(1)
                    bar.set_postfix(input=inp, f_hz=f"{f:.4g}", amplitude=f"{acq.amps[-1]:.3g}")
            bar.close()
            acq.t_acq_end = time.perf_counter()
            n_sat = sum(acq.n_saturated)
            if n_sat:
                run.say(f"saturation: {n_sat} saturated pixels masked out of the fit")
        except BaseException:
            acq.fitter.close()
            raise

    @staticmethod
    def windows(acq: SineAcquisition) -> ExposureWindow:
        """The windows of every job, ``[J, E*R]``."""
        return ExposureWindow(torch.stack([w.start for w in acq.windows]), torch.stack([w.duration for w in acq.windows]))

    def fit(self, run) -> None:
        """The fit stage: the fits of the chunks left, in point order (``run.fit``), and the timing."""
        acq = run.acquisition
        try:
            parts = acq.fitter.finish()
        finally:
            acq.fitter.close()
        t_fit_end = time.perf_counter()
        run.fit = concat_fits([p for _, p in parts])
        fitter, t_acq_end = acq.fitter, acq.t_acq_end
        overlapped = sum(max(0.0, min(e, t_acq_end) - s0) for s0, e in fitter.spans)
        run.timing = {"calibration_s": acq.t_sweep - run.t_start, "sweep_s": t_acq_end - acq.t_sweep, "fit_s": fitter.busy_s,
                      "fit_overlapped_s": overlapped, "after_sweep_s": t_fit_end - t_acq_end, "fit_chunks": len(parts),
                      "total_s": t_fit_end - run.t_start}
        exp = run.exp
        if exp is not None:
            run.timing["recording_write_s"] = exp.stats["write_s"]
            run.say(f"recording: {exp.stats['groups_written']} group(s) written ({exp.stats['write_s']:.2f} s), "
                    f"{exp.stats['groups_reused']} reused, in {exp.path}")
        run.say(f"fit: {len(parts)} chunk(s), {fitter.busy_s:.2f} s of fitting, {overlapped:.2f} s of it during the sweep; "
                f"{t_fit_end - t_acq_end:.2f} s from the last frame to the last fit")

    def assemble(self, run) -> None:
        """The assemble stage: the FrequencyResponse (``run.frf``), the images, windows and powers in the
        result's shapes (``run.images``, ``run.windows``, ``run.power``), and the truth where
        the rig knows it (``run.truth``)."""
        acq, cal, c = run.acquisition, run.cal, run.cfg.camera
        lay = acq.layout
        I, F, ER = len(lay.inputs), len(lay.freqs), lay.E * lay.R
        images = torch.stack(acq.frames)  # [J, P, E*R, h, w]
        windows = self.windows(acq)
        meta = {"seed": int(run.cfg.seed), **_drive_meta(run, lay)}
        if lay.still_psf is not None:
            meta["psf"] = lay.still_psf.kind  # the PSF the points were fitted with: "kernel" or "gaussian"
        elif lay.spots is not None:
            meta["psf"] = "kernel" if lay.spot_kernels is not None else "gaussian"
        if lay.single:
            meta["direction"] = list(cal.direction)  # the image direction of the fitted motion (x, y)
            run.images = images[:, 0]  # [F, E*R, H, W]
            run.frf = assemble_siso(run.fit, acq.amps, acq.omega_job, c, cal.latency_std_s, ER, meta)
        else:
            run.images = images.reshape((I, F) + tuple(images.shape[1:]))  # [I, F, P, E*R, h, w]
            windows = ExposureWindow(windows.start.reshape(I, F, ER), windows.duration.reshape(I, F, ER))
            if lay.spots is not None:
                meta["spot_centers_px"] = lay.spots.psf.center.tolist()
            run.frf = assemble_mimo(run.fit, acq.amps, acq.omega_job, c, cal.latency_std_s, ER, lay.inputs, lay.P,
                                    lay.spots is not None, meta)
        run.windows, run.power = windows, torch.tensor(acq.powers, dtype=_F64)
        frf = run.frf
        n_bad = int((~np.isfinite(frf.response)).sum())
        run.say(f"fit: {frf.response.size - n_bad} of {frf.response.size} {'points' if lay.single else 'channel points'} converged")
        if lay.spots is not None:
            for k in [k for k in range(lay.P) if not np.isfinite(frf.response[2 * k:2 * k + 2]).any()]:
                st = run.fit.status.reshape(I * F, lay.P)[:, k]
                why = "mostly outside the frame" if bool(lay.flagged[k]) else STATUS.get(int(st.mode().values), "?")
                run.say(f"spots: s{k} flagged at every point ({why}); its channels are NaN, the other spots are fitted")
        run.truth = truth_of(run.rig, lay.freqs, frf, lay.spots, lay.single)

    def fit_direct(self, run):
        """The direct model from ``run.model`` (one axis, one spot; see
        :func:`~torchblur.identify.model.fit_direct_model`)."""
        acq, cal = run.acquisition, run.cal
        return fit_direct_model(run.cfg, run.model, run.images, run.windows, acq.omega_job, acq.amps, cal.psf, run.power,
                                cal.noise, torch.stack(acq.masks)[:, 0], run.fit, cal.direction, still_psf=cal.still_psf,
                                latency_std_s=cal.latency_std_s if run.cfg.model.fit_delay else 0.0)

    def result(self, run) -> IdentificationResult:
        """The report stage: the :class:`IdentificationResult`."""
        acq, cal = run.acquisition, run.cal
        return IdentificationResult(frf=run.frf, model=run.model, psf=cal.psf, fit=run.fit, amplitude=np.asarray(acq.amps),
                                    latency_s=cal.latency_s, latency_std_s=cal.latency_std_s, saturation=cal.saturation,
                                    images=run.images, windows=run.windows, power=run.power, truth=run.truth,
                                    timing=run.timing, inputs=tuple(acq.layout.inputs),
                                    spots=cal.spots, direct_model=run.direct_model, direction=cal.direction, axis=cal.axis,
                                    limited=np.asarray(acq.limited, dtype=bool), moved_px=np.asarray(acq.moved_px, dtype=np.float64),
                                    noise=cal.noise, ptc=cal.ptc)
