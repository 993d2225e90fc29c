"""Measured-kernel fits (issue 15): a batch gives each item what a fit of it alone gives (each
item its own crop, its own quadrature rules and its own FFT grid, so identify's chunks cannot
change a point's values), and the crop keeps the kernel's faint wings (a bright spot's wings
are far above the noise beyond 5.5 sigmas: cut off, they count as unexplained light)."""
import math

import torch

from torchblur.design.windows import dual_exposure_windows
from torchblur.fit.problem import KERNEL_CROP_STEP, crop_to_reach, sine_problem
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.render.blur import render_blur
from torchblur.render.psf import KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

F64 = torch.float64
H, W = 36, 48


def _problems(seed=0):
    """Three items of one measured spot (a core and a faint ring, zero beyond 8 px), moved 3, 6 and 9 px along
    0.5 rad at 60, 300 and 700 Hz (so their crops and rules differ); noise std 4."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    r = ((xx - 23.3) ** 2 + 1.3 * (yy - 17.6) ** 2).sqrt()
    still = torch.exp(-r ** 2 / (2 * 1.6 ** 2)) + 0.02 * torch.exp(-(r - 4.5) ** 2 / 2)
    still = torch.where(r < 8.0, still, torch.zeros((), dtype=F64))  # ends, as psf_from_still's taper ends it
    M = torch.tensor([3.0, 6.0, 9.0], dtype=F64)
    phi = torch.tensor([0.3, -1.2, 2.5], dtype=F64)
    omega = 2 * math.pi * torch.tensor([60.0, 300.0, 700.0], dtype=F64)
    wins = [dual_exposure_windows(float(o), fractions=(0.3, 0.8), trigger_phase=0.7 * k) for k, o in enumerate(omega)]
    win = ExposureWindow(torch.stack([w.start for w in wins]), torch.stack([w.duration for w in wins]))
    kernel = 3000 * still / win.duration.amax(-1)[:, None, None]  # peak 3000 in the longer exposure
    d = torch.tensor([math.cos(0.5), math.sin(0.5)], dtype=F64)
    traj = Sinusoid((M[:, None] * d)[:, None, :], phi[:, None, None].expand(3, 1, 2), omega[:, None])
    clean = render_blur(traj, KernelPSF(kernel[:, None]), win, height=H, width=W)
    images = clean + 4.0 * torch.randn(clean.shape, generator=g, dtype=F64)
    return images, KernelPSF(kernel), win, omega, d, M, phi


def test_kernel_batch_equals_items_alone():
    images, psf, win, omega, d, M, phi = _problems()
    noise = torch.full((3,), 4.0, dtype=F64)
    batch = fit_sinusoid(images, psf, win, omega, axes=d, noise_std=noise)
    alone = [fit_sinusoid(images[i:i + 1], KernelPSF(psf.kernel[i:i + 1]), win[i:i + 1], omega[i:i + 1], axes=d, noise_std=noise[i:i + 1])
             for i in range(3)]
    assert bool((batch.status == 0).all())
    for name in ("amplitude", "phase", "amplitude_std", "phase_std", "cost", "reduced_chi2"):
        b, a = getattr(batch, name), torch.cat([getattr(f, name) for f in alone])
        assert torch.allclose(b, a, rtol=1e-9, atol=0), (name, b, a)
    z = (batch.amplitude - M) / batch.amplitude_std
    assert float(z.abs().max()) < 5  # and right


def test_kernel_crop_is_each_items_own():
    """The crop of an item depends on that item alone: its size a multiple of
    KERNEL_CROP_STEP (or the frame's), the item's pixels at the top-left, the rest weight 0,
    and the cut-off pixels' cost kept."""
    images, psf, win, omega, d, M, _ = _problems()
    direction = d.expand(3, 1, 2)
    p = sine_problem(images, psf, win, omega, direction, noise_std=torch.full((3,), 4.0, dtype=F64))
    bound = M[:, None]
    cropped = crop_to_reach(p, bound, fit_center=False)
    region = cropped.region
    assert region is not None and region.shape == (3, 4)
    assert len({tuple(r) for r in region[:, 2:].tolist()}) > 1  # different crops in one batch
    for n in range(3):
        x0, y0, w, h = region[n].tolist()
        assert w % KERNEL_CROP_STEP == 0 or w == W
        assert h % KERNEL_CROP_STEP == 0 or h == H
        one = crop_to_reach(sine_problem(images[n:n + 1], KernelPSF(psf.kernel[n:n + 1]), win[n:n + 1], omega[n:n + 1], direction[n:n + 1],
                                         noise_std=torch.full((1,), 4.0, dtype=F64)), bound[n:n + 1], fit_center=False)
        assert one.region[0].tolist() == [x0, y0, w, h]
        assert torch.equal(cropped.data[n, :, :h, :w], images[n, :, y0:y0 + h, x0:x0 + w])
        assert float(cropped.weight[n, :, h:].abs().sum() + cropped.weight[n, :, :, w:].abs().sum()) == 0
        assert torch.equal(cropped.psf.kernel[n, :h, :w], psf.kernel[n, y0:y0 + h, x0:x0 + w])
        full = (p.weight[n] * p.data[n] ** 2).sum()
        kept = (cropped.weight[n] * cropped.data[n] ** 2).sum()
        assert torch.allclose(cropped.cut_cost[n] + kept, full, rtol=1e-12)


def test_a_bright_kernels_wings_stay_in_the_crop():
    """A bright spot with a faint, wide halo (0.3 % of the peak, sigma 7 px: an Airy-like wing,
    beyond 5.5 sigmas of the spot's moments): the crop spans wherever the kernel is not zero,
    so the model explains the frames (reduced chi2 ~1; with the halo cut off by a 5.5-sigma
    crop it read 1.9-3.2 on HCIPy spots at 100x light) and the fit stays within its std."""
    g = torch.Generator().manual_seed(4)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    r2 = (xx - 23.6) ** 2 + (yy - 17.2) ** 2
    still = torch.exp(-r2 / (2 * 1.4 ** 2)) + 0.003 * torch.exp(-r2 / (2 * 7.0 ** 2))
    still = torch.where(r2 < 15.0 ** 2, still, torch.zeros((), dtype=F64))  # a kernel's taper ends it
    omega = 2 * math.pi * torch.tensor([150.0, 450.0], dtype=F64)
    M, phi = torch.tensor([4.0, 6.0], dtype=F64), torch.tensor([0.4, -2.0], dtype=F64)
    wins = [dual_exposure_windows(float(o), fractions=(0.3, 0.8), trigger_phase=1.1) for o in omega]
    win = ExposureWindow(torch.stack([w.start for w in wins]), torch.stack([w.duration for w in wins]))
    kernel = 4e5 * still / win.duration.amax(-1)[:, None, None]  # peak 4e5 e- in the longer exposure
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1)[:, None], phi[:, None, None].expand(2, 1, 2), omega[:, None])
    clean = render_blur(traj, KernelPSF(kernel[:, None]), win, height=H, width=W)
    noise = (clean + 9.0).sqrt()  # shot noise and 3 e- read noise
    images = clean + noise * torch.randn(clean.shape, generator=g, dtype=F64)
    p = crop_to_reach(sine_problem(images, KernelPSF(kernel), win, omega, torch.tensor([[[1.0, 0.0]]], dtype=F64).expand(2, 1, 2),
                                   noise_std=noise), M[:, None], fit_center=False)
    for n in range(2):  # the crop holds the kernel's non-zero pixels
        x0, y0, w, h = p.region[n].tolist() if p.region is not None else (0, 0, W, H)
        assert x0 <= 23.6 - 14 and x0 + w > 23.6 + 14 and y0 <= 17.2 - 14 and y0 + h > 17.2 + 14 or (w, h) == (W, H)
    fit = fit_sinusoid(images, KernelPSF(kernel), win, omega, axes="x", noise_std=noise)
    assert bool((fit.status == 0).all())
    assert float(fit.reduced_chi2.max()) < 1.15 and float(fit.reduced_chi2.min()) > 0.85
    assert float(((fit.amplitude - M) / fit.amplitude_std).abs().max()) < 5
