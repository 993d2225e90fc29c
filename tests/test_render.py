"""Renderer: accuracy against adaptive quadrature, gradients, batching, analytic cases."""
import math

import numpy as np
import pytest
import torch
from scipy.special import erf

import torchblur as tb
from conftest import make_case
from reference import dense_render, quad_render
from torchblur.render.blur import RenderSettings, choose_node_count

H = W = 40


@pytest.mark.parametrize("tilted", [True, False])
def test_accuracy_against_adaptive_quadrature(tilted):
    traj, psf, win = make_case(tilted=tilted)
    ref = quad_render(traj, psf, win, H, W)
    peak = ref.max()
    img64 = tb.render_blur(traj, psf, win, height=H, width=W).numpy()
    assert np.abs(img64 - ref).max() <= 1e-6 * peak
    t32, p32, w32 = traj.to(torch.float32), psf.to(torch.float32), win.to(torch.float32)
    img32 = tb.render_blur(t32, p32, w32, height=H, width=W)
    assert img32.dtype == torch.float32
    assert np.abs(img32.double().numpy() - ref).max() <= 1e-4 * peak


def test_fast_motion_of_twenty_psf_widths_several_periods():
    # A 0.9 px-wide tilted spot, 22 px amplitude (24 sigma), 2.3 periods: the nodes follow the path.
    psf = tb.GaussianPSF.from_axes(torch.tensor([30.2, 29.6], dtype=torch.float64), 1.4, 0.9, -0.7)
    traj = tb.Sinusoid(torch.tensor([22.0, 9.0], dtype=torch.float64), torch.tensor([0.2, 2.0], dtype=torch.float64), 2 * math.pi * 250)
    win = tb.ExposureWindow(1e-4, 2.3 / 250)
    ref = quad_render(traj, psf, win, 60, 60, epsabs=1e-12, epsrel=1e-9)
    img = tb.render_blur(traj, psf, win, height=60, width=60).numpy()
    assert np.abs(img - ref).max() <= 1e-6 * ref.max()
    S = choose_node_count(traj.path_length(win), psf.sigma_min(), RenderSettings())
    assert S > 256  # adaptive: far more than a fixed count
    coarse = tb.render_blur(traj, psf, win, height=60, width=60, settings=RenderSettings(nodes=32)).numpy()
    assert np.abs(coarse - ref).max() > 1e-2 * ref.max()  # a fixed count fails here


def test_node_count_grows_with_path_length():
    psf = tb.GaussianPSF.isotropic(torch.zeros(2), 2.0)
    win = tb.ExposureWindow(0.0, 5e-3)
    counts = [choose_node_count(tb.Sinusoid(torch.tensor([a, 0.0]), torch.zeros(2), 2 * math.pi * 100).path_length(win),
                                psf.sigma_min(), RenderSettings()) for a in (0.0, 5.0, 20.0, 80.0)]
    assert counts[0] == 8 and counts == sorted(counts) and counts[-1] >= 8 * counts[1]


