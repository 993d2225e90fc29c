"""A deformable mirror over the serial link: :class:`SerialDMRig`, the DM plan's rig
(:class:`~torchblur.rig.dm_contract.DMRig`) on a controller that speaks protocol 2 (``ACT?``,
``PAT``, ``PAT?``, the axis ``pat``; ``pattern_ladder`` needs protocol 3's ``WAVE pat HOLD``) and a
camera. Every waveform drives exactly the pattern asked for, its checksum checked after the load and
in the ``WAVE`` reply (docs/protocol.md, "A deformable mirror's pattern").
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from torchblur.errors import ParameterError, check_int, check_real_scalar
from torchblur.hardware.errors import DeviceError, PatternMismatch
from torchblur.hardware.protocol import HOLD_PROTOCOL, pattern_checksum
from torchblur.hardware.serial_rig import SerialRig
from torchblur.rig.base import Capture, PatternSines, check_drive, float_list
from torchblur.rig.dm_contract import check_dm_rig

__all__ = ["SerialDMRig", "describe_pattern", "open_dm_rig"]


def describe_pattern(pattern: np.ndarray) -> str:
    """A pattern's name in messages: its first values, its size and its checksum."""
    p = np.asarray(pattern, dtype=np.float64)
    head = ", ".join(f"{v:g}" for v in p[:6]) + (", ..." if p.size > 6 else "")
    return f"pattern [{head}] ({p.size} weights, crc {pattern_checksum(p)})"


