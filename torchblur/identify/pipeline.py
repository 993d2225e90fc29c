"""The identification end to end (paper section IV), as stages over one run record
(:class:`~torchblur.identify.record.RunRecord`):

1. **calibrate** (:mod:`torchblur.identify.calibration`): dark frame, saturation curve and
   mask, PSF (one spot, or a grid), trigger-to-exposure latency from laser pulses and, for
   one axis and one spot, the actuator's direction in the image (``fit.axis=measure``);
2. **sweep**: the excitation plan's acquisition (``excitation.kind``: one sine per point,
   :class:`~torchblur.identify.sweep.SinePlan`, the amplitude following the response; or
   multisine groups, :class:`~torchblur.identify.multisine.MultisinePlan`), fitting what is
   complete while it runs;
3. **fit**: the fits of every point;
4. **assemble**: a FrequencyResponse with covariances (fit, trigger jitter and latency
   calibration included), and the truth where the rig knows it;
5. **model**: a transfer-function model fitted to it, weighted by the uncertainties (with
   ``model.direct``, then fitted to every image at once);
6. **report**: the :class:`~torchblur.identify.result.IdentificationResult`.
"""
from __future__ import annotations

import contextlib
import logging
import time

from torchblur.errors import InputTypeError
from torchblur.hardware.errors import HardwareError
from torchblur.identify.calibration import calibrate
from torchblur.identify.config import IdentifyConfig
from torchblur.identify.drive import SESSION_KEY, SLEW_KEY
from torchblur.identify.multisine import MultisinePlan
from torchblur.identify.record import LOGGER, RunRecord, collect_log, console_logging, stage_bar
from torchblur.identify.result import IdentificationResult
from torchblur.identify.rigs import build_rig, open_experiment
from torchblur.identify.stages import run_plan
from torchblur.identify.sweep import SinePlan

__all__ = ["PLANS", "calibrate_stage", "identify", "run_stages"]

HARDWARE_LOGGER = logging.getLogger("torchblur.hardware")  # the rig's messages (faults, retries, reconnects)
PLANS = {"sine": SinePlan, "multisine": MultisinePlan}  # excitation.kind -> its plan of the sweep, fit and assemble stages


def identify(cfg: IdentifyConfig, rig=None, *, progress: bool = True, record=None) -> IdentificationResult:
    """Run the identification on ``rig`` (default: the rig of ``cfg.rig``: the simulated rig,
    or a :class:`~torchblur.hardware.SerialRig` on ``rig.port`` / ``rig.frames``).

    Args:
        cfg: the configuration.
        rig: a :class:`~torchblur.rig.base.Rig`, or None.
        progress: show progress bars (on a terminal) and, where nothing handles the
            ``torchblur`` logger, the run's messages on stderr (:func:`~torchblur.identify.record.console_logging`).
            The messages are in the result's ``log`` either way (:func:`~torchblur.identify.record.collect_log`).
        record: None, a directory, or a :class:`~torchblur.hardware.Experiment`: the run is
            recorded there as it goes (TIFF frames, ``manifest.jsonl``). Groups already
            recorded (a resumed run) are taken from the recording instead of the rig; a
            read-only experiment with :class:`~torchblur.hardware.recording.ReplayRig`
            re-fits a recording offline.

    Raises:
        HardwareError: the rig failed (the recording so far is kept; resume it);
        KeyboardInterrupt: likewise.
    """
    if not isinstance(cfg, IdentifyConfig):
        raise InputTypeError(f"cfg: expected an IdentifyConfig (see torchblur.identify.config.load_config), got {type(cfg).__name__}")
    if rig is not None and not all(hasattr(rig, a) for a in ("frame_shape", "dark", "still", "sine")):
        raise InputTypeError(f"rig: expected a torchblur Rig (frame_shape, dark, still, sine, ...) or None, got {type(rig).__name__}")
    shown = progress and not logging.getLogger("torchblur").hasHandlers()
    with console_logging() if shown else contextlib.nullcontext(), collect_log() as log:
        result = _identify(cfg, rig, progress, record)
    result.log = log
    return result


def _identify(cfg: IdentifyConfig, rig, progress: bool, record) -> IdentificationResult:
    """:func:`identify` after its checks: open the rig and the recording, run the stages."""
    own_rig = rig is None
    if own_rig:
        rig = build_rig(cfg, log=HARDWARE_LOGGER.info)
    elif hasattr(rig, "set_logger"):
        rig.set_logger(HARDWARE_LOGGER.info)
    exp = None
    try:
        exp = open_experiment(record, cfg, rig)
        if exp is not None and exp.writable:
            exp.start_session({"kind": cfg.rig.kind, "port": cfg.rig.port, "frames": cfg.rig.frames, "rig": repr(rig),
                               SESSION_KEY: getattr(rig, "input_limit", None),  # a replay plans with the same range
                               SLEW_KEY: getattr(rig, "slew_limit", None)})
            if exp.meta["sessions"] and len(exp.groups):
                LOGGER.info(f"resume: {len(exp.groups)} recorded group(s) in {exp.path} are reused")
        result = run_stages(RunRecord(cfg=cfg, rig=rig, exp=exp, progress=progress))
    except KeyboardInterrupt:
        if exp is not None:
            exp.end_session("interrupted", "KeyboardInterrupt")
        raise
    except BaseException as exc:
        if exp is not None:
            exp.end_session("stopped" if isinstance(exc, HardwareError) else "failed", f"{type(exc).__name__}: {exc}")
        raise
    finally:
        if own_rig and hasattr(rig, "close"):
            rig.close()
    if exp is not None:
        exp.end_session("complete")
    return result


def run_stages(run: RunRecord) -> IdentificationResult:
    """calibrate -> sweep -> fit -> assemble -> model -> report over ``run`` (its rig and
    recording open); the plan of ``run.cfg.excitation.kind`` does sweep, fit, assemble and
    the report's result."""
    run.t_start = time.perf_counter()
    calibrate_stage(run)
    run.plan = PLANS[run.cfg.excitation.kind]()
    return run_plan(run)


def calibrate_stage(run: RunRecord) -> None:
    """``run.cal``: :func:`~torchblur.identify.calibration.calibrate` (from the recording where it holds it)."""
    with stage_bar(run.progress, "calibration", calibration_stages(run.cfg)):
        run.cal = calibrate(run.cfg, run.rig, run.exp)


def calibration_stages(cfg: IdentifyConfig) -> int:
    """How many recorded stages :func:`~torchblur.identify.calibration.calibrate` takes:
    dark, saturation, PSF, latency and, for one axis and one spot with ``fit.axis=measure``,
    the axis."""
    spots = getattr(cfg, "spots", None) is not None and cfg.spots.enabled
    return 5 if (not cfg.plant.is_mimo and not spots and cfg.fit.axis == "measure") else 4
