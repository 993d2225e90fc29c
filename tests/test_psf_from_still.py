"""psf_from_still: the PSF identify should use, from still frames (issue 15)."""
import math

import numpy as np
import pytest
import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.image.psf_from_still import CHI2_Z, StillPSF, psf_from_still
from torchblur.render.blur import render_blur
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

H, W = 40, 48
EXPOSURE = 2e-3
BG, READ = 20.0, 3.0


def _camera(clean: np.ndarray, n: int, seed: int) -> torch.Tensor:
    """``n`` frames (electrons) of a noise-free image: Poisson(clean + BG) + Normal(0, READ)."""
    rng = np.random.default_rng(seed)
    f = rng.poisson(np.broadcast_to(np.clip(clean, 0, None) + BG, (n,) + clean.shape)).astype(float)
    return torch.as_tensor(f + READ * rng.standard_normal(f.shape))


def _gaussian_still(amplitude=1.5e6):
    """A tilted Gaussian still (point-sampled pixel centres, torchblur's renderer) and its PSF."""
    psf = GaussianPSF.from_axes(torch.tensor([23.4, 19.7], dtype=torch.float64), 2.1, 1.5, 0.4, amplitude=amplitude)
    zero = torch.zeros(2, dtype=torch.float64)
    clean = render_blur(Sinusoid(zero, zero, 1.0), psf, ExposureWindow(0.0, EXPOSURE), height=H, width=W)
    return clean.numpy(), psf


@pytest.fixture(scope="module")
def gaussian_case():
    clean, psf = _gaussian_still()
    return clean, psf, _camera(clean, 16, seed=3)


@pytest.fixture(scope="module")
def hcipy_case():
    pytest.importorskip("hcipy")
    import hcipy_frames as hf

    spot = hf.HcipySpot(hf.SpotOptics(), (23.3, 19.6), H, W)
    clean = spot.still(3000.0 / EXPOSURE, EXPOSURE)
    return clean, _camera(clean, 32, seed=5), _camera(clean, 32, seed=6)


def test_gaussian_still_chooses_the_gaussian(gaussian_case):
    clean, truth, frames = gaussian_case
    res = psf_from_still(frames, EXPOSURE)
    assert isinstance(res, StillPSF)
    assert res.kind == "gaussian" and isinstance(res.psf, GaussianPSF)
    assert float(res.chi2_gaussian) <= res.chi2_threshold
    assert abs(float(res.chi2_gaussian) - 1) < CHI2_Z * math.sqrt(2 / (int(res.support.sum()) - 6))
    assert "gaussian" in res.reason and "chi2" in res.reason
    # point-sampled pixels, the pixel model fit_sinusoid uses: the truth within 4 std
    fit = res.gaussian
    assert (fit.psf.center - truth.center).abs().max() < 4 * fit.center_std.max()
    assert (fit.psf.cov - truth.cov).abs().max() < 4 * fit.cov_std.max()
    assert abs(float(fit.psf.amplitude) - float(truth.amplitude)) < 4 * float(fit.amplitude_std)
    assert abs(float(res.background) - BG) < 0.1


def test_hcipy_still_chooses_the_kernel(hcipy_case):
    _, frames, _ = hcipy_case
    res = psf_from_still(frames, EXPOSURE)
    assert res.kind == "kernel" and isinstance(res.psf, KernelPSF)
    assert float(res.chi2_gaussian) > 5 * res.chi2_threshold  # Airy rings and aberrations: far from a Gaussian
    assert res.psf.frame_shape == (H, W) and isinstance(res.touches_edge, bool)  # faint rings may reach the border
    assert 0.7 < float(res.chi2_kernel) < 1.3  # the kernel leaves out nothing but noise


def test_kernel_reproduces_the_still_to_its_noise(hcipy_case):
    clean, frames, other = hcipy_case
    res = psf_from_still(frames, EXPOSURE, kind="kernel")
    model = res.kernel.kernel * EXPOSURE  # the still it predicts (background removed)
    sup = res.support
    # against the noise-free truth: the averaged still's noise, nothing more
    chi2_truth = ((model - torch.as_tensor(clean)) / res.noise_std)[sup].square().mean()
    assert 0.8 < float(chi2_truth) < 1.25
    # against an independent set of still frames: twice that noise
    indep = other.mean(0) - res.background
    chi2_indep = ((model - indep) / res.noise_std)[sup].square().mean() / 2
    assert 0.8 < float(chi2_indep) < 1.25
    # intensity per second: the kernel's light is the still's over its exposure, less the faint
    # Airy wings beyond the support (~0.2 e-/px here), which go into the background level
    assert abs(float(res.kernel.kernel.sum()) * EXPOSURE / float(torch.as_tensor(clean).sum()) - 1) < 0.015


