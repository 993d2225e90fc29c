"""Fit a rational transfer function with a pure delay to a measured frequency response.

python-control cannot fit a model to FRD data; this module can. Per channel (output o, input
i) the model is ``H(s) = K prod_k (s - z_k) / prod_k (s - p_k) exp(-s delay_s)``, ``s = j omega``,
with ``n_zeros <= n_poles`` (proper), omega in rad/s and H in the FRF's absolute units. The
method (frequency scaling, Sanathanan-Koerner iteration, delay search, factored nonlinear
polish), the weights, magnitude-only points and the order selection by BIC:
docs/transfer_function_fit.md.
"""
from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Sequence

import numpy as np
import scipy.linalg
import scipy.optimize

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_frequency_grid, check_bool, check_int, check_type,
                              excerpt)
from torchblur.sysid.frequency_response import FrequencyResponse, control_names
from torchblur.sysid.frequency_response_io import read_json_doc, write_json_doc
from torchblur.sysid.model_io import tf_fit_fields_from_dict, tf_fit_to_dict

__all__ = ["fit_transfer_function", "TransferFunctionFit"]

_WEIGHT_MODES = ("uncertainty", "uniform")
_MODAL_KINDS = ("poles", "zeros")
_DELAY_FORMS = (None, "pade", "frd")
_FLOOR_RTOL = 1e-9
_GRID_SK_ITER = 6
_PATIENCE = 6
_SCAN_NFEV = 8  # polish budget per parameter while comparing orders
_FINAL_NFEV = 100  # and for the chosen order


