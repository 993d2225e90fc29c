"""Every actuator's dynamics from its column of the dynamic interaction matrix.

Actuator ``j``'s column is rank one: ``D[:, j, f] = G[:, j] * H_j(j w_f)`` with
``H_j(s) = dc_gain * wn^2 / (s^2 + 2 zeta wn s + wn^2) * exp(-s delay_s)``, ``wn = 2 pi mode_hz``
(``dc_gain`` 1 is the nominal actuator, 0 a dead one). :func:`fit_actuators` projects each
column on ``G`` (:func:`project_columns`), fits the parameters with their stds (flagged
``poor_fit`` below :func:`poor_fit_p`, :data:`POOR_FIT_P` over the run's actuators, stds then inflated), measures the static column
(:func:`static_columns`) and gives each actuator its status (:func:`actuator_status`: dead,
weak or ok, :data:`DEAD_FRACTION`, :data:`WEAK_FRACTION`, :data:`STATUS_SIGMA`). A ``dc_gain_std``
grown afterwards by a share the fit leaves out (the registration's, the slope rows' gains) goes
through :func:`with_dc_gain_variance`, which decides the statuses again from the grown stds. The method:
docs/deformable_mirrors.md, "The actuators' fit"; the statuses: "Dead and weak".

Shapes: S = 2M slopes, N actuators, F frequencies.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize, stats

from torchblur.errors import ParameterError, ShapeError

__all__ = ["ActuatorTable", "fit_actuators", "second_order", "project_columns", "static_columns", "actuator_status",
           "status_reference", "with_dc_gain_variance", "poor_fit_p",
           "DEAD_P", "DEAD_SIGMA", "DEAD_FRACTION", "STATUS_SIGMA", "WEAK_FRACTION", "POOR_FIT_P"]

DEAD_P = 1e-3  #: no response detected: the column's chi2 against zero is this likely or more
DEAD_SIGMA = 3.0  #: dead when |dc_gain| < DEAD_SIGMA * dc_gain_std (kept: implied by the DEAD_FRACTION rule)
DEAD_FRACTION = 0.1  #: dead unless dc_gain is significantly above this fraction of the median responding dc_gain
STATUS_SIGMA = 3.0  #: "significantly": by this many dc_gain stds
WEAK_FRACTION = 0.5  #: weak when dc_gain is significantly below this fraction of the median responding dc_gain
POOR_FIT_P = 1e-3  #: the chance that a run whose every actuator model holds flags one of them poor fit (:func:`poor_fit_p`)
PARAMS = ("dc_gain", "mode_hz", "damping", "delay_s")


@dataclass(frozen=True)
class ActuatorTable:
    """Per-actuator estimates, every array ``[N]`` unless said.

    Attributes:
        dc_gain, mode_hz, damping, delay_s: the fitted ``H_j`` (NaN dynamics for a dead one).
        dc_gain_std, mode_hz_std, damping_std, delay_s_std: one standard deviation each.
        status: ``"ok"``, ``"weak"`` or ``"dead"`` per actuator (tuple of N).
        poor_fit: bool, the model does not explain the column (stds inflated, see the module).
        reduced_chi2: the parametric fit's chi2 per degree of freedom (NaN for a dead one).
        static_column: ``[2M, N]`` the measured ``D0`` (px per input unit).
        static_column_std: ``[2M, N]``.
        shape: ``[N, F]`` complex ``h_j(f)`` (step 1), shape_cov ``[N, F, 2, 2]``.
        freq_hz: ``[F]``.
        actuator_xy: ``[N, 2]`` positions (pitches) or None.
        status_reference: the median DC gain of the responding actuators the statuses are relative
            to (:func:`status_reference`; NaN: none responds).
    """

    dc_gain: np.ndarray
    dc_gain_std: np.ndarray
    mode_hz: np.ndarray
    mode_hz_std: np.ndarray
    damping: np.ndarray
    damping_std: np.ndarray
    delay_s: np.ndarray
    delay_s_std: np.ndarray
    status: tuple
    poor_fit: np.ndarray
    reduced_chi2: np.ndarray
    static_column: np.ndarray
    static_column_std: np.ndarray
    shape: np.ndarray
    shape_cov: np.ndarray
    freq_hz: np.ndarray
    actuator_xy: np.ndarray | None = None
    status_reference: float = math.nan

    def __len__(self) -> int:
        return len(self.status)


def second_order(freq_hz, dc_gain, mode_hz, damping, delay_s):
    """``H(j w) = dc_gain * wn^2 / (wn^2 - w^2 + 2 j zeta wn w) * exp(-j w delay_s)``, complex
    ``[..., F]`` for ``freq_hz`` ``[F]`` and parameters broadcastable to ``[...]``."""
    w = 2 * np.pi * np.asarray(freq_hz, dtype=np.float64)
    a = [np.asarray(v, dtype=np.float64)[..., None] for v in (dc_gain, mode_hz, damping, delay_s)]
    wn = 2 * np.pi * a[1]
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN parameters (a dead actuator) give NaN
        return a[0] * wn**2 / (wn**2 - w**2 + 2j * a[2] * wn * w) * np.exp(-1j * w * a[3])


def _inv2(cov):
    """Inverses of 2x2 covariances ``[..., 2, 2]``, 0 where not finite or not positive definite."""
    det = cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] * cov[..., 1, 0]
    ok = np.isfinite(cov).all((-1, -2)) & (det > 0) & (cov[..., 0, 0] > 0)
    return np.linalg.inv(np.where(ok[..., None, None], cov, np.eye(2))) * ok[..., None, None]


def _ri(z):
    return np.stack([z.real, z.imag], -1)


def project_columns(D, D_cov, G):
    """``h [N, F]`` complex: per actuator and frequency the generalised least-squares scalar
    ``h`` of ``D[:, j, f] = G[:, j] * h``, and ``h_cov [N, F, 2, 2]`` (slopes independent;
    NaN entries of ``D`` left out)."""
    W = _inv2(D_cov)  # [S, N, F, 2, 2]
    d = np.nan_to_num(_ri(D)) * (W.any((-1, -2))[..., None])
    normal = np.einsum("sj,sjfab->jfab", G**2, W)
    rhs = np.einsum("sj,sjfab,sjfb->jfa", G, W, d)
    cov = np.full_like(normal, np.nan)
    ok = np.linalg.det(normal) > 0
    cov[ok] = np.linalg.inv(normal[ok])
    x = np.einsum("jfab,jfb->jfa", cov, rhs)
    return x[..., 0] + 1j * x[..., 1], cov


def static_columns(D, D_cov, unit_shape):
    """``(D0 [S, N], D0_std [S, N])``: per slope and actuator the real least-squares scalar
    ``a`` of ``D[s, j, :] = a * unit_shape[j, :]`` (``unit_shape`` ``[N, F]`` complex, the fitted
    response of unit DC gain), over the frequencies; NaN where ``unit_shape`` is NaN; exactly 0
    (std 0) where ``D`` and ``D_cov`` are 0 at every frequency (off a sparse plan's support)."""
    W = _inv2(D_cov)
    u = _ri(unit_shape)  # [N, F, 2]
    good = np.isfinite(u).all(-1)
    u = np.where(good[..., None], u, 0.0)
    d = np.nan_to_num(_ri(D)) * (W.any((-1, -2))[..., None])
    num = np.einsum("jfa,sjfab,sjfb->sj", u, W, d)
    den = np.einsum("jfa,sjfab,jfb->sj", u, W, u)
    off = (den == 0) & np.all(D == 0, axis=-1) & np.all(D_cov == 0, axis=(-3, -2, -1))  # off a sparse plan's support: 0 exactly
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(off, 0.0, num / den), np.where(off, 0.0, 1.0 / np.sqrt(den))


def _whitener(cov):
    """``[F, 2, 2]`` matrices ``L^-1`` with ``L L^T = cov`` (rows of NaN cov: 0)."""
    ok = np.isfinite(cov).all((-1, -2))
    L = np.linalg.cholesky(np.where(ok[:, None, None], cov, np.eye(2)))
    return np.linalg.inv(L) * ok[:, None, None]


def _grid_start(freq_hz, h, Wh):
    """The best ``(dc_gain, mode_hz, damping, delay_s)`` of a grid over ``(mode_hz, damping)``;
    at each node the delay from the weighted slope of the ratio's phase, the gain in closed form."""
    f = np.asarray(freq_hz)
    fn = np.geomspace(f.min() / 3, f.max() * 3, 90)
    zeta = np.geomspace(3e-3, 2.0, 28)
    FN, Z = np.meshgrid(fn, zeta, indexing="ij")
    H0 = second_order(f, 1.0, FN, Z, 0.0)  # [g1, g2, F]
    r = h / H0
    w = 2 * np.pi * f
    wt = np.abs(H0) ** 2 * np.abs(r) ** 2 * np.where(np.isfinite(h), 1.0, 0.0)
    ph = np.unwrap(np.angle(np.nan_to_num(r)), axis=-1)
    ph = ph - 2 * np.pi * np.round(ph[..., :1] / (2 * np.pi))
    tau = -np.sum(wt * w * ph, -1) / np.maximum(np.sum(wt * w**2, -1), 1e-300)
    model = H0 * np.exp(-1j * w * tau[..., None])
    m = _ri(model)
    num = np.einsum("...fa,fab,fb->...", m, Wh, np.nan_to_num(_ri(h)))
    den = np.einsum("...fa,fab,...fb->...", m, Wh, m)
    k = num / np.maximum(den, 1e-300)
    e = _ri(h - k[..., None] * model)
    cost = np.einsum("...fa,fab,...fb->...", e, Wh, e)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    i, jz = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return np.array([k[i, jz], fn[i], zeta[jz], tau[i, jz]])


def _fit_one(freq_hz, h, h_cov):
    """Weighted least squares of :func:`second_order` to one actuator's ``h [F]``.
    Returns ``(params [4], std [4], chi2, dof)``."""
    good = np.isfinite(h) & np.isfinite(h_cov).all((-1, -2))
    f, h, h_cov = np.asarray(freq_hz)[good], h[good], h_cov[good]
    Lw = _whitener(h_cov)
    p0 = _grid_start(f, h, np.einsum("fba,fbc->fac", Lw, Lw))
    scale = np.array([max(abs(p0[0]), 1e-12), p0[1], max(p0[2], 1e-3), 1.0 / (2 * np.pi * f.max())])

    def resid(q):
        p = q * scale
        e = _ri(second_order(f, *p) - h)
        return np.einsum("fab,fb->fa", Lw, e).ravel()

    lo = np.array([-np.inf, 1e-3 * f.min(), 1e-5, -np.inf]) / scale
    sol = optimize.least_squares(resid, p0 / scale, bounds=(lo, np.inf), x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=400)
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J) * np.outer(scale, scale)
    except np.linalg.LinAlgError:
        cov = np.full((4, 4), np.nan)
    chi2 = float(2 * sol.cost)
    return sol.x * scale, np.sqrt(np.abs(np.diag(cov))), chi2, 2 * int(good.sum()) - 4


