"""The stages after the calibration, over one run record whose ``plan`` (the excitation's)
does the sweep, fit, assemble and report parts: :func:`run_plan` is ``sweep -> fit ->
assemble -> adequacy -> model -> report`` (adequacy: each point's flags,
:func:`~torchblur.identify.assemble.adequacy_stage`); :func:`model_stage` is the one model stage of every plan."""
from __future__ import annotations

from torchblur.identify.assemble import adequacy_stage
from torchblur.identify.model import fit_model
from torchblur.identify.record import RunRecord, progress_bar

__all__ = ["model_stage", "run_plan"]


def run_plan(run: RunRecord):
    """sweep -> fit -> assemble -> model -> report of ``run`` (calibrated: ``run.cal`` set)
    by its ``run.plan``; returns the plan's result. The model stages are :func:`adequacy_stage`
    and :func:`model_stage`, or the plan's ``model_stages`` (the DM's: none, its assemble fits each actuator's model)."""
    run.plan.sweep(run)  # its own bar, per point or group
    stages = (run.plan.fit, run.plan.assemble, *getattr(run.plan, "model_stages", (adequacy_stage, model_stage)))
    bar = progress_bar(run.progress, total=len(stages), desc="fit and model", unit="stage", leave=False)
    try:
        for stage in stages:
            bar.set_postfix_str(stage.__name__, refresh=True)
            stage(run)
            bar.update(1)
    finally:
        bar.close()
    return run.plan.result(run)


def model_stage(run: RunRecord) -> None:
    """``run.model`` (:func:`~torchblur.identify.model.fit_model`) and, with ``model.direct``
    and a plan that supports it, ``run.direct_model`` fitted to every image from it."""
    run.model = fit_model(run.cfg, run.frf)
    if not (run.cfg.model.direct and run.plan.supports_direct):
        return
    if run.model is None:
        run.say("direct: skipped (no two-step model to start from)")
    else:
        run.direct_model = run.plan.fit_direct(run)