def test_exact_path_length_of_a_sine():
    g = torch.Generator().manual_seed(3)
    A = torch.rand(50, 2, generator=g, dtype=torch.float64) * 10
    ph = torch.rand(50, 2, generator=g, dtype=torch.float64) * 6 - 3
    traj = tb.Sinusoid(A, ph, 2 * math.pi * 37.0)
    win = tb.ExposureWindow(torch.rand(50, generator=g, dtype=torch.float64) * 0.1, 0.061)
    t = win.start[:, None] + win.duration[:, None] * torch.linspace(0, 1, 100001, dtype=torch.float64)
    tv = traj.position(t).diff(dim=-2).abs().sum((-1, -2))
    torch.testing.assert_close(traj.path_length(win), tv, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("tilted", [True, False])
def test_matches_dense_reference_values_and_gradients(tilted):
    traj, psf, win = make_case(tilted=tilted, batch=(3,))
    S = 96
    params = [traj.amplitude.clone().requires_grad_(), traj.phase.clone().requires_grad_(),
              psf.center.clone().requires_grad_(), psf.cov.clone().requires_grad_()]

    def both():
        t = tb.Sinusoid(params[0], params[1], traj.omega)
        p = tb.GaussianPSF(params[2], params[3], psf.amplitude)
        fast = tb.render_blur(t, p, win, height=H, width=W, settings=RenderSettings(nodes=S))
        dense = dense_render(t, p, win, H, W, S)
        return fast, dense

    fast, dense = both()
    torch.testing.assert_close(fast, dense, rtol=0, atol=1e-12 * float(dense.detach().max()))
    weights = torch.rand(fast.shape, generator=torch.Generator().manual_seed(0), dtype=fast.dtype)
    g_fast = torch.autograd.grad((fast * weights).sum(), params)
    g_dense = torch.autograd.grad((dense * weights).sum(), params)
    for a, b in zip(g_fast, g_dense):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("tilted", [True, False])
def test_gradcheck_all_parameters(tilted):
    traj, psf, win = make_case(tilted=tilted)
    small = 10
    amp = (traj.amplitude / 4).clone().requires_grad_()
    ph = traj.phase.clone().requires_grad_()
    om = traj.omega[..., 0].clone().requires_grad_()
    cen = torch.tensor([4.6, 5.2], dtype=torch.float64, requires_grad=True)
    cov = psf.cov.clone().requires_grad_()
    a = psf.amplitude.clone().requires_grad_()
    st = win.start.clone().requires_grad_()
    du = win.duration.clone().requires_grad_()
    settings = RenderSettings(nodes=24)

    def f(amp, ph, om, cen, cov, a, st, du):
        cov = 0.5 * (cov + cov.transpose(-1, -2))
        return tb.render_blur(tb.Sinusoid(amp, ph, om), tb.GaussianPSF(cen, cov, a), tb.ExposureWindow(st, du),
                              height=small, width=small, settings=settings)

    assert torch.autograd.gradcheck(f, (amp, ph, om, cen, cov, a, st, du), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_batch_equals_stacked_singles():
    traj, psf, win = make_case(batch=(4,))
    windows = tb.ExposureWindow(torch.tensor([0.0, 1e-3, 2e-3, 3e-3], dtype=torch.float64), win.duration)
    batch = tb.render_blur(traj, psf, windows, height=H, width=W)
    settings = RenderSettings(nodes=choose_node_count(traj.path_length(windows), psf.sigma_min(), RenderSettings()))
    for k in range(4):
        single = tb.render_blur(traj[k], psf[k], windows[k], height=H, width=W, settings=settings)
        torch.testing.assert_close(batch[k], single, rtol=0, atol=1e-13)


def test_still_spot_is_psf_times_exposure():
    psf = tb.GaussianPSF.from_axes(torch.tensor([12.3, 9.8], dtype=torch.float64), 2.0, 1.1, 0.8, amplitude=5.0)
    traj = tb.Sinusoid(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), 100.0)
    te = 0.0123
    img = tb.render_blur(traj, psf, tb.ExposureWindow(0.3, te), height=24, width=26)
    x = torch.arange(26, dtype=torch.float64)
    y = torch.arange(24, dtype=torch.float64)[:, None]
    torch.testing.assert_close(img, te * psf.evaluate(x, y), rtol=1e-13, atol=1e-15)


def test_total_light():
    traj, psf, win = make_case()
    psf = tb.GaussianPSF(psf.center + 12.0, psf.cov, psf.amplitude)  # well inside the 64x64 frame
    img = tb.render_blur(traj, psf, win, height=64, width=64)
    expected = psf.total_light() * win.duration
    torch.testing.assert_close(img.sum(), expected, rtol=1e-10, atol=0)


def test_gaussian_and_kernel_psf_share_moments_light_and_items():
    # A measured kernel of a still Gaussian spot (sigma >= 1.5 px, 8 sigmas inside the frame) has
    # the Gaussian's moments and light; both index their batch alike, psf[..., None] included.
    g = tb.GaussianPSF(torch.tensor([[14.2, 15.7], [16.0, 13.1]], dtype=torch.float64),
                       torch.tensor([[[2.5, 0.4], [0.4, 3.0]], [[4.0, -0.5], [-0.5, 2.25]]], dtype=torch.float64),
                       torch.tensor([1.5, 0.7], dtype=torch.float64))
    x, y = torch.arange(32, dtype=torch.float64), torch.arange(30, dtype=torch.float64)[:, None]
    k = tb.KernelPSF(g[:, None, None].evaluate(x, y))  # [2, 30, 32]
    assert k.shape == g.shape == (2,)
    torch.testing.assert_close(k.total_light(), g.total_light(), rtol=1e-12, atol=0)
    for got, want in zip(k.moments(), g.moments()):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    assert g.moments()[0] is g.center and g.moments()[1] is g.cov
    for idx in (1, torch.tensor([1, 0]), torch.tensor([False, True]), (..., None), (None, ...)):
        gi, ki = g[idx], k[idx]
        assert gi.shape == ki.shape == g.amplitude[idx].shape
        torch.testing.assert_close(ki.total_light(), k.total_light()[idx], rtol=0, atol=0)
        torch.testing.assert_close(gi.total_light(), g.total_light()[idx], rtol=0, atol=0)
        torch.testing.assert_close(ki.moments()[0], gi.center, rtol=0, atol=1e-9)
    # cut to a crop [y0:y1, x0:x1] of the frame, both are the spot in the crop's frame
    gc, kc = g.cropped(5, 3, 27, 25), k.cropped(5, 3, 27, 25)
    assert kc.frame_shape == (22, 22) and gc.shape == kc.shape == g.shape
    torch.testing.assert_close(kc.kernel, gc[:, None, None].evaluate(x[:22], y[:22]), rtol=0, atol=1e-15)


def test_psf_footprint_holds_the_spot():
    # A Gaussian's box is `sigmas` standard deviations along x and y; a kernel cut to that box has
    # it (to whole pixels) as its footprint, whatever `sigmas` says; an item's box is the batch's.
    g = tb.GaussianPSF(torch.tensor([[14.2, 15.7], [16.0, 13.1]], dtype=torch.float64),
                       torch.tensor([[[2.5, 0.4], [0.4, 3.0]], [[4.0, -0.5], [-0.5, 2.25]]], dtype=torch.float64))
    lo, hi = g.footprint(3.0)
    sd = torch.diagonal(g.cov, dim1=-2, dim2=-1).sqrt()
    torch.testing.assert_close(lo, g.center - 3 * sd, rtol=0, atol=0)
    torch.testing.assert_close(hi, g.center + 3 * sd, rtol=0, atol=0)
    x, y = torch.arange(32, dtype=torch.float64), torch.arange(30, dtype=torch.float64)
    inside = (((x >= lo[:, None, None, 0]) & (x <= hi[:, None, None, 0]))
              & ((y[:, None] >= lo[:, None, None, 1]) & (y[:, None] <= hi[:, None, None, 1])))
    k = tb.KernelPSF(g[:, None, None].evaluate(x, y[:, None]) * inside)
    for s in (None, 1.0, 7.0):
        klo, khi = k.footprint(s)
        torch.testing.assert_close(klo, lo.ceil(), rtol=0, atol=0)
        torch.testing.assert_close(khi, hi.floor(), rtol=0, atol=0)
    torch.testing.assert_close(k[1].footprint()[0], klo[1], rtol=0, atol=0)
    torch.testing.assert_close(g[1].footprint(3.0)[1], hi[1], rtol=0, atol=0)


def test_pixel_integration_exact_for_narrow_spots():
    # Axis-aligned still spot: the pixel integral is a product of erf differences.
    sx, sy, cx, cy, te = 0.5, 0.7, 7.3, 6.6, 0.01
    psf = tb.GaussianPSF(torch.tensor([cx, cy], dtype=torch.float64), torch.diag(torch.tensor([sx**2, sy**2], dtype=torch.float64)))
    traj = tb.Sinusoid(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), 10.0)
    img = tb.render_blur(traj, psf, tb.ExposureWindow(0.0, te), height=14, width=15,
                         settings=RenderSettings(pixel_integration=True)).numpy()
    x = np.arange(15)
    y = np.arange(14)
    ix = sx * math.sqrt(math.pi / 2) * (erf((x + 0.5 - cx) / (sx * math.sqrt(2))) - erf((x - 0.5 - cx) / (sx * math.sqrt(2))))
    iy = sy * math.sqrt(math.pi / 2) * (erf((y + 0.5 - cy) / (sy * math.sqrt(2))) - erf((y - 0.5 - cy) / (sy * math.sqrt(2))))
    np.testing.assert_allclose(img, te * iy[:, None] * ix[None, :], rtol=0, atol=1e-9 * img.max())
    # Tilted, moving, narrow: total light holds for any sigma with pixel integration.
    psf = tb.GaussianPSF.from_axes(torch.tensor([20.0, 21.0], dtype=torch.float64), 0.6, 0.45, 0.4)
    traj = tb.Sinusoid(torch.tensor([6.0, 3.0], dtype=torch.float64), torch.tensor([0.1, 0.9], dtype=torch.float64), 600.0)
    img = tb.render_blur(traj, psf, tb.ExposureWindow(0.0, te), height=42, width=42, settings=RenderSettings(pixel_integration=True))
    torch.testing.assert_close(img.sum(), psf.total_light() * te, rtol=1e-8, atol=0)


