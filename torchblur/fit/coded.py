"""Coded exposure, the fit (issue 6 part 5): :func:`fit_sinusoid_coded` fits ``(M, phi[, scale])``
to single coded images (:mod:`torchblur.render.coded`, which breaks the time-reversal alias) by
batched Levenberg-Marquardt from a grid of phase starts; docs/multisine.md, "One image against the alias".
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from torchblur._compat import median_along
from torchblur.errors import as_tensor
from torchblur.fit.inputs import check_count, check_data, flat_count, flat_omega, flat_psf, flat_window
from torchblur.fit.multisine import render_multisine_with_jacobian
from torchblur.losses import fisher_covariance, image_loss, pixel_weights, residual_weights
from torchblur.optim import levenberg_marquardt
from torchblur.image.moments import image_moments
from torchblur.render.alias import canonical_sines, wrap_phase
from torchblur.render.blur import RenderSettings, choose_node_count
from torchblur.render.coded import check_code, coded_windows, render_coded
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

__all__ = ["CodedFit", "fit_sinusoid_coded"]


@dataclass
class CodedFit:
    """Result of :func:`fit_sinusoid_coded`, batch ``[...]``: ``amplitude`` (px), ``phase``
    (rad), their stds, ``cost``, ``alias_cost`` (the cost at the plain window's alias phase
    ``pi - 2c - phi``, same amplitude; equal to ``cost`` when the code does not break the alias),
    ``converged``, ``covariance`` ``[..., P, P]``, ``scale`` (or None)."""

    amplitude: torch.Tensor
    phase: torch.Tensor
    amplitude_std: torch.Tensor
    phase_std: torch.Tensor
    cost: torch.Tensor
    alias_cost: torch.Tensor
    converged: torch.Tensor
    covariance: torch.Tensor
    scale: torch.Tensor | None = None


@dataclass(frozen=True)
class _CodedProblem:
    """B flattened coded images and everything their model needs (checked, one dtype).

    ``center [B, 2]``, ``cov [B, 2, 2]``, ``amp [B]`` (the PSF; a measured kernel's centroid,
    second moments and 1), ``start, dur [B]`` (the whole exposures, s), ``om [B]`` rad/s,
    ``code [K, 2]``, ``height, width``, ``settings`` (with the node count fixed), ``fit_scale``,
    ``kernel [B, H, W]`` (a measured kernel, or None: the Gaussian) and ``pad`` (its FFT grid's
    padding, px, fixed with the node count). The motion is along x: ``theta = (M, phi[, scale])``.
    """

    center: torch.Tensor
    cov: torch.Tensor
    amp: torch.Tensor
    start: torch.Tensor
    dur: torch.Tensor
    om: torch.Tensor
    code: torch.Tensor
    height: int
    width: int
    settings: RenderSettings
    fit_scale: bool
    kernel: torch.Tensor | None = None
    pad: int = 0

    def psf(self, it: torch.Tensor | None = None) -> GaussianPSF | KernelPSF:
        """The PSF of the items ``it [n]`` (every item without): the measured kernel, or the Gaussian."""
        sel = slice(None) if it is None else it
        if self.kernel is not None:
            return KernelPSF(self.kernel[sel])
        return GaussianPSF(self.center[sel], self.cov[sel], self.amp[sel])

    def model(self, theta: torch.Tensor, it: torch.Tensor) -> torch.Tensor:
        """The rendered coded images of the items ``it [n]`` at ``theta [n, P]`` -> ``[n, H W]``
        (a kernel: the splat's image, the model :meth:`model_and_jacobian` differentiates)."""
        if self.kernel is not None:
            return self.model_and_jacobian(theta, it, jacobian=False)[0]
        M, ph = theta[:, 0], theta[:, 1]
        # omega [n, 2] (x, y): a plain [n] with n == 2 would read as one omega per axis
        traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([ph, ph], -1), self.om[it][:, None].expand(-1, 2))
        img = render_coded(traj, self.psf(it), ExposureWindow(self.start[it], self.dur[it]),
                           self.code, height=self.height, width=self.width, settings=self.settings)
        if self.fit_scale:
            img = img * theta[:, 2, None, None]
        return img.reshape(theta.shape[0], -1)

    def model_and_jacobian(self, theta: torch.Tensor, it: torch.Tensor, *, jacobian: bool = True):
        """Model ``[n, H W]`` (point-sampled pixels) and Jacobian ``[n, H W, P]`` (None without
        ``jacobian``): the one-tone :func:`~torchblur.fit.multisine.render_multisine_with_jacobian` of
        every open interval (a kernel: its Fourier shift), summed."""
        n = theta.shape[0]
        psf = self.psf(it)
        sub = coded_windows(ExposureWindow(self.start[it], self.dur[it]), self.code)  # [n, K]: the open intervals
        s = self.settings
        img, J = render_multisine_with_jacobian(theta, self.om[it][:, None], psf, sub, height=self.height,
                                                width=self.width, nodes=s.nodes, nodes_per_panel=s.nodes_per_panel,
                                                pad=self.pad, jacobian=jacobian)
        return img.sum(1).reshape(n, -1), J.sum(1).reshape(n, self.height * self.width, -1) if jacobian else None


