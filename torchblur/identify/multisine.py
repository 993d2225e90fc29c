"""The identification with multisine excitation (``excitation.kind=multisine``).

The multisine plan (:class:`MultisinePlan`) of the identification's stages: calibrate and
model are those of every run; the sweep, fit and assemble stages become, for each group of
``excitation.tones`` frequencies, tones on a common grid
(:func:`~torchblur.design.multisine.common_grid`), pilot frames that set the amplitudes, one image
set designed from the Fisher information (:func:`~torchblur.design.fisher.design_acquisition`,
recorded as ``sweep/multisine/{g:03d}``) and every tone fitted at once
(:func:`~torchblur.fit.multisine.fit_multisine`): ``H_k = M_k / a_k e^{j (phi_k - p_k)}`` with
its covariance (fit, trigger jitter and latency calibration). Each step: docs/multisine.md.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from torchblur.design.fisher import design_acquisition
from torchblur.design.multisine import common_grid, optimise_crest_factor
from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.identify.assemble import input_label, phase_std
from torchblur.identify.drive import is_limited, limited_summary
from torchblur.identify.record import progress_bar, run_stage
from torchblur.identify.result import IdentificationResult
from torchblur.image.moments import image_moments, moments_along
from torchblur.image.preprocess import subtract_dark
from torchblur.render.window import ExposureWindow
from torchblur.rig.base import command_peak, command_slew
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.frequency_response_io import json_floats

__all__ = ["MultisineIdentificationResult", "MultisinePlan", "group_frequencies"]

_F64 = torch.float64


@dataclass
class MultisineIdentificationResult(IdentificationResult):
    """:class:`~torchblur.identify.run.IdentificationResult` of a multisine run. Here ``fit`` is a
    list of :class:`~torchblur.fit.multisine.MultisineFit` (one per group), ``images``
    ``[I, H, W]`` every fitted frame of every group (electrons, divided by its laser power),
    ``windows`` ``[I]``, ``power`` ``[I]``, ``amplitude`` the command amplitude of each tone
    (in frequency order). ``groups``: per group a dict with ``freq_hz``, ``base_freq_hz``,
    ``harmonics``, ``amplitude``, ``phase_rad``, ``crest_factor``, ``design``
    (:class:`~torchblur.design.fisher.AcquisitionDesign`), ``images`` (slice into
    ``images``, the last pilot included), ``pilot_images`` (earlier pilot frames, not fitted), ``order`` (indices of
    its tones in the frequency response)."""

    groups: list = field(default_factory=list)
    fit_psf: object = None  # the PSF the groups were fitted with (the measured kernel or the Gaussian); None: ``psf``

    @property
    def images_used(self) -> int:
        """Frames taken by the multisine stages (pilots included)."""
        return sum(g["images"].stop - g["images"].start + g["pilot_images"] for g in self.groups)

    def residual_panels(self, n: int = 3):
        """``(data [n, H, W], model [n, H, W], labels)``: the first frame of the ``n`` groups
        with the largest cost per pixel, and its fitted model (for the residual figure)."""
        H, W = self.images.shape[-2:]
        cost = np.array([float(f.cost) / max(1, (g["images"].stop - g["images"].start) * H * W) for f, g in zip(self.fit, self.groups)])
        worst = np.argsort(np.nan_to_num(cost, nan=np.inf))[-n:][::-1]
        data, models, labels = [], [], []
        for gi in worst:
            g, f = self.groups[int(gi)], self.fit[int(gi)]
            i = g["images"].start
            data.append(self.images[i].numpy())
            if not bool(f.converged):
                models.append(np.zeros((H, W)))
            else:
                theta = torch.cat([f.amplitude, f.phase] + ([f.scale.reshape(1)] if f.scale is not None else []))
                om = torch.as_tensor(2 * np.pi * np.asarray(g["freq_hz"]), dtype=theta.dtype)
                w = ExposureWindow(self.windows.start[i:i + 1], self.windows.duration[i:i + 1])
                psf = self.fit_psf if self.fit_psf is not None else self.psf
                img = render_multisine(theta, om, psf, w, height=H, width=W, direction=self.direction)[0]
                models.append(img.detach().numpy())
            labels.append(f"{', '.join(f'{v:.4g}' for v in g['freq_hz'])} Hz")
        return np.stack(data), np.stack(models), labels


def group_frequencies(freq_hz, tones: int) -> list[list[float]]:
    """The sweep's frequencies (increasing) in consecutive groups of ``tones`` (the last one
    may be smaller)."""
    f = sorted(float(v) for v in freq_hz)
    return [f[i:i + tones] for i in range(0, len(f), tones)]


def _gain_guess(known: list, freq_hz: np.ndarray):
    """|H| at ``freq_hz`` from the fitted points ``known`` = [(f, |H|), ...]: the nearest in
    log frequency (None before any fit)."""
    if not known:
        return None
    kf = np.array([k[0] for k in known])
    kg = np.array([k[1] for k in known])
    idx = np.abs(np.log(kf)[None, :] - np.log(freq_hz)[:, None]).argmin(1)
    return kg[idx]



@dataclass
class _Group:
    """The tones of one group: ``f0`` (Hz) and ``harm`` (sorted harmonics), ``f_t`` (Hz) and
    ``om`` (rad/s) ``[N]``, ``T0`` (s), ``gains`` (|H| guesses or None), ``a0`` (first command
    amplitudes), ``rms_target`` (px), ``te_p`` (pilot exposure, s)."""

    f0: float
    harm: np.ndarray
    f_t: np.ndarray
    om: np.ndarray
    T0: float
    gains: np.ndarray | None
    a0: np.ndarray
    rms_target: float
    te_p: float


@dataclass
class _Settings:
    """What every group shares: ``peak_e`` (electrons at the still spot's peak in every
    frame), ``u`` (the motion's image direction ``[2]``), ``tone_px``, ``amax`` (the run's input
    range: the largest peak of the command, input units; inf: none), ``tmax`` (s), ``slew`` (the
    run's slew limit: the largest peak of the command's derivative, input units/s; inf: none)."""

    peak_e: float
    u: torch.Tensor
    tone_px: float
    amax: float
    tmax: float
    slew: float = math.inf  # the run's slew limit, input units/s (the command's |d/dt|; inf: none)


@dataclass
class MultisineAcquisition:
    """What the multisine sweep collected: per tone ``freq_hz``, ``response``, ``cov``
    ``[2, 2]``, ``amplitude``, ``limited`` (the group's peak at the input range's limit, its rms
    motion short of the target) and ``moved_px`` (the expected motion, px); per group ``fits``
    and ``groups`` (info dicts); every fitted
    frame's ``images`` (electrons at power 1), ``start``, ``duration`` and ``power``."""

    freq_hz: list = field(default_factory=list)
    response: list = field(default_factory=list)
    cov: list = field(default_factory=list)
    amplitude: list = field(default_factory=list)
    fits: list = field(default_factory=list)
    groups: list = field(default_factory=list)
    images: list = field(default_factory=list)
    start: list = field(default_factory=list)
    duration: list = field(default_factory=list)
    power: list = field(default_factory=list)
    known: list = field(default_factory=list)
    limited: list = field(default_factory=list)
    moved_px: list = field(default_factory=list)
    fit_s: float = 0.0
    t_sweep: float = 0.0
    t_acq_end: float = 0.0


