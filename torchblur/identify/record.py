"""The run record (:class:`RunRecord`): the one object the identification's stages
(:mod:`torchblur.identify.pipeline`) read and fill, each adding its part.

The run's messages go to the ``torchblur`` logger (``torchblur.identify`` and its children,
``torchblur.hardware`` for the rig's); nothing here prints. :func:`collect_log` (a
:class:`RunLog` handler) gathers them, in order, into the result's ``log`` for the report;
:func:`console_logging` shows them on stderr above any progress bar (the CLI does, and
:func:`~torchblur.identify.pipeline.identify` does with ``progress`` when nothing else handles
the ``torchblur`` logger). Progress bars (:func:`progress_bar`) show only on a terminal.
"""
from __future__ import annotations

import contextlib
import contextvars
import logging
import sys
from dataclasses import dataclass, field

from tqdm.auto import tqdm

__all__ = ["HARDWARE_LOGGER", "LOGGER", "RunLog", "RunRecord", "collect_log", "console_logging", "progress_bar", "run_stage", "stage_bar"]

LOGGER = logging.getLogger("torchblur.identify")
HARDWARE_LOGGER = logging.getLogger("torchblur.hardware")  # the rig's messages (faults, retries, reconnects, its link's statistics)
_STAGE_BAR: contextvars.ContextVar = contextvars.ContextVar("torchblur_stage_bar", default=None)


@dataclass
class RunRecord:
    """Everything one identification run has so far.

    ``cfg`` (IdentifyConfig), ``rig``, ``exp`` (the Experiment it is recorded in, or None),
    ``progress`` (show bars), ``t_start`` (perf_counter s);
    then, stage by stage: ``cal`` (Calibration), ``plan`` (the excitation's plan),
    ``acquisition`` (the plan's sweep: frames, windows, amplitudes, its fits as they come),
    ``fit`` (the fits of every point), ``frf`` (FrequencyResponse), the fitted ``images``,
    their ``windows`` and laser ``power`` (shapes as in the result) and ``truth``, ``model``
    (TransferFunctionFit or None) and ``direct_model``, ``timing`` (seconds per stage);
    ``executor``: the :class:`concurrent.futures.Executor` a plan may submit its fits to (None: its own worker thread).
    The run's messages go to :data:`LOGGER` (:meth:`say`), not to the record."""

    cfg: object
    rig: object
    exp: object = None
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
    executor: object = None

    def say(self, msg: str) -> None:
        """Log ``msg`` to the ``torchblur.identify`` logger at INFO (:func:`collect_log` gathers it for the report)."""
        LOGGER.info(msg)


class RunLog(logging.Handler):
    """Collects the message of every record at INFO and above that reaches it, in the order
    they come (from any thread), into ``lines``: a run's log for report.txt."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.lines = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.lines.append(record.getMessage())
        except Exception:  # noqa: BLE001 - logging's own contract: never raise from emit
            self.handleError(record)


@contextlib.contextmanager
def collect_log():
    """Collect the messages of the ``torchblur`` logger and its children (INFO and above) into a
    new list for the ``with`` block's duration; yields the list. The logger is
    enabled at INFO meanwhile where it was not (what is shown is still each handler's choice:
    :func:`console_logging` with ``--quiet`` shows warnings only)."""
    target = logging.getLogger("torchblur")
    handler = RunLog()
    old = target.level
    if not target.isEnabledFor(logging.INFO):
        target.setLevel(logging.INFO)
    target.addHandler(handler)
    try:
        yield handler.lines
    finally:
        target.removeHandler(handler)
        target.setLevel(old)


class _AboveBars(logging.Handler):
    """Writes each record on one line of the current ``sys.stderr``, above any tqdm bar."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # noqa: BLE001 - logging's own contract: never raise from emit
            self.handleError(record)


@contextlib.contextmanager
def console_logging(level: int = logging.INFO):
    """Show the ``torchblur`` logger's records at ``level`` and above on stderr, one line
    each (``warning: ...`` for warnings), for the ``with`` block's duration."""
    root = logging.getLogger("torchblur")
    handler = _AboveBars(level)
    handler.setFormatter(_Formatter())
    old = root.level
    root.addHandler(handler)
    root.setLevel(min(level, old) if old else level)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(old)


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        return msg if record.levelno < logging.WARNING else f"{record.levelname.lower()}: {msg}"


def progress_bar(progress: bool, **kwargs) -> tqdm:
    """A tqdm bar (``kwargs`` as tqdm's) shown only with ``progress`` and on a terminal, so
    that logs written to files get no carriage returns."""
    return tqdm(**kwargs, disable=None if progress else True)


@contextlib.contextmanager
def stage_bar(progress: bool, desc: str, total: int):
    """A :func:`progress_bar` over ``total`` stages that :func:`run_stage` advances (and
    names) inside the ``with`` block; yields the bar (``bar.update()`` for other steps)."""
    bar = progress_bar(progress, total=total, desc=desc, unit="stage", leave=False)
    token = _STAGE_BAR.set(bar)
    try:
        yield bar
    finally:
        _STAGE_BAR.reset(token)
        bar.close()


def run_stage(exp, key: str, kind: str, rig, fn, labels: dict | None = None):
    """``fn(rig)``, or with a recording ``exp`` the recorded result of group ``key`` (taken
    and recorded now if it is not there yet, every manifest line with ``labels``; a recorded
    group's calls are replayed and checked against the recorded ones); inside :func:`stage_bar`, one step of its bar."""
    bar = _STAGE_BAR.get()
    if bar is not None:
        bar.set_postfix_str(key, refresh=True)
    out = fn(rig) if exp is None else exp.stage(key, kind, rig, fn, labels=labels)[0]
    if bar is not None:
        bar.update(1)
    return out
