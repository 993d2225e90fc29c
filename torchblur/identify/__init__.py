"""The identification pipeline: ``config`` (the run's settings), ``run`` (calibration, sweep,
fits, frequency response and model), ``multisine`` (the multisine plan) and ``cli`` (the
``torchblur`` command).

The package is itself callable: ``torchblur.identify.run(cfg, rig)`` is
``torchblur.identify.identify(cfg, rig)``.
"""
import sys as _sys
import types as _types

from torchblur.identify.run import (
    Calibration, IdentificationResult, build_rig, build_simulated_rig, calibrate, calibrate_latency, check_resume_config,
    fit_model, identify, plant_of,
)

__all__ = [
    "Calibration", "IdentificationResult", "build_rig", "build_simulated_rig", "calibrate", "calibrate_latency",
    "check_resume_config", "fit_model", "identify", "plant_of",
]


class _CallableModule(_types.ModuleType):
    """``torchblur.identify.run`` is both this package and the function it is named after."""

    def __call__(self, *args, **kwargs):
        return identify(*args, **kwargs)


_sys.modules[__name__].__class__ = _CallableModule
