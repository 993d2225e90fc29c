"""The files and figures an identification run writes, every plan's (the ``torchblur identify`` and
``fit`` commands call :func:`write_outputs`): frf.csv, frf.mat, frf.json, model.json (and
model_two_step.json), bode.png, residuals.png, ptc.png, or a DM run's ``OUT/dm/``
(:mod:`torchblur.identify.dm_outputs`); and report.txt by :func:`write_report` (its sections from
:mod:`torchblur.identify.report`), the verdict line last.
Figures are matplotlib ``Figure`` objects (:mod:`torchblur.sysid.plots`): the caller's backend is
never switched.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

import torchblur as tb
from torchblur.dm.registration import DC_GAIN_REFERENCE, write_registration_json
from torchblur.identify.assemble import mark_limited
from torchblur.identify.dm_outputs import DMEstimate, write_dm_outputs
from torchblur.identify.dm_plan import DMResult
from torchblur.identify.model import model_exclusions
from torchblur.identify.record import collect_log
from torchblur.identify.report import dm_lines, dm_summary, response_lines, run_summary, verdict_summary
from torchblur.identify.verdict import final_verdict, verdict
from torchblur.image.photon_transfer import photon_transfer_figure
from torchblur.rig.factory import plant_of
from torchblur.sysid.flags import flag_names
from torchblur.sysid.model_check import inflate
from torchblur.sysid.plots import bode_figure, residual_figure

__all__ = ["exposure_label", "left_out_points", "write_bode", "write_dm_run", "write_figures", "write_models",
           "write_outputs", "write_ptc_figure", "write_report", "write_residuals"]


def write_outputs(cfg, res, out: Path, elapsed: float, stamp: str, as_json: bool = False, source: str = "run"):
    """frf.csv, frf.mat, frf.json, model.json, bode.png, residuals.png (a DM run's
    :class:`~torchblur.identify.dm_plan.DMResult`: ``OUT/dm/``, :func:`write_dm_run`), then
    report.txt and the terminal's lines (:func:`write_report`; the JSON summary:
    :func:`run_summary`). ``source``: "run" (frames acquired now), "re-fit" (of a recording) or
    "outside" (an outside recording). Returns the :class:`~torchblur.identify.verdict.Verdict`
    (exit_code: 0 trustworthy, 4 flagged)."""
    if isinstance(res, DMResult):
        return write_dm_run(cfg, res, out, elapsed, stamp, as_json=as_json)
    frf = res.frf  # immutable: a copy with the run's stamp and units (the Bode plot's axes) in its meta
    meta = {"output_unit": "px", "input_unit": "input unit", **frf.meta, "torchblur_version": tb.__version__, "seed": int(cfg.seed)}
    frf = res.frf = mark_limited(frf.replace(meta=meta), getattr(res, "limited", None))
    v = verdict(frf, cfg, motion_px=_motion_px(res), model=getattr(res, "model", None), direct=getattr(res, "direct_model", None),
                expected=("two-step", "direct") if cfg.model.direct else ("two-step",), truth=getattr(res, "truth", None))
    frf.to_csv(out / "frf.csv", extra_columns={"torchblur_version": tb.__version__, "seed": cfg.seed})
    frf.to_mat(out / "frf.mat")
    frf.to_json(out / "frf.json")
    write_models(cfg, res, out, v.models)
    write_figures(cfg, res, out, stamp)
    write_report(out, v, stamp=stamp, log=res.log, body=response_lines(cfg, res, elapsed, source), as_json=as_json,
                 summary={**run_summary(res, out, elapsed, cfg.fit.poor_fit_chi2), **verdict_summary(v)})
    return v


def write_dm_run(cfg, res: DMResult, out: Path, elapsed: float, stamp: str, as_json: bool = False):
    """A DM run's ``OUT/dm/`` (:func:`~torchblur.identify.dm_outputs.write_dm_outputs`, ``registration.json``) and
    report.txt (:func:`~torchblur.identify.report.dm_lines`, :func:`~torchblur.identify.report.dm_summary`) with
    the verdict of every DM guard (:func:`~torchblur.identify.verdict.final_verdict`) last; returns it."""
    meta = {"plan": res.plan.kind, "n_patterns": res.plan.n_patterns, "n_repeats": res.n_repeats,
            "n_frames": res.n_frames}
    reg = res.registration
    reference = {"dc_gain_reference": DC_GAIN_REFERENCE} if reg and reg.ok else {}
    unverified = tuple(((reg.edge_test or {}).get("gains_unverified") or ()) if reg is not None else ())
    with collect_log() as written:  # the outputs' own lines (dm: N files in ...), after the run's
        write_dm_outputs(out, DMEstimate(freq_hz=res.freq_hz, D=res.D, D_cov=res.D_cov, table=res.actuators, meta=meta,
                                         gains_unverified=unverified), figures=cfg.report.figures, **reference)
        if reg is not None:
            write_registration_json(out / "dm" / "registration.json", reg, res.support_check)
    v = final_verdict(res, float(cfg.fit.poor_fit_chi2))
    write_report(out, v, stamp=stamp, log=[*res.log, *written], body=dm_lines(res, elapsed),
                 summary=dm_summary(res, v, elapsed), as_json=as_json)
    return v


def write_report(out: Path, v, *, stamp: str, log, body, summary: dict, as_json: bool = False) -> None:
    """report.txt of any plan's run: its title (``stamp``), the run's ``log`` (shown on the terminal
    as it came), the plan's section ``body`` (lines: :func:`~torchblur.identify.report.response_lines`,
    :func:`~torchblur.identify.report.dm_lines`), the verdict's details and its line last
    (``v``, a :class:`~torchblur.identify.verdict.Verdict`). Then ``body``, what was written and
    the details and verdict on stdout, or with ``as_json`` on stderr and the one JSON ``summary``
    line on stdout. Written after every other output: a run whose report.txt is there is finished."""
    tail = [*v.details, v.line]
    (out / "report.txt").write_text("\n".join([f"torchblur identify report ({stamp})", "", *log, *body, "", *tail]) + "\n")
    human = sys.stderr if as_json else sys.stdout
    print("\n".join(body), file=human)
    print(f"wrote {', '.join(sorted(p.name for p in out.iterdir()))} in {out}", file=human)
    print("\n".join(tail), file=human, flush=True)
    if as_json:
        print(json.dumps(summary), flush=True)


def _motion_px(res):
    """[O, I, F] motion each point reached (px): |H| times the point's input amplitude; None
    where the amplitudes do not map onto the response's points."""
    frf = res.frf
    n_o, n_i, n_f = frf.response.shape
    a = getattr(res, "amplitude", None)
    a = None if a is None else np.asarray(a, dtype=np.float64).reshape(-1)
    if a is None or a.size != n_i * n_f:
        return None
    return frf.magnitude * a.reshape(1, n_i, n_f)