# ----------------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True, eq=False)
class TransferFunctionFit:
    """Result of :func:`fit_transfer_function`.

    Per-channel fields are plain values for a SISO FRF and nested lists ``[O][I]`` for MIMO
    (``field[o][i]`` = the value for output o, input i).

    Attributes:
        num: numerator coefficients of s (rad/s), highest power first, FRF units.
        den: denominator coefficients, highest power first, monic (den[0] == 1).
        delay_s: pure delay in seconds (not part of ``num``/``den``).
        n_poles, n_zeros: model orders.
        chi2: weighted sum of squares ``sum_f e_f^T e_f`` (docs/transfer_function_fit.md).
        dof: degrees of freedom, ``2 * n_points - n_parameters`` (real observations minus
            real parameters: K, the n_zeros + n_poles factor coefficients, and the delay if
            it was estimated).
        reduced_chi2: ``chi2 / dof`` (about 1 for a right model and right covariance).
        rms_relative_error: ``sqrt(mean_f |H_model - H|^2 / |H|^2)`` over the fitted points.
        poles, zeros: complex arrays in rad/s.
        dc_gain: H(0) (the delay does not change it); +-inf for a pole at 0.
        weighting: "uncertainty", "uniform" or "array" (the weighting actually used).
        delay_estimated: whether the delay was a free parameter.
        input_labels, output_labels: channel names from the FRF.
        param_names: the model's parameters in natural units:
            ``"dc_gain"`` (FRF units), per quadratic factor of the poles ``"p{k}_omega_n"``
            (rad/s) and ``"p{k}_zeta"`` (sorted by omega_n; zeta >= 1 is a pair of real poles),
            per linear factor ``"p{k}_rate"`` (rad/s, the pole is at -rate), the same for the
            zeros with ``"z"`` (a quadratic zero factor with a non-positive constant term as
            ``"z{k}_a1"`` rad/s, ``"z{k}_a0"`` rad^2/s^2 of ``s^2 + a1 s + a0``), and
            ``"delay_s"`` when estimated.
        params: [P] their values.
        covariance: [P, P] their covariance: the weighted least-squares Jacobian's
            ``(J^T J)^-1`` at the optimum (Gauss-Newton), carried to the natural parameters by
            the delta method; with ``weighting="uncertainty"`` (the noise scale known) as it
            is, otherwise scaled by ``reduced_chi2`` (the noise estimated from the residuals).
            NaN where ``J`` is rank deficient (a parameter the data do not determine).
        std: [P] ``sqrt(diag(covariance))``.
        candidates: the orders compared (:func:`fit_transfer_function`'s order selection):
            dicts ``{"n_poles", "n_zeros", "n_params", "chi2", "dof", "reduced_chi2", "bic",
            "chosen"}`` in the order tried (the scan's chi2 after a short polish; the chosen
            one's after the full polish). One row when both orders were given.
        order_criterion: how the order was chosen (``"BIC"``, or ``"fixed"``).
    """

    num: list
    den: list
    delay_s: Any
    n_poles: Any
    n_zeros: Any
    chi2: Any
    dof: Any
    reduced_chi2: Any
    rms_relative_error: Any
    poles: Any
    zeros: Any
    dc_gain: Any
    weighting: str
    delay_estimated: bool
    input_labels: tuple[str, ...]
    output_labels: tuple[str, ...]
    param_names: Any = ()
    params: Any = None
    covariance: Any = None
    std: Any = None
    candidates: Any = ()
    order_criterion: str = "BIC"

    @property
    def is_siso(self) -> bool:
        return len(self.input_labels) == 1 and len(self.output_labels) == 1

    def _channels(self, field):
        """Field as nested [O][I] (wrapping the SISO value)."""
        v = getattr(self, field)
        return [[v]] if self.is_siso else v

    def to_control(self, *, delay: str | None = None, pade_order: int = 5, omega=None, name: str = "model"):
        """The fitted model as a python-control system, named, with the FRF's channel labels.

        Args:
            delay: how the pure delay enters (python-control has no pure-delay transfer
                function):

                - ``None`` (default): left out; a ``control.TransferFunction`` of the
                  rational part ``num / den`` (multiply its response by
                  ``exp(-1j * omega * delay_s)``, or use :meth:`frequency_response`);
                - ``"pade"``: a ``control.TransferFunction`` of the rational part times
                  ``control.pade(delay_s, pade_order)`` (per channel for MIMO);
                - ``"frd"``: a ``control.FrequencyResponseData`` of the exact model, delay
                  included, on the grid ``omega`` (required).
            pade_order: order of the Pade approximation (an int >= 1), used with
                ``delay="pade"``.
            omega: [F] rad/s, strictly increasing, > 0: the grid of ``delay="frd"``.
            name: the system's name (python-control's ``bode_plot`` legends use it).

        Returns:
            ``control.TransferFunction`` or ``control.FrequencyResponseData`` with
            ``inputs=input_labels``, ``outputs=output_labels`` (names python-control refuses
            mapped by :func:`~torchblur.sysid.frequency_response.control_names`); 1x1 for
            SISO, OxI for MIMO.

        Raises:
            ParameterError: ``delay`` not one of ``{None, "pade", "frd"}``; ``pade_order``
                < 1; ``delay="frd"`` without ``omega``.
            InputTypeError: ``pade_order`` not an int, ``name`` not a string.
        """
        import control

        if delay not in _DELAY_FORMS:
            raise ParameterError(f"delay: must be one of {set(_DELAY_FORMS)}, got {excerpt(delay)}")
        check_type(name, "name", str, "a string")
        pade_order = check_int(pade_order, "pade_order", low=1)
        labels = dict(inputs=control_names(self.input_labels), outputs=control_names(self.output_labels), name=control_names([name])[0])
        if delay == "frd":
            if omega is None:
                raise ParameterError("omega: delay='frd' needs the frequency grid omega [F] (rad/s)")
            w = as_frequency_grid(omega, "omega")
            return control.frd(self.frequency_response(w), w, **labels)

        def channel(n, d, t):
            g = control.tf(list(n), list(d))
            return g * control.tf(*control.pade(float(t), pade_order)) if delay == "pade" and t > 0 else g

        rows = zip(*(self._channels(f) for f in ("num", "den", "delay_s")))
        return control.combine_tf([[channel(*c) for c in zip(*row)] for row in rows], **labels)

    def frequency_response(self, omega) -> np.ndarray:
        """Evaluate the fitted model, delay included, at ``s = j omega``.

        Args:
            omega: [F] angular frequencies, rad/s (finite).

        Returns:
            complex [F] (SISO) or [O, I, F]: ``K prod(s - z) / prod(s - p) exp(-s delay_s)``.
        """
        w = as_frequency_grid(omega, "omega")
        s = 1j * w
        num, den, z, p, tau = (self._channels(f) for f in ("num", "den", "zeros", "poles", "delay_s"))
        out = np.empty((len(self.output_labels), len(self.input_labels), w.size), dtype=np.complex128)
        for o in range(out.shape[0]):
            for i in range(out.shape[1]):
                gain = num[o][i][0] / den[o][i][0]
                h = np.full(w.size, gain, dtype=np.complex128)
                for zk in z[o][i]:
                    h *= s - zk
                for pk in p[o][i]:
                    h /= s - pk
                out[o, i] = h * np.exp(-s * tau[o][i])
        return out[0, 0] if self.is_siso else out

    def phase_std(self, omega, o: int = 0, i: int = 0) -> np.ndarray:
        """The std (rad) of the model's phase at ``omega`` (rad/s, ``[F]``) from the parameters'
        :attr:`covariance` (delta method, central differences over :attr:`params`), channel
        (o, i); NaN where the covariance is unknown."""
        w = as_frequency_grid(omega, "omega")
        names, vals, _ = self.channel_parameters(o, i)
        cov = np.asarray(self._channels("covariance")[o][i], dtype=np.float64) if names else None
        if cov is None or not np.all(np.isfinite(cov)):
            return np.full(w.size, math.nan)
        tau = float(self._channels("delay_s")[o][i])
        jac = np.empty((w.size, vals.size))
        for p in range(vals.size):
            d = np.zeros(vals.size)
            d[p] = 1e-6 * max(abs(float(vals[p])), 1e-9)
            with np.errstate(all="ignore"):
                ratio = _natural_response(names, vals + d, w, tau) / _natural_response(names, vals - d, w, tau)
            jac[:, p] = np.angle(ratio) / (2 * d[p])
        var = np.einsum("fp,pq,fq->f", jac, cov, jac)
        return np.sqrt(np.where(var >= 0, var, math.nan))

    def modal_parameters(self, kind: str = "poles"):
        """Natural frequency and damping ratio of each complex pair of poles (or zeros).

        Args:
            kind: "poles" (resonances) or "zeros" (anti-resonances).

        Returns:
            SISO: a list, sorted by frequency, of dicts ``{"omega_n": rad/s, "freq_hz": Hz,
            "zeta": damping ratio, "omega_n_std", "freq_hz_std", "zeta_std"}`` with
            omega_n = |p| and zeta = -Re(p) / |p|, one per pair p, conj(p) with Im p > 0 (real
            roots are left out); the stds from :attr:`covariance` (NaN where unknown). MIMO:
            nested lists [O][I].
        """
        if kind not in _MODAL_KINDS:
            raise ParameterError(f"kind: must be one of {set(_MODAL_KINDS)}, got {excerpt(kind)}")
        roots = self._channels(kind)
        out = [[_modes(roots[o][i], kind[0], *self.channel_parameters(o, i)) for i in range(len(self.input_labels))]
               for o in range(len(self.output_labels))]
        return out[0][0] if self.is_siso else out

    def channel_parameters(self, o: int = 0, i: int = 0) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
        """``(param_names, params [P], std [P])`` of channel (output o, input i); empty when
        the fit carries no covariance (a fit built by hand, or read from an older file)."""
        if self.params is None:
            return (), np.zeros(0), np.zeros(0)
        names, vals, std = (self._channels(f)[o][i] for f in ("param_names", "params", "std"))
        return tuple(names), np.asarray(vals, dtype=np.float64), np.asarray(std, dtype=np.float64)

    def parameter(self, name: str, o: int = 0, i: int = 0) -> tuple[float, float]:
        """``(value, std)`` of the named natural parameter of channel (o, i) (see
        :attr:`param_names`); ``(nan, nan)`` when the fit has no such parameter."""
        names, vals, std = self.channel_parameters(o, i)
        if name not in names:
            return math.nan, math.nan
        k = names.index(name)
        return float(vals[k]), float(std[k])

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict: coefficients, delay, orders, fit statistics, roots, the
        parameters' uncertainty (:func:`~torchblur.sysid.model_io.tf_fit_to_dict`).

        Roots are ``{"real": [...], "imag": [...]}``; non-finite numbers become ``None``.
        Per-channel values are nested [O][I] for MIMO as in the attributes.
        """
        return tf_fit_to_dict(self)

    @classmethod
    def from_dict(cls, doc: dict) -> "TransferFunctionFit":
        """Inverse of :meth:`to_dict` (checks ``schema``, ``schema_version`` and the keys of that
        version: ``torchblur.sysid.model_io.TF_SCHEMA_KEYS``; version 1 files, without ``units``, read too).

        Also reads the CLI's model.json, which adds ``torchblur_version``, ``seed``,
        ``left_out_points`` and ``poor_fit_points_kept`` beside the fit (checked, not kept).
        ``None`` reads back as NaN, except ``dc_gain``, recomputed from ``num`` and ``den`` (a
        pole at 0 gives +-inf, which JSON cannot hold).

        Raises:
            InputTypeError: ``doc`` is not a dict.
            ParameterError: another schema (a direct fit, or a failed fit's ``error``), an
                unsupported version, keys unknown to its version or missing, malformed values.
        """
        fields = tf_fit_fields_from_dict(doc)
        if len(fields["input_labels"]) == len(fields["output_labels"]) == 1:
            dc = _dc_gain(fields["num"], fields["den"])
        else:
            dc = [[_dc_gain(n, d) for n, d in zip(nr, dr)] for nr, dr in zip(fields["num"], fields["den"])]
        return cls(**fields, dc_gain=dc)

    def to_json(self, path: str | os.PathLike) -> None:
        """Write :meth:`to_dict` to a strict JSON file (read it back with :meth:`from_json`)."""
        write_json_doc(self.to_dict(), path, indent=2)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> "TransferFunctionFit":
        """Read a file written by :meth:`to_json`, or the CLI's model.json (two-step fit;
        with ``model.direct`` it is model_two_step.json); errors name ``path``
        (:func:`~torchblur.sysid.frequency_response_io.read_json_doc`)."""
        return read_json_doc(path, cls.from_dict, "model.json")

    def __repr__(self) -> str:
        if self.is_siso:
            return (
                f"TransferFunctionFit(n_poles={self.n_poles}, n_zeros={self.n_zeros}, "
                f"delay_s={self.delay_s:.4g}, reduced_chi2={self.reduced_chi2:.4g})"
            )
        return f"TransferFunctionFit({len(self.output_labels)}x{len(self.input_labels)} channels)"


def _dc_gain(num, den) -> float:
    """H(0) = num[-1] / den[-1]; +-inf for a pole at 0 (sign of num[-1]), NaN for 0/0."""
    if den[-1] != 0:
        return float(num[-1] / den[-1])
    return math.copysign(math.inf, num[-1]) if num[-1] else math.nan


def _natural_response(names, vals: np.ndarray, omega: np.ndarray, delay_s: float) -> np.ndarray:
    """H(j omega) ``[F]`` from natural parameters (:attr:`TransferFunctionFit.param_names`;
    ``delay_s`` where the delay is not among them): the DC gain times each zero factor over its
    value at 0, over each pole factor's."""
    s, p = 1j * omega, dict(zip(names, vals))
    h = np.full(omega.size, p["dc_gain"], dtype=np.complex128)
    for name, v in p.items():
        pre, _, kind = name.partition("_")
        if kind == "omega_n":
            f = (s * s + 2 * p[f"{pre}_zeta"] * v * s + v * v) / (v * v)
        elif kind == "a1":
            f = (s * s + v * s + p[f"{pre}_a0"]) / p[f"{pre}_a0"]
        elif kind == "rate":
            f = (s + v) / v
        else:
            continue
        h = h * f if pre[0] == "z" else h / f
    return h * np.exp(-s * p.get("delay_s", delay_s))


