"""Image preprocessing, the steps before a fit, in one namespace: dark frames (:mod:`~torchblur.image.dark`),
thresholds, spot finding and crops (:mod:`~torchblur.image.detection`), the still-spot PSF fit
(:mod:`~torchblur.image.psf_fit`), the PSF a fit should use (:mod:`~torchblur.image.psf_from_still`) and the saturation curve, paper Fig. 4 (:mod:`~torchblur.image.saturation`).

Conventions (as everywhere in torchblur): ``image[..., i, j]`` is the pixel at row ``i``,
column ``j``, whose centre is at ``x = j``, ``y = i``; positions in pixels (px), covariances
in px^2; ``[...]`` are batch dims; ``K`` spots or samples; ``N`` frames; ``H, W`` pixels.
Frames are in the camera's units (ADU, or electrons after
:meth:`~torchblur.render.camera.CameraModel.to_electrons`); a PSF's ``amplitude`` is its peak
intensity per second of exposure, in those units.

Every function is pure: tensors in, new tensors out, dtype and device taken from the
inputs. Image filtering and connected components use kornia (imported by this module only;
the package's ``__init__`` does not import it).

Typical use on a still-spot recording::

    dark = dark_frame(dark_frames)                       # [N, H, W] -> DarkFrame
    still = subtract_dark(still_frames, dark).mean(-3)   # average of N still frames
    spots = find_spots(still, noise_std=dark.read_noise / N**0.5)[0]
    crops, offset = crop(still, spots.centroid[0], (32, 32))
    fit = fit_gaussian_psf(crops, exposure_s=Te, mask=curve.mask(crops + dark_level))
    psf_full_frame = GaussianPSF(fit.psf.center + offset, fit.psf.cov, fit.psf.amplitude)
"""
from __future__ import annotations

from torchblur.image.dark import DarkFrame, dark_frame, subtract_dark
from torchblur.image.detection import Spots, crop, find_spots, threshold_mask
from torchblur.image.psf_fit import PSFFit, fit_gaussian_psf
from torchblur.image.psf_from_still import StillPSF, psf_from_still
from torchblur.image.saturation import SaturationCurve, saturation_curve

__all__ = [
    "DarkFrame",
    "dark_frame",
    "subtract_dark",
    "threshold_mask",
    "Spots",
    "find_spots",
    "crop",
    "PSFFit",
    "fit_gaussian_psf",
    "StillPSF",
    "psf_from_still",
    "SaturationCurve",
    "saturation_curve",
]