def _no_response(h, h_cov) -> bool:
    """The column's chi2 against zero is consistent with noise alone (survival > DEAD_P)."""
    good = np.isfinite(h) & np.isfinite(h_cov).all((-1, -2))
    if not good.any():
        return True
    chi2 = float(np.einsum("fa,fab,fb->", _ri(h[good]), _inv2(h_cov[good]), _ri(h[good])))
    return bool(stats.chi2.sf(chi2, 2 * int(good.sum())) > DEAD_P)


def _scalar_against(h, h_cov, shape):
    """The real least-squares scalar ``k`` of ``h = k * shape`` ``[F]`` and its std."""
    W = _inv2(h_cov)
    u, d = np.nan_to_num(_ri(shape)), np.nan_to_num(_ri(h))
    den = float(np.einsum("fa,fab,fb->", u, W, u))
    if not den > 0:
        return math.nan, math.nan
    return float(np.einsum("fa,fab,fb->", u, W, d)) / den, 1.0 / math.sqrt(den)


def status_reference(dc_gain, no_response) -> float:
    """The DC gain the statuses are relative to: the median ``dc_gain [N]`` of the actuators that
    respond (``no_response [N]`` False, finite gain); NaN where none does."""
    g = np.asarray(dc_gain, dtype=float)
    live = ~np.asarray(no_response, dtype=bool) & np.isfinite(g)
    return float(np.median(g[live])) if live.any() else math.nan


