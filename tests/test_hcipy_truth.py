"""Frames from an independent optics engine (HCIPy): the conventions first, then a reduced
version of benchmarks/bench_hcipy.py (issue 15)."""
import math

import numpy as np
import pytest
import torch

pytest.importorskip("hcipy")

import hcipy_frames as hf  # noqa: E402

from torchblur.render.blur import render_blur  # noqa: E402
from torchblur.render.psf import GaussianPSF  # noqa: E402
from torchblur.render.trajectory import Sinusoid  # noqa: E402
from torchblur.render.window import ExposureWindow  # noqa: E402

H, W = 48, 64


def test_conventions_match_torchblur_on_a_gaussian_pupil():
    """A Gaussian pupil makes a Gaussian spot: HCIPy's frames equal torchblur's renderer
    (pixel centres, x = j, y = i, t = 0 at the upward zero crossing, amplitude = peak per second)."""
    optics = hf.SpotOptics(gaussian_pupil=2.5 / (2 * math.sqrt(2) * math.pi * 2.0))
    assert optics.gaussian_sigma_px() == pytest.approx(2.0)
    c = (31.3, 23.6)
    spot = hf.HcipySpot(optics, c, H, W)
    psf = GaussianPSF.isotropic(torch.tensor(c, dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64), 1000.0)
    zero = torch.zeros(2, dtype=torch.float64)
    still = render_blur(Sinusoid(zero, zero, 1.0), psf, ExposureWindow(0.0, 0.01), height=H, width=W).numpy()
    assert np.abs(spot.still(1000.0, 0.01) - still).max() < 1e-4 * still.max()
    omega, A, phase = 2 * math.pi * 300, 7.0, 0.7
    d = np.array([math.cos(0.5), math.sin(0.5)])
    T = 2 * math.pi / omega
    starts, durs = np.array([0.2 * T, 0.2 * T]), np.array([0.3 * T, 0.8 * T])
    ours = spot.blurred(1000.0, starts, durs, A, phase, omega, direction=d, n_time=1000)
    traj = Sinusoid(torch.tensor(A * d), torch.tensor([phase, phase]), omega)
    ref = render_blur(traj, psf, ExposureWindow(torch.tensor(starts), torch.tensor(durs)), height=H, width=W).numpy()
    assert np.abs(ours - ref).max() < 1e-4 * ref.max()


def test_batched_dft_equals_hcipy_propagator():
    spot = hf.HcipySpot(hf.SpotOptics(obstruction=0.2), (30.2, 22.9), H, W)
    for dx, dy in ((0.0, 0.0), (3.3, -2.1), (-9.7, 4.4)):
        ref = spot.reference_intensity(dx, dy)
        assert np.abs(spot.intensity(dx, dy) - ref).max() < 1e-12
    assert spot.intensity(0.0, 0.0)[23, 30] < 1.0  # the peak (1) sits between pixels
    assert spot.intensity([1.0, 2.0], [0.0, 0.0]).shape == (2, H, W)


def test_time_integral_converged():
    """The fastest motion of the benchmark (800 Hz, 10 px, 0.8 period): 1000 and 2000 midpoint
    samples per exposure agree to 1e-4 of the frame's peak."""
    spot = hf.HcipySpot(hf.SpotOptics(), (31.5, 23.5), H, W)
    omega = 2 * math.pi * 800
    T = 2 * math.pi / omega
    args = (1.0, [0.1 * T], [0.8 * T], 10.0, 0.3, omega)
    a = spot.blurred(*args, direction=(math.cos(0.5), math.sin(0.5)), n_time=1000)
    b = spot.blurred(*args, direction=(math.cos(0.5), math.sin(0.5)), n_time=2000)
    assert np.abs(a - b).max() < 1e-4 * b.max()


@pytest.fixture(scope="module")
def problems():
    return [hf.make_problem(100 + k, rotated=bool(k % 2), n_time=1000) for k in range(4)]


def test_psf_from_still_is_accurate_and_honest_on_diffraction_spots(problems):
    out = hf.fit_problems(problems, "auto")
    assert out["kinds"] == ["kernel"] * 4
    assert (out["status"] == 0).all()
    assert np.abs(out["err_M_pct"]).max() < 1.0
    assert np.abs(out["err_phi_deg"]).max() < 1.0
    assert np.abs(out["z_M"]).max() < 4 and np.abs(out["z_phi"]).max() < 4


def test_gaussian_route_is_biased_and_its_still_says_so(problems):
    """The contrast: a Gaussian fitted to the same still misses by many of its own std, and
    the reduced chi2 of the still (what psf_from_still tests) shows it."""
    out = hf.fit_problems(problems, "gaussian")
    z = np.concatenate([out["z_M"], out["z_phi"]])
    assert np.sqrt(np.mean(z**2)) > 2
    assert (out["chi2_gaussian"] > 10).all()