def _check_inputs(images, psf, window, code, n_phases):
    """The public entry's checks (:func:`~torchblur.fit.inputs.check_data`) -> ``(images, psf, window, code [K, 2])``
    in one floating dtype."""
    images, psf, window = check_data(images, psf, window, frame_dims=2)
    check_count(n_phases, "n_phases")
    return images, psf, window, check_code(code, like=images)


def _amplitude_start(images, cov_xx, center_x, amplitude_guess, batch, B: int) -> torch.Tensor:
    """The amplitude start ``[B]``: ``amplitude_guess``, else from each image's second moment along x."""
    if amplitude_guess is not None:
        return as_tensor(amplitude_guess, "amplitude_guess", like=images).expand(batch).reshape(B).abs().clamp_min(1e-3)
    H, W = images.shape[-2:]
    flat = images.reshape(B, H * W)
    thr = median_along(flat) + 3 * median_along((flat - median_along(flat)[:, None]).abs()) * 1.4826
    _, cen, icov = image_moments(images.reshape(B, H, W), threshold=thr)
    ms = (icov[:, 0, 0] - cov_xx + (cen[:, 0] - center_x) ** 2).clamp_min(0.25)
    return (2 * ms).sqrt()


def _problem(images, psf: GaussianPSF | KernelPSF, window: ExposureWindow, code, omega, fit_scale: bool) -> _CodedProblem:
    """The flattened problem ``[B]``; its renderer settings have no node count yet (:func:`_with_nodes`)."""
    batch, (H, W) = images.shape[:-2], images.shape[-2:]
    B = flat_count(images, frame_dims=2)
    win, p = flat_window(window, batch, B), flat_psf(psf, batch, B)
    center, cov = p.moments()
    kernel = p.kernel if isinstance(p, KernelPSF) else None
    amp = torch.ones(B, dtype=images.dtype, device=images.device) if kernel is not None else p.amplitude
    return _CodedProblem(center=center, cov=cov, amp=amp, start=win.start, dur=win.duration,
                         om=flat_omega(omega, batch, B, images), code=code, height=H, width=W,
                         settings=RenderSettings(panel_path_sigmas=3.5), fit_scale=fit_scale, kernel=kernel)


def _with_nodes(prob: _CodedProblem, M0: torch.Tensor) -> _CodedProblem:
    """``prob`` with the node count fixed for motions up to ``1.5 M0 + 0.5`` px (``M0 [B]``)."""
    bound = Sinusoid(torch.stack([M0 * 1.5 + 0.5, torch.zeros_like(M0)], -1), torch.zeros_like(prob.center), prob.om[:, None].expand(-1, 2))
    smin = prob.psf().sigma_min()
    S = choose_node_count(bound.path_length(ExposureWindow(torch.zeros_like(prob.dur), prob.dur)), smin, prob.settings)
    pad = int(math.ceil(float((M0 * 1.5 + 0.5).max()))) + 2
    return dataclasses.replace(prob, settings=RenderSettings(panel_path_sigmas=3.5, nodes=S), pad=pad)


def _phase_grid_starts(M0: torch.Tensor, n_phases: int, fit_scale: bool) -> torch.Tensor:
    """Starts ``[B, K, P]``: the amplitude ``M0 [B]`` with ``K = n_phases`` phases on a grid over
    the circle (and a unit scale)."""
    B, K = M0.shape[0], n_phases
    ph0 = torch.arange(K, dtype=M0.dtype, device=M0.device) * (2 * math.pi / K) - math.pi
    theta0 = torch.stack([M0[:, None].expand(B, K), ph0.expand(B, K)], -1)
    if fit_scale:
        theta0 = torch.cat([theta0, torch.ones(B, K, 1, dtype=M0.dtype, device=M0.device)], -1)
    return theta0


