"""Rigs: where frames come from. :class:`Rig` is the interface an identification pipeline
uses; :class:`SimulatedRig` a simulated laboratory (LTI mirror, laser spot, noisy camera).

Not imported by ``import torchblur``; import ``torchblur.rig`` on use.
"""
from __future__ import annotations

from torchblur.rig.base import Capture, Rig
from torchblur.rig.simulated import SimulatedRig

__all__ = ["Capture", "Rig", "SimulatedRig"]
