"""The hardware adapter: a controller on a serial line (:class:`Controller`, docs/protocol.md), a
camera (:class:`FrameSource`: :class:`EmulatorFrames`, or a real one's SDK through :class:`SDKCamera`),
the rigs on them (:class:`SerialRig`, :class:`SerialDMRig`: ``identify(cfg, rig=SerialRig.open(port,
frames))`` runs unchanged), the experiment record (:class:`Experiment`) and ``torchblur emulator``
(:mod:`torchblur.hardware.emulator`, the bench in a process).

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
