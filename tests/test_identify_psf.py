"""identify's PSF from the still frames (fit.psf = auto | kernel | gaussian): the config key, the
choice on a spot that is not a Gaussian, the kernel's std rule, the Gaussian-only stages."""
import math
import types

import numpy as np
import pytest
import torch

from torchblur.errors import ConfigError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.identify.calibration import calibrate
from torchblur.identify.record import collect_log
from torchblur.config import load_config
from torchblur.identify.run import identify
from torchblur.identify.sweep import inflate_std
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow
from torchblur.rig.factory import build_simulated_rig
from torchblur.rig.simulated import SimulatedRig
from reference import truth_errors

SHORT = ["sweep.freq_hz=[20,200,600]", "camera.height=40", "camera.width=40", "fit.axis=x", "seed=5"]




def airy_rig(cfg, lambda_over_d_px: float = 4.0):
    """The simulated rig of ``cfg`` whose spot is an Airy pattern (a circular aperture, the
    first dark ring at 1.22 ``lambda_over_d_px``; band-limited, so sampled exactly): every
    image it renders (still, pulse, sweep) is that pattern, of the rig's peak rate, at the
    rig's spot position, moved by the motion (a KernelPSF)."""
    rig = build_simulated_rig(cfg)
    H, W = rig.frame_shape

    def render(self, trajectory, psf, window, shape=None):
        y = torch.arange(H, dtype=torch.float64)[:, None] - psf.center[1]
        x = torch.arange(W, dtype=torch.float64)[None, :] - psf.center[0]
        v = math.pi * (x * x + y * y).sqrt().clamp_min(1e-12) / lambda_over_d_px
        airy = (2 * torch.special.bessel_j1(v) / v) ** 2  # peak 1
        return SimulatedRig._render(self, trajectory, KernelPSF(airy * psf.amplitude), window, shape)

    rig._render = types.MethodType(render, rig)
    return rig


@pytest.mark.parametrize("value", ["auto", "kernel", "gaussian"])
def test_fit_psf_accepts_its_kinds(value):
    assert load_config(None, [f"fit.psf={value}"]).fit.psf == value


def test_fit_psf_default_is_auto():
    assert load_config(None, []).fit.psf == "auto"


def test_fit_psf_is_checked_with_the_key_named():
    with pytest.raises(ConfigError, match="fit.psf") as err:
        load_config(None, ["fit.psf=airy"])
    assert "expected one of" in str(err.value)


@pytest.mark.parametrize("route", [["excitation.kind=multisine"], ["model.direct=true"],
                                   ["spots.rows=2", "spots.cols=2", "excitation.target_px=3"]])
def test_fit_psf_kernel_is_refused_nowhere(route):
    """issue 29: every route fits with the measured kernel (it was refused for these three)."""
    assert load_config(None, ["fit.psf=kernel"] + route).fit.psf == "kernel"


def test_inflate_std_scales_the_stds_and_keeps_the_correlations():
    g = torch.Generator().manual_seed(0)
    psf = GaussianPSF(torch.tensor([15.3, 14.7], dtype=torch.float64), 4.0 * torch.eye(2, dtype=torch.float64),
                      torch.tensor(3e5, dtype=torch.float64))
    from torchblur.render.blur import render_blur
    from torchblur.render.trajectory import Sinusoid
    om = torch.tensor([2 * math.pi * 50.0, 2 * math.pi * 80.0], dtype=torch.float64)
    win = ExposureWindow(torch.tensor([[1e-3, 1e-3], [2e-3, 2e-3]], dtype=torch.float64),
                         torch.tensor([[3e-3, 8e-3], [2e-3, 6e-3]], dtype=torch.float64))
    img = torch.stack([render_blur(Sinusoid(torch.tensor([5.0, 0.0], dtype=torch.float64), torch.tensor([0.4, 0.0], dtype=torch.float64),
                                            om[b]), psf, ExposureWindow(win.start[b], win.duration[b]), height=30, width=30)
                       for b in range(2)])
    img = img + 10 * torch.randn(img.shape, generator=g, dtype=torch.float64)
    fit = fit_sinusoid(img, psf, win, om, axes="x", noise_std=10.0)
    factor = torch.tensor([1.5, 2.0], dtype=torch.float64)
    big = inflate_std(fit, factor)
    torch.testing.assert_close(big.amplitude_std, fit.amplitude_std * factor)
    torch.testing.assert_close(big.phase_std, fit.phase_std * factor)
    torch.testing.assert_close(big.covariance, fit.covariance * factor[:, None, None] ** 2)
    torch.testing.assert_close(big.amplitude, fit.amplitude)
    # the correlation the FRF's covariance is built from does not change
    i_m, i_p = 0, 1  # (amplitude, phase) of the one fitted axis, as assemble_siso reads them
    corr = lambda f: f.covariance[:, i_m, i_p] / (f.amplitude_std * f.phase_std)  # noqa: E731
    torch.testing.assert_close(corr(big), corr(fit))


@pytest.fixture(scope="module")
def airy_runs():
    out = {}
    for kind in ("auto", "gaussian"):
        cfg = load_config(None, SHORT + ["excitation.target_px=3", f"fit.psf={kind}"])
        out[kind] = identify(cfg, airy_rig(cfg), progress=False)
    return out


