"""A Basler camera through pypylon (the ``pylon`` extra): :class:`PylonCamera`, an
:class:`~torchblur.hardware.camera_sdk.SDKCamera` (external trigger on ``trigger_source``, one frame
per rising edge, timed exposure). Per acquisition :meth:`~SDKCamera.prepare` sets ``ExposureTime``,
restarts grabbing and waits until the camera is ready for a frame trigger, so the first edge is not
lost. The frame counter is pylon's ``BlockID``, which restarts with grabbing (at 1 on GigE, else 0).
The config (``rig.frames=pylon://SERIAL?...``) and the camera emulation it is tested on: README,
"Basler cameras through pypylon".
"""
from __future__ import annotations

import os

import numpy as np

from torchblur.config.camera_urls import pylon_url_options
from torchblur.errors import check_int, check_real_scalar
from torchblur.hardware.camera_sdk import SDKCamera, exposure_us
from torchblur.hardware.errors import ConnectionLost, FrameError, HardwareError
from torchblur.hardware.frames import CameraInfo

__all__ = ["PylonCamera"]

_GIGE_CLASS = "BaslerGigE"


def _pylon():
    try:
        from pypylon import pylon
    except ImportError as exc:
        raise ImportError("PylonCamera needs pypylon: pip install 'torchblur[pylon]' (or pip install pypylon)") from exc
    return pylon


def _set(cam, name: str, value, *, required: bool = True) -> None:
    """Set a GenICam feature (``required=False``: skip it where the camera lacks it)."""
    node = cam.GetNodeMap().GetNode(name)
    if node is None or not _writable(node):
        if required:
            raise HardwareError(f"camera: feature {name} is missing or not writable; cannot set it to {value!r}")
        return
    node.SetValue(value)


def _writable(node) -> bool:
    try:
        from pypylon import genicam

        return genicam.IsWritable(node)
    except Exception:  # noqa: BLE001
        return False


def _readable(cam, *names, maximum: bool = False):
    """The value (with ``maximum``: the largest allowed value) of the first readable feature
    among ``names``, else None."""
    from pypylon import genicam

    for name in names:
        node = cam.GetNodeMap().GetNode(name)
        if node is not None and genicam.IsReadable(node):
            return node.GetMax() if maximum else node.GetValue()
    return None


