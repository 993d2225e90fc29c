"""``torchblur emulator``: a separate process that behaves like the bench (docs/protocol.md, "The emulator").

It speaks the controller protocol on a pseudo-terminal (``transport=socket``: a loopback TCP port for
pyserial's ``socket://``), renders the frames with the config's simulated rig
(:mod:`torchblur.rig.factory`) on a simulated clock, serves them on a loopback TCP channel
(:mod:`torchblur.hardware.frames`), and prints one JSON start line (``serial``, ``frames``, ``pid``, ...).
"""
from __future__ import annotations

import json
import math
import os
import queue
import secrets
import select
import socket
import sys
import threading
import time
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field

import numpy as np
import torch

from torchblur.config import (CameraConfig, DMConfig, PlantConfig, SpotsConfig, WFSConfig, check_declared, key, load_dataclass,
                              validate_camera, validate_dm_model, validate_plant, validate_spots)
from torchblur.errors import ParameterError
from torchblur.hardware.frames import CameraInfo, encode_message, frame_message, raw_pixels
from torchblur.hardware.protocol import (E_ARGS, E_AXIS, E_BUSY, E_INTERNAL, E_LINE, E_RANGE, E_UNKNOWN, HOLD_PROTOCOL, MAX_LINE,
                                         PROTOCOL_VERSION, ProtocolViolation, format_err, format_ok, parse_command, pattern_checksum)
from torchblur.rig.base import check_drive, check_slew, check_tone_grid, command_peak, command_slew
from torchblur.rig.factory import build_dm, build_simulated_rig
from torchblur.rig.simulated import periodic_triggers, pulse_references
from torchblur import __version__

__all__ = ["FaultConfig", "EmulatorConfig", "load_emulator_config", "EmulatedDevice", "main"]

GARBAGE = b"\xff\x00\x1b[7m\x8f garbage \x07\n\xfe\x81\x00"


@dataclass(frozen=True)
class FaultConfig:
    timeout_after: int = key(-1, integer=True, low=-1)
    garbage_after: int = key(-1, integer=True, low=-1)
    reset_after: int = key(-1, integer=True, low=-1)
    drop_frame: int = key(-1, integer=True, low=-1)
    stale_frame: int = key(-1, integer=True, low=-1)
    exit_after: int = key(-1, integer=True, low=-1)
    hang_after: int = key(-1, integer=True, low=-1)
    disconnect_after: int = key(-1, integer=True, low=-1)
    repeat: int = key(1, integer=True, low=1)
    start: str = key("boot", choice=("boot", "wave"))  # the fault clock counts frames from "boot", or from the first WAVE ("wave": the sweep)