class SerialDMRig(PatternSines, SerialRig):
    """A DM's controller (protocol 2, axis ``pat``; 3 for ``pattern_ladder``) and camera as the DM run's rig.

    Args:
        controller, frames: as :class:`~torchblur.hardware.serial_rig.SerialRig`.
        trigger_delay_s: Td, the camera's nominal trigger-to-exposure delay (s; the config's
            ``camera.trigger_delay_s``): the run's exposure windows start at trigger + Td +
            the calibrated latency.
        **kwargs: ``retries``, ``reconnects``, ``poll_s``, ``max_wait_s``, ``idle_polls``, ``log`` as SerialRig.

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
        if self.device["protocol"] < HOLD_PROTOCOL:
            self._note(f"the controller speaks protocol {self.device['protocol']}: no static holds (WAVE pat HOLD, protocol "
                       f"{HOLD_PROTOCOL}), so this rig has no pattern_ladder (dm_plan.spot_model auto keeps the shifted still)")

    @property
    def n_actuators(self) -> int:
        return int(self._n_actuators)

    @property
    def pattern_ladder(self):
        """The bound :meth:`_pattern_ladder` where the controller speaks protocol 3 (``WAVE pat HOLD``);
        on an older controller an AttributeError saying so, so that ``getattr(rig, "pattern_ladder",
        None)`` is None there: the DM run's rig contract (:mod:`torchblur.rig.dm_contract`) then refuses
        ``dm_plan.spot_model=ladder`` before any frame and ``auto`` keeps the shifted still, both naming the rig."""
        if self.device["protocol"] < HOLD_PROTOCOL:
            raise AttributeError(f"pattern_ladder: the controller on {self.controller.port} speaks protocol {self.device['protocol']}; "
                                 f"static holds need protocol {HOLD_PROTOCOL} (WAVE pat HOLD, docs/protocol.md)")
        return self._pattern_ladder

    def _drive_pattern(self, p: np.ndarray, start) -> None:
        """Make the controller hold ``p`` (``PAT?``, loading it when it differs) and start its
        waveform, ``start(controller)`` -> (start, the crc of the pattern it drives): ``WAVE pat
        SINE`` or ``HOLD``; every checksum must be ``p``'s (module docstring)."""
        c, crc, name = self.controller, pattern_checksum(p), describe_pattern(p)
        held = c.pattern()
        if held["n"] != p.size:
            raise PatternMismatch(f"{name}: the controller holds {held['n']} weights")
        if held["crc"] != crc:
            c.load_pattern(p)
            held = c.pattern()
            if held["crc"] != crc:
                raise PatternMismatch(f"{name}: after loading it the controller holds a pattern with crc {held['crc']}")
        _, driven = start(c)
        if driven != crc:
            raise PatternMismatch(f"{name}: the waveform drives a pattern with crc {driven}")

    def pattern_sine(self, pattern, freq_hz: float, amplitude: float, exposures_s: Sequence[float],
                     trigger_offset_s: float | Sequence[float], n_repeats: int, settle_s: float | None = None, power: float = 1.0):
        """Frames ``[E, R, H, W]``, as :meth:`~torchblur.rig.dm_contract.DMRig.pattern_sine`
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
        return self._periodic_capture(f"pattern_sine {describe_pattern(p)} at {freq:g} Hz",
                                      lambda c: self._drive_pattern(p, lambda c: c.wave_pattern(freq, amp)), 1.0 / freq, exposures_s, trigger_offset_s, n_repeats, check_real_scalar(power, "power"), settle_s,
                                      {"kind": "pattern_sine", "pattern": p, "freq_hz": freq, "omega": 2 * math.pi * freq, "period_s": None,
                                       "amplitude": amp, "settle_s": None, "power": None, "trigger_delay_s": self.trigger_delay_s})

    def _pattern_ladder(self, pattern, levels: Sequence[float], n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """Frames ``[K, n, H, W]`` of the mirror held still at ``levels[k] * pattern``, as
        :meth:`~torchblur.rig.dm.SimulatedDMRig.pattern_ladder` (the rig's ``pattern_ladder`` on a
        protocol-3 controller): one transaction, each level after the controller's settling wait
        (``SETTLE AUTO``). Raises as :meth:`pattern_sine`, naming ``levels`` for a peak beyond RANGE
        (and ``n``, ``exposure_s``, ``power``)."""
        p = self._check_pattern(pattern)
        lv = float_list(levels, "levels")
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        power = self._check_power(power)
        check_drive(max(abs(u) for u in lv) * float(np.abs(p).max(initial=0.0)), self.input_limit, "levels")
        def body(c):
            out = []
            for u in lv:
                self._drive_pattern(p, lambda c, u=u: c.hold_pattern(u))
                out += self._armed(te, n)
            return out

        frames = self._transaction(f"pattern_ladder {describe_pattern(p)} at {len(lv)} levels", power, body, wave=True)
        return self._capture(frames, (len(lv), n), [0.0] * (len(lv) * n),
                             {"kind": "pattern_ladder", "pattern": p, "levels": lv, "power": power})

    def __repr__(self) -> str:
        return (f"SerialDMRig(port={self.controller.port!r}, frames={self.frames!r}, actuators={self.device.get('actuators')}, "
                f"protocol={self.device.get('protocol')}, boot={self._boot}, input_limit={self.input_limit})")


def open_dm_rig(cfg, *, log=None) -> SerialDMRig:
    """The DM rig of a config with ``rig.kind=serial``: the controller on ``rig.port``, the
    camera on ``rig.frames`` (``rig.timeout_s``, ``rig.retries``; Td from
    ``camera.trigger_delay_s``), checked against the config (:func:`~torchblur.rig.dm_contract.check_dm_rig`).

    Raises:
        ConfigError: naming ``dm.n_across`` or ``wfs.pitch_px`` when the controller's actuators or
            the camera's frame are not the config's mirror and sensor (the rig is closed);
            AcquisitionStopped: the controller or the camera cannot be reached.
    """
    r = cfg.rig
    rig = SerialDMRig.open(r.port, r.frames, timeout_s=float(r.timeout_s), retries=int(r.retries), log=log,
                           trigger_delay_s=float(cfg.camera.trigger_delay_s))
    try:
        check_dm_rig(rig, cfg)
    except BaseException:
        rig.close()
        raise
    return rig
