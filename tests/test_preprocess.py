"""Preprocessing: dark frames, thresholds, spot finding, crops, the still-spot PSF fit and
the saturation curve, each checked against simulated camera data with a known truth."""
import math

import pytest
import torch

import torchblur as tb
from torchblur.render.camera import CameraModel
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.image.preprocess import (
    DarkFrame,
    crop,
    dark_frame,
    find_spots,
    fit_gaussian_psf,
    saturation_curve,
    subtract_dark,
    threshold_mask,
)

F64 = torch.float64
TE = 0.01  # exposure of the still images (s)
PIX = tb.RenderSettings(pixel_integration=True)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Small tensors: two OpenMP threads on a shared machine cost ~10x (MEASURED.md).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def still_image(psf, height, width, exposure_s=TE):
    """Noise-free still-spot image from the renderer, [..., H, W]."""
    z = torch.zeros(psf.shape + (2,), dtype=F64)
    return tb.render_blur(tb.Sinusoid(z, z, 1.0), psf, tb.ExposureWindow(0.0, exposure_s),
                          height=height, width=width, settings=PIX)


def tilted_psf(peak_e=2000.0, center=(15.3, 16.6), size=32):
    """The tilted test spot (sigmas 2.4 / 1.5 px, angle 0.6 rad) scaled to ``peak_e`` per TE."""
    unit = tb.GaussianPSF.from_axes(torch.tensor(center, dtype=F64), torch.tensor(2.4, dtype=F64),
                                    torch.tensor(1.5, dtype=F64), torch.tensor(0.6, dtype=F64),
                                    amplitude=torch.tensor(1.0, dtype=F64))
    amp = peak_e / float(still_image(unit, size, size).max())
    return tb.GaussianPSF(unit.center, unit.cov, torch.tensor(amp, dtype=F64))


# --------------------------------------------------------------------------- dark frames


def test_dark_frame_recovers_level_noise_and_hot_pixels():
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0, gain_e_per_adu=1.0, hot_pixel_fraction=0.001)
    N, H, W = 16, 96, 96
    frames = cam.expose(torch.zeros(N, H, W, dtype=F64), generator=torch.Generator().manual_seed(11))
    d = dark_frame(frames)
    assert isinstance(d, DarkFrame) and d.n_frames == N
    hot = cam.hot_pixel_mask(H, W)
    assert int(hot.sum()) == 9
    sigma = math.sqrt(5.0**2 + 1 / 12)  # read noise plus rounding to whole ADU
    assert float((d.mean - 100.0)[~hot].abs().max()) < 5 * sigma / math.sqrt(N)
    assert abs(float(d.read_noise) / sigma - 1) < 0.10
    assert torch.equal(d.hot_pixels, hot)
    # subtracting it leaves zero-mean frames away from hot pixels
    sub = subtract_dark(frames, d)
    assert sub.shape == frames.shape
    assert abs(float(sub[:, ~hot].mean())) < 1e-9
    assert float(subtract_dark(frames, d, clip_negative=True).min()) == 0.0


def test_dark_frame_batch_equals_single():
    g = torch.Generator().manual_seed(5)
    frames = 100 + 3 * torch.randn(2, 8, 20, 24, generator=g, dtype=F64)
    frames[1, :, 4, 7] += 500  # one hot pixel in the second sensor
    d = dark_frame(frames)
    assert d.mean.shape == (2, 20, 24) and d.read_noise.shape == (2,) and d.hot_pixels.shape == (2, 20, 24)
    for b in range(2):
        s = dark_frame(frames[b])
        assert torch.equal(s.mean, d.mean[b]) and torch.equal(s.read_noise, d.read_noise[b])
        assert torch.equal(s.hot_pixels, d.hot_pixels[b])
    assert d.hot_pixels[1].nonzero().tolist() == [[4, 7]] and not d.hot_pixels[0].any()


# --------------------------------------------------------------------------- threshold and spots


def test_threshold_mask_false_positive_rate_matches_smoothed_noise():
    # White noise smoothed: k = 3 should pass 1 - Phi(3) = 0.135% of pixels.
    noise = 7.0 * torch.randn(4, 128, 128, generator=torch.Generator().manual_seed(2), dtype=F64)
    frac = float(threshold_mask(noise, 7.0, k=3.0).double().mean())
    assert 0.0007 < frac < 0.0025
    # per-item noise level: the same noise at twice the claimed std passes almost nothing
    m = threshold_mask(noise, torch.tensor([7.0, 7.0, 14.0, 14.0], dtype=F64), k=3.0)
    assert m.shape == noise.shape and int(m[2:].sum()) <= 1


