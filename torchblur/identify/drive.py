"""The safe drive: the input range (:attr:`~torchblur.rig.base.Rig.input_limit`, narrowed by
``excitation.max_amplitude``) and the slew-rate limit (:attr:`~torchblur.rig.base.Rig.slew_limit`,
input units/s, narrowed by ``excitation.max_slew``) every plan of a run keeps within: the run's
:class:`DriveLimit` (:func:`drive_limit`, fixed before the first frame; at ``f`` Hz the largest
amplitude is ``min(limit, slew / (2 pi f))``, :meth:`DriveLimit.at`), the points it limits
(:func:`is_limited`, :func:`limited_summary`) and the refusal of a recording beyond it
(:func:`check_recorded_drive`). What a run does at the limit: docs/reliability.md, "The safe
drive"; the slew limit: README.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchblur.errors import ConfigError
from torchblur.hardware.errors import RecordingError
from torchblur.rig.base import DRIVE_RTOL, command_peak, command_slew, within_drive

__all__ = ["DriveLimit", "drive_limit", "range_limit", "at_limit", "is_limited", "check_recorded_drive", "limited_summary", "SESSION_KEY",
           "SLEW_KEY"]

#: the key of a recording session's rig details that holds the rig's range (replays read it back)
SESSION_KEY = "input_limit"
#: the same for the rig's slew limit
SLEW_KEY = "slew_limit"


@dataclass(frozen=True)
class DriveLimit:
    """The run's input range: ``limit`` (the largest |command| the run may ask for, input
    units; inf only when replaying a recording that holds none), ``device`` (the rig's own
    range, or None where it does not say) and ``source`` (``"device"``,
    ``"excitation.max_amplitude"`` or ``"recording"``)."""

    limit: float
    device: float | None
    source: str
    slew: float = math.inf  # the largest |d command / dt| (input units/s); inf: no slew limit
    slew_device: float | None = None
    slew_source: str = "none"

    def at(self, freq_hz: float) -> float:
        """The largest sine amplitude (input units) at ``freq_hz`` Hz: ``min(limit, slew / (2 pi freq_hz))``."""
        f = abs(float(freq_hz))
        return float(min(self.limit, self.slew / (2 * math.pi * f))) if f > 0 and math.isfinite(self.slew) else float(self.limit)

    def describe(self) -> str:
        """One line for the log."""
        dev = "not reported" if self.device is None else f"+-{self.device:.6g}"
        line = f"drive: input range +-{self.limit:.6g} input units (device {dev}; from {self.source})"
        if math.isfinite(self.slew):
            sdev = "not reported" if self.slew_device is None else f"{self.slew_device:.6g}"
            line += (f", slew limit {self.slew:.6g} input units/s (device {sdev}; from {self.slew_source}): the full range "
                     f"up to {self.slew / (2 * math.pi * self.limit):.4g} Hz")
        return line


def _recorded_range(exp, key: str = SESSION_KEY) -> float | None:
    """The rig range (``key``: or slew limit) a recording's last session noted (None: not noted)."""
    for s in reversed(exp.meta.get("sessions", [])):
        v = (s.get("rig") or {}).get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            return float(v)
    return None


def drive_limit(rig, max_amplitude, exp=None, max_slew=None) -> DriveLimit:
    """The run's :class:`DriveLimit`: the range (:func:`range_limit`) and the slew limit (the
    rig's ``slew_limit``, None where it has none, narrowed by ``max_slew``: ``excitation.max_slew``).

    Raises:
        ConfigError: as :func:`range_limit`; naming ``excitation.max_slew`` when it is larger than
            the rig's slew limit (it may only narrow it).
    """
    rng = range_limit(rig, max_amplitude, exp)
    slew, device, source = _narrowed(rig, exp, SLEW_KEY, max_slew, "excitation.max_slew", (" input units/s", "slew limit ", "limit"))
    return rng if slew is None else DriveLimit(rng.limit, rng.device, rng.source, slew, device, source)


def range_limit(rig, max_amplitude, exp=None) -> DriveLimit:
    """The run's :class:`DriveLimit` from the rig's range and ``excitation.max_amplitude``.

    A rig without the ``input_limit`` attribute replaying a recording ``exp``
    (:class:`~torchblur.hardware.recording.ReplayRig`: nothing is commanded) has the range the
    recording's sessions noted, else none (inf: the recording's own amplitudes stand).

    Raises:
        ConfigError: naming ``excitation.max_amplitude``: it is larger than the rig's range
            (it may only narrow it), or the rig does not report a range and it is not given
            (an old controller that does not answer ``RANGE?``).
    """
    limit, device, source = _narrowed(rig, exp, SESSION_KEY, max_amplitude, "excitation.max_amplitude", ("", "input range +-", "range"))
    if limit is not None or source == "recording":
        return DriveLimit(math.inf if limit is None else limit, device, source)
    raise ConfigError(f"excitation.max_amplitude: the rig ({rig!r}) does not report its input range (a controller "
                      f"that does not answer RANGE?: an older firmware); give excitation.max_amplitude=..., the largest "
                      f"|command| (input units) the actuator may take, to run on it")


