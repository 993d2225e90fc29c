"""The text a run reports, per plan: report.txt's section (:func:`response_lines` for a sine or
multisine run: the table of points, the errors against the truth with their goals, the fit
quality, the models and the timing; :func:`dm_lines` for a DM run: its plan, time, statuses,
registration and errors against the simulated truth), the ``--json`` summary line
(:func:`run_summary` and :func:`verdict_summary`; :func:`dm_summary`) and the fit-quality line
(:func:`fit_quality`). Pure functions of a run's result; :func:`torchblur.identify.outputs.write_report`
writes report.txt, the same way for every plan.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import torchblur as tb
from torchblur.dm.registration import support_line
from torchblur.fit.status import FLAGS, POOR_FIT_CHI2, STATUS
from torchblur.identify.dm_plan import AMPLITUDE_LAG, truth_errors
from torchblur.identify.keep_up import pace_line, pace_summary
from torchblur.identify.model import model_parameter_lines
from torchblur.identify.read_outputs import SUMMARY_SCHEMA
from torchblur.identify.verdict import report_lines
from torchblur.render.psf import KernelPSF
from torchblur.sysid.model_check import judge_fit

__all__ = ["dm_lines", "dm_summary", "fit_quality", "response_lines", "run_summary", "verdict_summary"]


def response_lines(cfg, res, elapsed: float, source: str = "run") -> list[str]:
    """A sine or multisine run's section of report.txt (after the run's log, before the verdict):
    the table of points, the errors against the truth, the models and the timing. ``source``:
    "run", "re-fit" or "outside" (:func:`_timing_lines`)."""
    frf = res.frf
    truth = errors = None
    if res.truth is not None:
        truth = res.truth if res.truth.ndim == 3 else res.truth[None, None]
        errors = frf.errors_against(truth)  # [O, I, F] each; NaN where the truth is 0
    lines = _point_lines(frf, errors)
    if truth is not None:
        lines += _truth_lines(frf, truth, errors)
    quality = fit_quality(res.fit, cfg.fit.poor_fit_chi2)[1]
    if quality is not None:
        lines += ["", quality]
    lines += ["", *report_lines(frf, cfg)]
    lines += _model_lines(cfg, res.model) + _direct_lines(cfg, getattr(res, "direct_model", None))
    return lines + _timing_lines(cfg, res, elapsed, source)


def dm_lines(res, elapsed: float) -> list[str]:
    """A DM run's section of report.txt (a :class:`~torchblur.identify.dm_plan.DMResult`, ``elapsed``
    s): its plan and frames, the time of each stage, the statuses, the registration and, on the
    simulated rig, the errors against the truth."""
    t = res.timing_s
    lines = ["", f"dm run: {len(res.actuators)} actuators, {res.G.shape[0] // 2} spots, plan {res.plan.kind} ({res.plan.n_patterns} "
                 f"patterns x {len(res.freq_hz)} frequencies, {res.n_repeats} repeats): {res.n_frames} sweep frames, "
                 f"{res.plan_info['cost_ratio_to_one_at_a_time']:.3f} of the frames one at a time needs for the same accuracy",
             f"time: {elapsed:.1f} s (calibration {t['calibration']:.1f} s, acquisition {t['acquisition']:.1f} s, waiting for the "
             f"fits {t['fit_wait']:.1f} s, estimation {t['estimation']:.1f} s); failed spot fits: {res.n_failed}",
             "status: " + ", ".join(f"{s} {list(res.actuators.status).count(s)}" for s in ("ok", "weak", "dead"))
             + f"; {int(np.sum(res.actuators.poor_fit))} poor_fit (stds inflated)"]
    pace = _pace(res)
    if pace is not None:
        lines.append(pace_line(pace))
    if res.registration is not None:
        lines.append(res.registration.line())
        if support_line(res.support_check):
            lines.append(support_line(res.support_check))
    err = truth_errors(res)
    if err is not None:
        lines.append(f"against the simulated truth: mode {err['mode_hz_max_rel_error'] * 100:.3f} %, damping "
                     f"{err['damping_max_rel_error'] * 100:.2f} %, DC gain {err['dc_gain_max_rel_error'] * 100:.3f} % (largest over live "
                     f"actuators), D0 {err['D0_rms_error_over_max'] * 100:.3f} % rms of its largest element, dead reported dead: "
                     f"{err['dead_reported_dead']}; rms(error/std) over the live actuators: DC gain {err['dc_gain_rms_z']:.2f}, mode "
                     f"{err['mode_hz_rms_z']:.2f}, damping {err['damping_rms_z']:.2f}")
    return lines


def _pace(res) -> dict | None:
    """:func:`~torchblur.identify.keep_up.pace_summary` of a DM run's spot fits (None without their times; without its
    camera's frame rate, an outside recording's, the times only)."""
    fit_s = getattr(res, "fit_s", None)
    if fit_s is None:
        return None
    return pace_summary(fit_s, res.n_frames // len(res.freq_hz), getattr(res, "frame_rate_hz", None), AMPLITUDE_LAG)


def dm_summary(res, v, elapsed: float) -> dict:
    """A DM run's ``--json`` line: its frames, plan, stage times, errors against the simulated
    truth (null on a real rig) and the verdict ``v`` (a :class:`~torchblur.identify.verdict.DMVerdict`)."""
    return {"schema": SUMMARY_SCHEMA[0], "schema_version": SUMMARY_SCHEMA[1][-1], "elapsed_s": elapsed, "frames": res.n_frames,
            "plan": res.plan.kind, "timing_s": res.timing_s, "fit_pace": _pace(res), "truth_errors": truth_errors(res), "verdict": v.line,
            "trustworthy": v.trustworthy, "actuator_flags": {"poor_fit": list(v.poor_fit), "failed": list(v.failed)},
            "failed_spot_fits": v.failed_spot_fits, "spot_problems": v.spot_problems, "poor_spot_fits": v.poor_spot_fits,
            "spot_model_fails": v.spot_model_fails, "beyond_truth": None if v.beyond_truth is None else list(v.beyond_truth)}


def _point_lines(frf, errors) -> list[str]:
    """The table of points, one block per channel: frequency, |H| and phase with their stds and,
    with ``errors`` (:meth:`FrequencyResponse.errors_against` the truth, or None), each point's
    errors against the truth."""
    if errors is not None:
        err_m, err_p, err_z = errors
    head = (f"{'freq_hz':>10} {'|H|':>10} {'+-':>9} {'phase_deg':>10} {'+-':>7}"
            + (f" {'|H| err %':>9} {'ph err deg':>10} {'err/std':>8}" if errors is not None else ""))
    lines = []
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            if not frf.is_siso:
                lines += ["", f"output {frf.output_labels[o]} from input {frf.input_labels[i]}:"]
            lines += ["", head] if frf.is_siso else [head]
            for k in range(len(frf.omega)):
                m, ms = frf.magnitude[o, i, k], frf.magnitude_std[o, i, k]
                p, ps = np.degrees(frf.phase[o, i, k]), np.degrees(frf.phase_std[o, i, k])
                line = f"{frf.freq_hz[k]:10.4g} {m:10.5g} {ms:9.2g} {p:10.3f} {ps:7.3f}"
                if errors is not None:
                    line += f" {err_m[o, i, k] * 100:9.3f} {np.degrees(err_p[o, i, k]):10.3f} {err_z[o, i, k]:8.2f}"
                lines.append(line)
    return lines


def _truth_lines(frf, truth, errors) -> list[str]:
    """The largest ``errors`` (relative |H|, phase rad, error/std; [O, I, F] each) against
    ``truth`` ([O, I, F]) with their goals: one line for one channel (1% and 1 deg), else one
    per channel (2% and 2 deg)."""
    err_m, err_p, err_z = errors
    summary = []
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            em, ep, z = np.abs(err_m[o, i]), np.degrees(np.abs(err_p[o, i])), err_z[o, i]
            with np.errstate(invalid="ignore"):
                summary.append((frf.output_labels[o], frf.input_labels[i], np.nanmax(em) if np.isfinite(em).any() else np.nan,
                                np.nanmax(ep) if np.isfinite(ep).any() else np.nan, np.nanmax(z) if np.isfinite(z).any() else np.nan))
    if frf.is_siso:
        _, _, em, ep, z = summary[0]
        return ["", f"against the truth: max |H| error {em * 100:.3f}% (goal 1%), max phase error "
                    f"{ep:.3f} deg (goal 1 deg), max error/std {z:.2f} (goal 5){_goal_note(em, ep, z, 0.01, 1.0)}"]
    lines = ["", "against the truth, per channel (goal 2% and 2 deg):"]
    for (out_l, in_l, em, ep, z), (o, i) in zip(summary, [(o, i) for o in range(frf.n_outputs) for i in range(frf.n_inputs)]):
        if np.all(np.abs(truth[o, i]) == 0):  # no true motion on this channel: say how small the estimate is
            lines.append(f"  {out_l:>6} from {in_l}: true response 0, max |H| {np.nanmax(frf.magnitude[o, i]):.3g} "
                         f"(max |H| / std {np.nanmax(frf.magnitude[o, i] / frf.magnitude_std[o, i]):.2f})")
            continue
        lines.append(f"  {out_l:>6} from {in_l}: max |H| error {em * 100:.3f}%, max phase error {ep:.3f} deg, "
                     f"max error/std {z:.2f}{_goal_note(em, ep, z, 0.02, 2.0)}")
    return lines


def _model_lines(cfg, m) -> list[str]:
    """The two-step model ``m`` (TransferFunctionFit or None): orders, delay, fit, coefficients
    and parameters, per channel of a MIMO one."""
    if m is None:
        return []
    if m.is_siso:
        lines = ["", f"model: {m.n_poles} poles, {m.n_zeros} zeros, delay {m.delay_s * 1e6:.3f} us, reduced chi2 "
                     f"{m.reduced_chi2:.3f} (dof {m.dof}), rms relative error {m.rms_relative_error:.2e}",
                 f"  num = {list(map(float, m.num))}", f"  den = {list(map(float, m.den))}", *model_parameter_lines(m)]
        return lines + (["  (the two-step model: model_two_step.json)"] if cfg.model.direct else [])
    lines = []
    for o, out_l in enumerate(m.output_labels):
        for i, in_l in enumerate(m.input_labels):
            lines += ["", f"model {out_l} from {in_l}: {m.n_poles[o][i]} poles, {m.n_zeros[o][i]} zeros, delay "
                          f"{m.delay_s[o][i] * 1e6:.3f} us, reduced chi2 {m.reduced_chi2[o][i]:.3f} (dof {m.dof[o][i]}), "
                          f"rms relative error {m.rms_relative_error[o][i]:.2e}",
                      f"  num = {list(map(float, m.num[o][i]))}", f"  den = {list(map(float, m.den[o][i]))}"]
            lines += model_parameter_lines(m, o, i)
    return lines


def _direct_lines(cfg, d) -> list[str]:
    """The direct model ``d`` (DirectModelFit or None; ``model.direct``): its fit, modes and
    whether it passes the verdict's rule."""
    if d is None:
        if not cfg.model.direct:
            return []
        return ["", "direct model: none (see the log above); model.json holds the two-step model where it passed the verdict's "
                    "rule (else the error), model_two_step.json the two-step model"]
    lines = ["", f"direct model ({d.form}, fitted to every image; model.json): delay {d.delay_s * 1e6:.3f} us, reduced chi2 "
                 f"{d.reduced_chi2:.3f} (dof {d.dof}), {d.n_iter} iterations, converged {d.converged}, "
                 f"{int(d.used.sum())} points used, {d.n_excluded} excluded",
             f"  num = {d.num}", f"  den = {d.den}"]
    for mode in d.modal_parameters():
        lines.append(f"  mode: {mode['freq_hz']:.3f} +- {mode['freq_hz_std']:.3f} Hz, damping {mode['zeta']:.4f} +- "
                     f"{mode['zeta_std']:.4f}, gain {mode['gain']:.4g} +- {mode['gain_std']:.2g}")
    for j in judge_fit(d, "direct"):
        if not j.passed:
            lines.append(f"  the direct model fails the verdict's rule ({j.reason}): the stds above understate its error; "
                         "see the verdict for the model model.json holds")
    return lines


