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

from torchblur.errors import ShapeError
from torchblur.losses import gauss_newton_terms, image_loss

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
    shift: float = 0.0,
    dof: torch.Tensor | None = None,
) -> LMResult:
    """Minimise ``image_loss(model_fn(theta), data)`` for each of ``N`` problems.

    Args:
        model_fn: ``(theta [n, P], idx [n] long) -> model [n, R]``; ``idx`` says which of the
            ``N`` problems the rows are (so the caller can index its own per-problem data).
        theta0: starts ``[N, P]``.
        data: ``[N, R]``.
        loss: ``"l2"``, ``"poisson"`` or ``"l1"`` (by iteratively reweighted least squares).
        weight: per-pixel weights ``[N, R]`` (0 masks a pixel; the loss's own, see
            :func:`~torchblur.losses.loss_weight`) or None.
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
        shift: poisson's read-noise shift (counts, see :func:`~torchblur.losses.image_loss`).
        dof: optional ``[N]`` degrees of freedom behind ``gn_tol``'s standard deviation
            (default: each problem's rows of positive weight less ``P``), for a caller whose
            rows stand for several data each (repeats of one exposure merged into their
            weighted mean: their count, not the rows', is the data's).

    Returns:
        :class:`LMResult`. ``converged`` is False where ``max_iter`` ran out.
    """
    if dof is not None and tuple(dof.shape) != (theta0.shape[0],):
        raise ShapeError(f"dof: expected [N={theta0.shape[0]}] degrees of freedom, got shape {tuple(dof.shape)}")
    ne = _NormalEquations(data, weight, loss, shift)
    st = _LMState.start(model_fn, theta0, ne, jacobian_fn, lambda0, gn_tol is not None)
    if dof is not None and st.dof is not None:
        st.dof = dof.to(st.dof).clamp_min(1)
    for _ in range(max_iter):
        active = ~st.converged
        if not bool(active.any()):
            break
        jac_idx = st.all_idx[active & st.need_jac]
        if jac_idx.numel():
            model, J = st.jac(st.theta[jac_idx], jac_idx)
            st.JTJ[jac_idx], st.g[jac_idx], _ = ne(model, J, jac_idx)
            st.need_jac[jac_idx] = False
        idx = st.all_idx[active]
        if gn_tol is not None:
            idx = _gauss_newton_finish(st, idx, gn_tol, project)
            if not idx.numel():
                break
        _damped_step(st, idx, model_fn, ne, project, tol)
    return LMResult(theta=st.theta, cost=st.cost, converged=st.converged, n_iter=st.n_iter,
                    jtj=st.JTJ if st.lazy else None, model=st.model_store)


class _NormalEquations:
    """``(model [n, R], J [n, R, P], idx [n]) -> (J^T W J [n, P, P], J^T W r [n, P], cost [n])``
    with ``W`` the loss's Gauss-Newton weights (for l2 the cost comes from the same residuals).

    l2 with one weight per problem (the same noise level on every pixel, nothing masked):
    the weight multiplies the small products instead of every pixel (``row_w [N]``)."""

    def __init__(self, data, weight, loss, shift=0.0):
        self.data, self.weight, self.loss, self.shift = data, weight, loss, shift
        self.N = data.shape[0]
        self.row_w = None
        if loss == "l2":
            if weight is None:
                self.row_w = torch.ones(self.N, dtype=data.dtype, device=data.device)
            elif weight.shape[-1] and bool((weight == weight[:, :1]).all()):
                self.row_w = weight[:, 0].to(data.dtype)

    def rows(self, t, idx):
        """``t[idx]``, without the copy when ``idx`` is every row (in order)."""
        return t if t is None or idx.numel() == self.N else t[idx]

    def cost(self, model, idx):
        """The loss of ``model [n, R]`` against the rows ``idx`` of the data ``[n]``."""
        return image_loss(model, self.rows(self.data, idx), loss=self.loss, weight=self.rows(self.weight, idx), shift=self.shift)

    def __call__(self, model, J, idx):
        d, w = self.rows(self.data, idx), self.rows(self.weight, idx)
        r = d - model
        if self.row_w is not None:
            wr = self.rows(self.row_w, idx)
            Jt = J.transpose(-1, -2)
            return (Jt @ J) * wr[:, None, None], (Jt @ r[..., None])[..., 0] * wr[:, None], (r[:, None, :] @ r[..., None])[:, 0, 0] * wr
        W, Wr = gauss_newton_terms(model, d, loss=self.loss, weight=w, shift=self.shift)
        JW = J.transpose(-1, -2) * W[:, None, :]  # [n, P, R]: GEMMs below (fast when J is a view of [n, P, R])
        c = (W * r * r).sum(-1) if self.loss == "l2" else image_loss(model, d, loss=self.loss, weight=w, shift=self.shift)
        return JW @ J, (J.transpose(-1, -2) @ Wr[..., None])[..., 0], c

    def round_off_floor(self, dtype):
        """``[N]``: a cost this small is round-off (noise-free data), so it counts as converged."""
        data, weight, row_w = self.data, self.weight, self.row_w
        d2 = (data[:, None, :] @ data[..., None])[:, 0, 0] if weight is None or row_w is not None else (weight * data * data).sum(-1)
        return (10 * torch.finfo(dtype).eps) ** 2 * (d2 if row_w is None else d2 * row_w)


