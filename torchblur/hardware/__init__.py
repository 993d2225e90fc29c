"""The hardware adapter: a controller on a serial line, a camera, and the experiment record.

- :class:`Controller`: pyserial client of the line protocol (docs/protocol.md).
- :class:`FrameSource`: where frames come from (:class:`Frame`: a tensor with its counter,
  timestamp, exposure); :class:`EmulatorFrames` (the emulator's TCP camera channel),
  :class:`SDKCamera` (the base a real camera's SDK plugs into).
- :class:`SerialRig`: the :class:`~torchblur.rig.base.Rig` protocol on a controller and a
  camera, so ``identify(cfg, rig=SerialRig.open(port, frames))`` runs unchanged;
  :class:`SerialDMRig` the same for a deformable mirror (protocol 2; its static holds: 3), so
  ``identify(cfg_dm, rig=SerialDMRig.open(port, frames))`` does.
- :class:`Experiment`: the experiment directory written as a run goes (TIFF frames,
  ``manifest.jsonl``, the resolved config), read back to resume or re-fit.
- ``torchblur emulator``: :mod:`torchblur.hardware.emulator`, a process that behaves like
  the bench on a pseudo-terminal.

Not imported by ``import torchblur``; import ``torchblur.hardware`` on use.
"""
from __future__ import annotations

from torchblur.hardware.camera_sdk import SDKCamera
from torchblur.hardware.controller import Controller
from torchblur.hardware.errors import (AcquisitionStopped, ConnectionLost, DeviceError, DeviceReset, FrameError, FrameGap, FrameMismatch,
                     FrameTimeout, GarbageReply, HardwareError, PatternMismatch, RecordingError, ReplyTimeout, StaleFrame)
from torchblur.hardware.frames import CameraInfo, EmulatorFrames, Frame, FrameSource
from torchblur.hardware.protocol import ERROR_CODES, PROTOCOL_VERSION
from torchblur.hardware.recording import SCHEMA_VERSION, Experiment
from torchblur.hardware.serial_rig import SerialRig, open_frame_source
from torchblur.hardware.serial_dm_rig import SerialDMRig

__all__ = [
    "AcquisitionStopped",
    "CameraInfo",
    "ConnectionLost",
    "Controller",
    "DeviceError",
    "DeviceReset",
    "ERROR_CODES",
    "EmulatorFrames",
    "Experiment",
    "Frame",
    "FrameError",
    "FrameGap",
    "FrameMismatch",
    "FrameSource",
    "FrameTimeout",
    "GarbageReply",
    "HardwareError",
    "PROTOCOL_VERSION",
    "PatternMismatch",
    "RecordingError",
    "ReplyTimeout",
    "SCHEMA_VERSION",
    "SDKCamera",
    "SerialDMRig",
    "SerialRig",
    "StaleFrame",
    "open_frame_source",
]
