"""The camera's noise (issue 15): one noise model in electrons (CameraNoise), and every loss of
the sinusoid fit a likelihood of it, with a std that holds.

Monte Carlo on small simulated problems: frames from CameraModel (shot noise, read noise,
rounding to whole ADU), turned back into electrons; each loss's reported std against its actual
error; the losses against each other on the same images; the shifted Poisson unbiased under read
noise; and the identification's side: linf refused by name, `torchblur fit ... fit.loss=l1`
finite and in agreement with l2.
"""
import json
import math

import numpy as np
import pytest
import torch

import torchblur as tb
from torchblur.design.windows import dual_exposure_windows
from torchblur.errors import ConfigError, InputTypeError, ParameterError
from torchblur.losses import covariance_factor, gauss_newton_terms, image_loss, loss_weight
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur import cli
from torchblur.config import load_config
from torchblur.render.camera import CameraModel, CameraNoise, camera_noise_std
from torchblur.sysid.frequency_response import FrequencyResponse

F64 = torch.float64
H, W = 20, 24
N = 240  # Monte-Carlo items: the rms of err/std is within ~5% of its value (1/sqrt(2N))


def _scene(n, seed, peak_e=300.0):
    """Expected electrons ``[n, 2, H, W]`` of a spot moving along x (two exposures), with the
    PSF (amplitude in electrons per second), windows, omega and the truth (M px, phi rad)."""
    g = torch.Generator().manual_seed(seed)
    om = 2 * math.pi * (50 + 300 * torch.rand(n, generator=g, dtype=F64))
    M = 2.5 + 1.5 * torch.rand(n, generator=g, dtype=F64)
    phi = (2 * torch.rand(n, generator=g, dtype=F64) - 1) * math.pi
    win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=2 * math.pi * torch.rand(n, generator=g, dtype=F64))
    psf = tb.GaussianPSF.isotropic(torch.tensor([11.5, 9.5], dtype=F64).expand(n, 2), torch.full((n,), 1.6, dtype=F64))
    amp = torch.zeros(n, 2, dtype=F64)
    amp[:, 0] = M
    traj = tb.Sinusoid(amp[:, None], torch.stack([phi, phi], -1)[:, None], om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=H, width=W)
    k = peak_e / clean.amax((-1, -2, -3))
    return clean * k[:, None, None, None], tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * k), win, om, M, phi


CAMERA = CameraModel(read_noise_e=6.0, gain_e_per_adu=2.0, dark_level_adu=100.0, bit_depth=16, full_well_e=1e6)


@pytest.fixture(scope="module")
def mc():
    """One Monte-Carlo set: the frames in electrons, the true per-pixel std, and a fit per loss."""
    expected, psf, win, om, M, phi = _scene(N, 0)
    noise = CAMERA.noise
    img = noise.to_electrons(CAMERA.expose(expected, generator=torch.Generator().manual_seed(7)))
    sig = noise.std(expected)  # the weights from the expected charge: no correlation with the noise
    fits = {loss: fit_sinusoid(img, psf, win, om, loss=loss, noise_std=sig, noise=noise) for loss in ("l2", "poisson", "l1")}
    return dict(img=img, expected=expected, psf=psf, win=win, om=om, M=M, phi=phi, noise=noise, fits=fits)


def _z(fit, M, phi):
    return (fit.amplitude - M) / fit.amplitude_std, tb.wrap_phase(fit.phase - phi) / fit.phase_std


# --------------------------------------------------------------------------- the noise model


def test_camera_noise_std_is_the_variance_of_simulated_frames():
    expected = torch.tensor([0.0, 50.0, 800.0], dtype=F64)[:, None, None].expand(3, 100, 100)
    noise = CAMERA.noise
    e = noise.to_electrons(CAMERA.expose(expected, generator=torch.Generator().manual_seed(1)))
    var = e.var((-1, -2))
    want = noise.std(expected[:, 0, 0]) ** 2  # shot + read noise + rounding (gain^2 / 12), electrons^2
    assert torch.allclose(var, want, rtol=0.05), (var, want)
    torch.testing.assert_close(e.mean((-1, -2)), expected[:, 0, 0], atol=0.5, rtol=0.01)


def test_camera_noise_fields_and_methods():
    noise = CameraNoise(gain_e_per_adu=2.0, offset_adu=100.0, read_noise_e=3.0)
    e = torch.tensor([-4.0, 0.0, 16.0])
    torch.testing.assert_close(noise.std(e), camera_noise_std(e, 3.0))
    torch.testing.assert_close(noise.std(e), torch.tensor([3.0, 3.0, 5.0]))
    assert noise.poisson_shift_e == 9.0
    torch.testing.assert_close(noise.to_electrons(torch.tensor([100.0, 110.0])), torch.tensor([0.0, 20.0]))
    cam = CameraModel(read_noise_e=4.0, gain_e_per_adu=3.0, dark_level_adu=50.0)
    assert cam.noise == CameraNoise(3.0, 50.0, math.sqrt(16.0 + 9.0 / 12))
    assert CameraModel(read_noise_e=4.0, quantize=False).noise.read_noise_e == 4.0
    for kw, name in ((dict(gain_e_per_adu=0.0), "gain_e_per_adu"), (dict(read_noise_e=-1.0), "read_noise_e"),
                     (dict(offset_adu=float("nan")), "offset_adu")):
        with pytest.raises(ParameterError, match=name):
            CameraNoise(**kw)


