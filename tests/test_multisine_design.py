"""Multisine identifiability (Fisher information), the image-set design and the fit of the tones."""
import math

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwAD

from torchblur.fit.status import POOR_FIT
from torchblur.errors import ShapeError
from torchblur.design.fisher import candidate_windows, design_acquisition, image_fisher, predicted_std
from torchblur.fit.multisine import fit_multisine, render_multisine, render_multisine_with_jacobian
from torchblur.render.psf import GaussianPSF
from torchblur.render.window import ExposureWindow

F64 = torch.float64
F0 = 100 / 3
T0 = 1 / F0
OM = 2 * math.pi * F0 * torch.tensor([3.0, 4.0, 5.0], dtype=F64)
THETA = torch.tensor([3.0, 2.0, 2.5, 0.4, -2.0, 1.3, 1.0], dtype=F64)  # M (px), phi (rad), scale
H, W = 24, 40
PSF = GaussianPSF(torch.tensor([19.5, 11.5], dtype=F64), 4 * torch.eye(2, dtype=F64), torch.tensor(2000 / 3e-3, dtype=F64))


def windows(fracs_start, fracs_dur):
    return ExposureWindow(torch.tensor(fracs_start, dtype=F64) * T0, torch.tensor(fracs_dur, dtype=F64) * T0)


def test_jacobian_from_one_splat_equals_forward_ad_of_the_renderer():
    win = windows([[0.1, 0.55]], [[0.3, 0.2]])
    th = THETA[None]
    psf = GaussianPSF(PSF.center[None], PSF.cov[None], PSF.amplitude[None])
    img, J = render_multisine_with_jacobian(th, OM[None], psf, win, height=H, width=W, nodes=96)
    from torchblur.render.blur import RenderSettings

    settings = RenderSettings(nodes=96)
    ref = render_multisine(th, OM[None], psf, win, height=H, width=W, settings=settings)
    np.testing.assert_allclose(img.numpy(), ref.numpy(), atol=1e-9 * float(ref.max()))
    for k in range(7):
        with fwAD.dual_level():
            tangent = torch.zeros_like(th)
            tangent[0, k] = 1
            out = render_multisine(fwAD.make_dual(th, tangent), OM[None], psf, win, height=H, width=W, settings=settings)
            dk = fwAD.unpack_dual(out).tangent
        np.testing.assert_allclose(J[..., k].numpy(), dk.numpy(), atol=1e-8 * float(dk.abs().max()))


