"""Robust fitting (issue 8): injected defects are masked or modelled, flagged, and the estimate
stays within its reported uncertainty (|error| < 4 std on every item of several seeded designs)."""
import math

import pytest
import torch

import torchblur as tb
from torchblur.image import preprocess as pp
from torchblur.render.camera import CameraModel
from torchblur.design.windows import dual_exposure_windows
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.fit.status import MASKED, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED

F64 = torch.float64
H, W = 28, 36
N = 6


def make(seed, *, center=(17.5, 13.5), M_range=(3.0, 6.0), sigma_px=(2.0, 1.5), sigma_frac=0.01):
    """N dual-exposure items with random frequency, amplitude, phase and trigger phase."""
    g = torch.Generator().manual_seed(seed)
    om = 2 * math.pi * (50 + 700 * torch.rand(N, generator=g, dtype=F64))
    M = M_range[0] + (M_range[1] - M_range[0]) * torch.rand(N, generator=g, dtype=F64)
    phi = (2 * torch.rand(N, generator=g, dtype=F64) - 1) * math.pi
    b = 2 * math.pi * torch.rand(N, generator=g, dtype=F64)
    win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=b)
    c = torch.tensor(center, dtype=F64).expand(N, 2)
    psf = tb.GaussianPSF.from_axes(c, torch.full((N,), sigma_px[0], dtype=F64), torch.full((N,), sigma_px[1], dtype=F64),
                                   torch.full((N,), 0.4, dtype=F64))
    amp = torch.stack([M, torch.zeros_like(M)], -1)
    clean = tb.render_blur(tb.Sinusoid(amp[:, None], torch.stack([phi, phi], -1)[:, None], om[:, None]),
                           tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=H, width=W)
    peak = clean.amax((-1, -2, -3))
    sigma = sigma_frac * peak
    noise = sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64)
    return dict(clean=clean, images=clean + noise, psf=psf, win=win, om=om, M=M, phi=phi, sigma=sigma, peak=peak, g=g)


def zmax(res, d):
    """Largest |error| / reported std over amplitude and phase, per item."""
    zM = (res.amplitude - d["M"]) / res.amplitude_std
    zp = tb.wrap_phase(res.phase - d["phi"]) / res.phase_std
    return torch.maximum(zM.abs(), zp.abs())


def hot_pixel_scene(seed, n_hot=12):
    """Dark frames with hot pixels, and a science frame whose hot pixels are brighter (a longer
    exposure collects more dark current), dark-subtracted: ``clean + 2 h + noise``."""
    d = make(seed)
    g = d["g"]
    idx = torch.randperm(H * W, generator=g)[:n_hot]
    level = d["sigma"].mean() * (20 + 80 * torch.rand(n_hot, generator=g, dtype=F64))
    hot = torch.zeros(H * W, dtype=F64)
    hot[idx] = level
    hot = hot.reshape(H, W)
    darks = 100 + hot + d["sigma"].mean() * torch.randn((8, H, W), generator=g, dtype=F64)
    dark = pp.dark_frame(darks)
    science = 100 + d["images"] + 3 * hot
    d["images"] = pp.subtract_dark(science, dark)
    d["hot"], d["dark"] = hot > 0, dark
    return d


@pytest.mark.parametrize("seed", [0, 1])
def test_hot_pixels_masked_from_a_dark_frame_map(seed):
    d = hot_pixel_scene(seed)
    assert torch.equal(d["dark"].hot_pixels, d["hot"])
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"], mask=~d["dark"].hot_pixels)
    assert (res.status == 0).all() and (res.flags & MASKED != 0).all()
    assert (res.n_masked == 2 * int(d["hot"].sum())).all()
    assert float(zmax(res, d).max()) < 4
    # the defect matters: without the map the estimates leave their error bars
    plain = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    assert float(zmax(plain, d).max()) > 4


@pytest.mark.parametrize("seed", [0, 1])
def test_hot_pixels_found_without_a_map(seed):
    d = hot_pixel_scene(seed)
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"], outliers="reject")
    n_hot = 2 * int(d["hot"].sum())  # both exposures
    assert (res.status == 0).all() and (res.flags & OUTLIERS_MASKED != 0).all()
    assert ((res.n_outliers >= n_hot) & (res.n_outliers <= n_hot + 2)).all(), res.n_outliers
    assert float(zmax(res, d).max()) < 4


def add_cosmic_rays(d, hits=3):
    """1- and 2-pixel hits of 3 to 30 times the peak, anywhere on the spot's region."""
    g = d["g"]
    img = d["images"].clone()
    n_pix = 0
    for n in range(N):
        for k in range(hits):
            e = int(torch.randint(0, 2, (1,), generator=g))
            i = int(torch.randint(6, H - 6, (1,), generator=g))
            j = int(torch.randint(6, W - 7, (1,), generator=g))
            img[n, e, i, j] += float(3 + 27 * torch.rand(1, generator=g, dtype=F64)) * d["peak"][n]
            if k % 2 == 0:
                img[n, e, i, j + 1] += float(0.5 + torch.rand(1, generator=g, dtype=F64)) * d["peak"][n]
    d["images"] = img
    return d


