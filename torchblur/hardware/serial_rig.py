"""A :class:`~torchblur.rig.base.Rig` on a real (or emulated) bench: a controller on a serial line
(:class:`~torchblur.hardware.controller.Controller`) and a camera
(:class:`~torchblur.hardware.frames.FrameSource`); every call one transaction, every frame checked,
faults retried, then :class:`~torchblur.hardware.errors.AcquisitionStopped` (docs/protocol.md, "Client rules").
"""
from __future__ import annotations

import importlib
import math
import time
from typing import Callable, Sequence

import torch

from torchblur.errors import ConfigError, ParameterError, check_int, check_real_scalar
from torchblur.hardware.controller import Controller
from torchblur.hardware.errors import (AcquisitionStopped, ConnectionLost, DeviceError, DeviceReset, FrameGap, FrameMismatch, FrameTimeout,
                     GarbageReply, HardwareError, StaleFrame)
from torchblur.hardware.frames import CameraInfo, CameraProperties, EmulatorFrames, Frame, FrameSource
from torchblur.rig.base import Capture, RigChecks, check_drive, check_slew, command_peak, command_slew, float_list, per_exposure
from torchblur.hardware.aravis import AravisCamera  # imports its SDK on use
from torchblur.hardware.protocol import MAX_COUNT, MAX_LINE, MAX_TONES, format_tones
from torchblur.hardware.pylon import PylonCamera  # imports its SDK on use

__all__ = ["SerialRig", "open_frame_source"]

_F64 = torch.float64


def open_frame_source(spec: str) -> FrameSource:
    """A frame source from its config string: ``tcp://HOST:PORT`` (the emulator's camera
    channel), ``pylon://[SERIAL][?trigger=Line1&pixel_format=Mono12&readout_s=1e-3]`` (a Basler
    camera through pypylon, :class:`~torchblur.hardware.pylon.PylonCamera`; the ``pylon`` extra)
    ``aravis://[DEVICE][?trigger=Line1&pixel_format=Mono16&readout_s=1e-3]`` (a GenICam camera
    through Aravis, :class:`~torchblur.hardware.aravis.AravisCamera`; the ``aravis`` extra)
    or ``package.module:ClassName`` (a :class:`~torchblur.hardware.camera_sdk.SDKCamera`
    subclass, constructed without arguments).

    Raises:
        ConfigError: a malformed ``pylon://`` URL, naming ``rig.frames``.
        HardwareError: the camera cannot be opened (none found, no such serial).
    """
    if spec.startswith("tcp://"):
        return EmulatorFrames(spec)
    for scheme, camera in (("pylon://", PylonCamera), ("aravis://", AravisCamera)):
        if spec.startswith(scheme):
            try:
                return camera.from_url(spec)
            except ParameterError as exc:
                raise ConfigError(f"rig.frames: {spec!r}: {str(exc).removeprefix('url: ')}") from None
    mod, sep, name = spec.partition(":")
    if sep and mod and name and "/" not in spec:
        cls = getattr(importlib.import_module(mod), name)
        return cls()
    raise ValueError(f"rig.frames: expected tcp://HOST:PORT, pylon://[SERIAL][?...] or package.module:ClassName, got {spec!r}")