def test_loss_weights_and_covariance_factors():
    inv_var = torch.tensor([0.25, 4.0, 0.0], dtype=F64)
    torch.testing.assert_close(loss_weight("l2", inv_var), inv_var)
    torch.testing.assert_close(loss_weight("l1", inv_var), torch.tensor([0.5, 2.0, 0.0], dtype=F64))
    torch.testing.assert_close(loss_weight("poisson", inv_var), torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    assert covariance_factor("l2") == covariance_factor("poisson") == 1.0
    assert covariance_factor("l1") == pytest.approx(math.pi / 2)
    assert math.isnan(covariance_factor("linf"))
    with pytest.raises(ParameterError, match="loss"):
        loss_weight("l3", inv_var)


def test_shifted_poisson_deviance_and_its_gauss_newton_terms():
    model = torch.tensor([[0.0, 5.0, 40.0]], dtype=F64)
    data = torch.tensor([[-3.0, 7.0, 35.0]], dtype=F64)  # dark-subtracted: read noise makes it negative
    s = 9.0
    y, lam = (data + s).clamp_min(0), model + s
    want = 2 * (y * torch.log(y / lam) - (y - lam)).sum(-1)
    torch.testing.assert_close(image_loss(model, data, loss="poisson", shift=s), want)
    curv, grad = gauss_newton_terms(model, data, loss="poisson", weight=None, shift=s)
    torch.testing.assert_close(curv, 1 / lam)  # the Fisher weights: 1 / (model + read_noise^2)
    torch.testing.assert_close(grad, (data - model) / lam)
    # the l1 step: Newton's on the expected cost (curvature 2 n w^2 / (pi C)), gradient w sign(r)
    w = torch.tensor([[1.0, 0.5, 0.0]], dtype=F64)
    curv, grad = gauss_newton_terms(model, data, loss="l1", weight=w)
    C = float((w * (data - model).abs()).sum())
    torch.testing.assert_close(curv, 2 * w * w * 2 / (math.pi * C))
    torch.testing.assert_close(grad, w * torch.sign(data - model))


# --------------------------------------------------------------------------- each loss's std holds


@pytest.mark.parametrize("loss", ["l2", "poisson", "l1"])
def test_reported_std_is_calibrated_by_monte_carlo(mc, loss):
    fit = mc["fits"][loss]
    assert bool((fit.status == 0).all()), torch.bincount(fit.status)
    for z in _z(fit, mc["M"], mc["phi"]):
        rms = float(z.square().mean().sqrt())
        assert 0.8 <= rms <= 1.25, (loss, rms)


def test_every_likelihood_loss_reports_its_fit_quality(mc):
    for loss in ("l2", "poisson", "l1"):
        red = mc["fits"][loss].reduced_chi2
        assert 0.9 < float(red.median()) < 1.1 and float(red.max()) < 1.3, loss  # the model is right: about 1


def test_std_ratios_to_l2_are_the_estimators_efficiencies(mc):
    l2, po, l1 = (mc["fits"][k] for k in ("l2", "poisson", "l1"))
    for name in ("amplitude_std", "phase_std"):
        r_po = (getattr(po, name) / getattr(l2, name)).median()
        r_l1 = (getattr(l1, name) / getattr(l2, name)).median()
        assert 0.95 < float(r_po) < 1.05  # both maximum likelihood of the same noise
        assert abs(float(r_l1) - math.sqrt(math.pi / 2)) < 0.03  # least absolute deviations: sqrt(pi / 2)


def test_the_three_losses_agree_on_the_same_images(mc):
    l2 = mc["fits"]["l2"]
    for loss in ("poisson", "l1"):
        f = mc["fits"][loss]
        dz_a = (f.amplitude - l2.amplitude) / l2.amplitude_std
        dz_p = tb.wrap_phase(f.phase - l2.phase) / l2.phase_std
        assert float(dz_a.abs().max()) < 4 and float(dz_p.abs().max()) < 4, loss


def test_poisson_with_read_noise_is_unbiased_and_the_unshifted_one_is_not(mc):
    # the noise model alone: poisson weighs by its own model, so the weights do not see the noise
    fit = fit_sinusoid(mc["img"], mc["psf"], mc["win"], mc["om"], loss="poisson", noise=mc["noise"])
    za, zp = _z(fit, mc["M"], mc["phi"])
    assert abs(float(za.mean())) < 3 / math.sqrt(N) and abs(float(zp.mean())) < 3 / math.sqrt(N)
    assert 0.8 <= float(za.square().mean().sqrt()) <= 1.25
    # without the shift the dark-subtracted read noise, clamped at 0, is taken for light: its stds do not hold
    k = slice(0, 60)
    plain = fit_sinusoid(mc["img"][k], mc["psf"][k], mc["win"][k], mc["om"][k], loss="poisson")
    za, _ = _z(plain, mc["M"][k], mc["phi"][k])
    assert float(za.square().mean().sqrt()) > 2


def test_noise_argument_is_checked_and_sets_the_weights(mc):
    with pytest.raises(InputTypeError, match="noise"):
        fit_sinusoid(mc["img"][:2], mc["psf"][:2], mc["win"][:2], mc["om"][:2], noise=6.0)
    # noise alone: weights from the fitted model's expected charge, as good as the true one's
    k = slice(0, 8)
    a = fit_sinusoid(mc["img"][k], mc["psf"][k], mc["win"][k], mc["om"][k], noise=mc["noise"])
    b = fit_sinusoid(mc["img"][k], mc["psf"][k], mc["win"][k], mc["om"][k], noise_std=mc["noise"].std(mc["expected"][k]))
    assert float(((a.amplitude - b.amplitude) / b.amplitude_std).abs().max()) < 0.05
    torch.testing.assert_close(a.amplitude_std, b.amplitude_std, rtol=0.01, atol=0)


def test_weights_from_the_pixels_own_values_bias_the_amplitude_and_the_model_weights_do_not(mc):
    """A pixel weighed by its own noisy value counts less when it fluctuates up: the amplitude
    comes out low by about 0.3 of its std here (peak 300 e-, read noise 6 e-). Unseen in one fit,
    it puts an estimate averaged over thousands of fits (a deformable mirror's DC gain) several of
    its stds off. The noise model alone (a second pass weighted by the first fit's model) is
    unbiased: within 3 / sqrt(N) of 0, like weights from the true expected charge."""
    own = fit_sinusoid(mc["img"], mc["psf"], mc["win"], mc["om"], noise_std=mc["noise"].std(mc["img"]))
    za_own, _ = _z(own, mc["M"], mc["phi"])
    za, _ = _z(mc["fits"]["l2"], mc["M"], mc["phi"])  # weights from the true expected charge
    two = fit_sinusoid(mc["img"], mc["psf"], mc["win"], mc["om"], noise=mc["noise"])
    za_two, zp_two = _z(two, mc["M"], mc["phi"])
    assert float(za_own.mean()) < -0.15
    assert abs(float(za_two.mean())) < 3 / math.sqrt(N) and abs(float(zp_two.mean())) < 3 / math.sqrt(N)
    assert abs(float(za_two.mean() - za.mean())) < 0.05
    assert 0.85 <= float(za_two.square().mean().sqrt()) <= 1.15


# --------------------------------------------------------------------------- the identification


def test_linf_is_refused_for_an_identification_with_a_message_naming_fit_loss(tmp_path, capsys):
    with pytest.raises(ConfigError, match="fit.loss") as e:
        load_config(None, ["fit.loss=linf", "fit.optimizer=adam"])
    assert "likelihood" in str(e.value) and "l2" in str(e.value)
    assert cli.main(["identify", "--out", str(tmp_path / "r"), "--quiet", "fit.loss=linf", "fit.optimizer=lbfgs"]) == 2
    err = capsys.readouterr().err
    assert "fit.loss" in err and "linf" in err and len(err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def small_run(small_quiet_run):
    """identify --quiet sweep.freq_hz=[20,150,300,600], exit 0: the session's shared run (tests/conftest.py)."""
    return small_quiet_run[0]


@pytest.mark.parametrize("loss", ["l1", "poisson"])
def test_torchblur_fit_with_another_loss_is_finite_and_agrees_with_l2(small_run, tmp_path, loss, capsys):
    out = tmp_path / loss
    assert cli.main(["fit", str(small_run), "--out", str(out), "--quiet", f"fit.loss={loss}"]) == 0
    capsys.readouterr()
    ref, got = FrequencyResponse.from_json(small_run / "frf.json"), FrequencyResponse.from_json(out / "frf.json")
    assert np.isfinite(got.response).all() and np.isfinite(got.cov).all()
    s0 = np.sqrt(ref.cov[..., 0, 0]).reshape(-1), np.sqrt(ref.cov[..., 1, 1]).reshape(-1)
    h0, h1 = ref.response.reshape(-1), got.response.reshape(-1)
    assert (np.abs(np.abs(h1) - np.abs(h0)) / s0[0]).max() < 4
    assert (np.abs(np.angle(h1 * np.conj(h0))) / s0[1]).max() < 4
    ratio = np.sqrt(got.cov[..., 0, 0]).reshape(-1) / s0[0]
    assert np.allclose(ratio, math.sqrt(math.pi / 2) if loss == "l1" else 1.0, rtol=0.1), ratio
    assert json.loads((out / "source.json").read_text())["overrides"] == [f"fit.loss={loss}"]