def test_identify_picks_the_kernel_on_a_spot_that_is_not_a_gaussian(airy_runs):
    res = airy_runs["auto"]
    assert res.frf.meta["psf"] == "kernel"
    assert any(line.startswith("psf: kernel: the Gaussian does not explain the still") for line in res.log)
    em, ep, z = truth_errors(res)
    assert res.fit.converged.all()
    assert em.max() < 0.01 and ep.max() < 1.0
    assert z.max() < 3  # honest: within its (kernel-noise inflated) std


def test_a_forced_gaussian_on_that_spot_is_worse(airy_runs):
    res = airy_runs["gaussian"]
    assert res.frf.meta["psf"] == "gaussian"
    em_k, ep_k, z_k = truth_errors(airy_runs["auto"])
    em_g, ep_g, z_g = truth_errors(res)
    # the model mismatch: every point many of its stds off (6.1-7.7 against the kernel's worst 2.2, with the
    # fitter's model weights; 6.9-9.0 against 1.8 with the pixels' own values: the noise of one realisation)
    assert z_g.min() > 5 and z_g.min() > 2.5 * z_k.max()
    assert em_g.max() > 4 * em_k.max() and ep_g.max() > 2 * ep_k.max()


def test_kernel_points_do_not_depend_on_the_chunking():
    # a kernel fit gives each point its own crop, rules and FFT grid (tests/test_kernel_batch.py):
    # chunks of 8 points or of one give the same values
    keys = ["sweep.freq_hz=[2,50,300,420,900]", "camera.height=40", "camera.width=40", "fit.axis=x", "fit.psf=kernel"]
    runs = [identify(load_config(None, keys + [f"fit.chunk_points={n}"]), progress=False) for n in (8, 1)]
    assert all(r.frf.meta["psf"] == "kernel" for r in runs)
    np.testing.assert_allclose(runs[0].frf.response, runs[1].frf.response, rtol=1e-12)
    np.testing.assert_allclose(runs[0].frf.magnitude_std, runs[1].frf.magnitude_std, rtol=1e-12)


def test_the_multisine_route_fits_with_the_kernel_the_calibration_chose():
    """issue 29: the multisine fit takes the still's choice (the kernel on an Airy spot), with the
    kernel's pixel variance for its covariance (the kernel's own noise, propagated); no stage is
    left on the Gaussian (no warning)."""
    from torchblur.identify.multisine import fit_psf, kernel_variance

    cfg = load_config(None, SHORT + ["excitation.kind=multisine"])
    with collect_log() as log:
        cal = calibrate(cfg, airy_rig(cfg))
    assert cal.still_psf.kind == "kernel" and isinstance(cal.still_psf.psf, KernelPSF)
    assert isinstance(cal.psf, GaussianPSF)  # the centre, peak rate and axis calibration still use it
    assert fit_psf(cal) is cal.still_psf.psf
    assert not any("warning" in line and "psf" in line for line in log)
    var = kernel_variance(cal)
    assert var.shape == cal.still_psf.psf.kernel.shape
    torch.testing.assert_close(var, (cal.still_psf.noise_std * cal.still_psf.taper / cal.still_psf.exposure_s) ** 2)
    assert bool((var[cal.still_psf.support] > 0).all()) and bool((var[cal.still_psf.taper == 0] == 0).all())


def test_many_spots_take_every_spot_kernel_when_a_gaussian_fails():
    """issue 29, many spots: psf_from_still on each spot's crop of the still; Airy spots fail the
    Gaussian test, so every spot is fitted with its measured kernel (crop frame, e-/s at power 1),
    and fit.psf=gaussian keeps the Gaussians."""
    from torchblur.identify.calibration import SpotKernels, spot_kernels
    from torchblur.image.spots import locate_spots
    from torchblur.render.camera import camera_noise_std

    H = W = 44
    g = torch.Generator().manual_seed(3)
    y = torch.arange(H, dtype=torch.float64)[:, None]
    x = torch.arange(W, dtype=torch.float64)[None, :]
    still = torch.zeros(H, W, dtype=torch.float64)
    for cx, cy in ((11.3, 10.8), (32.6, 11.2), (10.9, 32.4), (32.2, 33.1)):
        v = math.pi * ((x - cx) ** 2 + (y - cy) ** 2).sqrt().clamp_min(1e-12) / 3.0
        still = still + 3000 * (2 * torch.special.bessel_j1(v) / v) ** 2
    frames = still + (still + 9).sqrt() * torch.randn((8, H, W), generator=g, dtype=torch.float64)
    mean = frames.mean(0)
    spots = locate_spots(mean, exposure_s=1e-3, noise_std=camera_noise_std(float(mean.max()), 3.0) / 4, pitch_px=22.0, crop_px=22)
    assert len(spots) == 4
    cfg = types.SimpleNamespace(fit=types.SimpleNamespace(psf="auto", fit_background=False))
    with collect_log() as log:
        sk = spot_kernels(cfg, frames, 1e-3, 3.0, spots)
    assert isinstance(sk, SpotKernels) and sk.psf.kernel.shape == (4, 22, 22)
    assert any("spots psf: the measured kernel of every spot (4 of 4 spots' Gaussians do not explain" in line for line in log)
    # each kernel is its spot's crop of the still, per second: about the Airy peak rate at its centre
    assert float(sk.psf.kernel.amax((-1, -2)).min()) > 0.8 * 3000 / 1e-3
    assert float(sk.kernel_noise_factor(torch.tensor([1e-3, 2e-3]))) == pytest.approx(math.sqrt(1 + 3 / 8))
    cfg.fit.psf = "gaussian"
    assert spot_kernels(cfg, frames, 1e-3, 3.0, spots) is None