def grid_frame(seed=3):
    g = torch.Generator().manual_seed(seed)
    c = torch.tensor([16.0, 48.0, 80.0], dtype=F64)
    cx, cy = torch.meshgrid(c, c, indexing="xy")
    centers = torch.stack([cx, cy], -1).reshape(9, 2) + torch.rand(9, 2, generator=g, dtype=F64) - 0.5
    amps = torch.linspace(0.6e5, 1.4e5, 9, dtype=F64)  # peaks about 600 .. 1400 e-
    psf = tb.GaussianPSF.isotropic(centers, torch.tensor(1.8, dtype=F64), amplitude=amps)
    expected = still_image(psf, 96, 96).sum(0)
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0)
    return cam.expose(expected, generator=g) - 100.0, centers, amps


def test_find_spots_grid_and_pure_noise():
    frame, centers, amps = grid_frame()
    spots = find_spots(frame, noise_std=5.0)
    assert isinstance(spots, list) and len(spots) == 1
    s = spots[0]
    assert len(s) == 9
    d = torch.cdist(s.centroid, centers)
    match = d.argmin(1)
    assert sorted(match.tolist()) == list(range(9))
    assert float(d.min(1).values.max()) < 0.1
    # brightest first, boxes contain their centroids, totals ~ the spots' light
    assert bool((s.total[:-1] >= s.total[1:]).all())
    assert int(match[0]) == 8
    x, y = s.centroid[:, 0], s.centroid[:, 1]
    assert bool(((s.box[:, 0] <= x) & (x < s.box[:, 2]) & (s.box[:, 1] <= y) & (y < s.box[:, 3])).all())
    true_total = amps[match] * TE * 2 * math.pi * 1.8**2
    assert float(((s.total - true_total) / true_total).abs().max()) < 0.02
    # max_spots keeps the brightest
    top = find_spots(frame, noise_std=5.0, max_spots=3)[0]
    assert torch.equal(top.centroid, s.centroid[:3])
    # pure noise: nothing
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0)
    noise = cam.expose(torch.zeros(4, 96, 96, dtype=F64), generator=torch.Generator().manual_seed(9)) - 100.0
    assert [len(x) for x in find_spots(noise, noise_std=5.0)] == [0, 0, 0, 0]


def test_find_spots_batch_equals_single():
    frame, _, _ = grid_frame(seed=4)
    stack = torch.stack([frame, frame.flip(-1), torch.zeros_like(frame)])
    many = find_spots(stack, noise_std=5.0)
    assert len(many) == 3 and len(many[2]) == 0
    for b in range(2):
        one = find_spots(stack[b], noise_std=5.0)[0]
        assert torch.equal(one.centroid, many[b].centroid) and torch.equal(one.box, many[b].box)


# --------------------------------------------------------------------------- crops


def test_crop_pixels_offsets_and_clamping():
    img = torch.arange(10 * 12, dtype=F64).reshape(10, 12)
    c, off = crop(img, torch.tensor([5.2, 4.6], dtype=F64), (3, 5))
    assert off.tolist() == [3, 4] and off.dtype == torch.long
    assert torch.equal(c, img[4:7, 3:8])
    # even size: centred between pixels
    _, off = crop(img, torch.tensor([5.5, 4.5], dtype=F64), (4, 4))
    assert off.tolist() == [4, 3]
    # clamped at every edge, always the full size
    centers = torch.tensor([[0.0, 0.0], [11.0, 9.0], [-3.0, 20.0], [6.0, 5.0]], dtype=F64)
    cs, offs = crop(img, centers, (4, 6))
    assert cs.shape == (4, 4, 6)
    assert offs.tolist() == [[0, 0], [6, 6], [0, 6], [4, 4]]  # even sizes round half up
    for k in range(4):
        x0, y0 = offs[k].tolist()
        assert torch.equal(cs[k], img[y0:y0 + 4, x0:x0 + 6])
    # batch of images with one centre each
    imgs = torch.stack([img, -img])
    cb, ob = crop(imgs, centers[:2], 3)
    assert torch.equal(cb[1], -img[ob[1, 1]:ob[1, 1] + 3, ob[1, 0]:ob[1, 0] + 3])


# --------------------------------------------------------------------------- PSF fit


