"""The identification end to end (paper section IV): :func:`identify` runs calibrate -> sweep ->
fit -> assemble -> model -> report over one run record
(:class:`~torchblur.identify.record.RunRecord`), the sweep, fit and assemble stages (and a
DM's opening and calibration) by the run's plan (:data:`PLANS`: sine, multisine, DM; or an
outside recording's). The stages and where each lives: docs/architecture.md.
"""
from __future__ import annotations

import contextlib
import logging
import time

from torchblur.errors import InputTypeError, check_type
from torchblur.identify.calibration import calibrate
from torchblur.config import IdentifyConfig
from torchblur.identify.dm_plan import DMPlan, DMResult, check_dm_config
from torchblur.identify.multisine import MultisinePlan
from torchblur.identify.record import HARDWARE_LOGGER, RunRecord, collect_log, console_logging, stage_bar
from torchblur.identify.result import IdentificationResult
from torchblur.identify.rigs import build_rig, open_experiment, session, session_info
from torchblur.identify.stages import run_plan
from torchblur.identify.sweep import SinePlan

__all__ = ["PLANS", "calibrate_stage", "identify", "plan_kind", "run_stages"]

#: the plan of the sweep, fit and assemble stages of each kind of run (:func:`plan_kind`)
PLANS = {"sine": SinePlan, "multisine": MultisinePlan, "dm": DMPlan}


def plan_kind(cfg: IdentifyConfig) -> str:
    """The key of ``cfg``'s plan in :data:`PLANS`: ``"dm"`` for a deformable mirror (``dm.n_across`` > 0), else ``excitation.kind``."""
    return "dm" if cfg.dm.enabled else cfg.excitation.kind


def identify(cfg: IdentifyConfig, rig=None, *, progress: bool = True, record=None, base_dir: str | None = None,
             executor=None, plan=None) -> IdentificationResult | DMResult:
    """Run the identification on ``rig`` (default: the rig of ``cfg.rig``: the simulated rig,
    or a :class:`~torchblur.hardware.SerialRig` on ``rig.port`` / ``rig.frames``), with the plan
    of ``cfg`` (:func:`plan_kind`); a deformable mirror's (``dm.n_across`` > 0) gives a
    :class:`~torchblur.identify.dm_plan.DMResult`.

    Args:
        cfg: the configuration.
        rig: a :class:`~torchblur.rig.base.Rig` (a deformable mirror's: a
            :class:`~torchblur.rig.dm_contract.DMRig`, checked before the first frame, docs/dm_rig.md), or None.
        progress: show progress bars (on a terminal) and, where nothing handles the
            ``torchblur`` logger, the run's messages on stderr (:func:`~torchblur.identify.record.console_logging`).
            The messages are in the result's ``log`` either way (:func:`~torchblur.identify.record.collect_log`).
        record: None, a directory, or a :class:`~torchblur.hardware.Experiment`: the run is
            recorded there as it goes (TIFF frames, ``manifest.jsonl``). Groups already
            recorded (a resumed run) are taken from the recording instead of the rig; a
            read-only experiment with :class:`~torchblur.hardware.recording.ReplayRig`
            re-fits a recording offline.
        base_dir: where a relative ``dm.actuator_table`` is read from (a DM run's simulated mirror).
        executor: a :class:`concurrent.futures.Executor` (Dask's ``client.get_executor()``
            included) the DM plan's spot fits are submitted to; None: one worker thread.
        plan: the plan to run instead of ``cfg``'s (:func:`plan_kind`): an outside DM recording's
            (:class:`~torchblur.identify.dm_outside.DMOutsidePlan`, no rig and no ``record``).

    Raises:
        HardwareError: the rig failed (the recording so far is kept; resume it);
        KeyboardInterrupt: likewise;
        InputTypeError: ``cfg`` is not an IdentifyConfig, or ``rig`` is not a rig of its plan;
        ConfigError: a DM rig with a config that is not a DM run's (``dm.n_across``), or a DM rig that does not match its config.
    """
    check_type(cfg, "cfg", IdentifyConfig, "an IdentifyConfig (see torchblur.config.load_config)")
    plan = PLANS[plan_kind(cfg)]() if plan is None else plan
    getattr(plan, "check", _check_rig)(cfg, rig)
    shown = progress and not logging.getLogger("torchblur").hasHandlers()
    with console_logging() if shown else contextlib.nullcontext(), collect_log() as log:
        with getattr(plan, "open", open_run)(cfg, rig, progress=progress, record=record, base_dir=base_dir, executor=executor) as run:
            run.plan = plan
            result = run_stages(run)
    result.log = log
    return result


def _check_rig(cfg: IdentifyConfig, rig) -> None:
    """Refuse a ``rig`` that is not a sine or multisine run's (a DM rig: its config is not a DM run's, ``dm.n_across``)."""
    if rig is not None and not all(hasattr(rig, a) for a in ("frame_shape", "dark", "still", "sine")):
        if hasattr(rig, "pattern_sine"):  # a deformable mirror's rig
            check_dm_config(cfg)
        raise InputTypeError(f"rig: expected a torchblur Rig (frame_shape, dark, still, sine, ...) or None, got {type(rig).__name__}")


@contextlib.contextmanager
def open_run(cfg: IdentifyConfig, rig, *, progress: bool, record, base_dir: str | None = None, executor=None):
    """The :class:`~torchblur.identify.record.RunRecord` of a sine or multisine run: its rig
    opened (``rig``, or the rig of ``cfg.rig``, closed after the run) and its recording with the
    run's session (:func:`~torchblur.identify.rigs.session`); a plan with its own (the DM's) opens its run itself.
    ``base_dir``: unused (no actuator table)."""
    own_rig = rig is None
    if own_rig:
        rig = build_rig(cfg, log=HARDWARE_LOGGER.info)
    elif hasattr(rig, "set_logger"):
        rig.set_logger(HARDWARE_LOGGER.info)
    try:
        exp = open_experiment(record, cfg, rig)
        with session(exp, session_info(cfg, rig)):
            yield RunRecord(cfg=cfg, rig=rig, exp=exp, progress=progress, executor=executor)
    finally:
        if own_rig and hasattr(rig, "close"):
            rig.close()


def run_stages(run: RunRecord) -> IdentificationResult:
    """calibrate -> sweep -> fit -> assemble -> model -> report over ``run`` (its rig and
    recording open); the plan of ``run.cfg`` (:func:`plan_kind`, unless ``run.plan`` is set) does
    sweep, fit, assemble and the report's result."""
    run.t_start = time.perf_counter()
    if run.plan is None:
        run.plan = PLANS[plan_kind(run.cfg)]()
    calibrate_stage(run)
    return run_plan(run)


def calibrate_stage(run: RunRecord) -> None:
    """``run.cal``: :func:`~torchblur.identify.calibration.calibrate` (from the recording where it
    holds it), or the plan's own calibration stage where it has one (the DM's: the sensor's spots)."""
    if hasattr(run.plan, "calibrate"):
        run.plan.calibrate(run)
        return
    with stage_bar(run.progress, "calibration", calibration_stages(run.cfg)):
        run.cal = calibrate(run.cfg, run.rig, run.exp)


def calibration_stages(cfg: IdentifyConfig) -> int:
    """How many recorded stages :func:`~torchblur.identify.calibration.calibrate` takes:
    dark, saturation, PSF, latency and, for one axis and one spot with ``fit.axis=measure``,
    the axis."""
    spots = getattr(cfg, "spots", None) is not None and cfg.spots.enabled
    return 5 if (not cfg.plant.is_mimo and not spots and cfg.fit.axis == "measure") else 4
