"""A deformable mirror over the serial link: :class:`SerialDMRig`, the interface
the DM plan (:class:`torchblur.identify.dm_plan.DMPlan`) uses on :class:`~torchblur.rig.dm.SimulatedDMRig`
(``pattern_sine``, ``dark``, ``still``, ``pulse``, ``input_limit``, the frame geometry), on a
controller that speaks protocol 2 (docs/protocol.md: ``ACT?``, ``PAT``, ``PAT?`` and the axis
``pat``) and a camera.

One ``pattern_sine`` is one transaction of :class:`~torchblur.hardware.serial_rig.SerialRig`
(``STOP``, ``POWER``, ``SETTLE``, the waveform, one ``ARM`` per exposure, ``STOP``) whose
waveform starts as follows:

    PAT?                         -> OK PAT n=9 crc=...        the device's pattern
    PAT 0 1.0 -1.0 ...           -> OK PAT start=0 count=9   (only when the crc differs)
    PAT?                         -> OK PAT n=9 crc=<ours>     else PatternMismatch
    WAVE pat SINE 200.0 0.31     -> OK WAVE axis=pat mode=SINE start=... crc=<ours>

so every waveform drives exactly the pattern asked for: the checksum (CRC-32 of the float64
values, :func:`~torchblur.hardware.protocol.pattern_checksum`) is checked after the load and
again in the ``WAVE`` reply, which names the pattern it drives. A mismatch is a
:class:`~torchblur.hardware.errors.PatternMismatch` naming the pattern; the call is redone
(the pattern loaded again) at most ``retries`` times, then the run stops.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from torchblur.errors import ConfigError, ParameterError, ShapeError, check_real_scalar
from torchblur.hardware.errors import DeviceError, PatternMismatch
from torchblur.hardware.protocol import pattern_checksum
from torchblur.hardware.serial_rig import SerialRig
from torchblur.rig.base import PatternSines, check_drive, float_list
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.shack_hartmann import ShackHartmann

__all__ = ["SerialDMRig", "describe_pattern", "open_dm_rig"]


def describe_pattern(pattern: np.ndarray) -> str:
    """A pattern's name in messages: its first values, its size and its checksum."""
    p = np.asarray(pattern, dtype=np.float64)
    head = ", ".join(f"{v:g}" for v in p[:6]) + (", ..." if p.size > 6 else "")
    return f"pattern [{head}] ({p.size} weights, crc {pattern_checksum(p)})"


