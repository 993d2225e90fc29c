"""The multisine fit's goodness of fit: its reduced chi2 per degree of freedom, the POOR_FIT status's
bound and no verdict without a given noise, the rules of fit_sinusoid (tests/test_fit_quality.py)."""
import math

import pytest
import torch

from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.fit.status import POOR_FIT, POOR_FIT_CHI2, POOR_FIT_FLAG, POOR_FIT_STATUS_CHI2, STATUS
from torchblur.render.psf import GaussianPSF
from torchblur.render.window import ExposureWindow

F64 = torch.float64
T0 = 0.03  # s: the tones' common period
OM = 2 * math.pi / T0 * torch.tensor([2.0, 3.0], dtype=F64)
THETA = torch.tensor([0.9, 0.6, 0.4, -1.2, 1.0], dtype=F64)  # M (px), phi (rad), scale: P = 5
PSF = GaussianPSF(torch.tensor([5.5, 5.5], dtype=F64), torch.eye(2, dtype=F64), torch.tensor(1000 / (0.3 * T0), dtype=F64))
WIN = ExposureWindow(torch.tensor([0.0, 0.21, 0.47, 0.73], dtype=F64) * T0, torch.tensor([0.3, 0.25, 0.35, 0.2], dtype=F64) * T0)
SIGMA = 10.0  # the pixel noise std; the spot's peak ~900
B = 256  # noise draws


def _frames(seed: int = 0):
    """``(clean [4, 12, 12], noisy [B, 4, 12, 12], mask [4, 12, 12])``: 4 px x 4 px around the spot kept in each
    frame, 64 pixels for P = 5 parameters, so that the degrees of freedom (59) differ from the pixels by 8 %."""
    clean = render_multisine(THETA, OM, PSF, WIN, height=12, width=12)
    g = torch.Generator().manual_seed(seed)
    noisy = clean + SIGMA * torch.randn((B,) + clean.shape, generator=g, dtype=F64)
    mask = torch.zeros(clean.shape, dtype=torch.bool)
    mask[:, 4:8, 4:8] = True
    return clean, noisy, mask


def _fit(images, mask, noise_std):
    return fit_multisine(images, PSF, WIN, OM, noise_std=noise_std, mask=mask, amplitude_guess=THETA[:2], phase_guess=THETA[2:4],
                         n_starts=0, n_refine=1)


@pytest.fixture(scope="module")
def frames():
    return _frames()


def test_reduced_chi2_is_per_degree_of_freedom(frames):
    """With the true noise given, the reduced chi2 (cost / (pixels used - P)) averages 1 over B noise
    draws, within 3 sampling errors; per pixel used (the old divisor) it is biased low by P / n_used
    (8 %), which these draws resolve (more than 3 sampling errors below 1)."""
    _, noisy, mask = frames
    fit = _fit(noisy, mask, SIGMA)
    n, P = int(mask.sum()), len(fit.param_names)
    assert P == 5 and bool((fit.status == 0).all())
    red = fit.extras["reduced_chi2"]
    mean, err = float(red.mean()), float(red.std()) / math.sqrt(B)
    assert abs(mean - 1) < 3 * err, (mean, err)
    assert mean * (n - P) / n < 1 - 3 * err  # the old divisor's mean: far from 1
    # the cost is the chi2 itself: per degree of freedom exactly
    torch.testing.assert_close(red, fit.cost / (n - P), rtol=1e-12, atol=0)


def test_poor_fit_status_above_its_named_bound(frames):
    """One noisy set fitted three times, with the noise std given true, / 1.5 and / 2.2: the reduced chi2
    scales as 1 / std^2 (1.22, 2.75, 5.9 here). Below POOR_FIT_CHI2: neither; between it and
    POOR_FIT_STATUS_CHI2: flagged, status ok; above: status POOR_FIT (after the wider search), flagged.
    The status is POOR_FIT exactly where the reduced chi2 is above POOR_FIT_STATUS_CHI2, the number its
    STATUS text quotes."""
    _, noisy, mask = frames
    fit = _fit(noisy[:1].expand(3, -1, -1, -1), mask, torch.tensor([SIGMA, SIGMA / 1.5, SIGMA / 2.2], dtype=F64))
    red = fit.extras["reduced_chi2"]
    torch.testing.assert_close(red[1:], red[0] * torch.tensor([1.5, 2.2], dtype=F64) ** 2, rtol=1e-6, atol=0)
    assert float(red[0]) < POOR_FIT_CHI2 < float(red[1]) < POOR_FIT_STATUS_CHI2 < float(red[2])
    assert fit.status.tolist() == [0, 0, POOR_FIT] and bool(fit.extras["retried"][2])
    assert ((fit.flags & POOR_FIT_FLAG) != 0).tolist() == [False, True, True]
    assert torch.equal(fit.status == POOR_FIT, red > POOR_FIT_STATUS_CHI2)
    assert f"reduced chi2 > {POOR_FIT_STATUS_CHI2:g}" in STATUS[POOR_FIT]


def test_no_verdict_without_a_given_noise(frames):
    """Without a noise std (or model) the reduced chi2 is unknown, NaN, as fit_sinusoid's: never
    POOR_FIT_FLAG nor status POOR_FIT, and no wider search (its trigger is the chi2), even where the
    images are far from the model (tones at other frequencies than fitted: flagged with the noise given)."""
    clean, noisy, mask = frames
    fit = _fit(noisy[:2], mask, None)
    assert torch.isnan(fit.extras["reduced_chi2"]).all() and bool((fit.status == 0).all()) and not bool(fit.flags.any())
    other = render_multisine(THETA, OM * torch.tensor([1.0, 1.6], dtype=F64), PSF, WIN, height=12, width=12) + (noisy[0] - clean)
    given = _fit(other, None, SIGMA)
    assert float(given.extras["reduced_chi2"]) > POOR_FIT_CHI2 and int(given.flags) & POOR_FIT_FLAG
    wrong = _fit(other, None, None)
    assert torch.isnan(wrong.extras["reduced_chi2"]) and int(wrong.status) != POOR_FIT and not bool(wrong.flags)
    assert not bool(wrong.extras["retried"])
