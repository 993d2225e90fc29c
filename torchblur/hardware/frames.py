"""Where frames come from: the :class:`FrameSource` interface (a :class:`Frame`: ``[H, W]`` ADU with
its counter, timestamp and exposure, which :class:`~torchblur.hardware.serial_rig.SerialRig` checks),
the emulator's camera channel (:class:`EmulatorFrames`) and its wire format (docs/protocol.md,
"The camera channel").
"""
from __future__ import annotations

import json
import math
import socket
import struct
import time
from abc import ABC, abstractmethod
from contextlib import suppress
from dataclasses import asdict, dataclass, field
from urllib.parse import urlparse

import numpy as np
import torch

from torchblur.hardware.errors import ConnectionLost, FrameTimeout, GarbageReply

__all__ = ["CameraInfo", "CameraProperties", "Frame", "FrameSource", "EmulatorFrames", "encode_message", "raw_pixels", "whole_adu", "WireDecoder", "DTYPES"]

MAGIC = b"TBF1"
_HEAD = struct.Struct(">4sII")
MAX_HEADER = 1 << 16
MAX_PAYLOAD = 1 << 28
DTYPES = {"uint8": "<u1", "uint16": "<u2", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}


@dataclass(frozen=True)
class CameraInfo:
    """What the pipeline needs to know about the camera: ``frame_shape`` (H, W) px,
    ``frame_rate_hz`` (highest), ``max_exposure_s``, ``readout_s`` (Tr), ``name``."""

    frame_shape: tuple
    frame_rate_hz: float
    max_exposure_s: float
    readout_s: float
    name: str = ""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["frame_shape"] = list(self.frame_shape)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "CameraInfo":
        return cls(frame_shape=tuple(int(v) for v in d["frame_shape"]), frame_rate_hz=float(d["frame_rate_hz"]),
                   max_exposure_s=float(d["max_exposure_s"]), readout_s=float(d["readout_s"]), name=str(d.get("name", "")))

    @classmethod
    def of(cls, rig, name: str = "") -> "CameraInfo":
        """The camera of any rig (its :class:`~torchblur.rig.base.CameraRig` properties), named
        ``name``, else as the rig's camera is, else by the rig's class."""
        return cls(frame_shape=tuple(int(v) for v in rig.frame_shape), frame_rate_hz=float(rig.frame_rate_hz),
                   max_exposure_s=float(rig.max_exposure_s), readout_s=float(rig.readout_s),
                   name=name or getattr(getattr(rig, "info", None), "name", "") or type(rig).__name__)


class CameraProperties:
    """The camera properties of :class:`~torchblur.rig.base.CameraRig` read from ``self.info``
    (a :class:`CameraInfo`): a rig whose camera is described by one."""

    @property
    def frame_shape(self) -> tuple[int, int]:
        return tuple(self.info.frame_shape)

    @property
    def frame_rate_hz(self) -> float:
        return self.info.frame_rate_hz

    @property
    def max_exposure_s(self) -> float:
        return self.info.max_exposure_s

    @property
    def readout_s(self) -> float:
        return self.info.readout_s


@dataclass
class Frame:
    """One camera frame.

    Attributes:
        data: ``[H, W]`` float64 tensor in ADU; ``data[i, j]`` = row i, column j (x = j, y = i).
        counter: frame counter (+1 per trigger since the controller's boot).
        timestamp_s: the controller clock at the frame's trigger (s since its boot).
        exposure_s: exposure time the camera used (s).
        trigger_time_s: trigger time on the command's own time base (s): since the waveform
            start for a sine, since the acquisition start otherwise; NaN if unknown.
        trigger_offset_s: trigger delay after its reference event (s); NaN if unknown.
        dtype: the pixel type delivered (``"uint16"``, ...); recordings keep it.
        boot: the controller boot id the frame belongs to (None if the source cannot tell).
        meta: anything else the source reports.
    """

    data: torch.Tensor
    counter: int
    timestamp_s: float
    exposure_s: float
    trigger_time_s: float = float("nan")
    trigger_offset_s: float = float("nan")
    dtype: str = "float64"
    boot: str | None = None
    meta: dict = field(default_factory=dict)


