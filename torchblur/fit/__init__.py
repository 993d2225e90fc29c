"""Fitting rendered blur to images: every frequency, exposure and spot in one batch (the modules:
README.md, "Layout"; the batched Levenberg-Marquardt and the image losses sit in the base layer,
:mod:`torchblur.optim` and :mod:`torchblur.losses`).
"""
from torchblur.losses import LOSSES, image_loss
from torchblur.optim import LMResult, levenberg_marquardt
from torchblur.fit.coded import CodedFit, fit_sinusoid_coded
from torchblur.fit.consistency import BlurConsistencyLoss, blur_consistency
from torchblur.fit.landscape import cost_landscape
from torchblur.fit.multisine import MultisineFit, fit_multisine
from torchblur.fit.sinusoid import SinusoidFit, fit_sinusoid
from torchblur.fit.status import FLAGS, MASKED, NO_MOTION, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED, STATUS

__all__ = [
    "FLAGS", "LOSSES", "MASKED", "NO_MOTION", "OUTLIERS_MASKED", "PARTLY_OUT_OF_FRAME", "SATURATED_MASKED", "STATUS",
    "BlurConsistencyLoss", "CodedFit", "LMResult", "MultisineFit", "SinusoidFit", "blur_consistency", "cost_landscape",
    "fit_multisine", "fit_sinusoid", "fit_sinusoid_coded", "image_loss", "levenberg_marquardt",
]
