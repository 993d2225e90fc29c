"""Fig. 11 of Tani, Mishra, Wen (CDC 2012): the identified frequency response against the truth.

1. The paper's settings with ``torchblur.identify.run.identify`` on the built-in simulated fast
   steering mirror (420 Hz resonance): a 30 Hz camera, 1-500 Hz, 20 frequencies, one
   exposure of half a period, ``w tcam = pi/2``, 4 images per point. With one exposure the
   fitter returns both branches of the phase (``fit.phase``, ``fit.alias_phase``); they cross
   at -90 degrees, right at the resonance. Plain nearest-neighbour continuity picks the wrong
   branch after the crossing; ``torchblur.design.windows.resolve_branches`` (anchored at low
   frequency, extrapolating the phase's slope) follows it. With 20 log-spaced points the step
   across the resonance is too coarse for any continuity rule (shown when ``compare_spacing``).
2. The default dual-exposure design (30% / 80% of the period), which needs no continuity,
   pushed to where it breaks: high frequency with a limited actuator range (the motion shrinks
   with the plant's roll-off), smaller motion, more read noise; where the errors exceed
   1% / 1 degree.

    python experiments/fig11_frequency_response.py --out runs/fig11 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, plt, save_figure, write_metrics

from torchblur.config import load_config
from torchblur.design.windows import resolve_branches
from torchblur.identify.run import build_simulated_rig, identify


def wrap(x):
    return np.angle(np.exp(1j * np.asarray(x, dtype=float)))


def frequencies(f_min, f_max, n, spacing):
    if spacing == "linear":
        return np.linspace(f_min, f_max, n)
    if spacing == "log":
        return np.geomspace(f_min, f_max, n)
    raise ValueError(f"spacing: expected 'linear' or 'log', got {spacing!r}")


def run_identify(cfg, freqs, extra):
    """``identify`` at the given frequencies with the config's base overrides plus ``extra``."""
    overrides = list(cfg.identify_overrides) + [f"seed={int(cfg.seed)}", "sweep.freq_hz=[" + ",".join(f"{f:.10g}" for f in freqs) + "]"]
    overrides += list(extra)
    icfg = load_config(None, overrides)
    return icfg, identify(icfg, progress=False)


def siso(a):
    """A FrequencyResponse's ``[O=1, I=1, F]`` array as ``[F]``."""
    return np.asarray(a)[0, 0]


def errors(res):
    """Relative magnitude error (%) and phase error (deg) against the truth, ``[F]`` each (NaN
    where the fit did not converge)."""
    truth = np.asarray(res.truth)
    mag_err = 100 * (siso(res.frf.magnitude) / np.abs(truth) - 1)
    ph_err = np.degrees(wrap(siso(res.frf.phase) - np.angle(truth)))
    return mag_err, ph_err


def nearest_neighbour(phase, alias, anchor=0.0):
    """Plain continuity: the first point takes the branch nearest ``anchor``, each later one
    the branch nearest the previous choice."""
    out, prev = [], anchor
    for a, b in zip(phase, alias):
        c = a if abs(wrap(a - prev)) <= abs(wrap(b - prev)) else b
        out.append(c)
        prev = c
    return np.asarray(out)


def branch_errors(chosen, phase, alias, truth_phase, sep):
    """Indices where the choice took the wrong branch (the branches more than ``sep`` rad apart)."""
    other = np.where(np.abs(wrap(chosen - phase)) < 1e-12, alias, phase)
    wrong = np.abs(wrap(chosen - truth_phase)) > np.abs(wrap(other - truth_phase))
    apart = np.abs(wrap(phase - alias)) > sep
    return np.nonzero(wrong & apart)[0]


def branch_crossings_hz(icfg, fraction, trigger_phase, f_lo, f_hi):
    """Frequencies where the true phase crosses the line where the two single-exposure branches
    coincide, ``phi = (pi - 2c) / 2 (mod pi)`` with ``c = b + p/2`` (the latency is compensated
    by the trigger, so c is the design's), from the true response on a dense grid."""
    rig = build_simulated_rig(icfg)
    f = np.geomspace(f_lo, f_hi, 4000)
    phi = np.angle(np.asarray([rig.truth(float(v)) for v in f]))
    c = trigger_phase + math.pi * fraction
    s = np.sin(phi + c - math.pi / 2)
    idx = np.nonzero(np.sign(s[1:]) != np.sign(s[:-1]))[0]
    return [float(np.sqrt(f[i] * f[i + 1])) for i in idx]