def _narrowed(rig, exp, key: str, value, name: str, words: tuple) -> tuple:
    """One of the rig's limits (its attribute ``key``: ``input_limit`` or ``slew_limit``; a rig
    without ``input_limit`` replaying a recording ``exp``: what the recording noted under ``key``)
    narrowed by the config's ``value`` (key ``name``; None: not given) -> ``(limit, device, source)``
    (``limit`` None where neither says; ``source`` then ``"recording"`` when replaying).

    Raises:
        ConfigError: naming ``name``, when ``value`` is beyond the rig's limit (``words``: the
            value's unit, the limit's name and its noun, for the message).
    """
    replay = exp is not None and not hasattr(rig, "input_limit")
    device = _recorded_range(exp, key) if replay else getattr(rig, key, None)
    device = None if device is None else float(device)
    want = None if value is None else float(value)
    unit, what, noun = words
    if want is not None and device is not None and want > device * (1 + DRIVE_RTOL):
        raise ConfigError(f"{name}: {want:g}{unit} is beyond the {what}{device:g} the rig reports ({rig!r}); it may only "
                          f"narrow the {noun}, not widen it")
    if want is not None:
        return want, device, name
    return device, device, "recording" if replay else ("device" if device is not None else "none")


def at_limit(amplitude: float, limit: float) -> bool:
    """Whether a command of peak ``amplitude`` is at the limit (within 1e-9)."""
    return abs(float(amplitude)) >= float(limit) * (1 - 1e-9)


def is_limited(amplitude: float, moved_px: float, target_px: float, limit: float, low: float = 0.75) -> bool:
    """A point driven at the limit whose motion ``moved_px`` stays below ``low`` times its
    target (or is NaN: nothing fitted): the range, not the plan, set its motion."""
    return at_limit(amplitude, limit) and not float(moved_px) >= low * float(target_px)


def check_recorded_drive(exp, limit: float, slew: float = math.inf) -> None:
    """Refuse to resume a recording on a rig whose range it exceeds: every recorded ``sine``
    amplitude and ``multisine`` peak (:func:`~torchblur.rig.base.command_peak`) must be within
    ``limit``, and its slew rate (:func:`~torchblur.rig.base.command_slew`) within ``slew``.

    Raises:
        RecordingError: naming the first group that exceeds it.
    """
    if exp is None or not (math.isfinite(limit) or math.isfinite(slew)):
        return
    seen = set()
    for ln in exp.lines:
        key = (ln.get("group"), ln.get("call"))
        if key in seen or ln.get("method") not in ("sine", "multisine"):
            continue
        seen.add(key)
        a = ln.get("args") or {}
        try:
            if ln["method"] == "sine":
                peak = abs(float(a["amplitude"]))
                rate = peak * 2 * math.pi * abs(float(a["freq_hz"]))
            else:
                peak = command_peak(a["freq_hz"], a["amplitude"], a["phase_rad"], a.get("base_freq_hz"))
                rate = command_slew(a["freq_hz"], a["amplitude"], a["phase_rad"], a.get("base_freq_hz"))
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{ln.get('group')}: the recorded {ln['method']} call has no readable amplitude ({exc})") from None
        if not within_drive(peak, limit):
            raise RecordingError(f"{ln.get('group')}: recorded with a command of peak {peak:.6g} input units, beyond the input "
                                 f"range +-{limit:.6g} of this run's rig; refused (resume it on the rig it was recorded on, or "
                                 f"record anew)")
        if not within_drive(rate, slew):
            raise RecordingError(f"{ln.get('group')}: recorded with a command slewing at {rate:.6g} input units/s, beyond the "
                                 f"slew limit {slew:.6g} units/s of this run's rig; refused (resume it on the rig it was "
                                 f"recorded on, or record anew)")


def limited_summary(freq_hz, limited, moved_px, target_px: float, limit: float, inputs=("x",), no_motion=None,
                    slew: float = math.inf) -> str | None:
    """The log line of the limited points (None when there are none): per point the frequency
    (Hz), the input when there are several, the motion reached (px) of the target, and where
    ``no_motion`` (bool per point, or None) says so, that the fit found no significant motion
    (its value is not a measurement: flagged, see :data:`~torchblur.fit.status.NO_MOTION`)."""
    lim = np.asarray(limited, dtype=bool).reshape(-1)
    if not lim.any():
        return None
    f = np.asarray(freq_hz, dtype=float).reshape(-1)
    moved = np.asarray(moved_px, dtype=float).reshape(-1)
    none = np.zeros_like(lim) if no_motion is None else np.asarray(no_motion, dtype=bool).reshape(-1)
    F = f.size
    items = []
    for j in np.nonzero(lim)[0]:
        where = f"{f[j % F]:.4g} Hz" + (f" ({inputs[j // F]})" if len(inputs) > 1 else "")
        items.append(f"{where}: {moved[j]:.3g} px" + (" (no significant motion: flagged, not a measurement)" if none[j] else ""))
    by = f"the input range +-{limit:.6g}" + (f" and the slew limit {slew:.6g} units/s" if math.isfinite(slew) else "")
    return (f"drive: {int(lim.sum())} of {lim.size} points limited by {by} (the target "
            f"{target_px:g} px not reached; fitted at the smaller motion): " + ", ".join(items))
