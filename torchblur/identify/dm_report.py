"""A deformable mirror's run written out (``torchblur identify`` and ``torchblur fit`` of a DM
config or recording): :func:`run_cli` runs it (:func:`torchblur.identify.pipeline.identify` with
the DM plan) or takes a fitted one, writes ``OUT/dm/`` (:mod:`torchblur.identify.dm_outputs`) and
``OUT/report.txt`` with the verdict line (:func:`torchblur.identify.dm_verdict.final_verdict`) last.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchblur.dm.registration import DC_GAIN_REFERENCE, support_line, write_registration_json
from torchblur.config import config_to_yaml
from torchblur.identify.dm_outputs import DMEstimate, write_dm_outputs
from torchblur.identify.dm_plan import DMResult, truth_errors
from torchblur.identify.dm_verdict import final_verdict
from torchblur.identify.pipeline import identify
from torchblur.identify.read_outputs import SUMMARY_SCHEMA
from torchblur.identify.record import collect_log

__all__ = ["run_cli"]


def _report(res: DMResult, elapsed: float) -> str:
    """The run's summary lines."""
    t = res.timing_s
    lines = [f"dm run: {len(res.actuators)} actuators, {res.G.shape[0] // 2} spots, plan {res.plan.kind} ({res.plan.n_patterns} "
             f"patterns x {len(res.freq_hz)} frequencies, {res.n_repeats} repeats): {res.n_frames} sweep frames, "
             f"{res.plan_info['cost_ratio_to_one_at_a_time']:.3f} of the frames one at a time needs for the same accuracy",
             f"time: {elapsed:.1f} s (calibration {t['calibration']:.1f} s, acquisition {t['acquisition']:.1f} s, waiting for the "
             f"fits {t['fit_wait']:.1f} s, estimation {t['estimation']:.1f} s); failed spot fits: {res.n_failed}",
             "status: " + ", ".join(f"{s} {list(res.actuators.status).count(s)}" for s in ("ok", "weak", "dead"))
             + f"; {int(np.sum(res.actuators.poor_fit))} poor_fit (stds inflated)"]
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
    return "\n".join(lines) + "\n"


def run_cli(cfg, out, *, quiet: bool = False, as_json: bool = False, record=None, rig=None, base_dir: str | None = None,
            run=None) -> int:
    """``torchblur identify`` for a DM config: run, recorded in ``OUT/experiment/`` (or in
    ``record``: an Experiment to resume, or a read-only one that ``rig``, its
    :class:`~torchblur.hardware.recording.ReplayRig`, re-fits), then write ``OUT/dm/`` and
    ``OUT/report.txt``, the verdict line (:func:`torchblur.identify.dm_verdict.final_verdict`) last in both
    and on stdout (stderr with ``as_json``, then one JSON summary line on stdout, with
    ``verdict`` and ``trustworthy``). Returns the exit status: the verdict's (0 trustworthy, 4
    actuators flagged); a stopped rig raises to the CLI, which names the recording. ``run``: a
    callable that gives the :class:`DMResult` instead of a run (an outside DM recording's fit,
    :func:`torchblur.identify.dm_outside.run_recording`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(config_to_yaml(cfg))
    torch.manual_seed(int(cfg.seed))
    t0 = time.perf_counter()
    res = run() if run is not None else identify(cfg, rig, progress=not quiet, record=out / "experiment" if record is None else record,
                                                 base_dir=base_dir)
    elapsed = time.perf_counter() - t0
    with collect_log() as written:  # the outputs' own lines (dm: N files in ...), after the run's
        _write_dm_outputs(res, out, figures=cfg.report.figures)
    v = final_verdict(res, float(cfg.fit.poor_fit_chi2))
    report = _report(res, elapsed) + "".join(f"{line}\n" for line in (*v.details, v.line))  # the verdict line last
    (out / "report.txt").write_text("\n".join([*res.log, *written]) + "\n" + report)
    print(report, end="", file=sys.stderr if as_json else sys.stdout, flush=True)
    if as_json:
        print(json.dumps({"schema": SUMMARY_SCHEMA[0], "schema_version": SUMMARY_SCHEMA[1][-1],
                          "elapsed_s": elapsed, "frames": res.n_frames, "plan": res.plan.kind, "timing_s": res.timing_s,
                          "truth_errors": truth_errors(res), "verdict": v.line, "trustworthy": v.trustworthy,
                          "actuator_flags": {"poor_fit": list(v.poor_fit), "failed": list(v.failed)},
                          "failed_spot_fits": v.failed_spot_fits, "spot_problems": v.spot_problems, "poor_spot_fits": v.poor_spot_fits,
                          "spot_model_fails": v.spot_model_fails,
                          "beyond_truth": None if v.beyond_truth is None else list(v.beyond_truth)}), flush=True)
    return v.exit_code


def _write_dm_outputs(res: DMResult, out, figures: bool = True) -> None:
    """``OUT/dm/`` by :func:`torchblur.identify.dm_outputs.write_dm_outputs` (``figures``: ``report.figures``)."""
    meta = {"plan": res.plan.kind, "n_patterns": res.plan.n_patterns, "n_repeats": res.n_repeats, "n_frames": res.n_frames}
    reg = res.registration
    reference = {"dc_gain_reference": DC_GAIN_REFERENCE} if reg and reg.ok else {}
    unverified = tuple(((reg.edge_test or {}).get("gains_unverified") or ()) if reg is not None else ())
    write_dm_outputs(out, DMEstimate(freq_hz=res.freq_hz, D=res.D, D_cov=res.D_cov, table=res.actuators, meta=meta,
                                     gains_unverified=unverified), figures=figures, **reference)
    if res.registration is not None:
        write_registration_json(out / "dm" / "registration.json", res.registration, res.support_check)
