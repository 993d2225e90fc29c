"""The mirror's registration on the Shack-Hartmann sensor, fitted to the measured static
interaction matrix D0 (issue 23: the geometry measured, not assumed).

:class:`Registration` places actuator j at ``p_j = magnification R(rotation) x_j + (shift_x,
shift_y)`` in the sensor's frame (nominal actuator pitches, x right, y down; a positive rotation
turns +x toward +y), its influence function ``magnification`` times wider there. The geometry
matrix mixes the mean slope and the diffraction spot's weighting, ``(1 - beta) G_mean + beta
G_diffraction`` (``diffraction_weight``); :func:`fit_registration` fits it to D0 by variable
projection (one gain per actuator in closed form), refits on the fully lit subapertures where the
model rule fails, and runs the edge test on the :func:`interior` ones. ``dc_gain``
(:data:`DC_GAIN_REFERENCE`) is relative to the fitted influence function's peak. The model, the
fit, the weighting, the edge test and their measured figures: docs/deformable_mirrors.md, "The
mirror's registration".

Shapes: S = 2M slopes (x of all M subapertures, then y), N actuators, Q quadrature points.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from torchblur.dm.actuator_fit import fit_actuators, with_dc_gain_variance
from torchblur.dm.mirror import influence_width
from torchblur.dm.plans import seen_by
from torchblur.dm.shack_hartmann import lit_rows
from torchblur.errors import ConfigError, ParameterError, ShapeError, check_real_scalar
from torchblur.sysid.frequency_response_io import json_floats
from torchblur.sysid.model_check import model_chi2_limit, model_fails

__all__ = ["Registration", "RegistrationFit", "fit_registration", "register_and_refit", "registration_model", "support_check",
           "support_line", "with_registration_stds", "whitened",
           "write_registration_json", "read_registration_json", "REGISTRATION_SCHEMA", "PARAMETERS", "SENSOR_PARAMETERS",
           "diffraction_quadrature", "fully_lit", "interior", "EDGE_TEST_P", "EDGE_TEST_MIN_INTERIOR",
           "EDGE_GAIN_SHARE"]

#: registration.json's schema and the versions read
REGISTRATION_SCHEMA = ("torchblur.dm.registration", (1,))
#: the fitted parameters, their units in registration.json
PARAMETERS = (("shift_x", "actuator pitch"), ("shift_y", "actuator pitch"), ("rotation_deg", "deg"), ("magnification", "1"),
              ("coupling", "1"))
DC_GAIN_REFERENCE = ("dc_gain is the actuator's static surface per unit command relative to the fitted influence function's peak "
                     "(a Gaussian of the fitted coupling, peak 1 at the actuator): 1 is an actuator whose static column is the geometry "
                     "matrix G at the fitted registration (shift, rotation, magnification, coupling) and sensor weighting "
                     "(diffraction_weight)")
#: the edge test's level (module docstring): high, since the test has little power at a few 1e-3 of noise and a
#: missed bias is silent, while a false alarm only widens stds (and says so)
EDGE_TEST_P = 0.05
#: a gain whose interior rows carry less than this share of its information cannot be tested (module docstring)
EDGE_GAIN_SHARE = 0.1
#: the fewest interior subapertures the edge test runs on
EDGE_TEST_MIN_INTERIOR = 4
#: the sensor's fitted weighting, its unit in registration.json (module docstring: sensor weighting)
SENSOR_PARAMETERS = (("diffraction_weight", "1 (0: mean slope over the subaperture, 1: a fully lit square lenslet's diffraction spot)"),)


@dataclass(frozen=True)
class Registration:
    """The mirror as the sensor sees it (module docstring).

    Attributes:
        shift_x, shift_y: actuator grid's shift on the sensor (nominal actuator pitches; x right, y down).
        rotation_deg: its rotation (degrees, +x toward +y).
        magnification: its scale (1 nominal).
        coupling: the influence functions' coupling at one mirror pitch (None: the mirror's nominal).
    """

    shift_x: float = 0.0
    shift_y: float = 0.0
    rotation_deg: float = 0.0
    magnification: float = 1.0
    coupling: float | None = None

    def __post_init__(self):
        for name in ("shift_x", "shift_y", "rotation_deg"):
            object.__setattr__(self, name, check_real_scalar(getattr(self, name), name))
        object.__setattr__(self, "magnification", check_real_scalar(self.magnification, "magnification", positive=True))
        if self.coupling is not None:
            object.__setattr__(self, "coupling", check_real_scalar(self.coupling, "coupling", positive=True))
            influence_width(self.coupling)  # in (0, 1)

    @classmethod
    def from_config(cls, r) -> "Registration":
        """From ``dm.registration`` (:class:`~torchblur.config.DMRegistrationConfig`)."""
        try:
            return cls(shift_x=r.shift_x, shift_y=r.shift_y, rotation_deg=r.rotation_deg, magnification=r.magnification,
                       coupling=r.coupling)
        except (ParameterError, TypeError, ValueError) as exc:
            raise ConfigError(f"dm.registration.{exc}") from None

    def actuators(self, actuator_xy) -> np.ndarray:
        """``[N, 2]`` the actuators' positions on the sensor (pitches) from the nominal ``[N, 2]``."""
        a = math.radians(self.rotation_deg)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return self.magnification * np.asarray(actuator_xy, dtype=np.float64) @ R.T + np.array([self.shift_x, self.shift_y])

    def sensor_coupling(self, coupling: float) -> float:
        """The coupling at one nominal pitch on the sensor (width ``magnification * w``) of a
        mirror whose coupling is ``coupling`` (replaced by :attr:`coupling` when set)."""
        w = self.magnification * influence_width(coupling if self.coupling is None else self.coupling)
        return math.exp(-1.0 / (2.0 * w * w))


