"""The interface an identification pipeline uses to take frames, and its result type.

A rig is a laser spot on a fast steering mirror (the plant) seen by a slow camera, with a
controller that makes the sine command and fires the camera trigger on the same clock
(PHYSICS.md sections 2 and 4). Times are in seconds, frequencies in Hz at this interface
(``freq_hz``), amplitudes in command units, frames in ADU.

Glossary of shapes: E exposures, R repeats, H, W pixels; ``[...]`` the batch of frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence, runtime_checkable

import numpy as np
import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_int, check_real_scalar

__all__ = ["CameraRig", "Capture", "PatternSines", "Rig", "RigChecks", "command_peak", "command_slew", "check_drive", "check_slew", "within_drive",
           "DRIVE_RTOL"]

#: relative slack of a drive check: a command rounded on its way to the device (the serial
#: protocol sends tones to 10 significant digits) still passes at the limit
DRIVE_RTOL = 1e-9


@dataclass
class Capture:
    """The frames of one rig call and when they were taken.

    Args:
        frames: frames in ADU, float, ``[..., H, W]``; ``frames[..., i, j]`` is the value of
            row i, column j (x = j, y = i).
        exposure_s: exposure time Te of each frame (s), ``[...]``.
        trigger_offset_s: commanded trigger time of each frame (s) relative to the reference
            event of the period the trigger falls in: for ``sine`` the upward zero crossing
            of the command in that period, in ``[0, period)``; for ``pulse`` the reference
            event the laser pulse is timed from; 0 for ``dark`` and ``still``. ``[...]``.
        trigger_time_s: absolute command-clock time of each trigger (s), ``[...]``; for
            ``sine`` t = 0 is the start of the sine.
        frame_counter: the camera's frame counter, ``[...]`` long; +1 per frame, across
            calls.
        meta: anything else (the call's arguments, the settle time, ...).
    """

    frames: torch.Tensor
    exposure_s: torch.Tensor
    trigger_offset_s: torch.Tensor
    trigger_time_s: torch.Tensor
    frame_counter: torch.Tensor
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> torch.Size:
        """Batch shape ``[...]`` of the frames."""
        return self.frames.shape[:-2]

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.frames.shape[-2:])


@runtime_checkable
class CameraRig(Protocol):
    """What every rig says about its camera and its drive: the properties the one-spot
    :class:`Rig` and the deformable mirror's :class:`~torchblur.rig.dm_contract.DMRig` share
    (a recording keeps them as its camera description; the run's checks read them)."""

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(H, W)`` of a frame in pixels."""
        ...

    @property
    def frame_rate_hz(self) -> float:
        """Highest frame rate of the camera (Hz)."""
        ...

    @property
    def max_exposure_s(self) -> float:
        """Longest exposure the camera accepts (s)."""
        ...

    @property
    def readout_s(self) -> float:
        """Readout time Tr (s) after each exposure."""
        ...

    @property
    def input_limit(self) -> float | None:
        """The input range: the largest |command| (input units) the actuator's amplifier takes,
        on every input (the peak of a multisine, :func:`command_peak`); None where the device
        does not say (an old controller: the run then needs ``excitation.max_amplitude``).
        A call that asks for more raises :class:`~torchblur.errors.ParameterError` naming
        ``amplitude`` (:func:`check_drive`), as a real amplifier would clip. A rig may also have
        ``slew_limit`` (optional: the largest |d command / dt|, input units per second, None where
        it has none or does not say; :func:`command_slew`, :func:`check_slew`)."""
        ...


@runtime_checkable
class Rig(CameraRig, Protocol):
    """What an identification pipeline needs from a rig (simulated or real).

    The camera's properties are :class:`CameraRig`'s. Every method returns a :class:`Capture`. Exposures longer than :attr:`max_exposure_s`
    raise :class:`~torchblur.errors.ParameterError` naming ``exposure_s``.
    """

    def dark(self, n: int, exposure_s: float) -> Capture:
        """``n`` frames with the laser off: frames ``[n, H, W]``."""
        ...

    def still(self, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """``n`` frames of the spot at rest (mirror still, laser at ``power``): ``[n, H, W]``."""
        ...

    def sine(
        self,
        freq_hz: float,
        amplitude: float,
        exposures_s: Sequence[float],
        trigger_offset_s: float | Sequence[float],
        n_repeats: int,
        settle_s: float | None = None,
        power: float = 1.0,
        input: str = "x",
    ) -> Capture:
        """Drive ``amplitude sin(2 pi freq_hz t)`` on ``input`` (``"x"``, or ``"y"`` on a
        two-axis mirror; the other axis held at rest) from rest at t = 0, wait ``settle_s``
        (default: the plant's settling time rounded up to whole periods), then take
        ``n_repeats`` frames per exposure, each triggered ``trigger_offset_s`` (one value,
        or one per exposure) after an upward zero crossing of the command: frames
        ``[E, R, H, W]``."""
        ...

    def pulse(
        self,
        exposure_s: float,
        trigger_offset_s: float | Sequence[float],
        pulse_time_s: float,
        pulse_width_s: float,
        n: int,
        power: float = 1.0,
    ) -> Capture:
        """Mirror still; per frame the controller fires the trigger ``trigger_offset_s``
        after a reference event of its clock and switches the laser on during
        ``[pulse_time_s, pulse_time_s + pulse_width_s]`` after the same event. Frame
        brightness vs trigger offset is a trapezoid whose edges give the trigger-to-exposure
        latency. Frames ``[..., n, H, W]`` with ``[...]`` the shape of ``trigger_offset_s``."""
        ...

    def multisine(
        self,
        freq_hz: Sequence[float],
        amplitude: Sequence[float],
        phase_rad: Sequence[float],
        exposures_s: Sequence[float],
        trigger_offset_s: float | Sequence[float],
        n_repeats: int,
        base_freq_hz: float | None = None,
        settle_s: float | None = None,
        power: float | Sequence[float] = 1.0,
    ) -> Capture:
        """Drive ``sum_k amplitude_k sin(2 pi freq_hz_k t + phase_rad_k)`` from rest at t = 0
        (every tone a whole multiple of ``base_freq_hz``, default the lowest tone, so the
        command repeats every ``T0 = 1 / base_freq_hz``), wait ``settle_s`` (default: the
        plant's settling time rounded up to whole ``T0``), then take ``n_repeats`` frames per
        exposure, each triggered ``trigger_offset_s`` (one value, or one per exposure) after
        the start of a common period, with the laser at ``power`` (one value, or one per
        exposure): frames ``[E, R, H, W]``."""
        ...


# ---------------------------------------------------------------- argument checks shared by the rigs


class RigChecks:
    """The argument checks of the :class:`Rig` calls, shared by the simulated and the serial rig
    (reading the rig's ``max_exposure_s``, ``input_limit`` and ``slew_limit``); each raises
    :class:`~torchblur.errors.ParameterError` (or InputTypeError, ShapeError) naming the argument."""

    def _check_exposure(self, value, name: str = "exposure_s") -> float:
        te = check_real_scalar(value, name, positive=True)
        if te > self.max_exposure_s:
            raise ParameterError(f"{name}: expected at most max_exposure_s = {self.max_exposure_s:g} s, got {te:g} s")
        return te

    def _check_power(self, power) -> float:
        return check_real_scalar(power, "power", nonnegative=True)

    def _check_sine(self, freq_hz, amplitude) -> tuple[float, float]:
        """``(freq_hz, amplitude)`` of a sine, its peak and slew rate within the drive's limits."""
        freq = check_real_scalar(freq_hz, "freq_hz", positive=True)
        amp = check_real_scalar(amplitude, "amplitude")
        check_drive(amp, self.input_limit)
        check_slew(abs(amp) * 2 * math.pi * freq, self.slew_limit)
        return freq, amp

    def _check_tones(self, freq_hz, amplitude, phase_rad, base_freq_hz) -> tuple[list, list, list, float]:
        """``(freqs, amplitudes, phases, f0)`` of a multisine: N tones each, every tone a whole
        multiple of ``f0`` (``base_freq_hz``, default the lowest tone)."""
        freqs = float_list(freq_hz, "freq_hz")
        amps = float_list(amplitude, "amplitude")
        phases = float_list(phase_rad, "phase_rad")
        for name, v in (("amplitude", amps), ("phase_rad", phases)):
            if len(v) != len(freqs):
                raise ShapeError(f"{name}: expected {len(freqs)} values (one per tone of freq_hz), got {len(v)}")
        freqs = [check_real_scalar(f, "freq_hz", positive=True) for f in freqs]
        f0 = min(freqs) if base_freq_hz is None else check_real_scalar(base_freq_hz, "base_freq_hz", positive=True)
        check_tone_grid(freqs, f0)
        return freqs, amps, phases, f0

    def _check_periodic(self, exposures_s, trigger_offset_s, n_repeats) -> tuple[list, list, int]:
        """``(exposures [E], trigger offsets [E], repeats R)`` of a periodic command's frames."""
        R = check_int(n_repeats, "n_repeats", low=1)
        te = [self._check_exposure(v, "exposures_s") for v in float_list(exposures_s, "exposures_s")]
        return te, per_exposure(trigger_offset_s, len(te), "trigger_offset_s"), R

    def _check_pulse(self, exposure_s, n, power, pulse_time_s, pulse_width_s) -> tuple[float, int, float, float, float]:
        """``(exposure_s, n, power, pulse_time_s, pulse_width_s)`` of a latency scan."""
        te = self._check_exposure(exposure_s)
        n = check_int(n, "n", low=1)
        power = self._check_power(power)
        return (te, n, power, check_real_scalar(pulse_time_s, "pulse_time_s"),
                check_real_scalar(pulse_width_s, "pulse_width_s", positive=True))


class PatternSines:
    """What a rig that drives a deformable mirror's patterns (``pattern_sine(pattern, freq_hz,
    amplitude, exposures_s, trigger_offset_s, n_repeats, settle_s, power)`` and ``n_actuators``)
    offers for the :class:`Rig` calls: inputs ``"a0"..."a{N-1}"``, :meth:`sine` of one actuator,
    no multisine. Mixed in before the rig's own base class (the simulated and the serial DM rig)."""

    @property
    def inputs(self) -> tuple[str, ...]:
        """``("a0", ..., "a{N-1}")``: :meth:`sine` drives one actuator."""
        return tuple(f"a{j}" for j in range(self.n_actuators))

    def sine(self, freq_hz: float, amplitude: float, exposures_s: Sequence[float], trigger_offset_s, n_repeats: int,
             settle_s: float | None = None, power: float = 1.0, input: str = "a0"):
        """``pattern_sine`` of one actuator, ``input = "a{j}"`` (the others at rest)."""
        if input not in self.inputs:
            raise ParameterError(f"input: expected one of 'a0'..'a{self.n_actuators - 1}', got {input!r}")
        pattern = np.zeros(self.n_actuators)
        pattern[int(input[1:])] = 1.0
        cap = self.pattern_sine(pattern, freq_hz, amplitude, exposures_s, trigger_offset_s, n_repeats, settle_s, power)
        cap.meta["input"] = input
        return cap

    def multisine(self, *args, **kwargs):
        raise ParameterError("multisine: the DM rig drives one sine per pattern (pattern_sine)")

    def _check_pattern(self, pattern) -> np.ndarray:
        """``pattern`` as float64 ``[N]``, finite (one command per actuator), else ShapeError naming it."""
        N = self.n_actuators
        p = np.asarray(float_list(pattern, "pattern") if np.ndim(pattern) <= 1 else pattern, dtype=np.float64)
        if p.shape != (N,):
            raise ShapeError(f"pattern: expected [{N}] (one command per actuator), got shape {p.shape}")
        return p

    def _ladder_commands(self, pattern, levels) -> np.ndarray:
        """The static commands of ``pattern_ladder``: ``[K, N]``, ``levels[k] * pattern``."""
        return np.asarray(float_list(levels, "levels"), dtype=np.float64)[:, None] * self._check_pattern(pattern)[None, :]


def float_list(value, name: str) -> list[float]:
    """A number or a 1-D sequence/array/tensor of finite numbers as a non-empty list of floats."""
    if isinstance(value, (bool, str, bytes)) or value is None:
        raise InputTypeError(f"{name}: expected a number or a list of numbers, got {type(value).__name__}")
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name}: expected a number or a list of numbers, got {value!r}") from exc
    if arr.ndim > 1:
        raise ShapeError(f"{name}: expected a number or a 1-D list, got shape {arr.shape}")
    arr = arr.reshape(-1)
    if arr.size == 0:
        raise ParameterError(f"{name}: expected at least one value, got an empty list")
    if not np.isfinite(arr).all():
        raise ParameterError(f"{name}: expected finite numbers, got {value!r}")
    return [float(v) for v in arr]


def per_exposure(value, E: int, name: str) -> list[float]:
    """One number, or E numbers (one per exposure), as a list of E floats."""
    values = float_list(value, name)
    if len(values) == 1:
        values = values * E
    if len(values) != E:
        raise ShapeError(f"{name}: expected 1 or {E} values (one per exposure), got {len(values)}")
    return values


def check_tone_grid(freqs: Sequence[float], base_hz: float) -> None:
    """Every tone a whole multiple (>= 1) of ``base_hz``, else :class:`ParameterError` naming ``freq_hz``."""
    ratio = np.asarray(freqs) / base_hz
    if np.any(np.abs(ratio - np.round(ratio)) > 1e-6 * ratio) or np.any(np.round(ratio) < 1):
        raise ParameterError(f"freq_hz: every tone must be a whole multiple of base_freq_hz = {base_hz:g} Hz, got {list(freqs)}")



# ---------------------------------------------------------------- the drive's range


def _tone_arrays(freq_hz, amplitude, phase_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The N tones as float64 arrays ``[N]`` (Hz, input units, rad); ShapeError naming ``amplitude`` for unequal sizes."""
    f, a, p = (np.asarray(float_list(v, name)) for v, name in ((freq_hz, "freq_hz"), (amplitude, "amplitude"), (phase_rad, "phase_rad")))
    if not (f.size == a.size == p.size):
        raise ShapeError(f"amplitude: expected one value per tone of freq_hz ({f.size}), got {a.size} amplitudes and "
                         f"{p.size} phases")
    return f, a, p


def command_peak(freq_hz, amplitude, phase_rad, base_freq_hz: float | None = None) -> float:
    """An upper bound of ``max_t |sum_k a_k sin(2 pi f_k t + p_k)|`` (input units), the peak
    a multisine commands.

    With every tone a whole multiple ``n_k`` of ``base_freq_hz`` (default the lowest tone) the
    command repeats every ``T0 = 1 / base_freq_hz``: it is sampled at ``S = max(1024, 64 max n_k)``
    points of a period, and the bound is the sampled maximum plus the most a maximum between
    samples can exceed it, ``sum_k |a_k| (2 pi n_k)^2 / (8 S^2)`` (Taylor's bound with the
    largest second derivative), never more than ``sum_k |a_k|``. Off a common grid:
    ``sum_k |a_k|``. One tone gives ``|a|``.

    Args:
        freq_hz, amplitude, phase_rad: the N tones (Hz, input units, rad), numbers or ``[N]``.
        base_freq_hz: f0 (Hz), or None.
    """
    f, a, p = _tone_arrays(freq_hz, amplitude, phase_rad)
    a = np.abs(a)
    total = float(a.sum())
    if f.size == 1:
        return total
    base = float(f.min()) if base_freq_hz is None else float(base_freq_hz)
    n = f / base
    if base <= 0 or np.any(np.abs(n - np.round(n)) > 1e-6 * n) or np.any(np.round(n) < 1):
        return total
    n = np.round(n)
    S = int(max(1024, 64 * n.max()))
    s = np.arange(S) / S
    x = (a[:, None] * np.sin(2 * np.pi * n[:, None] * s + p[:, None])).sum(0)
    between = float(np.sum(a * (2 * np.pi * n) ** 2)) / (8 * S * S)
    return min(total, float(np.abs(x).max()) + between)


def within_drive(value: float, limit: float | None) -> bool:
    """Whether ``|value|`` is within ``limit`` (None: no limit) up to :data:`DRIVE_RTOL` (NaN is
    not): the one test of a command's peak (input units) or slew rate (input units/s)."""
    return limit is None or abs(float(value)) <= float(limit) * (1 + DRIVE_RTOL)


def check_drive(peak: float, limit: float | None, what: str = "amplitude") -> None:
    """Refuse a command whose peak |command| ``peak`` exceeds ``limit`` (input units; None:
    no range known) by more than :data:`DRIVE_RTOL`: :class:`~torchblur.errors.ParameterError`
    naming ``what``."""
    if not within_drive(peak, limit):
        raise ParameterError(f"{what}: a command of peak {float(peak):.6g} input units is beyond the input range "
                             f"+-{float(limit):.6g} of this actuator (its amplifier would clip); refused")


def command_slew(freq_hz, amplitude, phase_rad, base_freq_hz: float | None = None) -> float:
    """An upper bound of the command's slew rate ``max_t |d/dt sum_k a_k sin(2 pi f_k t + p_k)|``
    (input units per second): :func:`command_peak` of the derivative, the tones
    ``a_k 2 pi f_k`` at ``p_k + pi / 2``. One tone gives ``|a| 2 pi f``.

    Args:
        freq_hz, amplitude, phase_rad: the N tones (Hz, input units, rad), numbers or ``[N]``.
        base_freq_hz: f0 (Hz), or None.
    """
    f, a, p = _tone_arrays(freq_hz, amplitude, phase_rad)
    return command_peak(f, np.abs(a) * 2 * np.pi * np.abs(f), p + np.pi / 2 * np.sign(a), base_freq_hz)


def check_slew(slew: float, limit: float | None, what: str = "amplitude") -> None:
    """Refuse a command whose slew rate ``slew`` (input units per second, :func:`command_slew`)
    exceeds the amplifier's ``limit`` (None: no slew limit known) by more than
    :data:`DRIVE_RTOL`: :class:`~torchblur.errors.ParameterError` naming ``what``."""
    if not within_drive(slew, limit):
        raise ParameterError(f"{what}: a command slewing at {float(slew):.6g} input units/s is beyond the slew limit "
                             f"{float(limit):.6g} units/s of this actuator's amplifier (amplitude * omega; it would overheat); refused")