def _timing_lines(cfg, res, elapsed: float, source: str) -> list[str]:
    """The method line, the elapsed time (s) and what it covered (``source``: "run" acquired
    frames now; "re-fit" and "outside" read them), the time of each stage where known."""
    what = {"re-fit": "re-fit of recorded frames: no acquisition", "outside": "fit of an outside recording: no acquisition"}.get(
        source, "simulated acquisition and fitting" if cfg.rig.kind == "simulated" else "acquisition and fitting")
    t = getattr(res, "timing", {}) or {}
    lines = ["", _method_line(cfg, res), f"elapsed {elapsed:.1f} s ({what})"]
    if t:
        sweep = "sweep" if source == "run" else "reading the sweep"
        lines.append(f"  calibration {t['calibration_s']:.2f} s, {sweep} {t['sweep_s']:.2f} s, fitting {t['fit_s']:.2f} s in "
                     f"{t['fit_chunks']} chunk(s) of which {t['fit_overlapped_s']:.2f} s during the sweep, "
                     f"{t['after_sweep_s']:.2f} s after the last frame")
    return lines


def _goal_note(err_rel, err_deg, z, goal_rel, goal_deg) -> str:
    """What a goal line says beside its figures, so that it never contradicts the verdict: nothing
    when the relative goals are met; else whether the errors are within 5 of their stds (the
    channel's precision does not reach the goal: its stds say so, the figures are not wrong) or
    beyond them (wrong beyond its stds)."""
    if not (math.isfinite(err_rel) and math.isfinite(err_deg) and math.isfinite(z)) or (err_rel <= goal_rel and err_deg <= goal_deg):
        return ""
    if z <= 5:
        return "; goal not met: the points' stds are larger than the goal (within 5 std of the truth: imprecise, not wrong)"
    return "; goal not met: beyond 5 std of the truth (wrong beyond its stds)"


