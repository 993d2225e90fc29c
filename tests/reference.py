"""Slow references for the renderer: adaptive quadrature and dense broadcasting."""
from __future__ import annotations

import numpy as np
import torch
from scipy.integrate import quad_vec

import torchblur as tb


def psf_dense(psf: tb.GaussianPSF, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Point-sampled Gaussian at pixel grids x [W], y [H] -> [..., H, W] (no batch broadcasting tricks)."""
    return psf.evaluate(x[None, :], y[:, None]) if psf.shape == () else psf.evaluate(x, y)


def quad_render(traj, psf: tb.GaussianPSF, window: tb.ExposureWindow, height: int, width: int,
                epsabs: float = 1e-13, epsrel: float = 1e-11) -> np.ndarray:
    """Adaptive quadrature (scipy quad_vec) of one item's blur integral, float64 numpy [H, W]."""
    assert psf.shape == () and window.shape == () and traj.shape == ()
    x = np.arange(width, dtype=np.float64)[None, :]
    y = np.arange(height, dtype=np.float64)[:, None]
    A, B, C = (float(v) for v in psf.to(torch.float64).precision())
    cx, cy = (float(v) for v in psf.center.detach().double())
    amp = float(psf.amplitude.detach())

    def integrand(t):
        d = traj.position(torch.tensor([t], dtype=torch.float64))[0].detach().double().numpy()
        dx = x - cx - d[0]
        dy = y - cy - d[1]
        return (amp * np.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy))).ravel()

    t0 = float(window.start)
    t1 = float(window.end)
    val, _ = quad_vec(integrand, t0, t1, epsabs=epsabs, epsrel=epsrel, limit=20000)
    return val.reshape(height, width)


def dense_render(traj, psf: tb.GaussianPSF, window: tb.ExposureWindow, height: int, width: int, n_nodes: int) -> torch.Tensor:
    """Dense [..., S, H, W] broadcasting with a composite Gauss-Legendre rule: the reference the
    fast path's values and gradients are checked against."""
    from torchblur.render.blur import quadrature_nodes

    m = 8
    tau, wq = quadrature_nodes(n_nodes // m, m, dtype=psf.center.dtype)
    t = window.start[..., None] + window.duration[..., None] * tau
    d = traj.position(t)  # [..., S, 2]
    cx = psf.center[..., None, 0] + d[..., 0]
    cy = psf.center[..., None, 1] + d[..., 1]
    A, B, C = psf.precision()
    x = torch.arange(width, dtype=cx.dtype)
    y = torch.arange(height, dtype=cx.dtype)
    dx = x - cx[..., None, None]  # [..., S, 1, W]
    dy = y[:, None] - cy[..., None, None]  # [..., S, H, 1]
    e = (...,) + (None,) * 3
    q = A[e] * dx * dx + 2 * B[e] * dx * dy + C[e] * dy * dy
    w = window.duration[..., None] * wq * psf.amplitude[..., None]
    return (torch.exp(-0.5 * q) * w[..., None, None]).sum(-3)


def truth_errors(res):
    """``(|relative magnitude error| [F], |phase error| deg [F], error/std [F])`` of an
    identification result's SISO response against its simulation's truth."""
    em, ep, z = res.frf.errors_against(res.truth)
    return np.abs(em[0, 0]), np.degrees(np.abs(ep[0, 0])), z[0, 0]
