"""Image processing on real frames: dark frames (``dark``), spot detection and crops
(``detection``, kornia), the still spot's PSF fit (``psf_fit``), the PSF a fit should use (``psf_from_still``: a measured
kernel, or a Gaussian where it explains the still to its noise), the saturation curve
(``saturation``), spot grids of a Shack-Hartmann sensor (``spots``), image moments
(``moments``) and frame-by-frame tracking below the frame rate (``tracking``).
``preprocess`` gathers the steps before a fit in one namespace."""
from torchblur.image.moments import image_moments, moments_along, sinusoid_from_moments
from torchblur.image.preprocess import (
    DarkFrame, PSFFit, SaturationCurve, Spots, crop, dark_frame, find_spots, fit_gaussian_psf, saturation_curve,
    subtract_dark, threshold_mask,
)
from torchblur.image.psf_from_still import StillPSF, psf_from_still
from torchblur.image.spots import SpotGrid, SpotLayout, SpotPSFs, crop_spots, locate_spots
from torchblur.image.tracking import AxisCalibration, TrackingResult, calibrate_axes, track_sine

__all__ = [
    "AxisCalibration", "DarkFrame", "PSFFit", "SaturationCurve", "SpotGrid", "SpotLayout", "SpotPSFs", "Spots", "StillPSF",
    "TrackingResult", "calibrate_axes", "crop", "crop_spots", "dark_frame", "find_spots", "fit_gaussian_psf",
    "image_moments", "locate_spots", "moments_along", "psf_from_still", "saturation_curve", "sinusoid_from_moments", "subtract_dark",
    "threshold_mask", "track_sine",
]