class FrameSource(ABC):
    """A camera as the rig sees it. Implement :attr:`info`, :meth:`read` and, if needed,
    :meth:`prepare`, :meth:`bind`, :meth:`drain`, :meth:`reopen`, :meth:`close`.

    The rig calls, per acquisition: ``prepare(exposure_s, count)`` (before the controller
    fires the triggers), then the controller's ``ARM``/``PULSE`` (which returns the first
    frame counter), ``bind(first, count)``, then ``read(timeout_s)`` once per frame. A frame's
    ``counter`` must be the controller's trigger count (see
    :class:`~torchblur.hardware.camera_sdk.SDKCamera` for a camera whose counter differs).
    """

    @property
    @abstractmethod
    def info(self) -> CameraInfo:
        """The camera's :class:`CameraInfo`."""

    def prepare(self, exposure_s: float, count: int) -> None:
        """Get ready for ``count`` externally triggered frames of ``exposure_s``."""

    def bind(self, first_counter: int, count: int) -> None:
        """The controller will trigger frames ``first_counter .. first_counter + count - 1``."""

    @abstractmethod
    def read(self, timeout_s: float) -> Frame:
        """The next frame. Raises :class:`~torchblur.hardware.errors.FrameTimeout` if none comes
        within ``timeout_s``, :class:`~torchblur.hardware.errors.ConnectionLost` if the camera
        is gone."""

    def drain(self, quiet_s: float = 0.05) -> int:
        """Discard frames already delivered; returns how many."""
        n = 0
        while True:
            try:
                self.read(quiet_s)
            except FrameTimeout:
                return n
            n += 1

    def reopen(self) -> None:
        """Reconnect after :class:`~torchblur.hardware.errors.ConnectionLost` (default: cannot)."""
        raise ConnectionLost(f"{type(self).__name__} cannot reconnect")

    def close(self) -> None:
        """Release the camera."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------- wire format


def encode_message(header: dict, payload: bytes = b"") -> bytes:
    """One message of the camera channel's wire format."""
    h = json.dumps(header, separators=(",", ":")).encode()
    return _HEAD.pack(MAGIC, len(h), len(payload)) + h + payload


def whole_adu(frames: np.ndarray) -> bool:
    """Every value of ``frames`` a whole number in uint16's range (a real camera's raw values)."""
    return bool(np.all(frames >= 0) and np.all(frames <= 65535) and np.all(frames == np.round(frames)))


def raw_pixels(frames: np.ndarray) -> np.ndarray:
    """``frames`` as uint16 when they hold integers in range (:func:`whole_adu`), else float64."""
    if frames.size and whole_adu(frames):
        return frames.astype(np.uint16)
    return frames.astype(np.float64)


def frame_message(frame_np: np.ndarray, **header) -> bytes:
    """A ``frame`` message for a 2-D array (its dtype one of :data:`DTYPES`)."""
    kind = np.dtype(frame_np.dtype).name
    if kind not in DTYPES:
        raise ValueError(f"frame dtype {kind} is not one of {sorted(DTYPES)}")
    arr = np.ascontiguousarray(frame_np, dtype=DTYPES[kind])
    hdr = {"type": "frame", **header, "shape": list(arr.shape), "dtype": kind}
    return encode_message(hdr, arr.tobytes())


class WireDecoder:
    """Incremental decoder: :meth:`feed` bytes, :meth:`next` returns ``(header, payload)`` or
    None. A bad magic or an impossible length raises :class:`GarbageReply`."""

    def __init__(self):
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        self._buf += data

    def next(self):
        if len(self._buf) < _HEAD.size:
            return None
        magic, hl, pl = _HEAD.unpack_from(self._buf)
        if magic != MAGIC or hl > MAX_HEADER or pl > MAX_PAYLOAD:
            head = bytes(self._buf[:12])
            nxt = self._buf.find(MAGIC, 1)  # skip to the next message head: back in step
            del self._buf[:nxt if nxt > 0 else max(0, len(self._buf) - len(MAGIC) + 1)]
            raise GarbageReply(f"camera channel out of step: bad message head {head!r}")
        end = _HEAD.size + hl + pl
        if len(self._buf) < end:
            return None
        raw = bytes(self._buf[_HEAD.size:_HEAD.size + hl])
        payload = bytes(self._buf[_HEAD.size + hl:end])
        del self._buf[:end]  # a bad header is skipped whole: the stream stays in step
        try:
            header = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise GarbageReply("camera channel: a message header is not JSON") from exc
        if not isinstance(header, dict):
            raise GarbageReply(f"camera channel: a message header is not a JSON object ({type(header).__name__})")
        return header, payload