@dataclass
class _LMState:
    """The iteration's per-problem state (``N`` problems, ``P`` parameters), updated in place."""

    theta: torch.Tensor  # [N, P]
    cost: torch.Tensor  # [N]
    JTJ: torch.Tensor  # [N, P, P] at theta
    g: torch.Tensor  # [N, P]: J^T W r at theta
    lam: torch.Tensor  # [N] damping
    converged: torch.Tensor  # [N] bool
    n_iter: torch.Tensor  # [N] long
    need_jac: torch.Tensor  # [N] bool: JTJ and g are stale (not lazy: after an accepted step)
    floor: torch.Tensor  # [N] round-off cost
    all_idx: torch.Tensor  # [N] arange
    jac: Callable
    lazy: bool
    model_store: torch.Tensor | None
    dof: torch.Tensor | None  # [N] degrees of freedom (gn_tol)
    s_prev: torch.Tensor | None  # [N] the last accepted step's length in std (gn_tol)

    @classmethod
    def start(cls, model_fn, theta0, ne: _NormalEquations, jacobian_fn, lambda0, track_steps: bool) -> "_LMState":
        """The state at ``theta0``. Lazy mode (an analytic Jacobian that also returns the model):
        each trial point is evaluated with its Jacobian in one call, kept if the step is accepted
        (the usual case from a good start), so an iteration costs one call and the final
        ``J^T W J`` is exact."""
        N, P = theta0.shape
        theta = theta0.detach().clone()
        dtype, device = theta.dtype, theta.device
        all_idx = torch.arange(N, device=device)
        lazy = jacobian_fn is not None
        jac = jacobian_fn or (lambda t, i: model_jacobian(model_fn, t, i))
        JTJ = torch.zeros(N, P, P, dtype=dtype, device=device)
        g = torch.zeros(N, P, dtype=dtype, device=device)
        model_store = dof = s_prev = None
        with torch.no_grad():
            if lazy:
                model0, J0 = jac(theta, all_idx)
                JTJ, g, cost = ne(model0, J0, all_idx)
                model_store = model0.clone()
            else:
                cost = ne.cost(model_fn(theta, all_idx), all_idx)
            floor = ne.round_off_floor(dtype)
            if track_steps:
                weight = ne.weight
                used = torch.full((N,), ne.data.shape[-1], dtype=dtype, device=device) if weight is None else (weight > 0).sum(-1)
                dof = (used - P).clamp_min(1).to(dtype)
                s_prev = torch.full((N,), float("nan"), dtype=dtype, device=device)
        return cls(theta=theta, cost=cost, JTJ=JTJ, g=g, lam=torch.full((N,), lambda0, dtype=dtype, device=device),
                   converged=torch.zeros(N, dtype=torch.bool, device=device), n_iter=torch.zeros(N, dtype=torch.long, device=device),
                   need_jac=torch.full((N,), not lazy, dtype=torch.bool, device=device), floor=floor, all_idx=all_idx, jac=jac,
                   lazy=lazy, model_store=model_store, dof=dof, s_prev=s_prev)