def write_models(cfg, res, out: Path, judged=()) -> None:
    """model.json (and, with ``model.direct``, model_two_step.json), each model with the
    verdict's ``judgement`` (:mod:`torchblur.sysid.model_check`, one per channel) and
    ``model_passed``; a model that failed has its stds inflated (``std_factor``). With
    ``model.direct``, model.json holds the direct model unless it failed and the two-step one
    passed: then the two-step model, the direct one under ``rejected_direct_model``."""
    two_j = [j for j in judged if j.name.startswith("two-step")]
    d_j = [j for j in judged if not j.name.startswith("two-step")]
    model = {"torchblur_version": tb.__version__, "seed": int(cfg.seed)}
    if res.model is not None:
        model.update(inflate(res.model, two_j).to_dict())
        model.update(left_out_points(cfg, res.frf))
        model.update(judgement=[j.to_dict() for j in two_j], model_passed=bool(two_j) and all(j.passed for j in two_j))
    else:
        model["error"] = "the model fit failed; see report.txt"
    direct = getattr(res, "direct_model", None)
    if cfg.model.direct:
        # model.json holds the direct model; the two-step one it started from is kept beside it.
        (out / "model_two_step.json").write_text(json.dumps(model, indent=2))
        two_step, model = model, {"torchblur_version": tb.__version__, "seed": int(cfg.seed)}
        if direct is not None:
            model.update(inflate(direct, d_j).to_dict())
            model.update(judgement=[j.to_dict() for j in d_j], model_passed=bool(d_j) and d_j[0].passed)
            if not model["model_passed"] and two_step.get("model_passed"):
                model = {**two_step, "rejected_direct_model": model}
        elif two_step.get("model_passed"):
            model = {**two_step, "direct_model_error": "the direct fit failed or was skipped; see report.txt"}
        else:
            model["error"] = "the direct fit failed or was skipped; see report.txt (the two-step model is in model_two_step.json)"
    (out / "model.json").write_text(json.dumps(model, indent=2))