class SerialDMRig(PatternSines, SerialRig):
    """A DM's controller (protocol 2, axis ``pat``) and camera as the DM run's rig.

    Args:
        controller, frames: as :class:`~torchblur.hardware.serial_rig.SerialRig`.
        trigger_delay_s: Td, the camera's nominal trigger-to-exposure delay (s; the config's
            ``camera.trigger_delay_s``): the run's exposure windows start at trigger + Td +
            the calibrated latency.
        **kwargs: ``retries``, ``reconnects``, ``poll_s``, ``max_wait_s``, ``log`` as SerialRig.

    Attributes:
        n_actuators: N, the controller's ``ACT?`` (read on connecting).
    """

    AXES = ("pat",)

    def __init__(self, controller, frames, *, trigger_delay_s: float = 0.0, **kwargs):
        if "axis" in kwargs:
            raise ParameterError("axis: a DM rig drives the axis 'pat' (the loaded pattern); do not give one")
        self.trigger_delay_s = check_real_scalar(trigger_delay_s, "trigger_delay_s", nonnegative=True)
        self._n_actuators: int | None = None  # ACT? of the first connection
        super().__init__(controller, frames, axis="pat", **kwargs)

    def _connect(self) -> None:
        """SerialRig's (ID? with the axis ``pat``, RANGE?, STOP, STATUS?), then ``ACT?``: the
        number of actuators, which must not change on a reconnect."""
        super()._connect()
        n = self.controller.actuators()
        if n < 1:
            raise DeviceError(5, "AXIS", "the controller has no actuator pattern (ACT? n=0)", "ACT?")
        if self._n_actuators is not None and n != self._n_actuators:
            raise DeviceError(4, "RANGE", f"the controller now has {n} actuators, it had {self._n_actuators}", "ACT?")
        self._n_actuators = self.device["actuators"] = n

    @property
    def n_actuators(self) -> int:
        return int(self._n_actuators)


    def _check_pattern(self, pattern) -> np.ndarray:
        N = self.n_actuators
        p = np.asarray(float_list(pattern, "pattern") if np.ndim(pattern) <= 1 else pattern, dtype=np.float64)
        if p.shape != (N,):
            raise ShapeError(f"pattern: expected [{N}] (one command per actuator of the controller), got shape {p.shape}")
        if not np.isfinite(p).all():
            raise ParameterError(f"pattern: expected finite weights, got {describe_pattern(p)}")
        return p

    def _start_pattern_wave(self, p: np.ndarray, freq: float, amp: float) -> None:
        """Make the controller hold ``p`` (``PAT?``, loading it when it differs) and start
        ``WAVE pat SINE``; every checksum must be ``p``'s (module docstring)."""
        c, crc, name = self.controller, pattern_checksum(p), describe_pattern(p)
        held = c.pattern()
        if held["n"] != p.size:
            raise PatternMismatch(f"{name}: the controller holds {held['n']} weights")
        if held["crc"] != crc:
            c.load_pattern(p)
            held = c.pattern()
            if held["crc"] != crc:
                raise PatternMismatch(f"{name}: after loading it the controller holds a pattern with crc {held['crc']}")
        _, driven = c.wave_pattern(freq, amp)
        if driven != crc:
            raise PatternMismatch(f"{name}: the waveform drives a pattern with crc {driven}")

    def pattern_sine(self, pattern, freq_hz: float, amplitude: float, exposures_s: Sequence[float],
                     trigger_offset_s: float | Sequence[float], n_repeats: int, settle_s: float | None = None, power: float = 1.0):
        """Frames ``[E, R, H, W]`` of the mirror driven with ``amplitude * pattern[j] * sin(2 pi
        freq_hz t)`` on actuator j, as :meth:`~torchblur.rig.dm.SimulatedDMRig.pattern_sine`
        (``settle_s`` None: ``SETTLE AUTO``, the controller's settling wait).

        Raises:
            ShapeError: ``pattern`` is not [N]; ParameterError: naming ``amplitude`` when the peak
            command ``|amplitude| max|pattern|`` exceeds the controller's RANGE (nothing sent);
            AcquisitionStopped: the controller refused, or the faults outlasted the retries.
        """
        p = self._check_pattern(pattern)
        freq = check_real_scalar(freq_hz, "freq_hz", positive=True)
        amp = check_real_scalar(amplitude, "amplitude")
        check_drive(abs(amp) * float(np.abs(p).max(initial=0.0)), self.input_limit)
        return self._periodic_capture(f"pattern_sine {describe_pattern(p)} at {freq:g} Hz", lambda c: self._start_pattern_wave(p, freq, amp),
                                      1.0 / freq, exposures_s, trigger_offset_s, n_repeats, check_real_scalar(power, "power"), settle_s,
                                      {"kind": "pattern_sine", "pattern": p, "freq_hz": freq, "omega": 2 * math.pi * freq, "period_s": None,
                                       "amplitude": amp, "settle_s": None, "power": None, "trigger_delay_s": self.trigger_delay_s})

    def __repr__(self) -> str:
        return (f"SerialDMRig(port={self.controller.port!r}, frames={self.frames!r}, actuators={self.device.get('actuators')}, "
                f"boot={self._boot}, input_limit={self.input_limit})")


def open_dm_rig(cfg, *, log=None) -> SerialDMRig:
    """The DM rig of a config with ``rig.kind=serial``: the controller on ``rig.port``, the
    camera on ``rig.frames`` (``rig.timeout_s``, ``rig.retries``; Td from
    ``camera.trigger_delay_s``). The controller's actuators and the camera's frame must be the
    config's mirror (``dm.n_across``) and sensor (``wfs.n_across`` x ``wfs.pitch_px``).

    Raises:
        ConfigError: naming ``dm.n_across`` or ``wfs.n_across`` when they differ (the rig is
            closed); AcquisitionStopped: the controller or the camera cannot be reached.
    """

    mirror = DeformableMirror.from_config(cfg.dm, seed=int(cfg.seed))
    wfs = ShackHartmann.from_config(cfg.wfs, mirror)
    r = cfg.rig
    rig = SerialDMRig.open(r.port, r.frames, timeout_s=float(r.timeout_s), retries=int(r.retries), log=log,
                           trigger_delay_s=float(cfg.camera.trigger_delay_s))
    problem = None
    if rig.n_actuators != mirror.n_actuators:
        problem = (f"dm.n_across: the controller on {r.port} drives {rig.n_actuators} actuators, the config's mirror "
                   f"(dm.n_across={cfg.dm.n_across}) has {mirror.n_actuators}")
    elif tuple(rig.frame_shape) != tuple(wfs.frame_shape):
        problem = (f"wfs.n_across: the camera on {r.frames} delivers {rig.frame_shape[0]}x{rig.frame_shape[1]} frames, the "
                   f"config's sensor {wfs.frame_shape[0]}x{wfs.frame_shape[1]} (wfs.n_across x wfs.pitch_px)")
    if problem is not None:
        rig.close()
        raise ConfigError(problem)
    return rig
