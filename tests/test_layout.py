"""The package's layout: the public surface, and the import paths of the flat layout still working."""
import importlib

import pytest

import torchblur as tb
from torchblur._legacy import MOVED

# Import paths the README and guides documented before the subpackages (old path, name, new home).
DOCUMENTED = [
    ("torchblur.fit", "fit_sinusoid", "torchblur.fit.sinusoid"),
    ("torchblur.fit", "SinusoidFit", "torchblur.fit.sinusoid"),
    ("torchblur.design", "dual_exposure_windows", "torchblur.design.windows"),
    ("torchblur.design", "resolve_branches", "torchblur.design.windows"),
    ("torchblur.design", "check_design", "torchblur.design.windows"),
    ("torchblur.design", "trigger_phase_for", "torchblur.design.windows"),
    ("torchblur.preprocess", "dark_frame", "torchblur.image.preprocess"),
    ("torchblur.preprocess", "fit_gaussian_psf", "torchblur.image.preprocess"),
    ("torchblur.preprocess", "find_spots", "torchblur.image.preprocess"),
    ("torchblur.identify", "identify", "torchblur.identify.run"),
    ("torchblur.consistency", "BlurConsistencyLoss", "torchblur.fit.consistency"),
    ("torchblur.landscape", "cost_landscape", "torchblur.fit.landscape"),
    ("torchblur.hardware", "SDKCamera", "torchblur.hardware.camera_sdk"),
    ("torchblur.hardware", "Controller", "torchblur.hardware.controller"),
    ("torchblur.tracking", "calibrate_axes", "torchblur.image.tracking"),
    ("torchblur.camera", "CameraModel", "torchblur.render.camera"),
    ("torchblur.excitation_design", "image_fisher", "torchblur.design.fisher"),
    ("torchblur.coded_exposure", "mirror_code", "torchblur.fit.coded"),
    ("torchblur.coded_exposure", "fit_sinusoid_coded", "torchblur.fit.coded"),
    ("torchblur.spots", "SpotGrid", "torchblur.image.spots"),
    ("torchblur.multisine_fit", "fit_multisine", "torchblur.fit.multisine"),
    ("torchblur.multisine", "LTIMultisineTrajectory", "torchblur.design.multisine"),
    ("torchblur.model_fit", "fit_transfer_function", "torchblur.sysid.tf_fit"),
    ("torchblur.frequency_response", "FrequencyResponse", "torchblur.sysid.frequency_response"),
    ("torchblur.mimo", "PlantMatrix", "torchblur.systems.mimo"),
    ("torchblur.direct", "fit_direct", "torchblur.sysid.direct"),
    ("torchblur.render", "render_blur", "torchblur.render.blur"),
    ("torchblur.psf", "GaussianPSF", "torchblur.render.psf"),
    ("torchblur.timing", "ExposureWindow", "torchblur.render.window"),
    ("torchblur.config", "load_config", "torchblur.identify.config"),
    ("torchblur.cli", "main", "torchblur.identify.cli"),
]


@pytest.mark.parametrize("old, name, new", DOCUMENTED)
def test_documented_import_paths_give_the_same_object(old, name, new):
    assert getattr(importlib.import_module(old), name) is getattr(importlib.import_module(new), name)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_every_moved_module_path_is_the_module_itself(old):
    assert importlib.import_module(old) is importlib.import_module(MOVED[old])


def test_from_import_of_a_moved_module():
    from torchblur import preprocess  # noqa: F401  (a submodule import through the old path)
    import torchblur.image.preprocess as new

    assert preprocess is new


@pytest.mark.parametrize("name", tb.__all__)
def test_public_names_resolve_and_are_documented(name):
    obj = getattr(tb, name)
    assert obj.__doc__ and obj.__doc__.strip(), name
    assert name in dir(tb)


def test_identify_is_the_package_and_runs_the_pipeline():
    import torchblur.identify as ident
    from torchblur.identify.run import identify

    assert tb.identify is ident and ident.identify is identify
    assert callable(tb.identify)


def test_unknown_attribute_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        tb.no_such_name  # noqa: B018