def test_constant_velocity_streak_is_erf_edged():
    # Over a short window around the zero crossing, a small-amplitude fast sine is ~linear;
    # use a spline with two knots: exactly constant velocity.
    v, te, s = 400.0, 0.02, 1.5  # px/s, s, px: an 8 px streak
    cx, cy = 10.2, 8.0
    traj = tb.SplineTrajectory(torch.tensor([0.0, te], dtype=torch.float64), torch.tensor([[0.0, 0.0], [v * te, 0.0]], dtype=torch.float64))
    psf = tb.GaussianPSF.isotropic(torch.tensor([cx, cy], dtype=torch.float64), s)
    img = tb.render_blur(traj, psf, tb.ExposureWindow(0.0, te), height=16, width=30).numpy()
    x = np.arange(30)[None, :]
    y = np.arange(16)[:, None]
    k = s * math.sqrt(2)
    expected = np.exp(-((y - cy) ** 2) / (2 * s * s)) * (s * math.sqrt(math.pi / 2) / v) * (erf((x - cx) / k) - erf((x - cx - v * te) / k))
    np.testing.assert_allclose(img, expected, rtol=0, atol=1e-10 * expected.max())


def test_measured_kernel_matches_gaussian_for_band_limited_spot():
    traj, psf, win = make_case(tilted=True)
    psf = tb.GaussianPSF.from_axes(torch.tensor([31.0, 30.0], dtype=torch.float64), 2.6, 2.1, 0.5)
    te_still = 0.05
    still = tb.render_blur(tb.Sinusoid(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), 1.0),
                           psf, tb.ExposureWindow(0.0, te_still), height=64, width=64)
    kernel = tb.KernelPSF(still, exposure_s=te_still)
    img_k = tb.render_blur(traj, kernel, win, height=64, width=64)
    img_g = tb.render_blur(traj, psf, win, height=64, width=64)
    assert float((img_k - img_g).abs().max()) <= 1e-6 * float(img_g.max())
    # differentiable in the trajectory
    amp = traj.amplitude.clone().requires_grad_()
    out = tb.render_blur(tb.Sinusoid(amp, traj.phase, traj.omega), kernel, win, height=64, width=64)
    (g,) = torch.autograd.grad(out.square().sum(), amp)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_module_matches_function_with_non_default_settings():
    traj, psf, win = make_case()
    mod = tb.BlurRenderer(height=20, width=30, pixel_integration=True, nodes_per_panel=6, panel_path_sigmas=1.5)
    fn = tb.render_blur(trajectory=traj, psf=psf, window=win, height=20, width=30,
                        settings=RenderSettings(pixel_integration=True, nodes_per_panel=6, panel_path_sigmas=1.5))
    torch.testing.assert_close(mod(traj, psf, win), fn, rtol=0, atol=0)
    assert "pixel_integration=True" in repr(mod)


