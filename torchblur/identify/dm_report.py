"""A deformable mirror's run written out (``torchblur identify`` and ``torchblur fit`` of a DM
config or recording): :func:`run_cli` runs it (:func:`torchblur.identify.pipeline.identify` with
the DM plan, or an outside recording's), writes ``OUT/dm/`` (:mod:`torchblur.identify.dm_outputs`) and
``OUT/report.txt`` (:func:`torchblur.identify.outputs.write_report`, the DM's section
:func:`torchblur.identify.report.dm_lines`) with the verdict line
(:func:`torchblur.identify.verdict.final_verdict`) last.
"""
from __future__ import annotations

import time
from pathlib import Path

import torch

import torchblur as tb
from torchblur.config import config_to_yaml
from torchblur.dm.registration import DC_GAIN_REFERENCE, write_registration_json
from torchblur.identify.dm_outputs import DMEstimate, write_dm_outputs
from torchblur.identify.dm_plan import DMResult
from torchblur.identify.outputs import write_report
from torchblur.identify.pipeline import identify
from torchblur.identify.record import collect_log
from torchblur.identify.report import dm_lines, dm_summary
from torchblur.identify.verdict import final_verdict

__all__ = ["run_cli"]


def run_cli(cfg, out, *, quiet: bool = False, as_json: bool = False, record=None, rig=None, base_dir: str | None = None,
            plan=None) -> int:
    """``torchblur identify`` for a DM config: run, recorded in ``OUT/experiment/`` (or in
    ``record``: an Experiment to resume, or a read-only one that ``rig``, its
    :class:`~torchblur.hardware.recording.ReplayRig`, re-fits), then write ``OUT/dm/`` and
    ``OUT/report.txt``, the verdict line last in both and on stdout (stderr with ``as_json``, then
    one JSON summary line on stdout: :func:`~torchblur.identify.report.dm_summary`). Returns the
    exit status: the verdict's (0 trustworthy, 4 actuators flagged); a stopped rig raises to the
    CLI, which names the recording. ``plan``: the plan to run instead of the config's, recorded
    nowhere (an outside DM recording's, :class:`torchblur.identify.dm_outside.DMOutsidePlan`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(config_to_yaml(cfg))
    torch.manual_seed(int(cfg.seed))
    t0 = time.perf_counter()
    if record is None and plan is None:
        record = out / "experiment"
    res = identify(cfg, rig, progress=not quiet, record=record, base_dir=base_dir, plan=plan)
    elapsed = time.perf_counter() - t0
    with collect_log() as written:  # the outputs' own lines (dm: N files in ...), after the run's
        _write_dm_outputs(res, out, figures=cfg.report.figures)
    v = final_verdict(res, float(cfg.fit.poor_fit_chi2))
    write_report(out, v, stamp=f"torchblur {tb.__version__}, seed {cfg.seed}", log=[*res.log, *written], body=dm_lines(res, elapsed),
                 summary=dm_summary(res, v, elapsed), as_json=as_json)
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
