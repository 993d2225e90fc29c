"""A GenICam camera (GigE Vision, USB3 Vision) through Aravis (the ``aravis`` extra): :class:`AravisCamera`,
an :class:`~torchblur.hardware.camera_sdk.SDKCamera` (external trigger, one frame per edge; the frame
counter is the buffer's frame id, GigE's 16-bit block id unwrapped). Aravis does not say which id the
next frame will carry before it comes: the first frame after opening fixes the mapping onto the
controller's count (a frame lost before the very first one is not seen); from then on each
acquisition continues the count. The config (``rig.frames=aravis://...``), the install and the fake
cameras it is tested on: README, "GenICam cameras through Aravis".
"""
from __future__ import annotations

import ctypes
import threading

import numpy as np

from torchblur.config.camera_urls import aravis_url_options
from torchblur.errors import ParameterError, check_int, check_real_scalar
from torchblur.hardware.camera_sdk import SDKCamera, exposure_us, sdk_frame
from torchblur.hardware.errors import ConnectionLost, FrameError, FrameTimeout, HardwareError
from torchblur.hardware.frames import CameraInfo, EmulatorFrames, Frame

__all__ = ["AravisCamera"]

_DTYPES = {"Mono8": np.uint8, "Mono10": "<u2", "Mono12": "<u2", "Mono14": "<u2", "Mono16": "<u2"}
_ID_WRAP = 65535  # GigE Vision 1.x block ids run 1..65535


def _aravis():
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise ImportError("AravisCamera needs PyGObject and Aravis 0.8's typelib: apt install gir1.2-aravis-0.8 (Debian), then "
                          "pip install 'torchblur[aravis]'") from exc
    return Aravis


