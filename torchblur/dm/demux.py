"""Demultiplexing: the dynamic interaction matrix ``D(jw)`` from the responses measured under
multiplexed excitation patterns, ``Y[p, s, f] = sum_j patterns[p, j] * D[s, j, f] + noise``.

:func:`demultiplex` solves it per slope row and frequency by generalised least squares over the
row's support (``D`` exactly 0 off it), or for large supports by ``pinv(patterns) Y`` with its
exact covariance (``method``): docs/deformable_mirrors.md, "The demultiplexing".

Shapes: P patterns, N actuators, S = 2M slopes (``[x of all M, y of all M]``), F frequencies.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg
import torch

from torchblur.errors import ParameterError, ShapeError, check_choice

__all__ = ["demultiplex", "check_support", "OLS_ABOVE"]

#: squared ratio of a normal matrix's Cholesky diagonal below which the item's data do not determine its row (NaN)
_RCOND = 1e-12
#: bytes of normal matrices held at once
_CHUNK_BYTES = 64 * 2**20
#: ``method="auto"`` solves supports of more actuators than this by ordinary least squares
OLS_ABOVE = 128


def _as_arrays(Y, Y_cov, patterns, support):
    Y = np.asarray(Y)
    Y_cov = np.asarray(Y_cov, dtype=np.float64)
    patterns = np.asarray(patterns, dtype=np.float64)
    if Y.ndim != 3:
        raise ShapeError(f"Y: expected [P, 2M, F] complex, got shape {Y.shape}")
    P, S, F = Y.shape
    if patterns.ndim != 2 or patterns.shape[0] != P:
        raise ShapeError(f"patterns: expected [P={P}, N], got shape {patterns.shape}")
    if not np.all(np.isfinite(patterns)):
        raise ParameterError("patterns: expected finite values, got NaN or Inf")
    if Y_cov.shape != (P, S, F, 2, 2):
        raise ShapeError(f"Y_cov: expected [P, 2M, F, 2, 2] = {(P, S, F, 2, 2)}, got shape {Y_cov.shape}")
    ok = np.isfinite(Y)  # where a fit failed (Y NaN) its covariance is not used
    vx, vy, cxy = Y_cov[..., 0, 0][ok], Y_cov[..., 1, 1][ok], Y_cov[..., 0, 1][ok]
    if np.any((vx < 0) | (vy < 0) | (cxy * cxy > vx * vy * (1 + 1e-9) + 1e-300)):
        raise ParameterError("Y_cov: expected covariances with variances >= 0 (positive semi-definite) where Y is finite, got "
                             "a negative or indefinite one")
    N = patterns.shape[1]
    if support is None:
        support = np.ones((S, N), dtype=bool)
    support = np.asarray(support)
    if support.shape != (S, N) or support.dtype != bool:
        raise ShapeError(f"support: expected bool [2M={S}, N={N}], got {support.dtype} {support.shape}")
    return Y.astype(np.complex128), Y_cov, patterns, support


def _rank_deficient(A) -> bool:
    """``A [P, n]`` has rank < n (eigenvalues of ``A^T A``, cheaper than an SVD for big mirrors)."""
    lam = np.linalg.eigvalsh(A.T @ A)
    return not lam[0] > 1e-10 * max(lam[-1], np.finfo(float).tiny)


def check_support(patterns, support) -> None:
    """Raise :class:`ParameterError` (naming ``support``) when a slope row's support is not
    determined by the patterns: ``patterns[:, support[s]]`` ``[P, n_s]`` must have rank ``n_s``
    (the first such row is named).

    Args:
        patterns: ``[P, N]`` real.
        support: ``[2M, N]`` bool.
    """
    patterns = np.asarray(patterns, dtype=np.float64)
    uniq, first = np.unique(np.asarray(support, dtype=bool), axis=0, return_index=True)
    for sup, s in zip(uniq, first):
        n = int(sup.sum())
        if n and _rank_deficient(patterns[:, sup]):
            raise ParameterError(f"support: slope row {int(s)} sees {n} actuators {np.flatnonzero(sup).tolist()[:8]}"
                                 f"{'...' if n > 8 else ''} but the patterns restricted to them have rank "
                                 f"{np.linalg.matrix_rank(patterns[:, sup])} < {n}: they are not determined")


def _weights(Y, Y_cov):
    """``(W [P, S, F, 2, 2], y [P, S, F, 2])``: the inverse covariances and the data, both 0 where
    the response or its covariance is not finite (a failed fit: that pattern is left out)."""
    y = np.stack([Y.real, Y.imag], -1)
    ok = np.isfinite(y).all(-1) & np.isfinite(Y_cov).all((-1, -2))
    det = Y_cov[..., 0, 0] * Y_cov[..., 1, 1] - Y_cov[..., 0, 1] * Y_cov[..., 1, 0]
    ok &= (det > 0) & (Y_cov[..., 0, 0] > 0)
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    W = np.stack([np.stack([Y_cov[..., 1, 1], -Y_cov[..., 0, 1]], -1), np.stack([-Y_cov[..., 1, 0], Y_cov[..., 0, 0]], -1)], -2)
    W = np.where(ok[..., None, None], W * inv_det[..., None, None], 0.0)
    return W, np.where(ok[..., None], y, 0.0)


def _spd_inverse(normal):
    """Inverses of symmetric normal matrices ``[..., k, k]`` by batched Cholesky (torch; an
    eigen-decomposition costs ~7x more); NaN where one is not positive definite or its
    Cholesky diagonal spans more than ``1 / sqrt(_RCOND)`` (the data do not determine it)."""
    t = torch.from_numpy(np.ascontiguousarray(normal))
    L, info = torch.linalg.cholesky_ex(t)
    d = torch.diagonal(L, dim1=-2, dim2=-1)
    good = (info == 0) & (d.min(-1).values ** 2 > _RCOND * (d.max(-1).values ** 2).clamp_min(torch.finfo(t.dtype).tiny))
    eye = torch.eye(t.shape[-1], dtype=t.dtype)
    inv = torch.cholesky_inverse(torch.where(good[..., None, None], L, eye))
    return torch.where(good[..., None, None], inv, torch.full_like(inv, float("nan"))).numpy()


def _estimable_inverse(normal):
    """``(ginv [k, m, m], undetermined [k, m])`` of singular normal matrices ``[k, m, m]``: the
    pseudo-inverse (eigenvalues below :data:`_RCOND` of the largest are the null space) and the
    unknowns with a share of the null space (above 1e-8 of their unit vector's squared norm). Every
    other unknown is estimable, and the pseudo-inverse gives its generalised least-squares value and
    variance exactly (any generalised inverse does for an estimable function)."""
    lam, V = np.linalg.eigh(normal)
    null = lam <= _RCOND * lam[:, -1:].clip(min=np.finfo(float).tiny)
    inv_lam = np.where(null, 0.0, 1.0 / np.where(null, 1.0, lam))
    ginv = (V * inv_lam[:, None, :]) @ np.swapaxes(V, -1, -2)
    undetermined = (np.where(null[:, None, :], V, 0.0) ** 2).sum(-1) > 1e-8
    return ginv, undetermined


def _solve_group(A, W, y):
    """Weighted least squares of one support group.

    Args:
        A: ``[P, n]`` the patterns on the group's support.
        W: ``[P, B, F, 2, 2]`` weights, y: ``[P, B, F, 2]`` data (B rows of the group).

    Returns ``(x [B, F, n, 2], cov [B, F, n, 2, 2])``: NaN for an actuator no pattern with data
    drives, and for each actuator the rest of the item's data do not determine on its own (its unit
    vector not in the span of the patterns left: :func:`_estimable_inverse`); the item's other
    actuators are solved exactly as without it.
    """
    n = A.shape[1]
    P, B, F = W.shape[:3]
    K = (A[:, :, None] * A[:, None, :]).reshape(P, n * n)  # [P, n*n]: a_p a_p^T
    normal = (K.T @ W.reshape(P, B * F * 4)).reshape(n, n, B, F, 2, 2)  # BLAS, not a 6-index einsum
    normal = normal.transpose(2, 3, 0, 4, 1, 5).reshape(B, F, 2 * n, 2 * n)
    Wy = (W @ y[..., None])[..., 0]  # [P, B, F, 2]
    rhs = (A.T @ Wy.reshape(P, B * F * 2)).reshape(n, B, F, 2).transpose(1, 2, 0, 3).reshape(B, F, 2 * n)
    # an actuator no pattern with data drives (its only pattern's fit failed: a sparse plan) is left
    # out of its item's system and NaN, the others solved without it
    none = ~(np.diagonal(normal, axis1=-2, axis2=-1).reshape(B, F, n, 2) > 0).all(-1)  # [B, F, n]
    drop = np.repeat(none, 2, axis=-1)  # [B, F, 2n]
    normal = np.where(drop[..., :, None] | drop[..., None, :], 0.0, normal) + drop[..., None, :] * np.eye(2 * n)
    cov = _spd_inverse(normal)
    singular = np.isnan(cov).any((-1, -2))  # [B, F]: the remaining patterns leave some combination undetermined
    if singular.any():
        cov[singular], undetermined = _estimable_inverse(normal[singular])
        none = none.copy()
        none[singular] |= undetermined.reshape(-1, n, 2).any(-1)
        drop = np.repeat(none, 2, axis=-1)
    x = (cov @ rhs[..., None])[..., 0]
    x[drop] = np.nan
    cov = cov.reshape(B, F, n, 2, n, 2)
    diag = np.moveaxis(cov[:, :, np.arange(n), :, np.arange(n), :], 0, 2)  # [B, F, n, 2, 2]
    diag[none] = np.nan
    return x.reshape(B, F, n, 2), diag


def _ols_group(Ap, Y, C):
    """Ordinary least squares of one support group with the exact (sandwich) covariance.

    Args:
        Ap: ``[n, P]`` the pseudo-inverse of the group's patterns ``A [P, n]`` (full column rank);
        Y: ``[P, B, F]`` complex (finite); C: ``[P, B, F, 2, 2]``.

    Returns ``(x [B, F, n] complex, cov [B, F, n, 2, 2])``: ``x = pinv(A) Y`` and
    ``cov_j = sum_p pinv(A)[j, p]^2 C_p`` (patterns independent)."""
    n, (P, B, F) = Ap.shape[0], Y.shape
    x = (Ap @ Y.reshape(P, B * F)).reshape(n, B, F)
    cov = ((Ap * Ap) @ C.reshape(P, B * F * 4)).reshape(n, B, F, 2, 2)
    return np.moveaxis(x, 0, -1), np.moveaxis(cov, 0, 2)


def demultiplex(Y, Y_cov, patterns, support=None, *, method: str = "auto"):
    """The dynamic interaction matrix ``D [2M, N, F]`` from the pattern responses (see the module).

    Args:
        Y: ``[P, 2M, F]`` complex: ``Y[p, s, f]`` = the response of slope ``s`` (px per input
            unit) to pattern ``p`` at frequency ``f``; NaN where its fit failed (left out).
        Y_cov: ``[P, 2M, F, 2, 2]`` the covariance of ``(Re, Im) Y[p, s, f]``.
        patterns: ``[P, N]`` real: the plan's pattern matrix.
        support: ``[2M, N]`` bool: ``support[s, j]`` = slope ``s`` sees actuator ``j`` (``D[s, j]``
            is an unknown); None: every actuator (Hadamard, one at a time).
        method: ``"wls"``: the weighted least squares of the module; ``"ols"``: ordinary least
            squares ``pinv(patterns) Y`` per row with its exact covariance ``sum_p pinv[j, p]^2
            Y_cov[p]`` (unbiased, a little less precise where the covariances differ between
            patterns, and ``n^2`` cheaper per row: for large mirrors; a row with a failed fit
            falls back to ``"wls"``); ``"auto"`` (default): ``"ols"`` for supports of more than
            :data:`OLS_ABOVE` actuators, else ``"wls"``.

    Returns:
        ``(D, D_cov)``: ``D [2M, N, F]`` complex128, ``D[s, j, f]`` = the response of slope ``s``
        to a unit sine on actuator ``j`` at frequency ``f`` (0 off the support; NaN where the
        data left out by failed fits no longer determine it: the actuators whose every driving
        pattern failed, as on a sparse plan, and those the patterns left determine only in
        combination with others, as two lost patterns of a Hadamard plan can leave; the row's
        other actuators keep their values and stds), and ``D_cov
        [2M, N, F, 2, 2]`` the covariance of ``(Re, Im) D[s, j, f]`` (the correlations between
        the actuators of one row are dropped).

    Raises:
        ParameterError: a row's support is not determined by the patterns (names ``support``),
            or ``method`` is not one of the three (names ``method``).
        ShapeError: a shape does not match (names the argument).

    Cost: ``"wls"``, one ``2n x 2n`` Cholesky inverse per (row, frequency), ``n``
    the row's support size; ``"ols"``, one ``n x P`` product per row; rows with the same support
    share their pattern matrix.
    """
    method = check_choice(method, "method", ("auto", "wls", "ols"))
    Y, Y_cov, patterns, support = _as_arrays(Y, Y_cov, patterns, support)
    check_support(patterns, support)
    P, S, F = Y.shape
    N = patterns.shape[1]
    D = np.zeros((S, N, F), dtype=np.complex128)
    D_cov = np.zeros((S, N, F, 2, 2))
    uniq, inverse = np.unique(support, axis=0, return_inverse=True)
    for g, sup in enumerate(uniq):
        cols = np.flatnonzero(sup)
        if cols.size == 0:
            continue
        rows = np.flatnonzero(inverse.reshape(-1) == g)
        A = patterns[:, cols]
        used = np.flatnonzero(np.any(A != 0, axis=1))  # patterns that drive none of the support say nothing
        A = A[used]
        ols = method == "ols" or (method == "auto" and cols.size > OLS_ABOVE)
        Ap = scipy.linalg.cho_solve(scipy.linalg.cho_factor(A.T @ A), A.T) if ols else None  # pinv(A): full column rank
        per_row = F * (P * 4 + (cols.size * 4 if ols else (2 * cols.size) ** 2)) * 8 * 4
        step = max(1, _CHUNK_BYTES // per_row)
        for r0 in range(0, rows.size, step):
            r = rows[r0:r0 + step]
            Yr, Cr = Y[np.ix_(used, r)], Y_cov[np.ix_(used, r)]
            W, y = _weights(Yr, Cr)
            if ols:
                complete = W.any((-1, -2)).all(0).all(-1)  # [b]: every pattern of the row fitted at every frequency
                x = np.full((r.size, F, cols.size), np.nan + 0j)
                cov = np.full((r.size, F, cols.size, 2, 2), np.nan)
                if complete.any():
                    x[complete], cov[complete] = _ols_group(Ap, Yr[:, complete], Cr[:, complete])
                if not complete.all():
                    xw, cov[~complete] = _solve_group(A, W[:, ~complete], y[:, ~complete])
                    x[~complete] = xw[..., 0] + 1j * xw[..., 1]
            else:
                x, cov = _solve_group(A, W, y)
                x = x[..., 0] + 1j * x[..., 1]
            D[np.ix_(r, cols)] = np.moveaxis(x, 1, 2)
            D_cov[np.ix_(r, cols)] = np.moveaxis(cov, 1, 2)
    return D, D_cov