@pytest.mark.parametrize("seed,given", [(2, True), (3, False)])
def test_cosmic_rays_rejected(seed, given):
    d = add_cosmic_rays(make(seed))
    kw = dict(noise_std=d["sigma"]) if given else {}
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], outliers="reject", **kw)
    assert (res.status == 0).all() and (res.flags & OUTLIERS_MASKED != 0).all()
    assert (res.n_outliers >= 4).all()  # 3 hits, two of them 2 px wide (unless two hits share a pixel)
    assert float(zmax(res, d).max()) < 4
    plain = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], **kw)
    assert float(zmax(plain, d).max()) > 4


@pytest.mark.parametrize("sigma_px", [(2.0, 1.5), (0.8, 0.8)])
def test_clean_data_loses_nothing_to_the_robust_pass(sigma_px):
    d = make(4, sigma_px=sigma_px)
    plain = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    robust = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"], outliers="reject")
    assert (robust.n_outliers == 0).all() and (robust.flags == 0).all()
    torch.testing.assert_close(robust.amplitude, plain.amplitude)
    torch.testing.assert_close(robust.phase, plain.phase)


@pytest.mark.parametrize("seed", [5, 6])
def test_partial_saturation_masked_by_level(seed):
    d = make(seed)
    level = 0.6 * d["peak"]
    clipped = torch.minimum(d["images"], level[:, None, None, None])
    res = fit_sinusoid(clipped, d["psf"], d["win"], d["om"], noise_std=d["sigma"], saturation_level=level)
    assert (res.status == 0).all() and (res.flags == SATURATED_MASKED).all()
    assert (res.n_masked > 0).all()
    assert float(zmax(res, d).max()) < 4
    plain = fit_sinusoid(clipped, d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    assert float(zmax(plain, d).max()) > 4


def test_partial_saturation_masked_from_the_camera():
    """A simulated camera clips the spot's core (full well); its saturation mask of the raw ADU
    frames excludes those pixels; shot noise is weighted per pixel."""
    d = make(7)
    cam = CameraModel(read_noise_e=5.0, full_well_e=2000.0, bit_depth=16, quantize=False)
    expected_e = d["clean"] * (4000.0 / d["peak"])[:, None, None, None]  # peak 4000 e: twice the full well
    raw = cam.expose(expected_e, generator=torch.Generator().manual_seed(70))
    sat = cam.saturated_mask(raw)
    electrons = cam.to_electrons(raw)
    gain = (4000.0 / d["peak"])[:, None, None, None]
    images = electrons / gain
    noise = cam.noise.std(expected_e) / gain
    res = fit_sinusoid(images, d["psf"], d["win"], d["om"], noise_std=noise, mask=~sat)
    assert sat.flatten(1).any(1).all()
    assert (res.status == 0).all() and (res.flags == MASKED).all()
    assert float(zmax(res, d).max()) < 4


@pytest.mark.parametrize("seed", [8, 9])
def test_stray_light_background_modelled(seed):
    d = make(seed)
    bg = 0.2 * d["peak"]
    images = d["images"] + bg[:, None, None, None]
    res = fit_sinusoid(images, d["psf"], d["win"], d["om"], fit_background=True)
    j = res.param_names.index("background")
    bg_std = res.covariance[:, j, j].sqrt()
    assert (res.status == 0).all()
    assert float(((res.background - bg) / bg_std).abs().max()) < 4
    assert float(zmax(res, d).max()) < 4


@pytest.mark.parametrize("seed", [10, 11])
def test_spot_partly_out_of_frame_fitted_on_what_is_visible(seed):
    d = make(seed, center=(2.5, 13.5), M_range=(4.0, 7.0))
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    assert (res.status == 0).all() and (res.flags == PARTLY_OUT_OF_FRAME).all()
    assert float(zmax(res, d).max()) < 4
    e = make(seed)  # the same designs, spot in the middle: no flag
    inside = fit_sinusoid(e["images"], e["psf"], e["win"], e["om"], noise_std=e["sigma"])
    assert (inside.flags == 0).all()


@pytest.mark.parametrize("seed", [12, 13])
def test_stray_light_gradient_removed(seed):
    """A tilted stray-light plane biases a fit with a constant background by hundreds of std
    (see benchmarks/bench_robust.py); fit_gradient removes it."""
    d = make(seed)
    y = torch.arange(H, dtype=F64)[:, None]
    x = torch.arange(W, dtype=F64)[None, :]
    plane = d["peak"][:, None, None, None] * (0.1 + 0.01 * (x - 10) + 0.004 * (y - 5))
    res = fit_sinusoid(d["images"] + plane, d["psf"], d["win"], d["om"], noise_std=d["sigma"], fit_gradient=True)
    assert (res.status == 0).all()
    assert float(zmax(res, d).max()) < 4
    want = torch.tensor([0.1 + 0.01 * ((W - 1) / 2 - 10) + 0.004 * ((H - 1) / 2 - 5), 0.01, 0.004], dtype=F64)
    torch.testing.assert_close(res.background_plane / d["peak"][:, None, None], want.expand(N, 2, 3), rtol=0, atol=2e-3)