@dataclass(frozen=True, eq=False)
class RegistrationFit:
    """A fitted registration (module docstring).

    Attributes:
        registration: the :class:`Registration` (its ``coupling`` set).
        diffraction_weight: the sensor's weighting beta (module docstring; NaN: not fitted).
        std: ``{parameter: std}`` for :data:`PARAMETERS` and :data:`SENSOR_PARAMETERS` (plus
            ``influence_width``, pitches).
        cov: ``[6, 6]`` covariance of (shift_x, shift_y, rotation rad, magnification, width pitches, beta).
        chi2, dof, reduced_chi2: the fit's chi2 over ``entries - actuators - 6`` degrees of freedom.
        inflated: the stds were multiplied by ``sqrt(reduced_chi2)`` (> 1).
        G: ``[2M, N]`` the geometry matrix at the fitted registration (px per input unit);
            G_std: ``[2M, N]`` its std from the registration's (first order).
        gain: ``[N]`` each actuator's static gain against ``G``; gain_var_registration: ``[N]``
            the share of its variance the registration's uncertainty adds.
        ok: the fit ran (else ``registration`` is the start, ``G`` the start's and ``message`` says why).
        message: why it did not, or how it ended.
        n_entries, n_columns: D0 entries and actuators used.
        fitted_on: "every subaperture", or "the fully lit subapertures" (module docstring).
        gain_jacobian: ``[N, 6]`` d gain / d theta (NaN rows: columns not used).
        edge_test: the edge test (module docstring): ``{"n_interior", "chi2", "dof", "p", "widened",
            "difference", "gains_widened", "gains_unverified"}``, or ``{"n_interior", "message"}`` where it did not run; None: no interior.
    """

    registration: Registration
    diffraction_weight: float
    std: dict
    cov: np.ndarray
    chi2: float
    dof: int
    reduced_chi2: float
    inflated: bool
    G: np.ndarray
    G_std: np.ndarray
    gain: np.ndarray
    gain_var_registration: np.ndarray
    ok: bool
    message: str
    n_entries: int
    n_columns: int
    fitted_on: str = "every subaperture"
    gain_jacobian: np.ndarray | None = None
    edge_test: dict | None = None

    def line(self) -> str:
        """One report line."""
        if not self.ok:
            return f"dm registration: not fitted ({self.message}); dc_gain is relative to the nominal geometry"
        r, s = self.registration, self.std
        return (f"dm registration (fitted to D0): shift x {r.shift_x:+.4f} +- {s['shift_x']:.4f}, y {r.shift_y:+.4f} +- "
                f"{s['shift_y']:.4f} actuator pitches, rotation {r.rotation_deg:+.3f} +- {s['rotation_deg']:.3f} deg, magnification "
                f"{r.magnification:.5f} +- {s['magnification']:.5f}, coupling {r.coupling:.4f} +- {s['coupling']:.4f}, sensor "
                f"weighting {self.diffraction_weight:.3f} +- {s['diffraction_weight']:.3f} (0 mean slope, 1 diffraction spots; fitted "
                f"on {self.n_entries} entries of {self.fitted_on}); reduced chi2 "
                f"{self.reduced_chi2:.3g}{' (stds inflated by its square root)' if self.inflated else ''}{self._judged()}"
                f"{self._edge_line()}; dc_gain "
                f"is relative to the fitted influence function's peak")

    def _judged(self) -> str:
        """The one model rule's word on this fit: empty when it passes."""
        if not model_fails(self.reduced_chi2, self.dof):
            return ""
        return (f"; the mirror model fails the model rule (limit {model_chi2_limit(self.dof):.3g}): these stds and dc_gain's "
                f"reference do not hold")


    def _edge_line(self) -> str:
        """The edge test's word (module docstring): empty when it did not run or passed."""
        e = self.edge_test
        if not e or "chi2" not in e:
            return ""
        out = ""
        if e["widened"]:
            out = (f"; the edge subapertures disagree with the {e['n_interior']} interior ones (chi2 {e['chi2']:.3g} on {e['dof']}, p "
                   f"{e['p']:.2g}: lenslet crosstalk or the pupil's edge): stds widened by the two fits' difference")
        if e["gains_widened"]:
            out += (f"; {len(e['gains_widened'])} actuator gain(s) disagree between the interior and every fitted subaperture: their "
                    f"stds widened by the difference")
        if e["gains_unverified"]:
            out += (f"; the gains of actuators {e['gains_unverified']} rest on the edge subapertures (under "
                    f"{EDGE_GAIN_SHARE:.0%} of their information inside): their stds do not hold")
        return out