def actuator_status(dc_gain, dc_gain_std, no_response, ref: float | None = None) -> tuple:
    """Status per actuator (module rules): ``"dead"`` where ``no_response`` or ``dc_gain -
    STATUS_SIGMA * dc_gain_std <= DEAD_FRACTION * ref`` (NaN gain or std: dead), ``"weak"`` where
    significantly between ``DEAD_FRACTION * ref`` and ``WEAK_FRACTION * ref``, else ``"ok"``; ``ref``
    by default the median DC gain of the actuators that respond (:func:`status_reference`, NaN
    gains and stds left out). Arrays ``[N]``."""
    g, s = np.asarray(dc_gain, dtype=float), np.asarray(dc_gain_std, dtype=float)
    silent = np.asarray(no_response, dtype=bool) | ~np.isfinite(g) | ~np.isfinite(s)
    ref = status_reference(g, silent) if ref is None else float(ref)
    lo, hi = g - STATUS_SIGMA * s, g + STATUS_SIGMA * s
    with np.errstate(invalid="ignore"):
        dead = silent | ~(lo > DEAD_FRACTION * ref) | ~(np.abs(g) >= DEAD_SIGMA * s)
        weak = ~dead & (hi < WEAK_FRACTION * ref)
    return tuple("dead" if d else "weak" if w else "ok" for d, w in zip(dead, weak))