class SerialRig(CameraProperties, RigChecks):
    """The :class:`~torchblur.rig.base.Rig` protocol over a controller and a camera.

    Args:
        controller: an open :class:`Controller`.
        frames: the camera, a :class:`FrameSource`.
        axis: the controller axis the sine drives (``"x"`` or ``"y"``).
        retries: how many times a failed call is redone (faults of the link or the frames).
        reconnects: how many times a lost connection is reopened during the run.
        poll_s: silence on the camera channel after which ``STATUS?`` is polled (s).
        idle_polls: how many polls in a row, with no frame between them, must find the controller
            idle (``pending=0``) while frames are missing for the next one to be declared lost
            (``FrameTimeout``; an int >= 1).
        max_wait_s: the longest wait for one acquisition's frames while the controller says
            they are still pending (s).
        log: callable taking one message string (faults, retries); default: kept in
            :attr:`events` only.
    """

    #: the controller axes this rig drives (a subclass for a deformable mirror drives ``"pat"``)
    AXES = ("x", "y")

    def __init__(self, controller: Controller, frames: FrameSource, *, axis: str = "x", retries: int = 2, reconnects: int = 1,
                 poll_s: float = 0.25, max_wait_s: float = 60.0, idle_polls: int = 2, log: Callable[[str], None] | None = None):
        if axis not in self.AXES:
            raise ParameterError(f"axis: expected one of {', '.join(repr(a) for a in self.AXES)}, got {axis!r}")
        self.controller = controller
        self.frames = frames
        self.axis = axis
        self.retries = check_int(retries, "retries", low=0)
        self.reconnects = int(reconnects)
        self.poll_s = check_real_scalar(poll_s, "poll_s", positive=True)
        self.max_wait_s = check_real_scalar(max_wait_s, "max_wait_s", positive=True)
        self.idle_polls = check_int(idle_polls, "idle_polls", low=1)
        self.events: list[str] = []
        self._log = log
        self._boot: str | None = None
        self._next: int = 0
        self._dirty = False
        self.device: dict = {}
        self.stats = {"calls": 0, "retries": 0, "stale_discarded": 0, "resets": 0, "reconnects": 0}
        try:
            self._connect()
        except HardwareError as exc:
            raise AcquisitionStopped(f"cannot talk to the controller on {controller.port}: {exc}", exc) from exc

    @classmethod
    def open(cls, port: str, frames: str | FrameSource, *, timeout_s: float = 2.0, **kwargs) -> "SerialRig":
        """Open the controller on ``port`` (device path or pyserial URL) and the camera
        ``frames`` (a :class:`FrameSource` or its config string, see :func:`open_frame_source`)."""
        try:
            ctl = Controller(port, timeout_s=timeout_s)
        except ConnectionLost as exc:
            raise AcquisitionStopped(str(exc), exc) from exc
        try:
            src = open_frame_source(frames) if isinstance(frames, str) else frames
        except HardwareError as exc:
            ctl.close()
            raise AcquisitionStopped(str(exc), exc) from exc
        except BaseException:
            ctl.close()
            raise
        try:
            return cls(ctl, src, **kwargs)
        except BaseException:
            ctl.close()
            src.close()
            raise

    # ------------------------------------------------------------------ Rig properties

    @property
    def info(self) -> CameraInfo:
        return self.frames.info

    @property
    def input_limit(self) -> float | None:
        """The controller's input range (``RANGE?``, read on connecting): the largest |command|
        (input units) it takes; None for a controller that does not answer the query."""
        return self.device.get("input_limit")

    @property
    def slew_limit(self) -> float | None:
        """The controller's slew-rate limit (``SLEW?``, read on connecting): the largest
        |d command / dt| (input units per second) it takes; None for a controller without one
        or one that does not answer the query (an older firmware)."""
        return self.device.get("slew_limit")

    def set_logger(self, log: Callable[[str], None] | None) -> None:
        self._log = log

    #: the longest a closing STOP waits for its reply (s): a healthy controller answers in
    #: milliseconds, and Ctrl-C on a hung one must not wait for the port's full timeout
    CLOSE_STOP_TIMEOUT_S = 1.0

    def close(self) -> None:
        """Stop the waveform (best effort, :attr:`CLOSE_STOP_TIMEOUT_S` at most) and close the
        controller and the frame source."""
        try:
            if self.controller.is_open:
                self.controller.stop(timeout_s=min(self.controller.timeout_s, self.CLOSE_STOP_TIMEOUT_S))
        except HardwareError:
            pass
        self.controller.close()
        self.frames.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ link management

    def _note(self, msg: str) -> None:
        self.events.append(msg)
        if self._log is not None:
            self._log(msg)

    def _connect(self) -> None:
        c = self.controller
        c.resync()
        self.device = c.identify()
        if self.axis not in self.device["axes"]:
            raise DeviceError(5, "AXIS", f"the controller has axes {self.device['axes']}, not {self.axis}", "ID?")
        self.device["input_limit"] = c.input_range()
        self.device["slew_limit"] = c.slew_rate()
        c.stop()
        st = c.status()
        self._boot, self._next = st["boot"], st["frames"]
        self.frames.drain()

    def _recover(self) -> None:
        """Back in step after a fault: resync, STOP, learn the counter and boot, drain frames."""
        c = self.controller
        c.resync()
        c.stop()
        st = c.status()
        self._boot_change(st, f"controller reset detected (boot {self._boot} -> {st['boot']}, frame counter now "
                              f"{st['frames']})")
        self._next = st["frames"]
        n = self.frames.drain()
        if n:
            self.stats["stale_discarded"] += n
            self._note(f"discarded {n} frame(s) left over from the failed attempt")

    def _boot_change(self, st: dict, message: str) -> bool:
        """Whether ``STATUS?``'s boot id ``st["boot"]`` is new: then counted, noted (``message``) and kept."""
        if st["boot"] == self._boot:
            return False
        self.stats["resets"] += 1
        self._note(message)
        self._boot = st["boot"]
        return True

    def _reconnect(self) -> None:
        self.stats["reconnects"] += 1
        self.controller.close()
        self.frames.close()
        time.sleep(0.2)
        self.controller.reopen()
        self.frames.reopen()
        self._connect()

    def _call(self, what: str, fn):
        """Run one transaction with bounded retries; raise AcquisitionStopped when they fail."""
        self.stats["calls"] += 1
        reconnects_left = self.reconnects
        last: BaseException | None = None
        attempt = 0
        while attempt <= self.retries:
            try:
                if self._dirty:
                    self._recover()
                self._dirty = True
                out = fn()
                self._dirty = False
                return out
            except ConnectionLost as exc:
                self._note(f"{what}: connection lost: {exc}")
                if reconnects_left <= 0:
                    raise AcquisitionStopped(f"{what}: the connection was lost ({exc}) and may not be reopened again", exc) from exc
                reconnects_left -= 1
                try:
                    self._reconnect()
                    self._dirty = False
                    self._note(f"{what}: reconnected to {self.controller.port}; redoing the call")
                except HardwareError as exc2:
                    raise AcquisitionStopped(f"{what}: the connection was lost ({exc}) and reopening it failed ({exc2})",
                                             exc2) from exc
                last = exc
            except DeviceError as exc:
                last = exc
                if not exc.recoverable:
                    raise AcquisitionStopped(f"{what}: the controller refused a command: {exc}", exc) from exc
                self._note(f"{what}: attempt {attempt + 1} failed: {exc}")
            except HardwareError as exc:
                last = exc
                self._note(f"{what}: attempt {attempt + 1} failed: {type(exc).__name__}: {exc}")
            attempt += 1
            if attempt <= self.retries:
                self.stats["retries"] += 1
                self._note(f"{what}: retrying ({attempt} of {self.retries})")
        raise AcquisitionStopped(f"{what}: gave up after {attempt} attempt(s); last fault: {type(last).__name__}: {last}", last)

    def _begin(self) -> None:
        """Each transaction starts by checking the controller did not reset since the last one."""
        st = self.controller.status()
        if self._boot_change(st, f"controller reset between calls detected (boot {self._boot} -> {st['boot']}); "
                                 f"earlier frames were complete and checked"):
            self._next = st["frames"]
        if st["frames"] < self._next:
            raise DeviceReset(f"frame counter went back from {self._next} to {st['frames']}")
        self._next = st["frames"]

    def _read_frames(self, first: int, n: int, exposure_s: float) -> list[Frame]:
        """Frames ``first .. first + n - 1``, each checked. Waiting, ``STATUS?`` is polled after
        every ``poll_s`` of silence; a frame is lost (``FrameTimeout``) when ``idle_polls`` polls
        in a row, with no frame between them, find the controller idle (``pending=0``; a frame leaves
        ``pending`` when it is sent, and may still be on its way at the first). Any frame that
        arrives, and any poll that finds frames pending, starts the count again; ``max_wait_s``
        bounds the whole wait."""
        c, src = self.controller, self.frames
        got: list[Frame] = []
        expected = first
        t_end = time.monotonic() + self.max_wait_s
        idle_polls = 0
        H, W = self.frame_shape
        while len(got) < n:
            try:
                fr = src.read(self.poll_s)
            except FrameTimeout:
                if time.monotonic() > t_end:
                    raise FrameTimeout(f"frame {expected} did not arrive within {self.max_wait_s:g} s") from None
                st = c.status()
                if st["boot"] != self._boot or st["state"] == "RESET":
                    raise DeviceReset(f"the controller reset while frames {expected}..{first + n - 1} were pending "
                                      f"(boot {self._boot} -> {st['boot']}, state {st['state']})") from None
                if st["frames"] < expected:
                    raise DeviceReset(f"frame counter went back from {expected} to {st['frames']}") from None
                idle_polls = idle_polls + 1 if st["pending"] == 0 else 0
                if idle_polls >= self.idle_polls:
                    raise FrameTimeout(f"frame {expected} was triggered but never arrived (controller idle for "
                                       f"{idle_polls} polls in a row with no frame, counter {st['frames']})") from None
                continue
            idle_polls = 0  # a frame arrived: the channel is still delivering, the count starts again
            if fr.boot is not None and self._boot is not None and fr.boot != self._boot:
                self.stats["stale_discarded"] += 1
                continue  # from before a reset: never ours
            if fr.counter < first:
                self.stats["stale_discarded"] += 1
                continue  # left over from an earlier, abandoned acquisition
            if fr.counter < expected:
                raise StaleFrame(f"frame {fr.counter} arrived again while frame {expected} was expected")
            if fr.counter > expected:
                raise FrameGap(f"frame counter jumped from {expected} to {fr.counter}: {fr.counter - expected} frame(s) dropped")
            if tuple(fr.data.shape) != (H, W):
                raise FrameMismatch(f"frame {fr.counter} has shape {tuple(fr.data.shape)}, expected {(H, W)}")
            if not torch.isfinite(fr.data).all():
                raise FrameMismatch(f"frame {fr.counter} holds NaN or infinite pixels")
            if not math.isclose(fr.exposure_s, exposure_s, rel_tol=1e-9, abs_tol=1e-12):
                raise FrameMismatch(f"frame {fr.counter} has exposure {fr.exposure_s!r} s, expected {exposure_s!r} s")
            got.append(fr)
            expected += 1
        return got

    def _acquire(self, exposure_s: float, n: int, fire) -> list[Frame]:
        """prepare the camera, fire the triggers (``fire()`` -> (first, count)), read the frames."""
        self.frames.prepare(exposure_s, n)
        first, count = fire()
        if count != n:
            raise GarbageReply(f"the controller armed {count} frames, {n} were asked")
        if first < self._next:
            raise DeviceReset(f"frame counter went back from {self._next} to {first}")
        self.frames.bind(first, n)
        frames = self._read_frames(first, n, exposure_s)
        self._next = first + n
        return frames

    # ------------------------------------------------------------------ captures

    def _capture(self, frames: list[Frame], shape: tuple, offsets, meta: dict):

        H, W = self.frame_shape
        data = torch.stack([f.data for f in frames]).reshape(shape + (H, W))
        t = lambda attr: torch.tensor([getattr(f, attr) for f in frames], dtype=_F64).reshape(shape)  # noqa: E731
        meta = dict(meta)
        meta.update({"boot": self._boot, "timestamp_s": t("timestamp_s"), "dtype": frames[0].dtype})
        return Capture(frames=data, exposure_s=t("exposure_s"), trigger_offset_s=torch.as_tensor(offsets, dtype=_F64).reshape(shape),
                       trigger_time_s=t("trigger_time_s"),
                       frame_counter=torch.tensor([f.counter for f in frames], dtype=torch.long).reshape(shape), meta=meta)

    def _armed(self, te: float, n: int) -> list[Frame]:
        """``n`` frames at exposure ``te`` with no offset (still, dark or a hold), ``ARM 0 te m`` as
        many times as it takes: an ARM fires at most MAX_COUNT triggers."""
        c = self.controller
        counts = [min(MAX_COUNT, n - k) for k in range(0, n, MAX_COUNT)]
        return [f for m in counts for f in self._acquire(te, m, lambda m=m: c.arm(0.0, te, m))]

    def _transaction(self, what: str, power: float, body, *, wave: bool = False,
                     settle_s: float | None = None) -> list[Frame]:
        """One rig call as a transaction redone on faults (:meth:`_call`): the boot checked
        (:meth:`_begin`), ``STOP``, ``POWER power``, with a ``wave`` ``SETTLE settle_s`` (None:
        ``AUTO``), then ``body(controller)`` -> its frames, then with a ``wave`` ``STOP``."""
        c = self.controller

        def once():
            self._begin()
            c.stop()
            c.power(power)
            if wave:
                c.settle(settle_s)
            frames = body(c)
            if wave:
                c.stop()
            return frames

        return self._call(what, once)

    def dark(self, n: int, exposure_s: float):
        """``n`` frames with the laser off (``POWER 0``, no waveform), ``[n, H, W]``."""
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        frames = self._transaction(f"dark ({n} x {te:g} s)", 0.0, lambda c: self._armed(te, n))
        return self._capture(frames, (n,), [0.0] * n, {"kind": "dark"})

    def still(self, n: int, exposure_s: float, power: float = 1.0):
        """``n`` frames of the spot at rest at ``power``, ``[n, H, W]``."""
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        power = self._check_power(power)
        frames = self._transaction(f"still ({n} x {te:g} s)", power, lambda c: self._armed(te, n))
        return self._capture(frames, (n,), [0.0] * n, {"kind": "still", "power": power})

    def sine(self, freq_hz: float, amplitude: float, exposures_s: Sequence[float], trigger_offset_s, n_repeats: int,
             settle_s: float | None = None, power: float = 1.0, input: str | None = None):
        """``WAVE <input> SINE f A`` (from rest), then per exposure ``ARM offset Te R``:
        frames ``[E, R, H, W]``. ``settle_s`` None sends ``SETTLE AUTO`` (the controller's
        default settling wait). ``input``: the driven axis, ``"x"`` or ``"y"`` (one the
        controller reported in ``ID?``); None: the rig's ``axis``."""
        axis = self.axis if input is None else input
        if axis not in ("x", "y"):
            raise ParameterError(f"input: expected 'x' or 'y', got {input!r}")
        if self.device.get("axes") and axis not in self.device["axes"]:
            raise ParameterError(f"input: the controller drives axes {self.device['axes']}, got {input!r}")
        freq, amp = self._check_sine(freq_hz, amplitude)
        return self._periodic_capture(f"sine {freq:g} Hz", lambda c: c.wave_sine(axis, freq, amp), 1.0 / freq, exposures_s,
                                      trigger_offset_s, n_repeats, check_real_scalar(power, "power"), settle_s,
                                      {"kind": "sine", "freq_hz": freq, "omega": 2 * math.pi * freq, "period_s": None, "amplitude": amp,
                                       "settle_s": None, "power": None, "axis": axis, "input": axis})

    def multisine(self, freq_hz, amplitude, phase_rad, exposures_s: Sequence[float], trigger_offset_s, n_repeats: int,
                  base_freq_hz: float | None = None, settle_s: float | None = None, power: float = 1.0):
        """``WAVE <axis> MULTI f0:0:0,f1:a1:p1,...`` (from rest), then per exposure ``ARM offset
        Te R``: frames ``[E, R, H, W]``. The controller times triggers from the periods of the
        first tone, so the base ``f0`` (default the lowest tone) goes first, with amplitude 0
        when it is not one of the tones; ``trigger_offset_s`` is then the delay after the start
        of a common period ``1 / f0``. ``power`` (one value or one per exposure) is sent
        before each ``ARM`` whose power differs from the last."""
        freqs, amps, phases, f0 = self._check_tones(freq_hz, amplitude, phase_rad, base_freq_hz)
        tones = sorted(zip(freqs, amps, phases))
        if not math.isclose(tones[0][0], f0, rel_tol=1e-12):
            tones = [(f0, 0.0, 0.0)] + tones
        # 10 significant digits keep the line short (phase errors ~1e-10 rad) and within MAX_LINE.
        tones = [tuple(float(f"{v:.10g}") for v in t) for t in tones]
        check_drive(command_peak(*zip(*tones), base_freq_hz=tones[0][0]), self.input_limit)
        check_slew(command_slew(*zip(*tones), base_freq_hz=tones[0][0]), self.slew_limit)

        line = f"WAVE {self.axis} MULTI {format_tones(tones)}"
        if len(tones) > MAX_TONES or len(line) > MAX_LINE:
            raise ParameterError(f"freq_hz: {len(tones)} tones (base included) make a WAVE line of {len(line)} bytes; the "
                                 f"protocol allows {MAX_TONES} tones and {MAX_LINE} bytes: use fewer tones")
        return self._periodic_capture(f"multisine {len(freqs)} tones from {min(freqs):g} Hz", lambda c: c.wave_multi(self.axis, tones), 1.0 / f0,
                                      exposures_s, trigger_offset_s, n_repeats, power, settle_s,
                                      {"kind": "multisine", "freq_hz": freqs, "amplitude": amps, "phase_rad": phases, "base_freq_hz": f0,
                                       "period_s": None, "settle_s": None, "power": None, "axis": self.axis})

    def _periodic_capture(self, what: str, start_wave, period: float, exposures_s, trigger_offset_s, n_repeats, power, settle_s,
                          meta: dict):
        """What every periodic call shares once its waveform is checked: the repeats, exposures,
        offsets, laser power (one, or one per exposure) and settling wait checked; one transaction
        that starts the waveform (``start_wave(controller)``) and fires ``ARM offs[e] te[e] R`` for
        each exposure (the laser following its power, the waveform running on); and the capture
        ``[E, R, H, W]`` with ``meta``, whose ``period_s``, ``settle_s`` and ``power`` entries are
        filled in (in the places ``meta`` gives them)."""
        te, offs, R = self._check_periodic(exposures_s, trigger_offset_s, n_repeats)
        E = len(te)
        powers = [self._check_power(p) for p in per_exposure(power, E, "power")]
        settle = None if settle_s is None else check_real_scalar(settle_s, "settle_s", nonnegative=True)

        def body(c):
            start_wave(c)
            out = []
            for e in range(E):
                if e and powers[e] != powers[e - 1]:
                    c.power(powers[e])
                out += self._acquire(te[e], R, lambda e=e: c.arm(offs[e], te[e], R))
            return out

        frames = self._transaction(what, powers[0], body, wave=True, settle_s=settle)
        meta.update(period_s=period, settle_s=settle, power=powers if len(set(powers)) > 1 else powers[0])
        return self._capture(frames, (E, R), [[o - math.floor(o / period) * period] * R for o in offs], meta)

    def pulse(self, exposure_s: float, trigger_offset_s, pulse_time_s: float, pulse_width_s: float, n: int, power: float = 1.0):
        """Mirror still; per offset ``PULSE offset pulse_time width Te n``: frames
        ``[..., n, H, W]`` with ``[...]`` the shape of ``trigger_offset_s``."""
        te, n, power, p0, width = self._check_pulse(exposure_s, n, power, pulse_time_s, pulse_width_s)
        offs_t = torch.as_tensor(trigger_offset_s, dtype=_F64) if not isinstance(trigger_offset_s, torch.Tensor) \
            else trigger_offset_s.detach().to(_F64)
        offs = float_list(offs_t, "trigger_offset_s")
        frames = self._transaction(f"pulse at {p0 * 1e6:.3g} us", power, lambda c: [
            f for o in offs for f in self._acquire(te, n, lambda o=o: c.pulse(o, p0, width, te, n))])
        shape = tuple(offs_t.shape) + (n,)
        return self._capture(frames, shape, [[o] * n for o in offs],
                             {"kind": "pulse", "pulse_time_s": p0, "pulse_width_s": width, "power": power})

    def __repr__(self) -> str:
        return (f"SerialRig(port={self.controller.port!r}, frames={self.frames!r}, device={self.device.get('name', '?')}, "
                f"boot={self._boot}, input_limit={self.input_limit}, slew_limit={self.slew_limit})")
