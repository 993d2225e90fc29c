"""Where a real camera plugs in: subclass :class:`SDKCamera` and implement its six methods (the
trigger and counter rules, and an example: docs/protocol.md, "A real camera").
"""
from __future__ import annotations

from abc import abstractmethod

import numpy as np
import torch

from torchblur.errors import ParameterError
from torchblur.hardware.errors import FrameTimeout
from torchblur.hardware.frames import CameraInfo, Frame, FrameSource

__all__ = ["SDKCamera"]


class SDKCamera(FrameSource):
    """Base class of a real camera driven through its vendor SDK (docs/protocol.md, "A real camera").

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
        return sdk_frame(arr, int(cam_counter) + self._offset, ts, te, camera_counter=int(cam_counter))

    def reopen(self) -> None:
        self.close()
        self._connect()

    def close(self) -> None:
        self._disconnect()


def exposure_us(exposure_s: float, low_us: float, high_us: float) -> float:
    """``exposure_s`` in microseconds (GenICam's ``ExposureTime``), within the camera's bounds
    ``[low_us, high_us]``, else :class:`~torchblur.errors.ParameterError` naming ``exposure_s``."""
    us = exposure_s * 1e6
    if not low_us <= us <= high_us:
        raise ParameterError(f"exposure_s: the camera takes {low_us * 1e-6:g}..{high_us * 1e-6:g} s, got {exposure_s:g}")
    return us


def sdk_frame(arr, counter: int, timestamp_s: float, exposure_s: float, boot: str | None = None, **meta) -> Frame:
    """A :class:`Frame` of an SDK's pixels ``arr`` ``[H, W]`` (float64 ADU, ``dtype`` the delivered type)."""
    arr = np.asarray(arr)
    return Frame(data=torch.from_numpy(arr.astype(np.float64)), counter=int(counter), timestamp_s=float(timestamp_s),
                 exposure_s=float(exposure_s), dtype=arr.dtype.name, boot=boot, meta=meta)
