"""The measured kernel's own noise in a fit's covariance, propagated exactly to first order
(``C G diag(var K) G^T C``; the derivation, and why not a scalar factor: docs/measured_psf.md,
"The kernel's noise on the multisine route, propagated").
"""
from __future__ import annotations

from typing import Callable

import torch

__all__ = ["kernel_noise_covariance"]


def kernel_noise_covariance(render: Callable[[torch.Tensor], torch.Tensor], kernel: torch.Tensor, kernel_var: torch.Tensor,
                            jac: torch.Tensor, weight: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """The estimates' covariance from the measured kernel's own pixel noise, ``[n, P, P]``.

    Args:
        render: ``kernel [n, h, w] -> model [n, R]``, the fit's model image at its solution as a
            function of the kernel (linear in it; differentiable by autograd).
        kernel: the kernel the fit used, ``[n, h, w]`` (intensity per second).
        kernel_var: its per-pixel variance, ``[n, h, w]`` ((intensity per second)^2; 0 where
            the kernel is exactly 0).
        jac: ``d model / d theta`` at the solution, ``[n, R, P]``.
        weight: the fit's pixel weights ``1 / std^2`` (0: unused), ``[n, R]``.
        covariance: the fit's covariance ``(J^T W J)^-1``, ``[n, P, P]``.

    Returns:
        ``C G diag(kernel_var) G^T C`` ``[n, P, P]``: add it to ``covariance``.
    """
    n, _, P = jac.shape
    k = kernel.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        model = render(k)
        v = (weight[..., None] * jac).detach()  # [n, R, P]
        G = torch.stack([torch.autograd.grad(model, k, v[..., p], retain_graph=p < P - 1)[0] for p in range(P)], 1)  # [n, P, h, w]
    A = covariance @ G.reshape(n, P, -1)  # [n, P, hw]
    return (A * kernel_var.reshape(n, 1, -1)) @ A.transpose(-1, -2)
