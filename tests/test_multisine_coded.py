"""Coded exposure (issue 6 part 5): one asymmetric coded image has no time-reversal alias."""
import math

import numpy as np
import pytest
import torch

from torchblur.fit.coded import fit_sinusoid_coded
from torchblur.render.coded import check_code, coded_windows, mirror_code, render_coded
from torchblur.errors import ParameterError
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

F64 = torch.float64
OM = 2 * math.pi * 200.0
T = 1 / 200.0
PSF = GaussianPSF(torch.tensor([23.5, 11.5], dtype=F64), 4 * torch.eye(2, dtype=F64), torch.tensor(2000 / (0.5 * T), dtype=F64))
CODE = torch.tensor([[0.0, 0.2], [0.45, 0.55], [0.8, 0.9]], dtype=F64)
WIN = ExposureWindow(torch.tensor(0.25 * T, dtype=F64), torch.tensor(0.5 * T, dtype=F64))


def sine(M, phi):
    M, phi = torch.as_tensor(M, dtype=F64), torch.as_tensor(phi, dtype=F64)
    return Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([phi, phi], -1), torch.tensor(OM, dtype=F64))


def test_coded_image_is_the_sum_of_its_open_windows_and_breaks_the_alias():
    sub = coded_windows(WIN, CODE)
    ref = sum(render_blur(sine(6.0, 0.7), PSF, sub[k], height=24, width=48) for k in range(3))
    img = render_coded(sine(6.0, 0.7), PSF, WIN, CODE, height=24, width=48)
    np.testing.assert_allclose(img.numpy(), ref.numpy(), atol=1e-10 * float(ref.max()))
    alias = math.pi - 2 * OM * float(WIN.center) - 0.7
    plain = render_blur(sine(6.0, 0.7), PSF, WIN, height=24, width=48)
    plain_alias = render_blur(sine(6.0, alias), PSF, WIN, height=24, width=48)
    assert float((plain - plain_alias).abs().max()) < 1e-9 * float(plain.max())  # one plain image: the same for both branches
    coded_alias = render_coded(sine(6.0, alias), PSF, WIN, CODE, height=24, width=48)
    assert float((img - coded_alias).abs().max()) > 0.05 * float(img.max())  # the coded image tells them apart
    # the alias of the code is its mirror: the mirrored code renders the alias branch's image
    mirrored = render_coded(sine(6.0, alias), PSF, WIN, mirror_code(CODE), height=24, width=48)
    np.testing.assert_allclose(mirrored.numpy(), img.numpy(), atol=1e-9 * float(img.max()))
    with pytest.raises(ParameterError, match="code"):
        check_code([[0.2, 0.1]])


def test_one_coded_image_gives_the_phase_within_its_std():
    phis = torch.tensor([-2.5, 0.4, 2.9], dtype=F64)
    img = render_coded(sine(torch.full((3,), 6.0, dtype=F64), phis), PSF, WIN.expand((3,)), CODE, height=24, width=48)
    noise = torch.sqrt(25 + img)
    g = torch.Generator().manual_seed(3)
    noisy = img + noise * torch.randn(img.shape, generator=g, dtype=F64)
    fit = fit_sinusoid_coded(noisy, PSF, WIN.expand((3,)), CODE, OM, noise_std=noise, n_phases=6)
    err = torch.remainder(fit.phase - phis + math.pi, 2 * math.pi) - math.pi
    assert fit.converged.all()
    assert float((err.abs() / fit.phase_std).max()) < 5 and float((fit.amplitude - 6).abs().div(fit.amplitude_std).max()) < 5
    assert float((fit.alias_cost / fit.cost).min()) > 1.5  # the alias branch fits far worse (ratio 1 for a plain exposure)