def _method_line(cfg, res) -> str:
    """What was done: the route, the loss and the PSF (the gain is on the dark line above)."""
    route = (f"multisine ({cfg.excitation.tones} tones per image set)" if cfg.excitation.kind == "multisine"
             else f"sine sweep, {len(cfg.sweep.exposures)} exposure(s) x {cfg.sweep.images_per_point} image(s) per point")
    psf = ("a measured kernel" if isinstance(res.psf, KernelPSF) else
           "a Gaussian per spot" if getattr(res, "spots", None) is not None else "a Gaussian (point-sampled)")
    model = "fitted directly to every image (model.direct)" if cfg.model.direct else "two-step (fitted to the response)"
    return f"method: {route}; fit.loss={cfg.fit.loss}; PSF {psf} (fit.psf={cfg.fit.psf}); model {model}"


def run_summary(res, out: Path, elapsed: float, threshold: float | None = None) -> dict:
    """The ``--json`` line: out dir, points (valid of all), the largest errors against the
    truth where it is known (else null), the fits' status and flag counts by name, the fit
    quality against ``threshold`` (``fit.poor_fit_chi2``), elapsed s, version."""
    frf = res.frf
    doc = {"schema": SUMMARY_SCHEMA[0], "schema_version": SUMMARY_SCHEMA[1][-1],
           "out": str(out), "points": int(frf.valid.size), "valid_points": int(frf.valid.sum()),
           "max_magnitude_error_pct": None, "max_phase_error_deg": None, "max_error_over_std": None}
    if res.truth is not None:
        em, ep, z = frf.errors_against(res.truth)  # NaN where there is no true motion
        for key, v in (("max_magnitude_error_pct", np.abs(em) * 100), ("max_phase_error_deg", np.degrees(np.abs(ep))),
                       ("max_error_over_std", z)):
            v = v[np.isfinite(em) & np.isfinite(v)]
            doc[key] = float(v.max()) if v.size else None
    doc["status"], doc["flags"] = _fit_counts(res.fit, STATUS, FLAGS)
    doc.update(fit_quality(res.fit, threshold)[0])
    doc.update({"elapsed_s": round(float(elapsed), 3), "torchblur_version": tb.__version__})
    return doc