def _modes(roots: np.ndarray, prefix: str = "p", names=(), vals=None, std=None) -> list[dict[str, float]]:
    """The complex pairs of ``roots`` as mode dicts, with the stds of the natural parameters
    ``{prefix}{k}_omega_n`` / ``_zeta`` of the same factor (matched by omega_n) where known."""
    factors = [(float(vals[j]), float(std[j]), float(std[j + 1])) for j, n in enumerate(names)
               if n.startswith(prefix) and n.endswith("_omega_n")]
    modes = []
    for r in np.asarray(roots, dtype=np.complex128):
        if r.imag > 0:
            wn = float(abs(r))
            sd = min(factors, key=lambda f: abs(f[0] - wn), default=(wn, math.nan, math.nan))
            if not abs(sd[0] - wn) <= 1e-6 * wn:
                sd = (wn, math.nan, math.nan)
            modes.append({"omega_n": wn, "freq_hz": wn / (2.0 * np.pi), "zeta": float(-r.real / wn),
                          "omega_n_std": sd[1], "freq_hz_std": sd[1] / (2.0 * np.pi), "zeta_std": sd[2]})
    return sorted(modes, key=lambda m: m["omega_n"])


# ----------------------------------------------------------------------- channel data
@dataclasses.dataclass
class _Data:
    """Valid points of one channel with their whitening, and the frequency scale."""

    omega: np.ndarray  # [N] rad/s
    h: np.ndarray  # [N] complex
    w00: np.ndarray  # [N] whitening W = [[w00, 0], [w10, w11]] applied to (Re r, Im r)
    w10: np.ndarray
    w11: np.ndarray
    wsc: np.ndarray  # [N] scalar weight for the linear SK steps (0 at a magnitude-only point)
    scale: float  # omega_s, rad/s
    mag_only: np.ndarray | None = None  # [N] bool: the point's phase is unknown, its magnitude fitted alone
    wm: np.ndarray | None = None  # [N] 1 / std of a magnitude-only point's magnitude

    @property
    def sp(self) -> np.ndarray:
        return 1j * self.omega / self.scale

    @property
    def wp(self) -> np.ndarray:
        return self.omega / self.scale

    @property
    def n_obs(self) -> int:
        return 2 * self.omega.size - (0 if self.mag_only is None else int(self.mag_only.sum()))


@dataclasses.dataclass
class _Cand:
    n_zeros: int
    n_poles: int
    theta: np.ndarray
    est_tau: bool
    tau_fixed: float  # seconds, used when not est_tau
    chi2: float

    @property
    def n_params(self) -> int:
        return self.theta.size