def test_coded_fit_recovers_the_truth_with_the_stds_of_forward_ad():
    """Noise-free: the fit lands on the truth, and its stds (Jacobian from one splat over the open
    intervals) equal the Cramer-Rao bound from forward AD through render_coded."""
    import torch.autograd.forward_ad as fwAD

    from torchblur.render.blur import RenderSettings

    img = render_coded(sine(6.0, 0.7), PSF, WIN, CODE, height=24, width=48)
    fit = fit_sinusoid_coded(img, PSF, WIN, CODE, OM, noise_std=1.0, amplitude_guess=6.0, n_phases=3)
    assert abs(float(fit.amplitude) - 6.0) < 1e-6 and abs(float(fit.phase) - 0.7) < 1e-6
    th = torch.tensor([6.0, 0.7], dtype=F64)
    cols = []
    for k in range(2):
        with fwAD.dual_level():
            tan = torch.zeros(2, dtype=F64)
            tan[k] = 1
            d = fwAD.make_dual(th, tan)
            out = render_coded(sine(d[0], d[1]), PSF, WIN, CODE, height=24, width=48, settings=RenderSettings(nodes=256))
            cols.append(fwAD.unpack_dual(out).tangent.reshape(-1))
    J = torch.stack(cols, -1)
    crb = torch.linalg.inv(J.T @ J).diagonal().sqrt()
    np.testing.assert_allclose([float(fit.amplitude_std), float(fit.phase_std)], crb.numpy(), rtol=1e-4)


def _old_coded_model_and_jacobian(theta, om, center, cov, amp, start, dur, code, S, H, W, fit_scale, m=8):
    """The hand-written node positions and derivatives of fit_sinusoid_coded before it called the
    one forward model (render.splat.sine_blur_with_jacobian): kept as a reference."""
    from torchblur.render.blur import quadrature_nodes
    from torchblur.render.splat import gaussian_splat_with_jacobian

    tau, wq = quadrature_nodes(S // m, m, dtype=theta.dtype)
    frac0, width = code[:, 0], code[:, 1] - code[:, 0]
    A_p, B_p, C_p = GaussianPSF(center, cov, amp).precision()
    n = theta.shape[0]
    te = dur[:, None, None]
    t = (start[:, None, None] + te * (frac0[:, None] + width[:, None] * tau)).reshape(n, -1)
    w = (te * width[:, None] * wq).reshape(n, -1) * amp[:, None]
    arg = om[:, None] * t + theta[:, 1, None]
    sn, cs = torch.sin(arg), torch.cos(arg)
    px = center[:, 0, None] + theta[:, 0, None] * sn
    py = center[:, 1, None].expand(px.shape)
    dpx = torch.stack([sn, theta[:, 0, None] * cs], -1)
    img, dimg = gaussian_splat_with_jacobian(px, py, dpx, torch.zeros_like(dpx), w, A_p, B_p, C_p, H, W)
    J = dimg.movedim(1, -1).reshape(n, H * W, 2)
    model = img.reshape(n, -1)
    if fit_scale:
        J = torch.cat([J * theta[:, 2, None, None], model[..., None]], -1)
        model = model * theta[:, 2, None]
    return model, J


@pytest.mark.parametrize("fit_scale", [False, True])
def test_coded_jacobian_on_the_one_forward_model_equals_the_old_hand_written_one(fit_scale):
    """The coded fit's image and Jacobian (sine_blur_with_jacobian over the nodes of every open
    interval) equal the hand-written ones they replaced, to round-off."""
    from torchblur.fit.coded import _CodedProblem
    from torchblur.render.blur import RenderSettings

    n, S, H, W = 2, 64, 24, 48
    center = torch.tensor([[23.5, 11.5], [20.0, 12.5]], dtype=F64)
    cov = torch.tensor([[[4.0, 0.0], [0.0, 4.0]], [[3.0, 0.7], [0.7, 5.0]]], dtype=F64)
    amp = torch.tensor([2000 / (0.5 * T), 1500 / (0.5 * T)], dtype=F64)
    start, dur = torch.tensor([0.25 * T, 0.1 * T], dtype=F64), torch.tensor([0.5 * T, 0.4 * T], dtype=F64)
    om = torch.tensor([OM, 1.3 * OM], dtype=F64)
    theta = torch.tensor([[6.0, 0.7, 1.1], [4.0, -2.2, 0.9]], dtype=F64)[:, :3 if fit_scale else 2]
    prob = _CodedProblem(center=center, cov=cov, amp=amp, start=start, dur=dur, om=om, code=CODE, height=H, width=W,
                         settings=RenderSettings(panel_path_sigmas=3.5, nodes=S), fit_scale=fit_scale)
    model, J = prob.model_and_jacobian(theta, torch.arange(n))
    ref, Jr = _old_coded_model_and_jacobian(theta, om, center, cov, amp, start, dur, CODE, S, H, W, fit_scale)
    np.testing.assert_allclose(model.numpy(), ref.numpy(), rtol=0, atol=1e-12 * float(ref.abs().max()))
    np.testing.assert_allclose(J.numpy(), Jr.numpy(), rtol=0, atol=1e-12 * float(Jr.abs().max()))
    # the rendered model (LM's cost) is the same image: a batch of exactly two items with two omegas
    # (omega [2] alone would read as one omega per axis)
    np.testing.assert_allclose(prob.model(theta, torch.arange(n)).numpy(), model.numpy(), rtol=0, atol=1e-9 * float(ref.abs().max()))


def test_coded_fit_of_two_images_at_two_frequencies():
    """Two coded images at different frequencies in one batch: each fit lands on its truth."""
    om = torch.tensor([OM, 1.3 * OM], dtype=F64)
    M, phi = torch.tensor([6.0, 4.0], dtype=F64), torch.tensor([0.7, -2.2], dtype=F64)
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([phi, phi], -1), om[:, None].expand(2, 2))
    win = WIN.expand((2,))
    img = render_coded(traj, PSF, win, CODE, height=24, width=48)
    fit = fit_sinusoid_coded(img, PSF, win, CODE, om, noise_std=1.0, amplitude_guess=M, n_phases=3)
    np.testing.assert_allclose(fit.amplitude.numpy(), M.numpy(), atol=1e-6)
    np.testing.assert_allclose(fit.phase.numpy(), phi.numpy(), atol=1e-6)
    # the alias cost of each: its own image at the plain window's alias phase, rendered alone
    for b in range(2):
        alias = math.pi - 2 * float(om[b]) * float(WIN.center) - float(phi[b])
        one = Sinusoid(torch.stack([M[b], torch.tensor(0.0, dtype=F64)]), torch.tensor([alias, alias], dtype=F64), om[b])
        expected = float(((render_coded(one, PSF, WIN, CODE, height=24, width=48) - img[b]) ** 2).sum())
        assert float(fit.alias_cost[b]) == pytest.approx(expected, rel=1e-6)