def _theta(reg: Registration, coupling: float) -> np.ndarray:
    return np.array([reg.shift_x, reg.shift_y, math.radians(reg.rotation_deg), reg.magnification,
                     influence_width(coupling if reg.coupling is None else reg.coupling)])


def _from_theta(theta) -> Registration:
    w = float(theta[4])
    return Registration(shift_x=float(theta[0]), shift_y=float(theta[1]), rotation_deg=math.degrees(float(theta[2])),
                        magnification=float(theta[3]), coupling=math.exp(-1.0 / (2.0 * w * w)))


def diffraction_quadrature(centres, side: float, pupil_radius: float, nodes: int = 8):
    """The diffraction weighting's quadrature (module docstring: sensor weighting): ``((points
    [M, Q, 2], weight [M, Q]) of the x slopes, (...) of the y slopes)``, points (x, y pitches) over
    the lit part of each subaperture (:func:`~torchblur.dm.shack_hartmann.lit_rows`' rows, ``nodes``
    Gauss-Legendre nodes along each), weights ``K(a) B(b)`` times the quadrature's, summing to 1
    per subaperture (an empty one: 0)."""
    centres = np.asarray(centres, dtype=np.float64)
    g, wg = np.polynomial.legendre.leggauss(nodes)
    out = []
    for axis in (0, 1):
        c = centres[:, ::-1] if axis else centres  # (along, across)
        t, wt, lo, hi = lit_rows(c, side, pupil_radius, nodes)  # [M, K]
        a = lo[..., None] + (hi - lo)[..., None] * (g + 1) / 2  # [M, K, L] along the slope
        ra, rb = (a - c[:, 0, None, None]) / side, (t - c[:, 1, None]) / side
        w = wt[..., None] * (hi - lo)[..., None] / 2 * wg * (5 / 64 - 3 * ra**2 / 8 + ra**4 / 4) * (3 / 4 - rb**2)[..., None]
        pts = np.stack([a, np.broadcast_to(t[..., None], a.shape)], -1)
        pts = pts[..., ::-1] if axis else pts
        w = w.reshape(len(c), -1)
        out.append((pts.reshape(len(c), -1, 2), w / np.where(w.sum(1, keepdims=True) > 0, w.sum(1, keepdims=True), 1.0)))
    return tuple(out)


def _geometry(theta, actuator_xy):
    """``(p [N, 2], dp [5, N, 2], W, dW [5])``: the actuators on the sensor, their influence width
    and the derivatives over (shift_x, shift_y, rotation rad, magnification, width)."""
    sx, sy, a, m, w = (float(v) for v in theta[:5])
    xy = np.asarray(actuator_xy, dtype=np.float64)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    dR = np.array([[-math.sin(a), -math.cos(a)], [math.cos(a), -math.sin(a)]])
    p = m * xy @ R.T + np.array([sx, sy])
    dp = np.stack([np.broadcast_to([1.0, 0.0], p.shape), np.broadcast_to([0.0, 1.0], p.shape), m * xy @ dR.T, xy @ R.T,
                   np.zeros_like(p)])
    return p, dp, m * w, np.array([0.0, 0.0, 0.0, w, m])