def with_dc_gain_variance(table: ActuatorTable, var) -> ActuatorTable:
    """``table`` with every ``dc_gain_std`` grown to ``sqrt(std^2 + var)`` (``var [N]``, the
    variance of a share the fit leaves out, in dc_gain units squared) and every status decided
    again from the grown std against the same :attr:`~ActuatorTable.status_reference`, so that
    status and std agree: a grown std can make an ok actuator dead (no longer significantly above
    :data:`DEAD_FRACTION` of the reference) or a weak one ok (no longer significantly below
    :data:`WEAK_FRACTION`); a dead actuator stays dead (its gain was measured against a median
    shape, and a larger std only keeps it dead)."""
    var = np.asarray(var, dtype=np.float64)
    if var.shape != np.shape(table.dc_gain):
        raise ShapeError(f"var: expected [N] = {np.shape(table.dc_gain)}, got shape {var.shape}")
    std = np.sqrt(np.asarray(table.dc_gain_std, dtype=np.float64) ** 2 + var)
    dead = np.array([s == "dead" for s in table.status], dtype=bool)
    ref = table.status_reference if math.isfinite(table.status_reference) else None  # none kept: the live gains' median
    return replace(table, dc_gain_std=std, status=actuator_status(table.dc_gain, std, dead, ref=ref))


def poor_fit_p(n_tested: int) -> float:
    """The chi2 survival below which one of ``n_tested`` actuator models is a poor fit:
    ``1 - (1 - POOR_FIT_P)^(1 / n)`` (Sidak), so that a run whose every model holds flags one with
    chance :data:`POOR_FIT_P` whatever its size (a per-actuator ``POOR_FIT_P`` would flag one in 5 %
    of 52-actuator runs and in 55 % of 800-actuator runs)."""
    return -math.expm1(math.log1p(-POOR_FIT_P) / max(int(n_tested), 1))


