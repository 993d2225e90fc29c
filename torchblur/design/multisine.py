"""Multisine excitation: tones on a common frequency grid, crest factor minimised, and the
exact response of an LTI plant to it (transients and delay included).

A multisine command is ``u(t) = sum_k a_k sin(omega_k t + p_k)`` with ``omega_k = n_k omega_0``
(integer harmonics ``n_k`` of a base ``f0 = omega_0 / 2 pi``), applied from rest at t = 0. It
repeats every common period ``T0 = 1 / f0``, so a trigger locked to ``t = k T0 + offset`` sees
the same phase of every tone in every frame (PHYSICS.md section 2, with the upward zero
crossing of the sine replaced by the start of a common period).

The phases ``p_k`` only matter for the peak of the command: a low crest factor
(``max |u| / rms(u)``) drives every tone as hard as possible for a given peak stroke.
:func:`schroeder_phases` gives the classic closed form; :func:`optimise_crest_factor` improves
on it by iterative clipping (Van den Bos) and a minimisation of the Lp norm of the signal over
the phases with p growing (Guillaume et al. 1991), keeping the best crest factor measured.

:class:`LTIMultisineTrajectory` is the plant output, by superposition of the tones'
responses from rest (the response to ``a sin(omega t + p)`` is the one of
:class:`~torchblur.systems.lti.LTISineTrajectory` with the complex amplitude ``a e^{jp}``):

    y(t) = 0                                                for t' = t - delay_s < 0,
    y(t) = sum_k a_k Im(H0(j omega_k) e^{j(omega_k t' + p_k)}) + C e^{A t'} x_tr0,
    x_tr0 = -sum_k a_k Im((j omega_k I - A)^-1 B e^{j p_k}).

This module needs scipy only for the optimiser; it is not imported by ``import torchblur``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor
from torchblur.systems.lti import LTIMultisineTrajectory  # noqa: F401  (re-exported beside the design)

__all__ = ["MultisineDesign", "crest_factor", "multisine_signal", "schroeder_phases", "optimise_crest_factor", "common_grid",
           "design_multisine", "LTIMultisineTrajectory"]


def _harmonics(harmonics) -> np.ndarray:
    h = np.asarray(harmonics)
    if h.ndim != 1 or h.size == 0:
        raise ShapeError(f"harmonics: expected a non-empty 1-D list of integers, got shape {h.shape}")
    if not np.all(np.asarray(h, dtype=np.float64) == np.round(np.asarray(h, dtype=np.float64))) or np.any(h < 1):
        raise ParameterError(f"harmonics: expected integers >= 1, got {h.tolist()}")
    h = h.astype(np.int64)
    if np.unique(h).size != h.size:
        raise ParameterError(f"harmonics: expected distinct harmonics, got {h.tolist()}")
    return h


def _amplitudes(amplitudes, n: int) -> np.ndarray:
    a = np.ones(n) if amplitudes is None else np.asarray(amplitudes, dtype=np.float64).reshape(-1)
    if a.size != n:
        raise ShapeError(f"amplitudes: expected {n} values (one per harmonic), got {a.size}")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or not np.any(a > 0):
        raise ParameterError(f"amplitudes: expected finite values >= 0, not all 0, got {a.tolist()}")
    return a


def crest_factor(signal) -> torch.Tensor:
    """``max |x| / rms(x)`` over the last axis of ``signal`` ``[..., S]`` (samples of one
    period) -> ``[...]``. A single sine has sqrt(2)."""
    x = as_tensor(signal, "signal")
    if x.dim() < 1 or x.shape[-1] < 2:
        raise ShapeError(f"signal: expected shape [..., S] with S >= 2 samples, got {tuple(x.shape)}")
    rms = x.square().mean(-1).sqrt()
    return x.abs().amax(-1) / rms


def multisine_signal(harmonics, amplitudes, phases, n_samples: int) -> np.ndarray:
    """One common period of ``sum_k a_k sin(2 pi n_k s / S + p_k)`` at ``S = n_samples``
    equally spaced samples, float64 ``[S]``."""
    h = _harmonics(harmonics)
    a = _amplitudes(amplitudes, h.size)
    p = np.asarray(phases, dtype=np.float64).reshape(-1)
    if p.size != h.size:
        raise ShapeError(f"phases: expected {h.size} values, got {p.size}")
    s = np.arange(int(n_samples)) / int(n_samples)
    return (a[:, None] * np.sin(2 * np.pi * h[:, None] * s + p[:, None])).sum(0)


def _n_samples(h: np.ndarray) -> int:
    """Samples per period that resolve the peak of a signal of highest harmonic ``max(h)``
    to about 1e-3 (32 samples per period of the fastest tone, at least 1024)."""
    return int(max(1024, 32 * int(h.max())))


def schroeder_phases(amplitudes) -> np.ndarray:
    """Schroeder's phases (1970) for tones of (power) amplitudes ``a_k`` on consecutive
    harmonics: ``p_k = -2 pi sum_{l<k} (k - l) a_l^2 / sum a^2`` (rad), ``[N]``; with equal
    amplitudes ``p_k = -pi k (k - 1) / N``."""
    a = np.asarray(amplitudes, dtype=np.float64).reshape(-1)
    w = a**2 / np.sum(a**2)
    k = np.arange(a.size)
    return np.array([-2 * np.pi * np.sum((kk - k[:kk]) * w[:kk]) for kk in k])


def optimise_crest_factor(harmonics, amplitudes=None, *, phases=None, clip_iterations: int = 200,
                          norms=(4, 8, 16, 32, 64, 128), n_samples: int | None = None) -> tuple[np.ndarray, float]:
    """Phases that minimise the crest factor of ``sum_k a_k sin(2 pi n_k t / T0 + p_k)``.

    Start from ``phases`` (default: Schroeder's), then (1) iterative clipping: clip the signal
    at a level that shrinks towards its rms, keep the phases of its tones (FFT), and (2)
    minimise the Lp norm of the signal over the phases for growing p (L-BFGS, exact
    gradients); the phases with the lowest crest factor measured on the sample grid win, so
    the result is never worse than the start.

    Args:
        harmonics: integer harmonics ``n_k`` of the base frequency, ``[N]``.
        amplitudes: ``a_k >= 0``, ``[N]``; default all 1.
        phases: start phases (rad), ``[N]``.
        clip_iterations: clipping iterations.
        norms: the p of the Lp stages.
        n_samples: samples per common period (default 32 per period of the fastest tone, at
            least 1024).

    Returns:
        ``(phases [N] rad, crest_factor)`` measured on the sample grid.
    """
    from scipy.optimize import minimize

    h = _harmonics(harmonics)
    a = _amplitudes(amplitudes, h.size)
    S = int(n_samples) if n_samples is not None else _n_samples(h)
    if S < 2 * int(h.max()) + 1:
        raise ParameterError(f"n_samples: expected at least 2 max(harmonics) + 1 = {2 * int(h.max()) + 1}, got {S}")
    p0 = schroeder_phases(a) if phases is None else np.asarray(phases, dtype=np.float64).reshape(-1)
    if p0.size != h.size:
        raise ShapeError(f"phases: expected {h.size} values, got {p0.size}")

    def cf(p):
        x = multisine_signal(h, a, p, S)
        return float(np.abs(x).max() / np.sqrt(np.mean(x * x)))

    best_p, best = p0.copy(), cf(p0)
    if h.size == 1:
        return np.array([0.0]) if phases is None else best_p, best
    # (1) Iterative clipping.
    p = p0.copy()
    for it in range(int(clip_iterations)):
        x = multisine_signal(h, a, p, S)
        level = np.abs(x).max() * (0.9 - 0.3 * it / max(1, clip_iterations))
        X = np.fft.rfft(np.clip(x, -level, level))
        # sin(w t + p) has FFT bin -j S/2 e^{jp}: p = angle(X) + pi/2
        p = np.angle(X[h]) + np.pi / 2
        c = cf(p)
        if c < best:
            best_p, best = p.copy(), c
    # (2) Lp norms with growing p.
    s = np.arange(S) / S
    arg0 = 2 * np.pi * h[:, None] * s  # [N, S]
    p = best_p.copy()
    for q in norms:
        def fun(pp, q=q):
            arg = arg0 + pp[:, None]
            x = (a[:, None] * np.sin(arg)).sum(0)
            scale = np.abs(x).max()
            r = np.abs(x / scale)
            m = np.mean(r**q)
            val = scale * m ** (1 / q)
            # d/dp_k of (mean |x|^q)^(1/q) = (mean|x|^q)^(1/q - 1) mean(|x|^(q-1) sign(x) a_k cos(arg_k))
            g = (m ** (1 / q - 1)) * np.mean((r ** (q - 1)) * np.sign(x) * a[:, None] * np.cos(arg), axis=1)
            return val, g

        res = minimize(fun, p, jac=True, method="L-BFGS-B", options={"maxiter": 200})
        p = res.x
        c = cf(p)
        if c < best:
            best_p, best = p.copy(), c
    return np.remainder(best_p + np.pi, 2 * np.pi) - np.pi, best


def common_grid(freq_hz, *, snap_tol: float = 0.05, max_harmonic: int = 64) -> tuple[float, np.ndarray]:
    """A base frequency ``f0`` and distinct integer harmonics ``n_k`` with ``n_k f0`` within
    ``snap_tol`` (relative) of each ``freq_hz[k]``, choosing the largest such ``f0`` of the form
    ``min(freq_hz) / n`` (the shortest common period).

    Returns ``(f0_hz, harmonics [N] int)``. Raises :class:`ParameterError` naming
    ``freq_hz`` when no grid up to ``max_harmonic`` fits."""
    f = np.asarray(freq_hz, dtype=np.float64).reshape(-1)
    if f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ParameterError(f"freq_hz: expected frequencies > 0, got {f.tolist()}")
    if not 0 < snap_tol < 0.5:
        raise ParameterError(f"snap_tol: expected a value in (0, 0.5), got {snap_tol!r}")
    fmin = f.min()
    for n1 in range(1, int(max_harmonic) + 1):
        f0 = fmin / n1
        n = np.round(f / f0).astype(np.int64)
        if n.max() > max_harmonic or np.unique(n).size != n.size or np.any(n < 1):
            continue
        if np.all(np.abs(n * f0 - f) <= snap_tol * f):
            return float(f0), n
    raise ParameterError(f"freq_hz: no common grid f0 = min(freq_hz) / n with harmonics <= {max_harmonic} places {f.tolist()} "
                         f"within snap_tol = {snap_tol:g}; use fewer tones per group or a larger excitation.snap_tol")


@dataclass(frozen=True)
class MultisineDesign:
    """A multisine command: ``u(t) = sum_k amplitudes[k] sin(2 pi harmonics[k] f0 t + phases[k])``.

    Attributes:
        base_freq_hz: f0 (Hz); the command repeats every ``period_s = 1 / f0``.
        harmonics: integer harmonics ``n_k``, ``(N,)``.
        amplitudes: command amplitudes ``a_k`` (command units), ``(N,)``.
        phases: command phases ``p_k`` (rad), ``(N,)``.
        crest_factor: ``max |u| / rms(u)`` of the command.
    """

    base_freq_hz: float
    harmonics: tuple
    amplitudes: tuple
    phases: tuple
    crest_factor: float

    @property
    def freq_hz(self) -> np.ndarray:
        """Tone frequencies (Hz), ``[N]``."""
        return self.base_freq_hz * np.asarray(self.harmonics, dtype=np.float64)

    @property
    def omega(self) -> np.ndarray:
        """Tone frequencies (rad/s), ``[N]``."""
        return 2 * np.pi * self.freq_hz

    @property
    def period_s(self) -> float:
        return 1.0 / self.base_freq_hz

    @property
    def n_tones(self) -> int:
        return len(self.harmonics)

    def peak(self) -> float:
        """``max |u(t)|`` over a period (command units)."""
        h = np.asarray(self.harmonics)
        return float(np.abs(multisine_signal(h, self.amplitudes, self.phases, _n_samples(h))).max())

    def scaled(self, amplitudes) -> "MultisineDesign":
        """The same tones and phases with other amplitudes ``[N]`` (crest factor re-measured)."""
        h = np.asarray(self.harmonics)
        a = _amplitudes(amplitudes, h.size)
        x = multisine_signal(h, a, self.phases, _n_samples(h))
        return MultisineDesign(self.base_freq_hz, self.harmonics, tuple(float(v) for v in a), self.phases,
                               float(np.abs(x).max() / np.sqrt(np.mean(x * x))))


def design_multisine(freq_hz, amplitudes=None, *, snap_tol: float = 0.05, max_harmonic: int = 64) -> MultisineDesign:
    """Tones near ``freq_hz`` (Hz, ``[N]``) on a common grid (:func:`common_grid`) with
    amplitudes ``[N]`` (default 1) and phases of minimal crest factor
    (:func:`optimise_crest_factor`)."""
    f0, n = common_grid(freq_hz, snap_tol=snap_tol, max_harmonic=max_harmonic)
    order = np.argsort(n)
    a = _amplitudes(amplitudes, n.size)
    n, a = n[order], a[order]
    p, c = optimise_crest_factor(n, a)
    return MultisineDesign(f0, tuple(int(v) for v in n), tuple(float(v) for v in a), tuple(float(v) for v in p), float(c))
