"""torchblur: identify fast actuator dynamics from the motion blur seen by a slow camera.

The core (renderer, PSFs, trajectories, windows, alias) imports only torch and numpy.
Fitting, identification, hardware and plotting live in submodules imported on use.
"""
from __future__ import annotations

from .alias import alias_phase, wrap_phase
from .consistency import BlurConsistencyLoss, blur_consistency
from .errors import ConfigError, InputTypeError, ParameterError, ShapeError, TorchblurError
from .psf import GaussianPSF, KernelPSF
from .render import BlurRenderer, RenderSettings, render_blur
from .timing import ExposureWindow, SensorTiming
from .trajectory import Multisine, Sinusoid, SplineTrajectory, Trajectory

__version__ = "0.1.0"

__all__ = [
    "BlurConsistencyLoss",
    "BlurRenderer",
    "ConfigError",
    "ExposureWindow",
    "GaussianPSF",
    "InputTypeError",
    "KernelPSF",
    "Multisine",
    "ParameterError",
    "RenderSettings",
    "SensorTiming",
    "ShapeError",
    "Sinusoid",
    "SplineTrajectory",
    "TorchblurError",
    "Trajectory",
    "alias_phase",
    "blur_consistency",
    "render_blur",
    "wrap_phase",
]