def _old_render_multisine_with_jacobian(theta, omega, psf, window, *, height, width, nodes, nodes_per_panel=8, direction=None):
    """The hand-written node positions and derivatives render_multisine_with_jacobian had before it
    called the one forward model (render.splat.sine_blur_with_jacobian): kept as a reference."""
    from torchblur.render.blur import quadrature_nodes
    from torchblur.render.splat import gaussian_splat_with_jacobian

    n, P = theta.shape
    N = omega.shape[-1]
    m = nodes_per_panel if nodes % nodes_per_panel == 0 else nodes
    tau, wq = quadrature_nodes(nodes // m, m, dtype=theta.dtype, device=theta.device)
    start, dur = window.start.to(theta.dtype), window.duration.to(theta.dtype)
    t = start[..., None] + dur[..., None] * tau  # [n, E, S]
    w = dur[..., None] * wq * psf.amplitude[:, None, None]
    arg = omega[:, None, None, :] * t[..., None] + theta[:, None, None, N:2 * N]  # [n, E, S, N]
    sn, cs = torch.sin(arg), torch.cos(arg)
    Mk = theta[:, None, None, :N]
    u = (torch.tensor([1.0, 0.0], dtype=theta.dtype) if direction is None else torch.as_tensor(direction, dtype=theta.dtype))
    u = (u / u.norm(dim=-1, keepdim=True)).expand(n, 2)
    ux, uy = u[:, 0, None, None], u[:, 1, None, None]
    disp = (Mk * sn).sum(-1)
    px = psf.center[:, 0, None, None] + ux * disp
    py = psf.center[:, 1, None, None] + uy * disp
    d = torch.cat([sn, Mk * cs], -1)
    A, B, C = psf.precision()
    img, dimg = gaussian_splat_with_jacobian(px, py, ux[..., None] * d, uy[..., None] * d, w, A[:, None], B[:, None], C[:, None],
                                             height, width)
    J = dimg.movedim(2, -1)
    if P == 2 * N + 1:
        sc = theta[:, 2 * N, None, None, None]
        J = torch.cat([J * sc[..., None], img[..., None]], -1)
        img = img * sc
    return img, J


@pytest.mark.parametrize("direction", [None, (0.6, -0.8)])
def test_jacobian_on_the_one_forward_model_equals_the_old_hand_written_one(direction):
    """render_multisine_with_jacobian on sine_blur_with_jacobian: the same image and Jacobian as the
    hand-written node derivatives it replaced, to round-off (two items, scale and no scale)."""
    win = windows([[0.1, 0.55], [0.2, 0.7]], [[0.3, 0.2], [0.45, 0.1]])
    psf = GaussianPSF(PSF.center.expand(2, 2), torch.tensor([[4.0, 0.8], [0.8, 3.0]], dtype=F64).expand(2, 2, 2),
                      PSF.amplitude.expand(2))
    th = torch.stack([THETA, THETA + 0.3])
    for P in (6, 7):
        kw = dict(height=H, width=W, nodes=64, direction=direction)
        img, J = render_multisine_with_jacobian(th[:, :P], OM.expand(2, 3), psf, win, **kw)
        ref, Jr = _old_render_multisine_with_jacobian(th[:, :P], OM.expand(2, 3), psf, win, **kw)
        np.testing.assert_allclose(img.numpy(), ref.numpy(), rtol=0, atol=1e-12 * float(ref.abs().max()))
        np.testing.assert_allclose(J.numpy(), Jr.numpy(), rtol=0, atol=1e-12 * float(Jr.abs().max()))


def test_fisher_is_singular_for_whole_period_windows_and_regular_for_the_design():
    amp = THETA[:3]
    # exposures of a whole common period cannot see a time shift: singular
    full = windows([0.0, 0.3, 0.7], [1.0, 1.0, 1.0])
    F_full = image_fisher(THETA[None], OM, PSF, full, frame_shape=(H, W), read_noise_e=5.0).sum(1)
    rel, ph = predicted_std(F_full, amp)
    assert torch.isinf(rel).all() and torch.isinf(ph).all()
    ev = torch.linalg.eigvalsh(F_full[0] / torch.outer(F_full[0].diagonal().sqrt(), F_full[0].diagonal().sqrt()))
    assert float(ev[0] / ev[-1]) < 1e-10
    # a single image: regular only in name (stds of 10-40 %), and it keeps the time-reversal alias
    kw = dict(period_s=T0, max_exposure_s=1.0, frame_shape=(H, W), read_noise_e=5.0, peak_e=2000.0, n_hypotheses=2,
              candidates=candidate_windows(T0, max_exposure_s=1.0, n_offsets=8, exposure_fractions=(0.05, 0.1, 0.3, 0.6, 1.0)))
    one = design_acquisition(amp, OM, PSF, n_images=1, phase=THETA[3:6], **kw)
    des = design_acquisition(amp, OM, PSF, n_images=6, phase=THETA[3:6], **kw)
    assert des.n_images == 6 and len(set(des.window_start_s)) >= 2
    assert np.all(np.isfinite(des.amplitude_rel_std)) and np.all(des.amplitude_rel_std < 0.01) and np.all(des.phase_std < 0.01)
    assert np.all(one.amplitude_rel_std > 10 * des.amplitude_rel_std)
    assert np.all(np.diff(des.log_det) > 0)  # every image adds information
    # auto size: grows until the predicted stds reach the target
    auto = design_acquisition(amp, OM, PSF, target_std=5e-3, max_images=12, **kw)
    assert auto.met_target and np.all(auto.amplitude_rel_std <= 5e-3) and np.all(auto.phase_std <= 5e-3)
    assert 2 <= auto.n_images < 12
    c = candidate_windows(T0, max_exposure_s=0.5 * T0, n_offsets=4, exposure_fractions=(0.1, 0.5, 1.0))
    assert c.shape == (8,) and float(c.duration.max()) == pytest.approx(0.5 * T0)  # capped and deduplicated


def test_noise_free_fit_recovers_the_tones():
    win = windows([0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.3, 0.5, 0.2, 0.7, 0.4, 0.25])
    img = render_multisine(THETA, OM, PSF, win, height=H, width=W)
    fit = fit_multisine(img, PSF, win, OM, n_starts=8, n_refine=2)
    assert bool(fit.converged)
    np.testing.assert_allclose(fit.amplitude.numpy(), THETA[:3].numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.exp(1j * fit.phase.numpy()), np.exp(1j * THETA[3:6].numpy()), atol=1e-6)
    assert float(fit.scale) == pytest.approx(1.0, rel=1e-6)
    with pytest.raises(ShapeError, match="theta"):
        render_multisine(THETA[:5], OM, PSF, win, height=H, width=W)


def test_noisy_fit_is_within_its_stds_and_the_batch_equals_single_items():
    # 6 images = 2N: the centroids alone give a start (linear in M e^{j phi})
    win = windows([0.0, 0.2, 0.45, 0.6, 0.8, 0.9], [1.0, 0.05, 0.1, 0.05, 0.05, 0.1])
    th2 = torch.stack([THETA, torch.tensor([2.0, 3.0, 1.5, -1.0, 0.5, 2.5, 1.0], dtype=F64)])
    img = render_multisine(th2, OM, PSF, win, height=H, width=W)
    noise = torch.sqrt(25 + img) / 1.0
    g = torch.Generator().manual_seed(5)
    noisy = img + noise * torch.randn(img.shape, generator=g, dtype=F64)
    fit = fit_multisine(noisy, PSF, win, OM, noise_std=noise, n_starts=6, n_refine=2, amplitude_guess=th2[:, :3])
    assert fit.converged.all() and fit.amplitude.shape == (2, 3)
    z_m = (fit.amplitude - th2[:, :3]).abs() / fit.amplitude_std
    z_p = torch.remainder(fit.phase - th2[:, 3:6] + math.pi, 2 * math.pi).sub(math.pi).abs() / fit.phase_std
    assert float(z_m.max()) < 5 and float(z_p.max()) < 5
    single = fit_multisine(noisy[1], PSF, win, OM, noise_std=noise[1], n_starts=6, n_refine=2, amplitude_guess=th2[1, :3])
    np.testing.assert_allclose(single.amplitude.numpy(), fit.amplitude[1].numpy(), rtol=1e-7)
    np.testing.assert_allclose(single.phase_std.numpy(), fit.phase_std[1].numpy(), rtol=1e-6)


def test_a_fit_far_above_the_noise_is_searched_again_then_flagged():
    """Images the model cannot explain (tones at other frequencies than fitted): the fit searches
    again from wider starts, and a reduced chi2 still above 3 is status POOR_FIT (6), not 'ok'."""
    win = windows([0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.3, 0.5, 0.2, 0.7, 0.4, 0.25])
    img = render_multisine(THETA, OM * torch.tensor([1.0, 1.5, 2.2], dtype=F64), PSF, win, height=H, width=W)
    noise = torch.sqrt(25 + img)
    g = torch.Generator().manual_seed(2)
    noisy = img + noise * torch.randn(img.shape, generator=g, dtype=F64)
    fit = fit_multisine(noisy, PSF, win, OM, noise_std=noise, n_starts=4, n_refine=1)
    assert bool(fit.extras["retried"]) and float(fit.extras["reduced_chi2"]) > 3
    assert int(fit.status) == POOR_FIT and not bool(fit.converged)
    good = fit_multisine(render_multisine(THETA, OM, PSF, win, height=H, width=W) + noise * torch.randn(img.shape, generator=g,
                                                                                                       dtype=F64),
                         PSF, win, OM, noise_std=noise, n_starts=4, n_refine=1)
    assert bool(good.converged) and float(good.extras["reduced_chi2"]) < 1.5 and not bool(good.extras["retried"])


def test_fit_along_a_rotated_direction_recovers_the_tones():
    """A multisine motion along an axis rotated 30 deg in the image: rendered and fitted along
    that direction, the tones come back exactly (noise-free); the one-splat Jacobian still
    equals forward AD of the renderer; a zero direction is refused naming it."""
    from torchblur.errors import ParameterError
    from torchblur.render.blur import RenderSettings

    u = torch.tensor([math.cos(math.radians(30)), math.sin(math.radians(30))], dtype=F64)
    win = windows([0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.3, 0.5, 0.2, 0.7, 0.4, 0.25])
    img = render_multisine(THETA, OM, PSF, win, height=H, width=W, direction=u)
    along_x = render_multisine(THETA, OM, PSF, win, height=H, width=W)
    assert float((img - along_x).abs().max()) > 0.1 * float(img.max())  # really a different motion
    fit = fit_multisine(img, PSF, win, OM, n_starts=8, n_refine=2, direction=2 * u)  # normalised
    assert bool(fit.converged)
    np.testing.assert_allclose(fit.amplitude.numpy(), THETA[:3].numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.exp(1j * fit.phase.numpy()), np.exp(1j * THETA[3:6].numpy()), atol=1e-6)
    th = THETA[None]
    psf = GaussianPSF(PSF.center[None], PSF.cov[None], PSF.amplitude[None])
    w1 = windows([[0.1, 0.55]], [[0.3, 0.2]])
    _, J = render_multisine_with_jacobian(th, OM[None], psf, w1, height=H, width=W, nodes=96, direction=u)
    with fwAD.dual_level():
        tangent = torch.zeros_like(th)
        tangent[0, 4] = 1.0  # phase of the second tone
        out = render_multisine(fwAD.make_dual(th, tangent), OM[None], psf, w1, height=H, width=W, settings=RenderSettings(nodes=96),
                               direction=u)
        ref = fwAD.unpack_dual(out).tangent
    np.testing.assert_allclose(J[..., 4].numpy(), ref.numpy(), atol=1e-8 * float(ref.abs().max()))
    with pytest.raises(ParameterError, match="direction"):
        fit_multisine(img, PSF, win, OM, direction=(0.0, 0.0))


def test_fisher_information_of_a_round_spot_does_not_depend_on_the_direction():
    """With a round PSF the images of a motion along any direction are rotations of each
    other: the design's Fisher information is the same (to the pixel grid's 1e-5), and "x"
    is the default, bit for bit."""
    psf = GaussianPSF(torch.tensor([31.5, 31.5], dtype=F64), 4 * torch.eye(2, dtype=F64), torch.tensor(1e6, dtype=F64))
    th = torch.tensor([[3.0, 2.0, 0.3, -1.0]], dtype=F64)
    om = 2 * math.pi * torch.tensor([60.0, 120.0], dtype=F64)
    win = ExposureWindow(torch.tensor([0.0, 0.003], dtype=F64), torch.tensor([0.01, 0.004], dtype=F64))
    kw = dict(frame_shape=(64, 64), read_noise_e=5.0)
    default = image_fisher(th, om, psf, win, **kw)
    assert torch.equal(default, image_fisher(th, om, psf, win, direction=(1.0, 0.0), **kw))
    for ang in (0.6, 2.0):
        rotated = image_fisher(th, om, psf, win, direction=(math.cos(ang), math.sin(ang)), **kw)
        assert float((rotated - default).abs().max() / default.abs().max()) < 1e-5


def test_unweighted_fit_with_a_dark_set_in_the_batch():
    """noise_std=None with a dark image set among live ones (it used to fail on the reduced chi2 of
    the live sets only): the dark set gets status 1 and NaN, each live one the fit it gets alone."""
    win = windows([0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.3, 0.5, 0.2, 0.7, 0.4, 0.25])
    img = render_multisine(THETA, OM, PSF, win, height=H, width=W)
    g = torch.Generator().manual_seed(4)
    noisy = img + 5.0 * torch.randn((2,) + img.shape, generator=g, dtype=F64)
    sets = torch.stack([noisy[0], torch.zeros_like(img), noisy[1]])
    fit = fit_multisine(sets, PSF, win, OM, n_starts=4)
    assert int(fit.status[1]) == 1 and torch.isnan(fit.amplitude[1]).all() and fit.extras["reduced_chi2"].shape == (3,)
    for b, k in ((0, 0), (2, 1)):
        one = fit_multisine(noisy[k], PSF, win, OM, n_starts=4)
        assert int(fit.status[b]) == int(one.status)
        np.testing.assert_allclose(fit.amplitude[b].numpy(), one.amplitude.numpy(), rtol=1e-6)
        np.testing.assert_allclose(fit.noise_std[b].numpy(), one.noise_std.numpy(), rtol=1e-6)
        # the cost (the reduced chi2 times the pixels used, all here: the same for both; the reduced chi2 itself is NaN without
        # a given noise, tests/test_multisine_fit_quality.py)
        assert float(fit.cost[b]) == pytest.approx(float(one.cost), rel=1e-6)


def test_kernel_psf_fit_equals_the_gaussian_fit_on_the_same_spot():
    """fit_multisine with a measured kernel (issue 29): the still spot's image of a 2 px Gaussian
    (band-limited: its Fourier shift is the Gaussian's own splat to ~1e-10 of peak) gives the
    Gaussian PSF's estimates and stds on the same noisy frames."""
    from torchblur.render.psf import KernelPSF

    y, x = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    kernel = KernelPSF(PSF.evaluate(x, y))
    win = windows([0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.3, 0.5, 0.2, 0.7, 0.4, 0.25])
    img = render_multisine(THETA, OM, PSF, win, height=H, width=W)
    assert float((render_multisine(THETA, OM, kernel, win, height=H, width=W) - img).abs().max()) < 1e-8 * float(img.max())
    noise = torch.sqrt(25 + img)
    noisy = img + noise * torch.randn(img.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    fk = fit_multisine(noisy, kernel, win, OM, noise_std=noise, n_starts=4, n_refine=1, amplitude_guess=THETA[:3])
    fg = fit_multisine(noisy, PSF, win, OM, noise_std=noise, n_starts=4, n_refine=1, amplitude_guess=THETA[:3])
    assert bool(fk.converged) and bool(fg.converged)
    assert float(((fk.amplitude - fg.amplitude) / fg.amplitude_std).abs().max()) < 1e-4
    assert float(((fk.phase - fg.phase) / fg.phase_std).abs().max()) < 1e-4
    np.testing.assert_allclose(fk.phase_std.numpy(), fg.phase_std.numpy(), rtol=1e-4)
    with pytest.raises(ShapeError, match="psf"):
        fit_multisine(noisy[:, :, :-1], kernel, win, OM)


@pytest.mark.parametrize("case", ["gaussian", "pixel_integration", "kernel"])
def test_coarse_cost_of_the_starts_ranks_them_as_the_rendered_cost(case, monkeypatch):
    """The search ranks its starts by a binned cost (_coarse_cost: each start's nodes binned onto a
    grid of a tenth of the PSF's width): on a fit's own starts (noisy images, weights 1/sigma^2) it
    equals the cost of the rendered model to 1 % and picks the same best starts."""
    from dataclasses import replace

    import torchblur.fit.multisine as ms
    from torchblur.render.blur import RenderSettings
    from torchblur.render.psf import KernelPSF

    seen = []
    search = ms._search
    monkeypatch.setattr(ms, "_search", lambda prob, cands, items, *a: seen.append((prob, cands, items)) or search(prob, cands, items, *a))
    y, x = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    psf = KernelPSF(PSF.evaluate(x, y)) if case == "kernel" else PSF
    win = windows([[0.0, 0.13, 0.37, 0.55, 0.71, 0.86], [0.05, 0.2, 0.3, 0.5, 0.6, 0.9]], [[0.3, 0.5, 0.2, 0.7, 0.4, 0.25]] * 2)
    img = render_multisine(torch.stack([THETA, THETA * 0.8]), OM, PSF, win, height=H, width=W)
    noise = torch.sqrt(25 + img)
    noisy = img + noise * torch.randn(img.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    fit_multisine(noisy, psf, win, OM, noise_std=noise, n_starts=24, n_refine=1, max_iter=1, fit_scale=True)
    prob, cands, items = seen[0]
    if case == "pixel_integration":  # the same problem with pixel-area integration (a fit of it costs 10x more)
        prob = replace(prob, settings=RenderSettings(pixel_integration=True, nodes=prob.settings.nodes))
    assert cands.shape[:2] == (2, 24 + 1)
    for k in range(2):
        coarse = ms._coarse_cost(prob, cands[k], int(items[k]))
        exact = ms._rendered_cost(prob, cands[k], int(items[k]))  # the rendered model's (the fallback for huge grids)
        assert float(((coarse - exact) / exact).abs().max()) < 1e-2
        assert set(coarse.argsort()[:4].tolist()) == set(exact.argsort()[:4].tolist())
