"""Batched optimisers for many small, independent problems.

:func:`levenberg_marquardt` fits ``N`` problems of ``P`` parameters each at once, with a
damping per problem, exact Jacobians by forward-mode automatic differentiation (``P``
forward passes) and an active set: a problem that has converged (or cannot improve) drops
out of the batch, so one bad problem never stalls or poisons the others.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
import torch.autograd.forward_ad as fwAD

from torchblur.fit.losses import image_loss, irls_weights

__all__ = ["LMResult", "levenberg_marquardt", "model_jacobian"]


@dataclass
class LMResult:
    """``theta [N, P]``, ``cost [N]``, ``converged [N]`` (bool), ``n_iter [N]``; with an
    analytic ``jacobian_fn`` also ``jtj [N, P, P]`` (``J^T W J`` with the loss's
    Gauss-Newton weights) and ``model [N, R]`` at the final ``theta``."""

    theta: torch.Tensor
    cost: torch.Tensor
    converged: torch.Tensor
    n_iter: torch.Tensor
    jtj: torch.Tensor | None = None
    model: torch.Tensor | None = None


def model_jacobian(model_fn: Callable, theta: torch.Tensor, idx: torch.Tensor):
    """``model_fn(theta, idx) -> [n, R]`` and its Jacobian ``[n, R, P]`` by forward AD."""
    P = theta.shape[-1]
    cols = []
    primal = None
    with fwAD.dual_level():
        for k in range(P):
            tangent = torch.zeros_like(theta)
            tangent[:, k] = 1
            out = model_fn(fwAD.make_dual(theta, tangent), idx)
            unpacked = fwAD.unpack_dual(out)
            if primal is None:
                primal = unpacked.primal.detach()
            cols.append(unpacked.tangent if unpacked.tangent is not None else torch.zeros_like(unpacked.primal))
    return primal, torch.stack(cols, -1)


def levenberg_marquardt(
    model_fn: Callable,
    theta0: torch.Tensor,
    data: torch.Tensor,
    *,
    loss: str = "l2",
    weight: torch.Tensor | None = None,
    max_iter: int = 50,
    tol: float = 1e-10,
    lambda0: float = 1e-3,
    project: Callable | None = None,
    jacobian_fn: Callable | None = None,
    gn_tol: float | None = None,
) -> LMResult:
    """Minimise ``image_loss(model_fn(theta), data)`` for each of ``N`` problems.

    Args:
        model_fn: ``(theta [n, P], idx [n] long) -> model [n, R]``; ``idx`` says which of the
            ``N`` problems the rows are (so the caller can index its own per-problem data).
        theta0: starts ``[N, P]``.
        data: ``[N, R]``.
        loss: ``"l2"``, ``"poisson"`` or ``"l1"`` (by iteratively reweighted least squares).
        weight: per-pixel weights ``[N, R]`` (``1/sigma^2``; 0 masks a pixel) or None.
        max_iter: iterations at most; tol: relative cost decrease that counts as converged.
        project: optional ``theta -> theta`` applied after each step (e.g. keep bounds).
        jacobian_fn: optional ``(theta [n, P], idx) -> (model [n, R], J [n, R, P])`` (an
            analytic Jacobian); default: forward-mode AD through ``model_fn``.
        gn_tol: optional (``l2`` and ``poisson``, weights ``1/sigma^2``): a problem has also
            converged when the full Gauss-Newton step from its current point is predicted to
            land within ``sqrt(gn_tol)`` standard deviations of the optimum; that step is
            then taken without the evaluation that would confirm it (``cost`` is lowered by
            the predicted decrease; ``jtj`` and ``model`` stay those of the point before it).
            Lengths are Mahalanobis, in units of the standard deviation
            (``s^2 = step^T J^T W J step`` over the cost per degree of freedom). The landing
            error is estimated as the step's length ``s`` itself or, once a step of length
            ``s_prev`` has been accepted, as ``s^2 / s_prev``: the convergence rate just
            observed (the previous step left a remainder ``s``, a fraction ``s / s_prev`` of
            itself) applied once more, whichever is smaller. With noisy data Gauss-Newton
            converges linearly near the optimum, at about that rate; far from it, or on a
            strongly curved cost, the remainder shrinks slowly and the estimate keeps the
            step evaluated. It is an estimate, not a bound: on 1200 problems of
            ``benchmarks/bench_fit.py`` the actual remainder after the steps in the
            0.05-5 std range was 0.2x the estimate at the median, at most 3.6x, and the steps
            taken unevaluated with ``gn_tol=1e-2`` landed within 0.026 std.

    Returns:
        :class:`LMResult`. ``converged`` is False where ``max_iter`` ran out.
    """
    N, P = theta0.shape
    theta = theta0.detach().clone()
    all_idx = torch.arange(N, device=theta.device)
    # Lazy mode (an analytic Jacobian that also returns the model): each trial point is
    # evaluated with its Jacobian in one call, kept if the step is accepted (the usual case
    # from a good start), so an iteration costs one call and the final J^T W J is exact.
    lazy = jacobian_fn is not None
    jac = jacobian_fn or (lambda t, i: model_jacobian(model_fn, t, i))
    JTJ = torch.zeros(N, P, P, dtype=theta.dtype, device=theta.device)
    g = torch.zeros(N, P, dtype=theta.dtype, device=theta.device)
    model_store = None

    def rows(t, idx):
        """``t[idx]``, without the copy when ``idx`` is every row (in order)."""
        return t if t is None or idx.numel() == N else t[idx]

    # l2 with one weight per problem (the same noise level on every pixel, nothing masked):
    # the weight multiplies the small products instead of every pixel.
    row_w = None
    if loss == "l2":
        if weight is None:
            row_w = torch.ones(N, dtype=theta.dtype, device=theta.device)
        elif weight.shape[-1] and bool((weight == weight[:, :1]).all()):
            row_w = weight[:, 0].to(theta.dtype)

    def normal_equations(model, J, idx):
        """``(J^T W J [n, P, P], J^T W r [n, P], cost [n])`` at ``model`` (``W``: the loss's
        Gauss-Newton weights; for l2 the cost comes from the same residuals)."""
        d, w = rows(data, idx), rows(weight, idx)
        r = d - model
        if row_w is not None:
            wr = rows(row_w, idx)
            Jt = J.transpose(-1, -2)
            return (Jt @ J) * wr[:, None, None], (Jt @ r[..., None])[..., 0] * wr[:, None], (r[:, None, :] @ r[..., None])[:, 0, 0] * wr
        W = irls_weights(model, d, loss=loss, weight=w)
        JW = J.transpose(-1, -2) * W[:, None, :]  # [n, P, R]: GEMMs below (fast when J is a view of [n, P, R])
        c = (W * r * r).sum(-1) if loss == "l2" else image_loss(model, d, loss=loss, weight=w)
        return JW @ J, (JW @ r[..., None])[..., 0], c

    with torch.no_grad():
        if lazy:
            model0, J0 = jac(theta, all_idx)
            JTJ, g, cost = normal_equations(model0, J0, all_idx)
            model_store = model0.clone()
        else:
            cost = image_loss(model_fn(theta, all_idx), data, loss=loss, weight=weight)
        # A cost this small is round-off: converged (noise-free data).
        d2 = (data[:, None, :] @ data[..., None])[:, 0, 0] if weight is None or row_w is not None else (weight * data * data).sum(-1)
        floor = (10 * torch.finfo(theta.dtype).eps) ** 2 * (d2 if row_w is None else d2 * row_w)
        if gn_tol is not None:
            used = torch.full((N,), data.shape[-1], dtype=theta.dtype, device=theta.device) if weight is None else (weight > 0).sum(-1)
            dof = (used - P).clamp_min(1).to(theta.dtype)
            s_prev = torch.full((N,), float("nan"), dtype=theta.dtype, device=theta.device)  # last accepted step, in std
    lam = torch.full((N,), lambda0, dtype=theta.dtype, device=theta.device)
    converged = torch.zeros(N, dtype=torch.bool, device=theta.device)
    n_iter = torch.zeros(N, dtype=torch.long, device=theta.device)
    need_jac = torch.full((N,), not lazy, dtype=torch.bool, device=theta.device)
    for _ in range(max_iter):
        active = ~converged
        if not bool(active.any()):
            break
        jac_idx = all_idx[active & need_jac]
        if jac_idx.numel():
            model, J = jac(theta[jac_idx], jac_idx)
            JTJ[jac_idx], g[jac_idx], _ = normal_equations(model, J, jac_idx)
            need_jac[jac_idx] = False
        idx = all_idx[active]
        if gn_tol is not None:
            A = JTJ[idx]
            ridge = 1e-12 * torch.diag_embed(torch.diagonal(A, dim1=-2, dim2=-1).abs() + 1e-300)
            gn, info = torch.linalg.solve_ex(A + ridge, g[idx][..., None])
            pred = (g[idx] * gn[..., 0]).sum(-1)
            s2 = pred / (cost[idx] / dof[idx]).clamp_min(1e-300)  # the step's squared length in std^2
            # Predicted landing error: the step itself, or s^2 / s_prev with the observed rate.
            land2 = torch.where(torch.isnan(s_prev[idx]), s2, s2 * s2 / s_prev[idx].square())
            tiny = (info == 0) & torch.isfinite(pred) & (torch.minimum(s2, land2) <= gn_tol)
            if bool(tiny.any()):
                # The last Gauss-Newton step is taken unevaluated: from a point this close,
                # the quadratic model is exact to a small fraction of the step.
                done_idx = idx[tiny]
                fin = theta[done_idx] + gn[tiny, :, 0]
                theta[done_idx] = fin if project is None else project(fin)
                cost[done_idx] = cost[done_idx] - pred[tiny]
                converged[done_idx] = True
            idx = idx[~tiny]
            if not idx.numel():
                break
        n_iter[idx] += 1
        A = JTJ[idx]
        # Marquardt's scaling (damping proportional to each diagonal) is invariant to the
        # parameters' units; the tiny relative term keeps a flat direction solvable.
        diag = torch.diagonal(A, dim1=-2, dim2=-1)
        diag = torch.where(diag > 0, diag, torch.ones_like(diag))
        damped = A + (lam[idx, None, None] + 1e-12) * torch.diag_embed(diag)
        step = torch.linalg.solve(damped, g[idx][..., None])[..., 0]
        step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
        trial = theta[idx] + step
        if project is not None:
            trial = project(trial)
        with torch.no_grad():
            if lazy:
                m_t, J_t = jac(trial, idx)
                jtj_t, g_t, new_cost = normal_equations(m_t, J_t, idx)
            else:
                new_cost = image_loss(model_fn(trial, idx), rows(data, idx), loss=loss, weight=rows(weight, idx))
        ok = torch.isfinite(new_cost) & (new_cost <= cost[idx])
        rel = (cost[idx] - new_cost) / cost[idx].abs().clamp_min(1e-300)
        small_step = (step.abs() <= 1e-12 * (theta[idx].abs() + 1e-8)).all(-1)
        acc = idx[ok]
        if gn_tol is not None:
            # The accepted step's length in std (the quadratic model's decrease along it).
            st = step[ok]
            s_prev[acc] = ((st[:, None, :] @ A[ok] @ st[..., None])[:, 0, 0] / (cost[acc] / dof[acc]).clamp_min(1e-300)).clamp_min(0).sqrt()
        theta[acc] = trial[ok]
        cost[acc] = new_cost[ok]
        if lazy:
            if acc.numel():
                JTJ[acc], g[acc], model_store[acc] = jtj_t[ok], g_t[ok], m_t[ok]
        else:
            need_jac[acc] = True
        lam[idx] = torch.where(ok, (lam[idx] / 3).clamp_min(1e-12), lam[idx] * 4)
        done = (ok & (rel < tol)) | small_step | (lam[idx] > 1e12) | (cost[idx] <= floor[idx])
        converged[idx[done]] = True
    return LMResult(theta=theta, cost=cost, converged=converged, n_iter=n_iter, jtj=JTJ if lazy else None, model=model_store)
