"""The measured kernel's own noise in a fit's covariance (torchblur.fit.kernel_noise, issue 29):
the propagated term is the estimate's first-order response to a kernel error, checked against
refits with a perturbed kernel."""
import math

import pytest
import torch

from torchblur.errors import ParameterError, ShapeError
from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow

F64 = torch.float64
H, W = 16, 24


@pytest.fixture(scope="module")
def case():
    """A 2-tone set of 4 noise-free frames rendered from a measured-style kernel (a tilted 1.6 px spot's image)."""
    yy, xx = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    spot = GaussianPSF(torch.tensor([11.3, 7.6], dtype=F64), torch.tensor([[2.6, 0.5], [0.5, 2.0]], dtype=F64), torch.tensor(4e5, dtype=F64))
    kernel = spot.evaluate(xx, yy)
    om = 2 * math.pi * torch.tensor([300.0, 500.0], dtype=F64)
    theta = torch.tensor([2.5, 1.5, 0.7, -1.9, 1.0], dtype=F64)
    g = torch.Generator().manual_seed(3)
    win = ExposureWindow(torch.rand(4, generator=g, dtype=F64) * 1e-2, (0.2 + 0.5 * torch.rand(4, generator=g, dtype=F64)) / 100)
    images = render_multisine(theta, om, KernelPSF(kernel), win, height=H, width=W)
    return kernel, om, theta, win, images


def _fit(case, kernel, kernel_var=None):
    _, om, theta, win, images = case
    return fit_multisine(images, KernelPSF(kernel), win, om, noise_std=5.0, amplitude_guess=theta[:2], phase_guess=theta[2:4],
                         n_starts=0, tol=1e-13, max_iter=12, kernel_var=kernel_var)


def test_the_kernel_term_is_the_estimates_response_to_a_kernel_pixel(case):
    """kernel_var = v at one pixel gives v a a^T, a = d theta / d K[pixel]: the refit with that
    pixel moved by eps moves theta by eps a (central difference, to 1e-3 of the largest)."""
    kernel = case[0]
    pixel = (7, 10)  # beside the spot's centre (11.3, 7.6): a pixel on its slope
    var = torch.zeros_like(kernel)
    var[pixel] = 1.0
    fit = _fit(case, kernel, var)
    kcov = fit.extras["kernel_covariance"]
    eps = 1e-3 * float(kernel.max())
    dk = torch.zeros_like(kernel)
    dk[pixel] = eps
    theta = [torch.cat([f.amplitude, f.phase, f.scale[None]]) for f in (_fit(case, kernel + dk), _fit(case, kernel - dk))]
    a = (theta[0] - theta[1]) / (2 * eps)
    torch.testing.assert_close(kcov, torch.outer(a, a), rtol=0, atol=1e-3 * float(a.abs().max()) ** 2)
    assert float(a.abs().max()) > 0
    own = fit.covariance - kcov
    torch.testing.assert_close(own, _fit(case, kernel).covariance, rtol=1e-9, atol=0)


def test_the_kernel_variance_is_checked(case):
    kernel = case[0]
    with pytest.raises(ShapeError, match="kernel_var"):
        _fit(case, kernel, torch.ones(3, 4, dtype=F64))
    with pytest.raises(ParameterError, match="kernel_var"):
        _fit(case, kernel, -torch.ones_like(kernel))
    _, om, theta, win, images = case
    with pytest.raises(ParameterError, match="kernel_var"):
        fit_multisine(images, GaussianPSF(torch.tensor([11.0, 7.0], dtype=F64), 2 * torch.eye(2, dtype=F64), torch.tensor(1.0, dtype=F64)),
                      win, om, noise_std=5.0, n_starts=0, kernel_var=torch.ones_like(kernel))
