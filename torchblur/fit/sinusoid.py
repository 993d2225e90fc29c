"""Batched sinusoid fitting: :func:`fit_sinusoid` (checks once, robust passes, flags) and one pass
of the fit in named steps (:func:`_fit_core`); its pieces are :mod:`~torchblur.fit.problem`,
:mod:`~torchblur.fit.sine_model`, :mod:`~torchblur.fit.results`, :mod:`~torchblur.fit.robust`.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_tensor, check_bool, check_choice, check_finite,
                              check_real_scalar, check_type, flat_noise_and_mask)
from torchblur.losses import (LOSSES, covariance_factor, fisher_covariance, image_loss, irls_weights, loss_weight,
                              residual_weights, singular_covariance)
from torchblur.optim import LMResult, levenberg_marquardt
from torchblur.fit.inputs import (check_count, check_data, flat_count, flat_direction, flat_omega, flat_psf,
                                  flat_window)
from torchblur.fit.problem import SineProblem, crop_to_reach, sine_problem, starting_points
from torchblur.fit.results import SinusoidFit, put_items
from torchblur.fit.robust import impulses, inpaint, plane_fit, plane_image, robust_scale
from torchblur.fit.sine_model import ParamLayout, SineModel, sine_model
from torchblur.render.alias import alias_phase as _alias_phase
from torchblur.render.alias import MIN_SEPARATION, alias_separation, canonical_sines, wrap_phase
from torchblur.render.blur import RenderSettings, panel_count, render_blur
from torchblur.render.camera import CameraNoise
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

from torchblur.fit.status import (DARK, MASKED, NO_MOTION, NO_PIXELS, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED,
                                  flag_branch_undecided, flag_poor_fit, item_status)
from torchblur.fit.status import STATUS  # noqa: F401  (identify.sweep imports it from here: another session's area)

__all__ = ["SinusoidFit", "fit_sinusoid"]

OPTIMIZERS = ("lm", "adam", "lbfgs")
AXES = ("x", "y", "xy")
OUTLIERS = ("none", "reject")


def _validate(images, psf, window, axes, optimizer, loss):
    """Check :func:`fit_sinusoid`'s data arguments (:func:`~torchblur.fit.inputs.check_data`), ``axes``
    (a name), ``optimizer`` and ``loss`` -> ``(images, psf, window)`` in one floating dtype."""
    images, psf, window = check_data(images, psf, window)
    if isinstance(axes, str):
        check_choice(axes, "axes", AXES)
    check_choice(optimizer, "optimizer", OPTIMIZERS)
    check_choice(loss, "loss", LOSSES)
    if optimizer == "lm" and loss == "linf":
        raise ParameterError("loss: 'linf' is not a sum of squares, so optimizer='lm' cannot fit it; use optimizer='adam' or 'lbfgs' "
                             "with it (the pairs that work: lm with l2, l1, poisson; adam and lbfgs with every loss)")
    return images, psf, window


@dataclass(frozen=True)
class _FitOptions:
    """The settings of one pass of :func:`fit_sinusoid` (checked there; see its arguments)."""

    optimizer: str = "lm"
    loss: str = "l2"
    fit_scale: bool = False
    fit_background: bool = False
    fit_center: bool = False
    normalize: bool = False
    max_iter: int | None = None
    tol: float = 1e-9
    render_settings: RenderSettings | None = None
    shift: float = 0.0  # poisson's read-noise shift (electrons^2 = counts), CameraNoise.poisson_shift_e


@dataclass(kw_only=True)
class _Solution(LMResult):
    """The chosen solution of each of ``N`` items (the :class:`LMResult` fields, ``theta``
    canonical: amplitudes >= 0, phases wrapped), and its alias branch: ``flipped [N, n_axes]``
    (the optimiser ended at ``-M``: the Jacobian's amplitude columns change sign); ``alias [N, P]``
    and its cost ``alias_cost [N]``.
    """

    flipped: torch.Tensor
    alias: torch.Tensor | None = None
    alias_cost: torch.Tensor | None = None


def _fit_core(data, psf, window: ExposureWindow, omega, direction, *, labels, options: _FitOptions, noise_std=None,
              use=None) -> SinusoidFit:
    """One pass of :func:`fit_sinusoid` on flat inputs it has checked (no robust options, no flags).

    Args:
        data: ``[N, E, H, W]``; psf: ``[N]``; window: ``[N, E]``; omega: ``[N]`` rad/s.
        direction: ``[N, n_axes, 2]`` unit image directions of the fitted axes, named ``labels``.
        options: the fit's settings. noise_std: None, ``[N]`` or ``[N, E, H, W]``.
        use: None or bool ``[N, E, H, W]`` (False excludes a pixel).

    Steps: the problem (weights, levels, degenerate items) -> the starts -> the crop -> the model
    -> optimise every candidate and keep the best, resolving the alias -> the uncertainty ->
    the result (flat batch ``[N]``).
    """
    o = options
    layout = ParamLayout(tuple(labels), o.fit_scale, o.fit_background, o.fit_center)
    problem = sine_problem(data, psf, window, omega, direction, noise_std=noise_std, use=use)
    theta0, amp0 = starting_points(problem, layout)
    K = amp0.shape[1]
    if o.loss == "l2" and not o.normalize and not o.fit_background:
        problem = crop_to_reach(problem, amp0.amax(1), fit_center=o.fit_center)
        if o.fit_center and problem.origin != (0, 0):
            theta0 = theta0.clone()
            theta0[:, layout.center:layout.center + 2] -= torch.tensor(problem.origin, dtype=data.dtype, device=data.device)
    p = problem
    H, W = p.data.shape[-2:]
    model = sine_model(layout, p.psf, p.start, p.duration, p.omega, p.direction, H, W, amplitude_bound=amp0.amax(1) * 1.2 + 0.5,
                       settings=o.render_settings, normalize=o.normalize, region=p.region)
    target = p.data
    if o.normalize:
        target = p.data / p.data.square().sum((-1, -2), keepdim=True).sqrt().clamp_min(1e-30)
    target = target.reshape(target.shape[0], -1)
    weight = loss_weight(o.loss, p.weight.reshape(target.shape))  # the loss's own weights [N, R] from 1 / sigma^2
    # The optimiser's final J^T W J and model are the Fisher information's (l2 and Poisson).
    reuse = model.analytic and o.optimizer == "lm" and o.loss in ("l2", "poisson") and bool(p.live.any())
    sol = _best_candidates(_refine_candidates(model, p, theta0, K, target, weight, o, reuse), layout, K)
    _resolve_alias(model, p, layout, sol, target, weight, o, reuse)
    cov, singular, sigma_used, fitted, chi2 = _uncertainty(model, p, sol, target, o, reuse)
    status = _item_status(model, p, sol, fitted, singular)
    res = _result(model, p, sol, status, cov, sigma_used, K)
    res.reduced_chi2 = torch.where(torch.isnan(res.cost), res.cost, chi2)  # the chi2 for now; per degree of freedom in _finish
    return res


def _refine_candidates(model: SineModel, problem: SineProblem, theta0, K: int, target, weight, o: _FitOptions, reuse: bool) -> dict:
    """Optimise the ``K`` candidate starts ``theta0 [N * K, P]`` of every live item (candidate
    row ``r`` is item ``r // K``) against ``target [N, R]`` with the loss's pixel weights
    ``weight [N, R]``: ``theta``, ``cost`` (inf where not fitted), ``converged``,
    ``n_iter`` ``[N * K]``, and with ``reuse`` the final ``jtj [N * K, P, P]`` and ``model [N * K, R]``."""
    N, P = problem.data.shape[0], theta0.shape[-1]
    dtype, device = theta0.dtype, theta0.device
    R = target.shape[-1]
    item = torch.div(torch.arange(N * K, device=device), K, rounding_mode="floor")
    live_idx = torch.arange(N * K, device=device)[problem.live.repeat_interleave(K)]
    out = dict(theta=theta0.clone(), cost=torch.full((N * K,), float("inf"), dtype=dtype, device=device),
               converged=torch.zeros(N * K, dtype=torch.bool, device=device), n_iter=torch.zeros(N * K, dtype=torch.long, device=device))
    if not live_idx.numel():
        return out
    target_k = target[:, None].expand(N, K, R).reshape(N * K, R)[live_idx]
    weight_k = weight.reshape(N, 1, R).expand(N, K, R).reshape(N * K, R)[live_idx]
    res = _optimise(model, item[live_idx], theta0[live_idx], target_k, weight_k, o)
    for name in ("theta", "cost", "converged", "n_iter"):
        out[name][live_idx] = getattr(res, name)
    if reuse:
        out["jtj"] = torch.eye(P, dtype=dtype, device=device).repeat(N * K, 1, 1)
        out["model"] = torch.zeros(N * K, R, dtype=dtype, device=device)
        out["jtj"][live_idx], out["model"][live_idx] = res.jtj, res.model
    return out


def _best_candidates(fits: dict, layout: ParamLayout, K: int) -> _Solution:
    """The candidate of least cost of each item, from :func:`_refine_candidates`' output."""
    P = layout.size
    N = fits["theta"].shape[0] // K
    th = fits["theta"].reshape(N, K, P)
    best = torch.nan_to_num(fits["cost"].reshape(N, K), nan=float("inf")).argmin(1)
    ar = torch.arange(N, device=best.device)

    def pick(name, tail=()):
        return fits[name].reshape((N, K) + tail)[ar, best] if name in fits else None

    return _Solution(theta=canonical_sines(th, layout.n_axes)[ar, best], cost=pick("cost"), converged=pick("converged"), n_iter=pick("n_iter"),
                     flipped=(th[..., :layout.n_axes] < 0)[ar, best], jtj=pick("jtj", (P, P)), model=pick("model", (-1,)))


def _resolve_alias(model: SineModel, problem: SineProblem, layout: ParamLayout, sol: _Solution, target, weight, o: _FitOptions,
                   reuse: bool) -> None:
    """Set ``sol.alias`` (the other branch of the first exposure) and its cost over every
    exposure; with two or more exposures, where the alias fits better than the consensus
    start, refit from it (a safety net) and keep the better; with one, move a fit off the
    branches' crossing (:func:`_leave_crossing`). Updates ``sol`` in place."""
    N = sol.theta.shape[0]
    ar = torch.arange(N, device=sol.theta.device)
    first = ExposureWindow(problem.start[:, :1], problem.duration[:, :1])
    n = layout.n_axes

    def alias_of(t, items):
        ta = t.clone()
        ta[:, n:2 * n] = _alias_phase(t[:, n:2 * n], problem.omega[items][:, None], first[items])
        return ta

    def alias_cost(items):
        with torch.no_grad():
            return image_loss(model.image(sol.alias[items], items), target[items], loss=o.loss, weight=weight[items], shift=o.shift)

    sol.alias = alias_of(sol.theta, ar)
    sol.alias_cost = alias_cost(ar)
    single = alias_separation(problem.omega, ExposureWindow(problem.start, problem.duration)) < MIN_SEPARATION  # [N]
    _leave_crossing(model, problem, layout, sol, target, weight, o, reuse, alias_of, alias_cost, single)
    if problem.start.shape[-1] < 2:
        return
    r = ar[problem.live & ~single & (sol.alias_cost < sol.cost)]
    _keep_better(model, layout, sol, r, sol.alias[r], target, weight, o, reuse, alias_of, alias_cost)


#: a single-exposure fit whose every axis' phase lies within this of the branches' crossing (rad)
#: is refitted from starts this far off it on either side (:func:`_leave_crossing`)
CROSSING_PROBE_RAD = 0.2


def _leave_crossing(model: SineModel, problem: SineProblem, layout: ParamLayout, sol: _Solution, target, weight, o: _FitOptions,
                    reuse: bool, alias_of, alias_cost, single) -> None:
    """Items ``single`` (bool ``[N]``: exposures that do not resolve the alias): an item whose phases all lie within :data:`CROSSING_PROBE_RAD` of the
    branches' crossing ``chi`` (phase = its alias) may sit on the stationary point the image's
    symmetry about ``chi`` makes (the image's phase derivative vanishes there, so Gauss-Newton
    stays put; its magnitude is then wrong with a small std). Refit it from ``chi -+
    CROSSING_PROBE_RAD`` per axis (every sign pattern up to the joint reflection) and keep a lower cost."""
    n = layout.n_axes
    ph, al = sol.theta[:, n:2 * n], sol.alias[:, n:2 * n]
    half = wrap_phase(ph - al) / 2  # phi - chi (the nearer crossing)
    near = problem.live & single & (half.abs() < CROSSING_PROBE_RAD).all(1)
    r = torch.nonzero(near).reshape(-1)
    if not r.numel():
        return
    chi = ph[r] - half[r]
    slow = replace(o, max_iter=4 * (o.max_iter or 60))  # a flat double well near the crossing: LM takes more steps
    for k in range(2 ** (n - 1)):
        signs = torch.tensor([-1.0] + [1.0 if (k >> (a - 1)) & 1 else -1.0 for a in range(1, n)], dtype=ph.dtype, device=ph.device)
        start = sol.theta[r].clone()
        start[:, n:2 * n] = wrap_phase(chi + signs * CROSSING_PROBE_RAD)
        _keep_better(model, layout, sol, r, start, target, weight, slow, reuse, alias_of, alias_cost)


def _keep_better(model: SineModel, layout: ParamLayout, sol: _Solution, r, start, target, weight, o: _FitOptions, reuse: bool,
                 alias_of, alias_cost) -> None:
    """Refit items ``r`` from ``start [len(r), P]``; where the cost is lower, that solution (and
    its alias) replaces ``sol``'s, in place."""
    if not r.numel():
        return
    n = layout.n_axes
    res = _optimise(model, r, start, target[r], weight[r], o)
    better = res.cost < sol.cost[r]
    rb = r[better]
    if not rb.numel():  # the solution held
        return
    sol.theta[rb] = canonical_sines(res.theta[better], layout.n_axes)
    sol.flipped[rb] = res.theta[better][:, :n] < 0
    if reuse:
        sol.jtj[rb], sol.model[rb] = res.jtj[better], res.model[better]
    sol.cost[rb] = res.cost[better]
    sol.converged[rb] = res.converged[better]
    sol.n_iter[rb] += res.n_iter[better]
    sol.alias[rb] = alias_of(sol.theta[rb], rb)
    sol.alias_cost[rb] = alias_cost(rb)


def _uncertainty(model: SineModel, problem: SineProblem, sol: _Solution, target, o: _FitOptions, reuse: bool):
    """The covariance of the estimates at the solution: ``(covariance [N, P, P], singular [N], noise std used
    [N], model [N, R], chi2 [N])``: the Fisher information of the loss's noise model (``sigma`` the given noise,
    else one std per item from the residuals, cut-off pixels included; poisson ``sigma^2 = model + shift``),
    inverted, times :func:`~torchblur.losses.covariance_factor` (the table: docs/reliability.md, "The camera's
    noise and the losses"). ``chi2``: ``sum r^2 / sigma^2`` with the given noise, the fit-quality check of
    every loss."""
    p, loss = problem, o.loss
    N, P = sol.theta.shape
    dtype, device = sol.theta.dtype, sol.theta.device
    w = p.weight.reshape(N, -1)
    if reuse:
        fitted = sol.model
        sign = torch.ones(N, P, dtype=dtype, device=device)
        sign[:, :model.layout.n_axes] = torch.where(sol.flipped, -1.0, 1.0)
        F = sol.jtj * sign[:, :, None] * sign[:, None, :]
    else:
        fitted, J = model.image_and_jacobian(sol.theta, torch.arange(N, device=device))
    resid = target - fitted
    ones = torch.ones(N, dtype=dtype, device=device)
    if loss == "poisson":
        fisher_w = irls_weights(fitted, target, loss="poisson", weight=(w > 0).to(dtype), shift=o.shift)
        sigma_used, scale2 = torch.full((N,), float("nan"), dtype=dtype, device=device), ones
    elif p.noise_given:
        fisher_w, sigma_used, scale2 = w, p.noise_level, ones
    else:
        fisher_w, sig2 = residual_weights(resid, w, P, cut_sq=p.cut_sq, cut_n=p.cut_n)
        sigma_used = sig2.sqrt()
        scale2 = 1 / sig2.clamp_min(torch.finfo(dtype).tiny)
    cov, info = torch.linalg.inv_ex(F * scale2[:, None, None]) if reuse else fisher_covariance(J, fisher_w)
    if loss != "linf":
        cov = cov * covariance_factor(loss)
    singular = singular_covariance(cov, info)
    chi2 = (resid * resid * w).sum(-1) + p.cut_cost
    return cov, singular, sigma_used, fitted, chi2


def _item_status(model: SineModel, problem: SineProblem, sol: _Solution, fitted, singular) -> torch.Tensor:
    """Status ``[N]`` (see :data:`STATUS`): not converged, singular, most of the spot's light
    outside the frame (Gaussian PSF: the fitted model's light against the spot's total), out of
    frame, dark; later codes win."""
    p, L = problem, model.layout
    N = sol.theta.shape[0]
    dtype, device = sol.theta.dtype, sol.theta.device
    out_of_frame = p.outside
    if isinstance(p.psf, GaussianPSF):
        with torch.no_grad():
            scale = sol.theta[:, L.scale] if L.fit_scale else torch.ones(N, dtype=dtype, device=device)
            inside = (fitted - (sol.theta[:, L.background, None] if L.fit_background else 0.0)).sum(-1)
            if model.normalize:
                inside = torch.full_like(inside, float("inf"))
            total = scale * (p.psf.total_light()[:, None] * p.duration).sum(-1)
            out_of_frame = out_of_frame | (inside < 0.5 * total)
    return item_status(sol.converged, singular, p.dark, out_of_frame=out_of_frame)


def _result(model: SineModel, problem: SineProblem, sol: _Solution, status, cov, sigma_used, K: int) -> SinusoidFit:
    """The :class:`SinusoidFit` of a pass, batch ``[N]``: NaN estimates for dark and
    out-of-frame items, the rest position back in full-frame coordinates."""
    p, L = problem, model.layout
    N, P = sol.theta.shape
    dtype, device = sol.theta.dtype, sol.theta.device
    n = L.n_axes
    bad = (status == DARK) | p.outside
    nan = torch.tensor(float("nan"), dtype=dtype, device=device)
    std = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    def per_axis(v):
        v = torch.where(bad[:, None], nan, v)
        return v if n == 2 else v[:, 0]

    res = SinusoidFit(
        amplitude=per_axis(L.amplitudes(sol.theta)),
        phase=per_axis(L.phases(sol.theta)),
        amplitude_std=per_axis(L.amplitudes(std)),
        phase_std=per_axis(L.phases(std)),
        alias_phase=per_axis(L.phases(sol.alias)),
        alias_cost=torch.where(bad, nan, sol.alias_cost + p.cut_cost),
        cost=torch.where(bad, nan, sol.cost + p.cut_cost),
        converged=status == 0,
        status=status,
        covariance=torch.where(bad[:, None, None], nan, cov),
        param_names=L.names,
        noise_std=sigma_used,
        n_iter=sol.n_iter,
    )
    if L.fit_scale:
        res.scale = sol.theta[:, L.scale]
    if L.fit_background:
        res.background = sol.theta[:, L.background]
    if L.fit_center:
        res.center = sol.theta[:, L.center:L.center + 2] + torch.tensor(p.origin, dtype=dtype, device=device)
    res.extras["nodes"] = model.settings.nodes
    if model.analytic:
        res.extras["nodes_per_frame"] = model.panels * model.nodes_per_panel
    res.extras["candidates"] = K
    return res


GN_TOL = 1e-2  # squared Mahalanobis length (in std^2) of a final Gauss-Newton step taken unevaluated
# l1: its cost is piecewise linear, so near the optimum its steps stall at a few 0.01 std^2 (the
# signs of the residuals change in jumps); a final step under 0.05 std^2 adds at most 3% to the
# variance of its estimate (pi / 2 std^2). Likewise an accepted step that lowers the cost by
# less than 0.02 (what a step of 0.2 std from the optimum gains: the expected cost rises by
# sqrt(2 / pi) s^2 / 2 at s std), i.e. less than 0.025 / R of a cost of about 0.8 per pixel (R pixels),
# ends the fit.
GN_TOL_L1 = 5e-2


def _optimise(model: SineModel, items, theta0, data, weight, o: _FitOptions):
    """Run the chosen optimiser on rows ``theta0 [n, P]`` of items ``items [n]`` against
    ``data [n, R]`` with pixel weights ``weight [n, R]``: Levenberg-Marquardt on the model's
    image and Jacobian (on the analytic path the Jacobian is cheap and comes with every
    trial point), Adam or L-BFGS on the rendered model by autograd."""
    loss, max_iter = o.loss, o.max_iter

    def model_fn(theta, i):
        return model.rendered(theta, items[i])

    if o.optimizer == "lm":
        it = max_iter or 60
        jacobian_fn = ((lambda theta, i: model.image_and_jacobian(theta, items[i]))  # noqa: E731
                       if model.analytic or model.kernel_jacobian else None)
        # Converged once the next Gauss-Newton step is below 0.1 standard deviation (that
        # step is then taken unevaluated; the result is within ~0.01 std of the optimum).
        tol = max(o.tol, 0.025 / data.shape[-1]) if loss == "l1" else o.tol
        return levenberg_marquardt(model_fn, theta0, data, loss=loss, weight=weight, max_iter=it, tol=tol,
                                   jacobian_fn=jacobian_fn, gn_tol={"linf": None, "l1": GN_TOL_L1}.get(loss, GN_TOL), shift=o.shift)
    n = theta0.shape[0]
    idx = torch.arange(n, device=theta0.device)
    scale = theta0.detach().abs().clamp_min(1.0)
    u = torch.zeros_like(theta0, requires_grad=True)

    def cost_at(v):  # the loss [n] at theta0 + v * scale
        return image_loss(model_fn(theta0 + v * scale, idx), data, loss=loss, weight=weight, shift=o.shift)

    if o.optimizer == "adam":
        it = max_iter or 400
        opt = torch.optim.Adam([u], lr=0.02)
        history = []
        for _ in range(it):
            opt.zero_grad()
            c = cost_at(u)
            c.sum().backward()
            opt.step()
            history.append(c.detach())
    else:
        it = max_iter or 100
        opt = torch.optim.LBFGS([u], lr=1.0, max_iter=it, line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                                tolerance_change=1e-14)

        def closure():
            opt.zero_grad()
            c = cost_at(u).sum()
            c.backward()
            return c

        opt.step(closure)
    with torch.no_grad():
        cost = cost_at(u)
    if o.optimizer == "adam":
        prev = history[-20] if len(history) >= 20 else history[0]
        conv, n_it = (prev - cost).abs() <= 1e-4 * cost.abs().clamp_min(1e-30), it
    else:
        n_it = int(opt.state[opt._params[0]].get("n_iter", it))
        conv = torch.full((n,), n_it < it, dtype=torch.bool, device=theta0.device)
    n_iter = torch.full((n,), n_it, dtype=torch.long, device=theta0.device)
    return LMResult((theta0 + u * scale).detach(), cost, conv, n_iter)


# --------------------------------------------------------------------------- public entry: checks, masks, robust pass, flags


@dataclass(frozen=True, eq=False)
class _FlatInputs:
    """:func:`fit_sinusoid`'s inputs, checked and flattened to ``N`` items.

    ``data [N, E, H, W]``, ``psf [N]``, ``window [N, E]``, ``omega [N]``; ``axis_dirs [N, n_axes, 2]``
    the fitted axes' unit image directions, named ``labels``; ``direction [N, 2]`` the one
    direction of a one-axis fit (None: Lissajous, see :func:`_axes_xy`); ``noise`` None, ``[N]``
    or ``[N, E, H, W]``; ``keep [N, E, H, W]`` the pixels neither masked nor saturated;
    ``user_masked``, ``sat_masked [N]`` whether the mask, the saturation level excluded pixels;
    ``shift`` poisson's read-noise shift (:func:`noise_terms`); ``noise_model`` the camera's noise
    model where the weights are to come from the fitted model (``noise`` given, ``noise_std``
    not: :func:`_reweight_by_model`), else None.
    """

    data: torch.Tensor
    psf: GaussianPSF | KernelPSF
    window: ExposureWindow
    omega: torch.Tensor
    axis_dirs: torch.Tensor
    labels: tuple
    direction: torch.Tensor | None
    noise: torch.Tensor | None
    keep: torch.Tensor
    user_masked: torch.Tensor
    sat_masked: torch.Tensor
    shift: float = 0.0
    noise_model: CameraNoise | None = None


def _check_options(*, optimizer, loss, fit_scale, fit_background, fit_center, fit_gradient, normalize, outliers, outlier_sigma,
                   max_iter, tol, render_settings) -> tuple[_FitOptions, float]:
    """Check :func:`fit_sinusoid`'s options (``optimizer`` and ``loss`` are checked by
    ``_validate``): ``(the pass settings without the noise's shift, outlier_sigma)``."""
    for name, v in (("fit_scale", fit_scale), ("fit_background", fit_background), ("fit_center", fit_center), ("fit_gradient", fit_gradient),
                    ("normalize", normalize)):
        check_bool(v, name)
    check_choice(outliers, "outliers", OUTLIERS)
    outlier_sigma = check_real_scalar(outlier_sigma, "outlier_sigma", positive=True)
    if fit_gradient and normalize:
        raise ParameterError("fit_gradient: expected False with normalize=True (the plane is in image units), got True")
    if outliers == "reject" and normalize:
        raise ParameterError("outliers: expected 'none' with normalize=True (the robust pass compares data and model in image units), "
                             "got 'reject'")
    check_count(max_iter, "max_iter", optional=True)
    tol = check_real_scalar(tol, "tol", nonnegative=True)
    if render_settings is not None and not isinstance(render_settings, RenderSettings):
        raise InputTypeError(f"render_settings: expected a RenderSettings or None, got {type(render_settings).__name__}")
    return _FitOptions(optimizer=optimizer, loss=loss, fit_scale=fit_scale, fit_background=fit_background, fit_center=fit_center,
                       normalize=normalize, max_iter=max_iter, tol=tol, render_settings=render_settings), outlier_sigma


def noise_terms(images: torch.Tensor, noise_std, noise: CameraNoise | None):
    """What a fit takes from the camera's noise model ``noise`` (a :class:`~torchblur.render.camera.CameraNoise`
    or None; ``images [..., E, H, W]`` in dark-subtracted electrons): ``(noise_std, shift)``: the caller's
    ``noise_std``, else ``noise.std(images)`` (the first pass's weights: :func:`_reweight_by_model`), else None;
    poisson's read-noise shift ``noise.poisson_shift_e`` (0 without ``noise``: pure counts)."""
    if noise is None:
        return noise_std, 0.0
    check_type(noise, "noise", CameraNoise, "a CameraNoise or None")
    return (noise.std(images) if noise_std is None else noise_std), noise.poisson_shift_e


def _flat_inputs(images, psf, window, omega, axes, noise_std, mask, saturation_level, noise=None) -> _FlatInputs:
    """The checked ``images [..., E, H, W]`` and the rest, flattened (checks ``window``, ``omega``,
    ``axes``, ``noise_std``, ``mask``, ``saturation_level``, ``noise``: :func:`noise_terms`)."""
    noise_model = noise if noise_std is None else None
    noise_std, shift = noise_terms(images, noise_std, noise)
    dtype, device = images.dtype, images.device
    batch = images.shape[:-3]
    E, H, W = images.shape[-3:]
    N = flat_count(images)
    data = images.reshape(N, E, H, W)
    win, omega = flat_window(window, batch, N, E), flat_omega(omega, batch, N, data)
    if isinstance(axes, str):
        eye = torch.eye(2, dtype=dtype, device=device)
        axis_dirs, labels = {"x": eye[:1], "y": eye[1:], "xy": eye}[axes][None].expand(N, len(axes), 2), tuple(axes)
    else:
        axis_dirs, labels = flat_direction(axes, batch, N, data, "axes")[:, None, :], ("u",)
    sig, m = flat_noise_and_mask(noise_std, mask, images)
    keep = torch.ones(N, E, H, W, dtype=torch.bool, device=device)
    user_masked = torch.zeros(N, dtype=torch.bool, device=device)
    if m is not None:
        keep = keep & m
        user_masked = (~m).flatten(1).any(1)
    sat_masked = torch.zeros(N, dtype=torch.bool, device=device)
    if saturation_level is not None:
        lvl = check_finite(as_tensor(saturation_level, "saturation_level", like=data), "saturation_level")
        try:
            lvl = lvl.expand(batch).reshape(N)
        except RuntimeError:
            raise ShapeError(f"saturation_level: expected a number or the images' batch {tuple(batch)}, got {tuple(lvl.shape)}") from None
        sat = data >= lvl[:, None, None, None]
        sat_masked = (sat & keep).flatten(1).any(1)
        keep = keep & ~sat
    return _FlatInputs(data=data, psf=flat_psf(psf, batch, N), window=win, omega=omega, axis_dirs=axis_dirs,
                       labels=labels, direction=None if axes == "xy" else axis_dirs[:, 0], noise=sig, keep=keep,
                       user_masked=user_masked, sat_masked=sat_masked, shift=shift, noise_model=noise_model)


def _fit_items(inp: _FlatInputs, o: _FitOptions, data: torch.Tensor, idx: torch.Tensor, use: torch.Tensor) -> SinusoidFit:
    """One pass of :func:`_fit_core` over items ``idx`` of ``data [N, E, H, W]`` with the pixels
    ``use [n, E, H, W]`` (all items: no copies)."""
    mask = None if bool(use.all()) else use
    if idx.numel() == data.shape[0]:
        return _fit_core(inpaint(data, use), inp.psf, inp.window, inp.omega, inp.axis_dirs, labels=inp.labels, options=o,
                         noise_std=inp.noise, use=mask)
    noise = None if inp.noise is None else inp.noise[idx]
    return _fit_core(inpaint(data[idx], use), inp.psf[idx], inp.window[idx], inp.omega[idx],
                     inp.axis_dirs[idx], labels=inp.labels, options=o, noise_std=noise, use=mask)


def _robust_fit(inp: _FlatInputs, o: _FitOptions, outliers: str, outlier_sigma: float, fit_gradient: bool):
    """The fit with the robust options: ``(inputs, result [N], rejected [N, E, H, W], plane [N, E, 3]
    or None, outlier passes)``. Impulses are rejected before the first pass (Gaussian PSF); with
    ``fit_gradient`` a stray-light plane is fitted to the border, then to the pixels the spot
    does not reach, and the spot refitted; with a noise model and no ``noise_std``, refitted
    with the model's weights (:func:`_reweight_by_model`; the returned inputs carry them); with
    ``outliers="reject"``, up to 3 passes."""
    data, keep = inp.data, inp.keep
    N, E, H, W = data.shape
    everything = torch.arange(N, device=data.device)
    rejected = torch.zeros_like(keep)
    if outliers == "reject" and isinstance(inp.psf, GaussianPSF):
        if inp.noise is not None:
            noise0 = inp.noise if inp.noise.dim() == 4 else inp.noise[:, None, None, None]
        else:
            noise0 = robust_scale(data, keep)
        rejected = impulses(data, inp.psf, noise0, outlier_sigma) & keep
    plane = None
    if fit_gradient:
        border = torch.ones(H, W, dtype=torch.bool, device=data.device)
        border[2:-2, 2:-2] = False
        plane = plane_fit(data, keep & ~rejected & border)
        data = data - plane_image(plane, H, W)
    res = _fit_items(inp, o, data, everything, keep & ~rejected)
    if fit_gradient:
        live = everything[torch.isfinite(res.cost)]
        if live.numel():
            spot = _model_images(res, live, inp, o, with_background=False)
            far = spot < 1e-4 * spot.amax((-1, -2), keepdim=True)
            plane[live] = plane_fit(inp.data[live], keep[live] & ~rejected[live] & far)
            data = inp.data - plane_image(plane, H, W)
            put_items(res, live, _fit_items(inp, o, data, live, keep[live] & ~rejected[live]))
    if inp.noise_model is not None and o.loss != "poisson":
        inp = _reweight_by_model(inp, o, data, res, keep & ~rejected)
    passes = _outlier_passes(inp, o, data, res, rejected, outlier_sigma) if outliers == "reject" else 0
    return inp, res, rejected, plane, passes


def _reweight_by_model(inp: _FlatInputs, o: _FitOptions, data, res: SinusoidFit, use) -> _FlatInputs:
    """The second pass of a fit weighted by the camera's noise model: every fitted item refitted
    with ``inp.noise_model.std`` of its first-pass model image (with the background: stray light
    is light), and ``inp`` returned with those stds. Why (the first pass's weights correlate with
    the noise and bias the amplitudes low): docs/reliability.md, "The camera's noise and the losses"."""
    live = torch.arange(data.shape[0], device=data.device)[torch.isfinite(res.cost) & (res.status != 3)]
    if live.numel() == 0:
        return inp
    model = _model_images(res, live, inp, o, with_background=o.fit_background)
    sig = inp.noise.clone() if inp.noise.dim() == 4 else inp.noise[:, None, None, None].expand(data.shape).clone()
    sig[live] = inp.noise_model.std(model)
    inp = replace(inp, noise=sig)
    put_items(res, live, _fit_items(inp, o, data, live, use[live]))
    return inp


def _outlier_passes(inp: _FlatInputs, o: _FitOptions, data, res: SinusoidFit, rejected, outlier_sigma: float) -> int:
    """Up to 3 passes: exclude the pixels whose residual exceeds ``outlier_sigma`` noise stds
    and refit the items whose excluded set changed. Updates ``res`` and ``rejected [N, E, H, W]``
    in place; returns the number of passes."""
    everything = torch.arange(data.shape[0], device=data.device)
    sig = inp.noise
    passes = 0
    for passes in range(1, 4):
        idx = everything[torch.isfinite(res.cost) & ((res.status == 0) | (res.status == 2) | (res.status == 4))]
        if idx.numel() == 0:
            break
        model = _model_images(res, idx, inp, o, with_background=o.fit_background)
        r = data[idx] - model
        used = inp.keep[idx]
        scale = sig[idx] if sig is not None and sig.dim() == 4 else (
            sig[idx][:, None, None, None] if sig is not None else robust_scale(r, used))
        new = (r.abs() > outlier_sigma * scale) & used
        changed = (new != rejected[idx]).flatten(1).any(1)
        if not bool(changed.any()):
            break
        ci = idx[changed]
        rejected[ci] = new[changed]
        put_items(res, ci, _fit_items(inp, o, data, ci, inp.keep[ci] & ~rejected[ci]))
    return passes


def _finish(res: SinusoidFit, inp: _FlatInputs, o: _FitOptions, rejected, plane, passes: int, *, batch) -> SinusoidFit:
    """Status :data:`NO_PIXELS` where nothing is left to fit, the :data:`FLAGS`, the pixel
    counts and the plane, set on the flat result ``[N]``; then every field reshaped to ``batch``."""
    N, E, H, W = inp.data.shape
    n_used = (inp.keep & ~rejected).flatten(1).sum(1)
    empty = n_used <= len(res.param_names)
    if bool(empty.any()):
        for name in ("amplitude", "phase", "amplitude_std", "phase_std", "alias_phase", "alias_cost", "cost", "covariance"):
            getattr(res, name)[empty] = float("nan")
        res.status[empty] = NO_PIXELS
        res.converged[empty] = False
    n_out = rejected.flatten(1).sum(1)
    flags = torch.zeros(N, dtype=torch.long, device=inp.data.device)
    flags |= MASKED * inp.user_masked.long()
    flags |= SATURATED_MASKED * inp.sat_masked.long()
    flags |= OUTLIERS_MASKED * (n_out > 0).long()
    with torch.no_grad():
        frac = _light_in_frame(res, inp, o.fit_center)
    flags |= PARTLY_OUT_OF_FRAME * ((frac < 0.999) & (res.status != 3)).long()
    amp_z = res.amplitude / res.amplitude_std
    if inp.direction is not None:
        flags |= NO_MOTION * ((amp_z < 3) & ~torch.isnan(res.amplitude)).long()
    else:
        flags |= NO_MOTION * ((amp_z < 3).any(-1) & ~torch.isnan(res.amplitude).any(-1)).long()
    res.flags = flags
    res.n_masked = E * H * W - n_used
    res.n_outliers = n_out
    res.extras["outlier_passes"] = passes
    # With the noise given, the l2 cost is a chi-square: per degree of freedom about 1 when the
    # model explains the images, and the stds mean what they say only then.
    dof = (n_used - len(res.param_names)).clamp_min(1).to(res.cost.dtype)
    chi2 = res.cost if o.loss == "l2" else torch.where(torch.isnan(res.cost), res.cost, res.reduced_chi2)
    res.reduced_chi2 = chi2 / dof if (inp.noise is not None and o.loss != "linf") else torch.full_like(res.cost, float("nan"))
    res.flags = flag_poor_fit(res.flags, res.reduced_chi2)
    # the alias's cost less the fit's is a chi2 difference for l2 and poisson (a deviance) with the noise given
    # (an item with no significant motion is NO_MOTION already: its phase means nothing on either branch)
    resolving = (alias_separation(inp.omega, inp.window) >= MIN_SEPARATION) & (o.loss in ("l2", "poisson")) & ((res.flags & NO_MOTION) == 0)
    res.flags = flag_branch_undecided(res.flags, torch.where(torch.isnan(res.reduced_chi2), res.reduced_chi2, res.alias_cost - res.cost),
                                      resolving)
    res.background_plane = plane
    for f in fields(SinusoidFit):
        v = getattr(res, f.name)
        if isinstance(v, torch.Tensor):
            setattr(res, f.name, v.reshape(batch + v.shape[1:]))
    return res


def _axes_xy(amplitude: torch.Tensor, phase: torch.Tensor, direction: torch.Tensor | None):
    """Per-axis ``(amplitude [n, 2], phase [n, 2])`` of a fit: ``direction [n, 2]`` the unit
    image direction of a one-axis fit, None for a Lissajous (``"xy"``) fit."""
    if direction is None:
        return amplitude, phase
    return amplitude[:, None] * direction, torch.stack([phase, phase], -1)


def _fitted_psf(res: SinusoidFit, psf, idx, fit_scale: bool, fit_center: bool):
    """The PSF of items ``idx`` with the fitted scale and rest position, batch ``[n, 1]``."""
    scale = res.scale[idx] if fit_scale else None
    if isinstance(psf, GaussianPSF):
        c = res.center[idx] if fit_center else psf.center[idx]
        a = psf.amplitude[idx] * (scale if scale is not None else 1.0)
        return GaussianPSF(c[:, None], psf.cov[idx][:, None], a[:, None])
    k = psf.kernel[idx]
    return KernelPSF((k * scale[:, None, None] if scale is not None else k)[:, None])


def _model_images(res: SinusoidFit, idx, inp: _FlatInputs, o: _FitOptions, *, with_background: bool) -> torch.Tensor:
    """The fitted model ``[n, E, H, W]`` of items ``idx`` of a flat result in the full frame (with
    the fitted background where ``with_background``), each rendered with the quadrature its own
    motion needs: Gaussian items grouped by their panel count
    and by whether the PSF is tilted, measured kernels one by one (the FFT grid follows the
    batch's largest motion), so an item's image, and the weights made from it, do not depend on
    which other items share its batch (a chunk of a sweep gives the values the whole sweep gives)."""
    H, W = inp.data.shape[-2:]
    amp, ph = _axes_xy(res.amplitude[idx], res.phase[idx], None if inp.direction is None else inp.direction[idx])
    traj = Sinusoid(amp[:, None, :], ph[:, None, :], inp.omega[idx][:, None])
    psf = _fitted_psf(res, inp.psf, idx, o.fit_scale, o.fit_center)
    win = inp.window[idx]
    settings = o.render_settings or RenderSettings()
    panels = panel_count(traj.path_length(win), psf.sigma_min(), settings, traj.phase_span(win)).amax(-1).long()  # [n]
    if isinstance(psf, GaussianPSF):
        key = 2 * panels + (psf.cov[..., 0, 1] != 0).flatten(1).any(1).long()
    else:  # a kernel's FFT grid is padded by the batch's largest displacement: each item alone
        key = torch.arange(len(idx), device=panels.device)
    out = torch.empty((len(idx),) + tuple(inp.data.shape[1:]), dtype=inp.data.dtype, device=inp.data.device)
    with torch.no_grad():
        for k in torch.unique(key).tolist():
            sel = (key == k).nonzero().flatten()
            n_panels = k // 2 if isinstance(psf, GaussianPSF) else int(panels[sel[0]])
            rule = replace(settings, nodes=int(n_panels) * settings.nodes_per_panel)
            sub = Sinusoid(amp[sel][:, None, :], ph[sel][:, None, :], inp.omega[idx][sel][:, None])
            out[sel] = render_blur(sub, psf[sel], ExposureWindow(win.start[sel], win.duration[sel]),
                                   height=H, width=W, settings=rule)
    if with_background:
        out = out + res.background[idx][:, None, None, None]
    return out


def _light_in_frame(res: SinusoidFit, inp: _FlatInputs, fit_center: bool, n_t: int = 64) -> torch.Tensor:
    """Fraction ``[N]`` of the fitted spot's light that falls inside the frame
    ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (worst exposure), from the Gaussian marginals of the
    PSF along the fitted path (NaN where the fit has no estimate)."""
    H, W = inp.data.shape[-2:]
    psf, win, om = inp.psf, inp.window, inp.omega
    amp, ph = _axes_xy(res.amplitude, res.phase, inp.direction)
    centre, cov = psf.moments()
    if fit_center and res.center is not None:
        centre = res.center
    dtype, device = amp.dtype, amp.device
    tau = (torch.arange(n_t, dtype=dtype, device=device) + 0.5) / n_t
    t = win.start[..., None] + win.duration[..., None] * tau  # [N, E, T]
    pos = centre[:, None, None, :] + amp[:, None, None, :] * torch.sin(om[:, None, None, None] * t[..., None] + ph[:, None, None, :])
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(1e-12).sqrt()[:, None, None, :]
    hi = torch.tensor([W - 0.5, H - 0.5], dtype=dtype, device=device)
    inside = torch.special.ndtr((hi - pos) / sd) - torch.special.ndtr((-0.5 - pos) / sd)  # [N, E, T, 2]
    return inside.prod(-1).mean(-1).amin(-1)


def fit_sinusoid(
    images, psf, window: ExposureWindow, omega, *, axes="x", optimizer: str = "lm", loss: str = "l2", noise_std=None,
    noise: CameraNoise | None = None, mask=None, saturation_level=None, outliers: str = "none", outlier_sigma: float = 5.0,
    fit_scale: bool = False, fit_background: bool = False, fit_center: bool = False, fit_gradient: bool = False,
    normalize: bool = False, max_iter: int | None = None, tol: float = 1e-9, render_settings: RenderSettings | None = None,
) -> SinusoidFit:
    """Fit ``y(t) = M sin(omega t + phi)`` to blurred images of a moving spot.

    Args:
        images: ``[..., E, H, W]``: E exposures of the same motion (E = 1, 2 or more), dark
            level subtracted, in the units of the PSF times seconds; a real tensor, floating
            or integer (a camera's counts; subtract the dark level first, e.g.
            ``preprocess.subtract_dark``); bool and complex images are refused.
        psf: ``GaussianPSF`` or ``KernelPSF``, batch ``[...]`` (shared by the E exposures).
        window: exposure windows, batch broadcastable to ``[..., E]``.
        omega: rad/s, ``[...]``.
        axes: ``"x"`` or ``"y"``: a motion along that axis (amplitude, phase ``[...]``);
            ``"xy"``: a 2-D Lissajous motion (amplitude, phase ``[..., 2]``); or an image
            direction ``(x, y)`` (a pair, or a tensor ``[2]`` or ``[..., 2]``, normalised): a
            motion along it, e.g. an actuator axis rotated in the camera's image
            (:func:`torchblur.image.tracking.calibrate_axes` measures it); the amplitude is then
            along that direction (``[...]``) and the parameters are named ``amplitude_u``,
            ``phase_u``.
        optimizer: ``"lm"`` (batched Levenberg-Marquardt, default), ``"adam"``, ``"lbfgs"``.
        loss: ``"l2"`` (default), ``"l1"``, ``"linf"`` (adam/lbfgs only), ``"poisson"``: see :mod:`torchblur.losses`.
        noise_std: pixel noise std: a number, ``[...]`` or ``[..., E, H, W]``; None: from ``noise`` (a refit
            weighted by ``noise.std`` of a first fit's model: unbiased, :func:`_reweight_by_model`), else the
            l2 fit is unweighted and the noise is estimated from the residuals.
        noise: the camera's :class:`~torchblur.render.camera.CameraNoise` (images in electrons), or None.
        mask: bool ``[..., E, H, W]``, False excludes a pixel (hot pixels from
            ``preprocess.dark_frame(...).hot_pixels``, saturated pixels from
            ``SaturationCurve.mask`` or ``CameraModel.saturated_mask`` of the raw frames).
            Sets :data:`MASKED`.
        saturation_level: pixels of ``images`` at or above it are excluded (the clipping level
            in the units of ``images``, i.e. less the dark level): a number or ``[...]``.
            Sets :data:`SATURATED_MASKED`. None (default): nothing is clipped.
        outliers: ``"none"`` (default) or ``"reject"``: pixels no blurred spot can produce, and after the
            fit those whose residual exceeds ``outlier_sigma`` noise stds, are excluded and the item refitted
            (up to 3 passes; docs/reliability.md, "Robust fitting"). Sets :data:`OUTLIERS_MASKED`, ``n_outliers``.
        outlier_sigma: the rejection threshold in standard deviations (> 0, default 5: 6e-7 of clean pixels).
        fit_scale, fit_background, fit_center: fit an intensity scale, a constant background
            (stray light), the rest position jointly (nuisance parameters).
        fit_gradient: remove a stray-light plane per exposure, fitted to the frame's 2-px border, then to
            every pixel where the fitted spot is below 1e-4 of its peak (the spot refitted after each);
            reported in ``background_plane``, its uncertainty not added to the estimates'.
        normalize: the paper's eq. 8: compare images divided by their Frobenius norms (an
            option; it weights the exposures unequally and loses precision).
        max_iter: optimiser iterations, an int >= 1 (default 60 for lm, 400 for adam, 100 for lbfgs).
        tol: relative cost decrease that counts as converged (lm), >= 0.
        render_settings: renderer settings; the node count is fixed for the whole fit
            (default: panels of 3.5 PSF widths, model error < 1e-6 of the peak).

    dtype: the fit computes in, and returns, :func:`fit_dtype` (float16/bfloat16 and integer images are promoted,
    float32 images with a float64 PSF or window give a float64 fit); ``omega``, ``noise_std`` and ``saturation_level`` too.

    Returns:
        :class:`SinusoidFit`. Degenerate items are flagged, never raised, and do not change the other
        items: ``status`` 1 (no signal, :func:`torchblur.fit.problem.dark_items`), 3 (spot mostly outside
        the frame), 5 (no usable pixel) give NaN estimates; ``flags``: docs/reliability.md, "Degenerate
        frames are flagged per item, never raised".

    Example:
        >>> fit = fit_sinusoid(images, psf, window, omega, mask=~dark.hot_pixels, outliers="reject")
        >>> bad = (fit.flags & PARTLY_OUT_OF_FRAME) != 0
    """
    images, psf, window = _validate(images, psf, window, axes, optimizer, loss)
    options, outlier_sigma = _check_options(optimizer=optimizer, loss=loss, fit_scale=fit_scale, fit_background=fit_background,
                                            fit_center=fit_center, fit_gradient=fit_gradient, normalize=normalize, outliers=outliers,
                                            outlier_sigma=outlier_sigma, max_iter=max_iter, tol=tol, render_settings=render_settings)
    inp = _flat_inputs(images, psf, window, omega, axes, noise_std, mask, saturation_level, noise)
    options = replace(options, shift=inp.shift)
    inp, res, rejected, plane, passes = _robust_fit(inp, options, outliers, outlier_sigma, fit_gradient)
    return _finish(res, inp, options, rejected, plane, passes, batch=images.shape[:-3])
