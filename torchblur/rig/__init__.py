"""Rigs: where frames come from. :class:`Rig` is the interface an identification pipeline
uses; :class:`CameraRig` the camera's properties every rig has; :class:`SimulatedRig` a simulated laboratory (LTI mirror, laser spot, noisy camera);
:class:`DMRig` the contract of a deformable-mirror rig (:func:`check_dm_rig`, docs/dm_rig.md), whose
simulated one is :class:`~torchblur.rig.dm.SimulatedDMRig`.

Not imported by ``import torchblur``; import ``torchblur.rig`` on use.
"""
from __future__ import annotations

from torchblur.rig.base import CameraRig, Capture, Rig
from torchblur.rig.dm_contract import DMRig, check_dm_rig
from torchblur.rig.simulated import SimulatedRig

__all__ = ["CameraRig", "Capture", "DMRig", "Rig", "SimulatedRig", "check_dm_rig"]