def _weighted_slopes(quad, p, dp, W, dW):
    """``(G [2M, N], dG [5, 2M, N])``: the weighted mean slopes of the actuators' influence
    functions over ``quad`` (:func:`diffraction_quadrature`) and their derivatives:
    ``d/dp_b of -d_a phi / W^2 = phi (delta_ab - d_a d_b / W^2) / W^2`` and ``d/dW = phi d_a (2 -
    |d|^2 / W^2) / W^3`` (d = point - actuator)."""
    G, dG = [], []
    for axis, (pts, w) in enumerate(quad):
        d = pts[:, :, None, :] - p  # [M, Q, N, 2]
        r2 = (d * d).sum(-1)
        wphi = w[..., None] * np.exp(-r2 / (2 * W * W))  # [M, Q, N]
        da = d[..., axis]
        Sb = [(wphi * (float(axis == b) - da * d[..., b] / W**2)).sum(1) / W**2 for b in (0, 1)]
        G.append(-(wphi * da).sum(1) / W**2)
        dG.append(Sb[0][None] * dp[:, None, :, 0] + Sb[1][None] * dp[:, None, :, 1]
                  + ((wphi * da * (2 - r2 / W**2)).sum(1) / W**3)[None] * dW[:, None, None])
    return np.concatenate(G), np.concatenate(dG, axis=1)


def registration_model(theta, rows, actuator_xy, slope_px: float, quad=None) -> tuple[np.ndarray, np.ndarray]:
    """The geometry matrix and its derivatives at ``theta`` = (shift_x, shift_y, rotation rad,
    magnification, width pitches[, beta]): ``(G [2M, N], dG [T, 2M, N])``, px per input unit, T
    the length of ``theta``; the rule of :func:`~torchblur.dm.shack_hartmann.mean_slopes` (a
    slope's mean is the difference of the surface at the ends of each lit row), differentiated:
    ``d phi / d p = phi (u - p) / W^2``, ``d phi / d W = phi |u - p|^2 / W^3`` at every row end u;
    with ``beta`` (and ``quad``) mixed with the diffraction weighting as ``(1 - beta) G_mean + beta
    G_diffraction`` (module docstring: sensor weighting).

    Args:
        rows: ``((t, weight, lo, hi) of the x slopes, (...) of the y slopes)``, each ``[M, K]``
            from :func:`~torchblur.dm.shack_hartmann.lit_rows` (the y slopes' on swapped centres).
        actuator_xy: ``[N, 2]`` nominal positions (pitches).
        slope_px: px per unit mean slope.
        quad: :func:`diffraction_quadrature` (needed with ``beta``).
    """
    p, dp, W, dW = _geometry(theta, actuator_xy)
    G, dG = [], []
    for axis, (t, wt, lo, hi) in enumerate(rows):
        area = np.maximum((wt * (hi - lo)).sum(-1), 1e-300)[:, None]
        S = 0.0  # [4, M, N]: sums over the rows of weight * (phi, phi dx / W^2, phi dy / W^2, phi r^2 / W^3), hi end less lo end
        for sign, e in ((1.0, hi), (-1.0, lo)):
            u = np.stack([e, t], -1)[..., ::-1] if axis else np.stack([e, t], -1)  # [M, K, 2] row ends (x, y)
            d = u[:, :, None, :] - p  # [M, K, N, 2]
            r2 = (d * d).sum(-1)
            wphi = wt[..., None] * np.exp(-r2 / (2 * W * W))  # [M, K, N]
            S = S + sign * np.stack([wphi.sum(1), (wphi * d[..., 0]).sum(1) / W**2, (wphi * d[..., 1]).sum(1) / W**2,
                                     (wphi * r2).sum(1) / W**3])
        G.append(S[0] / area)
        dG.append((S[1][None] * dp[:, None, :, 0] + S[2][None] * dp[:, None, :, 1] + S[3][None] * dW[:, None, None]) / area)
    G, dG = np.concatenate(G), np.concatenate(dG, axis=1)
    if len(theta) > 5:
        beta = float(theta[5])
        Gd, dGd = _weighted_slopes(quad, p, dp, W, dW)
        G, dG = (1 - beta) * G + beta * Gd, np.concatenate([(1 - beta) * dG + beta * dGd, (Gd - G)[None]])
    return slope_px * G, slope_px * dG


def fully_lit(wfs) -> np.ndarray:
    """``[M]`` bool: the subapertures whose square lies inside the pupil."""
    c, h = np.abs(wfs.centres), wfs.side / 2
    return np.hypot(c[:, 0] + h, c[:, 1] + h) <= wfs.pupil_diameter / 2 * (1 + 1e-12)


