"""Whether the model explains the images: the fit's reduced chi2 and the report's line on it."""
import math
import types

import numpy as np
import torch

import torchblur as tb
from torchblur.fit.status import POOR_FIT_CHI2
from torchblur.identify.report import fit_quality

F64 = torch.float64


def _problem(seed=0):
    g = torch.Generator().manual_seed(seed)
    omega = 2 * math.pi * torch.tensor([40.0, 120.0, 350.0, 800.0], dtype=F64)
    win = tb.dual_exposure_windows(omega, fractions=(0.3, 0.8), trigger_phase=0.7)
    psf = tb.GaussianPSF.from_axes(torch.tensor([32.0, 24.0], dtype=F64), 2.4, 1.6, 0.5, amplitude=2e5)
    truth = tb.Sinusoid(torch.tensor([[6.0, 0.0]] * 4, dtype=F64)[:, None], torch.ones(4, 1, 2, dtype=F64), omega[:, None])
    clean = tb.render_blur(truth, psf, win, height=48, width=64)
    sigma = torch.sqrt(25 + clean)
    return clean + sigma * torch.randn(clean.shape, generator=g, dtype=F64), sigma, psf, win, omega


def test_reduced_chi2_is_one_for_the_right_model_and_large_for_a_wrong_psf():
    images, sigma, psf, win, omega = _problem()
    right = tb.fit_sinusoid(images, psf, win, omega, noise_std=sigma)
    assert right.reduced_chi2.shape == (4,)
    np.testing.assert_allclose(right.reduced_chi2.numpy(), 1.0, atol=0.1)  # 6144 pixels: std of chi2/dof ~0.02
    wide = tb.GaussianPSF.from_axes(psf.center, 2.9, 1.9, 0.5, amplitude=2e5 * (2.4 * 1.6) / (2.9 * 1.9))
    wrong = tb.fit_sinusoid(images, wide, win, omega, noise_std=sigma)
    # the wrong PSF biases M by 5 % (20 std) at 40 Hz: the reduced chi2 is what shows it
    assert float(wrong.reduced_chi2[0]) > POOR_FIT_CHI2
    assert abs(float(wrong.amplitude[0]) - 6.0) > 10 * float(wrong.amplitude_std[0])


def test_reduced_chi2_unknown_without_a_given_noise():
    images, _, psf, win, omega = _problem()
    assert torch.isnan(tb.fit_sinusoid(images, psf, win, omega).reduced_chi2).all()


def test_the_report_says_when_the_model_does_not_explain_the_images():
    good = types.SimpleNamespace(reduced_chi2=torch.tensor([0.98, 1.02, 1.01], dtype=F64))
    doc, line = fit_quality(good)
    assert doc == {"max_reduced_chi2": 1.02, "poor_fit_problems": 0} and line.startswith("fit quality:")
    bad = types.SimpleNamespace(reduced_chi2=torch.tensor([1.01, 2.4, float("nan")]))
    doc, line = fit_quality(bad)
    assert doc["poor_fit_problems"] == 1 and line.startswith("warning: 1 of 2 fitted problems")
    assert "stds understate the error" in line
    multisine = types.SimpleNamespace(extras={"reduced_chi2": torch.tensor([1.0])})  # a MultisineFit keeps it in extras
    assert fit_quality([multisine])[0]["poor_fit_problems"] == 0
    assert fit_quality(types.SimpleNamespace())[1] is None  # nothing known: no line, no claim