def _settings(cfg, rig, cal) -> _Settings:
    c, x = cfg.camera, cfg.excitation
    return _Settings(peak_e=c.peak_fraction * cal.full_adu * cal.gain,
                     u=torch.tensor(cal.direction if cal.direction is not None else (1.0, 0.0), dtype=_F64),
                     tone_px=float(x.tone_px) if x.tone_px is not None else 0.75 * float(x.target_px), amax=cal.input_limit,
                     tmax=min(float(c.max_exposure_s), float(rig.max_exposure_s)),
                     slew=math.inf if cal.drive is None else float(cal.drive.slew))


def _group(fg, snap_tol: float, known: list, st: _Settings) -> _Group:
    """The tones of the frequencies ``fg`` on a common grid, and their first amplitudes."""
    f0, harm = common_grid(fg, snap_tol=snap_tol)
    harm = harm[np.argsort(harm)]
    f_t = f0 * harm.astype(np.float64)
    gains = _gain_guess(known, f_t)
    N = len(f_t)
    return _Group(f0=f0, harm=harm, f_t=f_t, om=2 * np.pi * f_t, T0=1.0 / f0, gains=gains,
                  a0=st.tone_px / (gains if gains is not None else np.full(N, 10.0)), rms_target=st.tone_px * math.sqrt(N / 2),
                  te_p=min(1.0 / f0, st.tmax))


