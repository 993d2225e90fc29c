"""The DM spot fitter with each spot's measured PSF (issue 23): sinc^2 lenslet spots with a
crosstalk floor (tests/sinc_spots.py), fitted with the kernel psf_from_still chooses per spot."""
from __future__ import annotations

import math

import pytest
import torch

from sinc_spots import sinc2_case
from torchblur.dm.spot_fit import PerSpotPSF, fit_spot_problems
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.image.psf_from_still import psf_from_still
from torchblur.render.camera import camera_noise_std
from torchblur.render.psf import GaussianPSF, KernelPSF

MOTIONS = (0.5, 1.0, 2.0, 3.0)
N_EACH = 3  # points per motion size


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small FFT-path fits: a second OpenMP thread only adds overhead (25x slower at load 10 here)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def sinc():
    c = sinc2_case([m for m in MOTIONS for _ in range(N_EACH)], n_side=2, n_rows=1, n_still=64, seed=3)
    M = c["offset"].shape[0]
    still = [psf_from_still(c["still_crops"][:, m], c["still_s"], camera_noise_std(c["still_crops"][:, m].mean(0), 3.0), background=0.0)
             for m in range(M)]
    g = [s.gaussian.psf for s in still]
    c["gauss"] = GaussianPSF(torch.stack([p.center for p in g]), torch.stack([p.cov for p in g]), torch.stack([p.amplitude for p in g]))
    c["kernel"] = KernelPSF(torch.stack([s.kernel.kernel for s in still]))
    c["still_psf"] = still
    c["factor"] = still[0].kernel_noise_factor(c["window"].duration)[..., None]  # [1, F, 1]: every spot's still has the same light
    c["fits"] = fit_spot_problems(c["crops"], c["kernel"], c["window"], c["omega"], noise_std=c["noise"], kernel_noise=c["factor"])
    c["gauss_fits"] = fit_spot_problems(c["crops"], c["gauss"], c["window"], c["omega"], noise_std=c["noise"], chunk=2)
    return c


def _amp_std(fits):
    return torch.stack([fits.covariance[..., 0, 0], fits.covariance[..., 2, 2]], -1).sqrt()


def test_kernel_response_does_not_depend_on_the_motion(sinc):
    """measured/true of every motion size (0.5-3 px) within its stds with the per-spot kernel; the
    Gaussian, which psf_from_still refuses on these spots, fits them worse."""
    c = sinc
    assert all(s.kind == "kernel" for s in c["still_psf"])  # the Gaussian does not explain a sinc^2 still
    fits = c["fits"]
    assert bool((fits.status == 0).all())
    z = ((fits.amplitude[0] - c["amplitude"]) / _amp_std(fits)[0]).unflatten(0, (len(MOTIONS), N_EACH))  # [motion, point, M, 2]
    ratio = (fits.amplitude[0] / c["amplitude"]).unflatten(0, (len(MOTIONS), N_EACH))
    rel_std = (_amp_std(fits)[0] / c["amplitude"]).unflatten(0, (len(MOTIONS), N_EACH))
    for f, m in enumerate(MOTIONS):
        n = z[f].numel()
        assert abs(float(z[f].mean())) < 3 / math.sqrt(n) + 0.5, (m, z[f])  # no motion-size bias beyond the stds
        rel = float(rel_std[f].square().mean().sqrt())  # the relative std of one fit
        assert abs(float(ratio[f].mean()) - 1) < 3 * rel / math.sqrt(n) + 0.5 * rel, (m, ratio[f])
    assert 0.6 < float(z.square().mean().sqrt()) < 1.4
    assert float(c["gauss_fits"].reduced_chi2.median()) > float(fits.reduced_chi2.median())


def test_per_spot_psf_mixes_kernel_and_gaussian_and_inflates_only_kernel_stds(sinc):
    c = sinc
    use = torch.tensor([True, False])
    sel = dict(window=c["window"][:, :2], omega=c["omega"][:2], noise_std=c["noise"][:, :2])
    crops = c["crops"][:, :2]
    mixed = fit_spot_problems(crops, PerSpotPSF(c["gauss"], c["kernel"], use), kernel_noise=c["factor"][:, :2] * 1.5, **sel)
    kern, gaus = c["fits"], c["gauss_fits"]  # the whole batch, fitted alone by kind (the Gaussians in chunks of 2)
    torch.testing.assert_close(mixed.amplitude[:, :, use], kern.amplitude[:, :2, use], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mixed.amplitude[:, :, ~use], gaus.amplitude[:, :2, ~use], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mixed.covariance[:, :, use], 2.25 * kern.covariance[:, :2, use], rtol=1e-7, atol=0)
    torch.testing.assert_close(mixed.covariance[:, :, ~use], gaus.covariance[:, :2, ~use], rtol=1e-7, atol=0)
    assert mixed.n_chunks == 2  # one chunk of each kind


def test_spot_psf_arguments_are_checked(sinc):
    c = sinc
    args = (c["crops"][:, :1], c["gauss"], c["window"][:, :1], c["omega"][:1])
    with pytest.raises(ParameterError, match="kernel_noise"):
        fit_spot_problems(*args, kernel_noise=0.5)
    with pytest.raises(ShapeError, match="kernel_noise"):
        fit_spot_problems(*args, kernel_noise=torch.ones(3))
    with pytest.raises(ShapeError, match="use_kernel"):
        PerSpotPSF(c["gauss"], c["kernel"], torch.ones(3, dtype=torch.bool))
    with pytest.raises(InputTypeError, match="psf"):
        fit_spot_problems(args[0], "gaussian", *args[2:])
    with pytest.raises(ShapeError, match="psf"):
        fit_spot_problems(args[0], KernelPSF(c["kernel"].kernel[:, :8, :8]), *args[2:])
