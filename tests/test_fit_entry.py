"""fit_sinusoid's entry (issues 16 and 15): dtypes, every loss with every optimizer, dim streaks.

- dtypes: the fit runs in the widest floating dtype of images, PSF and window (at least
  float32); integer, float16 and bfloat16 images are promoted; bool and complex refused.
- loss x optimizer: every pair fits a small clean problem or is refused by name (lm + linf).
"""
import sys
from pathlib import Path

import pytest
import torch

import torchblur as tb
from torchblur.errors import InputTypeError, ParameterError
from torchblur.fit.sinusoid import fit_dtype, fit_sinusoid

sys.path.insert(0, str(Path(__file__).parent))
from test_fit import make  # noqa: E402

F64, F32 = torch.float64, torch.float32


def _wrap(x):
    return tb.wrap_phase(x)


def _as(d, img_dtype, psf_dtype, win_dtype):
    win = tb.ExposureWindow(d["win"].start.to(win_dtype), d["win"].duration.to(win_dtype))
    return d["clean"].to(img_dtype), d["psf"].to(psf_dtype), win


# --------------------------------------------------------------------------- dtypes

DTYPES = [
    # (images, psf, window, expected fit dtype)
    (torch.float16, F32, F32, F32),
    (torch.bfloat16, F32, F32, F32),
    (F32, F64, F32, F64),
    (F32, F32, F64, F64),
    (F32, F32, F32, F32),
    (F64, F32, F32, F64),
    (torch.float16, F64, F64, F64),
]


@pytest.mark.parametrize("img_dtype,psf_dtype,win_dtype,expected", DTYPES, ids=[f"{a}-{b}-{c}".replace("torch.", "") for a, b, c, _ in DTYPES])
@pytest.mark.parametrize("optimizer", ["lm", "lbfgs"])
def test_mixed_dtypes_are_promoted_to_the_widest(img_dtype, psf_dtype, win_dtype, expected, optimizer):
    d = make(N=2, tilted=False)
    images, psf, win = _as(d, img_dtype, psf_dtype, win_dtype)
    assert fit_dtype(images, psf, win) == expected
    res = fit_sinusoid(images, psf, win, d["om"].to(win_dtype), optimizer=optimizer)
    assert res.amplitude.dtype == res.phase.dtype == res.covariance.dtype == expected
    # Half-precision images carry a rounding error of ~1e-3 of the peak: the fit stays close.
    tol = 2e-2 if img_dtype in (torch.float16, torch.bfloat16) else 1e-3
    assert (res.status == 0).all()
    torch.testing.assert_close(res.amplitude.double(), d["M"], rtol=tol, atol=0)
    assert float(_wrap(res.phase.double() - d["phi"]).abs().max()) < tol


def test_float64_fit_of_float32_images_equals_the_float64_images_fit():
    """Promotion is a plain cast: float32 images with a float64 window fit as the cast images."""
    d = make(N=2, sigma_frac=0.01, seed=3)
    img32 = d["images"].to(F32)
    mixed = fit_sinusoid(img32, d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    cast = fit_sinusoid(img32.to(F64), d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    assert mixed.amplitude.dtype == F64
    torch.testing.assert_close(mixed.amplitude, cast.amplitude, rtol=1e-12, atol=0)
    torch.testing.assert_close(mixed.phase_std, cast.phase_std, rtol=1e-12, atol=0)


@pytest.mark.parametrize("int_dtype", [torch.uint8, torch.int16, torch.int32, torch.int64])
def test_integer_images_are_promoted(int_dtype):
    """A camera's counts (dark level subtracted, e.g. by the camera) fit as their float copy."""
    d = make(N=2, tilted=False)
    scale = 200.0 / float(d["clean"].max())
    counts = (d["clean"] * scale).round()
    psf = tb.GaussianPSF(d["psf"].center, d["psf"].cov, d["psf"].amplitude * scale)
    res = fit_sinusoid(counts.to(int_dtype), psf.to(F32), d["win"].to(F32), d["om"])
    ref = fit_sinusoid(counts.to(F32), psf.to(F32), d["win"].to(F32), d["om"])
    assert res.amplitude.dtype == F32
    torch.testing.assert_close(res.amplitude, ref.amplitude, rtol=0, atol=0)
    torch.testing.assert_close(res.phase, ref.phase, rtol=0, atol=0)


@pytest.mark.parametrize("bad", [torch.bool, torch.complex64])
def test_bool_and_complex_images_are_refused_by_name(bad):
    d = make(N=1, tilted=False)
    images = d["clean"] > 0.1 if bad == torch.bool else d["clean"].to(bad)
    with pytest.raises(InputTypeError, match="images"):
        fit_sinusoid(images, d["psf"], d["win"], d["om"])


def test_noise_std_and_saturation_level_follow_the_fit_dtype():
    d = make(N=2, sigma_frac=0.01, seed=4)
    images, psf, win = _as(d, F32, F32, F64)
    res = fit_sinusoid(images, psf, win, d["om"].to(F32), noise_std=d["sigma"].to(F32),
                       saturation_level=torch.full((2,), 1e9, dtype=F32))
    assert res.amplitude.dtype == F64 and (res.status == 0).all()


# --------------------------------------------------------------------------- loss x optimizer

LOSSES = ("l2", "l1", "linf", "poisson")
OPTIMIZERS = ("lm", "adam", "lbfgs")
REFUSED = {("lm", "linf")}


@pytest.mark.parametrize("dtype", [F32, F64])
@pytest.mark.parametrize("loss", LOSSES)
@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_every_loss_with_every_optimizer_fits_or_is_refused_by_name(optimizer, loss, dtype):
    """On one small clean problem (images in ``dtype``, a float64 window as
    ``dual_exposure_windows`` gives): each pair reaches the truth or is refused with a
    ParameterError naming ``loss`` and the optimizers that take it."""
    d = make(N=2, tilted=False)
    images, psf = d["clean"].to(dtype), d["psf"].to(dtype)
    if (optimizer, loss) in REFUSED:
        with pytest.raises(ParameterError, match="loss.*adam.*lbfgs"):
            fit_sinusoid(images, psf, d["win"], d["om"], optimizer=optimizer, loss=loss)
        return
    res = fit_sinusoid(images, psf, d["win"], d["om"], optimizer=optimizer, loss=loss)
    # Adam's fixed step ends within ~1e-2 px on the non-smooth losses (status 2: not converged
    # by its cost-change rule); the others reach the optimum.
    tol = 5e-2 if optimizer == "adam" else 1e-4
    assert bool(torch.isfinite(res.amplitude).all())
    assert set(res.status.tolist()) <= {0, 2}
    torch.testing.assert_close(res.amplitude, d["M"], rtol=tol, atol=0)
    assert float(_wrap(res.phase - d["phi"]).abs().max()) < tol