def test_spline_is_natural_cubic():
    from scipy.interpolate import CubicSpline

    t = torch.tensor([0.0, 0.3, 0.5, 1.1, 1.6], dtype=torch.float64)
    v = torch.tensor([[0.0, 1.0], [2.0, -1.0], [1.0, 0.5], [-3.0, 2.0], [0.5, 0.0]], dtype=torch.float64)
    spl = tb.SplineTrajectory(t, v)
    q = torch.linspace(0, 1.6, 97, dtype=torch.float64)
    ref = CubicSpline(t.numpy(), v.numpy(), bc_type="natural")(q.numpy())
    np.testing.assert_allclose(spl.position(q).numpy(), ref, atol=1e-12)


def test_multisine_is_sum_of_tones():
    g = torch.Generator().manual_seed(5)
    A = torch.rand(3, 2, generator=g, dtype=torch.float64)
    P = torch.rand(3, 2, generator=g, dtype=torch.float64)
    om = torch.tensor([100.0, 230.0, 410.0], dtype=torch.float64)
    ms = tb.Multisine(A, P, om)
    t = torch.linspace(0, 0.05, 33, dtype=torch.float64)
    parts = sum(tb.Sinusoid(A[n], P[n], om[n]).position(t) for n in range(3))
    torch.testing.assert_close(ms.position(t), parts)