def _fisher_covariance(prob: _CodedProblem, theta, data, weight, noise_given: bool) -> torch.Tensor:
    """Inverse Fisher information ``[B, P, P]`` at ``theta [B, P]``; without a given noise the
    weights are scaled by the reduced chi2 (noise from the residuals)."""
    ar = torch.arange(theta.shape[0], device=theta.device)
    model, J = prob.model_and_jacobian(theta, ar)
    if noise_given:
        return fisher_covariance(J, weight)[0]
    return fisher_covariance(J, residual_weights(data - model, weight, theta.shape[-1])[0])[0]


def fit_sinusoid_coded(images, psf: GaussianPSF | KernelPSF, window: ExposureWindow, code, omega, *, noise_std=None, amplitude_guess=None,
                       fit_scale: bool = False, n_phases: int = 12, max_iter: int = 60, tol: float = 1e-10) -> CodedFit:
    """Fit ``y(t) = M sin(omega t + phi)`` along x to single coded images.

    Args:
        images: ``[..., H, W]``, one coded exposure each (dark subtracted).
        psf: :class:`GaussianPSF`, or a measured :class:`KernelPSF` (kernel ``[..., H, W]``, shifted
            as a band-limited image), batch ``[...]``.
        window: the whole exposures ``[...]`` (s, command clock).
        code: ``[K, 2]`` open intervals (fractions of the exposure).
        omega: rad/s, ``[...]``.
        noise_std: pixel noise std (number, ``[...]`` or ``[..., H, W]``); None: unweighted,
            noise from the residuals.
        amplitude_guess: M start (px), ``[...]``; default from the image's second moment.
        fit_scale: also fit an intensity scale.
        n_phases: phase starts on a grid over the circle (all refined, the best kept).

    Returns:
        :class:`CodedFit`.
    """
    images, psf, window, code = _check_inputs(images, psf, window, code, n_phases)
    batch = images.shape[:-2]
    prob = _problem(images, psf, window, code, omega, fit_scale)
    B, K = prob.om.shape[0], n_phases
    data = images.reshape(B, -1)
    weight = pixel_weights(noise_std, None, images, frame_dims=2)[0].reshape(B, -1)
    M0 = _amplitude_start(images, prob.cov[:, 0, 0], prob.center[:, 0], amplitude_guess, batch, B)
    prob = _with_nodes(prob, M0)
    theta0 = _phase_grid_starts(M0, K, fit_scale)
    P = theta0.shape[-1]
    item = torch.arange(B, device=images.device).repeat_interleave(K)
    res = levenberg_marquardt(lambda th, i: prob.model(th, item[i]), theta0.reshape(B * K, P), data[item], weight=weight[item],
                              max_iter=max_iter, tol=tol, jacobian_fn=lambda th, i: prob.model_and_jacobian(th, item[i]))
    cost = torch.nan_to_num(res.cost, nan=float("inf")).reshape(B, K)
    best = cost.argmin(-1)
    ar = torch.arange(B, device=images.device)
    theta = canonical_sines(res.theta.reshape(B, K, P)[ar, best], 1)
    # The plain window's alias branch: the code breaks the alias when its cost is higher there.
    ta = theta.clone()
    ta[:, 1] = wrap_phase(math.pi - 2 * prob.om * (prob.start + prob.dur / 2) - theta[:, 1])
    covm = _fisher_covariance(prob, theta, data, weight, noise_std is not None)
    std = torch.diagonal(covm, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    def out(x, tail=()):
        return x.reshape(batch + tail)

    return CodedFit(amplitude=out(theta[:, 0]), phase=out(theta[:, 1]), amplitude_std=out(std[:, 0]), phase_std=out(std[:, 1]),
                    cost=out(cost[ar, best]), alias_cost=out(image_loss(prob.model(ta, ar).detach(), data, weight=weight)),
                    converged=out(res.converged.reshape(B, K)[ar, best]), covariance=out(covm, (P, P)),
                    scale=out(theta[:, 2]) if fit_scale else None)
