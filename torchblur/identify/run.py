"""The identification's public names, where they have always been imported from.

The pipeline itself lives in stages over one run record: :mod:`torchblur.identify.pipeline`
(:func:`identify`), :mod:`~torchblur.identify.calibration`, :mod:`~torchblur.identify.sweep`
(the sine plan), :mod:`~torchblur.identify.multisine` (the multisine plan),
:mod:`~torchblur.identify.fitting`, :mod:`~torchblur.identify.assemble`,
:mod:`~torchblur.identify.model`, :mod:`~torchblur.identify.result`, and
:mod:`~torchblur.identify.rigs` (the rig and the recording; the simulated rig is
:mod:`torchblur.rig.factory`'s); a deformable mirror's run is the DM plan's (:mod:`~torchblur.identify.dm_plan`,
its result :class:`DMResult`), its outside recordings :mod:`~torchblur.identify.dm_outside`'s.
"""
from __future__ import annotations

from torchblur.identify.calibration import Calibration, calibrate, calibrate_latency
from torchblur.identify.dm_outside import export_dm_recording, identify_dm_recording, read_dm_recording, write_dm_recording
from torchblur.identify.dm_plan import DMResult
from torchblur.identify.model import fit_model, modes_outside_band
from torchblur.identify.pipeline import identify
from torchblur.identify.result import IdentificationResult
from torchblur.identify.rigs import build_rig, build_simulated_rig, check_resume_config, plant_of

__all__ = ["IdentificationResult", "Calibration", "identify", "calibrate", "fit_model", "build_simulated_rig", "build_rig", "plant_of",
           "calibrate_latency", "check_resume_config", "modes_outside_band", "DMResult", "read_dm_recording", "write_dm_recording",
           "export_dm_recording", "identify_dm_recording"]
