"""The DM spot fitter with each spot's measured PSF (issue 23): sinc^2 lenslet spots with a
crosstalk floor (tests/sinc_spots.py), fitted with the kernel psf_from_still chooses per spot."""
from __future__ import annotations

import math

import pytest
import torch

from sinc_spots import sinc2_case
from torchblur.dm.spot_fit import PerSpotPSF, fit_spot_problems
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.render.alias import wrap_phase
from torchblur.render.psf import GaussianPSF, KernelPSF

MOTIONS = (0.5, 1.0, 2.0, 3.0)
N_EACH = 4  # points per motion size


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small FFT-path fits: a second OpenMP thread only adds overhead (25x slower at load 10 here)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def sinc():
    """Two sinc^2 spots side by side (each one's wings in the other's crop, 12 px pitch); spot 0's
    problems are fitted with its measured kernel (its averaged still crop per second: what
    psf_from_still keeps where a floor fills the crop; psf_from_still itself chooses the kernel on
    these spots in benchmarks/bench_dm_kernel.py, and costs seconds here) and with the Gaussian of the
    kernel's moments."""
    c = sinc2_case([m for m in MOTIONS for _ in range(N_EACH)], n_side=2, n_rows=1, pitch=12, n_still=64, seed=3)
    c["crops"], c["noise"], c["amplitude"] = c["crops"][:, :, :1], c["noise"][:, :, :1], c["amplitude"][:, :1]
    n_still = c["still_crops"].shape[0]
    c["kernel"] = KernelPSF(c["still_crops"][:, :1].mean(0), c["still_s"])  # [1, h, w]
    centre, cov = c["kernel"].moments()
    c["gauss"] = GaussianPSF(centre, cov, c["kernel"].kernel.sum((-1, -2)) / (2 * math.pi * torch.linalg.det(cov).sqrt()))
    # the kernel's own noise (StillPSF.kernel_noise_factor's rule): sqrt(1 + a point's light / the still's light)
    c["factor"] = (1 + c["window"].duration.sum(-1) / (n_still * c["still_s"])).sqrt()[..., None]  # [1, F, 1]
    c["fits"] = fit_spot_problems(c["crops"], c["kernel"], c["window"], c["omega"], noise_std=c["noise"], kernel_noise=c["factor"])
    c["gauss_fits"] = fit_spot_problems(c["crops"], c["gauss"], c["window"], c["omega"], noise_std=c["noise"], chunk=5)
    return c


def _amp_std(fits):
    return torch.stack([fits.covariance[..., 0, 0], fits.covariance[..., 2, 2]], -1).sqrt()


def test_kernel_response_does_not_depend_on_the_motion(sinc):
    """measured/true of every motion size (0.5-3 px) within its stds with the spot's kernel; a
    Gaussian fits the same frames worse."""
    c = sinc
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


@pytest.fixture(scope="module")
def mixed(sinc):
    """Spot 0's first 3 problems twice, as two spots, the first with its kernel, the second with its Gaussian:
    ``(args, kwargs, fits)`` of :func:`fit_spot_problems` (the kernel noise factor 1.5 times the still's rule)."""
    c = sinc
    g, k = c["gauss"], c["kernel"]
    psf = PerSpotPSF(GaussianPSF(g.center.expand(2, 2), g.cov.expand(2, 2, 2), g.amplitude.expand(2)), KernelPSF(k.kernel.expand(2, -1, -1)),
                     torch.tensor([True, False]))
    crops = c["crops"][:, :3].expand(-1, -1, 2, -1, -1, -1)
    args, kw = (crops, psf, c["window"][:, :3], c["omega"][:3]), {"noise_std": c["noise"][:, :3], "kernel_noise": c["factor"][:, :3] * 1.5}
    return args, kw, fit_spot_problems(*args, **kw)


