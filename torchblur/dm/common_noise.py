"""The ladder's static-shift noise in the static columns D0: an error common to every frequency.

The ladder spot model (:mod:`torchblur.dm.ladder_fit`) reports spot ``m``'s motion under pattern
``p`` as ``s G + N n``: ``s`` (px per input unit) the spot's static shift per unit command, from
the pattern's held levels (:func:`~torchblur.dm.ladder_fit.static_slope`), one ``s`` for every
frequency of that (pattern, spot). Its noise ``delta_s`` (:func:`~torchblur.dm.ladder_fit.slope_covariance`)
moves the response ``Y[p, row, f]`` by ``delta_s_a G_f`` at every frequency alike. Each spot fit's
covariance holds it once, so no single frequency's std is short; but the actuator fit, taking the
frequencies as independent, averages it down in the static column ``D0[row, j]`` (the DC value
fitted over every frequency) and in ``dc_gain``, which it does not average. On HCIPy's lenslet
frames (the whole grid, 16 frequencies x 6 repeats) that left the measured D0's stds short by a
factor of about 2.5 at the brightest entries (docs/deformable_mirrors.md, "The ladder's common
error").

:func:`static_column_variance` gives that error's variance in D0. At zero frequency the command
phasor ``G_0`` of (pattern, spot) is read from the measured D0 itself, ``G_0 = s . Y0 / |s|^2``,
``Y0 = patterns D0^T`` (the pattern's static response; where the spot barely moves, ``|s|^2 <
9 trace cov(s)``, its pattern's median over the spots that do); the variance ``cov(s)_aa G_0^2``
of each (pattern, slope row) goes through the demultiplexing's map (ordinary least squares per
row over its support, :func:`~torchblur.dm.demux.demultiplex`, the map weighted least squares
takes where the patterns' stds are alike) into ``D0``. :func:`with_common_variance` adds it to an
:class:`~torchblur.dm.actuator_fit.ActuatorTable`'s ``static_column_std`` and, through the
projection on ``G`` that defines ``dc_gain``, to ``dc_gain_std`` (statuses decided again). Left
out: the ladder's noise through the fit itself (``dtheta = -C J^T W dY/dL dL``), also shared by the
frequencies but through a sensitivity that changes with the motion; the x-y correlation of one
spot's ``s``.

Shapes: P patterns, M spots, S = 2M slopes (x of all M, then y), N actuators.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from torchblur.dm.actuator_fit import with_dc_gain_variance
from torchblur.dm.demux import demultiplex
from torchblur.errors import ShapeError

__all__ = ["common_noise_line", "static_column_variance", "with_common_variance", "MOVING_SNR2"]

#: a spot moves under a pattern when ``|s|^2`` exceeds this many times ``trace cov(s)``
MOVING_SNR2 = 9.0


def _dc_commands(slope, slope_cov, Y0) -> np.ndarray:
    """``[P, M]`` each (pattern, spot)'s command at zero frequency, ``s . Y0 / |s|^2``, its
    pattern's median over the moving spots where the spot barely moves (0 where none moves)."""
    s2 = (slope * slope).sum(-1)
    moving = s2 > MOVING_SNR2 * np.trace(slope_cov, axis1=-2, axis2=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(moving, (slope * Y0).sum(-1) / np.where(moving, s2, 1.0), np.nan)
    med = np.array([np.median(r[np.isfinite(r)]) if np.isfinite(r).any() else 0.0 for r in g])
    return np.where(np.isfinite(g), g, med[:, None])


def static_column_variance(slope, slope_cov, patterns, support, D0) -> np.ndarray:
    """``[S, N]`` (px per input unit)^2: the variance the ladder's ``s`` adds to the static columns
    (module docstring); 0 off a sparse plan's support.

    Args:
        slope: ``[P, M, 2]`` each (pattern, spot)'s static shift per unit command (px).
        slope_cov: ``[P, M, 2, 2]`` its covariance (:func:`~torchblur.dm.ladder_fit.slope_covariance`).
        patterns: ``[P, N]`` the plan's patterns.
        support: ``[S, N]`` bool or None (every actuator), as :func:`~torchblur.dm.demux.demultiplex`.
        D0: ``[S, N]`` the measured static columns (px per input unit; NaN entries read as 0).
    """
    s, C = np.asarray(slope, dtype=np.float64), np.asarray(slope_cov, dtype=np.float64)
    A, D0 = np.asarray(patterns, dtype=np.float64), np.asarray(D0, dtype=np.float64)
    P, M = s.shape[:2]
    if s.shape != (P, M, 2) or C.shape != (P, M, 2, 2) or A.shape[0] != P or D0.shape != (2 * M, A.shape[1]):
        raise ShapeError(f"slope [P, M, 2], slope_cov [P, M, 2, 2], patterns [P, N], D0 [2M, N]: got {s.shape}, {C.shape}, "
                         f"{A.shape}, {D0.shape}")
    Y0 = A @ np.nan_to_num(D0).T  # [P, 2M]
    g0 = _dc_commands(s, C, np.stack([Y0[:, :M], Y0[:, M:]], -1))
    var = np.concatenate([C[..., 0, 0], C[..., 1, 1]], 1) * np.concatenate([g0, g0], 1) ** 2  # [P, 2M]
    var = np.maximum(np.nan_to_num(var), np.finfo(np.float64).tiny)
    cov = np.zeros((P, 2 * M, 1, 2, 2))
    cov[..., 0, 0, 0] = cov[..., 0, 1, 1] = var
    _, D_cov = demultiplex(np.zeros((P, 2 * M, 1), dtype=np.complex128), cov, A, support, method="ols")
    return np.nan_to_num(D_cov[:, :, 0, 0, 0])


def with_common_variance(table, var, G):
    """``table`` with ``static_column_std`` grown to ``sqrt(std^2 + var)`` (``var [S, N]``,
    :func:`static_column_variance`) and ``dc_gain_std`` by that variance projected as ``dc_gain``
    is, ``sum_s (G_sj / std_sj^2)^2 var_sj / (sum_s G_sj^2 / std_sj^2)^2`` times ``dc_gain``'s scale
    (the static column's stds before growing; statuses decided again,
    :func:`~torchblur.dm.actuator_fit.with_dc_gain_variance`)."""
    var, G = np.asarray(var, dtype=np.float64), np.asarray(G, dtype=np.float64)
    std = np.asarray(table.static_column_std, dtype=np.float64)
    if var.shape != std.shape or G.shape != std.shape:
        raise ShapeError(f"var, G: expected [S, N] = {std.shape}, got {var.shape}, {G.shape}")
    ok = np.isfinite(std) & (std > 0) & np.isfinite(G)
    v = np.where(ok, var, 0.0)
    w = np.where(ok, G / np.where(ok, std, 1.0) ** 2, 0.0)
    den = (w * G).sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        add = np.where(den > 0, (w * w * v).sum(0) / np.where(den > 0, den, 1.0) ** 2, 0.0)
    grown = replace(table, static_column_std=np.where(ok, np.sqrt(std**2 + v), std))
    return with_dc_gain_variance(grown, add)


def common_noise_line(var, table) -> str:
    """The report's line on the ladder's common error: how much it grew the static columns' stds
    (``table`` after :func:`with_common_variance`)."""
    var = np.asarray(var, dtype=np.float64)
    std = np.asarray(table.static_column_std, dtype=np.float64)
    on = np.isfinite(std) & (std > 0) & (var > np.finfo(np.float64).tiny) & (std**2 > var)
    if not on.any():
        return "dm ladder common error: none on the measured entries (no static column's std changed)"
    f = std[on] / np.sqrt(std[on] ** 2 - var[on])
    return (f"dm ladder common error: the ladder's static shifts' noise, common to every frequency of a spot, grows the static "
            f"columns' stds by x{np.median(f):.3f} (median; largest x{f.max():.2f}, over {int(on.sum())} entries) and each "
            f"dc_gain std by its projection (the held frames' noise from the camera's noise model, to first order; the ladder's "
            f"noise through the fit itself is not in it: docs/deformable_mirrors.md, \"The ladder's common error\")")
