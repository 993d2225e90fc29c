"""System identification from the fitted points: the frequency response, transfer-function
models fitted to it (``tf_fit``), a parametric model fitted straight to the images
(``direct``), and Bode and residual figures (``plots``, matplotlib imported on use).
"""
from torchblur.sysid.alias_resolution import AliasResolution, resolve_alias_with_model
from torchblur.sysid.direct import DirectModelFit, fit_direct
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import TransferFunctionFit, fit_transfer_function

__all__ = [
    "AliasResolution", "DirectModelFit", "FrequencyResponse", "TransferFunctionFit", "fit_direct",
    "fit_transfer_function", "resolve_alias_with_model",
]
