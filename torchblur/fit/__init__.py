"""Fitting rendered blur to images: every frequency, exposure and spot in one batch.

``sinusoid`` (:func:`fit_sinusoid`, its steps), ``results`` (:class:`SinusoidFit`), ``status``
(the one table of status codes and flags), ``problem`` (a fit's inputs flattened, its starts and
crop), ``sine_model`` (the image and Jacobian of the parameters, on the one forward model
:func:`torchblur.render.splat.sine_blur_with_jacobian`), ``robust`` (outliers, stray-light
planes), ``multisine``, ``coded`` (a coded exposure), ``consistency``
(:class:`BlurConsistencyLoss`, the renderer as a loss inside learned models), ``landscape`` (the
loss over a parameter grid). The batched Levenberg-Marquardt (:mod:`torchblur.optim`) and the
image losses (:mod:`torchblur.losses`) sit in the base layer: the image layer fits with them too.
"""
from torchblur.losses import LOSSES, image_loss
from torchblur.optim import LMResult, levenberg_marquardt
from torchblur.fit.coded import CodedFit, fit_sinusoid_coded
from torchblur.fit.consistency import BlurConsistencyLoss, blur_consistency
from torchblur.fit.landscape import cost_landscape
from torchblur.fit.multisine import MultisineFit, fit_multisine
from torchblur.fit.sinusoid import (
    FLAGS, MASKED, NO_MOTION, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED, STATUS, SinusoidFit, fit_sinusoid,
)

__all__ = [
    "FLAGS", "LOSSES", "MASKED", "NO_MOTION", "OUTLIERS_MASKED", "PARTLY_OUT_OF_FRAME", "SATURATED_MASKED", "STATUS",
    "BlurConsistencyLoss", "CodedFit", "LMResult", "MultisineFit", "SinusoidFit", "blur_consistency", "cost_landscape",
    "fit_multisine", "fit_sinusoid", "fit_sinusoid_coded", "image_loss", "levenberg_marquardt",
]
