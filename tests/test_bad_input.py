"""The input contract: each bad input and the exact exception it raises (issue 2 / issue 8).

Every error subclasses ValueError or TypeError and its message names the argument.
"""
import math

import pytest
import torch

import torchblur as tb
from torchblur.errors import InputTypeError, ParameterError, ShapeError

F64 = torch.float64
C = torch.tensor([10.0, 10.0], dtype=F64)
I2 = torch.eye(2, dtype=F64)
Z2 = torch.zeros(2, dtype=F64)
NAN = float("nan")


def good():
    return tb.Sinusoid(torch.tensor([3.0, 0.0], dtype=F64), Z2, 600.0), tb.GaussianPSF(C, 4 * I2), tb.ExposureWindow(0.0, 1e-3)


CASES = [
    # (description, callable, exception class, text the message must contain)
    ("covariance not positive definite", lambda: tb.GaussianPSF(C, torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)), ParameterError, "cov"),
    ("covariance with negative variance", lambda: tb.GaussianPSF(C, -I2), ParameterError, "cov"),
    ("covariance not symmetric", lambda: tb.GaussianPSF(C, torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64)), ParameterError, "cov"),
    ("covariance wrong shape", lambda: tb.GaussianPSF(C, torch.ones(3, 3, dtype=F64)), ShapeError, "cov"),
    ("center wrong shape", lambda: tb.GaussianPSF(torch.zeros(3, dtype=F64), I2), ShapeError, "center"),
    ("NaN center", lambda: tb.GaussianPSF(torch.tensor([NAN, 1.0], dtype=F64), I2), ParameterError, "center"),
    ("NaN amplitude", lambda: tb.GaussianPSF(C, I2, amplitude=NAN), ParameterError, "amplitude"),
    ("Inf covariance", lambda: tb.GaussianPSF(C, I2 * float("inf")), ParameterError, "cov"),
    ("complex center", lambda: tb.GaussianPSF(torch.zeros(2, dtype=torch.complex64), I2), InputTypeError, "center"),
    ("string amplitude", lambda: tb.GaussianPSF(C, I2, amplitude="bright"), InputTypeError, "amplitude"),
    ("sigma zero", lambda: tb.GaussianPSF.isotropic(C, 0.0), ParameterError, "sigma"),
    ("zero exposure", lambda: tb.ExposureWindow(0.0, 0.0), ParameterError, "duration"),
    ("negative exposure", lambda: tb.ExposureWindow(0.0, -1e-3), ParameterError, "duration"),
    ("NaN window start", lambda: tb.ExposureWindow(NAN, 1e-3), ParameterError, "start"),
    ("window shapes do not broadcast", lambda: tb.ExposureWindow(torch.zeros(3), torch.ones(4)), ShapeError, "start"),
    ("Ts too short", lambda: tb.SensorTiming(0.0, 1e-3, 0.03, 0.01, 1 / 30), ParameterError, "sample_period_s"),
    ("negative trigger delay", lambda: tb.SensorTiming(0.0, -1e-3, 0.01, 0.01, 1 / 30), ParameterError, "trigger_delay_s"),
    ("bool exposure", lambda: tb.SensorTiming(0.0, 0.0, True, 0.01, 1 / 30), InputTypeError, "exposure_s"),
    ("n_frames zero", lambda: tb.SensorTiming(0.0, 0.0, 0.01, 0.01, 1 / 30).windows(0), ParameterError, "n_frames"),
    ("omega zero", lambda: tb.Sinusoid(Z2, Z2, 0.0), ParameterError, "omega"),
    ("omega negative", lambda: tb.Sinusoid(Z2, Z2, torch.tensor([-1.0, 2.0])), ParameterError, "omega"),
    ("NaN phase", lambda: tb.Sinusoid(Z2, torch.tensor([NAN, 0.0]), 1.0), ParameterError, "phase"),
    ("amplitude not per axis", lambda: tb.Sinusoid(torch.zeros(3), Z2, 1.0), ShapeError, "amplitude"),
    ("sinusoid batch mismatch", lambda: tb.Sinusoid(torch.zeros(4, 2), torch.zeros(3, 2), 1.0), ShapeError, "amplitude"),
    ("multisine omega count", lambda: tb.Multisine(torch.zeros(3, 2), torch.zeros(3, 2), torch.ones(4)), ShapeError, "omega"),
    ("spline knots not increasing", lambda: tb.SplineTrajectory(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3, 2)), ParameterError, "times"),
    ("spline single knot", lambda: tb.SplineTrajectory(torch.tensor([0.0]), torch.zeros(1, 2)), ShapeError, "values"),
    ("renderer height zero", lambda: tb.BlurRenderer(0, 8), ParameterError, "height"),
    ("renderer unknown setting", lambda: tb.BlurRenderer(8, 8, nodez=3), InputTypeError, "nodez"),
    ("renderer bad nodes_per_panel", lambda: tb.BlurRenderer(8, 8, nodes_per_panel=0), ParameterError, "nodes_per_panel"),
    ("render batch mismatch", lambda: tb.render_blur(tb.Sinusoid(torch.zeros(4, 2, dtype=F64), torch.zeros(4, 2, dtype=F64), 1.0),
                                                     tb.GaussianPSF(torch.zeros(3, 2, dtype=F64), I2), tb.ExposureWindow(0.0, 1.0),
                                                     height=8, width=8), ShapeError, "trajectory"),
    ("render psf of wrong type", lambda: tb.render_blur(good()[0], "psf", good()[2], height=8, width=8), InputTypeError, "psf"),
    ("render trajectory of wrong type", lambda: tb.render_blur(object(), good()[1], good()[2], height=8, width=8), InputTypeError, "trajectory"),
    ("kernel of wrong frame size", lambda: tb.render_blur(good()[0], tb.KernelPSF(torch.ones(5, 5, dtype=F64)), good()[2], height=8, width=8), ShapeError, "psf"),
    ("kernel with NaN", lambda: tb.KernelPSF(torch.full((4, 4), NAN)), ParameterError, "image"),
    ("kernel exposure zero", lambda: tb.KernelPSF(torch.ones(4, 4), exposure_s=0.0), ParameterError, "exposure_s"),
    ("motion longer than max_nodes", lambda: tb.render_blur(tb.Sinusoid(torch.tensor([1e4, 0.0], dtype=F64), Z2, 1e4), good()[1],
                                                            tb.ExposureWindow(0.0, 1.0), height=8, width=8), ParameterError, "max_nodes"),
    ("alias with omega zero", lambda: tb.alias_phase(0.1, 0.0, tb.ExposureWindow(0.0, 1.0)), ParameterError, "omega"),
]


@pytest.mark.parametrize("desc,fn,exc,name", CASES, ids=[c[0] for c in CASES])
def test_bad_input_raises_named_error(desc, fn, exc, name):
    with pytest.raises(exc) as info:
        fn()
    assert type(info.value) is exc
    assert name in str(info.value)
    assert isinstance(info.value, (ValueError, TypeError))