def _gauss_newton_finish(st: _LMState, idx, gn_tol, project):
    """Finish the problems ``idx`` whose full Gauss-Newton step is predicted to land within
    ``sqrt(gn_tol)`` std (see :func:`levenberg_marquardt`); returns the problems left."""
    A = st.JTJ[idx]
    ridge = 1e-12 * torch.diag_embed(torch.diagonal(A, dim1=-2, dim2=-1).abs() + 1e-300)
    gn, info = torch.linalg.solve_ex(A + ridge, st.g[idx][..., None])
    pred = (st.g[idx] * gn[..., 0]).sum(-1)
    s2 = pred / (st.cost[idx] / st.dof[idx]).clamp_min(1e-300)  # the step's squared length in std^2
    # Predicted landing error: the step itself, or s^2 / s_prev with the observed rate.
    land2 = torch.where(torch.isnan(st.s_prev[idx]), s2, s2 * s2 / st.s_prev[idx].square())
    tiny = (info == 0) & torch.isfinite(pred) & (torch.minimum(s2, land2) <= gn_tol)
    if bool(tiny.any()):
        # The last Gauss-Newton step is taken unevaluated: from a point this close,
        # the quadratic model is exact to a small fraction of the step.
        done_idx = idx[tiny]
        fin = st.theta[done_idx] + gn[tiny, :, 0]
        st.theta[done_idx] = fin if project is None else project(fin)
        st.cost[done_idx] = st.cost[done_idx] - pred[tiny]
        st.converged[done_idx] = True
    return idx[~tiny]


def _damped_step(st: _LMState, idx, model_fn, ne: _NormalEquations, project, tol) -> None:
    """One damped (Levenberg-Marquardt) step for the problems ``idx``: accepted where the cost
    does not rise, the damping adapted, convergence decided."""
    st.n_iter[idx] += 1
    A = st.JTJ[idx]
    # Marquardt's scaling (damping proportional to each diagonal) is invariant to the
    # parameters' units; the tiny relative term keeps a flat direction solvable.
    diag = torch.diagonal(A, dim1=-2, dim2=-1)
    diag = torch.where(diag > 0, diag, torch.ones_like(diag))
    damped = A + (st.lam[idx, None, None] + 1e-12) * torch.diag_embed(diag)
    step = torch.linalg.solve(damped, st.g[idx][..., None])[..., 0]
    step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
    trial = st.theta[idx] + step
    if project is not None:
        trial = project(trial)
    with torch.no_grad():
        if st.lazy:
            m_t, J_t = st.jac(trial, idx)
            jtj_t, g_t, new_cost = ne(m_t, J_t, idx)
        else:
            new_cost = ne.cost(model_fn(trial, idx), idx)
    cost = st.cost[idx]
    ok = torch.isfinite(new_cost) & (new_cost <= cost)
    rel = (cost - new_cost) / cost.abs().clamp_min(1e-300)
    small_step = (step.abs() <= 1e-12 * (st.theta[idx].abs() + 1e-8)).all(-1)
    acc = idx[ok]
    if st.s_prev is not None:
        # The accepted step's length in std (the quadratic model's decrease along it).
        sa = step[ok]
        st.s_prev[acc] = ((sa[:, None, :] @ A[ok] @ sa[..., None])[:, 0, 0] / (st.cost[acc] / st.dof[acc]).clamp_min(1e-300)).clamp_min(0).sqrt()
    st.theta[acc] = trial[ok]
    st.cost[acc] = new_cost[ok]
    if st.lazy:
        if acc.numel():
            st.JTJ[acc], st.g[acc], st.model_store[acc] = jtj_t[ok], g_t[ok], m_t[ok]
    else:
        st.need_jac[acc] = True
    st.lam[idx] = torch.where(ok, (st.lam[idx] / 3).clamp_min(1e-12), st.lam[idx] * 4)
    done = (ok & (rel < tol)) | small_step | (st.lam[idx] > 1e12) | (st.cost[idx] <= st.floor[idx])
    st.converged[idx[done]] = True
