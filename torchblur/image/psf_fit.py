"""The still spot's PSF: a 2-D Gaussian with full covariance fitted to a still frame (batched
Levenberg-Marquardt, Fisher-information uncertainties). Conventions: x = column j, y = row i, px, px^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchblur._compat import median_along
from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_image, as_tensor, broadcast_batch, check_bool,
                              check_int, check_positive, check_type)
from torchblur.optim import levenberg_marquardt
from torchblur.image.dark import _MAD_TO_STD
from torchblur.image.moments import image_moments
from torchblur.render.blur import RenderSettings, _subpixel, _subpixel_count, render_blur
from torchblur.render.psf import GaussianPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

__all__ = ["PSFFit", "fit_gaussian_psf", "point_sampled_equivalent"]


@dataclass
class PSFFit:
    """Result of :func:`fit_gaussian_psf`, batch ``[...]``.

    Attributes:
        psf: the fitted :class:`~torchblur.render.psf.GaussianPSF` (center ``[..., 2]`` px, cov
            ``[..., 2, 2]`` px^2, amplitude ``[...]`` = peak intensity per second).
        background: ``[...]`` fitted constant offset (image units; 0 if not fitted).
        residual_rms: ``[...]`` rms of ``image - model`` over the fitted pixels.
        relative_residual: ``[...]`` ``residual_rms`` over the model's peak above background.
        cov_std: ``[..., 2, 2]`` one standard deviation of each covariance entry (px^2);
            NaN where the information matrix is singular (the same for the two below).
        center_std: ``[..., 2]`` one standard deviation of the centre (px).
        amplitude_std: ``[...]`` one standard deviation of the amplitude.
        converged: ``[...]`` bool: the Levenberg-Marquardt iteration converged.
        model: ``[..., H, W]`` the fitted image (renderer output plus background).
    """

    psf: GaussianPSF
    background: torch.Tensor
    residual_rms: torch.Tensor
    relative_residual: torch.Tensor
    cov_std: torch.Tensor
    center_std: torch.Tensor
    amplitude_std: torch.Tensor
    converged: torch.Tensor
    model: torch.Tensor


def point_sampled_equivalent(psf: GaussianPSF) -> GaussianPSF:
    """The point-sampled Gaussian that stands for ``psf`` integrated over unit pixels: the same
    centre, the same light (``amplitude * 2 pi sqrt(det cov)``) and the same second moments,
    ``cov + I / 12`` (a unit box's variance on each axis). Batch ``[...]`` as ``psf``.

    Why: a camera's pixels integrate the spot, and the fast renderer (and so
    :func:`~torchblur.fit.sinusoid.fit_sinusoid`'s Gaussian path) samples it at pixel centres.
    Fit a still with ``pixel_integration=True`` (the right model) and hand the fitter this
    moment match. Fitting the still point-sampled instead lets the box's flat top bend the
    Gaussian's width (for a 1.2 px spot: cov 1.5246 instead of 1.5233 px^2), and a blur fit
    that holds the width fixed turns that into the motion: amplitudes 0.1 % low, most for
    small motions, the same on every frame of a spot. The moment match leaves only the box's
    fourth moment, 1e-4 of the amplitude."""
    check_type(psf, "psf", GaussianPSF, "a GaussianPSF")
    cov = psf.cov + torch.eye(2, dtype=psf.cov.dtype, device=psf.cov.device) / 12.0
    amplitude = psf.amplitude * (torch.linalg.det(psf.cov) / torch.linalg.det(cov)).sqrt()
    return GaussianPSF(psf.center, cov, amplitude)


def _cholesky_cov(theta: torch.Tensor) -> torch.Tensor:
    """theta[:, 2:5] = (log L00, L10, log L11) -> cov [n, 2, 2] = L L^T."""
    L00 = torch.exp(theta[:, 2])
    L11 = torch.exp(theta[:, 4])
    L10 = theta[:, 3]
    # Exactly 0 would send the renderer down its axis-aligned path, which ignores the cross
    # term and so has no derivative in it; a relative eps keeps the tilted path.
    L10 = L10 + (L10 == 0).to(L10.dtype) * torch.finfo(L10.dtype).eps * L00
    sxx = L00 * L00
    sxy = L00 * L10
    syy = L10 * L10 + L11 * L11
    return torch.stack([torch.stack([sxx, sxy], -1), torch.stack([sxy, syy], -1)], -2)


def fit_gaussian_psf(
    image,
    *,
    exposure_s,
    noise_std=None,
    mask=None,
    fit_background: bool = True,
    pixel_integration: bool = True,
    max_iter: int = 100,
) -> PSFFit:
    """Fit a 2-D Gaussian PSF (full covariance), its amplitude and a background to a still spot.

    The model image is the library's renderer in still mode,
    ``render_blur(Sinusoid(0, 0, 1), GaussianPSF(c, cov, a), ExposureWindow(0, exposure_s),
    settings=RenderSettings(pixel_integration=...)) + background``, so the fitted PSF is
    exactly the one the renderer reproduces the image with: ``amplitude`` is per second of
    exposure and the pixel-integration setting matches. Parameters
    ``(cx, cy, log L00, L10, log L11, a[, b])`` with ``cov = L L^T`` (L lower triangular,
    positive diagonal) keep the covariance positive definite. The fit is a batched
    Levenberg-Marquardt (:func:`torchblur.optim.levenberg_marquardt`) started from the image
    moments, computed in float64 (results cast back to the image's dtype).

    Args:
        image: still-spot image ``[..., H, W]`` (averaged still frames, dark-subtracted),
            finite where ``mask`` is True.
        exposure_s: exposure of ``image`` in seconds, a number or ``[...]`` (> 0).
        noise_std: pixel noise std of ``image``: a number, ``[...]`` or a per-pixel map
            ``[..., H, W]`` (recognised by its trailing ``(H, W)``); the fit is weighted by
            ``1 / noise_std^2`` and ``cov_std`` comes from the Fisher information. None: an
            unweighted fit whose uncertainty is the heteroscedasticity-consistent (sandwich)
            estimate ``(J^T J)^-1 J^T diag(r^2) J (J^T J)^-1`` from the residuals ``r``.
        mask: bool ``[..., H, W]`` (or ``[H, W]``), False excludes a pixel (saturated, hot).
        fit_background: fit a constant offset (else background 0).
        pixel_integration: the renderer's pixel-area integration (must match how the PSF
            will be rendered).
        max_iter: Levenberg-Marquardt iterations at most (>= 1).

    Returns:
        :class:`PSFFit`, batch ``[...]`` (the broadcast of image, exposure, noise and mask
        batches).

    Example:
        >>> psf = GaussianPSF.from_axes(torch.tensor([12.3, 11.6]), 2.4, 1.5, 0.6, amplitude=1e4)
        >>> img = render_blur(Sinusoid(torch.zeros(2), torch.zeros(2), 1.0), psf, ExposureWindow(0.0, 0.1),
        ...                   height=24, width=24, settings=RenderSettings(pixel_integration=True))
        >>> fit_gaussian_psf(img, exposure_s=0.1).psf.cov.shape
        torch.Size([2, 2])
    """
    pb = _psf_problem(image, exposure_s, noise_std, mask, fit_background, pixel_integration)
    max_iter = check_int(max_iter, "max_iter", low=1)
    theta0 = _psf_start(pb.data, pb.used, pb.expo, pb.H, pb.W, fit_background)
    # Amplitude and background are fitted in units of their start's scale, so every Jacobian
    # column has a comparable size (the optimiser's small absolute regulariser then damps none).
    data, used = pb.data, pb.used
    span = (torch.where(used, data, -torch.inf).amax(-1) - torch.where(used, data, torch.inf).amin(-1)).clamp_min(1e-30)
    a_scale = torch.where(theta0[:, 5] > 0, theta0[:, 5], span / pb.expo)
    b_scale = span
    theta0[:, 5] = theta0[:, 5] / a_scale
    if fit_background:
        theta0[:, 6] = theta0[:, 6] / b_scale
    model_fn, jac_fn, project = _psf_model(pb, a_scale, b_scale)
    res = levenberg_marquardt(model_fn, theta0, data, weight=pb.weight, max_iter=max_iter, project=project, jacobian_fn=jac_fn)
    theta = res.theta
    model, J = jac_fn(theta, torch.arange(pb.N, device=data.device))
    resid = (data - model) * used
    cov_theta = _theta_covariance(J, pb.weight, used, resid, noise_given=noise_std is not None)
    return _psf_result(pb, theta, cov_theta, model, resid, a_scale, b_scale, res.converged)


@dataclass(frozen=True)
class _PSFProblem:
    """A batch of still-spot images flattened to ``N`` problems of ``H W`` pixels (float64 or wider)."""

    data: torch.Tensor  # [N, H W], 0 where unused
    used: torch.Tensor  # bool [N, H W]
    weight: torch.Tensor  # [N, H W]: used / noise^2 (used alone without a noise)
    expo: torch.Tensor  # [N] exposure (s)
    batch: torch.Size
    H: int
    W: int
    in_dtype: torch.dtype
    fit_background: bool
    pixel_integration: bool

    @property
    def N(self) -> int:
        return self.data.shape[0]

    @property
    def P(self) -> int:
        return 6 + int(self.fit_background)


def _psf_problem(image, exposure_s, noise_std, mask, fit_background, pixel_integration) -> _PSFProblem:
    """Check :func:`fit_gaussian_psf`'s inputs and flatten them into a :class:`_PSFProblem`."""
    image = as_image(image, "image")
    H, W = image.shape[-2:]
    in_dtype, device = image.dtype, image.device
    dtype = torch.float64 if torch.finfo(in_dtype).bits < 64 else in_dtype
    fit_background = check_bool(fit_background, "fit_background")
    pixel_integration = check_bool(pixel_integration, "pixel_integration")
    exposure = check_positive(as_tensor(exposure_s, "exposure_s", like=image), "exposure_s")
    shapes = {"image": image.shape[:-2], "exposure_s": exposure.shape}
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError(f"mask: expected a bool tensor [..., H, W], got {type(mask).__name__}"
                                 f"{'' if not isinstance(mask, torch.Tensor) else ' of dtype ' + str(mask.dtype)}")
        if mask.dim() < 2 or tuple(mask.shape[-2:]) != (H, W):
            raise ShapeError(f"mask: expected shape [..., {H}, {W}] like image, got {tuple(mask.shape)}")
        shapes["mask"] = mask.shape[:-2]
    per_pixel = False
    if noise_std is not None:
        sigma = check_positive(as_tensor(noise_std, "noise_std", like=image), "noise_std")
        per_pixel = sigma.dim() >= 2 and tuple(sigma.shape[-2:]) == (H, W)
        shapes["noise_std"] = sigma.shape[:-2] if per_pixel else sigma.shape
    batch = broadcast_batch(shapes)
    N = math.prod(batch)

    data = image.detach().to(dtype).expand(batch + (H, W)).reshape(N, H * W)
    used = torch.ones(N, H * W, dtype=torch.bool, device=device)
    if mask is not None:
        used = mask.to(device).expand(batch + (H, W)).reshape(N, H * W).clone()
    bad = ~torch.isfinite(data) & used
    if bool(bad.any()):
        raise ParameterError(f"image: expected finite values where mask is True, got {int(bad.sum())} NaN/Inf entries")
    data = torch.where(used, data, torch.zeros_like(data))
    P = 6 + int(fit_background)
    n_used = used.sum(-1)
    if bool((n_used <= P).any()):
        raise ParameterError(f"mask: expected more than {P} usable pixels per image, got {int(n_used.min())}")
    weight = used.to(dtype)
    if noise_std is not None:
        s = sigma.detach().to(dtype)
        s = s.expand(batch + (H, W)) if per_pixel else s.expand(batch)[..., None, None].expand(batch + (H, W))
        weight = weight / s.reshape(N, H * W).square()
    expo = exposure.detach().to(dtype).expand(batch).reshape(N)
    return _PSFProblem(data, used, weight, expo, batch, H, W, in_dtype, fit_background, pixel_integration)


def _psf_model(pb: _PSFProblem, a_scale, b_scale):
    """The still spot's model ``theta [n, P] -> image [n, H W]``, its Jacobian (one forward-AD
    pass for all ``P`` columns) and the projection that keeps theta in a sane box."""
    H, W, P = pb.H, pb.W, pb.P
    dtype, device = pb.data.dtype, pb.data.device
    settings = RenderSettings(pixel_integration=pb.pixel_integration, nodes=1)  # a still spot: one time node is exact
    zeros2 = torch.zeros(1, 2, dtype=dtype, device=device)

    def model_fn(theta, idx):
        n = theta.shape[0]
        psf = GaussianPSF(theta[:, 0:2], _cholesky_cov(theta), theta[:, 5] * a_scale[idx])
        still = Sinusoid(zeros2.expand(n, 2), zeros2.expand(n, 2), 1.0)
        img = render_blur(still, psf, ExposureWindow(0.0, pb.expo[idx]), height=H, width=W, settings=settings)
        img = img.reshape(n, H * W)
        if pb.fit_background:
            img = img + theta[:, 6:7] * b_scale[idx, None]
        return img

    def jac_fn(theta, idx):
        # The model from the renderer (the values the fit matches), its Jacobian in closed form
        # (forward-mode AD through the renderer cost the same and imported torch._dynamo, ~2 s).
        theta = theta.detach()
        J = _still_jacobian(theta, pb.expo[idx] * a_scale[idx], H, W, pb.pixel_integration)
        if pb.fit_background:
            J = torch.cat([J, b_scale[idx, None, None].expand(theta.shape[0], H * W, 1)], -1)
        return model_fn(theta, idx), J

    log_lo, log_hi = math.log(0.05), math.log(4.0 * max(H, W))

    def project(theta):
        theta = theta.clone()
        theta[:, 2] = theta[:, 2].clamp(log_lo, log_hi)
        theta[:, 4] = theta[:, 4].clamp(log_lo, log_hi)
        theta[:, 3] = theta[:, 3].clamp(-4.0 * max(H, W), 4.0 * max(H, W))
        theta[:, 0] = theta[:, 0].clamp(-W, 2 * W)
        theta[:, 1] = theta[:, 1].clamp(-H, 2 * H)
        theta[:, 5] = theta[:, 5].clamp_min(0.0)  # a spot the Gaussian cannot describe ends at 0 light, never raises (issue 23)
        return theta

    return model_fn, jac_fn, project


def _still_jacobian(theta: torch.Tensor, light: torch.Tensor, H: int, W: int, pixel_integration: bool) -> torch.Tensor:
    """``d image / d theta[:, :6]`` ``[n, H W, 6]`` of the still spot that :func:`_psf_model` renders:
    ``image = theta_5 light sum_ab w_a w_b exp(-q/2)`` over the renderer's sub-pixel nodes (one
    node at the pixel centre when point-sampled), ``q = |L^-1 (x - c)|^2 = u^2 + v^2`` with
    ``u = dx / L00``, ``v = (dy - L10 u) / L11``. ``theta [n, 6+]`` as :func:`fit_gaussian_psf`'s,
    ``light [n]`` = exposure times the amplitude's scale."""
    n, dtype, device = theta.shape[0], theta.dtype, theta.device
    cov = _cholesky_cov(theta)
    if pixel_integration:
        off, ow = _subpixel(_subpixel_count(GaussianPSF(theta[:, :2], cov).sigma_min()), dtype, device)
    else:
        off, ow = torch.zeros(1, dtype=dtype, device=device), torch.ones(1, dtype=dtype, device=device)
    m = off.numel()
    e0, e1 = torch.exp(-theta[:, 2]), torch.exp(-theta[:, 4])
    c = cov[:, 0, 1] * e0  # L10 as the renderer used it (an exact 0 nudged, see _cholesky_cov)
    cols = []
    step = max(1, int(4e6 // (H * W * m * m)))  # problems per chunk: the [n, H, m, W, m] grids stay ~32 MB
    for i in range(0, n, step):
        s = slice(i, i + step)
        dx = (torch.arange(W, dtype=dtype, device=device)[:, None] + off) - theta[s, 0, None, None]  # [k, W, m]
        dy = (torch.arange(H, dtype=dtype, device=device)[:, None] + off) - theta[s, 1, None, None]  # [k, H, m]
        u = (dx * e0[s, None, None])[:, None, None]  # [k, 1, 1, W, m]
        v = (dy[..., None, None] - c[s, None, None, None, None] * u) * e1[s, None, None, None, None]  # [k, H, m, W, m]
        g = torch.exp(-0.5 * (u * u + v * v)) * (ow[:, None, None] * ow)  # sub-pixel weights folded in
        k = g.shape[0]
        # -q/2's derivatives: centre (x, y), log L00, L10, log L11
        d = torch.stack([u * e0[s, None, None, None, None] - v * (c * e0 * e1)[s, None, None, None, None],
                         (v * e1[s, None, None, None, None]).expand_as(g), u * u - v * (c * e1)[s, None, None, None, None] * u,
                         v * u * e1[s, None, None, None, None], v * v], -1)  # [k, H, m, W, m, 5]
        scale = theta[s, 5] * light[s]
        dg = (g[..., None] * d).sum((2, 4)).reshape(k, H * W, 5) * scale[:, None, None]
        cols.append(torch.cat([dg[..., :5], (g.sum((2, 4)).reshape(k, H * W) * light[s, None])[..., None]], -1))
    return torch.cat(cols, 0)


def _theta_covariance(J, weight, used, resid, *, noise_given: bool) -> torch.Tensor:
    """Parameter covariance ``[N, P, P]``: the Fisher information's inverse (noise given) or the
    HC2 sandwich estimate from the residuals; NaN where the information matrix is singular."""
    if noise_given:
        F = (J * weight[..., None]).transpose(-1, -2) @ J
        cov_theta, info = torch.linalg.inv_ex(F)
    else:
        Ju = J * used.to(J.dtype)[..., None]
        bread, info = torch.linalg.inv_ex(Ju.transpose(-1, -2) @ Ju)
        # HC2: r^2 / (1 - h) with the leverages h = diag(J (J^T J)^-1 J^T) undoes the
        # shrinkage of the residuals of the few high-leverage (spot) pixels.
        lev = ((Ju @ bread) * Ju).sum(-1).clamp(0, 0.99)
        Jr = Ju * (resid / (1 - lev).sqrt())[..., None]
        meat = Jr.transpose(-1, -2) @ Jr
        cov_theta = bread @ meat @ bread
    # A singular information matrix (no spot, or a parameter the data cannot fix): NaN std.
    return torch.where((info != 0)[:, None, None], torch.full_like(cov_theta, float("nan")), cov_theta)


def _psf_result(pb: _PSFProblem, theta, cov_theta, model, resid, a_scale, b_scale, converged) -> PSFFit:
    """The :class:`PSFFit` of the fitted ``theta [N, P]``, with the covariance's stds propagated
    through ``cov = L L^T``, reshaped to the batch and cast back to the image's dtype."""
    N, P, dtype = pb.N, pb.P, theta.dtype
    L00, L10, L11 = torch.exp(theta[:, 2]), theta[:, 3], torch.exp(theta[:, 4])
    G = torch.zeros(N, 3, P, dtype=dtype, device=theta.device)  # d(sxx, sxy, syy) / d theta
    G[:, 0, 2] = 2 * L00 * L00
    G[:, 1, 2] = L00 * L10
    G[:, 1, 3] = L00
    G[:, 2, 3] = 2 * L10
    G[:, 2, 4] = 2 * L11 * L11
    var_c = torch.diagonal(G @ cov_theta @ G.transpose(-1, -2), dim1=-2, dim2=-1).clamp_min(0)
    std_c = var_c.sqrt()
    cov_std = torch.stack([torch.stack([std_c[:, 0], std_c[:, 1]], -1), torch.stack([std_c[:, 1], std_c[:, 2]], -1)], -2)
    std_theta = torch.diagonal(cov_theta, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    bg = theta[:, 6] * b_scale if pb.fit_background else torch.zeros(N, dtype=dtype, device=theta.device)
    rms = (resid.square().sum(-1) / pb.used.sum(-1).to(dtype)).sqrt()
    peak = (model - bg[:, None]).amax(-1)
    rel = rms / peak.abs().clamp_min(torch.finfo(dtype).tiny)

    def out(x, tail=()):
        return x.detach().reshape(pb.batch + tail).to(pb.in_dtype)

    psf = GaussianPSF(out(theta[:, 0:2], (2,)), out(_cholesky_cov(theta), (2, 2)), out(theta[:, 5] * a_scale))
    return PSFFit(
        psf=psf,
        background=out(bg),
        residual_rms=out(rms),
        relative_residual=out(rel),
        cov_std=out(cov_std, (2, 2)),
        center_std=out(std_theta[:, 0:2], (2,)),
        amplitude_std=out(std_theta[:, 5] * a_scale),
        converged=converged.reshape(pb.batch),
        model=out(model, (pb.H, pb.W)),
    )


def _psf_start(data, used, expo, H, W, fit_background):
    """Moment start ``[N, P]`` for the PSF fit from flattened data ``[N, H*W]``."""
    N = data.shape[0]
    dtype = data.dtype
    img = data.reshape(N, H, W)
    u = used.reshape(N, H, W)
    nan = torch.full_like(img, float("nan"))
    vals = torch.where(u, img, nan).reshape(N, -1)
    if fit_background:
        edge = torch.zeros(H, W, dtype=torch.bool, device=img.device)
        edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        ev = torch.where(u & edge, img, nan).reshape(N, -1)
        bg = torch.where(torch.isnan(ev).all(-1), median_along(vals, ignore_nan=True), median_along(ev, ignore_nan=True))
    else:
        bg = torch.zeros(N, dtype=dtype, device=img.device)
    sig = img - bg[:, None, None]
    noise = _MAD_TO_STD * median_along((vals - bg[:, None]).abs(), ignore_nan=True)
    peak = torch.where(u, sig, torch.full_like(sig, -float("inf"))).amax((-1, -2))
    thr = torch.maximum(0.02 * peak, 3 * noise)
    total, centroid, cov = image_moments(torch.where(u, sig, torch.zeros_like(sig)), threshold=thr)
    good = (total > 0) & torch.isfinite(cov).all(-1).all(-1)
    sxx = torch.where(good, cov[:, 0, 0], torch.ones_like(total)).clamp_min(0.05)
    syy = torch.where(good, cov[:, 1, 1], torch.ones_like(total)).clamp_min(0.05)
    sxy = torch.where(good, cov[:, 0, 1], torch.zeros_like(total))
    sxy = sxy.clamp(-0.95 * (sxx * syy).sqrt(), 0.95 * (sxx * syy).sqrt())
    centre = torch.where(good[:, None], centroid, torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=dtype, device=img.device))
    L00 = sxx.sqrt()
    L10 = sxy / L00
    L11 = (syy - L10 * L10).clamp_min(0.0025).sqrt()
    det = (sxx * syy - sxy * sxy).clamp_min(1e-6)
    amp = torch.where(good, total / (2 * math.pi * det.sqrt()), peak.clamp_min(0)) / expo
    cols = [centre[:, 0], centre[:, 1], L00.log(), L10, L11.log(), amp]
    if fit_background:
        cols.append(bg)
    return torch.stack(cols, -1)