def test_fit_gaussian_psf_noise_free_is_exact():
    psf = tilted_psf()
    img = still_image(psf, 32, 32) + 30.0
    fit = fit_gaussian_psf(img, exposure_s=TE)
    assert bool(fit.converged)
    rel = lambda a, b: float((a - b).abs().max() / b.abs().max())  # noqa: E731
    assert rel(fit.psf.cov, psf.cov) < 1e-6
    assert rel(fit.psf.center, psf.center) < 1e-6
    assert rel(fit.psf.amplitude, psf.amplitude) < 1e-6
    assert abs(float(fit.background) - 30.0) < 1e-6
    assert float(fit.relative_residual) < 1e-9
    # the model IS the renderer's image of the fitted PSF (default settings: adaptive nodes)
    assert float((still_image(fit.psf, 32, 32) + fit.background - fit.model).abs().max()) < 1e-10 * 2000
    assert torch.allclose(fit.model, img, rtol=0, atol=1e-6 * 2000)


@pytest.mark.parametrize("pixel_integration", [True, False])
def test_fit_gaussian_psf_jacobian_equals_forward_ad_of_the_renderer(pixel_integration):
    """The PSF fit's closed-form Jacobian (image/psf_fit._still_jacobian) is the renderer's own
    derivative: torch.func.jacfwd through the model, a batch of three with a tilted, a narrow and
    an untilted (L10 = 0) spot, with and without background."""
    from torch.func import jacfwd

    from torchblur.image.psf_fit import _psf_model, _psf_problem

    theta = torch.tensor([[10.3, 9.1, math.log(1.3), 0.4, math.log(0.9), 1.2, 0.1],
                          [11.0, 8.0, math.log(0.5), -0.2, math.log(0.7), 0.8, -0.3],
                          [9.0, 12.0, math.log(2.0), 0.0, math.log(1.5), 1.0, 0.0]], dtype=torch.float64)
    expo = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    for bg in (True, False):
        pb = _psf_problem(torch.rand(3, 20, 24, dtype=torch.float64), expo, None, None, bg, pixel_integration)
        model_fn, jac_fn, _ = _psf_model(pb, expo + 1, expo * 2)
        idx = torch.arange(3)
        th = theta if bg else theta[:, :6]
        model, J = jac_fn(th, idx)
        ref = jacfwd(lambda t: model_fn(t, idx))(th)  # [3, R, 3, P]: the batch together (its sub-pixel count is the batch's)
        assert torch.equal(model, model_fn(th, idx))
        torch.testing.assert_close(J, torch.stack([ref[i, :, i] for i in range(3)]), rtol=0, atol=1e-12 * float(ref.abs().max()))


def test_fit_gaussian_psf_float32_in_float32_out():
    psf = tb.GaussianPSF.from_axes(torch.tensor([9.6, 10.2], dtype=F64), torch.tensor(2.0, dtype=F64),
                                   torch.tensor(1.6, dtype=F64), torch.tensor(-0.4, dtype=F64), amplitude=torch.tensor(1e5, dtype=F64))
    img = still_image(psf, 20, 20).float()
    fit = fit_gaussian_psf(img, exposure_s=TE, fit_background=False)
    assert fit.psf.cov.dtype == torch.float32 and fit.model.dtype == torch.float32 and fit.cov_std.dtype == torch.float32
    assert float(fit.background) == 0.0
    assert float((fit.psf.cov.double() - psf.cov).abs().max()) < 1e-4


def noisy_still(psf, n, seed, background=30.0, size=32):
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0)
    expected = still_image(psf, size, size) + background
    frames = cam.expose(expected.expand(n, size, size), generator=torch.Generator().manual_seed(seed))
    return frames - 100.0, cam.noise.std(expected)


def test_fit_gaussian_psf_noisy_within_reported_uncertainty():
    psf = tilted_psf()
    data, sigma = noisy_still(psf, 16, seed=21)
    fit = fit_gaussian_psf(data, exposure_s=TE, noise_std=sigma)
    assert fit.psf.shape == (16,) and fit.cov_std.shape == (16, 2, 2) and bool(fit.converged.all())
    z = (fit.psf.cov - psf.cov) / fit.cov_std
    assert float(z[0].abs().max()) < 3  # one image: each covariance entry within 3 std
    # calibration over 16 images: the reported std is the scatter (rms z-score ~ 1)
    # (pooled over the three entries: 16 draws alone scatter the rms by ~18%)
    zu = torch.stack([z[:, 0, 0], z[:, 0, 1], z[:, 1, 1]])
    assert 0.7 < float(zu.square().mean().sqrt()) < 1.35
    zc = (fit.psf.center - psf.center) / fit.center_std
    assert 0.6 < float(zc.square().mean().sqrt()) < 1.5
    # noise-level residual: shot + read noise of ~ 2000 e- peak is ~0.5% of the peak
    assert float(fit.relative_residual.max()) < 0.01
    # unweighted fit: sandwich uncertainty, also within 3 std
    fit0 = fit_gaussian_psf(data[:2], exposure_s=TE)
    assert float(((fit0.psf.cov - psf.cov) / fit0.cov_std).abs().max()) < 3