def verdict_summary(v) -> dict:
    """The --json summary's verdict keys: ``verdict`` (the line), ``point_flags`` (counts of
    the response's points by flag), ``flagged_points``, ``trustworthy`` and ``timing_limit_hz``
    (null: none, or unknown)."""
    d = v.to_dict()
    return {"verdict": v.line, "point_flags": {k: d[k] for k in ("poor_fit", "timing", "failed", "limited", "no_motion", "alias")},
            "beyond_truth": d["beyond_truth"], "model_beyond_truth": d["model_beyond_truth"],
            "flagged_points": v.flagged, "timing_limit_hz": d["timing_limit_hz"], "trustworthy": v.trustworthy}


def _fit_counts(fits, status_names: dict, flag_names: dict) -> tuple[dict, dict]:
    """``({status name: count}, {flag name: count})`` over every fit of the run (a fit result
    or a list of them, as the multisine plan has); zero counts left out."""
    fits = fits if isinstance(fits, (list, tuple)) else [fits]
    codes = [np.asarray(f.status).reshape(-1) for f in fits if getattr(f, "status", None) is not None]
    bits = [np.asarray(f.flags).reshape(-1) for f in fits if getattr(f, "flags", None) is not None]
    codes = np.concatenate(codes) if codes else np.zeros(0, dtype=int)
    bits = np.concatenate(bits) if bits else np.zeros(0, dtype=int)
    status = {status_names.get(int(c), str(int(c))): int((codes == c).sum()) for c in np.unique(codes)}
    flags = {name: int(((bits.astype(np.int64) & bit) != 0).sum()) for bit, name in flag_names.items()}
    return status, {k: v for k, v in flags.items() if v}