class PylonCamera(SDKCamera):
    """A Basler camera (USB3 Vision or GigE) as a :class:`~torchblur.hardware.frames.FrameSource`.

    Args:
        serial: the camera's serial number; None: the first camera pylon finds.
        trigger_source: ``"Line1"`` (default: the controller's trigger wire), ``"Line2"``,
            ..., or ``"Software"`` (frames fired by :meth:`software_trigger`).
        pixel_format: e.g. ``"Mono12"``, ``"Mono16"``; None keeps the camera's.
        frame_shape: ``(H, W)`` px to set; None keeps the camera's.
        readout_s: the sensor readout time Tr (s), used when the camera does not report
            ``SensorReadoutTime``.
        buffers: pylon's ``MaxNumBuffer``, frames held between reads.
        image_files: emulation only: a folder (or one file) of images the emulated camera
            serves in name order, cycling, instead of its test pattern (pylon's
            ``ImageFilename``); TIFF or PNG, of the frame shape and pixel format.

    A frame's ``data`` is float64 ADU ``[H, W]`` (``data[i, j]`` = row i, column j), its
    ``dtype`` the delivered pixel type, ``exposure_s`` the exposure set for the acquisition,
    ``timestamp_s`` the camera's ``TimeStamp`` x 1e-9 (ns on USB3; 0 on the emulation) and
    ``meta["camera_counter"]`` the ``BlockID``.

    Raises:
        ImportError: pypylon is missing (names the extra).
        HardwareError: no camera, no camera with that serial, or a trigger feature missing.
    """

    def __init__(self, serial: str | None = None, *, trigger_source: str = "Line1", pixel_format: str | None = None,
                 frame_shape: tuple[int, int] | None = None, readout_s: float = 0.0, buffers: int = 64,
                 image_files: str | os.PathLike | None = None):
        buffers = check_int(buffers, "buffers", low=1)
        readout_s = check_real_scalar(readout_s, "readout_s", nonnegative=True)
        self._serial = serial
        self._trigger_source = str(trigger_source)
        self._pixel_format = pixel_format
        self._frame_shape = frame_shape
        self._readout_s = float(readout_s)
        self._buffers = buffers
        self._image_files = None if image_files is None else os.path.abspath(os.fspath(image_files))
        self._exposure_s = float("nan")
        self.cam = None
        super().__init__()

    @classmethod
    def from_url(cls, url: str) -> "PylonCamera":
        """From ``pylon://[SERIAL][?trigger=Line1&pixel_format=Mono12&readout_s=1e-3]``
        (no serial: the first camera); the URL as :func:`pylon_url_options` reads it."""
        opts = pylon_url_options(url)
        return cls(opts.pop("serial"), **opts)

    # ----------------------------------------------------------------- SDKCamera
    def _connect(self) -> None:
        pylon = _pylon()
        tlf = pylon.TlFactory.GetInstance()
        devices = list(tlf.EnumerateDevices())
        if not devices:
            raise HardwareError("camera: pylon finds no camera (connected? powered? PYLON_CAMEMU=1 for the emulation)")
        if self._serial is not None:
            match = [d for d in devices if d.GetSerialNumber() == str(self._serial)]
            if not match:
                raise HardwareError(f"serial: no camera {self._serial!r}; pylon finds {[d.GetSerialNumber() for d in devices]}")
            devices = match
        self._device_class = devices[0].GetDeviceClass()
        self.cam = pylon.InstantCamera(tlf.CreateDevice(devices[0]))
        self.cam.Open()
        self._setup()

    def _setup(self) -> None:
        cam = self.cam
        if self._frame_shape is not None:
            _set(cam, "Width", int(self._frame_shape[1]))
            _set(cam, "Height", int(self._frame_shape[0]))
        if self._pixel_format is not None:
            _set(cam, "PixelFormat", str(self._pixel_format))
        if self._image_files is not None:
            _set(cam, "TestImageSelector", "Off", required=False)
            _set(cam, "ImageFilename", self._image_files)
            _set(cam, "ImageFileMode", "On")
        _set(cam, "TriggerSelector", "FrameStart")
        _set(cam, "TriggerMode", "On")
        _set(cam, "TriggerSource", self._trigger_source)
        _set(cam, "TriggerActivation", "RisingEdge", required=False)
        _set(cam, "ExposureMode", "Timed", required=False)
        _set(cam, "MaxNumBuffer", self._buffers, required=False)

    def _disconnect(self) -> None:
        if self.cam is not None:
            if self.cam.IsGrabbing():
                self.cam.StopGrabbing()
            self.cam.Close()
            self.cam = None

    def _camera_info(self) -> CameraInfo:
        cam = self.cam
        info = cam.GetDeviceInfo()
        rate = _readable(cam, "ResultingFrameRate", "BslResultingFrameRate", "ResultingFrameRateAbs")
        if rate is None:
            rate = _readable(cam, "AcquisitionFrameRate", "AcquisitionFrameRateAbs", maximum=True)
        max_exposure_us = _readable(cam, "ExposureTime", "ExposureTimeAbs", maximum=True)
        readout_us = _readable(cam, "SensorReadoutTime")
        return CameraInfo(
            frame_shape=(int(cam.GetNodeMap().GetNode("Height").GetValue()), int(cam.GetNodeMap().GetNode("Width").GetValue())),
            frame_rate_hz=float(rate) if rate is not None else float("nan"),
            max_exposure_s=float(max_exposure_us) * 1e-6 if max_exposure_us is not None else float("nan"),
            readout_s=float(readout_us) * 1e-6 if readout_us is not None else self._readout_s,
            name=f"{info.GetModelName()} ({info.GetSerialNumber()})",
        )

    def _configure(self, exposure_s: float, count: int) -> None:
        pylon = _pylon()
        cam = self.cam
        if cam.IsGrabbing():
            cam.StopGrabbing()
        node = cam.GetNodeMap().GetNode("ExposureTime")
        if node is None:
            node = cam.GetNodeMap().GetNode("ExposureTimeAbs")  # older GigE cameras
        node.SetValue(exposure_us(exposure_s, node.GetMin(), node.GetMax()))
        self._exposure_s = float(node.GetValue()) * 1e-6  # what the camera will use (its own rounding)
        cam.StartGrabbingMax(int(count), pylon.GrabStrategy_OneByOne)
        if cam.CanWaitForFrameTriggerReady() and not cam.WaitForFrameTriggerReady(2000, pylon.TimeoutHandling_Return):
            raise HardwareError("camera: not ready for a frame trigger 2 s after the start of grabbing")

    def _next_camera_counter(self) -> int:
        # _configure restarts grabbing, and BlockID restarts with it (1 on GigE, 0 elsewhere).
        return 1 if self._device_class == _GIGE_CLASS else 0

    def _grab(self, timeout_s: float):
        pylon = _pylon()
        if self.cam is None or not self.cam.IsOpen():
            raise ConnectionLost("camera: closed")
        try:
            res = self.cam.RetrieveResult(max(1, int(round(timeout_s * 1e3))), pylon.TimeoutHandling_Return)
        except Exception as exc:  # pylon raises RuntimeException when grabbing stopped or the camera is gone
            raise ConnectionLost(f"camera: {exc}") from exc
        if res is None or not res.IsValid():
            return None
        try:
            if not res.GrabSucceeded():
                raise FrameError(f"camera: grab of block {res.BlockID} failed: {res.ErrorCode} {res.ErrorDescription}")
            arr = np.array(res.Array, copy=True)
            return arr, int(res.BlockID), float(res.TimeStamp) * 1e-9, self._exposure_s
        finally:
            res.Release()

    # --------------------------------------------------------------------- extras
    def software_trigger(self, timeout_s: float = 2.0) -> None:
        """Fire one frame from software (``trigger_source="Software"``): tests, emulation."""
        pylon = _pylon()
        if self.cam.CanWaitForFrameTriggerReady() and not self.cam.WaitForFrameTriggerReady(
                max(1, int(timeout_s * 1e3)), pylon.TimeoutHandling_Return):
            raise HardwareError(f"camera: not ready for a frame trigger within {timeout_s:g} s")
        self.cam.ExecuteSoftwareTrigger()