def _peak(a, phases, grp: _Group) -> float:
    """The command's peak (:func:`~torchblur.rig.base.command_peak`, the bound every rig checks)."""
    return command_peak(grp.f_t, a, phases, grp.f0)


def _use(a, phases, grp: _Group, amax: float, slew: float = math.inf) -> float:
    """How much of the drive the command uses: ``max(peak / amax, slew rate / slew)`` (1: at the limit)."""
    use = _peak(a, phases, grp) / amax if amax is not None and math.isfinite(amax) else 0.0
    if math.isfinite(slew):
        use = max(use, command_slew(grp.f_t, a, phases, grp.f0) / slew)
    return use


def _limit(a, phases, grp: _Group, amax: float, slew: float = math.inf):
    """``a`` scaled down so the command's peak stays within ``amax`` and its slew rate
    (:func:`~torchblur.rig.base.command_slew`) within ``slew`` (inf: no limit)."""
    use = _use(a, phases, grp, amax, slew)
    return a if use <= 1.0 else a / use


def _pilots(r, run, grp: _Group, st: _Settings):
    """Pilot frames over one common period until the rms motion is within [0.75, 1.33] of the
    target (at most 3). Returns ``(amplitudes, phases, pilot captures, rms px)``."""
    cal, dark, gain = run.cal, run.cal.dark, run.cal.gain
    phases, _ = optimise_crest_factor(grp.harm, grp.a0)
    a = _limit(grp.a0, phases, grp, st.amax, st.slew)
    pilots = []
    for attempt in range(3):
        cap = r.multisine(freq_hz=[float(v) for v in grp.f_t], amplitude=[float(v) for v in a], phase_rad=[float(v) for v in phases],
                          exposures_s=[grp.te_p], trigger_offset_s=[0.0], n_repeats=1, base_freq_hz=float(grp.f0),
                          settle_s=run.cfg.sweep.settle_s, power=float(st.peak_e / (cal.peak_rate * grp.te_p)))
        pilots.append(cap)
        img = subtract_dark(cap.frames.to(_F64), dark)[0, 0] * gain
        _, cen, cv = image_moments(img, threshold=3 * cal.read_noise_e)
        along, vex = moments_along(cen - cal.psf.center, cv - cal.psf.cov, st.u)
        rms = math.sqrt(max(float(vex + along**2), 1e-4))  # rms motion along the axis
        ok = 0.75 * grp.rms_target <= rms <= 1.33 * grp.rms_target
        at_limit = rms < grp.rms_target and np.allclose(_limit(a * 1.01, phases, grp, st.amax, st.slew), a, rtol=1e-9)
        if ok or at_limit or attempt == 2:
            break
        a = _limit(a * grp.rms_target / max(rms, 0.05 * grp.rms_target), phases, grp, st.amax, st.slew)
    return a, phases, pilots, rms


