"""The slopes' own gains: how far each slope row of the measured static columns D0 scales away
from the fitted geometry beyond its noise, and each actuator's ``dc_gain`` std grown by its share.

A Shack-Hartmann subaperture reads a tilt with its own gain: crosstalk from its neighbours' spots,
the pupil's edge across a lenslet, the spot's sampling (its fitted shift's convention) differ from
lenslet to lenslet, and no geometry model (:mod:`torchblur.dm.registration`) holds them. Such a
gain ``1 + delta_r`` scales row ``r`` of ``D (jw)`` at every frequency alike, so it reaches
actuator ``j``'s response ``h_j`` (D's column projected on G, :func:`~torchblur.dm.actuator_fit.project_columns`)
as one gain common to every frequency: no single frequency's std shows it, and the actuator fit,
taking the frequencies as independent, leaves it out of ``dc_gain_std``.

:func:`slope_gains` measures it. Row ``r``'s gain ``g_r`` is the weighted least-squares scale of
``D0[r, :]`` against ``dc_gain_j G[r, j]`` (weights ``1 / D0_std^2``), ``g_std_r`` its std; their
scatter beyond those stds, ``tau``, is the DerSimonian-Laird random-effects estimate (0 where the
rows agree within their noise), apart for the fully lit subapertures' rows and the others (the
pupil's edge, where the scatter is larger). :func:`with_slope_gain_stds` grows every ``dc_gain_std``
to ``sqrt(std^2 + dc_gain^2 sum_r w_rj^2 tau_r^2)``, ``w_rj = G[r, j]^2 / D0_std[r, j]^2``
normalised over the rows (the projection's weights at zero frequency), and decides every status
again from the grown std; modes, dampings and
delays are left as they are (a gain common to every frequency does not move them). What part of
the rows' gain errors the actuators' own gains absorb (a smooth pattern of them) is not seen in
the scatter, and is not in the stds.

Shapes: S = 2M slopes (x of all M subapertures, then y), N actuators.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchblur.dm.actuator_fit import with_dc_gain_variance
from torchblur.dm.registration import whitened
from torchblur.errors import ShapeError

__all__ = ["SlopeGains", "slope_gains", "random_effects_scatter", "with_slope_gain_stds", "slope_gains_line"]


@dataclass(frozen=True)
class SlopeGains:
    """The slope rows' gains against the fitted geometry (module docstring).

    Attributes:
        gain, gain_std: ``[S]`` each row's scale ``g_r`` and its std (NaN: the row sees no actuator).
        lit: ``[S]`` bool, the row of a fully lit subaperture.
        tau: ``{"lit", "edge"}`` the rows' gain scatter beyond their noise (fraction, 0: none).
        q_over_dof: ``{"lit", "edge"}`` Cochran's Q over its degrees of freedom (about 1 without scatter).
        n_rows: ``{"lit", "edge"}`` rows used.
        dc_gain_share: ``[N]`` the relative std each actuator's ``dc_gain`` gains from ``tau``.
    """

    gain: np.ndarray
    gain_std: np.ndarray
    lit: np.ndarray
    tau: dict
    q_over_dof: dict
    n_rows: dict
    dc_gain_share: np.ndarray


def random_effects_scatter(g, g_std) -> tuple[float, float, float]:
    """``(mean, tau, Q / dof)``: the DerSimonian-Laird between-item std ``tau`` of estimates ``g
    [k]`` with stds ``g_std [k]`` (NaN where k < 2), the weighted mean and Cochran's Q per degree of
    freedom (``k - 1``)."""
    g, s = np.asarray(g, dtype=np.float64), np.asarray(g_std, dtype=np.float64)
    if g.size < 2:
        return math.nan, math.nan, math.nan
    w = 1.0 / s**2
    mean = float(np.sum(w * g) / np.sum(w))
    q = float(np.sum(w * (g - mean) ** 2))
    denom = float(np.sum(w) - np.sum(w**2) / np.sum(w))
    tau2 = max(0.0, (q - (g.size - 1)) / denom) if denom > 0 else 0.0
    return mean, math.sqrt(tau2), q / (g.size - 1)


def slope_gains(D0, D0_std, G, dc_gain, lit) -> SlopeGains:
    """The rows' gains and their scatter (module docstring).

    Args:
        D0, D0_std: ``[S, N]`` the measured static columns and their stds (px per input unit;
            entries with std 0 or NaN are left out: off a sparse plan's support, dead columns).
        G: ``[S, N]`` the geometry the actuators were fitted on (the fitted registration's).
        dc_gain: ``[N]`` the actuators' gains against ``G`` (NaN: left out).
        lit: ``[S]`` bool, the rows of fully lit subapertures.
    """
    D0, s, G = (np.asarray(x, dtype=np.float64) for x in (D0, D0_std, G))
    a, lit = np.asarray(dc_gain, dtype=np.float64), np.asarray(lit, dtype=bool)
    if D0.ndim != 2 or s.shape != D0.shape or G.shape != D0.shape or a.shape != D0.shape[1:] or lit.shape != D0.shape[:1]:
        raise ShapeError(f"D0, D0_std, G: expected [S, N], dc_gain [N], lit [S]; got {D0.shape}, {s.shape}, {G.shape}, "
                         f"{a.shape}, {lit.shape}")
    wt = whitened(D0, s)[1]
    good = (wt > 0) & np.isfinite(a)[None] & np.isfinite(G)
    w = np.where(good, wt * wt, 0.0)
    X = np.where(good, G * np.nan_to_num(a)[None], 0.0)
    den = np.sum(X * X * w, 1)
    seen = den > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(seen, np.sum(X * np.nan_to_num(D0) * w, 1) / den, np.nan)
        g_std = np.where(seen, 1.0 / np.sqrt(den), np.nan)
    tau, qd, n = {}, {}, {}
    for name, sel in (("lit", lit & seen), ("edge", ~lit & seen)):
        _, t, q = random_effects_scatter(g[sel], g_std[sel])
        tau[name], qd[name], n[name] = (0.0 if not math.isfinite(t) else t), q, int(sel.sum())
    tau_r = np.where(lit, tau["lit"], tau["edge"])
    Wp = np.where(good, G * G * w, 0.0)
    tot = Wp.sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(tot > 0, np.sqrt(np.sum((Wp / np.where(tot > 0, tot, 1.0)) ** 2 * tau_r[:, None] ** 2, 0)), 0.0)
    return SlopeGains(gain=g, gain_std=g_std, lit=lit, tau=tau, q_over_dof=qd, n_rows=n, dc_gain_share=share)


def with_slope_gain_stds(table, gains: SlopeGains):
    """``table`` (an :class:`~torchblur.dm.actuator_fit.ActuatorTable`) with every ``dc_gain_std``
    grown by the rows' gain scatter: ``sqrt(std^2 + (dc_gain * dc_gain_share)^2)`` (NaN gains kept),
    and the statuses decided again from the grown stds
    (:func:`~torchblur.dm.actuator_fit.with_dc_gain_variance`)."""
    add = np.nan_to_num(np.asarray(table.dc_gain, dtype=np.float64)) * gains.dc_gain_share
    return with_dc_gain_variance(table, add**2)


def slope_gains_line(gains: SlopeGains) -> str:
    """The report's line on the rows' gains, and what the grown stds still leave out."""
    names = {"lit": "fully lit subapertures", "edge": "edge subapertures"}
    parts = [f"{names[name]} {gains.tau[name] * 100:.3f} % (Q/dof {gains.q_over_dof[name]:.2f} over {gains.n_rows[name]} rows)"
             for name in ("lit", "edge") if gains.n_rows[name] >= 2]
    if not parts:
        return "dm slope gains: fewer than 2 slope rows of D0 in each group: not measured, no dc_gain std changed"
    share = gains.dc_gain_share[gains.dc_gain_share > 0]
    tail = (f"every dc_gain std includes its share (median {np.median(share) * 100:.3f} %, largest {share.max() * 100:.3f} %)"
            if share.size else "no dc_gain std changed")
    return ("dm slope gains: the slope rows of D0 scale about the fitted geometry beyond their noise by tau = " + ", ".join(parts)
            + f"; {tail}; a gain common to every row, and the part of the rows' gains the actuators' own gains absorb, are not in "
            "the stds")