def _pointer(gobj) -> int:
    """The C address of a PyGObject object (its ``__gpointer__`` capsule)."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype, get.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return int(get(gobj.__gpointer__, None))


class AravisCamera(SDKCamera):
    """A GenICam camera through Aravis as a :class:`~torchblur.hardware.frames.FrameSource`.

    Args:
        device: Aravis's device id (``"Fake_1"``, ``"Basler-12345678"``, ...); None: the first camera.
        trigger_source: ``"Line1"`` (default), ``"Line0"``, ... or ``"Software"`` (:meth:`software_trigger`).
        pixel_format: e.g. ``"Mono16"``; None keeps the camera's (Mono8..Mono16 are read).
        frame_shape: ``(H, W)`` px of the region to set; None keeps the camera's.
        readout_s: the sensor readout time Tr (s).
        buffers: buffers queued on the stream (frames held between reads).
        feed: emulation only: a :class:`~torchblur.hardware.frames.FrameSource` (the emulator's
            ``tcp://`` camera channel) whose frames the fake camera (``device="Fake_..."``) delivers,
            one per software trigger; each delivered frame is checked against the feed's counter.

    A frame's ``data`` is float64 ADU ``[H, W]``, its ``dtype`` the delivered pixel type, ``exposure_s``
    the exposure the camera took for the acquisition, ``timestamp_s`` the buffer's timestamp x 1e-9 and
    ``meta["camera_counter"]`` the (unwrapped) frame id.

    Raises:
        ImportError: Aravis is missing (names the extra).
        HardwareError: no camera, no such device, or a trigger feature missing.
        ParameterError: a bad argument (named).
    """

    def __init__(self, device: str | None = None, *, trigger_source: str = "Line1", pixel_format: str | None = None,
                 frame_shape: tuple[int, int] | None = None, readout_s: float = 0.0, buffers: int = 16, feed=None):
        buffers = check_int(buffers, "buffers", low=1)
        readout_s = check_real_scalar(readout_s, "readout_s", nonnegative=True)
        if feed is not None and not str(device).startswith("Fake"):
            raise ParameterError(f"device: a feed (emulation) needs Aravis's in-process fake camera ('Fake_1'), got {device!r}")
        if feed is not None and trigger_source != "Software":
            raise ParameterError(f"trigger_source: a feed (emulation) fires software triggers; expected 'Software', got {trigger_source!r}")
        self._device, self._trigger_source, self._pixel_format = device, str(trigger_source), pixel_format
        if feed is not None and frame_shape is None:
            frame_shape = tuple(feed.info.frame_shape)  # the emulator's frames
        self._frame_shape, self._readout_s, self._buffers, self._feed = frame_shape, float(readout_s), buffers, feed
        self._exposure_s = float("nan")
        self.cam = self._stream = self._hook = None
        self._mem: dict[int, np.ndarray] = {}
        self._last_raw = self._pending_first = None
        self._wraps = 0
        self._queue: list[Frame] = []  # with a feed: the feed frame triggered and not yet read (at most one)
        super().__init__()

    @classmethod
    def from_url(cls, url: str, *, feed=None) -> "AravisCamera":
        """From ``aravis://[DEVICE][?trigger=Line1&pixel_format=Mono16&readout_s=1e-3]``; a ``feed=tcp://...``
        option (emulation) opens the emulator's camera channel as the feed."""
        opts = aravis_url_options(url)
        spec = opts.pop("feed")
        if spec is not None and feed is None:
            feed = EmulatorFrames(spec)
        return cls(opts.pop("device"), feed=feed, **opts)

    # ----------------------------------------------------------------- SDKCamera
    def _connect(self) -> None:
        Aravis = _aravis()
        if self._device is not None and str(self._device).startswith("Fake"):
            Aravis.enable_interface("Fake")
        Aravis.update_device_list()
        if Aravis.get_n_devices() == 0:
            raise HardwareError("camera: Aravis finds no camera (connected? powered? aravis://Fake_1 for its fake camera)")
        try:
            self.cam = Aravis.Camera.new(self._device)
        except Exception as exc:  # noqa: BLE001 - GLib.Error: no such device
            found = [Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())]
            raise HardwareError(f"device: no camera {self._device!r} ({exc}); Aravis finds {found}") from None
        self._setup()

    def _setup(self) -> None:
        cam = self.cam
        try:
            if self._frame_shape is not None:
                cam.set_region(0, 0, int(self._frame_shape[1]), int(self._frame_shape[0]))
            if self._pixel_format is not None:
                cam.set_pixel_format_from_string(str(self._pixel_format))
            if self._trigger_source not in cam.dup_available_trigger_sources():
                raise HardwareError(f"trigger_source: the camera offers {cam.dup_available_trigger_sources()}, not {self._trigger_source!r}")
            cam.set_trigger(self._trigger_source)  # TriggerSelector=FrameStart, TriggerMode=On, this source
            self._format = cam.get_pixel_format_as_string()
            if self._format not in _DTYPES:
                raise HardwareError(f"pixel_format: {self._format} is not read (expected one of {sorted(_DTYPES)})")
        except HardwareError:
            raise
        except Exception as exc:  # noqa: BLE001 - GLib.Error from a feature write
            raise HardwareError(f"camera: cannot set up external triggering ({exc})") from None
        if self._feed is not None:
            self._hook = _FillHook(self)
            # the in-process fake free-runs (setting the rate turns its trigger off): at its fastest, 1000 frames/s
            cam.set_frame_rate(float(cam.get_frame_rate_bounds()[1]))
        self._stream = cam.create_stream(None, None)
        Aravis = _aravis()
        for _ in range(self._buffers):
            mem = np.zeros(int(cam.get_payload()), dtype=np.uint8)
            buf = Aravis.Buffer.new(mem.nbytes, mem.ctypes.data)  # Aravis writes into this numpy memory
            self._mem[_pointer(buf)] = mem
            self._stream.push_buffer(buf)

    def _disconnect(self) -> None:
        if self.cam is not None:
            try:
                self.cam.stop_acquisition()
            except Exception:  # noqa: BLE001 - closing
                pass
            if self._hook is not None:
                self._hook.detach()
            self._stream = self.cam = self._hook = None
        self._mem.clear()

    def close(self) -> None:
        super().close()
        if self._feed is not None:
            self._feed.close()

    def drain(self, quiet_s: float = 0.05) -> int:
        """Drop frames of an earlier acquisition (the feed's and Aravis's queued buffers; their ids are
        counted as seen, so the next acquisition's mapping continues from them); how many."""
        n = self._feed.drain(quiet_s) if self._feed is not None else 0
        for _ in range(self._buffers):  # at most the queued buffers (a free-running fake camera never goes quiet)
            b = None if self._stream is None else self._stream.timeout_pop_buffer(int(quiet_s * 1e6))
            if b is None:
                break
            self._seen(int(b.get_frame_id()))
            self._stream.push_buffer(b)
            n += 1
        if self._hook is not None:
            self._hook.clear()
        self._queue.clear()
        return n

    def _seen(self, raw: int) -> None:
        if self._last_raw is not None and raw < self._last_raw and self._last_raw - raw > _ID_WRAP // 2:
            self._wraps += 1
        self._last_raw = raw

    def _camera_info(self) -> CameraInfo:
        cam = self.cam
        _, _, w, h = cam.get_region()
        rate = cam.get_frame_rate_bounds()
        exp = cam.get_exposure_time_bounds()
        name = f"{cam.get_vendor_name()} {cam.get_model_name()} ({cam.get_device_serial_number() or cam.get_device_id()})"
        info = CameraInfo(frame_shape=(int(h), int(w)), frame_rate_hz=float(rate[1]), max_exposure_s=float(exp[1]) * 1e-6,
                          readout_s=self._readout_s, name=name)
        if self._feed is not None:  # emulation: the emulated sensor's limits (its controller checks them)
            f = self._feed.info
            info = CameraInfo(frame_shape=info.frame_shape, frame_rate_hz=min(info.frame_rate_hz, f.frame_rate_hz),
                              max_exposure_s=min(info.max_exposure_s, f.max_exposure_s), readout_s=f.readout_s, name=f"{name} fed by {f.name}")
        return info

    def _configure(self, exposure_s: float, count: int) -> None:
        cam = self.cam
        cam.stop_acquisition()
        cam.set_exposure_time(exposure_us(exposure_s, *cam.get_exposure_time_bounds()))
        self._exposure_s = float(cam.get_exposure_time()) * 1e-6  # what the camera will use (its own rounding)
        while (b := self._stream.try_pop_buffer()) is not None:  # frames of an earlier acquisition: not this one's
            self._seen(int(b.get_frame_id()))
            self._stream.push_buffer(b)
        if self._feed is not None:
            self._hook.clear()  # nor the feed frames sent for it
            self._queue.clear()
            self._feed.prepare(exposure_s, count)
        cam.start_acquisition()

    def _next_camera_counter(self) -> int:
        return -1 if self._last_raw is None else self._unwrap(self._last_raw) + 1  # -1: unknown until the first frame

    def bind(self, first_counter: int, count: int) -> None:
        super().bind(first_counter, count)
        self._pending_first = int(first_counter) if self._cam_next == -1 else None  # fixed by the first frame (read)
        if self._feed is not None:
            self._feed.bind(first_counter, count)

    def _unwrap(self, raw: int) -> int:
        return int(raw) + self._wraps * _ID_WRAP

    def _grab(self, timeout_s: float):
        if self.cam is None:
            raise ConnectionLost("camera: closed")
        if self._feed is not None and not self._queue:  # a new feed frame once the one sent before came (one late: waited for)
            frame = self._feed.read(timeout_s)
            self._queue.append(frame)
            self._hook.send(frame)
            self.cam.software_trigger()
        buf = self._stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
        while buf is not None and self._feed is not None and not self._hook.holds(_pointer(buf)):
            # the fake camera also emits frames of its own (one as an acquisition starts): not the feed's, skipped
            self._stream.push_buffer(buf)
            buf = self._stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
        if buf is None:
            return None
        try:
            Aravis = _aravis()
            if buf.get_status() != Aravis.BufferStatus.SUCCESS:
                raise FrameError(f"camera: frame {buf.get_frame_id()} failed: {buf.get_status().value_nick}")
            h, w = int(buf.get_image_height()), int(buf.get_image_width())
            dtype = np.dtype(_DTYPES[self._format])
            arr = self._mem[_pointer(buf)][:h * w * dtype.itemsize].view(dtype).reshape(h, w).copy()
            raw = int(buf.get_frame_id())
            ts = float(buf.get_timestamp()) * 1e-9
            sent = self._hook.take(_pointer(buf)) if self._feed is not None else None
        finally:
            self._stream.push_buffer(buf)
        self._seen(raw)
        if sent is not None:  # emulation: the feed frame the hook wrote into this buffer, its counter the controller's
            return arr, sent, ts, self._exposure_s
        if self._pending_first is not None:  # the mapping waits for the first frame
            self._offset, self._pending_first = self._pending_first - self._unwrap(raw), None
        return arr, self._unwrap(raw), ts, self._exposure_s

    def read(self, timeout_s: float) -> Frame:
        """The next frame (:meth:`SDKCamera.read`); with a feed, a frame that is not the feed's next
        is a :class:`FrameError`."""
        if self._feed is None:
            return super().read(timeout_s)
        got = self._grab(timeout_s)
        if got is None:
            raise FrameTimeout(f"no frame from {self._info.name} within {timeout_s:g} s")
        arr, delivered, ts, _ = got  # emulation: the feed frame Aravis delivered
        sent = self._queue.pop(0)
        if delivered is not sent:
            raise FrameError(f"camera: Aravis delivered feed frame {delivered.counter}, the next sent was "
                             f"{sent.counter}")
        return sdk_frame(arr, sent.counter, ts, sent.exposure_s, sent.boot, camera_counter=int(self._last_raw),
                         **sent.meta)

    # --------------------------------------------------------------------- extras
    def software_trigger(self) -> None:
        """Fire one frame from software (``trigger_source="Software"``): tests, the fake camera."""
        self.cam.software_trigger()


