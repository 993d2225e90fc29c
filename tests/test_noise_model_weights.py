"""One noise-weight rule for the multisine and the direct fits (as fit_sinusoid's): given the camera's
noise model and no noise_std, a first pass weighted by each pixel's own value, then a refit weighted
by ``noise.std`` of the first fit's model image.

Monte Carlo on small simulated problems (frames from CameraModel: shot noise, read noise, rounding to
whole ADU, turned back into electrons): weights from the pixels' own values bias the amplitudes (the
multisine's tones, the direct model's gain) low by about 0.3 of their std at a few hundred electrons;
the noise model's rule is within 3 / sqrt(N) of 0 and agrees with weights from the true expected
charge. Then the arguments' checks, and fit.loss with the multisine plan refused by name.
"""
import math

import numpy as np
import pytest
import torch

import torchblur as tb
from torchblur.errors import ConfigError, InputTypeError, ParameterError, ShapeError
from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.config import load_config
from torchblur.render.camera import CameraModel, CameraNoise
from torchblur.sysid.direct import fit_direct
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function

F64 = torch.float64
CAMERA = CameraModel(read_noise_e=6.0, gain_e_per_adu=2.0, dark_level_adu=100.0, bit_depth=16, full_well_e=1e6)


def _electrons(expected, seed):
    """Camera frames of ``expected`` electrons, back in electrons (dark subtracted)."""
    return CAMERA.noise.to_electrons(CAMERA.expose(expected, generator=torch.Generator().manual_seed(seed)))


# --------------------------------------------------------------------------- multisine
MS_B = 100  # image sets (2 tones each: 200 amplitudes)
MS_OM = 2 * math.pi * 100.0 * torch.tensor([2.0, 3.0], dtype=F64)


@pytest.fixture(scope="module")
def ms():
    """Image sets of 2 tones, 5 images each at laser powers that give every image about the same
    light (images and PSF divided by the power, as the multisine plan fits them): the truth and
    the fits with the three weights (the pixels' own values, the noise model, the true charge)."""
    g = torch.Generator().manual_seed(0)
    M = 2.0 + torch.rand(MS_B, 2, generator=g, dtype=F64)
    phi = (2 * torch.rand(MS_B, 2, generator=g, dtype=F64) - 1) * math.pi
    T0 = 0.01
    win = tb.ExposureWindow(torch.tensor([0.0, 0.15, 0.4, 0.6, 0.8], dtype=F64) * T0,
                            torch.tensor([0.9, 0.1, 0.15, 0.1, 0.2], dtype=F64) * T0)
    pw = 0.3 * T0 / win.duration  # [E]
    psf = tb.GaussianPSF(torch.tensor([14.5, 7.5], dtype=F64), 1.6**2 * torch.eye(2, dtype=F64), torch.tensor(1.0, dtype=F64))
    unit = render_multisine(torch.cat([M, phi], -1), MS_OM, psf, win, height=16, width=30)  # at power 1
    k = 300.0 / float((unit * pw[:, None, None]).amax())  # peak 300 e-
    psf = tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * k)
    expected = unit * k * pw[:, None, None]  # electrons the camera records
    e = _electrons(expected, 7)
    p = pw[:, None, None]
    kw = dict(amplitude_guess=M, phase_guess=phi, n_starts=0, n_refine=1)
    fits = {"own": fit_multisine(e / p, psf, win, MS_OM, noise_std=CAMERA.noise.std(e) / p, **kw),
            "model": fit_multisine(e / p, psf, win, MS_OM, noise=CAMERA.noise, power=pw, **kw),
            "true": fit_multisine(e / p, psf, win, MS_OM, noise_std=CAMERA.noise.std(expected) / p, **kw)}
    return dict(M=M, phi=phi, win=win, pw=pw, psf=psf, img=e / p, fits=fits)


def _z_ms(fit, M, phi):
    return (fit.amplitude - M) / fit.amplitude_std, tb.wrap_phase(fit.phase - phi) / fit.phase_std