def paper_run(cfg, spacing):
    p = cfg.paper
    freqs = frequencies(float(p.f_min_hz), float(p.f_max_hz), int(p.n), spacing)
    extra = [f"sweep.exposures=[{','.join(str(float(e)) for e in p.exposures)}]", f"sweep.trigger_phase_rad={float(p.trigger_phase_rad)}",
             f"sweep.images_per_point={int(p.images_per_point)}", "camera.frame_rate_hz=30"]
    icfg, res = run_identify(cfg, freqs, extra)
    omega = 2 * math.pi * freqs
    phase, alias = res.fit.phase.numpy(), res.fit.alias_phase.numpy()
    truth = np.asarray(res.truth)
    tphase = np.angle(truth)
    nn = nearest_neighbour(phase, alias)
    rb = resolve_branches(torch.tensor(omega), torch.tensor(phase), torch.tensor(alias), delay_s=float(p.resolver_delay_s)).numpy()
    sep = math.radians(float(cfg.branch_sep_deg))
    err_nn = branch_errors(nn, phase, alias, tphase, sep)
    err_rb = branch_errors(rb, phase, alias, tphase, sep)
    crossings = branch_crossings_hz(icfg, float(p.exposures[0]), float(p.trigger_phase_rad), float(p.f_min_hz), float(p.f_max_hz))
    mag_err = 100 * (siso(res.frf.magnitude) / np.abs(truth) - 1)
    ok = np.setdiff1d(np.arange(len(freqs)), err_rb)
    rb_phase_err = np.degrees(wrap(rb - tphase))
    m = {
        "spacing": spacing, "freq_hz": freqs.tolist(), "n_converged": int(res.fit.converged.sum()),
        "branch_crossings_hz": crossings,
        "nearest_neighbour_branch_errors": int(len(err_nn)), "nearest_neighbour_error_freq_hz": freqs[err_nn].tolist(),
        "resolver_branch_errors": int(len(err_rb)), "resolver_error_freq_hz": freqs[err_rb].tolist(),
        "max_abs_mag_err_pct": float(np.nanmax(np.abs(mag_err))),
        "max_abs_phase_err_deg_resolver": float(np.nanmax(np.abs(rb_phase_err))),
        "max_abs_phase_err_deg_resolver_right_branch": float(np.nanmax(np.abs(rb_phase_err[ok]))) if ok.size else float("nan"),
        "max_abs_phase_err_deg_nearest_neighbour": float(np.nanmax(np.abs(np.degrees(wrap(nn - tphase))))),
        "magnitude_err_pct": mag_err.tolist(), "phase_err_deg_resolver": rb_phase_err.tolist(),
    }
    data = dict(freqs=freqs, res=res, phase=phase, alias=alias, nn=nn, rb=rb, err_nn=err_nn, err_rb=err_rb, crossings=crossings, icfg=icfg)
    return m, data


def push_frequency(cfg):
    q = cfg.push.frequency
    freqs = frequencies(float(q.f_min_hz), float(q.f_max_hz), int(q.n), "log")
    icfg, res = run_identify(cfg, freqs, [f"excitation.max_amplitude={float(q.max_amplitude)}"])
    mag_err, ph_err = errors(res)
    tol_m, tol_p = float(cfg.tolerance.magnitude_pct), float(cfg.tolerance.phase_deg)
    bad = ~(np.abs(mag_err) <= tol_m) | ~(np.abs(ph_err) <= tol_p)  # NaN (not converged) counts as bad
    over_m = np.nonzero(~(np.abs(mag_err) <= tol_m))[0]
    over_p = np.nonzero(~(np.abs(ph_err) <= tol_p))[0]
    m = {"freq_hz": freqs.tolist(), "motion_px": res.fit.amplitude.numpy().tolist(), "magnitude_err_pct": mag_err.tolist(),
         "phase_err_deg": ph_err.tolist(), "magnitude_std_pct": (100 * siso(res.frf.magnitude_std) / siso(res.frf.magnitude)).tolist(),
         "phase_std_deg": np.degrees(siso(res.frf.phase_std)).tolist(), "max_amplitude": float(q.max_amplitude),
         "first_freq_over_magnitude_tol_hz": float(freqs[over_m[0]]) if over_m.size else None,
         "first_freq_over_phase_tol_hz": float(freqs[over_p[0]]) if over_p.size else None,
         "first_freq_over_either_tol_hz": float(freqs[np.nonzero(bad)[0][0]]) if bad.any() else None,
         "n_converged": int(res.fit.converged.sum())}
    return m, dict(freqs=freqs, mag_err=mag_err, ph_err=ph_err, res=res)