def _acquire_group(r, run, grp: _Group, st: _Settings, g: int):
    """Pilots, then the image set designed from the Fisher information, in one
    ``rig.multisine`` call. Returns ``(a, phases, M_exp, design, pilots, capture, offsets, powers)``."""
    cfg, cal = run.cfg, run.cal
    c, x = cfg.camera, cfg.excitation
    H, W = r.frame_shape
    a, phases, pilots, rms = _pilots(r, run, grp, st)
    N = len(grp.f_t)
    # Expected output amplitudes: the gains' shape (or equal tones) scaled to the measured rms.
    shape = a * (grp.gains if grp.gains is not None else np.ones(N))
    M_exp = shape * rms / math.sqrt(float(np.sum(shape**2)) / 2)
    # The last pilot shows the final motion: it is one image of the set (window from offset 0).
    pilot_win = ExposureWindow(torch.tensor([c.trigger_delay_s + cal.latency_s], dtype=_F64), torch.tensor([grp.te_p], dtype=_F64))
    design = design_acquisition(M_exp, grp.om, cal.psf, period_s=grp.T0, max_exposure_s=st.tmax, frame_shape=(H, W),
                                read_noise_e=cal.read_noise_e, n_images=None if x.images is None else max(1, int(x.images) - 1),
                                max_images=int(x.max_images) - 1, target_std=float(x.target_std), peak_e=st.peak_e, taken=pilot_win,
                                fit_scale=bool(cfg.fit.fit_scale), seed=int(cfg.seed) + g, direction=st.u)
    te = list(design.exposure_s)
    offsets = [(s - c.trigger_delay_s - cal.latency_s) % grp.T0 for s in design.window_start_s]
    powers = [float(st.peak_e / (cal.peak_rate * t)) for t in te]
    cap = r.multisine(freq_hz=[float(v) for v in grp.f_t], amplitude=[float(v) for v in a], phase_rad=[float(v) for v in phases],
                      exposures_s=te, trigger_offset_s=offsets, n_repeats=1, base_freq_hz=float(grp.f0),
                      settle_s=cfg.sweep.settle_s, power=powers)
    return a, phases, M_exp, design, pilots, cap, offsets, powers


def _fit_group(run, acq: MultisineAcquisition, grp: _Group, st: _Settings, acquired) -> None:
    """Fit every tone of one group from its image set (the last pilot first) and add the
    points, images and info to ``acq``."""
    c, cal = run.cfg.camera, run.cal
    H, W = run.rig.frame_shape
    a, phases, M_exp, design, pilot, cap, offsets, powers = acquired
    offsets = [0.0] + offsets
    powers = [float(st.peak_e / (cal.peak_rate * grp.te_p))] + powers
    exposures = [grp.te_p] + list(design.exposure_s)
    frames = torch.cat([pilot[-1].frames.reshape(1, H, W), cap.frames.reshape(-1, H, W)]).to(_F64)
    E, N = len(offsets), len(grp.f_t)
    img = subtract_dark(frames, cal.dark) * cal.gain  # electrons
    pw = torch.tensor(powers, dtype=_F64)
    img = img / pw[:, None, None]  # electrons at power 1 (the noise model applies to img * pw)
    start = torch.tensor([o + c.trigger_delay_s + cal.latency_s for o in offsets], dtype=_F64)
    dur = torch.tensor(exposures, dtype=_F64)
    t0 = time.perf_counter()
    fit = fit_multisine(img, fit_psf(cal), ExposureWindow(start, dur), torch.tensor(grp.om, dtype=_F64), noise=cal.noise, power=pw,
                        mask=cal.saturation.mask(frames), amplitude_guess=torch.tensor(M_exp, dtype=_F64),
                        fit_scale=bool(run.cfg.fit.fit_scale), seed=int(run.cfg.seed), direction=st.u, kernel_var=kernel_variance(cal))
    acq.fit_s += time.perf_counter() - t0
    a_t = np.asarray(a, dtype=np.float64)
    resp = fit.amplitude.numpy() / a_t * np.exp(1j * (fit.phase.numpy() - np.asarray(phases)))
    ph_std = phase_std(fit.phase_std.numpy(), grp.om, c, cal.latency_std_s, E)
    cov = np.zeros((N, 2, 2))
    cov[:, 0, 0] = (fit.amplitude_std.numpy() / a_t) ** 2
    cov[:, 1, 1] = ph_std**2
    cov[:, 0, 1] = cov[:, 1, 0] = fit.covariance.numpy()[np.arange(N), N + np.arange(N)] / a_t
    if not bool(fit.converged):
        resp[:] = np.nan
        cov[:] = np.nan
    else:
        acq.known += [(float(f), float(abs(h))) for f, h in zip(grp.f_t, resp)]
    i0 = len(acq.images)
    acq.images += list(img)
    acq.start += start.tolist()
    acq.duration += dur.tolist()
    acq.power += powers
    acq.fits.append(fit)
    acq.groups.append({"freq_hz": grp.f_t.tolist(), "base_freq_hz": float(grp.f0), "harmonics": grp.harm.tolist(),
                       "amplitude": a_t.tolist(), "phase_rad": list(map(float, phases)), "design": design, "images": slice(i0, i0 + E),
                       "pilot_images": len(pilot) - 1, "trigger_offset_s": offsets})
    acq.freq_hz += grp.f_t.tolist()
    acq.response += list(resp)
    acq.cov += list(cov)
    acq.amplitude += a_t.tolist()
    rms = math.sqrt(float(np.sum(np.asarray(M_exp) ** 2)) / 2)
    acq.limited += [is_limited(_use(a_t, phases, grp, st.amax, st.slew), rms, grp.rms_target, 1.0)] * N
    acq.moved_px += [float(m) for m in np.abs(M_exp)]
    run.say(f"multisine group {len(acq.fits) - 1}: tones {', '.join(f'{v:.4g}' for v in grp.f_t)} Hz (f0 {grp.f0:.4g} Hz, harmonics "
            f"{grp.harm.tolist()}), {len(pilot)} pilot(s) + {E - 1} designed frames, {E} fitted (exposures "
            f"{', '.join(f'{t / grp.T0:.2f}' for t in exposures)} T0), predicted std |H| "
            f"{100 * float(np.max(design.amplitude_rel_std)):.3f}% / phase "
            f"{math.degrees(float(np.max(design.phase_std))):.3f} deg; {_fit_word(fit, float(run.cfg.fit.poor_fit_chi2))}")


