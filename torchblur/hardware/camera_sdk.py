"""Where a real camera plugs in: subclass :class:`SDKCamera` and implement five methods.

The controller fires the camera's trigger line (``ARM``/``PULSE``); the camera delivers the
frames on its own link (USB3 Vision, GigE, CoaXPress ...) through its vendor SDK (Aravis,
Spinnaker, pylon, Vimba, ...). This class turns such an SDK into a
:class:`~torchblur.hardware.frames.FrameSource` the rig can check:

- the camera must run in external-trigger mode with the exposure set per acquisition
  (:meth:`SDKCamera._configure`), one frame per trigger edge;
- the rig needs each frame's counter to equal the controller's trigger count. Cameras count
  their own frames (from their power-up); :class:`SDKCamera` asks the camera, before the
  triggers fire, which counter its next frame will carry (:meth:`SDKCamera._next_camera_counter`)
  and maps ``camera counter - that + first trigger count``. The mapping is fixed before any
  frame arrives, so a dropped frame shows up as a gap
  (:class:`~torchblur.hardware.errors.FrameGap`) and a repeated buffer as a stale frame, never
  as a silently wrong frame.

Example (a sketch with a hypothetical ``vendor`` SDK)::

    class MyCamera(SDKCamera):
        def _connect(self):
            self.cam = vendor.open(serial="1234")
            self.cam.trigger_mode = "external-rising"
        def _disconnect(self):
            self.cam.close()
        def _camera_info(self):
            return CameraInfo(frame_shape=(self.cam.height, self.cam.width), frame_rate_hz=self.cam.max_fps,
                              max_exposure_s=self.cam.max_exposure_us * 1e-6, readout_s=self.cam.readout_us * 1e-6,
                              name=self.cam.model)
        def _configure(self, exposure_s, count):
            self.cam.exposure_us = exposure_s * 1e6
            self.cam.start(n_buffers=count)
        def _next_camera_counter(self):
            return self.cam.frame_counter + 1          # the id the next exposure will carry
        def _grab(self, timeout_s):
            buf = self.cam.wait_buffer(timeout_ms=int(timeout_s * 1e3))   # None on timeout
            if buf is None:
                return None
            return buf.numpy(), buf.frame_id, buf.timestamp_ns * 1e-9, buf.exposure_us * 1e-6

    rig = SerialRig(Controller("/dev/ttyACM0"), MyCamera())
"""
from __future__ import annotations

from abc import abstractmethod

import numpy as np
import torch

from torchblur.hardware.errors import FrameTimeout
from torchblur.hardware.frames import CameraInfo, Frame, FrameSource

__all__ = ["SDKCamera"]


class SDKCamera(FrameSource):
    """Base class of a real camera driven through its vendor SDK (see the module docstring).

    Implement:
        ``_connect()``: open the camera, external trigger mode.
        ``_disconnect()``: release it.
        ``_camera_info() -> CameraInfo``: frame shape, rates, exposure limit, readout.
        ``_configure(exposure_s, count)``: set the exposure, arm ``count`` triggered frames.
        ``_next_camera_counter() -> int``: the counter the camera's next frame will carry.
        ``_grab(timeout_s) -> (array [H, W], camera_counter, timestamp_s, exposure_s) | None``:
            the next frame (None when none came within ``timeout_s``).
    """

    def __init__(self):
        self._connect()
        self._info = self._camera_info()
        self._cam_next = 0
        self._offset = 0  # trigger count - camera counter, fixed by prepare() + bind() before the triggers

    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...

    @abstractmethod
    def _camera_info(self) -> CameraInfo: ...

    @abstractmethod
    def _configure(self, exposure_s: float, count: int) -> None: ...

    @abstractmethod
    def _next_camera_counter(self) -> int: ...

    @abstractmethod
    def _grab(self, timeout_s: float): ...

    @property
    def info(self) -> CameraInfo:
        return self._info

    def prepare(self, exposure_s: float, count: int) -> None:
        self._cam_next = int(self._next_camera_counter())  # before any trigger of this acquisition
        self._configure(float(exposure_s), int(count))

    def bind(self, first_counter: int, count: int) -> None:
        self._offset = int(first_counter) - self._cam_next

    def read(self, timeout_s: float) -> Frame:
        got = self._grab(timeout_s)
        if got is None:
            raise FrameTimeout(f"no frame from {self._info.name or type(self).__name__} within {timeout_s:g} s")
        arr, cam_counter, ts, te = got
        arr = np.asarray(arr)
        return Frame(data=torch.from_numpy(arr.astype(np.float64)), counter=int(cam_counter) + self._offset, timestamp_s=float(ts),
                     exposure_s=float(te), dtype=arr.dtype.name, boot=None, meta={"camera_counter": int(cam_counter)})

    def reopen(self) -> None:
        self.close()
        self._connect()

    def close(self) -> None:
        self._disconnect()