def test_fit_gaussian_psf_batch_equals_single():
    psf = tilted_psf()
    data, sigma = noisy_still(psf, 2, seed=8)
    both = fit_gaussian_psf(data, exposure_s=torch.tensor([TE, TE], dtype=F64), noise_std=sigma)
    for b in range(2):
        one = fit_gaussian_psf(data[b], exposure_s=TE, noise_std=sigma)
        assert torch.allclose(one.psf.cov, both.psf.cov[b], rtol=1e-8, atol=1e-10)
        assert torch.allclose(one.cov_std, both.cov_std[b], rtol=1e-6)


def test_fit_gaussian_psf_flags_wrong_shape():
    # A double spot is no Gaussian: the residual is a large fraction of the peak.
    psf = tilted_psf()
    other = tb.GaussianPSF(psf.center + torch.tensor([5.0, -2.0], dtype=F64), psf.cov, psf.amplitude * 0.7)
    img = still_image(psf, 32, 32) + still_image(other, 32, 32)
    data = CameraModel(dark_level_adu=0.0, read_noise_e=5.0).expose(img, generator=torch.Generator().manual_seed(1))
    bad = fit_gaussian_psf(data, exposure_s=TE)
    good = fit_gaussian_psf(noisy_still(psf, 1, seed=2)[0][0], exposure_s=TE)
    assert float(good.relative_residual) < 0.01
    assert float(bad.relative_residual) > 0.03 and float(bad.relative_residual) > 5 * float(good.relative_residual)


def test_fit_with_saturation_mask_recovers_clipped_spot():
    # Peak 6000 e- on a 12-bit camera (dark 100): the core clips at 4095 ADU.
    psf = tilted_psf(peak_e=6000.0)
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0)
    raw = cam.expose(still_image(psf, 32, 32), generator=torch.Generator().manual_seed(4))
    clipped = cam.saturated_mask(raw)
    assert int(clipped.sum()) > 5
    t = torch.linspace(0.0, 0.06, 25, dtype=F64)
    peaks = (100 + 1e5 * t + 5 * torch.randn(25, generator=torch.Generator().manual_seed(6), dtype=F64)).round().clamp(max=4095)
    curve = saturation_curve(peaks, t)
    usable = curve.mask(raw)
    assert not bool((usable & clipped).any())
    fit = fit_gaussian_psf(raw - 100.0, exposure_s=TE, mask=usable)
    naive = fit_gaussian_psf(raw - 100.0, exposure_s=TE)
    err = lambda f: float(((f.psf.cov - psf.cov) / f.cov_std).abs().max())  # noqa: E731
    assert err(fit) < 3
    assert abs(float(fit.psf.amplitude / psf.amplitude) - 1) < 0.01
    assert abs(float(naive.psf.amplitude / psf.amplitude) - 1) > 0.1  # fitting clipped pixels fails


# --------------------------------------------------------------------------- saturation


def test_saturation_curve_recovers_slope_and_plateau():
    g = torch.Generator().manual_seed(6)
    t = torch.linspace(0.0, 0.06, 25, dtype=F64)
    true = 100 + 1e5 * t
    peaks = (true + 5 * torch.randn(25, generator=g, dtype=F64)).round().clamp(max=4095)
    perm = torch.randperm(25, generator=g)  # order must not matter
    c = saturation_curve(peaks[perm], t[perm])
    assert c.saturated_in_data
    assert abs(float(c.slope_adu_per_s) / 1e5 - 1) < 0.01
    assert abs(float(c.saturation_adu) / 4095 - 1) < 0.01
    assert abs(float(c.linear_limit_s) - 3995 / 1e5) < 0.01 * 0.04
    assert abs(float(c.offset_adu) - 100) < 10
    assert 0.03 <= float(c.linear_limit_s) < 0.05  # the peak is on the line at 30 ms, not at 50 ms
    assert float((c(t) - torch.minimum(true, torch.tensor(4095.0, dtype=F64))).abs().max()) < 20
    m = c.mask(torch.tensor([100.0, 3000.0, 4000.0, 4090.0, 4095.0], dtype=F64))
    assert m.tolist() == [True, True, True, False, False]
    assert c.mask(torch.tensor([4090.0], dtype=F64), margin_adu=0.0).tolist() == [True]
    # only the linear part sampled: no plateau in the data, the full scale closes the line
    lin = saturation_curve(peaks[:15], t[:15], full_scale_adu=4095.0)
    assert not lin.saturated_in_data
    assert abs(float(lin.slope_adu_per_s) / 1e5 - 1) < 0.01
    assert float(lin.saturation_adu) == 4095.0
    assert math.isinf(float(saturation_curve(peaks[:15], t[:15]).saturation_adu))