def push_setting(cfg, section, key, values):
    """Max errors over a 1-500 Hz sweep (log, ``section.n`` points) for each value of a setting."""
    freqs = frequencies(float(cfg.paper.f_min_hz), float(cfg.paper.f_max_hz), int(section.n), "log")
    rows = []
    for v in values:
        _, res = run_identify(cfg, freqs, [f"{key}={float(v)}"])
        mag_err, ph_err = errors(res)
        rows.append({"value": float(v), "max_abs_mag_err_pct": float(np.nanmax(np.abs(mag_err))) if np.isfinite(mag_err).any() else None,
                     "max_abs_phase_err_deg": float(np.nanmax(np.abs(ph_err))) if np.isfinite(ph_err).any() else None,
                     "rms_phase_std_deg": float(np.degrees(np.sqrt(np.nanmean(siso(res.frf.phase_std) ** 2)))),
                     "n_converged": int(res.fit.converged.sum()), "n": len(freqs)})
    tol_m, tol_p = float(cfg.tolerance.magnitude_pct), float(cfg.tolerance.phase_deg)
    breaks = [r["value"] for r in rows if r["n_converged"] < r["n"] or r["max_abs_mag_err_pct"] is None
              or r["max_abs_mag_err_pct"] > tol_m or r["max_abs_phase_err_deg"] > tol_p]
    return {"setting": key, "freq_hz": freqs.tolist(), "rows": rows, "first_value_over_tol": breaks[0] if breaks else None}