class _FillHook:
    """Emulation: the fake camera's fill-pattern hook (through ctypes: Aravis calls it from its stream
    thread, which free-runs) writes the oldest feed frame sent and not yet written into the buffer it is
    filling (numpy memory of the camera), as 16-bit pixels: each frame sent goes into one buffer only,
    however late the reader takes it (the frames to write and the buffers written are kept under one lock)."""

    _FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32)

    def __init__(self, camera: AravisCamera):
        self._lib = ctypes.CDLL("libaravis-0.8.so.0")
        self._lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, self._FILL, ctypes.c_void_p]
        self._camera = camera
        self._fake = _pointer(camera.cam.get_device().get_fake_camera())
        self._filled: dict[int, Frame] = {}  # buffer address -> the feed frame written into it (under _lock)
        self._sent: list[Frame] = []  # feed frames sent (triggered) and not yet written into a buffer, oldest first
        self._lock = threading.Lock()
        self._callback = self._FILL(self._fill)  # kept alive while the fake camera may call it
        self._lib.arv_fake_camera_set_fill_pattern(self._fake, self._callback, None)

    def send(self, frame) -> None:
        """``frame`` (a feed :class:`~torchblur.hardware.frames.Frame`) was triggered: the next buffer filled holds it."""
        with self._lock:
            self._sent.append(frame)

    def holds(self, address: int) -> bool:
        """Whether the buffer at ``address`` holds a feed frame."""
        with self._lock:
            return address in self._filled

    def take(self, address: int):
        """The feed frame written into the buffer at ``address`` (the reader's now)."""
        with self._lock:
            return self._filled.pop(address)

    def clear(self) -> None:
        """Forget the frames sent and the buffers written (an earlier acquisition's)."""
        with self._lock:
            self._sent.clear()
            self._filled.clear()

    def _fill(self, buffer, data, exposure_us, gain, pixel_format) -> None:
        mem = self._camera._mem.get(int(buffer))
        with self._lock:
            self._filled.pop(int(buffer), None)  # written again: what it held before is gone
            if not self._sent or mem is None:
                return  # a frame of the fake camera's own (no trigger of ours): left unmarked, skipped by _grab
            img = np.clip(np.rint(self._sent[0].data.numpy()), 0, 65535).astype("<u2")
            if mem.nbytes >= img.nbytes:
                mem[:img.nbytes] = np.frombuffer(img.tobytes(), dtype=np.uint8)
                self._filled[int(buffer)] = self._sent.pop(0)

    def detach(self) -> None:
        self._lib.arv_fake_camera_set_fill_pattern(self._fake, ctypes.cast(None, self._FILL), None)
