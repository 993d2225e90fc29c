"""Import paths of the flat layout (torchblur <= 0.1), kept working.

Each old module path imports the very module that now holds its code, so
``torchblur.preprocess.fit_gaussian_psf is torchblur.image.preprocess.fit_gaussian_psf``.
Old paths that are now packages (``torchblur.fit``, ``torchblur.render``, ``torchblur.design``,
``torchblur.identify``) re-export their public names from the package itself.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

#: old module path -> the module that holds its code now
MOVED = {
    "torchblur.alias": "torchblur.render.alias",
    "torchblur.psf": "torchblur.render.psf",
    "torchblur.trajectory": "torchblur.render.trajectory",
    "torchblur.timing": "torchblur.render.window",
    "torchblur.splat_jacobian": "torchblur.render.splat",
    "torchblur.camera": "torchblur.render.camera",
    "torchblur.multisine_fit": "torchblur.fit.multisine",
    "torchblur.coded_exposure": "torchblur.fit.coded",
    "torchblur.consistency": "torchblur.fit.consistency",
    "torchblur.landscape": "torchblur.fit.landscape",
    "torchblur.optim": "torchblur.fit.optim",
    "torchblur.losses": "torchblur.fit.losses",
    "torchblur.frequency_response": "torchblur.sysid.frequency_response",
    "torchblur.model_fit": "torchblur.sysid.tf_fit",
    "torchblur.direct": "torchblur.sysid.direct",
    "torchblur.plots": "torchblur.sysid.plots",
    "torchblur.lti": "torchblur.systems.lti",
    "torchblur.mimo": "torchblur.systems.mimo",
    "torchblur.preprocess": "torchblur.image.preprocess",
    "torchblur.spots": "torchblur.image.spots",
    "torchblur.moments": "torchblur.image.moments",
    "torchblur.tracking": "torchblur.image.tracking",
    "torchblur.multisine": "torchblur.design.multisine",
    "torchblur.excitation_design": "torchblur.design.fisher",
    "torchblur.config": "torchblur.identify.config",
    "torchblur.identify_multisine": "torchblur.identify.multisine",
    "torchblur.cli": "torchblur.identify.cli",
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old module path to the module that holds its code now."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module):  # the target module is already executed
        return None


def install() -> None:
    """Put the finder on ``sys.meta_path`` once."""
    if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())