def test_noise_model_is_the_camera(hcipy_case):
    _, frames, _ = hcipy_case
    res = psf_from_still(frames, EXPOSURE)
    c0, c1 = res.noise_model
    assert abs(c1 - 1) < 0.1  # electrons: shot noise variance = value
    assert abs(c0 - READ**2) < 2.5
    raw = torch.full((2, H, W), 100.0, dtype=torch.float64)
    assert res.frame_noise_std(raw).shape == (2, H, W)
    assert torch.allclose(res.frame_noise_std(raw), torch.tensor(math.sqrt(c0 + c1 * 100.0), dtype=torch.float64))


def test_forced_kinds_and_given_noise(gaussian_case):
    clean, _, frames = gaussian_case
    k = psf_from_still(frames, EXPOSURE, kind="kernel")
    g = psf_from_still(frames, EXPOSURE, kind="gaussian")
    assert k.kind == "kernel" and g.kind == "gaussian" and "asked for" in k.reason
    assert float(k.chi2_gaussian) == pytest.approx(float(g.chi2_gaussian))
    sigma = torch.as_tensor(np.sqrt(READ**2 + clean + BG))
    given = psf_from_still(frames, EXPOSURE, noise_std=sigma)
    assert given.noise_model is None and given.kind == "gaussian"
    assert torch.allclose(given.noise_std, sigma / 4)
    assert given.frame_noise_std(frames[:2]).shape == (2, H, W)


def test_kernel_noise_factor(gaussian_case):
    """sqrt(1 + sum_e T_e / (N T_still)) for the kernel, 1 for a Gaussian, one per item."""
    _, _, frames = gaussian_case
    k = psf_from_still(frames, EXPOSURE, kind="kernel")
    f = k.kernel_noise_factor(torch.tensor([[1e-3, 3e-3], [16e-3, 16e-3]]))
    assert f.shape == (2,)
    assert torch.allclose(f, torch.tensor([math.sqrt(1 + 4e-3 / (16 * EXPOSURE)), math.sqrt(2.0)], dtype=f.dtype))
    assert float(k.kernel_noise_factor(EXPOSURE)) == pytest.approx(math.sqrt(1 + 1 / 16))
    g = psf_from_still(frames, EXPOSURE, kind="gaussian")
    assert float(g.kernel_noise_factor([1e-3, 3e-3])) == 1.0
    with pytest.raises(ParameterError, match="exposures_s"):
        k.kernel_noise_factor(-1.0)


def test_given_background_and_a_spot_that_fills_the_frame(gaussian_case):
    _, truth, frames = gaussian_case
    given = psf_from_still(frames, EXPOSURE, background=BG)
    assert float(given.background) == BG and given.kind == "gaussian"
    wide = GaussianPSF.isotropic(torch.tensor([23.0, 19.0], dtype=torch.float64), torch.tensor(7.0, dtype=torch.float64), 5e6)
    zero = torch.zeros(2, dtype=torch.float64)
    clean = render_blur(Sinusoid(zero, zero, 1.0), wide, ExposureWindow(0.0, EXPOSURE), height=H, width=W).numpy()
    full = _camera(clean, 8, seed=9)
    with pytest.raises(ParameterError, match="background"):
        psf_from_still(full, EXPOSURE)
    res = psf_from_still(full, EXPOSURE, background=BG)
    assert res.touches_edge and res.kind == "gaussian"
    assert abs(float(res.gaussian.psf.cov[0, 0]) - 49.0) < 4 * float(res.gaussian.cov_std[0, 0])


def test_no_gaussian_fits_a_spot_wider_than_the_frame():
    wide = GaussianPSF.isotropic(torch.tensor([23.0, 19.0], dtype=torch.float64), torch.tensor(12.0, dtype=torch.float64), 5e5)
    zero = torch.zeros(2, dtype=torch.float64)
    clean = render_blur(Sinusoid(zero, zero, 1.0), wide, ExposureWindow(0.0, EXPOSURE), height=H, width=W).numpy()
    full = _camera(clean, 8, seed=9)
    res = psf_from_still(full, EXPOSURE, background=BG)
    if res.gaussian is None:  # the fit failed: the kernel, and the reason says so
        assert res.kind == "kernel" and math.isinf(float(res.chi2_gaussian)) and "Gaussian fit failed" in res.reason
        with pytest.raises(ParameterError, match="kind"):
            psf_from_still(full, EXPOSURE, background=BG, kind="gaussian")
    else:
        assert res.kind == "gaussian"


def test_a_hot_pixel_is_not_part_of_the_kernel(gaussian_case):
    """A hot pixel away from the spot is significant but not connected to it: weight 0."""
    _, _, frames = gaussian_case
    hot = frames.clone()
    hot[:, 4, 5] += 500.0
    res = psf_from_still(hot, EXPOSURE)
    assert not bool(res.support[4, 5]) and float(res.taper[4, 5]) == 0.0 and float(res.kernel.kernel[4, 5]) == 0.0
    assert res.kind == "gaussian"