def _reduced_chi2(fits):
    """Every fitted problem's reduced chi2, flat (NaN where unknown: no noise given, not l2)."""
    fits = fits if isinstance(fits, (list, tuple)) else [fits]
    vals = []
    for f in fits:
        r = getattr(f, "reduced_chi2", None)
        if r is None:
            r = getattr(f, "extras", {}).get("reduced_chi2")
        if r is not None:
            vals.append(np.asarray(r, dtype=float).reshape(-1))
    return np.concatenate(vals) if vals else np.zeros(0)


def fit_quality(fits, threshold: float | None = None) -> tuple[dict, str | None]:
    """``({max_reduced_chi2, poor_fit_problems}, one report line or None)``: whether the model
    explains the images to their noise (reduced chi2 at most ``threshold``, the run's
    ``fit.poor_fit_chi2``; default :data:`POOR_FIT_CHI2`). The stds hold only where it does."""
    red = _reduced_chi2(fits)
    red = red[np.isfinite(red)]
    if not red.size:
        return {"max_reduced_chi2": None, "poor_fit_problems": None}, None
    threshold = POOR_FIT_CHI2 if threshold is None else float(threshold)
    poor = int((red > threshold).sum())
    doc = {"max_reduced_chi2": float(red.max()), "poor_fit_problems": poor}
    if poor:
        line = (f"warning: {poor} of {red.size} fitted problems have a reduced chi2 above {threshold:g} (max "
                f"{red.max():.2f}): the model does not explain their images, and their stds understate the error")
    else:
        line = (f"fit quality: reduced chi2 median {np.median(red):.2f}, max {red.max():.2f} over {red.size} fitted problems "
                f"(all below {threshold:g}: the model explains the images to their noise)")
    return doc, line