def test_per_axis_frequency_lissajous():
    traj = tb.Sinusoid(torch.tensor([3.0, 2.0]), torch.tensor([0.0, 0.5]), torch.tensor([100.0, 150.0]))
    t = torch.tensor([0.01, 0.02])
    pos = traj.position(t)
    torch.testing.assert_close(pos[:, 1], 2.0 * torch.sin(150.0 * t + 0.5))


def test_alias_phase_renders_the_same_image():
    g = torch.Generator().manual_seed(11)
    for _ in range(5):
        f = float(20 + 800 * torch.rand((), generator=g))
        om = 2 * math.pi * f
        te = float(0.2 + 0.7 * torch.rand((), generator=g)) / f
        win = tb.ExposureWindow(torch.tensor(float(torch.rand((), generator=g)) / f, dtype=torch.float64), te)
        phi = torch.tensor(float(6 * torch.rand((), generator=g) - 3), dtype=torch.float64)
        phi2 = tb.alias_phase(phi, om, win)
        psf = tb.GaussianPSF.from_axes(torch.tensor([24.0, 23.0], dtype=torch.float64), 2.0, 1.3, 0.3)
        direction = torch.tensor([0.8, 0.6], dtype=torch.float64)
        imgs = [tb.render_blur(tb.Sinusoid(9.0 * direction, p.expand(2), om), psf, win, height=48, width=48) for p in (phi, phi2)]
        assert float((imgs[0] - imgs[1]).abs().max()) <= 1e-12 * float(imgs[0].max())
        assert abs(float(tb.wrap_phase(phi2 - phi))) > 1e-3  # genuinely different phase


def test_alias_formula_paper_settings():
    # p = pi, b = pi/2: phi2 = pi - pi - pi - phi = -pi - phi.
    f = 100.0
    win = tb.ExposureWindow(torch.tensor(0.25 / f, dtype=torch.float64), 0.5 / f)
    phi = torch.tensor(0.3, dtype=torch.float64)
    torch.testing.assert_close(tb.alias_phase(phi, 2 * math.pi * f, win), tb.wrap_phase(-math.pi - phi))


def test_dtype_follows_inputs():
    for dtype in (torch.float32, torch.float64):
        traj, psf, win = make_case(dtype=dtype)
        assert tb.render_blur(traj, psf, win, height=8, width=8).dtype == dtype


@pytest.mark.parametrize("ratio, periods, phase", [(0.1, 0.9, 0.0), (0.7, 0.875, 0.0), (1.0, 1.0, 1.0), (0.3, 1.5, 2.2), (1.5, 0.75, 0.4)])
def test_small_motion_over_most_of_a_period_is_integrated_exactly(ratio, periods, phase):
    """The node rule also bounds the phase per panel: a motion shorter than the PSF over most
    of a period used to get one 8-node panel (2.5e-4 of the peak off)."""
    om = torch.tensor(2 * math.pi * 20.0, dtype=torch.float64)
    sigma = 1.75
    psf = tb.GaussianPSF.isotropic(torch.tensor([13.5, 11.5], dtype=torch.float64), sigma)
    win = tb.ExposureWindow(torch.tensor(0.0, dtype=torch.float64), torch.tensor(periods / 20.0, dtype=torch.float64))
    traj = tb.Sinusoid(torch.tensor([ratio * sigma, 0.0], dtype=torch.float64), torch.tensor([phase, phase], dtype=torch.float64), om)
    ref = tb.render_blur(traj, psf, win, height=24, width=28, settings=RenderSettings(nodes=2048))
    img = tb.render_blur(traj, psf, win, height=24, width=28)
    assert float((img - ref).abs().max() / ref.max()) < 1e-6
    assert choose_node_count(traj.path_length(win), psf.sigma_min(), RenderSettings(), traj.phase_span(win)) >= 8 * math.ceil(
        2 * math.pi * periods / (2 * math.pi / 3))
