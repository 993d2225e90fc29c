"""torchblur: identify fast actuator dynamics from the motion blur seen by a slow camera.

The names a user calls (each documented where it lives):

- image formation: :class:`BlurRenderer`, :func:`render_blur`, :class:`RenderSettings`,
  :class:`GaussianPSF`, :class:`KernelPSF`, :class:`Sinusoid`, :class:`Multisine`,
  :class:`SplineTrajectory`, :class:`ExposureWindow`, :class:`SensorTiming`,
  :func:`alias_phase`, :func:`wrap_phase`, :class:`CameraModel`;
- fitting: :func:`fit_sinusoid`, :func:`dual_exposure_windows`, :class:`BlurConsistencyLoss`,
  :func:`blur_consistency`;
- identification: :class:`FrequencyResponse`, :func:`fit_transfer_function`,
  :class:`TransferFunctionFit` (its result; ``from_json`` reads model.json), :func:`identify`
  (the pipeline; also the package ``torchblur.identify``), :func:`load_config`;
- errors: :class:`TorchblurError` and its subclasses.

``import torchblur`` loads torch and numpy only: the image-formation names are imported at
once, the others (and the subpackages ``fit``, ``sysid``, ``image``, ``design``, ``systems``,
``identify``, ``rig``, ``hardware``) on first use.
"""
from __future__ import annotations

import importlib as _importlib
import os as _os
import sys as _sys

if _sys.argv and _os.path.basename(_sys.argv[0]) == "torchblur":  # the console script (not a user's program)
    from torchblur import _console

    _console.install()  # a Ctrl-C while torch loads is one line too

from torchblur.errors import ConfigError, InputTypeError, ParameterError, ShapeError, TorchblurError
from torchblur.render.alias import alias_phase, wrap_phase
from torchblur.render.blur import BlurRenderer, RenderSettings, render_blur
from torchblur.render.camera import CameraModel
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Multisine, Sinusoid, SplineTrajectory, Trajectory
from torchblur.render.window import ExposureWindow, SensorTiming

__version__ = "0.1.0"

#: name -> module that defines it, imported on first access
_LAZY = {
    "fit_sinusoid": "torchblur.fit.sinusoid",
    "SinusoidFit": "torchblur.fit.sinusoid",
    "BlurConsistencyLoss": "torchblur.fit.consistency",
    "blur_consistency": "torchblur.fit.consistency",
    "dual_exposure_windows": "torchblur.design.windows",
    "FrequencyResponse": "torchblur.sysid.frequency_response",
    "fit_transfer_function": "torchblur.sysid.tf_fit",
    "TransferFunctionFit": "torchblur.sysid.tf_fit",
    "load_config": "torchblur.config",
}


def __getattr__(name: str):
    if name == "identify":  # the callable package (torchblur.identify(cfg, rig) runs the pipeline)
        return _importlib.import_module("torchblur.identify")
    if name in _LAZY:
        value = getattr(_importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchblur' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "BlurConsistencyLoss",
    "BlurRenderer",
    "CameraModel",
    "ConfigError",
    "ExposureWindow",
    "FrequencyResponse",
    "GaussianPSF",
    "InputTypeError",
    "KernelPSF",
    "Multisine",
    "ParameterError",
    "RenderSettings",
    "SensorTiming",
    "ShapeError",
    "Sinusoid",
    "SinusoidFit",
    "SplineTrajectory",
    "TorchblurError",
    "Trajectory",
    "TransferFunctionFit",
    "alias_phase",
    "blur_consistency",
    "dual_exposure_windows",
    "fit_sinusoid",
    "fit_transfer_function",
    "identify",
    "load_config",
    "render_blur",
    "wrap_phase",
]
