"""The identification with multisine excitation (``excitation.kind=multisine``).

Stages 1-4 (dark frame, saturation, PSF, latency) and 7 (the model) are those of
:func:`torchblur.identify.run.identify` (:func:`~torchblur.identify.run.calibrate`,
:func:`~torchblur.identify.run.fit_model`). Stages 5-6 become, for each group of
``excitation.tones`` frequencies of the sweep:

1. tones on a common grid ``n_k f0`` (:func:`~torchblur.design.multisine.common_grid`, each frequency
   moved by at most ``excitation.snap_tol``); command amplitudes so that every tone moves the
   spot ``excitation.tone_px`` (from the gains of the groups fitted before; the first group
   starts at 1/10 px per input unit); phases of minimal crest factor;
2. a pilot frame over one common period: its second moment is the mean square of the motion
   (``sum_k M_k^2 / 2``), and the amplitudes are rescaled until it is within [0.75, 1.33] of the
   target (at most 3 pilots, as the sine sweep's attempts);
3. the image set designed from the Fisher information at the expected amplitudes
   (:func:`~torchblur.design.fisher.design_acquisition`: windows at different positions in
   the common period and exposures, the laser power following each exposure so every frame
   gets the same peak exposure), taken in one ``rig.multisine`` call (recorded as
   ``sweep/multisine/{g:03d}``);
4. every tone of the group fitted at once from the set
   (:func:`~torchblur.fit.multisine.fit_multisine`), ``H_k = M_k / a_k e^{j (phi_k - p_k)}``
   with its covariance (fit, trigger jitter and latency calibration).

All points form one :class:`~torchblur.sysid.frequency_response.FrequencyResponse` at the tones'
(grid) frequencies, then the model is fitted as usual.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from torchblur.identify.run import IdentificationResult, _log, _stage, fit_model

__all__ = ["MultisineIdentificationResult", "identify_multisine", "group_frequencies"]


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

    @property
    def images_used(self) -> int:
        """Frames taken by the multisine stages (pilots included)."""
        return sum(g["images"].stop - g["images"].start + g["pilot_images"] for g in self.groups)

    def residual_panels(self, n: int = 3):
        """``(data [n, H, W], model [n, H, W], labels)``: the first frame of the ``n`` groups
        with the largest cost per pixel, and its fitted model (for the residual figure)."""
        from torchblur.fit.multisine import render_multisine
        from torchblur.render.psf import GaussianPSF
        from torchblur.render.window import ExposureWindow

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
                img = render_multisine(theta, om, self.psf, w, height=H, width=W, direction=self.direction)[0]
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


def identify_multisine(cfg, rig, exp, log, progress, cal, t_start: float) -> MultisineIdentificationResult:
    """Stages 5-7 of the identification with multisine excitation (see the module
    docstring), after the calibration ``cal`` (:func:`~torchblur.identify.run.calibrate`)."""
    from tqdm.auto import tqdm

    from torchblur.design.fisher import design_acquisition
    from torchblur.sysid.frequency_response import FrequencyResponse
    from torchblur.image.moments import image_moments, moments_along
    from torchblur.design.multisine import common_grid, optimise_crest_factor
    from torchblur.fit.multisine import fit_multisine
    from torchblur.image.preprocess import subtract_dark
    from torchblur.render.window import ExposureWindow

    c, x = cfg.camera, cfg.excitation
    dtype = torch.float64
    H, W = rig.frame_shape
    dark, read_noise_e, sat, full_adu = cal.dark, cal.read_noise_e, cal.saturation, cal.full_adu
    psf, peak_rate, latency, latency_std, gain = cal.psf, cal.peak_rate, cal.latency_s, cal.latency_std_s, cal.gain
    peak_e = c.peak_fraction * full_adu * gain  # electrons at the still spot's peak in every frame
    u = torch.tensor(cal.direction if cal.direction is not None else (1.0, 0.0), dtype=dtype)  # the motion's image direction
    tone_px = float(x.tone_px) if x.tone_px is not None else 0.75 * float(x.target_px)
    amax = x.max_amplitude
    tmax = min(float(c.max_exposure_s), float(rig.max_exposure_s))
    groups = group_frequencies(cfg.frequencies_hz(), int(x.tones))
    known: list = []
    out_f, out_h, out_cov, out_amp, fits, infos = [], [], [], [], [], []
    all_imgs, all_start, all_dur, all_pow = [], [], [], []
    t_sweep = time.perf_counter()
    fit_s = 0.0
    bar = tqdm(total=len(groups), desc="multisine", unit="group", disable=not progress)
    for g, fg in enumerate(groups):
        f0, harm = common_grid(fg, snap_tol=float(x.snap_tol))
        order = np.argsort(harm)
        harm = harm[order]
        f_t = f0 * harm.astype(np.float64)
        om = 2 * np.pi * f_t
        T0 = 1.0 / f0
        N = len(f_t)
        gains = _gain_guess(known, f_t)
        a0 = tone_px / (gains if gains is not None else np.full(N, 10.0))
        rms_target = tone_px * math.sqrt(N / 2)
        settle = cfg.sweep.settle_s
        te_p = min(T0, tmax)

        def limit(a, phases):
            if amax is None:
                return a
            from torchblur.design.multisine import multisine_signal

            peak = np.abs(multisine_signal(harm, a, phases, max(1024, 32 * int(harm.max())))).max()
            return a * min(1.0, float(amax) / peak)

        def acquire(r, a=a0):
            phases, _ = optimise_crest_factor(harm, a)
            a = limit(a, phases)
            pilots = []
            for attempt in range(3):
                cap = r.multisine(freq_hz=[float(v) for v in f_t], amplitude=[float(v) for v in a], phase_rad=[float(v) for v in phases],
                                  exposures_s=[te_p], trigger_offset_s=[0.0], n_repeats=1, base_freq_hz=float(f0), settle_s=settle,
                                  power=float(peak_e / (peak_rate * te_p)))
                pilots.append(cap)
                img = subtract_dark(cap.frames.to(dtype), dark)[0, 0] * gain
                _, cen, cv = image_moments(img, threshold=3 * read_noise_e)
                along, vex = moments_along(cen - psf.center, cv - psf.cov, u)
                ms = float(vex + along**2)  # mean square motion along the axis
                rms = math.sqrt(max(ms, 1e-4))
                ok = 0.75 * rms_target <= rms <= 1.33 * rms_target
                at_limit = amax is not None and rms < rms_target and np.allclose(limit(a * 1.01, phases), a, rtol=1e-9)
                if ok or at_limit or attempt == 2:
                    break
                a = limit(a * rms_target / max(rms, 0.05 * rms_target), phases)
            # Expected output amplitudes: the gains' shape (or equal tones) scaled to the measured rms.
            shape = a * (gains if gains is not None else np.ones(N))
            M_exp = shape * rms / math.sqrt(float(np.sum(shape**2)) / 2)
            # The last pilot shows the final motion: it is one image of the set (window from offset 0).
            pilot_win = ExposureWindow(torch.tensor([c.trigger_delay_s + latency], dtype=dtype), torch.tensor([te_p], dtype=dtype))
            n_more = None if x.images is None else max(1, int(x.images) - 1)
            design = design_acquisition(M_exp, om, psf, period_s=T0, max_exposure_s=tmax, frame_shape=(H, W),
                                        read_noise_e=read_noise_e, n_images=n_more, max_images=int(x.max_images) - 1,
                                        target_std=float(x.target_std), peak_e=peak_e, taken=pilot_win,
                                        fit_scale=bool(cfg.fit.fit_scale), seed=int(cfg.seed) + g, direction=u)
            te = list(design.exposure_s)
            offsets = [(s - c.trigger_delay_s - latency) % T0 for s in design.window_start_s]
            powers = [float(peak_e / (peak_rate * t)) for t in te]
            cap = r.multisine(freq_hz=[float(v) for v in f_t], amplitude=[float(v) for v in a], phase_rad=[float(v) for v in phases],
                              exposures_s=te, trigger_offset_s=offsets, n_repeats=1, base_freq_hz=float(f0), settle_s=settle,
                              power=powers)
            return a, phases, M_exp, design, pilots, cap, offsets, powers

        a, phases, M_exp, design, pilot, cap, offsets, powers = _stage(exp, f"sweep/multisine/{g:03d}", "sweep", rig, acquire)
        n_pilot = len(pilot)
        offsets = [0.0] + offsets
        powers = [float(peak_e / (peak_rate * te_p))] + powers
        exposures = [te_p] + list(design.exposure_s)
        frames = torch.cat([pilot[-1].frames.reshape(1, H, W), cap.frames.reshape(-1, H, W)]).to(dtype)
        E = len(offsets)
        img = subtract_dark(frames, dark) * gain  # electrons
        mask = sat.mask(frames)
        pw = torch.tensor(powers, dtype=dtype)[:, None, None]
        noise = torch.sqrt(read_noise_e**2 + img.clamp_min(0)) / pw
        img = img / pw  # electrons at power 1
        start = torch.tensor([o + c.trigger_delay_s + latency for o in offsets], dtype=dtype)
        dur = torch.tensor(exposures, dtype=dtype)
        win = ExposureWindow(start, dur)
        t0 = time.perf_counter()
        fit = fit_multisine(img, psf, win, torch.tensor(om, dtype=dtype), noise_std=noise, mask=mask,
                            amplitude_guess=torch.tensor(M_exp, dtype=dtype), fit_scale=bool(cfg.fit.fit_scale), seed=int(cfg.seed),
                            direction=u)
        fit_s += time.perf_counter() - t0
        a_t = np.asarray(a, dtype=np.float64)
        M, ph = fit.amplitude.numpy(), fit.phase.numpy()
        Ms, phs = fit.amplitude_std.numpy(), fit.phase_std.numpy()
        resp = M / a_t * np.exp(1j * (ph - np.asarray(phases)))
        ph_std = np.sqrt(phs**2 + (om * c.jitter_s) ** 2 / E + (om * latency_std) ** 2)
        cov = np.zeros((N, 2, 2))
        cov[:, 0, 0] = (Ms / a_t) ** 2
        cov[:, 1, 1] = ph_std**2
        cm = fit.covariance.numpy()
        cov[:, 0, 1] = cov[:, 1, 0] = cm[np.arange(N), N + np.arange(N)] / a_t
        if not bool(fit.converged):
            resp[:] = np.nan
            cov[:] = np.nan
        else:
            known += [(float(f), float(abs(h))) for f, h in zip(f_t, resp)]
        i0 = len(all_imgs)
        all_imgs += list(img)
        all_start += start.tolist()
        all_dur += dur.tolist()
        all_pow += powers
        fits.append(fit)
        infos.append({"freq_hz": f_t.tolist(), "base_freq_hz": float(f0), "harmonics": harm.tolist(), "amplitude": a_t.tolist(),
                      "phase_rad": list(map(float, phases)), "design": design, "images": slice(i0, i0 + E),
                      "pilot_images": n_pilot - 1, "trigger_offset_s": offsets})
        out_f += f_t.tolist()
        out_h += list(resp)
        out_cov += list(cov)
        out_amp += a_t.tolist()
        _log(log, f"multisine group {g}: tones {', '.join(f'{v:.4g}' for v in f_t)} Hz (f0 {f0:.4g} Hz, harmonics "
                  f"{harm.tolist()}), {n_pilot} pilot(s) + {E - 1} designed frames, {E} fitted (exposures "
                  f"{', '.join(f'{t / T0:.2f}' for t in exposures)} T0), predicted std |H| "
                  f"{100 * float(np.max(design.amplitude_rel_std)):.3f}% / phase "
                  f"{math.degrees(float(np.max(design.phase_std))):.3f} deg; fit {'ok' if bool(fit.converged) else 'FAILED'}",
             progress)
        bar.update(1)
    bar.close()
    t_acq_end = time.perf_counter()
    idx = np.argsort(out_f, kind="stable")
    freq = np.asarray(out_f)[idx]
    response = np.asarray(out_h)[idx]
    cov = np.asarray(out_cov)[idx]
    rank = np.empty_like(idx)
    rank[idx] = np.arange(idx.size)
    pos = 0
    for info in infos:
        n = len(info["freq_hz"])
        info["order"] = rank[pos:pos + n].tolist()
        pos += n
    frf = FrequencyResponse(2 * np.pi * freq, response, cov=cov, input_labels=["x"], output_labels=["x"],
                            meta={"seed": int(cfg.seed), "excitation": "multisine", "direction": [float(v) for v in u]})
    n_bad = int(np.isnan(response).sum())
    _log(log, f"fit: {len(freq) - n_bad} of {len(freq)} points converged ({len(groups)} multisine group(s))", progress)
    model = fit_model(cfg, frf, log, progress)
    truth = np.asarray([rig.truth(float(f)) for f in freq]) if hasattr(rig, "truth") else None
    t_end = time.perf_counter()
    timing = {"calibration_s": t_sweep - t_start, "sweep_s": t_acq_end - t_sweep - fit_s, "fit_s": fit_s, "fit_overlapped_s": 0.0,
              "after_sweep_s": t_end - t_acq_end, "fit_chunks": len(groups), "total_s": t_end - t_start}
    images = torch.stack(all_imgs) if all_imgs else torch.zeros(0, H, W, dtype=dtype)
    windows = ExposureWindow(torch.tensor(all_start, dtype=dtype), torch.tensor(all_dur, dtype=dtype))
    return MultisineIdentificationResult(frf=frf, model=model, psf=psf, fit=fits, amplitude=np.asarray(out_amp)[idx], latency_s=latency,
                                         latency_std_s=latency_std, saturation=sat, images=images, windows=windows,
                                         power=torch.tensor(all_pow, dtype=dtype), truth=truth, log=log, timing=timing, groups=infos,
                                         direction=cal.direction, axis=cal.axis)