def left_out_points(cfg, frf) -> dict:
    """model.json's ``left_out_points`` (the poor-fit and alias points the model was not fitted to:
    freq_hz, output, input, reduced_chi2, flags) and ``poor_fit_points_kept`` (channels where too few
    points would have remained: output, input, count) by
    :func:`~torchblur.identify.model.model_exclusions`."""
    left_out, kept = model_exclusions(frf, cfg)
    pts = [{"freq_hz": float(frf.freq_hz[k]), "output": frf.output_labels[o], "input": frf.input_labels[i],
            "reduced_chi2": float(frf.reduced_chi2[o, i, k]), "flags": flag_names(frf.flags[o, i, k])}
           for o, i, k in zip(*np.nonzero(left_out))]
    return {"left_out_points": pts, "poor_fit_points_kept": [{"output": o, "input": i, "count": n} for o, i, n in kept]}


def write_figures(cfg, res, out: Path, stamp: str) -> None:
    """bode.png (with the truth where known), residuals.png (the worst fits) and ptc.png; none
    with ``report.figures=false`` (every number file is written all the same)."""
    if not cfg.report.figures:
        return
    write_bode(cfg, res, out, stamp)
    write_residuals(res, out, stamp)
    write_ptc_figure(cfg, res, out, stamp)


def write_bode(cfg, res, out: Path, stamp: str) -> None:
    """bode.png: the response, the model, the truth where known."""
    frf = res.frf
    truth = None
    if res.truth is not None:
        if getattr(res, "spots", None) is not None:
            truth = res.truth  # [O, I, F] at the measured points
        else:
            truth = plant_of(cfg).frequency_response
    frame_rate = None if cfg.rig.kind == "outside" else float(cfg.camera.frame_rate_hz)  # an outside recording's is unknown
    fig = bode_figure(frf, model=res.model, truth=truth, stamp=stamp, frame_rate_hz=frame_rate)
    fig.savefig(out / "bode.png", dpi=110 if frf.n_outputs <= 2 else 80, metadata={"Description": stamp})


def write_residuals(res, out: Path, stamp: str) -> None:
    """residuals.png: the worst fits' data, model and residual."""
    exposures = None
    if hasattr(res, "residual_panels"):  # multisine: one panel per image set
        data, models, labels = res.residual_panels(3)
        reason = f"the {len(labels)} groups with the largest fit cost per pixel"
    else:
        cost = res.fit.cost.reshape(-1).numpy()
        n_pix = res.images.shape[-3] * res.images.shape[-2] * res.images.shape[-1]
        worst = [int(q) for q in np.argsort(np.nan_to_num(cost / max(1, n_pix), nan=-np.inf))[-3:][::-1]]
        masks = _problem_flags(res)
        extra = _one_per_flag(masks, worst)
        data, models, labels, exposures = _fitted_images(res, worst + extra)
        labels = [lab + (f" [{flag_names(masks[q])}]" if masks[q] else "") for lab, q in zip(labels, worst + extra)]
        reason = f"the {len(worst)} points with the largest fit cost per pixel" + (
            f", and {len(extra)} more so that each flag kind is shown" if extra else "")
    sigma = None
    if getattr(res, "noise", None) is not None:  # the residual in units of the noise the fit weighed each pixel by
        sigma = res.noise.std(torch.as_tensor(models, dtype=torch.float64)).numpy()
        sigma = sigma if np.all(sigma > 0) else None  # a noiseless camera model: the residual in e- instead
    fig = residual_figure(data, models, labels, stamp=stamp, unit="e-", exposures=exposures, reason=reason, sigma=sigma)
    fig.savefig(out / "residuals.png", dpi=90, metadata={"Description": stamp})


def write_ptc_figure(cfg, res, out: Path, stamp: str) -> None:
    """ptc.png: the photon transfer curve the calibration measured (where it did), with camera.gain's line."""
    ptc = getattr(res, "ptc", None)
    if ptc is None:
        return
    fig = photon_transfer_figure(ptc, configured_gain=float(cfg.camera.gain))
    fig.savefig(out / "ptc.png", dpi=90, metadata={"Description": stamp})