def whitened(D0, D0_std):
    """``(B [S, N], weight [S, N], columns [N] bool)``: D0 / std and 1 / std where the entry is
    usable (finite, std finite and > 0; 0 elsewhere), and the columns with 2 usable entries or more.
    The weights of every least-squares fit to D0 (the registration's, :mod:`torchblur.dm.slope_gains`')."""
    D0, std = np.asarray(D0, dtype=np.float64), np.asarray(D0_std, dtype=np.float64)
    if D0.ndim != 2 or std.shape != D0.shape:
        raise ShapeError(f"D0, D0_std: expected two [2M, N] arrays, got shapes {D0.shape} and {std.shape}")
    good = np.isfinite(D0) & np.isfinite(std) & (std > 0)
    wt = np.where(good, 1.0 / np.where(good, std, 1.0), 0.0)
    return np.where(good, D0, 0.0) * wt, wt, good.sum(0) >= 2


def _projected(theta, model, B, wt):
    """Variable projection at ``theta``: ``(residual [S*N'], Jacobian [S*N', T], gains [N'], dgain [N', T])``."""
    G, dG = model(theta)
    A, dA = G * wt, dG * wt  # [S, N], [5, S, N]
    aa = np.maximum((A * A).sum(0), 1e-300)
    g = (A * B).sum(0) / aa
    r = g * A - B
    gdA = g * dA
    J = gdA - A * ((A * gdA).sum(1) / aa)[:, None, :]  # [T, S, N], Kaufman
    dg = ((dA * B).sum(1) - 2 * g * (A * dA).sum(1)) / aa  # [T, N]
    return r.reshape(-1), J.reshape(len(theta), -1).T, g, dg.T


def fit_registration(D0, D0_std, wfs, actuator_xy, coupling: float, *, start: Registration | None = None) -> RegistrationFit:
    """The registration that best explains the measured static columns (module docstring).

    Args:
        D0, D0_std: ``[2M, N]`` the measured static interaction matrix (px per input unit) and its
            std (entries with std 0, NaN or a NaN value are left out: off a sparse plan's support).
        wfs: the :class:`~torchblur.dm.shack_hartmann.ShackHartmann` sensor.
        actuator_xy: ``[N, 2]`` nominal actuator positions (pitches).
        coupling: the mirror's nominal coupling (the start's width).
        start: where the fit starts (default: nominal).

    Returns:
        :class:`RegistrationFit`; never raises on data: a D0 that cannot constrain the
        registration (fewer entries than unknowns, no usable column) gives ``ok=False`` and the
        start's geometry.
    """
    xy = np.asarray(actuator_xy, dtype=np.float64)
    start = Registration() if start is None else start
    centres, R = wfs.centres, wfs.pupil_diameter / 2
    rows = (lit_rows(centres, wfs.side, R, wfs.oversample), lit_rows(centres[:, ::-1], wfs.side, R, wfs.oversample))
    quad = diffraction_quadrature(centres, wfs.side, R)
    if np.shape(D0) != (2 * wfs.n_valid, xy.shape[0]):
        raise ShapeError(f"D0: expected [2M, N] = [{2 * wfs.n_valid}, {xy.shape[0]}], got {np.shape(D0)}")
    full = lambda th: registration_model(th, rows, xy, wfs.slope_px, quad)  # noqa: E731
    fit = _fit_on(D0, D0_std, full, start, coupling, xy.shape[0])
    lit = np.tile(fully_lit(wfs), 2)[:, None]
    if fit.ok and model_fails(fit.reduced_chi2, fit.dof) and not lit.all():
        inner = _fit_on(D0, np.where(lit, D0_std, np.nan), full, start, coupling, xy.shape[0])
        if inner.ok and inner.reduced_chi2 < fit.reduced_chi2:
            fit, D0_std = replace(inner, fitted_on="the fully lit subapertures"), np.where(lit, D0_std, np.nan)
    return _edge_test(fit, D0, D0_std, full, coupling, wfs, xy.shape[0])


def interior(wfs) -> np.ndarray:
    """``[M]`` bool: the fully lit subapertures whose 8 neighbours are fully lit subapertures."""
    lit, c, s = fully_lit(wfs), np.asarray(wfs.centres, dtype=np.float64), wfs.side
    out = lit.copy()
    for off in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)):
        q = c + np.array(off) * s
        out &= np.abs(q[:, None, :] - c[lit][None]).max(-1).min(1, initial=np.inf) < 1e-6 * s
    return out