def test_one_frame_and_dtype(gaussian_case):
    _, _, frames = gaussian_case
    one = psf_from_still(frames[0].float(), EXPOSURE)
    assert one.n_frames == 1 and one.noise_model is None
    assert one.kernel.kernel.dtype == torch.float32 and one.gaussian.psf.cov.dtype == torch.float32
    assert abs(float(one.frame_noise[0, 0]) - math.sqrt(READ**2 + BG)) < 0.5


def test_kernel_fits_a_blur_like_the_truth(gaussian_case):
    """The kernel renders the blur the true PSF renders, within the kernel's noise."""
    clean, truth, frames = gaussian_case
    res = psf_from_still(frames, EXPOSURE, kind="kernel")
    traj = Sinusoid(torch.tensor([5.0, 2.0], dtype=torch.float64), torch.tensor([0.3, 0.3], dtype=torch.float64), 2 * math.pi * 50)
    win = ExposureWindow(1e-3, 6e-3)
    a = render_blur(traj, res.kernel, win, height=H, width=W)
    b = render_blur(traj, truth, win, height=H, width=W)
    assert float((a - b).abs().max()) < 0.02 * float(b.max())


@pytest.mark.parametrize("call, exc", [
    (lambda f: psf_from_still(f[0, 0], EXPOSURE), ShapeError),
    (lambda f: psf_from_still(f[None], EXPOSURE), ShapeError),
    (lambda f: psf_from_still(f[:, :3, :3], EXPOSURE), ShapeError),
    (lambda f: psf_from_still(f.to(torch.complex128), EXPOSURE), InputTypeError),
    (lambda f: psf_from_still(f > 0, EXPOSURE), InputTypeError),
    (lambda f: psf_from_still(f, 0.0), ParameterError),
    (lambda f: psf_from_still(f, [1e-3, 2e-3]), ShapeError),
    (lambda f: psf_from_still(f, EXPOSURE, kind="airy"), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, noise_std=torch.ones(3, 3)), ShapeError),
    (lambda f: psf_from_still(f, EXPOSURE, noise_std=-1.0), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, margin_px=-1), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, taper_px=1.5), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, support_sigma=0.0), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, background=float("nan")), ParameterError),
    (lambda f: psf_from_still(BG + READ * torch.randn(4, H, W, generator=torch.Generator().manual_seed(0), dtype=torch.float64),
                              EXPOSURE), ParameterError),
    (lambda f: psf_from_still(f, EXPOSURE, background="dark"), InputTypeError),
    (lambda f: psf_from_still(torch.where(f > 1e9, f, f.new_tensor(float("nan"))), EXPOSURE), ParameterError),
])
def test_bad_input_is_named(gaussian_case, call, exc):
    with pytest.raises(exc) as info:
        call(gaussian_case[2])
    msg = str(info.value)
    assert any(name in msg for name in ("still", "exposure_s", "kind", "noise_std", "margin_px", "taper_px", "support_sigma", "background"))


def test_the_dark_means_noise_enters_the_stills_noise():
    """identify subtracts a dark frame's mean (as many frames as the still) from every still
    frame: that mean's noise is common to the frames, so neither their scatter nor sqrt(N)
    sees it. Without ``dark_std`` the still's noise is understated (variance x2 where read
    noise dominates): the Gaussian that made the frames fails its own test and the kernel's
    light left out reads ~1.8; with it both are about 1 and the Gaussian is chosen."""
    clean, _ = _gaussian_still(amplitude=2e5)
    rng = np.random.default_rng(11)
    read = 5.0
    n = 16

    def frames(light):  # Poisson(light) + Normal(0, read), electrons, no offset
        return rng.poisson(np.broadcast_to(np.clip(light, 0, None), (n,) + light.shape)).astype(float) + read * rng.standard_normal((n,) + light.shape)

    dark_mean = frames(np.zeros_like(clean)).mean(0)
    still = torch.as_tensor(frames(clean) - dark_mean)
    one_frame = torch.as_tensor(np.sqrt(read ** 2 + np.clip(clean, 0, None)))  # one frame's noise (the camera model)
    without = psf_from_still(still, EXPOSURE, one_frame, background=0.0)
    with_dark = psf_from_still(still, EXPOSURE, one_frame, background=0.0, dark_std=read / math.sqrt(n))
    assert without.kind == "kernel" and float(without.chi2_kernel) > 1.5  # 1.70-1.87 over seeds 11-13
    assert with_dark.kind == "gaussian" and 0.8 < float(with_dark.chi2_kernel) < 1.1  # 0.89-0.94: the taper keeps a little noise
    assert torch.allclose(with_dark.noise_std, (one_frame ** 2 / n + read ** 2 / n).sqrt())


def test_dark_std_is_checked():
    clean, _ = _gaussian_still()
    frames = _camera(clean, 4, seed=1)
    with pytest.raises(ParameterError, match="dark_std"):
        psf_from_still(frames, EXPOSURE, dark_std=-1.0)
    with pytest.raises(ShapeError, match="dark_std"):
        psf_from_still(frames, EXPOSURE, dark_std=torch.ones(3, 3))