def decode_frame(header: dict, payload: bytes) -> Frame:
    """A :class:`Frame` from a ``frame`` message; raises :class:`GarbageReply` if the payload
    does not match the header's shape and dtype."""
    try:
        dtype = DTYPES[header["dtype"]]
        shape = tuple(int(v) for v in header["shape"])
        if len(shape) != 2 or min(shape) < 1:
            raise ValueError(f"shape {shape}")
        arr = np.frombuffer(payload, dtype=dtype)
        arr = arr.reshape(shape)
        counter = header["counter"]
        if isinstance(counter, bool) or not isinstance(counter, int):
            raise ValueError(f"counter {counter!r}")
        times = {k: float(header.get(k, float("nan")) if header.get(k) is not None else float("nan"))
                 for k in ("timestamp_s", "trigger_time_s", "trigger_offset_s")}
        exposure_s = float(header["exposure_s"])
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure_s {exposure_s!r}")
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise GarbageReply(f"camera channel: a malformed frame message ({type(exc).__name__}: {exc}; header "
                           f"{str(header)[:200]})") from exc
    data = torch.from_numpy(arr.astype(np.float64))
    if not torch.isfinite(data).all():
        raise GarbageReply(f"camera channel: frame {counter} holds NaN or infinite pixels")
    return Frame(data=data, counter=counter, exposure_s=exposure_s, dtype=header["dtype"], boot=header.get("boot"),
                 meta={k: v for k, v in header.items() if k in ("kind",)}, **times)


# ---------------------------------------------------------------------- emulator channel


def parse_tcp_url(url: str) -> tuple[str, int]:
    """``tcp://host:port`` -> ``(host, port)``; ValueError otherwise."""
    u = urlparse(url)
    if u.scheme != "tcp" or not u.hostname or u.port is None:
        raise ValueError(f"expected tcp://HOST:PORT, got {url!r}")
    return u.hostname, int(u.port)


class EmulatorFrames(FrameSource):
    """The emulator's camera: frames read from its loopback TCP channel.

    Args:
        url: ``tcp://127.0.0.1:PORT`` (the ``frames`` field of the emulator's start line).
        connect_timeout_s: time to connect and receive the hello message.
    """

    def __init__(self, url: str, *, connect_timeout_s: float = 5.0):
        self.url = url
        self._addr = parse_tcp_url(url)
        self.connect_timeout_s = float(connect_timeout_s)
        self._sock: socket.socket | None = None
        self._dec = WireDecoder()
        self._info: CameraInfo | None = None
        self.open()

    def open(self) -> None:
        self._dec = WireDecoder()
        try:
            self._sock = socket.create_connection(self._addr, timeout=self.connect_timeout_s)
        except OSError as exc:
            self._sock = None
            raise ConnectionLost(f"cannot connect to the camera channel {self.url}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        hello = self._message(self.connect_timeout_s)
        if hello is None or hello[0].get("type") != "hello":
            raise GarbageReply(f"the camera channel {self.url} did not greet with a hello message")
        try:
            self._info = CameraInfo.from_dict(hello[0]["camera"])
        except (KeyError, ValueError, TypeError, AttributeError) as exc:
            raise GarbageReply(f"the camera channel {self.url} greeted with a malformed camera ({exc})") from None

    @property
    def info(self) -> CameraInfo:
        return self._info

    def _message(self, timeout_s: float):
        if self._sock is None:
            raise ConnectionLost(f"the camera channel {self.url} is closed")
        t_end = time.monotonic() + max(0.0, timeout_s)
        while True:
            msg = self._dec.next()
            if msg is not None:
                return msg
            left = t_end - time.monotonic()
            if left <= 0:
                return None
            self._sock.settimeout(left)
            try:
                data = self._sock.recv(1 << 16)
            except socket.timeout:
                return None
            except OSError as exc:
                raise ConnectionLost(f"the camera channel {self.url} failed: {exc}") from exc
            if not data:
                raise ConnectionLost(f"the camera channel {self.url} was closed by the camera")
            self._dec.feed(data)

    def read(self, timeout_s: float) -> Frame:
        while True:
            msg = self._message(timeout_s)
            if msg is None:
                raise FrameTimeout(f"no frame within {timeout_s:g} s on {self.url}")
            header, payload = msg
            if header.get("type") == "frame":
                return decode_frame(header, payload)
            # other message types (future extensions) are skipped

    def drain(self, quiet_s: float = 0.05) -> int:
        n = 0
        while self._message(quiet_s) is not None:
            n += 1
        return n

    def reopen(self) -> None:
        self.close()
        self.open()

    def close(self) -> None:
        if self._sock is not None:
            with suppress(OSError):
                self._sock.close()
        self._sock = None

    def __repr__(self) -> str:
        return f"EmulatorFrames({self.url!r})"