@dataclass(frozen=True)
class EmulatorConfig:
    plant: PlantConfig = field(default_factory=PlantConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    spots: SpotsConfig = field(default_factory=SpotsConfig)  # many spots (rows > 0), as in identify
    dm: DMConfig = field(default_factory=DMConfig)  # dm.n_across > 0: the DM mode (a mirror read by the wfs sensor)
    wfs: WFSConfig = field(default_factory=WFSConfig)  # the DM mode's Shack-Hartmann sensor
    seed: int = key(0, integer=True, low=0)
    transport: str = key("pty", choice=("pty", "socket"))  # "pty" (a pseudo-terminal) or "socket" (pyserial socket://)
    serial_port: int = key(0, integer=True, low=0, high=65535)  # transport=socket: TCP port of the serial line (0 = any free port)
    frames_port: int = key(0, integer=True, low=0, high=65535)  # TCP port of the camera channel (0 = any free port)
    threads: int = key(1, integer=True, low=1)  # torch threads for rendering
    exit_with_parent: bool = key(False, flag=True)  # exit when the process that started the emulator ends (tests)
    range_query: bool = key(True, flag=True)  # false: an older firmware that answers RANGE? with ERR 1 UNKNOWN (its range still holds)
    slew_query: bool = key(True, flag=True)  # false: an older firmware that answers SLEW? with ERR 1 UNKNOWN (its slew limit still holds)
    hold_wave: bool = key(True, flag=True)  # false: a protocol-2 firmware: ID? says protocol=2, WAVE pat HOLD is ERR 2 ARGS
    fault: FaultConfig = field(default_factory=FaultConfig)


def load_emulator_config(path: str | None = None, overrides: list[str] | None = None) -> EmulatorConfig:
    """Defaults, the YAML file (its identify-only sections ``sweep``, ``excitation``, ``fit``,
    ``model``, ``rig``, ``dm_plan`` are skipped, so one file serves both commands), then
    overrides; ``dm.n_across`` > 0 is the DM mode (docs/protocol.md, "The emulator").

    Raises:
        ConfigError: naming the key.
    """
    cfg = load_dataclass(EmulatorConfig, path, overrides, ignore_file_sections=("sweep", "excitation", "fit", "model", "rig", "dm_plan"))
    validate_dm_model(cfg.dm, cfg.wfs)
    validate_plant(cfg.plant)
    validate_camera(cfg.camera)
    validate_spots(cfg.spots, cfg.camera)
    check_declared(cfg, "")
    check_declared(cfg.fault, "fault")
    return cfg


def _log(msg: str) -> None:
    print(f"emulator: {msg}", file=sys.stderr, flush=True)


@dataclass
class _Job:
    epoch: int
    kind: str  # dark | still | hold | sine | multi | pulse
    first: int
    count: int
    exposure_s: float
    base_s: float  # clock time the schedule is relative to
    rel_trig: list  # trigger times relative to base_s
    args: dict


class FrameServer:
    """The camera channel: one client at a time on a loopback TCP port (a new client replaces
    the old one); a hello message on connect, then frame messages."""

    def __init__(self, info: CameraInfo, port: int = 0, protocol: int = PROTOCOL_VERSION):
        self.info, self.protocol = info, protocol
        self._srv = socket.create_server(("127.0.0.1", port), backlog=4)  # SO_REUSEADDR on POSIX
        self.port = self._srv.getsockname()[1]
        self._conn: socket.socket | None = None
        self._lock = threading.Lock()
        threading.Thread(target=self._accept_loop, name="frames-accept", daemon=True).start()

    @property
    def url(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    def _accept_loop(self) -> None:
        while True:
            try:
                conn, _ = self._srv.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            try:  # the hello before the client is published, outside the lock
                conn.settimeout(SEND_TIMEOUT_S)
                conn.sendall(encode_message({"type": "hello", "camera": self.info.to_dict(), "protocol": self.protocol}))
            except OSError:
                conn.close()
                continue
            with self._lock:
                old, self._conn = self._conn, conn
            if old is not None:
                with suppress(OSError):
                    old.close()

    def disconnect(self) -> None:
        """Close the current client's connection (it may connect again)."""
        with self._lock:
            if self._conn is not None:
                with suppress(OSError):
                    self._conn.shutdown(socket.SHUT_RDWR)
                    self._conn.close()
                self._conn = None

    def send(self, message: bytes) -> bool:
        """Send one message to the current client. The lock is held only to look the client
        up, never across ``sendall``; a client that does not take a message within
        :data:`SEND_TIMEOUT_S` is dropped (it may connect again), so a client that never
        reads cannot block the channel for the next one."""
        with self._lock:
            conn = self._conn
        if conn is None:
            return False
        try:
            conn.settimeout(SEND_TIMEOUT_S)
            conn.sendall(message)
            return True
        except OSError:  # socket.timeout included
            with self._lock:
                if self._conn is conn:
                    self._conn = None
            with suppress(OSError):
                conn.close()
            return False


SEND_TIMEOUT_S = 2.0
# The emulated device's ranges (ERR 4 RANGE beyond them; "pattern": a PAT weight); the command's
# amplitude (the peak of the waveform) is the simulated plant's input range, plant.input_limit
# (the DM mode: dm.input_limit, else plant.input_limit; RANGE? reports it).
DEVICE_RANGES = {"settle_s": 3600.0, "power": 1e6, "freq_hz": 1e5, "pattern": 1e6}


@contextmanager
def _range_error():
    """A rig check's :class:`ParameterError` answered as ``ERR 4 RANGE``."""
    try:
        yield
    except ParameterError as exc:
        raise ProtocolViolation(E_RANGE, str(exc)) from None


def _in_range(value: float, name: str) -> float:
    if abs(value) > DEVICE_RANGES[name]:
        raise ProtocolViolation(E_RANGE, f"{name}: at most {DEVICE_RANGES[name]:g} on this device, got {value!r}")
    return value


class EmulatedDevice:
    """The controller + camera state machine (transport independent).

    :meth:`handle` takes one command line and returns the reply bytes (None: no reply, a
    timeout fault). Acquisitions are scheduled on the simulated clock at once (``ARM``
    replies with the first frame counter) and rendered by a camera thread that sends the
    frames through ``send(message_bytes)``.
    """

    def __init__(self, cfg: EmulatorConfig, send, *, firmware: str = "0.1.0", name: str = "torchblur-emulator"):
        self.cfg = cfg
        if cfg.dm.enabled:  # the DM mode: one axis, "pat", the loaded pattern on every actuator
            mirror, _, self.rig = build_dm(cfg)  # the mirror, the sensor and the SimulatedDMRig a DM run builds
            self.axes, self.n_actuators = ("pat",), mirror.n_actuators
            limit = cfg.dm.input_limit if cfg.dm.input_limit is not None else cfg.plant.input_limit
        else:
            self.rig = build_simulated_rig(cfg)  # its plant, camera, spots and seed sections
            self.axes, self.n_actuators = tuple(self.rig.inputs), 0  # "x", or "x", "y" for a 2x2 plant; no pattern drive
            limit = self.rig.input_limit
        self._settling_s = self.rig._settling_time_s()  # the plant's, or the mirror's slowest actuator's
        self.input_limit = float(limit)  # RANGE?: the largest |command| on any actuator (dm.input_limit, else plant.input_limit)
        slew = None if cfg.dm.enabled else cfg.plant.slew_limit
        self.slew_limit = None if slew is None else float(slew)  # SLEW?: the largest |d command / dt| (None: none)
        self._send = send
        self.firmware, self.name = firmware, name
        self.protocol = PROTOCOL_VERSION if cfg.hold_wave else HOLD_PROTOCOL - 1  # ID?'s (hold_wave=false: the version before HOLD)
        self.lock = threading.RLock()
        self.jobs: queue.Queue = queue.Queue()
        f = cfg.fault
        self._timeouts_left = f.repeat
        self._garbage_left = f.repeat
        self._resets_left = f.repeat
        self._reset_at = f.reset_after
        self._disconnects_left = f.repeat
        self.on_disconnect = None  # set by the transport: close the client connections
        self.hung = False
        self.served = 0  # frames the camera finished with (sent or dropped)
        self._fault_base = 0 if f.start == "boot" else None  # the fault clock is served - base
        self._last_msg: bytes | None = None
        self.epoch = 0
        self._boot_state()
        threading.Thread(target=self._camera_loop, name="camera", daemon=True).start()

    # ------------------------------------------------------------------ state

    def _boot_state(self) -> None:
        self.boot = secrets.token_hex(4)
        self.counter = 0
        self.clock = 0.0
        self.cam_ready = 0.0
        self.wave: dict | None = None
        self.power = 0.0
        self.settle: float | None = None
        self.pending = 0
        self.reset_flag = False
        self.pattern = np.zeros(self.n_actuators)  # PAT: every actuator's weight (0 after a boot)

    def _reboot(self, why: str) -> None:
        with self.lock:
            self.epoch += 1
            self._boot_state()
            self.reset_flag = True
        _log(f"fault: controller reset ({why}); new boot {self.boot}")

    def fault_clock(self) -> float:
        """Frames served since the fault clock started (-inf before it starts)."""
        return -math.inf if self._fault_base is None else self.served - self._fault_base

    @property
    def camera_info(self) -> CameraInfo:
        return CameraInfo.of(self.rig, self.name)

    def _state(self) -> str:
        if self.reset_flag:
            return "RESET"
        if self.pending > 0:
            return "ARMED"
        return "RUNNING" if self.wave is not None else "IDLE"

    # ------------------------------------------------------------------ commands

    def handle(self, raw: bytes) -> bytes | None:
        """The reply to one line (None: no reply)."""
        if self.hung:
            return None
        f = self.cfg.fault
        if f.timeout_after >= 0 and self.fault_clock() >= f.timeout_after and self._timeouts_left > 0:
            self._timeouts_left -= 1
            _log(f"fault: no reply to {raw.strip()[:40]!r} (timeout_after={f.timeout_after}, served {self.served})")
            return None
        try:
            cmd = parse_command(raw)
            reply = self._execute(cmd)
        except ProtocolViolation as v:
            reply = v.reply
        except Exception as exc:  # a bug must not kill the device; say so on the line
            _log(f"internal error on {raw!r}: {exc!r}")
            reply = format_err(E_INTERNAL, f"{type(exc).__name__}: {exc}")
        out = reply.encode("ascii")
        if f.garbage_after >= 0 and self.fault_clock() >= f.garbage_after and self._garbage_left > 0:
            self._garbage_left -= 1
            _log(f"fault: garbage before the reply to {raw.strip()[:40]!r} (served {self.served})")
            out = GARBAGE + out
        return out

    def _execute(self, cmd) -> str:
        w, a = cmd.word, cmd.args
        with self.lock:
            if w == "ID?":
                return format_ok("ID", name=self.name, firmware=self.firmware, protocol=self.protocol, axes=",".join(self.axes))
            if w == "STATUS?":
                return format_ok("STATUS", state=self._state(), frames=self.counter, pending=self.pending, clock=float(self.clock),
                                 boot=self.boot)
            if w == "PING":
                return format_ok("PING", token=a[0])
            if w == "RANGE?":
                if not self.cfg.range_query:
                    raise ProtocolViolation(E_UNKNOWN, "unknown command 'RANGE?'")
                return format_ok("RANGE", amplitude=self.input_limit)
            if w == "SLEW?":
                if not self.cfg.slew_query:
                    raise ProtocolViolation(E_UNKNOWN, "unknown command 'SLEW?'")
                return format_ok("SLEW", rate="none" if self.slew_limit is None else self.slew_limit)
            if w == "RESET":
                self.epoch += 1
                self._boot_state()
                return format_ok("RESET", boot=self.boot)
            if w == "STOP":
                self.epoch += 1  # aborts frames not yet sent
                self.pending = 0
                self.wave = None
                self.reset_flag = False
                return format_ok("STOP")
            if w == "POWER":
                self.power = _in_range(a[0], "power")
                return format_ok("POWER", p=a[0])
            if w == "SETTLE":
                self.settle = a[0] if a[0] is None else _in_range(a[0], "settle_s")
                return format_ok("SETTLE", s="AUTO" if a[0] is None else a[0])
            if w == "WAVE":
                return self._wave(a)
            if w == "ARM":
                return self._arm(*a)
            if w == "PULSE":
                return self._pulse(*a)
            if w == "ACT?":
                return format_ok("ACT", n=self.n_actuators)
            if w in ("PAT", "PAT?"):
                return self._pat(*a)
        raise ProtocolViolation(E_INTERNAL, f"no handler for {w}")  # pragma: no cover - parse_command knows the words

    def _check_exposure(self, te: float) -> None:
        if te > self.rig.max_exposure_s:
            raise ProtocolViolation(E_RANGE, f"exposure_s: at most {self.rig.max_exposure_s!r} s on this camera, got {te!r}")

    def _check_drive(self, peak: float, slew: float = 0.0) -> None:
        """ERR 4 RANGE for a waveform whose peak |command| exceeds the plant's input range, or
        whose slew rate ``slew`` (input units/s) exceeds its slew limit."""
        with _range_error():
            check_drive(peak, self.input_limit)
            check_slew(slew, self.slew_limit)

    def _wave(self, a) -> str:
        axis, mode = a[0], a[1]
        if axis not in self.axes:
            raise ProtocolViolation(E_AXIS, f"this device drives axis {' and '.join(self.axes)} only, got {axis}")
        if mode == "HOLD" and self.protocol < HOLD_PROTOCOL:
            raise ProtocolViolation(E_ARGS, f"WAVE: mode must be SINE or MULTI, got {mode!r}")  # as a protocol-2 firmware says
        if mode == "HOLD" and axis != "pat":
            raise ProtocolViolation(E_AXIS, f"HOLD drives axis pat only, got {axis}")
        if mode == "MULTI" and axis != "x":
            raise ProtocolViolation(E_AXIS, f"MULTI drives axis x only, got {axis}")
        if self.pending:
            raise ProtocolViolation(E_BUSY, f"{self.pending} frame(s) pending; STOP first")
        self.reset_flag = False
        if self._fault_base is None:
            self._fault_base = self.served
        if axis == "pat":
            return self._pattern_wave(mode, *a[2:])
        if mode == "SINE":
            _in_range(a[2], "freq_hz")
            self._check_drive(abs(a[3]), abs(a[3]) * 2 * math.pi * a[2])
            self.wave = {"mode": "SINE", "freq_hz": a[2], "amplitude": a[3], "start": self.clock, "period": 1.0 / a[2], "axis": axis}
            return format_ok("WAVE", axis=axis, mode=mode, start=float(self.clock))
        tones, f0 = a[2], a[2][0][0]
        with _range_error():  # the triggers count the first tone's periods: every tone a whole multiple of it
            check_tone_grid([t[0] for t in tones], f0)
        self._check_drive(command_peak(*zip(*tones), base_freq_hz=f0), command_slew(*zip(*tones), base_freq_hz=f0))
        self.wave = {"mode": "MULTI", "tones": tones, "start": self.clock, "period": 1.0 / f0}
        return format_ok("WAVE", axis=axis, mode=mode, tones=len(tones), start=float(self.clock))

    def _pat(self, start: int | None = None, values: tuple = ()) -> str:
        """``PAT?`` (no arguments) or ``PAT <start> <v> ...``: the pattern's size and checksum, or
        load ``values`` at ``start``. Refused while a waveform runs (it drives the pattern)."""
        N = self.n_actuators
        if N == 0:
            raise ProtocolViolation(E_AXIS, "this device has no actuator pattern (ACT? n=0)")
        if start is None:
            return format_ok("PAT", n=N, crc=pattern_checksum(self.pattern))
        if start + len(values) > N:
            raise ProtocolViolation(E_RANGE, f"PAT: entries {start}..{start + len(values) - 1} beyond the {N} actuators")
        if self.wave is not None or self.pending:
            raise ProtocolViolation(E_BUSY, "PAT while a waveform runs or frames are pending; STOP first")
        bad = [v for v in values if abs(v) > DEVICE_RANGES["pattern"]]
        if bad:
            raise ProtocolViolation(E_RANGE, f"pattern: a weight of at most {DEVICE_RANGES['pattern']:g} in magnitude, got {bad[0]!r}")
        self.pattern[start:start + len(values)] = values
        return format_ok("PAT", start=start, count=len(values))

    def _pattern_wave(self, mode: str, *args) -> str:
        """``WAVE pat SINE f a`` (``a * pattern[j] * sin(2 pi f (t - start))`` on actuator j) or
        ``WAVE pat HOLD u`` (protocol 3: actuator j held still at ``u * pattern[j]`` from now). The
        peak command (``|a|`` or ``|u|`` times ``max |pattern|``) must be within RANGE (the safe
        drive) and the simulated rig's own checks of the command (its spots stay in their crops)
        must pass, else ERR 4; the reply names the checksum of the pattern it drives."""
        if mode == "SINE":
            _in_range(args[0], "freq_hz")
        pattern = self.pattern.copy()
        self._check_drive(abs(args[-1]) * float(np.abs(pattern).max(initial=0.0)))
        with _range_error():
            if mode == "SINE":
                self.rig.check_pattern(pattern, *args)
            else:
                self.rig.check_ladder(pattern, list(args))
        wave = {"freq_hz": args[0], "amplitude": args[1], "period": 1.0 / args[0]} if mode == "SINE" else {"level": args[0]}
        self.wave = {"mode": mode, **wave, "start": self.clock, "axis": "pat", "pattern": pattern}
        return format_ok("WAVE", axis="pat", mode=mode, start=float(self.clock), crc=pattern_checksum(pattern))

    def _arm(self, off: float, te: float, n: int) -> str:
        self._check_exposure(te)
        if self.pending:
            raise ProtocolViolation(E_BUSY, f"{self.pending} frame(s) of the last acquisition pending")
        cycle = self.rig._cycle_s(te)
        self.reset_flag = False
        if self.wave is None or self.wave["mode"] == "HOLD":  # still: every camera cycle, the first offset after ready
            if off < 0:
                raise ProtocolViolation(E_RANGE, "trigger_offset_s: must be >= 0 without a waveform or with a HOLD")
            base = max(self.clock, self.cam_ready) + off
            rel = [i * cycle for i in range(n)]
            kind = "dark" if self.power == 0 else "still"
            args = {"power": self.power}
            if self.wave is not None:  # a hold: its settling wait (SETTLE, else the mirror's settling time) first
                settle = self.settle if self.settle is not None else self._settling_s
                base = max(base, self.wave["start"] + settle + off)
                kind, args = "hold", {"wave": dict(self.wave), "offset": off, "power": self.power}
        else:
            wv = self.wave
            period = wv["period"]
            settle = self.settle if self.settle is not None else math.ceil(self._settling_s / period - 1e-9) * period
            ready = max(settle, self.cam_ready - wv["start"])
            rel = periodic_triggers(ready, period, off, n, cycle)  # SimulatedRig.sine's schedule
            base = wv["start"]
            kind = "sine" if wv["mode"] == "SINE" else "multi"
            args = {"wave": dict(wv), "settle_s": ready, "offset": off, "power": self.power}
        return self._schedule(kind, te, n, base, rel, cycle, args, "ARM")

    def _pulse(self, off: float, p0: float, width: float, te: float, n: int) -> str:
        self._check_exposure(te)
        if self.pending:
            raise ProtocolViolation(E_BUSY, f"{self.pending} frame(s) of the last acquisition pending")
        if self.wave is not None:
            raise ProtocolViolation(E_BUSY, "PULSE needs the mirror still: STOP the waveform first")
        self.reset_flag = False
        cycle = self.rig._cycle_s(te)
        base = max(self.clock, self.cam_ready)
        refs, ready = pulse_references([off] * n, p0, width, cycle)  # SimulatedRig.pulse's schedule
        rel = [ref + off for ref in refs]
        args = {"offset": off, "pulse_time_s": p0, "pulse_width_s": width, "power": self.power, "end": ready}
        return self._schedule("pulse", te, n, base, rel, cycle, args, "PULSE")

    def _schedule(self, kind, te, n, base, rel, cycle, args, word) -> str:
        first = self.counter
        self.counter += n
        self.pending = n
        end = base + (args["end"] if kind == "pulse" else rel[-1] + cycle)
        self.cam_ready = end
        self.clock = max(self.clock, end)
        self.jobs.put(_Job(self.epoch, kind, first, n, te, base, rel, args))
        return format_ok(word, first=first, count=n)

    # ------------------------------------------------------------------ camera

    def _render(self, job: _Job):
        """Frames ``[n, H, W]`` (ADU) and their trigger times relative to the job's base."""
        r = self.rig
        te, n, a = job.exposure_s, job.count, job.args
        if job.kind == "dark":
            cap = r.dark(n=n, exposure_s=te)
        elif job.kind == "still":
            cap = r.still(n=n, exposure_s=te, power=a["power"])
        elif job.kind == "pulse":
            cap = r.pulse(exposure_s=te, trigger_offset_s=a["offset"], pulse_time_s=a["pulse_time_s"],
                          pulse_width_s=a["pulse_width_s"], n=n, power=a["power"])
        elif job.kind == "hold":  # the DM mode's static hold: SimulatedDMRig's pattern_ladder, one level
            wv = a["wave"]
            cap = r.pattern_ladder(pattern=wv["pattern"], levels=[wv["level"]], n=n, exposure_s=te, power=a["power"])
        elif job.kind == "sine" and a["wave"]["axis"] == "pat":  # the DM mode: SimulatedDMRig's own renderer
            wv = a["wave"]
            cap = r.pattern_sine(wv["pattern"], wv["freq_hz"], wv["amplitude"], [te], a["offset"], n, settle_s=a["settle_s"],
                                 power=a["power"])
        elif job.kind == "sine":
            wv = a["wave"]
            cap = r.sine(freq_hz=wv["freq_hz"], amplitude=wv["amplitude"], exposures_s=[te], trigger_offset_s=a["offset"],
                         n_repeats=n, settle_s=a["settle_s"], power=a["power"], input=wv.get("axis", "x"))
        else:  # MULTI, tones on the first's grid (WAVE checks): SimulatedRig.multisine's schedule and exact response
            f, amp, phase = zip(*a["wave"]["tones"])
            cap = r.multisine(freq_hz=f, amplitude=amp, phase_rad=phase, exposures_s=[te], trigger_offset_s=a["offset"],
                              n_repeats=n, base_freq_hz=f[0], settle_s=a["settle_s"], power=a["power"])
        trig = cap.trigger_time_s.reshape(-1).tolist()
        if not np.allclose(trig, job.rel_trig, rtol=0, atol=1e-9):
            _log(f"warning: schedule mismatch for {job.kind}: {trig[:3]} vs {job.rel_trig[:3]}")
        return cap.frames.reshape((n,) + tuple(r.frame_shape)).numpy(), trig

    def _camera_loop(self) -> None:
        while True:
            job = self.jobs.get()
            if job.epoch != self.epoch or self.hung:
                continue
            try:
                frames, trig = self._render(job)
            except Exception as exc:
                _log(f"internal error rendering {job.kind}: {exc!r}")
                with self.lock:
                    if job.epoch == self.epoch:
                        self.pending = 0
                continue
            off = job.args.get("offset", 0.0)
            if job.kind in ("sine", "multi"):
                period = job.args["wave"]["period"]
                off = off - math.floor(off / period) * period
            for i in range(job.count):
                if not self._serve(job, i, frames[i], trig[i], off):
                    break

    def _serve(self, job: _Job, i: int, frame: np.ndarray, trig: float, off: float) -> bool:
        f = self.cfg.fault
        with self.lock:
            if job.epoch != self.epoch or self.hung:
                return False
            idx = self.fault_clock()
            self.served += 1
            self.pending -= 1
            counter = job.first + i
            msg = frame_message(raw_pixels(frame), counter=counter, timestamp_s=job.base_s + trig, trigger_time_s=trig,
                                trigger_offset_s=off, exposure_s=job.exposure_s, boot=self.boot, kind=job.kind)
        send = msg
        if f.drop_frame >= 0 and f.drop_frame <= idx < f.drop_frame + f.repeat:
            _log(f"fault: dropped frame {counter} (fault clock {idx})")
            send = None
        elif f.stale_frame >= 0 and f.stale_frame <= idx < f.stale_frame + f.repeat:
            _log(f"fault: stale frame instead of frame {counter} (fault clock {idx})")
            send = self._last_msg
        if send is not None:
            self._send(send)
        self._last_msg = msg
        n_served = idx + 1  # on the fault clock
        if f.exit_after >= 0 and n_served >= f.exit_after:
            _log(f"fault: exiting after {n_served} frames (exit_after={f.exit_after})")
            os._exit(3)
        if f.hang_after >= 0 and n_served >= f.hang_after:
            self.hung = True
            _log(f"fault: hanging after {n_served} frames (hang_after={f.hang_after})")
            return False
        if f.disconnect_after >= 0 and n_served >= f.disconnect_after and self._disconnects_left > 0:
            self._disconnects_left -= 1
            _log(f"fault: closing the client connections after {n_served} frames (disconnect_after={f.disconnect_after})")
            if self.on_disconnect is not None:
                self.on_disconnect()
        if self._reset_at >= 0 and n_served >= self._reset_at and self._resets_left > 0:
            self._resets_left -= 1
            self._reset_at = n_served + 1
            self._reboot(f"reset_after={f.reset_after}, after {n_served} frames")
            return False
        return True


# ---------------------------------------------------------------------- transports


class _LineBuffer:
    """Splits a byte stream into lines; an over-long line becomes one ERR 7 reply."""

    def __init__(self):
        self.buf = b""
        self.overflow = False

    def feed(self, data: bytes):
        self.buf += data
        out = []
        while True:
            i = self.buf.find(b"\n")
            if i < 0:
                if len(self.buf) > MAX_LINE + 1:
                    self.overflow = True
                    self.buf = b""
                return out
            line, self.buf = self.buf[: i + 1], self.buf[i + 1:]
            if self.overflow:
                self.overflow = False
                out.append(None)  # the tail of an over-long line
            else:
                out.append(line)


def _reply(device: EmulatedDevice, line: bytes | None) -> bytes | None:
    if line is None:
        return None if device.hung else format_err(E_LINE, f"line longer than {MAX_LINE} bytes").encode()
    return device.handle(line)


def serve_pty(device: EmulatedDevice, master: int) -> None:
    """Serve the protocol on a pseudo-terminal master until killed."""
    lines = _LineBuffer()
    os.set_blocking(master, False)
    while True:
        r, _, _ = select.select([master], [], [], 1.0)
        if not r:
            continue
        try:
            data = os.read(master, 4096)
        except BlockingIOError:
            continue
        except OSError:  # no client has the slave open right now
            time.sleep(0.05)
            continue
        for line in lines.feed(data):
            out = _reply(device, line)
            if out:
                _write_all(master, out)


def _write_all(fd: int, data: bytes) -> None:
    t_end = time.monotonic() + 1.0
    while data and time.monotonic() < t_end:
        try:
            n = os.write(fd, data)
            data = data[n:]
        except BlockingIOError:
            select.select([], [fd], [], 0.05)
        except OSError:
            return  # nobody reading: the bytes are lost, as on a real line


def serve_socket(device: EmulatedDevice, srv: socket.socket, current: dict | None = None) -> None:
    """Serve the protocol on a TCP listening socket (pyserial ``socket://``), one client at a time;
    ``current["conn"]`` is the client's connection (for the disconnect fault)."""
    current = {} if current is None else current
    while True:
        conn, _ = srv.accept()
        current["conn"] = conn
        lines = _LineBuffer()
        with conn:
            while True:
                try:
                    data = conn.recv(4096)
                except OSError:
                    break
                if not data:
                    break
                for line in lines.feed(data):
                    out = _reply(device, line)
                    if out:
                        try:
                            conn.sendall(out)
                        except OSError:
                            break


def main(argv: list[str] | None = None, *, config_path: str | None = None) -> int:
    """Run the emulator with ``key=value`` overrides; prints the JSON start line."""
    import tty

    cfg = load_emulator_config(config_path, list(argv or []))
    torch.set_num_threads(int(cfg.threads))
    if cfg.exit_with_parent:
        parent = os.getppid()

        def watch():
            while os.getppid() == parent:
                time.sleep(0.5)
            os._exit(0)

        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    holder: dict = {}
    device = EmulatedDevice(cfg, lambda msg: holder["frames"].send(msg), firmware=__version__)
    holder["frames"] = FrameServer(device.camera_info, cfg.frames_port, device.protocol)
    serial_conn: dict = {}

    def disconnect():
        holder["frames"].disconnect()
        conn = serial_conn.get("conn")
        if conn is not None:
            with suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)

    device.on_disconnect = disconnect
    info = {"frames": holder["frames"].url, "pid": os.getpid(), "protocol": device.protocol, "transport": cfg.transport,
            "name": device.name, "firmware": __version__, "boot": device.boot, "seed": int(cfg.seed)}
    if cfg.transport == "pty":
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CRLF translation
        info["serial"] = os.ttyname(slave)
        print(json.dumps(info), flush=True)
        try:
            serve_pty(device, master)  # keeps `slave` open so the master never sees EIO
        finally:
            os.close(slave)
    else:
        srv = socket.create_server(("127.0.0.1", int(cfg.serial_port)), backlog=1)
        info["serial"] = f"socket://127.0.0.1:{srv.getsockname()[1]}"
        print(json.dumps(info), flush=True)
        serve_socket(device, srv, serial_conn)
    return 0