def _problem_flags(res):
    """The flag mask (:mod:`torchblur.sysid.flags`) of each problem of ``res.fit`` (flat
    index), int [n]: its point's flags, OR-ed over the outputs of its input."""
    frf = res.frf
    F = len(frf.omega)
    if res.fit.amplitude.dim() == 1:
        return np.asarray(frf.flags[0, 0], dtype=np.int64)
    P = res.fit.amplitude.shape[1]
    per_point = np.bitwise_or.reduce(np.asarray(frf.flags, dtype=np.int64), axis=0)  # [I, F]
    return np.array([per_point[(q // P) // F, (q // P) % F] for q in range(res.fit.cost.numel())], dtype=np.int64)


def _one_per_flag(masks, shown: list, most: int = 3) -> list:
    """Problems (flat indices) to show besides ``shown`` so that each flag kind present in
    ``masks`` appears at least once (the first problem carrying it), at most ``most``."""
    extra = []
    for b in range(63):
        bit = 1 << b
        if len(extra) >= most or not any(int(m) & bit for m in masks) or any(int(masks[q]) & bit for q in shown + extra):
            continue
        extra.append(next(q for q, m in enumerate(masks) if int(m) & bit))
    return extra


def _fitted_images(res, idx):
    """The first frame of problems ``idx`` (flat indices of ``res.fit``), its fitted model, a
    label and its exposure each (for the residual figure): ``(data [n, h, w], models [n, h, w],
    labels, exposures)``, an exposure like ``"exposure 1 of 2 (0.5-3 ms)"``."""
    frf = res.frf
    single = res.fit.amplitude.dim() == 1
    F = len(frf.omega)
    P = 1 if single else res.fit.amplitude.shape[1]
    data, out, labels, exposures = [], [], [], []
    for q in idx:
        q = int(q)
        j, p = divmod(q, P)
        k = j % F
        if single:
            img_d = res.images[j, 0]
            w_point = res.windows[j]
            label = f"{frf.freq_hz[k]:.4g} Hz"
        else:
            ii = j // F
            img_d = res.images[ii, k, p, 0]
            w_point = res.windows[ii, k]
            label = f"{frf.freq_hz[k]:.4g} Hz, input {res.inputs[ii]}" + (f", spot s{p}" if res.spots is not None else "")
        data.append(img_d.numpy())
        labels.append(label)
        w = w_point[0]
        exposures.append(exposure_label(w_point))
        fit = res.fit
        at = (j,) if single else (j, p)
        if not bool(fit.converged[at]):
            out.append(np.zeros_like(img_d.numpy()))
            continue
        if single:
            amp = torch.stack([fit.amplitude[j], torch.zeros_like(fit.amplitude[j])])
            ph = fit.phase[j].expand(2)
            psf = res.psf
        else:
            amp, ph = fit.amplitude[j, p], fit.phase[j, p]
            psf = res.spots.psf_in_crops()[p] if res.spots is not None else res.psf
        scale = res.power[j] * (fit.scale[at] if fit.scale is not None else 1.0)
        psf = tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * scale)
        om = 2 * math.pi * float(frf.freq_hz[k])
        img = tb.render_blur(tb.Sinusoid(amp, ph, om), psf, w, height=img_d.shape[-2], width=img_d.shape[-1])
        if fit.background is not None:
            img = img + fit.background[at]
        out.append(img.detach().numpy())
    return np.stack(data), np.stack(out), labels, exposures


def exposure_label(window, index: int = 0) -> str:
    """``"exposure e of E, L ms long (start-end ms), image r of R"`` of image ``index`` of one
    point's ``window`` ``[E*R]``: E distinct exposures (start, duration), each repeated R times
    in a row (the sweep's layout)."""
    start, dur = window.start.reshape(-1).tolist(), window.duration.reshape(-1).tolist()
    distinct = list(dict.fromkeys(zip(start, dur)))
    R = max(1, len(start) // max(1, len(distinct)))
    e = distinct.index((start[index], dur[index]))
    r = sum(1 for q in range(index) if (start[q], dur[q]) == distinct[e])
    s, d = start[index] * 1e3, dur[index] * 1e3
    return f"exposure {e + 1} of {len(distinct)}, {d:.3g} ms long ({s:.3g}-{s + d:.3g} ms), image {r + 1} of {R}"