def fit_psf(cal):
    """The PSF the multisine fit uses: the calibration's choice (``cal.still_psf.psf``, the
    measured kernel or the Gaussian, at laser power 1), else its Gaussian ``cal.psf``."""
    return cal.still_psf.psf if cal.still_psf is not None else cal.psf


def kernel_variance(cal):
    """The measured kernel's pixel variance ``[H, W]`` where the multisine fit uses it
    (:meth:`~torchblur.image.psf_from_still.StillPSF.kernel_variance`, at laser power 1 as the
    kernel): ``fit_multisine(kernel_var=)`` propagates the kernel's own noise into each group's
    covariance (:mod:`torchblur.fit.kernel_noise`); None with a Gaussian.

    Not the one-spot sweep's scalar rule (``kernel_noise_factor``): on a multisine set the kernel's
    light error goes into the fitted intensity scale, not the tones (HCIPy spots: the rule's 1.22
    made the phase stds too large, rms(error/std) 0.73; ``benchmarks/bench_hcipy_routes.py``)."""
    sp = cal.still_psf
    return sp.kernel_variance() if sp is not None and sp.kind == "kernel" else None


def _fit_word(fit, poor_fit_chi2: float) -> str:
    """The group line's verdict on its fit: ``fit FAILED`` (not converged), ``poor fit`` (reduced
    chi2 above ``fit.poor_fit_chi2``: its points are flagged and left out of the model), or
    ``fit ok``, with the reduced chi2 where the noise was known."""
    chi2 = float(fit.extras.get("reduced_chi2", float("nan")))
    tail = f" (reduced chi2 {chi2:.3g})" if math.isfinite(chi2) else ""
    if not bool(fit.converged):
        return "fit FAILED" + tail
    if math.isfinite(chi2) and chi2 > poor_fit_chi2:
        return f"poor fit{tail}: its points are flagged poor_fit"
    return "fit ok" + tail