def test_per_spot_psf_mixes_kernel_and_gaussian_and_inflates_only_kernel_stds(sinc, mixed):
    """Spot 0's crops twice, as two spots: the first fitted with its kernel, the second with its
    Gaussian (one batch), each equal to its kind's fit alone; the kernel noise factor only on the first."""
    c = sinc
    mixed = mixed[2]
    kern, gaus = c["fits"], c["gauss_fits"]  # the whole batch, fitted alone by kind (the Gaussians in chunks of 5)
    torch.testing.assert_close(mixed.amplitude[:, :, :1], kern.amplitude[:, :3], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mixed.amplitude[:, :, 1:], gaus.amplitude[:, :3], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mixed.covariance[:, :, :1], 2.25 * kern.covariance[:, :3], rtol=1e-7, atol=0)
    torch.testing.assert_close(mixed.covariance[:, :, 1:], gaus.covariance[:, :3], rtol=1e-7, atol=0)
    assert mixed.n_chunks == 2  # one chunk of each kind


def _same_to_roundoff(got, ref) -> None:
    """The same statuses and flags, the estimates within 1e-5 of their own stds (an H200 gave 1.9e-8 px on
    an amplitude, 1.1e-7 relative: a float64 solve's round-off through the fit's conditioning), the
    covariance and chi2 within 1e-6 relative."""
    assert torch.equal(got.status, ref.status) and torch.equal(got.flags, ref.flags)
    sd = torch.diagonal(ref.covariance, dim1=-2, dim2=-1).sqrt()
    for name, diff, s in (("amplitude", got.amplitude - ref.amplitude, sd[..., 0::2]),
                          ("phase", wrap_phase(got.phase - ref.phase), sd[..., 1::2])):
        d = diff.abs() / s
        assert torch.equal(diff.isnan(), getattr(ref, name).isnan()), name
        assert bool((d[~d.isnan()] <= 1e-5).all()), (name, float(d.nan_to_num().max()))
    for name in ("covariance", "reduced_chi2"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=1e-6, atol=0, equal_nan=True)


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_fit_device_moves_the_spot_fits_and_brings_them_back(mixed, device):
    """``fit.device`` (the DM plan's ``_fit_spots``): the mixed kernel/Gaussian batch fitted on ``device``
    (crops, PerSpotPSF, window, omega, noise and kernel noise moved there), every fit back on the CPU:
    bit for bit the direct call on the CPU, the same to round-off on a GPU (:func:`_same_to_roundoff`)."""
    from torchblur.identify.dm_plan import _fit_spots

    args, kw, ref = mixed
    got = _fit_spots(*args, device=device, **kw)
    assert got.n_chunks == ref.n_chunks
    for name in ("amplitude", "phase", "covariance", "status", "flags", "reduced_chi2"):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.device.type == "cpu" and a.dtype == b.dtype
        if device == "cpu":
            assert torch.equal(a, b), name
    _same_to_roundoff(got, ref)


def test_spot_psf_arguments_are_checked(sinc):
    c = sinc
    args = (c["crops"][:, :1], c["gauss"], c["window"][:, :1], c["omega"][:1])
    with pytest.raises(ParameterError, match="kernel_noise"):
        fit_spot_problems(*args, kernel_noise=0.5)
    with pytest.raises(ShapeError, match="kernel_noise"):
        fit_spot_problems(*args, kernel_noise=torch.ones(3))
    with pytest.raises(ShapeError, match="use_kernel"):
        PerSpotPSF(c["gauss"], c["kernel"], torch.ones(3, dtype=torch.bool))
    with pytest.raises(ShapeError, match="use_kernel"):
        PerSpotPSF(c["gauss"], c["kernel"], torch.ones(1))
    with pytest.raises(InputTypeError, match="psf"):
        fit_spot_problems(args[0], "gaussian", *args[2:])
    with pytest.raises(ShapeError, match="psf"):
        fit_spot_problems(args[0], KernelPSF(c["kernel"].kernel[:, :8, :8]), *args[2:])
    with pytest.raises(ShapeError, match="psf"):
        fit_spot_problems(args[0], KernelPSF(c["kernel"].kernel.expand(3, -1, -1)), *args[2:])