def test_multisine_own_value_weights_bias_the_amplitudes_and_the_noise_model_does_not(ms):
    n = ms["M"].numel()
    za_own, _ = _z_ms(ms["fits"]["own"], ms["M"], ms["phi"])
    za, zp = _z_ms(ms["fits"]["model"], ms["M"], ms["phi"])
    za_true, _ = _z_ms(ms["fits"]["true"], ms["M"], ms["phi"])
    assert all(bool(f.converged.all()) for f in ms["fits"].values())
    assert float(za_own.mean()) < -0.15
    assert abs(float(za.mean())) < 3 / math.sqrt(n) and abs(float(zp.mean())) < 3 / math.sqrt(n)
    assert abs(float((za - za_true).mean())) < 0.05  # as good as the true expected charge
    assert 0.85 <= float(za.square().mean().sqrt()) <= 1.15 and 0.85 <= float(zp.square().mean().sqrt()) <= 1.15
    # the noise std reported is the model's (power-1 units), close to the true one's
    torch.testing.assert_close(ms["fits"]["model"].noise_std, ms["fits"]["true"].noise_std, rtol=0.02, atol=0)


def test_multisine_noise_model_batch_equals_single_items(ms):
    one = fit_multisine(ms["img"][3], ms["psf"], ms["win"], MS_OM, noise=CAMERA.noise, power=ms["pw"],
                        amplitude_guess=ms["M"][3], phase_guess=ms["phi"][3], n_starts=0, n_refine=1)
    np.testing.assert_allclose(one.amplitude.numpy(), ms["fits"]["model"].amplitude[3].numpy(), rtol=1e-7)
    np.testing.assert_allclose(one.amplitude_std.numpy(), ms["fits"]["model"].amplitude_std[3].numpy(), rtol=1e-6)


def test_multisine_noise_and_power_are_checked(ms):
    args = (ms["img"][:2], ms["psf"], ms["win"], MS_OM)
    with pytest.raises(InputTypeError, match="noise"):
        fit_multisine(*args, noise=6.0)
    with pytest.raises(ParameterError, match="power"):
        fit_multisine(*args, power=ms["pw"])  # without noise
    with pytest.raises(ShapeError, match="power"):
        fit_multisine(*args, noise=CAMERA.noise, power=torch.ones(3, dtype=F64))
    with pytest.raises(ParameterError, match="power"):
        fit_multisine(*args, noise=CAMERA.noise, power=-ms["pw"])
    with pytest.raises(ParameterError, match="read_noise_e"):
        fit_multisine(*args, noise=CameraNoise(read_noise_e=0.0))


# --------------------------------------------------------------------------- direct
D_N = 20  # sweeps, one direct fit each (paired comparisons: the weights' effect is measured on the same data)
RATE, GAIN, DELAY = 2 * math.pi * 300.0, 4.0, 30e-6


@pytest.fixture(scope="module")
def direct():
    """A first-order plant swept at 4 frequencies (2 exposures each, peak 100 e-), ``D_N`` noisy
    sweeps, each fitted with the three weights: the gain's error over its std per fit."""
    size = 14
    om = 2 * math.pi * np.geomspace(80.0, 900.0, 4)
    h = GAIN / (1 + 1j * om / RATE) * np.exp(-1j * om * DELAY)
    A = 3.0 / np.abs(h)
    F = om.size
    win = tb.ExposureWindow(torch.tensor([[0.7 / w] * 2 for w in om], dtype=F64),
                            torch.tensor([[fr * 2 * math.pi / w for fr in (0.3, 0.8)] for w in om], dtype=F64))
    c = torch.full((F, 2), (size - 1) / 2, dtype=F64)
    cov = (1.6**2 * torch.eye(2, dtype=F64)).expand(F, 2, 2)
    traj = tb.Sinusoid((torch.tensor(np.abs(h) * A, dtype=F64)[:, None] * torch.tensor([1.0, 0.0], dtype=F64))[:, None],
                       torch.tensor(np.angle(h), dtype=F64)[:, None, None].expand(F, 1, 2), torch.tensor(om, dtype=F64)[:, None])
    unit = tb.render_blur(traj, tb.GaussianPSF(c[:, None], cov[:, None], (1.0 / win.duration.amax(-1))[:, None]), win,
                          height=size, width=size)
    k = 100.0 / unit.amax((-1, -2, -3))
    expected = unit * k[:, None, None, None]
    psf = tb.GaussianPSF(c, cov, k / win.duration.amax(-1))
    start = fit_transfer_function(FrequencyResponse(om, h), n_poles=1, n_zeros=0, delay_s=None, weights="uniform")
    z = {"own": [], "model": [], "true": []}
    fits = []
    for i in range(D_N):
        e = _electrons(expected, 100 + i)
        for name, kw in (("own", dict(noise_std=CAMERA.noise.std(e))), ("model", dict(noise=CAMERA.noise)),
                         ("true", dict(noise_std=CAMERA.noise.std(expected)))):
            d = fit_direct(e, psf, win, torch.tensor(om), torch.tensor(A), start, **kw)
            j = d.param_names.index("gain")
            z[name].append((d.params[j] - GAIN) / d.std[j])
            fits.append(d)
    return dict(z={k: np.asarray(v) for k, v in z.items()}, fits=fits, args=(e, psf, win, torch.tensor(om), torch.tensor(A), start))