# --------------------------------------------------------------------- model algebra
def _split(theta, nz, npo):
    i = 1
    zq = theta[i:i + 2 * (nz // 2)].reshape(-1, 2)
    i += 2 * (nz // 2)
    zl = theta[i:i + nz % 2]
    i += nz % 2
    pq = theta[i:i + 2 * (npo // 2)].reshape(-1, 2)
    i += 2 * (npo // 2)
    pl = theta[i:i + npo % 2]
    i += npo % 2
    return theta[0], zq, zl, pq, pl, theta[i:]


def _model(theta, nz, npo, est_tau, tau_fixed, data: _Data, jac: bool):
    """H_model at the data points [N] (and dH/dtheta [N, P] if jac)."""
    sp = data.sp[:, None]
    k, zq, zl, pq, pl, rest = _split(theta, nz, npo)
    qz = sp * (sp + zq[:, 0]) + zq[:, 1]  # [N, nz // 2]
    lz = sp + zl  # [N, nz % 2]
    qp = sp * (sp + pq[:, 0]) + pq[:, 1]
    lp = sp + pl
    g = np.prod(qz, axis=1) * np.prod(lz, axis=1) / (np.prod(qp, axis=1) * np.prod(lp, axis=1))
    taup = rest[0] if est_tau else tau_fixed * data.scale
    ge = g * np.exp(-1j * data.wp * taup)
    hm = k * ge
    if not jac:
        return hm, None
    n = sp.shape[0]
    iqz, iqp = 1.0 / qz, 1.0 / qp
    dlog = np.concatenate(
        [
            np.stack([sp * iqz, iqz], axis=2).reshape(n, -1),
            1.0 / lz,
            -np.stack([sp * iqp, iqp], axis=2).reshape(n, -1),
            -1.0 / lp,
        ],
        axis=1,
    )
    cols = [ge[:, None], hm[:, None] * dlog]
    if est_tau:
        cols.append((-1j * data.wp * hm)[:, None])
    return hm, np.concatenate(cols, axis=1)


def _whiten(r: np.ndarray, data: _Data) -> np.ndarray:
    """[N] complex (or [N, P]) -> stacked real [2N] (or [2N, P]) whitened residuals."""
    if r.ndim == 1:
        return np.concatenate([data.w00 * r.real, data.w10 * r.real + data.w11 * r.imag])
    w00, w10, w11 = data.w00[:, None], data.w10[:, None], data.w11[:, None]
    return np.concatenate([w00 * r.real, w10 * r.real + w11 * r.imag], axis=0)


def _residuals(hm: np.ndarray, data: _Data, j: np.ndarray | None = None):
    """Whitened residuals ``[n_obs]`` of the model ``hm [N]`` (and their Jacobian ``[n_obs, P]``
    from ``dH/dtheta`` ``j [N, P]``): two per point, one (``|hm| - |h|`` over its std) at a
    magnitude-only point."""
    e = _whiten(hm - data.h, data)
    jw = None if j is None else _whiten(j, data)
    mo = data.mag_only
    if mo is None or not mo.any():
        return e, jw
    n, a = data.omega.size, np.abs(hm[mo])
    e[:n][mo] = data.wm[mo] * (a - np.abs(data.h[mo]))
    if jw is not None:
        jw[:n][mo] = data.wm[mo, None] * (np.conj(hm[mo])[:, None] * j[mo]).real / a[:, None]
    keep = np.concatenate([np.ones(n, dtype=bool), ~mo])
    return e[keep], None if jw is None else jw[keep]


def _chi2(c: _Cand, data: _Data) -> float:
    with np.errstate(all="ignore"):
        hm, _ = _model(c.theta, c.n_zeros, c.n_poles, c.est_tau, c.tau_fixed, data, False)
        e, _ = _residuals(hm, data)
    v = float(e @ e)
    return v if math.isfinite(v) else math.inf


def _quad_roots(b: float, c: float) -> np.ndarray:
    """Roots of x^2 + b x + c, computed without cancellation."""
    disc = b * b - 4.0 * c
    if disc < 0:
        re, im = -0.5 * b, 0.5 * math.sqrt(-disc)
        return np.array([complex(re, im), complex(re, -im)])
    q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
    if q == 0.0:
        return np.array([0j, 0j])
    return np.array([complex(q, 0.0), complex(c / q, 0.0)])


def _factors_from_roots(roots: np.ndarray, n: int):
    """Real factor coefficients (quadratics [n//2, 2], linear [n%2]) of prod(x - roots)."""
    roots = np.asarray(roots, dtype=np.complex128)
    if roots.size != n:
        return None
    tol = 1e-12 * np.maximum(np.abs(roots), 1e-300)
    upper = roots[roots.imag > tol]
    reals = np.sort(roots[np.abs(roots.imag) <= tol].real)
    if 2 * upper.size + reals.size != n:
        return None
    quads = [(-2.0 * p.real, abs(p) ** 2) for p in upper]
    lin = []
    if n % 2:
        lin = [-reals[-1]]
        reals = reals[:-1]
    for r1, r2 in zip(reals[0::2], reals[1::2]):
        quads.append((-(r1 + r2), r1 * r2))
    return np.array(quads, dtype=np.float64).reshape(-1, 2), np.array(lin, dtype=np.float64)


def _roots_of(quads, lins, scale) -> np.ndarray:
    r = [_quad_roots(b, c) for b, c in quads] + [np.array([complex(-c, 0.0)]) for c in lins]
    if not r:
        return np.zeros(0, dtype=np.complex128)
    return np.concatenate(r) * scale


def _poly_of(lead, quads, lins, scale) -> np.ndarray:
    """``lead`` times the factors ``s^2 + a1 s + a0`` and ``s + c`` of the scaled frequency,
    in s (rad/s): coefficients, highest power first."""
    poly = np.array(lead)
    for a1, a0 in quads:
        poly = np.polymul(poly, [1.0, a1 * scale, a0 * scale * scale])
    for c in lins:
        poly = np.polymul(poly, [1.0, c * scale])
    return poly


def _reflect(p: np.ndarray) -> np.ndarray:
    return np.where(p.real > 0, -p.real + 1j * p.imag, p)


# ------------------------------------------------------------------- linear SK stage
def _lstsq(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least squares on stacked real/imaginary parts, columns equilibrated (QR, full rank)."""
    ar = np.concatenate([a.real, a.imag], axis=0)
    br = np.concatenate([b.real, b.imag])
    colscale = np.sqrt(np.einsum("ij,ij->j", ar, ar))
    colscale[~(colscale > 0)] = 1.0
    ar = ar / colscale
    q, r = np.linalg.qr(ar)
    d = np.abs(np.diag(r))
    if not np.all(d > 1e-14 * d.max()):
        x = np.linalg.lstsq(ar, br, rcond=None)[0]
    else:
        x = scipy.linalg.solve_triangular(r, q.T @ br, check_finite=False)
    return x / colscale


def _sk(data: _Data, target: np.ndarray, nz: int, npo: int, n_iter: int, stable: bool):
    """SK fit of N(s')/D(s') to target; returns (gain, zeros, poles) in scaled units.

    The weights 1/|D_prev(j w')| do not change when poles are reflected across the imaginary
    axis (|j w - p| = |j w + conj(p)|), so the reflection is applied once, to the final
    denominator, before the numerator is refit.
    """
    sp, wsc = data.sp, data.wsc
    vn = sp[:, None] ** np.arange(nz + 1)
    dprev = np.ones_like(sp)
    poles = np.zeros(0, dtype=np.complex128)
    if npo > 0:
        vd = sp[:, None] ** np.arange(npo)
        rhs = target * sp ** npo
        den = None
        for _ in range(n_iter):
            wk = wsc / np.maximum(np.abs(dprev), 1e-300)
            a = np.concatenate([vn * wk[:, None], -(target * wk)[:, None] * vd], axis=1)
            x = _lstsq(a, rhs * wk)
            den = np.concatenate([[1.0], x[nz + 1:][::-1]])
            if not np.all(np.isfinite(den)):
                return None
            dnew = np.polyval(den, sp)
            step = np.max(np.abs(np.abs(dnew) - np.abs(dprev)) / np.maximum(np.abs(dnew), 1e-300))
            dprev = dnew
            if step < 1e-10:
                break
        poles = np.roots(den)
        if stable and np.any(poles.real > 0):
            poles = _reflect(poles)
            dprev = np.polyval(np.real(np.poly(poles)), sp)
    # the exact weighted problem for the numerator with D fixed: sum |wsc (N / D - target)|^2
    num = _lstsq(vn * (wsc / dprev)[:, None], target * wsc)[::-1]
    nz_eff = np.flatnonzero(num)
    if nz_eff.size == 0:
        return 0.0, np.full(nz, -1.0 + 0j), poles
    num = num[nz_eff[0]:]
    zeros = np.roots(num)
    gain = num[0]
    # a vanishing leading coefficient: put the missing zeros far away, keeping the gain
    for _ in range(nz - zeros.size):
        zeros = np.append(zeros, -1e3 + 0j)
        gain = gain / 1e3
    return float(gain), zeros, poles


def _theta(gain, zeros, poles, nz, npo):
    fz = _factors_from_roots(zeros, nz)
    fp = _factors_from_roots(poles, npo)
    if fz is None or fp is None:
        return None
    return np.concatenate([[gain], fz[0].ravel(), fz[1], fp[0].ravel(), fp[1]])


def _sk_candidate(data, nz, npo, tau, est_tau, n_iter, stable):
    with np.errstate(all="ignore"):
        target = data.h * np.exp(1j * data.omega * tau)
        sk = _sk(data, target, nz, npo, n_iter, stable)
    if sk is None:
        return None
    theta = _theta(*sk, nz, npo)
    if theta is None or not np.all(np.isfinite(theta)):
        return None
    if est_tau:
        theta = np.append(theta, tau * data.scale)
    c = _Cand(nz, npo, theta, est_tau, 0.0 if est_tau else tau, math.inf)
    c.chi2 = _chi2(c, data)
    return c


# ----------------------------------------------------------------- nonlinear polish
def _polish(c: _Cand, data: _Data, stable: bool, max_nfev: int) -> _Cand:
    """Levenberg-Marquardt on the exact weighted error.

    Parameters that must stay >= 0 (the pole factor coefficients when ``stable``, the delay
    when estimated) are optimised as u with theta = u^2, which keeps them in range without
    bounds, so MINPACK's fast unconstrained LM can be used.
    """
    nz, npo = c.n_zeros, c.n_poles
    sq = np.zeros(c.theta.size, dtype=bool)
    if stable:
        sq[1 + nz:1 + nz + npo] = True
    if c.est_tau:
        sq[-1] = True
    u0 = np.where(sq, np.sqrt(np.maximum(c.theta, 0.0)), c.theta)
    cache: dict[str, Any] = {}

    def theta_of(u):
        return np.where(sq, u * u, u)

    def evaluate(u):
        key = u.tobytes()
        if cache.get("key") != key:
            with np.errstate(all="ignore"):
                hm, j = _model(theta_of(u), nz, npo, c.est_tau, c.tau_fixed, data, True)
                j = j * np.where(sq, 2.0 * u, 1.0)
                e, jw = _residuals(hm, data, j)
            ok = np.all(np.isfinite(e)) and np.all(np.isfinite(jw))
            cache.update(key=key, e=e if ok else np.full(e.shape, 1e150), j=jw if ok else np.zeros(jw.shape))
        return cache

    try:
        res = scipy.optimize.least_squares(
            lambda u: evaluate(u)["e"],
            u0,
            jac=lambda u: evaluate(u)["j"],
            method="lm",
            x_scale="jac",
            ftol=1e-10,
            xtol=1e-10,
            gtol=1e-10,
            max_nfev=max_nfev,
        )
    except (ValueError, np.linalg.LinAlgError):
        return c
    out = _Cand(nz, npo, theta_of(res.x), c.est_tau, c.tau_fixed, math.inf)
    out.chi2 = _chi2(out, data)
    return out if out.chi2 <= c.chi2 else c


# ----------------------------------------------------------------- one channel
def _delay_grid(data: _Data) -> np.ndarray:
    wmax = float(data.omega.max())
    w, h = data.omega, data.h
    m = max(3, w.size // 8)
    slope = 0.0
    if w.size >= 3:
        top = slice(w.size - min(m, w.size), None)
        ph = np.unwrap(np.angle(h[top]))
        with np.errstate(all="ignore"):
            fit = np.polyfit(w[top], ph, 1)[0]
        if np.isfinite(fit):
            slope = max(0.0, -float(fit))
    tau_hi = max(2.0 * np.pi / wmax, 1.5 * slope)
    step = 0.25 * np.pi / wmax
    n = int(min(64, math.ceil(tau_hi / step))) + 1
    grid = np.linspace(0.0, tau_hi, n)
    if slope > 0:
        grid = np.sort(np.append(grid, slope))
    return grid


def _fit_order(data, nz, npo, delay_s, n_iter, stable, grid, nfev) -> _Cand | None:
    """SK (over the delay grid if the delay is estimated), then the polish."""
    est_tau = delay_s is None
    if est_tau:
        n_sk = min(n_iter, _GRID_SK_ITER)

        def score(tau):  # a few SK steps per delay are enough to rank them
            c = _sk_candidate(data, nz, npo, float(tau), True, n_sk, stable)
            return c.chi2 if c is not None else math.inf

        scores = [score(tau) for tau in grid]
        k = int(np.argmin(scores))
        if not math.isfinite(scores[k]):
            return None
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        tau0 = float(grid[k])
        if hi > lo:
            r = scipy.optimize.minimize_scalar(score, bounds=(lo, hi), method="bounded",
                                               options={"xatol": 1e-3 * (hi - lo)})
            if r.fun < scores[k]:
                tau0 = float(r.x)
        best = _sk_candidate(data, nz, npo, tau0, True, n_iter, stable)
        if best is None:
            return None
    else:
        best = _sk_candidate(data, nz, npo, delay_s, False, n_iter, stable)
        if best is None:
            return None
    return _polish(best, data, stable, nfev * (best.n_params + 1))


def _criterion(chi2: float, n_params: int, data: _Data, sigma2_known: bool, floor: float) -> float:
    """BIC; the known-variance form when the weights are the FRF's uncertainty."""
    log_n = math.log(data.n_obs)
    if sigma2_known:
        return chi2 + n_params * log_n
    return data.n_obs * math.log(max(chi2, data.n_obs * floor) / data.n_obs) + n_params * log_n


def _fit_channel(data: _Data, orders, delay_s, n_iter, stable, sigma2_known: bool):
    """Fit every candidate order (fewest parameters first) and return the BIC-best.

    A candidate with P parameters cannot score below its penalty term (chi2 >= 0, or chi2 at
    the floor), so once that bound exceeds the best score so far the remaining, larger
    candidates are skipped: an exact shortcut, it never changes the choice. The scan also
    stops once candidates have ``_PATIENCE`` parameters more than the best (a heuristic).
    """
    grid = _delay_grid(data) if delay_s is None else None
    extra = 1 if delay_s is None else 0
    wh = _whiten(data.h, data)
    floor = _FLOOR_RTOL ** 2 * float(wh @ wh) / data.n_obs
    todo = sorted(
        ((1 + nz + npo + extra, npo, nz) for npo, nz in orders if 1 + nz + npo + extra < data.n_obs)
    )
    best, best_crit, rows, chosen = None, math.inf, [], -1
    for n_params, npo, nz in todo:
        if _criterion(0.0, n_params, data, sigma2_known, floor) >= best_crit:
            break  # exact: no candidate with this many parameters can win
        if best is not None and n_params > best.n_params + _PATIENCE:
            break  # heuristic: _PATIENCE more parameters have not helped
        nfev = _FINAL_NFEV if len(todo) == 1 else _SCAN_NFEV
        c = _fit_order(data, nz, npo, delay_s, n_iter, stable, grid, nfev)
        if c is None or not math.isfinite(c.chi2):
            continue
        crit = _criterion(c.chi2, n_params, data, sigma2_known, floor)
        rows.append(_candidate_row(c, crit, data.n_obs))
        if crit < best_crit:
            best, best_crit, chosen = c, crit, len(rows) - 1
    if best is not None and len(todo) > 1:
        best = _polish(best, data, stable, _FINAL_NFEV * (best.n_params + 1))
    if best is not None:
        rows[chosen] = {**_candidate_row(best, _criterion(best.chi2, best.n_params, data, sigma2_known, floor), data.n_obs),
                        "chosen": True}
    return best, rows


def _candidate_row(c: _Cand, crit: float, n_obs: int) -> dict[str, Any]:
    """One row of :attr:`TransferFunctionFit.candidates`."""
    dof = n_obs - c.n_params
    return {"n_poles": c.n_poles, "n_zeros": c.n_zeros, "n_params": c.n_params, "chi2": c.chi2, "dof": dof,
            "reduced_chi2": c.chi2 / dof, "bic": crit, "chosen": False}


def _natural(theta: np.ndarray, nz: int, npo: int, est_tau: bool, scale: float, order=None):
    """``(names, values [P])``: the natural parameters of a factored model (see
    :attr:`TransferFunctionFit.param_names`); ``order`` fixes the quadratic factors' order
    (``(zero order, pole order)``, by their constant terms; computed when None)."""
    k, zq, zl, pq, pl, rest = _split(theta, nz, npo)
    if order is None:
        order = (np.argsort(zq[:, 1], kind="stable"), np.argsort(pq[:, 1], kind="stable"))
    with np.errstate(all="ignore"):
        dc = k * np.prod(zq[:, 1]) * np.prod(zl) / (np.prod(pq[:, 1]) * np.prod(pl))
        names, vals = ["dc_gain"], [float(dc)]
        for pre, quads, lins, idx in (("z", zq, zl, order[0]), ("p", pq, pl, order[1])):
            for n, (a1, a0) in enumerate(quads[idx], start=1):
                if a0 > 0:
                    names += [f"{pre}{n}_omega_n", f"{pre}{n}_zeta"]
                    vals += [math.sqrt(a0) * scale, a1 / (2.0 * math.sqrt(a0))]
                else:
                    names += [f"{pre}{n}_a1", f"{pre}{n}_a0"]
                    vals += [a1 * scale, a0 * scale * scale]
            for c in lins:
                names.append(f"{pre}{len(quads) + 1}_rate")
                vals.append(c * scale)
    if est_tau:
        names.append("delay_s")
        vals.append(rest[0] / scale)
    return tuple(names), np.array(vals, dtype=np.float64)


def _covariance(c: _Cand, data: _Data, sigma2_known: bool):
    """``(names, values [P], covariance [P, P])`` of the natural parameters at the optimum
    ``c``: Gauss-Newton ``(J^T J)^-1`` of the whitened residuals (scaled by chi2 / dof when the
    noise scale is not known), carried over by the delta method (central differences)."""
    nz, npo, theta = c.n_zeros, c.n_poles, c.theta
    k, zq, zl, pq, pl, rest = _split(theta, nz, npo)
    order = (np.argsort(zq[:, 1], kind="stable"), np.argsort(pq[:, 1], kind="stable"))
    names, vals = _natural(theta, nz, npo, c.est_tau, data.scale, order)
    nan = np.full((vals.size, vals.size), math.nan)
    with np.errstate(all="ignore"):
        hm, j = _model(theta, nz, npo, c.est_tau, c.tau_fixed, data, True)
        jw = _residuals(hm, data, j)[1]
    if not np.all(np.isfinite(jw)):
        return names, vals, nan
    _, sv, vt = np.linalg.svd(jw, full_matrices=False)
    if not sv.min() > 1e-10 * sv.max():
        return names, vals, nan  # a parameter the data do not determine
    cov_t = (vt.T / sv ** 2) @ vt
    dof = data.n_obs - c.n_params
    if not sigma2_known:
        cov_t = cov_t * (c.chi2 / dof)
    jn = np.empty((vals.size, theta.size))
    for p in range(theta.size):
        h = 1e-6 * max(abs(float(theta[p])), 1e-3)
        tp, tm = theta.copy(), theta.copy()
        tp[p] += h
        tm[p] -= h
        jn[:, p] = (_natural(tp, nz, npo, c.est_tau, data.scale, order)[1]
                    - _natural(tm, nz, npo, c.est_tau, data.scale, order)[1]) / (2.0 * h)
    with np.errstate(all="ignore"):
        cov = jn @ cov_t @ jn.T
    return names, vals, np.where(np.isfinite(cov), cov, math.nan)


def _physical(c: _Cand, data: _Data, sigma2_known: bool = True) -> dict[str, Any]:
    s = data.scale
    k, zq, zl, pq, pl, rest = _split(c.theta, c.n_zeros, c.n_poles)
    den = _poly_of([1.0], pq, pl, s)
    num = _poly_of([k * s ** (c.n_poles - c.n_zeros)], zq, zl, s)
    tau = float(rest[0] / s) if c.est_tau else float(c.tau_fixed)
    with np.errstate(all="ignore"):
        hm, _ = _model(c.theta, c.n_zeros, c.n_poles, c.est_tau, c.tau_fixed, data, False)
        err = hm - data.h if data.mag_only is None else np.where(data.mag_only, np.abs(hm) - np.abs(data.h), hm - data.h)
        rel = float(np.sqrt(np.mean(np.abs(err) ** 2 / np.abs(data.h) ** 2)))
    dof = data.n_obs - c.n_params
    names, vals, cov = _covariance(c, data, sigma2_known)
    return {
        "param_names": names,
        "params": vals,
        "covariance": cov,
        "std": np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), math.nan)),
        "num": [float(x) for x in num],
        "den": [float(x) for x in den],
        "delay_s": tau,
        "n_poles": c.n_poles,
        "n_zeros": c.n_zeros,
        "chi2": c.chi2,
        "dof": dof,
        "reduced_chi2": c.chi2 / dof,
        "rms_relative_error": rel,
        "poles": _roots_of(pq, pl, s),
        "zeros": _roots_of(zq, zl, s),
        "dc_gain": _dc_gain(num, den),
    }


# ---------------------------------------------------------------------- entry point
def _weights(frf: FrequencyResponse, weights, use: np.ndarray):
    """Whitening arrays [O, I, F] (w00, w10, w11), scalar weights [O, I, F] and a label."""
    shape = frf.response.shape
    if isinstance(weights, str):
        if weights not in _WEIGHT_MODES:
            raise ParameterError(f"weights: must be one of {set(_WEIGHT_MODES)} or an array, got {excerpt(weights)}")
        if weights == "uncertainty":
            sr, si, corr = frf.response_std()
            known = np.isfinite(sr) & np.isfinite(si)
            if np.any(known[use]):
                if not np.all(known[use]):
                    raise ParameterError(
                        "weights: 'uncertainty' needs frf.cov at every valid point, but it is known at "
                        f"{int(np.sum(known[use]))} of {int(np.sum(use))}; pass weights='uniform' or an array"
                    )
                corr = np.where(np.isfinite(corr), corr, 0.0)
                l00 = sr
                l11 = si * np.sqrt(np.maximum(1.0 - corr * corr, 0.0))
                if np.any(~((l00 > 0) & (l11 > 0))[use]):
                    raise ParameterError(
                        "weights: frf.cov gives a singular (Re, Im) covariance at some valid points "
                        "(a zero std or |correlation| = 1); pass weights='uniform' or an array"
                    )
                with np.errstate(all="ignore"):
                    w00 = 1.0 / l00
                    w11 = 1.0 / l11
                    w10 = -(corr * si) / (l00 * l11)
                    wsc = np.sqrt(2.0 / (sr * sr + si * si))
                return w00, w10, w11, wsc, "uncertainty"
        ones = np.ones(shape)
        return ones, np.zeros(shape), ones, ones, "uniform"
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"weights: expected a string or an array of real numbers, got {type(weights).__name__}") from exc
    if w.shape == shape[-1:]:
        w = np.broadcast_to(w, shape)
    if w.shape != shape:
        raise ShapeError(f"weights: expected shape [F] = {shape[-1:]} or [O, I, F] = {shape}, got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ParameterError("weights: expected finite values >= 0")
    return w, np.zeros(shape), w, w, "array"


def fit_transfer_function(
    frf: FrequencyResponse,
    *,
    n_poles: int | None = None,
    n_zeros: int | None = None,
    delay_s: float | None = None,
    weights: str | Sequence[float] | np.ndarray = "uncertainty",
    max_order: int = 8,
    n_iter: int = 30,
    stable: bool = True,
    common_delay_std_s: float = 0.0,
    magnitude_only=None,
) -> TransferFunctionFit:
    """Fit ``K prod(s - z) / prod(s - p) exp(-s delay_s)`` to each channel of ``frf``.

    Method, weighting and the order-selection rule: docs/transfer_function_fit.md.
    Failed points (``frf.valid`` False) and points of weight 0 are skipped. MIMO FRFs are
    fit channel by channel (own orders, own delay).

    Args:
        frf: the measured response ([O, I, F], omega in rad/s).
        n_poles: number of poles (>= 0); None selects it among 1..max_order.
        n_zeros: number of zeros (0..n_poles); None selects it among 0..n_poles.
        delay_s: pure delay in s: None estimates it (>= 0), a float >= 0 fixes it, 0 = none.
        weights: "uncertainty" (whiten with the covariance from ``frf.response_std()``;
            uniform if ``frf.cov`` is unknown everywhere), "uniform", or real weights [F] or
            [O, I, F] (1 / std of the real and of the imaginary part of each point).
        max_order: largest n_poles tried when selecting (1..30).
        n_iter: maximum number of Sanathanan-Koerner iterations (>= 1).
        stable: keep every pole in the closed left half plane.
        common_delay_std_s: std (s, >= 0) of a timing error shared by every point, such as the
            latency calibration's (a phase error ``omega * e`` with one ``e`` for the whole
            sweep), whose share ``(omega * common_delay_std_s)**2`` ``frf.cov``'s phase
            variance holds (identify's :func:`~torchblur.identify.assemble.phase_std`). The
            estimated delay absorbs such an error exactly, the other parameters not at all, so
            the share is taken out of the weights and ``common_delay_std_s**2`` is added to the
            delay's variance: counted once, fully correlated, instead of as independent
            per-point errors that average down. Needs ``delay_s=None``.
        magnitude_only: bool ``[F]`` or ``[O, I, F]``: points whose phase is unknown (an undecided
            alias branch), fitted by their magnitude alone (docs/transfer_function_fit.md).

    Returns:
        :class:`TransferFunctionFit` (per-channel values nested [O][I] for MIMO).

    Raises:
        InputTypeError, ParameterError, ShapeError naming the argument; ParameterError when a
        channel has too few valid points for the requested order.
    """
    check_type(frf, "frf", FrequencyResponse, "a FrequencyResponse")
    orders, delay_s = _candidate_orders(n_poles, n_zeros, max_order, delay_s)
    n_iter = check_int(n_iter, "n_iter", low=1)
    stable = check_bool(stable, "stable")
    common = _common_delay_std(common_delay_std_s, delay_s)
    w00, w10, w11, wsc, label = _weights(_without_common_delay(frf, common, weights), weights, frf.valid)
    use = frf.valid & (wsc > 0) & (w00 > 0)
    mag_only, wm = _magnitude_only(magnitude_only, frf, w00 if label != "uncertainty" else None, use)
    results = [[None] * frf.n_inputs for _ in range(frf.n_outputs)]
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            data = _channel_data(frf, o, i, use[o, i], (w00, w10, w11, wsc), mag_only, wm)
            best, rows = _fit_channel(data, orders, delay_s, n_iter, stable, label == "uncertainty")
            if best is None:
                raise ParameterError(
                    f"n_poles: no model of the requested order fits output {excerpt(frf.output_labels[o])}, "
                    f"input {excerpt(frf.input_labels[i])}: {int(np.sum(use[o, i]))} valid points give {data.n_obs} real "
                    f"observations, fewer than the parameters plus one"
                )
            results[o][i] = _with_common_delay({**_physical(best, data, label == "uncertainty"), "candidates": tuple(rows)}, common)

    def field(name):
        if frf.is_siso:
            return results[0][0][name]
        return [[results[o][i][name] for i in range(frf.n_inputs)] for o in range(frf.n_outputs)]

    names = ("num", "den", "delay_s", "n_poles", "n_zeros", "chi2", "dof", "reduced_chi2", "rms_relative_error", "poles",
             "zeros", "dc_gain", "param_names", "params", "covariance", "std", "candidates")
    return TransferFunctionFit(**{n: field(n) for n in names}, weighting=label, delay_estimated=delay_s is None,
                               input_labels=tuple(frf.input_labels), output_labels=tuple(frf.output_labels),
                               order_criterion="BIC" if len(orders) > 1 else "fixed")


def _channel_data(frf: FrequencyResponse, o: int, i: int, m: np.ndarray, weights: tuple, mag_only=None, wm=None) -> "_Data":
    """The points ``m [F]`` (bool) of channel ``(o, i)`` with their weights ``(w00, w10, w11,
    wsc)`` (each ``[O, I, F]``, see :func:`_weights`) and the magnitude-only ones (``mag_only``,
    their weights ``wm``, each ``[O, I, F]`` or None); ParameterError where no point is left."""
    if np.sum(m) == 0:
        raise ParameterError(f"frf: output {excerpt(frf.output_labels[o])}, input {excerpt(frf.input_labels[i])} has no valid point")
    omega = frf.omega[m]
    w00, w10, w11, wsc = (w[o, i, m] for w in weights)
    mo = None if mag_only is None or not mag_only[o, i, m].any() else mag_only[o, i, m]
    return _Data(omega=omega, h=frf.response[o, i, m], w00=w00, w10=w10, w11=w11, wsc=wsc,
                 scale=float(np.sqrt(omega[0] * omega[-1])), mag_only=mo, wm=None if mo is None else np.where(mo, wm[o, i, m], 1.0))

def _magnitude_only(value, frf: FrequencyResponse, weight, use: np.ndarray):
    """The checked ``magnitude_only`` of :func:`fit_transfer_function` as ``(mask, wm)``: bool
    ``[O, I, F]`` (None: none) and the weight of each such point's magnitude (``weight``, or 1 /
    the magnitude's std where None); ``use`` loses the points whose weight is unknown."""
    if value is None:
        return None, None
    shape = frf.response.shape
    m = np.asarray(value)
    if m.dtype != bool:
        raise InputTypeError(f"magnitude_only: expected None or a bool array, got dtype {m.dtype}")
    if m.shape not in (shape, shape[-1:]):
        raise ShapeError(f"magnitude_only: expected shape [F] = {shape[-1:]} or [O, I, F] = {shape}, got {m.shape}")
    if not m.any():
        return None, None
    with np.errstate(all="ignore"):
        wm = 1.0 / frf.magnitude_std if weight is None else weight
    m = np.broadcast_to(m, shape) & use
    use &= ~m | (wm > 0)
    return m, wm


def _seconds(value, name: str) -> float:
    """``value`` checked as a duration: a real number (numpy's too), finite, >= 0 (s)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InputTypeError(f"{name}: expected a real number (s), got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ParameterError(f"{name}: expected a finite value >= 0 seconds, got {value:g}")
    return value


def _common_delay_std(value, delay_s) -> float:
    """The checked ``common_delay_std_s`` of :func:`fit_transfer_function` (s)."""
    value = _seconds(value, "common_delay_std_s")
    if value > 0 and delay_s is not None:
        raise ParameterError(f"common_delay_std_s: a timing error common to every point is absorbed by an estimated delay; "
                             f"it needs delay_s=None, got delay_s={delay_s:g} with common_delay_std_s={value:g}")
    return value


def _without_common_delay(frf: FrequencyResponse, common: float, weights) -> FrequencyResponse:
    """``frf`` with the common timing error's share ``(omega * common)**2`` taken out of its phase
    variance (for the weights); ParameterError where the phase variance does not hold it."""
    if common == 0 or not (isinstance(weights, str) and weights == "uncertainty") or frf.cov is None:
        return frf
    cov = np.array(frf.cov)
    share = (frf.omega * common) ** 2
    left = cov[..., 1, 1] - share
    known = frf.valid & np.isfinite(cov[..., 1, 1])
    if np.any(known & ~(left > 0)):
        k = int(np.argmax((known & ~(left > 0)).any(axis=(0, 1))))
        raise ParameterError(f"common_delay_std_s: {common:g} s gives a phase variance share {share[k]:.3g} rad^2 at "
                             f"{frf.freq_hz[k]:.4g} Hz that frf.cov's phase variance does not hold; it must be part of it")
    cov[..., 1, 1] = np.where(known, left, cov[..., 1, 1])
    return frf.replace(cov=cov)


def _with_common_delay(res: dict, common: float) -> dict:
    """One channel's :func:`_physical` result with ``common**2`` added to the delay's variance."""
    if common == 0 or "delay_s" not in res["param_names"]:
        return res
    k = list(res["param_names"]).index("delay_s")
    cov = np.array(res["covariance"])
    cov[k, k] += common * common
    return {**res, "covariance": cov, "std": np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), math.nan))}


def _candidate_orders(n_poles, n_zeros, max_order, delay_s):
    """The ``(n_poles, n_zeros)`` pairs to try (checked) and the checked fixed delay (s) or None."""
    max_order = check_int(max_order, "max_order", low=1, high=30)
    if n_poles is not None:
        n_poles = check_int(n_poles, "n_poles", low=0, high=30)
    if n_zeros is not None:
        n_zeros = check_int(n_zeros, "n_zeros", low=0, high=30)
        if n_poles is not None and n_zeros > n_poles:
            raise ParameterError(f"n_zeros: expected <= n_poles = {n_poles} (a proper model), got {n_zeros}")
        if n_poles is None and n_zeros > max_order:
            raise ParameterError(f"n_zeros: expected <= max_order = {max_order}, got {n_zeros}")
    if delay_s is not None:
        delay_s = _seconds(delay_s, "delay_s")
    pole_range = [n_poles] if n_poles is not None else list(range(max(1, n_zeros or 0), max_order + 1))
    orders = [(p, z) for p in pole_range for z in ([n_zeros] if n_zeros is not None else range(p + 1))]
    return orders, delay_s