def _check(freq_hz, D, D_cov, G):
    f = np.asarray(freq_hz, dtype=np.float64).reshape(-1)
    D, D_cov, G = np.asarray(D), np.asarray(D_cov, dtype=np.float64), np.asarray(G, dtype=np.float64)
    if D.ndim != 3 or D.shape[2] != f.size:
        raise ShapeError(f"D: expected [2M, N, F={f.size}] complex, got shape {D.shape}")
    if D_cov.shape != D.shape + (2, 2):
        raise ShapeError(f"D_cov: expected {D.shape + (2, 2)}, got shape {D_cov.shape}")
    if G.shape != D.shape[:2]:
        raise ShapeError(f"G_nominal: expected [2M, N] = {D.shape[:2]}, got shape {G.shape}")
    if f.size < 3 or not np.all(f > 0):
        raise ParameterError(f"freq_hz: expected at least 3 positive frequencies, got {f.tolist()[:5]}")
    return f, D.astype(np.complex128), D_cov, G


def fit_actuators(freq_hz, D, D_cov, G_nominal, *, actuator_xy=None) -> ActuatorTable:
    """Every actuator's ``dc_gain, mode_hz, damping, delay_s`` (with stds), status and static
    column from the dynamic interaction matrix (see the module for the steps and rules).

    Args:
        freq_hz: ``[F]`` (F >= 3).
        D: ``[2M, N, F]`` complex (px per input unit), from :func:`~torchblur.dm.demux.demultiplex`.
        D_cov: ``[2M, N, F, 2, 2]`` covariance of ``(Re, Im) D``.
        G_nominal: ``[2M, N]`` the mirror model's geometry (px per input unit, gain 1).
        actuator_xy: optional ``[N, 2]`` positions kept in the table.

    Returns:
        :class:`ActuatorTable`.
    """
    f, D, D_cov, G = _check(freq_hz, D, D_cov, G_nominal)
    N = D.shape[1]
    h, h_cov = project_columns(D, D_cov, G)
    est = np.full((N, 4), np.nan)
    std = np.full((N, 4), np.nan)
    red = np.full(N, np.nan)
    silent = np.array([_no_response(h[j], h_cov[j]) for j in range(N)])
    p = np.full(N, np.nan)
    for j in np.flatnonzero(~silent):
        est[j], std[j], chi2, dof = _fit_one(f, h[j], h_cov[j])
        red[j] = chi2 / dof if dof > 0 else np.nan
        p[j] = stats.chi2.sf(chi2, dof) if dof > 0 else np.nan
    poor = p < poor_fit_p(int(np.isfinite(p).sum()))
    std[poor] *= np.sqrt(red[poor])[:, None]
    gain_ref = status_reference(est[:, 0], silent | ~np.isfinite(std[:, 0]))
    status = actuator_status(est[:, 0], std[:, 0], silent, ref=gain_ref)
    dead = np.array([s == "dead" for s in status])
    unit = second_order(f, 1.0, est[:, 1], est[:, 2], est[:, 3])  # [N, F], the fitted shapes of unit DC gain
    if dead.any():
        live = ~dead & np.isfinite(est[:, 1])
        med = np.median(est[live, 1:], axis=0) if live.any() else np.array([np.median(f), 0.7, 0.0])
        ref = second_order(f, 1.0, *med)
        for j in np.flatnonzero(dead):
            est[j, 0], std[j, 0] = _scalar_against(h[j], h_cov[j], ref)
            est[j, 1:], std[j, 1:], red[j] = np.nan, np.nan, np.nan
            unit[j] = ref
    D0, D0_std = static_columns(D, D_cov, unit)
    xy = None if actuator_xy is None else np.asarray(actuator_xy, dtype=np.float64)
    return ActuatorTable(*(a for k in range(4) for a in (est[:, k], std[:, k])), status=status, poor_fit=poor, reduced_chi2=red,
                         static_column=D0, static_column_std=D0_std, shape=h, shape_cov=h_cov, freq_hz=f, actuator_xy=xy,
                         status_reference=gain_ref)
