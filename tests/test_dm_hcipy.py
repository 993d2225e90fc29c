"""The DM route on Shack-Hartmann frames from an independent optics engine (HCIPy, issue 23):
the generator's physics, the calibration on the sensor's known layout, and a PSF fit that
flags a spot it cannot describe instead of raising. Reduced sizes; the full measurement is
benchmarks/bench_dm_hcipy.py."""
import math

import numpy as np
import pytest
import torch

pytest.importorskip("hcipy")

import hcipy_sh as hs  # noqa: E402

from torchblur.image.psf_fit import fit_gaussian_psf  # noqa: E402
from torchblur.image.spot_layout import layout_spots, predict_layout, register_layout  # noqa: E402


@pytest.fixture(scope="module")
def small():
    """A 4 x 4 lenslet sensor (12 valid) behind a 4 x 4 actuator DM: 64 x 64 px."""
    return hs.HcipySH(hs.SHOptics(n_lenslets=4, dm_across=4))


@pytest.fixture(scope="module")
def full():
    """configs/identify_dm.yaml's geometry: 10 x 10 lenslets, 80 valid, 52 actuators, 160 x 160 px."""
    return hs.HcipySH()


def _noisy(img, rng, peak=3000.0, background=20.0, read=3.0):
    e = img * peak
    return rng.poisson(e + background).astype(float) - background + read * rng.standard_normal(e.shape)


def test_generator_is_hcipys_propagation_with_crosstalk(full):
    """The batched FFT path equals HCIPy's DeformableMirror + MicroLensArray + FresnelPropagator
    forward (single precision: < 1e-5 of the peak); the geometry is the config's (80 valid of
    10 x 10, 52 actuators, spots at the declared rest positions) and the lenslets' sinc^2 wings
    leave a crosstalk floor between spots (what thresholding cannot separate)."""
    assert full.valid.size == 80 and full.n_actuators == 52 and full.shape == (160, 160)
    cmd = np.random.default_rng(3).normal(size=full.n_actuators)
    ours = full.intensity(cmd[None])[0]
    assert np.abs(ours - full.reference_intensity(cmd)).max() < 1e-5 * ours.max()
    full.device = "cpu"  # the same propagation in torch (a benchmark's --device)
    try:
        assert np.abs(full.intensity(cmd[None])[0] - ours).max() < 1e-5 * ours.max()
    finally:
        full.device = None
    still = full.still()
    inner = full.aperture.reshape(10, 16, 10, 16).mean((1, 3)).reshape(-1)[full.valid] > 0.999  # fully lit subapertures
    at_rest = still[np.round(full.rest_px[inner, 1]).astype(int), np.round(full.rest_px[inner, 0]).astype(int)]
    assert at_rest.min() > 0.9  # every fully lit spot peaks at its declared place (the peak sits between pixels)
    corner = still[16:144:16, 16:144:16]  # the corners between four spots
    assert 1e-4 < np.median(corner) < 0.05


def test_time_integral_converged(small):
    """The node rule: doubling the Gauss-Legendre nodes changes a frame by < 1e-3 of its peak
    (a 3 px motion over 0.3 of a period)."""
    omega = 2 * math.pi * 700.0
    T = 2 * math.pi / omega
    slopes = small.shift_truth()
    amp = np.zeros(small.n_actuators)
    amp[5] = 3.0 / np.abs(slopes[:, 5]).max()
    ph = np.full(small.n_actuators, 0.4)
    n = small.node_count(3.0, omega, 0.3 * T)
    a = small.blurred(amp, ph, omega, [0.1 * T], [0.3 * T], n)
    b = small.blurred(amp, ph, omega, [0.1 * T], [0.3 * T], 2 * n)
    assert np.abs(a - b).max() < 1e-3 * b.max()


def _warp(img, offset, rot, scale):
    """``img`` seen by a camera whose layout maps by (offset, rot, scale) about the centre (cubic)."""
    from scipy.ndimage import affine_transform

    H, W = img.shape
    c0 = np.array([(W - 1) / 2, (H - 1) / 2])
    R = np.array([[math.cos(rot), -math.sin(rot)], [math.sin(rot), math.cos(rot)]])
    Ri = np.linalg.inv(R) / scale
    P = np.array([[0, 1], [1, 0]])  # (x, y) <-> (row, col)
    return affine_transform(img, P @ Ri @ P, offset=P @ (c0 - Ri @ (c0 + np.asarray(offset))), order=3)


def test_layout_registration_finds_every_valid_spot(full):
    """On a noisy HCIPy still of the full sensor seen by a shifted, rotated and magnified camera,
    the layout registration recovers the map and centres every valid spot (partly lit edge
    subapertures included) in its own cell."""
    rng = np.random.default_rng(11)
    off, rot, scale = (2.6, -3.1), math.radians(0.8), 1.015
    img = _warp(_noisy(full.still(), rng), off, rot, scale)
    reg = register_layout(torch.as_tensor(img), full.rest_px, pitch_px=16.0)
    true = predict_layout(full.rest_px, img.shape, off, rot, scale)
    assert reg.status == ["ok"] * 80
    assert np.abs(reg.predicted_px - true).max() < 0.1
    assert np.abs(reg.center_px - true).max() < 0.35


def test_psf_fit_flags_a_spot_it_cannot_describe(small):
    """A still whose subaperture 0 is dark (a blocked lenslet) and whose subaperture 5 holds a
    ring with no core: nothing raises, every other spot is fitted at its place, the two are named."""
    rng = np.random.default_rng(2)
    still = small.still()
    rest = small.rest_px
    x0, y0 = (rest[0] - 7.5).astype(int)  # the cell of spot 0
    still[y0:y0 + 16, x0:x0 + 16] = 0.0
    img = _noisy(still, rng)
    x5, y5 = (rest[5] - 7.5).astype(int)
    yy, xx = np.mgrid[0:16, 0:16]
    rr = np.hypot(xx - 7.5, yy - 7.5)
    img[y5:y5 + 16, x5:x5 + 16] = 400.0 * np.exp(-0.5 * ((rr - 6.0) / 0.8) ** 2) + 3 * rng.standard_normal((16, 16))
    reg = register_layout(torch.as_tensor(img), rest, pitch_px=16.0)
    assert reg.status[0] == "dark" and reg.status[5] == "not_compact" and reg.status.count("ok") == len(rest) - 2
    # the fit (the slow part: four of the declared spots) goes on around the flagged ones
    some = [0, 5, 6, 9]
    spots, reg, flags = layout_spots(torch.as_tensor(img), exposure_s=1.0, noise_std=math.sqrt(3029.0), rest_px=rest[some], pitch_px=16.0)
    assert flags == ["dark", "not_compact", "ok", "ok"]
    assert bool((spots.psf.amplitude >= 0).all()) and float(spots.psf.amplitude[0]) == 0.0
    assert np.abs(spots.psf.center.numpy()[2:] - rest[[6, 9]]).max() < 0.3
    # the fit alone on a crop it cannot describe (a dip left by a wrong dark frame): no
    # ParameterError (it raised "amplitude: expected every value >= 0"), an amplitude of 0
    dip = torch.as_tensor(-300 * np.exp(-0.5 * rr**2 / 1.5**2) + 3 * rng.standard_normal((16, 16)))
    fit = fit_gaussian_psf(dip, exposure_s=1.0, noise_std=3.0, max_iter=2)
    assert float(fit.psf.amplitude) >= 0.0