def test_coded_fit_with_a_measured_kernel_equals_the_gaussian_fit():
    """issue 29: fit_sinusoid_coded with the still image of the 2 px Gaussian as a KernelPSF (its
    Fourier shift is the Gaussian's splat to ~1e-10 of peak): the same estimates and stds."""
    from torchblur.render.psf import KernelPSF

    y, x = torch.meshgrid(torch.arange(24, dtype=F64), torch.arange(48, dtype=F64), indexing="ij")
    kernel = KernelPSF(PSF.evaluate(x, y))
    phis = torch.tensor([-2.5], dtype=F64)
    img = render_coded(sine(torch.full((1,), 6.0, dtype=F64), phis), PSF, WIN.expand((1,)), CODE, height=24, width=48)
    img_k = render_coded(sine(torch.full((1,), 6.0, dtype=F64), phis), kernel, WIN.expand((1,)), CODE, height=24, width=48)
    assert float((img_k - img).abs().max()) < 1e-8 * float(img.max())
    noise = torch.sqrt(25 + img)
    noisy = img + noise * torch.randn(img.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    fk = fit_sinusoid_coded(noisy, kernel, WIN.expand((1,)), CODE, OM, noise_std=noise, n_phases=3)
    fg = fit_sinusoid_coded(noisy, PSF, WIN.expand((1,)), CODE, OM, noise_std=noise, n_phases=3)
    assert fk.converged.all() and fg.converged.all()
    assert float(((fk.phase - fg.phase) / fg.phase_std).abs().max()) < 1e-4
    assert float(((fk.amplitude - fg.amplitude) / fg.amplitude_std).abs().max()) < 1e-4
    np.testing.assert_allclose(fk.phase_std.numpy(), fg.phase_std.numpy(), rtol=1e-4)