class MultisinePlan:
    """Multisine groups: the sweep, fit, assemble and report stages of ``excitation.kind=multisine``
    (see the module docstring). Each group is fitted as soon as its image set is taken."""

    kind = "multisine"
    supports_direct = False

    def sweep(self, run) -> None:
        """Every group in turn: pilots, the designed image set, its fit."""
        cfg = run.cfg
        st = _settings(cfg, run.rig, run.cal)
        groups = group_frequencies(cfg.frequencies_hz(), int(cfg.excitation.tones))
        acq = run.acquisition = MultisineAcquisition(t_sweep=time.perf_counter())
        bar = progress_bar(run.progress, total=len(groups), desc="multisine", unit="group")
        for g, fg in enumerate(groups):
            grp = _group(fg, float(cfg.excitation.snap_tol), acq.known, st)
            acquired = run_stage(run.exp, f"sweep/multisine/{g:03d}", "sweep", run.rig, lambda r: _acquire_group(r, run, grp, st, g))
            _fit_group(run, acq, grp, st, acquired)
            bar.update(1)
        bar.close()
        acq.t_acq_end = time.perf_counter()

    def fit(self, run) -> None:
        """The groups' fits (taken during the sweep), one MultisineFit per group."""
        run.fit = run.acquisition.fits

    def assemble(self, run) -> None:
        """One FrequencyResponse at the tones' (grid) frequencies, in frequency order; each
        group's ``order`` (its tones' indices in it); the images, windows, powers; the truth."""
        acq, cal = run.acquisition, run.cal
        idx = np.argsort(acq.freq_hz, kind="stable")
        freq = np.asarray(acq.freq_hz)[idx]
        response = np.asarray(acq.response)[idx]
        rank = np.empty_like(idx)
        rank[idx] = np.arange(idx.size)
        pos = 0
        for info in acq.groups:
            n = len(info["freq_hz"])
            info["order"] = rank[pos:pos + n].tolist()
            pos += n
        u = cal.direction if cal.direction is not None else (1.0, 0.0)
        limited = np.asarray(acq.limited, dtype=bool)[idx]
        limit = cal.input_limit
        line = limited_summary(freq, limited, np.asarray(acq.moved_px)[idx], float(run.cfg.excitation.tone_px or
                               0.75 * float(run.cfg.excitation.target_px)), limit,
                               slew=math.inf if cal.drive is None else cal.drive.slew)
        if line is not None:
            run.say(line)
        run.frf = FrequencyResponse(2 * np.pi * freq, response, cov=np.asarray(acq.cov)[idx], input_labels=[input_label("x")], output_labels=["x"],
                                    meta={"seed": int(run.cfg.seed), "excitation": "multisine", "direction": [float(v) for v in u],
                                          "input_limit": json_floats(limit),
                                          "slew_limit": None if cal.drive is None else json_floats(cal.drive.slew),
                                          "limited_hz": [float(f) for f in freq[limited]],
                                          "psf": cal.still_psf.kind if cal.still_psf is not None else "gaussian"})
        n_bad = int(np.isnan(response).sum())
        run.say(f"fit: {len(freq) - n_bad} of {len(freq)} points converged ({len(acq.groups)} multisine group(s))")
        H, W = run.rig.frame_shape
        run.images = torch.stack(acq.images) if acq.images else torch.zeros(0, H, W, dtype=_F64)
        run.windows = ExposureWindow(torch.tensor(acq.start, dtype=_F64), torch.tensor(acq.duration, dtype=_F64))
        run.power = torch.tensor(acq.power, dtype=_F64)
        run.truth = np.asarray([run.rig.truth(float(f)) for f in freq]) if hasattr(run.rig, "truth") else None

    def result(self, run) -> MultisineIdentificationResult:
        """The :class:`MultisineIdentificationResult` (timing up to now)."""
        acq, cal = run.acquisition, run.cal
        t_end = time.perf_counter()
        run.timing = {"calibration_s": acq.t_sweep - run.t_start, "sweep_s": acq.t_acq_end - acq.t_sweep - acq.fit_s,
                      "fit_s": acq.fit_s, "fit_overlapped_s": 0.0, "after_sweep_s": t_end - acq.t_acq_end,
                      "fit_chunks": len(acq.groups), "total_s": t_end - run.t_start}
        idx = np.argsort(acq.freq_hz, kind="stable")
        return MultisineIdentificationResult(frf=run.frf, model=run.model, psf=cal.psf, fit=run.fit,
                                             amplitude=np.asarray(acq.amplitude)[idx], latency_s=cal.latency_s,
                                             latency_std_s=cal.latency_std_s, saturation=cal.saturation, images=run.images,
                                             windows=run.windows, power=run.power, truth=run.truth, timing=run.timing,
                                             groups=acq.groups, direction=cal.direction, axis=cal.axis, fit_psf=fit_psf(cal),
                                             limited=np.asarray(acq.limited, dtype=bool)[idx],
                                             moved_px=np.asarray(acq.moved_px, dtype=np.float64)[idx], noise=cal.noise,
                                             ptc=cal.ptc)