def test_direct_own_value_weights_bias_the_gain_and_the_noise_model_does_not(direct):
    z = direct["z"]
    assert all(f.converged for f in direct["fits"])
    assert float(np.mean(z["own"] - z["model"])) < -0.15  # the same sweeps: the own values' weights pull the gain low
    assert float(np.mean(z["own"])) < 0
    assert abs(float(np.mean(z["model"]))) < 3 / math.sqrt(D_N)
    assert abs(float(np.mean(z["model"] - z["true"]))) < 0.05  # as good as the true expected charge
    model_fits = direct["fits"][1::3]
    assert not any(f.noise_estimated for f in model_fits)
    assert 0.85 < float(np.mean([f.reduced_chi2 for f in model_fits])) < 1.15


def test_direct_noise_is_checked_and_noise_std_wins(direct):
    args = direct["args"]
    with pytest.raises(InputTypeError, match="noise"):
        fit_direct(*args, noise=6.0)
    with pytest.raises(ParameterError, match="read_noise_e"):
        fit_direct(*args, noise=CameraNoise(read_noise_e=0.0))
    sig = CAMERA.noise.std(args[0])
    a = fit_direct(*args, noise_std=sig, noise=CAMERA.noise)  # noise_std given: one pass with it
    b = fit_direct(*args, noise_std=sig)
    np.testing.assert_allclose(a.params, b.params, rtol=1e-12)


# --------------------------------------------------------------------------- fit.loss with the multisine plan
@pytest.mark.parametrize("loss", ["l1", "poisson"])
def test_fit_loss_other_than_l2_is_refused_with_the_multisine_plan(loss):
    with pytest.raises(ConfigError, match="fit.loss"):
        load_config(None, overrides=["excitation.kind=multisine", f"fit.loss={loss}"])
    assert load_config(None, overrides=["excitation.kind=multisine", "fit.loss=l2"]).fit.loss == "l2"
    assert load_config(None, overrides=[f"fit.loss={loss}"]).fit.loss == loss  # the sine sweep uses it


def test_the_direct_model_says_fit_loss_is_not_applied_to_it():
    """model.direct with fit.loss=l1: the direct fit is l2; the log says so, naming fit.loss."""
    from torchblur.identify.model import fit_direct_model
    from torchblur.identify.record import collect_log

    psf = tb.GaussianPSF(torch.tensor([2.0, 2.0], dtype=F64), torch.eye(2, dtype=F64), torch.tensor(1.0, dtype=F64))
    args = (torch.zeros(1, 1, 5, 5, dtype=F64), tb.ExposureWindow(torch.zeros(1, 1, dtype=F64), torch.ones(1, 1, dtype=F64)),
            torch.ones(1, dtype=F64), [1.0], psf, torch.ones(1, dtype=F64), CAMERA.noise, None, None)
    for loss, warned in (("l1", True), ("l2", False)):
        cfg = load_config(None, overrides=[f"fit.loss={loss}"])
        with collect_log() as log:
            assert fit_direct_model(cfg, None, *args, (1.0, 0.0)) is None  # no start model: the fit fails, logged
        assert any("fit.loss=l1" in m and "direct" in m for m in log) == warned
        assert any("direct: fit failed" in m for m in log)