# --------------------------------------------------------------------------- bad input

NAN = float("nan")


def _psf_img():
    return still_image(tilted_psf(), 32, 32)


BAD = [
    ("NaN dark frames", lambda: dark_frame(torch.full((4, 8, 8), NAN, dtype=F64)), ParameterError, "frames"),
    ("1-D dark frames", lambda: dark_frame(torch.zeros(8, dtype=F64)), ShapeError, "frames"),
    ("a single dark frame", lambda: dark_frame(torch.zeros(1, 8, 8, dtype=F64)), ShapeError, "frames"),
    ("dark not a DarkFrame", lambda: subtract_dark(torch.zeros(8, 8), "dark"), InputTypeError, "dark"),
    ("dark of another size", lambda: subtract_dark(torch.zeros(8, 8, dtype=F64), dark_frame(torch.zeros(2, 6, 6, dtype=F64))), ShapeError, "dark"),
    ("1-D spot image", lambda: find_spots(torch.zeros(8, dtype=F64), noise_std=1.0), ShapeError, "image"),
    ("zero noise", lambda: threshold_mask(torch.zeros(8, 8, dtype=F64), 0.0), ParameterError, "noise_std"),
    ("NaN spot image", lambda: find_spots(torch.full((8, 8), NAN, dtype=F64), noise_std=1.0), ParameterError, "image"),
    ("crop larger than frame", lambda: crop(torch.zeros(8, 8), torch.zeros(2), (9, 3)), ParameterError, "size"),
    ("crop centre not (x, y)", lambda: crop(torch.zeros(8, 8), torch.zeros(3), (3, 3)), ShapeError, "center_xy"),
    ("crop NaN centre", lambda: crop(torch.zeros(8, 8), torch.tensor([NAN, 1.0]), (3, 3)), ParameterError, "center_xy"),
    ("negative exposure", lambda: fit_gaussian_psf(_psf_img(), exposure_s=-0.01), ParameterError, "exposure_s"),
    ("1-D psf image", lambda: fit_gaussian_psf(torch.zeros(32, dtype=F64), exposure_s=TE), ShapeError, "image"),
    ("NaN psf image", lambda: fit_gaussian_psf(torch.full((16, 16), NAN, dtype=F64), exposure_s=TE), ParameterError, "image"),
    ("mask of another size", lambda: fit_gaussian_psf(_psf_img(), exposure_s=TE, mask=torch.ones(31, 32, dtype=torch.bool)), ShapeError, "mask"),
    ("mask not bool", lambda: fit_gaussian_psf(_psf_img(), exposure_s=TE, mask=torch.ones(32, 32)), InputTypeError, "mask"),
    ("mask batch mismatch", lambda: fit_gaussian_psf(_psf_img().expand(2, 32, 32), exposure_s=TE, mask=torch.ones(3, 32, 32, dtype=torch.bool)), ShapeError, "mask"),
    ("negative noise", lambda: fit_gaussian_psf(_psf_img(), exposure_s=TE, noise_std=-1.0), ParameterError, "noise_std"),
    ("peaks not 1-D", lambda: saturation_curve(torch.zeros(2, 5), torch.zeros(2, 5)), ShapeError, "peak_adu"),
    ("exposure count", lambda: saturation_curve(torch.arange(5.0), torch.arange(4.0)), ShapeError, "exposures_s"),
    ("negative exposure time", lambda: saturation_curve(torch.arange(5.0), torch.arange(5.0) - 1), ParameterError, "exposures_s"),
    ("two exposures only", lambda: saturation_curve(torch.arange(4.0), torch.tensor([0.0, 0.0, 1.0, 1.0])), ParameterError, "exposures_s"),
]


@pytest.mark.parametrize("desc,fn,exc,name", BAD, ids=[b[0] for b in BAD])
def test_bad_input_raises_named_error(desc, fn, exc, name):
    with pytest.raises(exc) as info:
        fn()
    assert type(info.value) is exc
    assert name in str(info.value)
