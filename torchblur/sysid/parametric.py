"""Parametric models of a frequency response for the direct fit: structure, response, roots.

The forms "tf" (normalised factors, a gain, ``n0`` roots at the origin) and "modal" (a sum of
modes and a feedthrough D), both with a pure delay: docs/direct_identification.md.
:class:`_Structure` says which parameters a model has; :func:`_response` is ``H(s)`` from the
natural parameters (differentiable by autograd); :func:`_poles_zeros` and :func:`_modal_polys`
give its roots and polynomials; :func:`_structure_from_tf` turns a two-step
:class:`~torchblur.sysid.tf_fit.TransferFunctionFit` into a structure and start values.
Frequencies are rad/s throughout.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from torchblur.errors import ParameterError

@dataclasses.dataclass(frozen=True)
class _Structure:
    """Which parameters a model has. ``kinds`` lists, in parameter order, one entry per
    natural parameter: (name, transform) with transform "log" (optimised as its log, > 0)
    or "lin"."""

    form: str
    n_zero_pairs: int = 0
    n_zero_real: int = 0
    n_pole_pairs: int = 0
    n_pole_real: int = 0
    n_origin: int = 0  # tf: power of s (zeros at 0 minus poles at 0)
    feedthrough: bool = False  # modal: D
    fit_delay: bool = True

    def names_transforms(self) -> list[tuple[str, str]]:
        out: list[tuple[str, str]] = []
        if self.form == "tf":
            out.append(("gain", "lin"))
            for i in range(self.n_zero_pairs):
                out += [(f"zero_pair{i + 1}_omega_n", "log"), (f"zero_pair{i + 1}_zeta", "lin")]
            for i in range(self.n_zero_real):
                out.append((f"zero{i + 1}_rate", "lin"))
            for i in range(self.n_pole_pairs):
                out += [(f"pole_pair{i + 1}_omega_n", "log"), (f"pole_pair{i + 1}_zeta", "log")]
            for i in range(self.n_pole_real):
                out.append((f"pole{i + 1}_rate", "log"))
        else:
            for i in range(self.n_pole_pairs):
                out += [(f"mode{i + 1}_gain", "lin"), (f"mode{i + 1}_omega_n", "log"), (f"mode{i + 1}_zeta", "log")]
            for i in range(self.n_pole_real):
                out += [(f"real_mode{i + 1}_gain", "lin"), (f"real_mode{i + 1}_rate", "log")]
            if self.feedthrough:
                out.append(("feedthrough", "lin"))
        if self.fit_delay:
            out.append(("delay_s", "lin"))
        return out


def _response(struct: _Structure, p: torch.Tensor, s: torch.Tensor, delay_s: float) -> torch.Tensor:
    """H(s) [F] (complex) from natural parameters ``p`` [P] (real) at ``s`` [F] (complex)."""
    i = 0
    one = torch.ones_like(s)
    if struct.form == "tf":
        h = p[0] * one
        i = 1
        for _ in range(struct.n_zero_pairs):
            x = s / p[i]
            h = h * (x * x + 2 * p[i + 1] * x + 1)
            i += 2
        for _ in range(struct.n_zero_real):
            h = h * (1 + s / p[i])
            i += 1
        for _ in range(struct.n_pole_pairs):
            x = s / p[i]
            h = h / (x * x + 2 * p[i + 1] * x + 1)
            i += 2
        for _ in range(struct.n_pole_real):
            h = h / (1 + s / p[i])
            i += 1
        if struct.n_origin:
            h = h * s ** struct.n_origin
    else:
        h = torch.zeros_like(s)
        for _ in range(struct.n_pole_pairs):
            g, wn, z = p[i], p[i + 1], p[i + 2]
            h = h + g * wn * wn / (s * s + 2 * z * wn * s + wn * wn)
            i += 3
        for _ in range(struct.n_pole_real):
            g, a = p[i], p[i + 1]
            h = h + g * a / (s + a)
            i += 2
        if struct.feedthrough:
            h = h + p[i]
            i += 1
    tau = p[i] if struct.fit_delay else delay_s
    return h * torch.exp(-s * tau)


def _poles_zeros(struct: _Structure, p: np.ndarray):
    """(poles, zeros, high-frequency gain K) with H = K prod(s - z) / prod(s - p) (rad/s)."""
    p = np.asarray(p, dtype=np.float64)

    def pair(wn, z):
        r = -z * wn + 1j * wn * np.sqrt(complex(1 - z * z))
        return [r, np.conj(r)] if abs(1 - z * z) > 0 and z * z < 1 else [complex(-z * wn + wn * np.sqrt(z * z - 1)),
                                                                           complex(-z * wn - wn * np.sqrt(z * z - 1))]

    if struct.form == "tf":
        i, K = 1, p[0]
        zeros, poles = [], []
        for _ in range(struct.n_zero_pairs):
            zeros += pair(p[i], p[i + 1])
            K = K / p[i] ** 2
            i += 2
        for _ in range(struct.n_zero_real):
            zeros.append(complex(-p[i]))
            K = K / p[i]
            i += 1
        for _ in range(struct.n_pole_pairs):
            poles += pair(p[i], p[i + 1])
            K = K * p[i] ** 2
            i += 2
        for _ in range(struct.n_pole_real):
            poles.append(complex(-p[i]))
            K = K * p[i]
            i += 1
        if struct.n_origin > 0:
            zeros += [0j] * struct.n_origin
        elif struct.n_origin < 0:
            poles += [0j] * (-struct.n_origin)
        return np.array(poles, dtype=np.complex128), np.array(zeros, dtype=np.complex128), float(K)
    num, den = _modal_polys(struct, p)
    nz = np.trim_zeros(num, "f")
    return np.roots(den).astype(np.complex128), np.roots(nz).astype(np.complex128), float(nz[0] / den[0]) if nz.size else 0.0


def _modal_polys(struct: _Structure, p: np.ndarray):
    """num, den polynomial coefficients (highest power first) of the modal form."""
    terms, i = [], 0
    for _ in range(struct.n_pole_pairs):
        g, wn, z = p[i:i + 3]
        terms.append((np.array([g * wn * wn]), np.array([1.0, 2 * z * wn, wn * wn])))
        i += 3
    for _ in range(struct.n_pole_real):
        g, a = p[i:i + 2]
        terms.append((np.array([g * a]), np.array([1.0, a])))
        i += 2
    den = np.array([1.0])
    for _, d in terms:
        den = np.polymul(den, d)
    num = np.zeros(1)
    for k, (n, _) in enumerate(terms):
        other = np.array([1.0])
        for j, (_, d) in enumerate(terms):
            if j != k:
                other = np.polymul(other, d)
        num = np.polyadd(num, np.polymul(n, other))
    if struct.feedthrough:
        num = np.polyadd(num, p[i] * den)
    return num, den


# ---------------------------------------------------------------------- start values
def _structure_from_tf(tf_fit, form: str, fit_delay: bool):
    """(structure, natural parameters [P], delay_s) from a SISO TransferFunctionFit (or a
    DirectModelFit: anything with ``poles``, ``zeros``, ``num``, ``den`` and ``delay_s``)."""
    poles = np.asarray(tf_fit.poles, dtype=np.complex128)
    zeros = np.asarray(tf_fit.zeros, dtype=np.complex128)
    K = float(tf_fit.num[0] / tf_fit.den[0])
    delay = float(tf_fit.delay_s)
    scale = max(1.0, float(np.max(np.abs(np.concatenate([poles, zeros])))) if poles.size + zeros.size else 1.0)
    tol = 1e-9 * scale

    def split(roots):
        origin = int(np.sum(np.abs(roots) <= tol))
        rest = roots[np.abs(roots) > tol]
        upper = rest[rest.imag > 1e-9 * np.abs(rest)]
        real = rest[np.abs(rest.imag) <= 1e-9 * np.abs(rest)].real
        return origin, upper, np.sort(real)

    zo, zu, zr = split(zeros)
    po, pu, pr = split(poles)
    if np.any(pu.real >= 0) or np.any(pr >= 0):
        raise ParameterError("start: the two-step model has an unstable pole; the direct fit needs a stable start")
    if form == "tf":
        struct = _Structure("tf", len(zu), len(zr), len(pu), len(pr), zo - po, False, fit_delay)
        # H = K prod(s - z)/prod(s - p): normalised factor (s - r) = -r (1 - s/r), pair |r|^2 (...).
        gain = K
        vals = [0.0]
        for r in zu:
            vals += [abs(r), -r.real / abs(r)]
            gain *= abs(r) ** 2
        for r in zr:
            vals.append(-r)
            gain *= -r
        for r in pu:
            vals += [abs(r), -r.real / abs(r)]
            gain /= abs(r) ** 2
        for r in pr:
            vals.append(-r)
            gain /= -r
        vals[0] = gain
    else:
        if po:
            raise ParameterError("start: the modal form cannot hold a pole at the origin; use form='tf'")
        allp = np.concatenate([pu, pr.astype(np.complex128)])
        if allp.size and np.min(np.abs(allp[:, None] - allp[None, :]) + np.eye(allp.size) * 1e300) < 1e-9 * scale:
            raise ParameterError("start: the two-step model has repeated poles; the modal form needs distinct poles, use form='tf'")
        n_p, n_z = poles.size, zeros.size
        struct = _Structure("modal", 0, 0, len(pu), len(pr), 0, n_z == n_p, fit_delay)

        def residue(pk):
            others = poles[np.abs(poles - pk) > 0]
            return K * np.prod(pk - zeros) / np.prod(pk - others)

        vals = []
        for r in pu:  # the pair's numerator b1 s + b0; the modal form keeps b0 (a real modal residue)
            res = residue(r)
            wn = abs(r)
            vals += [-2 * (res * np.conj(r)).real / wn**2, wn, -r.real / wn]
        for r in pr:
            res = residue(complex(r)).real
            vals += [res / -r, -r]
        if struct.feedthrough:
            vals.append(K)
    if fit_delay:
        vals.append(delay)
    return struct, np.asarray(vals, dtype=np.float64), delay
