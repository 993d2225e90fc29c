"""The identification's public names, where they have always been imported from (each module
that defines them: the package's docstring, :mod:`torchblur.identify`).
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
