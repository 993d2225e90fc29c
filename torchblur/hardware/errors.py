"""Exceptions of the hardware adapter.

Every fault the adapter detects is a :class:`HardwareError` (a
:class:`~torchblur.errors.TorchblurError`). ``recoverable`` says whether retrying the rig call
can help (a timeout, garbage bytes, a reset controller, a dropped or stale frame) or not (an
ERR reply to a malformed command, a lost connection that cannot be reopened).
"""
from __future__ import annotations

from torchblur.errors import TorchblurError

__all__ = [
    "HardwareError",
    "ReplyTimeout",
    "GarbageReply",
    "DeviceError",
    "ConnectionLost",
    "DeviceReset",
    "FrameError",
    "FrameTimeout",
    "FrameGap",
    "StaleFrame",
    "FrameMismatch",
    "PatternMismatch",
    "AcquisitionStopped",
    "RecordingError",
]


class HardwareError(TorchblurError):
    """A fault of the controller, the camera or the link to them."""

    recoverable = True


class ReplyTimeout(HardwareError, TimeoutError):
    """The controller did not answer a command within the timeout."""


class GarbageReply(HardwareError):
    """A reply that is not a well-formed ``OK``/``ERR`` line for the command sent (line noise,
    a stale reply, a boot banner)."""


class DeviceError(HardwareError):
    """The controller answered ``ERR <code> <NAME> <message>``.

    Attributes: ``code`` (int), ``name`` (the code's name, e.g. ``RANGE``), ``detail``
    (the free text), ``command`` (the line sent). ``BUSY`` (6, retried after ``STOP``),
    ``LINE`` (7: line noise garbled the command; resynchronise and redo) and ``INTERNAL``
    (8: retry) are recoverable (docs/protocol.md); codes 1-5 mean the command itself was
    wrong.
    """

    def __init__(self, code: int, name: str, detail: str, command: str):
        self.code, self.name, self.detail, self.command = int(code), name, detail, command
        super().__init__(f"controller replied ERR {code} {name} {detail} (to {command!r})")
        self.recoverable = self.code in (6, 7, 8)


class ConnectionLost(HardwareError, ConnectionError):
    """The serial link or the camera channel closed or failed (cable pulled, device gone)."""


class DeviceReset(HardwareError):
    """The controller reset (its boot id changed, its frame counter went back, or STATUS says
    RESET) while a rig call was under way: the call's frames cannot be trusted."""


class FrameError(HardwareError):
    """A frame that cannot be accepted."""


class FrameTimeout(FrameError, TimeoutError):
    """An expected frame did not arrive in time."""


class FrameGap(FrameError):
    """A frame counter jumped forward: a frame was dropped."""


class StaleFrame(FrameError):
    """A frame already delivered (a repeated counter) arrived again."""


class FrameMismatch(FrameError):
    """A frame's metadata (exposure, shape, dtype) is not what was asked for."""


class PatternMismatch(HardwareError):
    """The DM controller does not hold (``PAT?``), or does not drive (``WAVE pat``), the pattern
    that was loaded: the message names the pattern. Retried (the retry loads it again)."""


class AcquisitionStopped(HardwareError):
    """A rig call failed after its retries (or the connection is gone): the run must stop.

    ``cause`` is the last fault. The recording made so far is complete and consistent; the
    run can be resumed with ``torchblur identify --resume DIR``.
    """

    recoverable = False

    def __init__(self, message: str, cause: BaseException | None = None):
        super().__init__(message)
        self.cause = cause


class RecordingError(TorchblurError, ValueError):
    """An experiment directory is missing, of an unknown schema, or does not match the
    configuration it is resumed or re-fitted with."""
