"""The blurred image of a multisine motion (:func:`render_multisine`) and the fit of its tones
``theta = (M_1..M_N, phi_1..phi_N[, scale])`` from an image set (:func:`fit_multisine`); why one
image leaves ambiguities and how the starts and the search work: docs/multisine.md.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import torch

from torchblur._compat import lstsq_solution, median_along
from torchblur.render.alias import canonical_sines
from torchblur.errors import ParameterError, ShapeError, as_tensor, check_finite, check_positive
from torchblur.fit.inputs import (check_count, check_data, flat_count, flat_direction, flat_omega, flat_psf,
                                  flat_window, unit_direction)
from torchblur.fit.kernel_noise import kernel_noise_covariance
from torchblur.losses import fisher_covariance, image_loss, pixel_weights, residual_weights, singular_covariance
from torchblur.image.moments import image_moments, moments_along
from torchblur.optim import levenberg_marquardt, model_jacobian
from torchblur.fit.problem import cut_sums
from torchblur.fit.results import ToneFit
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.camera import CameraNoise, noise_sets_weights
from torchblur.render.blur import RenderSettings, _kernel_fourier, choose_node_count, quadrature_nodes, render_blur
from torchblur.render.splat import sine_blur_with_jacobian, window_nodes
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Multisine, Sinusoid

__all__ = ["MultisineFit", "render_multisine", "render_multisine_with_jacobian", "fit_multisine"]

# A set whose chi2 per used pixel (with the noise given; not per degree of freedom, the reported
# reduced chi2: this bound was measured per pixel, and the two differ by P / (n_used - P), 1.4e-4 on
# configs/identify_multisine.yaml's 12 frames of 64 x 64 px) exceeds this after the first search is
# searched again from a wider set of starts (_wide_starts). A local minimum was measured at 1.42 (one group of configs/identify_multisine.yaml:
# |H| 19-41 % off, "converged") where the right fit gives 0.96; the first search's 48 random phase
# starts land there for some seeds.
RETRY_CHI2 = 1.15

from torchblur.fit.status import POOR_FIT_STATUS_CHI2, above_chi2, flag_poor_fit, item_status


def render_multisine(theta, omega, psf: GaussianPSF | KernelPSF, window: ExposureWindow, *, height: int, width: int,
                     settings: RenderSettings | None = None, direction=None) -> torch.Tensor:
    """Images of a spot moving along ``direction`` (default x) as ``sum_k M_k sin(omega_k t + phi_k)``.

    Args:
        theta: ``[..., 2N]`` ``(M_1..M_N px, phi_1..phi_N rad)`` or ``[..., 2N + 1]`` with an
            intensity scale last.
        omega: rad/s, ``[..., N]``.
        psf: the spot at rest, batch ``[...]``: a GaussianPSF, or a KernelPSF (kernel ``[..., H, W]``).
        window: exposure windows (s), batch ``[..., E]`` (E images of the same motion).
        height, width: frame size H, W.
        settings: renderer settings.
        direction: the image direction (x, y) of the motion, ``[2]`` or ``[..., 2]``
            (normalised); None: +x.

    Returns:
        ``image[..., e, i, j]``, ``[..., E, H, W]``. Differentiable in ``theta``.
    """
    omega = as_tensor(omega, "omega", like=theta)
    N = omega.shape[-1]
    if theta.shape[-1] not in (2 * N, 2 * N + 1):
        raise ShapeError(f"theta: expected a last dim of 2N = {2 * N} or 2N + 1 (with the scale), got {tuple(theta.shape)}")
    amp = theta[..., :N, None] * unit_direction(direction, theta)[..., None, :]  # [..., N, 2]
    ph = theta[..., N:2 * N]
    traj = Multisine(amp[..., None, :, :], torch.stack([ph, ph], -1)[..., None, :, :], omega[..., None, :])
    img = render_blur(traj, psf[..., None], window, height=height, width=width, settings=settings)
    if theta.shape[-1] == 2 * N + 1:
        img = img * theta[..., 2 * N, None, None, None]
    return img


def render_multisine_with_jacobian(theta, omega, psf: GaussianPSF | KernelPSF, window: ExposureWindow, *, height: int, width: int,
                                   nodes: int, nodes_per_panel: int = 8, direction=None, pad=None,
                                   jacobian: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`render_multisine` (point-sampled pixels, ``nodes`` time nodes) and its Jacobian
    from one splat: the forward model :func:`~torchblur.render.splat.sine_blur_with_jacobian`
    with N components along the unit ``direction`` ``u`` (default +x), node positions
    ``c + u sum_k M_k sin(omega_k t_s + phi_k)`` (a Gaussian), or the kernel shifted by
    ``u sum_k ...`` (a measured kernel, its Fourier shift).

    Args:
        theta: ``[n, 2N]`` or ``[n, 2N + 1]`` (scale last).
        omega: ``[n, N]`` rad/s; psf: batch ``[n]`` (a GaussianPSF, or a KernelPSF of kernel
            ``[n, H, W]``); window: ``[n, E]``.
        height, width: frame size; nodes: time nodes (a multiple of ``nodes_per_panel``).
        direction: ``[2]`` or ``[n, 2]``, as in :func:`render_multisine`.
        pad: a kernel's FFT padding (px; :func:`~torchblur.render.splat.kernel_shift_with_jacobian`).
        jacobian: False: the image alone (``jac`` empty, ``P = 0``).

    Returns:
        ``(image [n, E, H, W], jac [n, E, H, W, P])``, ``jac[..., p] = d image / d theta_p``.
    """
    n, P = theta.shape
    N = omega.shape[-1]
    m = nodes_per_panel if nodes % nodes_per_panel == 0 else nodes
    tau, wq = quadrature_nodes(nodes // m, m, dtype=theta.dtype, device=theta.device)
    kern = isinstance(psf, KernelPSF)
    amp_psf = torch.ones(n, dtype=theta.dtype, device=theta.device) if kern else psf.amplitude
    t, w = window_nodes(window.start.to(theta.dtype), window.duration.to(theta.dtype), tau, wq, amp_psf[:, None])  # [n, E, S]
    u = unit_direction(direction, theta).expand(n, 2)
    center = theta.new_zeros(n, 2) if kern else psf.center
    precision = None if kern else tuple(v[:, None] for v in psf.precision())
    img, dimg = sine_blur_with_jacobian(t, w, theta[:, None, :N], theta[:, None, N:2 * N], omega[:, None, :],
                                        u[:, None, None, :], center[:, None, :], precision, height, width, jacobian=jacobian,
                                        kernel=psf.kernel[:, None] if kern else None, pad=pad)
    J = dimg.movedim(2, -1)  # [n, E, H, W, 2N]
    if P == 2 * N + 1:
        sc = theta[:, 2 * N, None, None, None]
        if jacobian:
            J = torch.cat([J * sc[..., None], img[..., None]], -1)
        img = img * sc
    return img, J


@dataclass(kw_only=True)
class MultisineFit(ToneFit):
    """Result of :func:`fit_multisine`: the :class:`~torchblur.fit.results.ToneFit` fields, with
    ``amplitude``, ``phase`` and their stds ``[..., N]`` (one per tone), ``param_names``
    ``amplitude_k``, ``phase_k`` (and ``scale``), ``cost`` the weighted sum of squared residuals,
    ``noise_std`` the median pixel noise std used, ``n_iter`` the LM iterations of the best start
    (plus the refit's, weighted by the noise model), ``flags`` :data:`~torchblur.fit.status.POOR_FIT_FLAG`.
    ``extras``: ``nodes``, ``starts``, ``refined``, ``crop``, ``retried``, ``reduced_chi2`` (``[...]``,
    the cost per degree of freedom, pixels used minus P, with the noise given, as
    :attr:`~torchblur.fit.results.SinusoidFit.reduced_chi2`; NaN without it); with
    ``kernel_var``, ``kernel_covariance [..., P, P]``: the measured kernel's part of ``covariance``.
    """


def _centroid_start(data, rest, u, start, dur, omega, thr):
    """``z_k = M_k e^{j phi_k}`` from the image centroids along the unit direction ``u [n, 2]``
    (``rest [n, 2]``), least squares. The window mean of ``Im(z e^{j w t})`` is
    ``Im(z G) / Te`` with ``G = (e^{j w t1} - e^{j w t0}) / (j w)``, linear in (Re z, Im z).
    data [n, E, H, W] -> (M [n, N], phi [n, N], rank-ok [n])."""
    _, cen, _ = image_moments(data, threshold=thr)
    mu = ((cen - rest[:, None]) * u[:, None]).sum(-1)  # [n, E]
    w = omega[:, None, :]  # [n, 1, N]
    t0, t1 = start[..., None], (start + dur)[..., None]
    # G / Te = (e^{j w t1} - e^{j w t0}) / (j w Te): real and imaginary parts
    re = (torch.sin(w * t1) - torch.sin(w * t0)) / (w * dur[..., None])
    im = -(torch.cos(w * t1) - torch.cos(w * t0)) / (w * dur[..., None])
    Amat = torch.cat([im, re], -1)  # [n, E, 2N]: mu = x Im G + y Re G
    sol = lstsq_solution(Amat, mu[..., None])[..., 0]
    sv = torch.linalg.svdvals(Amat)
    ok = sv[..., -1] > 1e-3 * sv[..., 0]
    N = omega.shape[-1]
    x, y = sol[..., :N], sol[..., N:]
    return torch.hypot(x, y), torch.atan2(y, x), ok


@dataclass(frozen=True)
class _Flat:
    """The inputs of :func:`fit_multisine` checked and flattened to ``B`` image sets.

    ``data [B, E, H, W]``; ``om [B, N]`` rad/s; ``start, dur [B, E]`` s; ``psf`` batch ``[B]``;
    ``center [B, 2]``, ``cov [B, 2, 2]`` its moments (a measured kernel's centroid and second
    moments); ``u [B, 2]`` the unit direction; ``batch`` the images' leading dims;
    :attr:`kernel` the psf's (a measured kernel's image ``[B, H, W]``, None for a Gaussian).
    """

    data: torch.Tensor
    om: torch.Tensor
    start: torch.Tensor
    dur: torch.Tensor
    center: torch.Tensor
    cov: torch.Tensor
    u: torch.Tensor
    batch: tuple
    psf: GaussianPSF | KernelPSF

    @property
    def kernel(self) -> torch.Tensor | None:
        """A measured kernel's image ``[B, H, W]`` (intensity per second), None for a Gaussian."""
        return self.psf.kernel if isinstance(self.psf, KernelPSF) else None


def _check_and_flatten(images, psf, window, omega, direction, counts: dict) -> _Flat:
    """The public entry's checks (:mod:`~torchblur.fit.inputs`), and the inputs flattened to ``B`` image sets."""
    images, psf, window = check_data(images, psf, window)
    for name, v in counts.items():
        check_count(v, name, 0 if name == "n_starts" else 1)
    batch, (E, H, W) = images.shape[:-3], images.shape[-3:]
    B = flat_count(images)
    data = images.reshape(B, E, H, W)
    win, p = flat_window(window, batch, B, E), flat_psf(psf, batch, B)
    center, cov = p.moments()
    return _Flat(data=data, om=flat_omega(omega, batch, B, data, tones=True), start=win.start, dur=win.duration,
                 center=center, cov=cov, u=flat_direction(direction, batch, B, data), batch=batch, psf=p)


def _noise_power(noise, power, noise_std, flat: _Flat) -> torch.Tensor | None:
    """Check ``noise`` (a :class:`~torchblur.render.camera.CameraNoise` or None) and ``power``
    (``[..., E]`` or a number, > 0; only with ``noise``) -> ``power [B, E]`` (ones when not given)
    where the noise model sets the weights (``noise`` given, ``noise_std`` not), else None."""
    by_model = noise_sets_weights(noise, noise_std)
    if power is None:
        pw = torch.ones_like(flat.start)
    elif noise is None:
        raise ParameterError("power: only the noise model uses it (the electrons the camera recorded are images * power); "
                             "pass noise= too, or leave power out")
    else:
        p = check_positive(check_finite(as_tensor(power, "power", like=flat.data), "power"), "power")
        try:
            pw = p.expand(flat.batch + flat.start.shape[-1:]).reshape(flat.start.shape)
        except RuntimeError:
            raise ShapeError(f"power: expected a number or [..., E] = {tuple(flat.batch + flat.start.shape[-1:])}, "
                             f"got {tuple(p.shape)}") from None
    return pw if by_model else None


def _own_value_std(noise: CameraNoise, pw: torch.Tensor, flat: _Flat) -> torch.Tensor:
    """The first pass's pixel noise std ``[..., E, H, W]`` (images' units): ``noise.std`` of each
    pixel's own charge ``images * power`` (electrons), divided by the power."""
    p = pw[:, :, None, None]
    return (noise.std(flat.data * p) / p).reshape(flat.batch + flat.data.shape[1:])


def _reweight_by_model(prob: _Problem, box, data, weight, theta, live, noise: CameraNoise, pw, stats, *, max_iter: int, tol: float):
    """The second pass of a fit weighted by the camera's noise model: the live sets ``live [L]``
    of ``data [B, E, H, W]`` (first-pass weights ``weight``, same shape) refitted by LM from the
    first pass's ``theta [B, P]`` with weights ``1 / std^2``, ``std =
    noise.std(model * power) / power`` of the first fit's model image (rendered by the problem's
    own forward model; 0 outside the crop, where every model is 0), masked pixels still 0.

    Why: docs/reliability.md, "The camera's noise and the losses".
    ``stats``: the fit's ``(cost, converged, n_iter, noise std) [B]``, set in place for the live
    sets (the refit's cost and convergence, the iterations added, the median of the new pixel
    stds). Returns ``(problem with the new weights, theta [B, P])``.
    """
    B, E, H, W = weight.shape
    lo_y, hi_y, lo_x, hi_x = box
    p = pw[live][:, :, None, None]
    expected = torch.zeros((live.numel(), E, H, W), dtype=weight.dtype, device=weight.device)
    with torch.no_grad():
        expected[..., lo_y:hi_y, lo_x:hi_x] = prob.model(theta[live], live).reshape(live.numel(), E, hi_y - lo_y, hi_x - lo_x)
    std = noise.std(expected * p) / p
    w2 = weight.clone()
    w2[live] = torch.where(weight[live] > 0, 1 / std**2, torch.zeros_like(std))
    prob = replace(prob, wflat=w2[..., lo_y:hi_y, lo_x:hi_x].reshape(B, -1), outside_cost=cut_sums(data, w2, box)[0])
    jac = (lambda th, i: prob.model_and_jacobian(th, live[i])) if prob.analytic else None
    res = levenberg_marquardt(lambda th, i: prob.model(th, live[i]), theta[live], prob.target[live], loss="l2", weight=prob.wflat[live],
                              max_iter=max_iter, tol=tol, jacobian_fn=jac)
    theta = theta.clone()
    theta[live] = res.theta
    cost, converged, n_iter, level = stats
    cost[live], converged[live], level[live] = res.cost, res.converged, median_along(std.reshape(live.numel(), -1))
    n_iter[live] += res.n_iter
    return prob, theta


def _levels(data: torch.Tensor, noise_level):
    """``(noise_level [B], dark [B], threshold [B, 1])`` from the pixel statistics: the noise
    (the given one, else the MAD), dark sets (peak below 8 noise stds), the moments' threshold."""
    B = data.shape[0]
    flat = data.reshape(B, -1)
    med = median_along(flat)
    mad = median_along((flat - med[:, None]).abs()) * 1.4826
    if noise_level is None:
        noise_level = mad
    peak = (flat - med[:, None]).amax(-1)
    dark = ~(peak > 8 * noise_level.clamp_min(torch.finfo(data.dtype).tiny))
    return noise_level, dark, med[:, None] + 3 * noise_level[:, None]


def _amplitude_start(flat: _Flat, amplitude_guess, thr) -> torch.Tensor:
    """``M0 [B, N]``: ``amplitude_guess``, else equal tones with the mean square of the motion
    from the images' second moments."""
    B, N = flat.om.shape
    if amplitude_guess is None:
        _, cen, icov = image_moments(flat.data, threshold=thr)
        along, vex = moments_along(cen - flat.center[:, None], icov - flat.cov[:, None], flat.u[:, None])
        ms = (vex + along**2).mean(-1).clamp_min(0.25)
        return (2 * ms / N).sqrt()[:, None].expand(B, N)
    M0 = check_finite(as_tensor(amplitude_guess, "amplitude_guess", like=flat.data), "amplitude_guess").abs()
    return M0.expand(flat.batch + (N,)).reshape(B, N).clamp_min(1e-3)


def _starts(flat: _Flat, M0, thr, phase_guess, n_starts: int, g: torch.Generator, fit_scale: bool) -> torch.Tensor:
    """Starts ``[B, K, P]``: the centroid least squares (with ``E >= 2N`` images), the phase
    guess, ``n_starts`` random phase vectors (from ``g``); the scale from the total light."""
    B, E, H, W = flat.data.shape
    N = flat.om.shape[-1]
    dtype, device = flat.data.dtype, flat.data.device
    cands = []
    if E >= 2 * N:
        Mc, pc, ok = _centroid_start(flat.data, flat.center, flat.u, flat.start, flat.dur, flat.om, thr)
        Mc = torch.where(ok[:, None] & torch.isfinite(Mc), Mc, M0)
        cands.append(torch.cat([Mc.clamp(min=1e-3, max=math.hypot(H, W)), torch.nan_to_num(pc)], -1))
    if phase_guess is not None:
        pg = check_finite(as_tensor(phase_guess, "phase_guess", like=flat.data), "phase_guess").expand(flat.batch + (N,)).reshape(B, N)
        cands.append(torch.cat([M0, pg], -1))
    if n_starts:
        rnd = (torch.rand(n_starts, N, generator=g, dtype=dtype) * 2 * math.pi - math.pi).to(device)
        for r in range(n_starts):
            cands.append(torch.cat([M0, rnd[r].expand(B, N)], -1))
    if not cands:
        cands.append(torch.cat([M0, torch.zeros_like(M0)], -1))
    theta_c = torch.stack(cands, 1)  # [B, K, 2N]
    if fit_scale:
        K = theta_c.shape[1]
        expected = (flat.psf.total_light()[:, None] * flat.dur).sum(-1)
        sc = (flat.data.sum((-1, -2, -3)) / expected.clamp_min(1e-30)).clamp_min(1e-3)
        theta_c = torch.cat([theta_c, sc[:, None, None].expand(B, K, 1)], -1)
    return theta_c


def _crop_box(flat: _Flat, theta_c) -> tuple[int, int, int, int]:
    """``(lo_y, hi_y, lo_x, hi_x)``: where the model of any start reaches (the whole frame if that is under 4 px)."""
    H, W = flat.data.shape[-2:]
    N = flat.om.shape[-1]
    reach = (theta_c[..., :N].abs().sum(-1).amax(1) * 1.3 + 0.5)[:, None] * flat.u.abs()  # [B, 2] (x, y) px
    lo, hi = flat.psf.footprint(7.0)
    lo_x = int(max(0, math.floor(float((lo[:, 0] - reach[:, 0]).min()))))
    hi_x = int(min(W, math.ceil(float((hi[:, 0] + reach[:, 0]).max())) + 1))
    lo_y = int(max(0, math.floor(float((lo[:, 1] - reach[:, 1]).min()))))
    hi_y = int(min(H, math.ceil(float((hi[:, 1] + reach[:, 1]).max())) + 1))
    if hi_x - lo_x < 4 or hi_y - lo_y < 4:
        return 0, H, 0, W
    return lo_y, hi_y, lo_x, hi_x


@dataclass(frozen=True)
class _Problem:
    """The cropped problem every search step evaluates.

    ``target, wflat [B, R]`` (R = E Hc Wc pixels in the crop); ``om [B, N]``; ``start, dur
    [B, E]``; ``psf`` (batch ``[B]``, centre in crop coordinates; a KernelPSF cut with the
    frame); ``u [B, 2]``; ``height, width`` of the crop; ``settings`` (node count fixed);
    ``outside_cost, outside_sq, outside_n [B]``: the weighted and plain sums of squares and the
    count of the used pixels outside the crop (a constant of the cost); ``pad``: a kernel's FFT
    padding (px), fixed from the starts' motion so the model does not jump between iterations;
    ``kernel_var [B, Hc, Wc]``: a measured kernel's pixel variance (cut like it), or None.
    """

    target: torch.Tensor
    wflat: torch.Tensor
    om: torch.Tensor
    start: torch.Tensor
    dur: torch.Tensor
    psf: GaussianPSF
    u: torch.Tensor
    height: int
    width: int
    settings: RenderSettings
    outside_cost: torch.Tensor
    outside_sq: torch.Tensor
    outside_n: torch.Tensor
    pad: int = 0
    kernel_var: torch.Tensor | None = None

    @property
    def analytic(self) -> bool:
        """Whether the Jacobian comes from the splat (point-sampled pixels; a kernel always)."""
        return isinstance(self.psf, KernelPSF) or not self.settings.pixel_integration

    def _items(self, item):
        p = self.psf
        return p[item], ExposureWindow(self.start[item], self.dur[item])

    def model(self, theta, item) -> torch.Tensor:
        """Rendered images of the sets ``item [n]`` at ``theta [n, P]`` -> ``[n, R]`` (a kernel:
        the splat's image, the very model :meth:`model_and_jacobian` differentiates)."""
        psf_i, win_i = self._items(item)
        if isinstance(psf_i, KernelPSF):
            return self._splat(theta, item, psf_i, win_i, jacobian=False)[0]
        img = render_multisine(theta, self.om[item], psf_i, win_i, height=self.height, width=self.width, settings=self.settings,
                               direction=self.u[item])
        return img.reshape(theta.shape[0], -1)

    def model_and_jacobian(self, theta, item):
        """``(model [n, R], J [n, R, P])`` from one splat (:func:`render_multisine_with_jacobian`)."""
        psf_i, win_i = self._items(item)
        return self._splat(theta, item, psf_i, win_i, jacobian=True)

    def _splat(self, theta, item, psf_i, win_i, *, jacobian: bool):
        img, J = render_multisine_with_jacobian(theta, self.om[item], psf_i, win_i, height=self.height, width=self.width,
                                                nodes=self.settings.nodes, nodes_per_panel=self.settings.nodes_per_panel,
                                                direction=self.u[item], pad=self.pad, jacobian=jacobian)
        return img.reshape(theta.shape[0], -1), J.reshape(theta.shape[0], -1, theta.shape[-1]) if jacobian else None


def _problem(flat: _Flat, weight, theta_c, render_settings, kernel_var=None) -> tuple[_Problem, tuple]:
    """The problem cropped to where the starts reach, its node count fixed for them -> ``(problem, crop box)``."""
    B, N = flat.om.shape
    dtype, device = flat.data.dtype, flat.data.device
    data = flat.data
    lo_y, hi_y, lo_x, hi_x = box = _crop_box(flat, theta_c)
    psf_c = flat.psf.cropped(lo_x, lo_y, hi_x, hi_y)
    reach = float((theta_c[..., :N].abs().sum(-1).amax(1) * 1.3 + 0.5).max()) if B else 0.0
    settings = render_settings or RenderSettings(panel_path_sigmas=3.5)
    if settings.nodes is None:
        bound = Multisine(((theta_c[..., :N].abs().amax(1) * 1.3 + 0.5)[..., None] * flat.u[:, None, :])[:, None],
                          torch.zeros(B, 1, N, 2, dtype=dtype, device=device), flat.om[:, None])
        S = choose_node_count(bound.path_length(ExposureWindow(torch.zeros_like(flat.dur), flat.dur)), psf_c.sigma_min()[:, None],
                              settings)
        settings = replace(settings, nodes=S)
    outside_cost, outside_sq, outside_n = cut_sums(data, weight, box)
    prob = _Problem(target=data[..., lo_y:hi_y, lo_x:hi_x].reshape(B, -1),
                    wflat=weight[..., lo_y:hi_y, lo_x:hi_x].reshape(B, -1), om=flat.om, start=flat.start, dur=flat.dur,
                    psf=psf_c, u=flat.u, height=hi_y - lo_y, width=hi_x - lo_x, settings=settings,
                    outside_cost=outside_cost, outside_sq=outside_sq, outside_n=outside_n,
                    pad=int(math.ceil(reach)) + 2,
                    kernel_var=None if kernel_var is None else kernel_var[:, lo_y:hi_y, lo_x:hi_x])
    return prob, box


def _coarse_cost(prob: _Problem, cands: torch.Tensor, item: int) -> torch.Tensor:
    """The cost ``[K]`` of the starts ``cands [K, P]`` of set ``item``, to rank them: each start's
    time nodes (the problem's) binned linearly by their position along ``u`` onto a grid of a
    tenth of the PSF's smallest width, the images the bins' light times the spot rendered still
    at each grid point (the spot rendered G times per set instead of E S times per start). The
    binning spreads each node's light over two grid points, a variance of at most ``h^2 / 4``
    px^2 along the motion (``h`` the grid step): 1/400 of the spot's."""
    N = prob.om.shape[-1]
    K, P = cands.shape
    dtype, device = cands.dtype, cands.device
    psf_i, _ = prob._items(slice(item, item + 1))
    kern = isinstance(psf_i, KernelPSF)
    S = prob.settings.nodes
    m = prob.settings.nodes_per_panel if S % prob.settings.nodes_per_panel == 0 else S
    tau, wq = quadrature_nodes(S // m, m, dtype=dtype, device=device)
    amp = torch.ones(1, dtype=dtype, device=device) if kern else psf_i.amplitude
    t, w = window_nodes(prob.start[item], prob.dur[item], tau, wq, amp.expand(prob.start.shape[-1]))  # [E, S]
    E = t.shape[0]
    arg = prob.om[item, :, None] * t.reshape(1, -1)  # [N, E S]
    phi = torch.cat([torch.sin(arg), torch.cos(arg)])  # sin(a + b) = sin a cos b + cos a sin b
    M, ph = cands[:, :N], cands[:, N:2 * N]
    coef = torch.cat([M * torch.cos(ph), M * torch.sin(ph)], -1)  # [K, 2N]
    ok = torch.isfinite(cands).all(-1)
    coef = torch.where(ok[:, None], coef, torch.zeros_like(coef))
    h = float(psf_i.sigma_min()) / 10
    reach = float(coef.abs().sum(-1).max()) + h
    G = int(math.ceil(2 * reach / h)) + 2
    if G * prob.height * prob.width > 2e7:  # a long path over a narrow spot: the grid's images would not fit, render each start
        return _rendered_cost(prob, cands, item)
    grid = torch.arange(G, dtype=dtype, device=device) * h - reach
    u = prob.u[item]
    if kern:
        basis = _kernel_fourier(psf_i.kernel, grid[:, None] * u[0], grid[:, None] * u[1], torch.ones(G, 1, dtype=dtype, device=device),
                                pad=prob.pad)
    else:
        zero = torch.zeros(G, 2, dtype=dtype, device=device)
        basis = render_blur(Sinusoid(zero, zero, 1.0), GaussianPSF(psf_i.center + grid[:, None] * u, psf_i.cov, 1.0),
                            ExposureWindow(0.0, 1.0), height=prob.height, width=prob.width,
                            settings=RenderSettings(pixel_integration=prob.settings.pixel_integration, nodes=1))
    basis = basis.reshape(G, -1)  # [G, Hc Wc]
    costs = []
    chunk = max(1, int(4e6 // (E * max(S, basis.shape[1], G))))
    for i in range(0, K, chunk):
        x = (coef[i:i + chunk] @ phi + reach) / h  # [k, E S] grid coordinate of every node
        j0 = x.floor().clamp(0, G - 2)
        f = x - j0
        j0 = j0.long().reshape(-1, E, S)
        wn = w.expand(j0.shape)
        hist = torch.zeros(j0.shape[0], E, G, dtype=dtype, device=device)
        hist.scatter_add_(-1, j0, wn * (1 - f.reshape(j0.shape))).scatter_add_(-1, j0 + 1, wn * f.reshape(j0.shape))
        model = (hist @ basis).reshape(hist.shape[0], -1)
        if P == 2 * N + 1:
            model = model * cands[i:i + chunk, 2 * N, None]
        costs.append(image_loss(model, prob.target[item], loss="l2", weight=prob.wflat[item]))
    return torch.where(ok, torch.cat(costs), torch.full_like(ok, float("nan"), dtype=dtype))


def _rendered_cost(prob: _Problem, cands: torch.Tensor, item: int) -> torch.Tensor:
    """The cost ``[K]`` of the starts ``cands [K, P]`` of set ``item`` from their rendered images (chunks of ~2e7 elements)."""
    E = prob.start.shape[-1]
    chunk = max(1, int(2e7 // max(1, E * prob.settings.nodes * (prob.height + prob.width))))
    it = torch.full((cands.shape[0],), item, dtype=torch.long, device=cands.device)
    return torch.cat([image_loss(prob.model(cands[i:i + chunk], it[i:i + chunk]), prob.target[item], loss="l2", weight=prob.wflat[item])
                      for i in range(0, cands.shape[0], chunk)])


def _search(prob: _Problem, cands, items_l, n_ref: int, max_iter: int, tol: float):
    """Coarse cost of every start ``cands [L, K, P]`` of the items ``items_l [L]`` (one render per
    chunk), then batched LM from the ``n_ref`` best of each -> the best result per item
    ``(theta [L, P], cost [L], converged [L], n_iter [L], refined)``."""
    L, Kc, P = cands.shape
    device = cands.device
    E = prob.start.shape[-1]
    with torch.no_grad():
        cost0 = torch.stack([_coarse_cost(prob, cands[k], int(items_l[k])) for k in range(L)])
    R_ = min(n_ref, Kc)
    best_k = torch.nan_to_num(cost0, nan=float("inf")).argsort(-1)[:, :R_]
    th0 = cands[torch.arange(L, device=device)[:, None], best_k].reshape(-1, P)
    items = items_l.repeat_interleave(R_)
    jac = (lambda th, i: prob.model_and_jacobian(th, items[i])) if prob.analytic else None
    res = levenberg_marquardt(lambda th, i: prob.model(th, items[i]), th0, prob.target[items], loss="l2", weight=prob.wflat[items],
                              max_iter=max_iter, tol=tol, jacobian_fn=jac)
    c = torch.nan_to_num(res.cost, nan=float("inf")).reshape(L, R_)
    pick = c.argmin(-1)
    ar = torch.arange(L, device=device)
    return (res.theta.reshape(L, R_, P)[ar, pick], c[ar, pick], res.converged.reshape(L, R_)[ar, pick],
            res.n_iter.reshape(L, R_)[ar, pick], R_)


def _reduced_chi2(prob: _Problem, cost, n_params: int) -> torch.Tensor:
    """The cost ``[B]`` (inside the crop; plus the problem's outside it) per degree of freedom:
    the used pixels (inside and outside the crop) less ``n_params`` (the fitted parameters P;
    0: per used pixel), at least 1 -> ``[B]``."""
    n_used = (prob.wflat > 0).sum(-1).to(cost.dtype) + prob.outside_n
    return (cost + prob.outside_cost) / (n_used - n_params).clamp_min(1)


def _search_all(prob: _Problem, theta_c, live, M0, *, sigma_given: bool, n_starts: int, n_refine: int, fit_scale: bool,
                g: torch.Generator, max_iter: int, tol: float):
    """The search for every live set ``live [L]``; with the noise given, sets left far above it
    (chi2 per used pixel > :data:`RETRY_CHI2`: a local minimum) are searched again from a wider set of
    starts (:func:`_wide_starts`), the better kept -> ``(theta [B, P], cost [B], converged [B], n_iter [B],
    refined, retried [B])``."""
    B = theta_c.shape[0]
    N = prob.om.shape[-1]
    dtype, device = theta_c.dtype, theta_c.device
    theta_best = theta_c[:, 0].clone()
    cost_best = torch.full((B,), float("nan"), dtype=dtype, device=device)
    conv_best = torch.zeros(B, dtype=torch.bool, device=device)
    iters_best = torch.zeros(B, dtype=torch.long, device=device)
    retried = torch.zeros(B, dtype=torch.bool, device=device)
    R_ = 0
    if not live.numel():
        return theta_best, cost_best, conv_best, iters_best, R_, retried
    th, cst, cv, itr, R_ = _search(prob, theta_c[live], live, n_refine, max_iter, tol)
    theta_best[live], cost_best[live], conv_best[live], iters_best[live] = th, cst, cv, itr
    if sigma_given:
        poor = live[_reduced_chi2(prob, cost_best, 0)[live] > RETRY_CHI2]  # per used pixel, as RETRY_CHI2 was measured
        if poor.numel():
            c2 = _wide_starts(M0[poor], theta_best[poor], theta_c[poor], N, n_starts, g, fit_scale)
            th, cst, cv, itr, _ = _search(prob, c2, poor, max(4 * n_refine, 24), max_iter, tol)
            better = cst < cost_best[poor]
            pb = poor[better]
            theta_best[pb], cost_best[pb], conv_best[pb], iters_best[pb] = th[better], cst[better], cv[better], itr[better]
            retried[poor] = True
    return theta_best, cost_best, conv_best, iters_best, R_, retried


def _wide_starts(M0, best, theta_c, N: int, n_starts: int, g: torch.Generator, fit_scale: bool) -> torch.Tensor:
    """The wider search's starts ``[L, K, P]`` for sets left above :data:`RETRY_CHI2`: random
    phase vectors (from ``g``) paired with amplitude vectors that a local minimum can hide: the
    guess ``M0 [L, N]`` times 0.6, 1 and 1.6, the best fit's mean amplitude on every tone, and the amplitudes of the best fit so far
    ``best [L, P]`` in every order of the tones (a local minimum often trades amplitude between
    tones; at most 24 orders). ``theta_c [L, K0, P]`` gives the scale start."""
    L = M0.shape[0]
    dtype, device = M0.dtype, M0.device
    perms = list(itertools.islice(itertools.permutations(range(N)), 24))
    even = best[:, :N].abs().mean(-1, keepdim=True).expand_as(M0)  # the same motion on every tone
    amps = [M0 * f for f in (0.6, 1.0, 1.6)] + [even] + [best[:, list(q)].abs() for q in perms]  # each [L, N]
    K2 = max(1024, 4 * n_starts)
    rnd = (torch.rand(K2, N, generator=g, dtype=dtype) * 2 - 1).to(device) * math.pi
    A = torch.stack(amps, 1)  # [L, nA, N]
    pick = torch.arange(K2, device=device) % A.shape[1]
    c2 = torch.cat([A[:, pick], rnd.expand(L, K2, N)], -1)
    if fit_scale:
        c2 = torch.cat([c2, theta_c[:, :1, 2 * N:].expand(L, K2, 1)], -1)
    return c2


def _fisher(prob: _Problem, theta, live, noise_level):
    """Inverse Fisher information at the solution -> ``(covariance [B, P, P], noise std used [B],
    singular [B], kernel term [B, P, P] or None)`` (NaN for sets not live). With ``noise_level``
    None the noise is estimated from the residuals (inside and outside the crop). With the
    problem's ``kernel_var`` the measured kernel's own noise is added to the covariance
    (:func:`_kernel_term`) and returned apart."""
    B, P = theta.shape
    dtype, device = theta.dtype, theta.device
    cov_out = torch.full((B, P, P), float("nan"), dtype=dtype, device=device)
    sigma_used = torch.full((B,), float("nan"), dtype=dtype, device=device)
    singular = torch.zeros(B, dtype=torch.bool, device=device)
    if not live.numel():
        return cov_out, sigma_used, singular, None
    if prob.analytic:
        model, J = prob.model_and_jacobian(theta[live], live)
    else:
        model, J = model_jacobian(lambda th, i: prob.model(th, live[i]), theta[live], torch.arange(live.numel(), device=device))
    wl = prob.wflat[live]
    if noise_level is not None:
        fw = wl
        sigma_used[live] = noise_level[live]
    else:
        fw, sig2 = residual_weights(prob.target[live] - model, wl, P, cut_sq=prob.outside_sq[live],
                                    cut_n=prob.outside_n[live])
        sigma_used[live] = sig2.sqrt()
    c_l, info = fisher_covariance(J, fw)
    kcov = None
    if prob.kernel_var is not None:
        kcov = torch.full_like(cov_out, float("nan"))
        kcov[live] = _kernel_term(prob, theta[live], live, J, fw, c_l)
        c_l = c_l + kcov[live]
    singular[live] = singular_covariance(c_l, info)
    cov_out[live] = c_l
    return cov_out, sigma_used, singular, kcov


def _kernel_term(prob: _Problem, theta, live, J, fw, cov) -> torch.Tensor:
    """The measured kernel's own noise in the covariance of the live sets ``[L, P, P]``
    (:func:`~torchblur.fit.kernel_noise.kernel_noise_covariance`, the splat's model as a function of the kernel)."""
    win = ExposureWindow(prob.start[live], prob.dur[live])

    def render(k):
        return prob._splat(theta, live, KernelPSF(k), win, jacobian=False)[0]

    return kernel_noise_covariance(render, prob.psf.kernel[live], prob.kernel_var[live], J, fw, cov)


def _kernel_variance(kernel_var, flat: _Flat) -> torch.Tensor | None:
    """``kernel_var`` checked (only with a KernelPSF; >= 0; the kernel's shape) -> ``[B, H, W]`` or None."""
    if kernel_var is None:
        return None
    if flat.kernel is None:
        raise ParameterError("kernel_var: the variance of a measured kernel; the psf is a GaussianPSF (leave kernel_var out)")
    v = check_finite(as_tensor(kernel_var, "kernel_var", like=flat.data), "kernel_var")
    if bool((v < 0).any()):
        raise ParameterError(f"kernel_var: expected every value >= 0, got minimum {float(v.min()):g}")
    try:
        return v.expand(flat.batch + flat.kernel.shape[-2:]).reshape(flat.kernel.shape)
    except RuntimeError:
        raise ShapeError(f"kernel_var: expected the kernel's shape {tuple(flat.kernel.shape[-2:])} (or one that "
                         f"broadcasts to "
                         f"{tuple(flat.batch + flat.kernel.shape[-2:])}), got {tuple(v.shape)}") from None


def fit_multisine(
    images,
    psf: GaussianPSF | KernelPSF,
    window: ExposureWindow,
    omega,
    *,
    noise_std=None,
    noise: CameraNoise | None = None,
    power=None,
    mask=None,
    amplitude_guess=None,
    phase_guess=None,
    fit_scale: bool = True,
    n_starts: int = 48,
    n_refine: int = 3,
    max_iter: int = 60,
    tol: float = 1e-9,
    seed: int = 0,
    render_settings: RenderSettings | None = None,
    direction=None, kernel_var=None,
) -> MultisineFit:
    """Fit the N tones ``(M_k, phi_k)`` of a multisine motion along ``direction`` (default x) to an image set.

    Args:
        images: ``[..., E, H, W]``: E images of the same periodic motion (dark subtracted, in
            the PSF's units times seconds), each over its own window.
        psf: :class:`GaussianPSF` or a measured :class:`KernelPSF` (``[..., H, W]``), batch ``[...]`` (the laser power in it)
        window: exposure windows (s) on the command clock, batch ``[..., E]``.
        omega: tone frequencies (rad/s), ``[..., N]``.
        noise_std: pixel noise std: a number, ``[...]`` or ``[..., E, H, W]``; None: from
            ``noise`` (unbiased: :func:`_reweight_by_model`), else unweighted, the noise level
            estimated from the residuals.
        noise: the camera's :class:`~torchblur.render.camera.CameraNoise` (of ``images * power``), or None.
        power: ``[..., E]`` or a number (default 1), only with ``noise``: the laser power each
            image (and the PSF) was divided by, so that ``noise`` applies to ``images * power``.
        mask: bool ``[..., E, H, W]``, False excludes a pixel (saturated).
        amplitude_guess: expected ``M_k`` (px), ``[..., N]`` or a number; default from the
            images' second moments (equal tones).
        phase_guess: an extra start for the phases (rad), ``[..., N]``.
        fit_scale: fit an intensity scale too.
        n_starts: random phase vectors whose cost is evaluated (plus the centroid start and
            ``phase_guess``); ``n_refine`` of the best are refined by LM.
        max_iter, tol: LM settings.
        seed: seed of the random starts.
        render_settings: renderer settings (default: panels of 3.5 PSF widths, node count
            fixed for the whole fit).
        direction: the image direction (x, y) of the motion, ``[2]`` or ``[..., 2]``
            (normalised): an actuator axis rotated in the camera's image
            (:func:`torchblur.image.tracking.calibrate_axes`); None: +x.
        kernel_var: a measured kernel's pixel variance ``[..., H, W]``: its noise in the covariance (:mod:`~torchblur.fit.kernel_noise`).

    Returns:
        :class:`MultisineFit`.
    """
    flat = _check_and_flatten(images, psf, window, omega, direction, {"n_starts": n_starts, "n_refine": n_refine, "max_iter": max_iter})
    batch, (B, N) = flat.batch, flat.om.shape
    pw = _noise_power(noise, power, noise_std, flat)
    weight, s = pixel_weights(noise_std if pw is None else _own_value_std(noise, pw, flat), mask,
                              flat.data.reshape(batch + flat.data.shape[1:]))
    given_level = None if s is None else median_along(s.reshape(B, -1))  # the median given noise std per image set
    sigma_given = given_level is not None
    noise_level, dark, thr = _levels(flat.data, given_level)
    M0 = _amplitude_start(flat, amplitude_guess, thr)
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    theta_c = _starts(flat, M0, thr, phase_guess, n_starts, g, fit_scale)
    K = theta_c.shape[1]
    prob, crop = _problem(flat, weight, theta_c, render_settings, _kernel_variance(kernel_var, flat))
    live = torch.arange(B, device=flat.data.device)[~dark]
    theta_best, cost_best, conv_best, iters_best, R_, retried = _search_all(
        prob, theta_c, live, M0, sigma_given=sigma_given, n_starts=n_starts, n_refine=n_refine, fit_scale=fit_scale, g=g,
        max_iter=max_iter, tol=tol)
    if pw is not None and live.numel():
        prob, theta_best = _reweight_by_model(prob, crop, flat.data, weight, canonical_sines(theta_best, N), live, noise, pw,
                                              (cost_best, conv_best, iters_best, noise_level), max_iter=max_iter, tol=tol)
    search = {"starts": K, "refined": R_, "crop": crop, "retried": retried}
    return _multisine_result(prob, canonical_sines(theta_best, N), (cost_best, conv_best, iters_best), live, dark, noise_level,
                             sigma_given, fit_scale, batch, search)


def _multisine_result(prob, theta_best, best, live, dark, noise_level, sigma_given: bool, fit_scale: bool, batch: tuple,
                      search: dict) -> MultisineFit:
    """The :class:`MultisineFit` (batch shape ``batch``) of the best parameters ``theta_best
    [B, P]`` (canonical) with their ``best = (cost [B], converged [B], iterations [B])``: the
    Fisher covariance, status and flags; NaN where ``dark [B]``; ``search`` (starts, refined,
    crop, retried [B]) goes into ``extras``."""
    cost_best, conv_best, iters_best = best
    N = (theta_best.shape[-1] - int(fit_scale)) // 2
    P = theta_best.shape[-1]
    cov_out, sigma_used, singular, kcov = _fisher(prob, theta_best, live, noise_level if sigma_given else None)
    std = torch.diagonal(cov_out, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    # per degree of freedom, as fit_sinusoid's; NaN without a given noise (unknown: never flagged, never POOR_FIT)
    red_chi2 = _reduced_chi2(prob, cost_best, P) if sigma_given else torch.full_like(cost_best, float("nan"))
    # POOR_FIT: still far above the given noise (reduced chi2 > POOR_FIT_STATUS_CHI2) after the wider search
    status = item_status(conv_best, singular, dark, poor=above_chi2(red_chi2, POOR_FIT_STATUS_CHI2))
    nan = torch.tensor(float("nan"), dtype=theta_best.dtype, device=theta_best.device)

    def out(x, tail=()):
        return x.reshape(batch + tail)

    bad = dark[:, None]
    res = MultisineFit(
        amplitude=out(torch.where(bad, nan, theta_best[:, :N]), (N,)),
        phase=out(torch.where(bad, nan, theta_best[:, N:2 * N]), (N,)),
        amplitude_std=out(torch.where(bad, nan, std[:, :N]), (N,)),
        phase_std=out(torch.where(bad, nan, std[:, N:2 * N]), (N,)),
        covariance=out(cov_out, (P, P)),
        param_names=tuple([f"amplitude_{k}" for k in range(N)] + [f"phase_{k}" for k in range(N)]
                          + ["scale"] * fit_scale),
        cost=out(cost_best + prob.outside_cost),
        converged=out(status == 0),
        status=out(status),
        noise_std=out(sigma_used),
        n_iter=out(iters_best),
        scale=out(torch.where(dark, nan, theta_best[:, 2 * N])) if fit_scale else None,
    )
    res.extras.update({"nodes": prob.settings.nodes, "starts": search["starts"], "refined": search["refined"],
                       "crop": search["crop"], "retried": out(search["retried"]), "reduced_chi2": out(red_chi2)}
                      | ({} if kcov is None else {"kernel_covariance": out(kcov, (P, P))}))
    res.flags = out(flag_poor_fit(None, red_chi2))
    return res