def _edge_test(fit, D0, D0_std, full, coupling, wfs, N) -> RegistrationFit:
    """The edge test (module docstring) of ``fit``, fitted on ``D0_std``'s entries."""
    inner = interior(wfs)
    if not fit.ok or inner.sum() < EDGE_TEST_MIN_INTERIOR or inner.all():
        return fit
    rows = np.tile(inner, 2)[:, None]
    inside = _fit_on(D0, np.where(rows, D0_std, np.nan), full, fit.registration, coupling, N, beta0=fit.diffraction_weight)
    if not inside.ok:
        return replace(fit, edge_test={"n_interior": int(inner.sum()), "message": inside.message})
    theta = lambda f: np.append(_theta(f.registration, coupling), f.diffraction_weight)  # noqa: E731
    d = theta(fit) - theta(inside)
    lam, U = np.linalg.eigh(inside.cov / max(1.0, inside.reduced_chi2) - fit.cov / max(1.0, fit.reduced_chi2))
    keep = lam > 1e-9 * lam.max()
    if not keep.any():  # every fitted entry is an interior one: nothing to compare
        return replace(fit, edge_test={"n_interior": int(inner.sum()), "message": "no fitted subaperture outside the interior"})
    chi2 = float(((U[:, keep].T @ d) ** 2 / lam[keep]).sum())
    p = float(stats.chi2.sf(chi2, int(keep.sum())))
    # each actuator's gain on the interior rows against its gain on every fitted row, at the same G
    B, wt, _ = whitened(D0, D0_std)
    A = fit.G * wt
    a_all, a_in = (A * A).sum(0), (A * A * rows).sum(0)
    g_in = (A * B * rows).sum(0) / np.where(a_in > 0, a_in, 1.0)
    dg = np.where(a_in > 0, fit.gain - g_in, 0.0)
    z = dg / np.sqrt(np.maximum(1 / np.where(a_in > 0, a_in, 1.0) - 1 / np.maximum(a_all, 1e-300), 1e-300))
    checkable = np.isfinite(fit.gain) & (a_in >= EDGE_GAIN_SHARE * a_all) & (p < EDGE_TEST_P)
    widen_g = checkable & (np.abs(z) > stats.norm.isf(EDGE_TEST_P / 2))
    unverified = np.isfinite(fit.gain) & ~checkable & (p < EDGE_TEST_P)
    test = {"n_interior": int(inner.sum()), "chi2": chi2, "dof": int(keep.sum()), "p": p, "widened": p < EDGE_TEST_P,
            "difference": dict(zip(("shift_x", "shift_y", "rotation_rad", "magnification", "influence_width", "diffraction_weight"),
                                   d.tolist())), "gains_widened": np.flatnonzero(widen_g).tolist(),
            "gains_unverified": np.flatnonzero(unverified).tolist()}
    cov = fit.cov + np.outer(d, d) if p < EDGE_TEST_P else fit.cov
    x = theta(fit)
    dG = full(x)[1]
    gvar = np.nan_to_num(np.einsum("jk,kl,jl->j", fit.gain_jacobian, cov, fit.gain_jacobian)) + np.where(widen_g, dg * dg, 0.0)
    return replace(fit, edge_test=test, cov=cov, std=_stds(x, cov), G_std=np.sqrt(np.abs(np.einsum("ksj,kl,lsj->sj", dG, cov, dG))),
                   gain_var_registration=gvar)


