"""The settings of ``torchblur identify`` (layer 8: it imports the physics, estimators and the
DM's physics below it, nothing of the rigs, the hardware, the pipeline or the command line):

- :mod:`~torchblur.config.schema`: the frozen dataclasses, one per section, and their defaults;
- :mod:`~torchblur.config.load`: defaults, YAML file and overrides merged, and the file's safety;
- :mod:`~torchblur.config.checks`: every key's value and the rules between keys;
- :mod:`~torchblur.config.budget`: what a run takes (frames, memory, disk, bench time, a DM
  run's plan) and the limits it is refused beyond;
- :mod:`~torchblur.config.keys`: every key with its unit (``torchblur config``);
- :mod:`~torchblur.config.camera_urls`: what an SDK camera's ``rig.frames`` URL names.

The bench emulator imports these settings without loading the pipeline.
"""
from torchblur.config.budget import (DM_DARK_FRAMES, DM_STILL_FRAMES, GEOMETRY_EVALUATIONS, LATENCY_SCAN, LIMITS,
                                     SATURATION_STEPS, STILL_BYTES, calibration_frames, check_dm_bounds, check_dm_exposures,
                                     check_limits, dm_geometry, dm_plan, dm_sensor, dm_size_bounds, dm_still_frames,
                                     dm_sweep_size, estimate_run, latency_scan_times)
from torchblur.config.camera_urls import aravis_url_options, camera_url_query, pylon_url_options
from torchblur.config.checks import (check_declared, check_number, validate, validate_camera, validate_dm, validate_dm_model,
                                     validate_drive_limits, validate_excitation, validate_exposure_time, validate_fit,
                                     validate_loss_for_plan, validate_model, validate_plan_compatibility, validate_plant,
                                     validate_report, validate_rig, validate_spot_room, validate_spots, validate_sweep,
                                     whole_periods)
from torchblur.config.keys import UNITS, config_keys, format_config_keys, unit_of
from torchblur.config.load import CONFIG_SCHEMA, MAX_CONFIG_BYTES, MAX_LIST_ENTRIES, config_to_yaml, load_config, load_dataclass
from torchblur.config.schema import (AXIS_MODES, DEFAULT_PLANT, DM_PLAN_KINDS, EXCITATION_KINDS, GAIN_FROM, MIN_PSF_SIGMA_PX, RIG_KINDS,
                                     CameraConfig, DMConfig, DMPlanConfig, DMRegistrationConfig, ExcitationConfig, FitConfig,
                                     IdentifyConfig, ModelConfig, PlantConfig, ReportConfig, RigConfig, SpotsConfig,
                                     SweepConfig, WFSConfig, is_nested, key)

__all__ = [
    "IdentifyConfig", "PlantConfig", "SweepConfig", "ExcitationConfig", "CameraConfig", "FitConfig", "ModelConfig",
    "ReportConfig", "RigConfig", "SpotsConfig", "DMConfig", "DMRegistrationConfig", "WFSConfig", "DMPlanConfig",
    "DEFAULT_PLANT", "RIG_KINDS", "EXCITATION_KINDS", "AXIS_MODES", "GAIN_FROM", "DM_PLAN_KINDS", "is_nested",
    "load_config", "load_dataclass", "config_to_yaml", "CONFIG_SCHEMA", "MAX_CONFIG_BYTES", "MAX_LIST_ENTRIES",
    "validate", "validate_plant", "validate_camera", "validate_spots", "validate_excitation", "validate_sweep",
    "validate_rig", "validate_dm", "validate_dm_model", "validate_fit", "validate_model", "validate_report",
    "validate_spot_room", "validate_drive_limits", "validate_exposure_time", "validate_plan_compatibility",
    "validate_loss_for_plan", "whole_periods", "check_number", "check_declared", "MIN_PSF_SIGMA_PX", "key",
    "LIMITS", "SATURATION_STEPS", "LATENCY_SCAN", "GEOMETRY_EVALUATIONS", "estimate_run", "check_limits",
    "check_dm_bounds", "dm_size_bounds", "calibration_frames", "latency_scan_times", "DM_DARK_FRAMES", "DM_STILL_FRAMES",
    "STILL_BYTES", "check_dm_exposures", "dm_geometry", "dm_plan", "dm_still_frames", "dm_sweep_size", "dm_sensor",
    "UNITS", "config_keys", "format_config_keys", "unit_of",
    "camera_url_query", "pylon_url_options", "aravis_url_options",
]