def bode_panel(ax_m, ax_p, d, title):
    res, freqs = d["res"], d["freqs"]
    rig = build_simulated_rig(d["icfg"])
    fd = np.geomspace(freqs.min(), freqs.max(), 600)
    truth_d = np.asarray([rig.truth(float(v)) for v in fd])
    ax_m.loglog(fd, np.abs(truth_d), "k", lw=1, label="truth")
    ax_m.errorbar(freqs, siso(res.frf.magnitude), yerr=siso(res.frf.magnitude_std), fmt="o", ms=4, color="C0", label="identified")
    ax_m.set_ylabel("magnitude (px / input)")
    ax_m.set_title(title, fontsize=9)
    ax_m.legend(fontsize=7)
    deg = np.degrees
    ax_p.semilogx(fd, deg(np.angle(truth_d)), "k", lw=1, label="truth")
    ax_p.plot(freqs, deg(d["phase"]), ".", color="0.65", ms=7, label="both branches")
    ax_p.plot(freqs, deg(d["alias"]), ".", color="0.65", ms=7)
    ax_p.plot(freqs, deg(d["nn"]), "x", color="C3", ms=7, mew=1.5, label=f"nearest neighbour ({len(d['err_nn'])} wrong)")
    ax_p.plot(freqs, deg(d["rb"]), "o", mfc="none", color="C0", ms=8, label=f"resolve_branches ({len(d['err_rb'])} wrong)")
    for fc in d["crossings"]:
        ax_p.axvline(fc, color="C1", ls=":", lw=1)
    ax_p.axhline(-90, color="C1", ls=":", lw=0.8, label="branch crossing (-90 deg)")
    ax_p.set_ylim(-185, 185)
    ax_p.set_yticks([-180, -90, 0, 90, 180])
    ax_p.set_xlabel("frequency (Hz)")
    ax_p.set_ylabel("phase (deg)")
    ax_p.legend(fontsize=7, loc="lower left")


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig11_frequency_response.yaml")
    torch.set_num_threads(int(cfg.threads))
    metrics = {}
    spacings = [str(cfg.paper.spacing)] + ([str(cfg.paper.compare_spacing)] if cfg.paper.compare_spacing else [])
    paper = {}
    for sp in spacings:
        t0 = time.time()
        m, d = paper_run(cfg, sp)
        m["elapsed_s"] = round(time.time() - t0, 2)
        metrics[f"paper_single_exposure_{sp}"] = m
        paper[sp] = d
        print(f"paper design, {sp} spacing: nearest-neighbour branch errors {m['nearest_neighbour_branch_errors']} "
              f"(at {[round(f) for f in m['nearest_neighbour_error_freq_hz']]} Hz), resolver {m['resolver_branch_errors']} "
              f"(at {[round(f) for f in m['resolver_error_freq_hz']]} Hz); crossing at {[round(f, 1) for f in m['branch_crossings_hz']]} Hz; "
              f"max |mag err| {m['max_abs_mag_err_pct']:.2f}%, max |phase err| (resolver) {m['max_abs_phase_err_deg_resolver']:.2f} deg")

    t0 = time.time()
    mf, df = push_frequency(cfg)
    mf["elapsed_s"] = round(time.time() - t0, 2)
    metrics["dual_push_frequency"] = mf
    print(f"dual design to {cfg.push.frequency.f_max_hz:g} Hz (max input {mf['max_amplitude']:g}): first over 1% at "
          f"{mf['first_freq_over_magnitude_tol_hz']} Hz, over 1 deg at {mf['first_freq_over_phase_tol_hz']} Hz")
    pushes = {}
    for name, key, values in (("motion", "excitation.target_px", list(cfg.push.motion.target_px)),
                              ("noise", "camera.read_noise", list(cfg.push.noise.read_noise))):
        if values:
            sec = cfg.push[name]
            pushes[name] = push_setting(cfg, sec, key, values)
            metrics[f"dual_push_{name}"] = pushes[name]
            print(f"dual design vs {key}: " + ", ".join(f"{r['value']:g}: {r['max_abs_mag_err_pct']:.2f}% / {r['max_abs_phase_err_deg']:.2f} deg"
                                                       for r in pushes[name]["rows"] if r["max_abs_mag_err_pct"] is not None))

    lin = metrics[f"paper_single_exposure_{spacings[0]}"]
    metrics["summary"] = {
        "paper_max_abs_mag_err_pct": lin["max_abs_mag_err_pct"],
        "paper_max_abs_phase_err_deg_resolver": lin["max_abs_phase_err_deg_resolver"],
        "paper_branch_crossings_hz": lin["branch_crossings_hz"],
        "paper_nearest_neighbour_branch_errors": lin["nearest_neighbour_branch_errors"],
        "paper_resolver_branch_errors": lin["resolver_branch_errors"],
        "dual_first_freq_over_1pct_hz": mf["first_freq_over_magnitude_tol_hz"],
        "dual_first_freq_over_1deg_hz": mf["first_freq_over_phase_tol_hz"],
    }
    if len(spacings) > 1:
        cmp_ = metrics[f"paper_single_exposure_{spacings[1]}"]
        metrics["summary"][f"{spacings[1]}_spacing_resolver_branch_errors"] = cmp_["resolver_branch_errors"]
        metrics["summary"][f"{spacings[1]}_spacing_nearest_neighbour_branch_errors"] = cmp_["nearest_neighbour_branch_errors"]

    P = plt()
    ncol = len(spacings)
    fig, axes = P.subplots(2, ncol, figsize=(6.2 * ncol, 6.4), sharex="col", squeeze=False)
    for j, sp in enumerate(spacings):
        bode_panel(axes[0, j], axes[1, j], paper[sp],
                   f"one exposure (p = T/2, w tcam = pi/2), 4 images/pt, {len(paper[sp]['freqs'])} {sp} points")
    fig.suptitle("Fig. 11: identified frequency response vs truth (30 Hz camera)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig11_frequency_response.png")

    npan = 1 + len(pushes)
    fig, axes = P.subplots(1, npan, figsize=(5.0 * npan, 4.0), squeeze=False)
    ax = axes[0, 0]
    ax.semilogy(df["freqs"], np.abs(df["mag_err"]), "o-", ms=4, label="|magnitude error| (%)")
    ax.semilogy(df["freqs"], np.abs(df["ph_err"]), "s-", ms=4, label="|phase error| (deg)")
    ax.axhline(1.0, color="k", ls=":", lw=1, label="1% / 1 deg")
    ax.set_xscale("log")
    ax.set_xlabel("frequency (Hz)")
    ax.set_title(f"dual exposure 30%/80%, input <= {mf['max_amplitude']:g}", fontsize=9)
    ax2 = ax.twinx()
    ax2.loglog(df["freqs"], mf["motion_px"], color="0.6", lw=1, ls="--")
    ax2.set_ylabel("spot motion M (px, dashed)", color="0.4")
    ax.legend(fontsize=7, loc="upper left")
    for k, (name, pm) in enumerate(pushes.items(), start=1):
        ax = axes[0, k]
        cap = 1e3  # errors beyond this are failed fits: drawn at the cap
        v = np.asarray([r["value"] for r in pm["rows"]])
        for key, mk, lab in (("max_abs_mag_err_pct", "o", "max |magnitude error| (%)"), ("max_abs_phase_err_deg", "s", "max |phase error| (deg)")):
            e = np.asarray([np.inf if r[key] is None else r[key] for r in pm["rows"]], dtype=float)
            line, = ax.loglog(v, np.minimum(e, cap), mk + "-", label=lab)
            off = e > cap
            if off.any():
                ax.plot(v[off], np.full(off.sum(), cap), "^", ms=10, color=line.get_color(), mfc="none")
        ax.axhline(1.0, color="k", ls=":", lw=1)
        ax.set_xticks(v, [f"{x:g}" for x in v])
        ax.minorticks_off()
        ax.set_xlabel({"motion": "spot motion target (px)", "noise": "read noise (e-)"}[name]
                      + ("; ^ = off scale (run failed)" if any((r["max_abs_mag_err_pct"] or np.inf) > cap for r in pm["rows"]) else ""))
        ax.set_title(f"dual exposure, 1-500 Hz, {len(pm['freq_hz'])} points", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, "fig11_breaking_point.png")
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"wrote {out}/fig11_frequency_response.png, fig11_breaking_point.png, metrics.json in {time.time() - started:.1f} s")


if __name__ == "__main__":
    main()