def _fit_on(D0, D0_std, full, start, coupling, N, beta0: float = 0.0) -> RegistrationFit:
    """:func:`fit_registration` on the entries of ``D0`` with a usable std; ``full``: theta ->
    (G, dG) of every subaperture."""
    B, wt, cols = whitened(D0, D0_std)
    theta0 = np.append(_theta(start, coupling), beta0)
    sub = np.flatnonzero(cols)
    n_entries = int((wt[:, sub] > 0).sum())
    dof = n_entries - sub.size - theta0.size
    if sub.size == 0 or dof < 1:
        return _failed(start, theta0, full, N, f"{n_entries} usable D0 entries over {sub.size} columns: fewer than the "
                                                         f"unknowns", n_entries, int(sub.size))
    part = lambda th: tuple(a[..., sub] for a in full(th))  # noqa: E731
    cache = {}

    def proj(th):
        key = th.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _projected(th, part, B[:, sub], wt[:, sub])
        return cache[key]

    try:
        sol = optimize.least_squares(lambda th: proj(th)[0], theta0, jac=lambda th: proj(th)[1], method="lm", x_scale="jac",
                                     xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    except ValueError as exc:  # a residual that is not finite (a width driven to 0)
        return _failed(start, theta0, full, N, f"the fit failed ({exc})", n_entries, int(sub.size))
    r, J, g_sub, dg = proj(sol.x)
    if not (np.isfinite(sol.x).all() and sol.x[3] > 0 and sol.x[4] > 0 and np.isfinite(r).all()):  # beta may leave [0, 1]
        return _failed(start, theta0, full, N, f"the fit left the model's domain ({sol.message})", n_entries, int(sub.size))
    chi2 = float(r @ r)
    red = chi2 / dof
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((theta0.size,) * 2, np.nan)
    if not (np.isfinite(cov).all() and np.all(np.diag(cov) > 0)):
        return _failed(start, theta0, full, N, "D0 does not determine the registration (singular information matrix)",
                       n_entries, int(sub.size))
    inflated = red > 1
    cov = cov * max(1.0, red)
    gain = np.full(N, np.nan)
    gain[sub] = g_sub
    gvar = np.zeros(N)
    gvar[sub] = np.einsum("jk,kl,jl->j", dg, cov, dg)
    gjac = np.full((N, theta0.size), np.nan)
    gjac[sub] = dg
    G, dG = full(sol.x)
    G_std = np.sqrt(np.abs(np.einsum("ksj,kl,lsj->sj", dG, cov, dG)))
    return RegistrationFit(registration=_from_theta(sol.x), diffraction_weight=float(sol.x[5]), std=_stds(sol.x, cov), cov=cov,
                           chi2=chi2, dof=int(dof),
                           reduced_chi2=float(red), inflated=bool(inflated), G=G, G_std=G_std, gain=gain, gain_var_registration=gvar,
                           ok=True, message=str(sol.message), n_entries=n_entries, n_columns=int(sub.size), gain_jacobian=gjac)


def _stds(theta, cov) -> dict:
    sd = np.sqrt(np.abs(np.diag(cov)))
    w = float(theta[4])
    c = math.exp(-1.0 / (2 * w * w))
    return {"shift_x": float(sd[0]), "shift_y": float(sd[1]), "rotation_deg": math.degrees(float(sd[2])), "magnification": float(sd[3]),
            "coupling": float(c / w**3 * sd[4]), "influence_width": float(sd[4]), "diffraction_weight": float(sd[5])}


def _failed(start, theta0, model, N, why, n_entries, n_columns) -> RegistrationFit:
    nan = {k: math.nan for k, _ in PARAMETERS + SENSOR_PARAMETERS} | {"influence_width": math.nan}
    return RegistrationFit(registration=_from_theta(theta0) if start.coupling is None else start, diffraction_weight=math.nan, std=nan,
                           cov=np.full((theta0.size,) * 2, np.nan),
                           chi2=math.nan, dof=0, reduced_chi2=math.nan, inflated=False, G=model(theta0)[0],
                           G_std=np.full_like(model(theta0)[0], np.nan), gain=np.full(N, np.nan),
                           gain_var_registration=np.zeros(N), ok=False, message=why, n_entries=n_entries, n_columns=n_columns)


def with_registration_stds(table, fit: RegistrationFit):
    """``table`` (an :class:`~torchblur.dm.actuator_fit.ActuatorTable` fitted on ``fit.G``) with
    each ``dc_gain_std`` grown by the registration's share ``sqrt(std^2 + gain_var_registration)``
    and the statuses decided again from the grown stds
    (:func:`~torchblur.dm.actuator_fit.with_dc_gain_variance`)."""
    if not fit.ok:
        return table
    return with_dc_gain_variance(table, fit.gain_var_registration)


def support_check(support, G, threshold: float, G_std=None) -> dict:
    """The plan's support re-checked against the geometry ``G [2M, N]`` (the fitted one): the
    (subaperture, actuator) pairs that :func:`~torchblur.dm.plans.seen_by` at ``threshold`` needs
    and ``support [2M, N]`` lacks (the plan measured them as 0). With ``G_std [2M, N]`` (the
    registration's uncertainty) a pair counts only when its spot motion exceeds the threshold by
    more than 3 stds (``hypot`` of its x and y stds), so that a fit of the nominal mirror does not
    flag the pairs that sit on the threshold. Returns ``{"missing": [[subaperture, actuator],
    ...], "n_missing", "largest_missing_over_max", "threshold"}``."""
    support = np.asarray(support, dtype=bool)
    M = support.shape[0] // 2
    length = np.hypot(G[:M], G[M:])
    margin = 0.0 if G_std is None else 3.0 * np.hypot(G_std[:M], G_std[M:])
    need = seen_by(G, threshold) & (length - margin > threshold * length.max())
    miss = need & ~(support[:M] & support[M:])
    worst = float(length[miss].max() / length.max()) if miss.any() else 0.0
    return {"missing": np.argwhere(miss).tolist(), "n_missing": int(miss.sum()), "largest_missing_over_max": worst,
            "threshold": float(threshold)}


def write_registration_json(path, fit: RegistrationFit, support: dict | None = None) -> None:
    """``registration.json``: the fitted registration, its stds and units, the fit's reduced chi2
    and what ``dc_gain`` is relative to (``schema`` and ``schema_version``: :data:`REGISTRATION_SCHEMA`)."""
    r = fit.registration
    doc = {"schema": REGISTRATION_SCHEMA[0], "schema_version": REGISTRATION_SCHEMA[1][-1], "fitted": bool(fit.ok),
           "message": fit.message, "units": dict(PARAMETERS) | {"influence_width": "actuator pitch"},
           "registration": {k: getattr(r, k) for k, _ in PARAMETERS} | {"influence_width": influence_width(r.coupling)},
           "sensor": {"diffraction_weight": json_floats(fit.diffraction_weight),
                      "units": dict(SENSOR_PARAMETERS), "fitted_on": fit.fitted_on},
           "std": {k: json_floats(v) for k, v in fit.std.items()},
           "reduced_chi2": json_floats(fit.reduced_chi2), "dof": fit.dof,
           "stds_inflated_by_sqrt_reduced_chi2": bool(fit.inflated), "n_entries": fit.n_entries, "n_columns": fit.n_columns,
           "frame": "sensor: p_j = magnification * R(rotation) x_j + shift, nominal actuator pitches, x right, y down, "
                    "rotation +x toward +y",
           "edge_test": fit.edge_test,
           "dc_gain_reference": DC_GAIN_REFERENCE if fit.ok else "dc_gain is relative to the nominal geometry (not fitted)",
           "support_check": support}
    Path(path).write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")


def read_registration_json(path) -> dict:
    """``registration.json`` read back: the document with ``registration`` as a :class:`Registration`.

    Raises:
        ParameterError: naming ``path``, another schema or version, a missing or non-numeric parameter.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ParameterError(f"{path}: not a registration.json ({type(exc).__name__})") from None
    if not isinstance(doc, dict) or doc.get("schema") != REGISTRATION_SCHEMA[0] or doc.get("schema_version") not in REGISTRATION_SCHEMA[1]:
        raise ParameterError(f"{path}: expected schema {REGISTRATION_SCHEMA[0]} version in {REGISTRATION_SCHEMA[1]}")
    reg = doc.get("registration")
    try:
        doc["registration"] = Registration(**{k: reg[k] for k, _ in PARAMETERS})
    except (KeyError, TypeError, ValueError) as exc:
        raise ParameterError(f"{path}: registration: {exc}") from None
    return doc


def register_and_refit(freq_hz, D, D_cov, table, wfs, actuator_xy, coupling: float, *, support=None,
                       threshold: float = 0.01):
    """The run's step after :func:`~torchblur.dm.actuator_fit.fit_actuators` on the nominal G:
    the registration fitted to ``table``'s static columns, the actuators fitted again on the
    fitted G (so ``dc_gain`` is relative to the fitted influence function's peak, its
    std with the registration's share) and the plan's ``support [2M, N]`` re-checked against the
    fitted G (:func:`support_check`; None without a support).

    Returns:
        ``(table, fit, support_info)``: ``table`` unchanged when the fit did not run (``fit.ok`` False).
    """
    fit = fit_registration(table.static_column, table.static_column_std, wfs, actuator_xy, coupling)
    if not fit.ok:
        return table, fit, None
    refit = fit_actuators(freq_hz, D, D_cov, fit.G, actuator_xy=table.actuator_xy)
    info = None if support is None else support_check(support, fit.G, threshold, fit.G_std)
    return with_registration_stds(refit, fit), fit, info


def support_line(info: dict | None) -> str | None:
    """The report's line on the plan's support against the fitted G (None: nothing missing)."""
    if not info or not info["n_missing"]:
        return None
    pairs = ", ".join(f"s{m}/a{j}" for m, j in info["missing"][:8]) + (" ..." if info["n_missing"] > 8 else "")
    return (f"dm plan support: the fitted geometry needs {info['n_missing']} (subaperture, actuator) pair(s) the plan measured as 0 "
            f"({pairs}; largest {info['largest_missing_over_max'] * 100:.2f} % of the largest spot motion, threshold "
            f"{info['threshold'] * 100:g} %): those D entries are biased; choose the plan again on the fitted geometry or use "
            f"dm_plan.kind=hadamard")
