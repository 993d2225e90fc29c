"""The run record: the one object the identification's stages read and fill.

:func:`torchblur.identify.pipeline.identify` is ``calibrate -> sweep -> fit -> assemble ->
model -> report``; each stage is a function of a :class:`RunRecord` that adds its part
(``cal``, ``acquisition``, ``fit``, ``frf`` and ``truth``, ``model`` and ``direct_model``,
the result). What differs between excitations (one sine per point, or multisine groups) is
the record's ``plan`` (:mod:`torchblur.identify.sweep`, :mod:`torchblur.identify.multisine`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from tqdm.auto import tqdm

__all__ = ["RunRecord", "log_message", "run_stage"]


@dataclass
class RunRecord:
    """Everything one identification run has so far.

    ``cfg`` (IdentifyConfig), ``rig``, ``exp`` (the Experiment it is recorded in, or None),
    ``log`` (messages), ``progress`` (print them, show bars), ``t_start`` (perf_counter s);
    then, stage by stage: ``cal`` (Calibration), ``plan`` (the excitation's plan),
    ``acquisition`` (the plan's sweep: frames, windows, amplitudes, its fits as they come),
    ``fit`` (the fits of every point), ``frf`` (FrequencyResponse), the fitted ``images``,
    their ``windows`` and laser ``power`` (shapes as in the result) and ``truth``, ``model``
    (TransferFunctionFit or None) and ``direct_model``, ``timing`` (seconds per stage)."""

    cfg: object
    rig: object
    exp: object = None
    log: list = field(default_factory=list)
    progress: bool = True
    t_start: float = 0.0
    cal: object = None
    plan: object = None
    acquisition: object = None
    fit: object = None
    frf: object = None
    images: object = None
    windows: object = None
    power: object = None
    truth: object = None
    model: object = None
    direct_model: object = None
    timing: dict = field(default_factory=dict)

    def say(self, msg: str) -> None:
        """Log ``msg`` (and print it with ``progress``)."""
        log_message(self.log, msg, self.progress)


def log_message(log: list, msg: str, progress: bool) -> None:
    """Append ``msg`` to ``log``; print it (above any progress bar) if ``progress``."""
    log.append(msg)
    if progress:
        tqdm.write(msg)


def run_stage(exp, key: str, kind: str, rig, fn):
    """``fn(rig)``, or with a recording ``exp`` the recorded result of group ``key`` (taken
    and recorded now if it is not there yet)."""
    if exp is None:
        return fn(rig)
    return exp.stage(key, kind, rig, fn)[0]
