"""A continuous LTI plant with a pure delay, and its exact response to a sine from rest.

The plant ``H(s) = num(s) / den(s) * exp(-s delay_s)`` maps the command u (input units) to
the spot's displacement y (px along the motion direction). Conventions (PHYSICS.md
section 2): ``omega`` in rad/s, phases in radians, ``u(t) = amplitude sin(omega t)`` applied
from rest at t = 0 (an upward zero crossing of the command).

:class:`LTISineTrajectory` is the *exact* output, transient included:

    y(t) = 0                                   for t' = t - delay_s < 0,
    y(t) = y_ss(t') + y_tr(t')                 otherwise,
    y_ss(t') = amplitude Im(H0(j omega) e^{j omega t'})        (H0: H without the delay)
    y_tr(t') = C e^{A t'} x_tr0,   x_tr0 = -x_ss(0) = -amplitude Im((j omega I - A)^-1 B)

with ``(A, B, C, D)`` a (balanced) state-space form of ``num / den``. ``C e^{A t'} x_tr0`` is
a modal sum ``sum_k Re(c_k e^{lambda_k t'})`` (eigendecomposition of A, computed once in
float64), or ``C expm(A t') x_tr0`` when the eigenvectors are ill-conditioned (repeated poles).

This module is not imported by ``import torchblur`` (it needs scipy); import it on use.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.signal
import torch

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_tensor, broadcast_batch, check_finite, check_int,
                              check_positive, check_real_scalar, check_type)
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Trajectory, _sine_path_bound

__all__ = ["Plant", "LTIResponse", "LTISineTrajectory", "LTIMultisineTrajectory"]

_EIG_COND_MAX = 1e10  # above: matrix-exponential evaluation
_EIG_COND_BOUND = 1e4  # above: the modal coefficients cancel, path bound from sampling
_METHODS = ("auto", "modal", "expm")


def _as_coefficients(value, name: str) -> tuple[float, ...]:
    """A non-empty 1-D sequence of finite real numbers as a tuple of floats."""
    if isinstance(value, (str, bytes, bool)) or value is None:
        raise InputTypeError(f"{name}: expected a sequence of real numbers (highest power first), got {type(value).__name__}")
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:  # pragma: no cover - numpy accepts nearly anything
        raise InputTypeError(f"{name}: expected a sequence of real numbers, got {type(value).__name__}") from exc
    if arr.dtype == object or arr.dtype.kind not in "biuf":
        raise InputTypeError(f"{name}: expected a sequence of real numbers (highest power first), got dtype {arr.dtype}")
    if arr.ndim == 0:
        arr = arr[None]
    if arr.ndim != 1:
        raise ShapeError(f"{name}: expected a 1-D sequence of coefficients, got shape {arr.shape}")
    if arr.size == 0:
        raise ParameterError(f"{name}: expected at least one coefficient, got an empty sequence")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{name}: expected finite coefficients, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class Plant:
    """A stable, proper continuous-time transfer function with a pure delay.

    ``H(s) = (num[0] s^m + ... + num[m]) / (den[0] s^n + ... + den[n]) * exp(-s delay_s)``

    Args:
        num: numerator coefficients, highest power first (leading zeros are dropped); the
            output is in px per input unit.
        den: denominator coefficients, highest power first, ``den[0] != 0``.
        delay_s: pure delay in seconds (>= 0).

    Raises :class:`~torchblur.errors.ParameterError` naming ``num`` (empty, NaN/Inf, improper:
    deg num > deg den), ``den`` (empty, NaN/Inf, zero leading coefficient, unstable: a pole
    with real part >= 0) or ``delay_s`` (negative, NaN); ``InputTypeError`` for non-numbers.

    Example:
        >>> wn = 2 * math.pi * 300
        >>> p = Plant(num=(wn**2,), den=(1.0, 2 * 0.05 * wn, wn**2), delay_s=40e-6)
        >>> abs(p.frequency_response(wn)) > 9.9
        True
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay_s: float = 0.0

    def __post_init__(self):
        num = _as_coefficients(self.num, "num")
        den = _as_coefficients(self.den, "den")
        if den[0] == 0.0:
            raise ParameterError(f"den: expected a non-zero leading coefficient, got den = {den}")
        nz = np.trim_zeros(np.asarray(num), "f")
        num = tuple(float(v) for v in nz) if nz.size else (0.0,)
        if len(num) > len(den):
            raise ParameterError(
                f"num: expected a proper transfer function (deg num <= deg den = {len(den) - 1}), "
                f"got deg num = {len(num) - 1}"
            )
        poles = np.roots(den) if len(den) > 1 else np.zeros(0, complex)
        if poles.size and not np.all(poles.real < 0):
            worst = poles[np.argmax(poles.real)]
            raise ParameterError(
                f"den: expected a stable plant (every pole with real part < 0), got a pole at {worst:.6g}"
            )
        delay = check_real_scalar(self.delay_s, "delay_s", nonnegative=True)
        object.__setattr__(self, "num", num)
        object.__setattr__(self, "den", den)
        object.__setattr__(self, "delay_s", delay)

    # ------------------------------------------------------------------ descriptions

    @property
    def order(self) -> int:
        """Number of poles (degree of ``den``)."""
        return len(self.den) - 1

    def poles(self) -> np.ndarray:
        """Poles in rad/s, complex ``[order]``."""
        return np.roots(self.den) if self.order else np.zeros(0, complex)

    def zeros(self) -> np.ndarray:
        """Finite zeros in rad/s, complex."""
        return np.roots(self.num) if len(self.num) > 1 else np.zeros(0, complex)

    def dc_gain(self) -> float:
        """``H(0)`` (px per input unit)."""
        return self.num[-1] / self.den[-1]

    def frequency_response(self, omega) -> np.ndarray:
        """``H(j omega)`` with the delay included, complex, same shape as ``omega`` (rad/s)."""
        w = np.asarray(omega, dtype=np.float64)
        s = 1j * w
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay_s)

    def settling_time_s(self, tol: float = 1e-7) -> float:
        """Time (s) after which every transient mode has decayed by the factor ``tol``:
        ``max_k ln(1/tol) / |Re p_k| + delay_s`` (``delay_s`` for a static gain).

        The bound is per mode (a repeated pole's ``t^k`` factor is not included)."""
        tol = check_real_scalar(tol, "tol", positive=True)
        if tol >= 1:
            raise ParameterError(f"tol: expected a value in (0, 1), got {tol:g}")
        p = self.poles()
        if p.size == 0:
            return self.delay_s
        return float(math.log(1.0 / tol) / np.min(np.abs(p.real))) + self.delay_s

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A balanced realisation ``(A [n, n], B [n], C [n], D scalar)`` of ``num / den``
        (no delay), float64. Balancing (a diagonal similarity) keeps the eigenvectors of
        high-order, high-frequency companion forms well conditioned."""
        if self.order == 0:
            return np.zeros((0, 0)), np.zeros(0), np.zeros(0), np.float64(self.num[-1] / self.den[0])
        A, B, C, D = scipy.signal.tf2ss(self.num, self.den)  # controller canonical form
        A, (scale, _) = scipy.linalg.matrix_balance(A, permute=False, separate=True)  # LAPACK gebal: powers of 2, exact
        return A, B[:, 0] / scale, C[0] * scale, np.float64(D[0, 0])

    def to_control(self, pade_order: int | None = None):
        """A ``control.TransferFunction`` of ``num / den``.

        python-control has no pure delay: with ``pade_order`` (an integer >= 1) the delay is
        included as a Pade approximation of that order, otherwise it is left out.
        """
        try:
            import control
        except ImportError as exc:  # pragma: no cover - control is a dependency
            raise ImportError("Plant.to_control needs python-control: pip install control") from exc
        tf = control.TransferFunction(list(self.num), list(self.den))
        if pade_order is None or self.delay_s == 0:
            return tf
        pade_order = check_int(pade_order, "pade_order", low=1)
        pn, pd = control.pade(self.delay_s, pade_order)
        return tf * control.TransferFunction(pn, pd)


class LTIResponse(Trajectory):
    """The response of a plant to a command applied from rest at t = 0: the steady state
    (:meth:`_steady`, defined by each subclass) plus the transient (modal, or by the matrix
    exponential), 0 before the delay; the spot moves along ``direction`` (px per output
    unit). Subclasses hold ``delay_s``, ``direction``, ``method`` and ``_lam``, ``_c``
    (modal) or ``_a``, ``_cvec``, ``_x0`` (matrix exponential)."""

    def _init_transient(self, A, C, x0, shape, device, method: str = "auto") -> None:
        """The free response from the state ``x0`` ``[b, n]`` (b = prod(shape)) of
        ``x' = A x, y = C x``: modal (eigen-decomposition, when its eigenvectors are
        well conditioned or ``method="modal"``) or by the matrix exponential."""
        n = A.shape[0]
        self._cond = 1.0
        if n:
            lam, V = np.linalg.eig(A)
            self._cond = float(np.linalg.cond(V))
        use_modal = method == "modal" or (method == "auto" and self._cond <= _EIG_COND_MAX)
        self.method = "modal" if (use_modal or n == 0) else "expm"
        self._lam = self._c = self._a = self._cvec = self._x0 = None
        if self.method == "modal":
            if n:
                c = (C @ V) * np.linalg.solve(V, x0.T.astype(complex)).T  # [b, n]
            else:
                lam, c = np.zeros(0, complex), np.zeros((x0.shape[0], 0), complex)
            self._lam = torch.as_tensor(np.stack([lam.real, lam.imag], -1), device=device)  # [n, 2]
            self._c = torch.as_tensor(np.stack([c.real, c.imag], -1).reshape(tuple(shape) + (n, 2)), device=device)
        else:
            self._a = torch.as_tensor(A, device=device)
            self._cvec = torch.as_tensor(C, device=device)
            self._x0 = torch.as_tensor(x0.reshape(tuple(shape) + (n,)), device=device)

    def _steady(self, tp: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """The steady-state output at times ``tp`` after the delay (float64 ``[..., S]``)."""
        raise NotImplementedError

    def output(self, t: torch.Tensor) -> torch.Tensor:
        """The plant output y (output units) at absolute times ``t`` (s), ``[..., S]`` ->
        ``[..., S]``, computed in float64 and returned in ``t``'s dtype."""
        return self._output(t, transient=True, steady=True)

    def transient(self, t: torch.Tensor) -> torch.Tensor:
        """The transient part ``y_tr`` (0 before the delay), ``[..., S]`` -> ``[..., S]``."""
        return self._output(t, transient=True, steady=False)

    def position(self, t: torch.Tensor) -> torch.Tensor:
        """Displacement (px) ``[..., S, 2]`` at absolute command times ``t`` (s) ``[..., S]``."""
        y = self.output(t)
        return y[..., None] * self.direction.to(device=y.device, dtype=y.dtype)[..., None, :]

    def _span_after_delay(self, window: ExposureWindow):
        """``(t0, t1)`` float64 ``[...]``: the window in the response's own time ``t - delay_s``,
        clamped at 0 (the output is zero before the delay), detached."""
        start = window.start.detach().to(torch.float64)
        end = start + window.duration.detach().to(torch.float64)
        return (start - self.delay_s).clamp_min(0.0), (end - self.delay_s).clamp_min(0.0)

    def _transient_path_bound(self, t0: torch.Tensor, t1: torch.Tensor) -> torch.Tensor:
        """Bound of the total variation of ``self.transient`` over ``[t0, t1]`` (times after the
        delay, float64 ``[...]``): ``sum_k |c_k| |lambda_k| integral e^{Re lambda_k t'} dt'``
        (modal, well-conditioned eigenvectors), or estimated from 2049 samples with a 10 % margin
        (nearly repeated poles, where the modal terms cancel and their bound is far too loose)."""
        dev = t0.device
        if self.method == "modal" and self._cond <= _EIG_COND_BOUND:
            lam = self._lam.to(dev)
            if not lam.shape[0]:
                return torch.zeros_like(t0)
            sigma = lam[:, 0]  # < 0
            mag = torch.linalg.vector_norm(lam, dim=-1)
            cabs = torch.linalg.vector_norm(self._c.to(dev), dim=-1)  # [..., n]
            integral = torch.exp(sigma * t0[..., None]) * (-torch.expm1(sigma * (t1 - t0)[..., None])) / (-sigma)
            return (cabs * mag * integral).sum(-1)
        u = torch.linspace(0.0, 1.0, 2049, dtype=torch.float64, device=dev)
        ts = (t0[..., None] + (t1 - t0)[..., None] * u) + self.delay_s
        return 1.1 * self.transient(ts).diff(dim=-1).abs().sum(-1)

    def _output(self, t, *, transient: bool, steady: bool) -> torch.Tensor:
        if not isinstance(t, torch.Tensor):
            t = as_tensor(t, "t", dtype=torch.float64)
        out_dtype = t.dtype
        tt = t.detach().to(torch.float64)
        dev = tt.device
        tp = tt - self.delay_s
        started = tp >= 0
        tp = tp.clamp_min(0.0)
        y = torch.zeros((), dtype=torch.float64, device=dev)
        if steady:
            y = y + self._steady(tp)
        if transient:
            if self.method == "modal":
                lam = self._lam.to(dev)
                if lam.shape[0]:
                    c = self._c.to(dev)[..., None, :, :]  # [..., 1, n, 2]
                    x = tp[..., None]  # [..., S, 1]
                    decay = torch.exp(lam[:, 0] * x)
                    arg = lam[:, 1] * x
                    y = y + (decay * (c[..., 0] * torch.cos(arg) - c[..., 1] * torch.sin(arg))).sum(-1)
            else:
                a, cvec, x0 = self._a.to(dev), self._cvec.to(dev), self._x0.to(dev)
                phi = torch.linalg.matrix_exp(a * tp[..., None, None])  # [..., S, n, n]
                y = y + ((phi @ x0[..., None, :, None])[..., 0] * cvec).sum(-1)
        y = torch.where(started, y, torch.zeros((), dtype=torch.float64, device=dev))
        return y.to(out_dtype)


class LTIMultisineTrajectory(LTIResponse):
    """The exact response of a :class:`~torchblur.systems.lti.Plant` to the multisine command
    ``u(t) = sum_k amplitude_k sin(omega_k t + phase_k)`` applied from rest at t = 0,
    transients and delay included, mapped to the image as ``direction * y(t)``.

    Args:
        plant: the :class:`~torchblur.systems.lti.Plant`.
        amplitude: command amplitudes (command units), ``[..., N]``.
        omega: tone frequencies (rad/s), ``[..., N]``, > 0.
        phase: command phases (rad), ``[..., N]``; default 0.
        direction: px per output unit along (x, y), ``[2]`` or ``[..., 2]``; default (1, 0).
        method: ``"auto"`` (modal sum, or matrix exponential when the eigenvector matrix has
            a condition number above 1e10), ``"modal"`` or ``"expm"``.

    Batch ``[...]``: the broadcast of the leading dims. Coefficients are computed once in
    float64 (numpy) at construction; :meth:`position` is plain torch on ``t``; not
    differentiable in the plant or the tones. With every phase 0 it equals the sum of
    :class:`~torchblur.systems.lti.LTISineTrajectory` responses.

    ``position(t)[..., s, :]`` = displacement (px) from the rest position at the absolute
    command time ``t[..., s]`` (s).

    Example:
        >>> p = Plant(num=(1.0,), den=(1e-3, 1.0))
        >>> traj = LTIMultisineTrajectory(p, [1.0, 0.5], [2 * math.pi * 50, 2 * math.pi * 150], [0.0, 1.0])
        >>> traj.position(torch.zeros(5, dtype=torch.float64)).shape
        torch.Size([5, 2])
    """

    __slots__ = ("plant", "amplitude", "omega", "phase", "direction", "delay_s", "method", "_h0", "_lam", "_c", "_a", "_cvec",
                 "_x0", "_cond")

    def __init__(self, plant: Plant, amplitude, omega, phase=None, *, direction=(1.0, 0.0), method: str = "auto"):
        check_type(plant, "plant", Plant, "a torchblur.systems.lti.Plant")
        if method not in _METHODS:
            raise ParameterError(f"method: must be one of {set(_METHODS)}, got {method!r}")
        f64 = torch.float64
        amplitude = check_finite(as_tensor(amplitude, "amplitude", dtype=f64), "amplitude")
        omega = check_positive(as_tensor(omega, "omega", dtype=f64), "omega")
        phase = torch.zeros_like(amplitude) if phase is None else check_finite(as_tensor(phase, "phase", dtype=f64), "phase")
        direction = check_finite(as_tensor(direction, "direction", dtype=f64), "direction")
        for name, v in (("amplitude", amplitude), ("omega", omega), ("phase", phase)):
            if v.dim() == 0:
                raise ShapeError(f"{name}: expected shape [..., N] (one value per tone), got a scalar")
        if direction.dim() == 0 or direction.shape[-1] != 2:
            raise ShapeError(f"direction: expected shape [2] or [..., 2] (x, y px per output unit), got {tuple(direction.shape)}")
        N = max(amplitude.shape[-1], omega.shape[-1], phase.shape[-1])
        for name, v in (("amplitude", amplitude), ("omega", omega), ("phase", phase)):
            if v.shape[-1] not in (1, N):
                raise ShapeError(f"{name}: expected a last dim of {N} (tones), got shape {tuple(v.shape)}")
        shape = broadcast_batch({"amplitude": amplitude.shape[:-1], "omega": omega.shape[:-1], "phase": phase.shape[:-1],
                                 "direction": direction.shape[:-1]})
        device = amplitude.device
        self.plant = plant
        self.delay_s = plant.delay_s
        self.amplitude = amplitude.detach().expand(shape + (N,))
        self.omega = omega.detach().to(device).expand(shape + (N,))
        self.phase = phase.detach().to(device).expand(shape + (N,))
        self.direction = direction.detach().to(device).expand(shape + (2,))

        A, B, C, D = plant.state_space()
        n = A.shape[0]
        amp = self.amplitude.cpu().numpy().reshape(-1, N)
        w = self.omega.cpu().numpy().reshape(-1, N)
        ph = np.exp(1j * self.phase.cpu().numpy().reshape(-1, N))
        if n:
            M = 1j * w[..., None, None] * np.eye(n) - A  # [b, N, n, n]
            v = np.linalg.solve(M, np.broadcast_to(B.astype(complex), w.shape + (n,))[..., None])[..., 0]  # [b, N, n]
            h0 = v @ C + D
            x0 = -(amp[..., None] * (v * ph[..., None]).imag).sum(-2)  # [b, n]
        else:
            h0 = np.full(w.shape, complex(D))
            x0 = np.zeros((w.shape[0], 0))
        self._h0 = torch.as_tensor(np.stack([h0.real, h0.imag], -1).reshape(tuple(shape) + (N, 2)), device=device)
        self._init_transient(A, C, x0, shape, device, method)

    @property
    def shape(self) -> torch.Size:
        return self.amplitude.shape[:-1]

    @property
    def n_tones(self) -> int:
        return self.amplitude.shape[-1]

    def steady_state_amplitude(self) -> torch.Tensor:
        """Output amplitude of each tone ``|a_k| |H(j omega_k)|`` (output units), ``[..., N]``."""
        return self.amplitude.abs() * torch.linalg.vector_norm(self._h0, dim=-1)

    def steady_state_phase(self) -> torch.Tensor:
        """Output phase of each tone (rad, in (-pi, pi]): ``p_k + angle H(j omega_k)`` (delay
        included, plus pi for a negative amplitude), ``[..., N]``."""
        ph = torch.atan2(self._h0[..., 1], self._h0[..., 0]) - self.omega * self.delay_s + self.phase
        ph = ph + math.pi * (self.amplitude < 0)
        return torch.atan2(torch.sin(ph), torch.cos(ph))

    def _steady(self, tp: torch.Tensor) -> torch.Tensor:
        """The steady-state output at times ``tp`` after the delay (float64 ``[..., S]``): the
        sum of the tones' sine responses."""
        dev = tp.device
        amp = self.amplitude.to(dev)[..., None, :]  # [..., 1, N]
        arg = self.omega.to(dev)[..., None, :] * tp[..., None] + self.phase.to(dev)[..., None, :]  # [..., S, N]
        h = self._h0.to(dev)[..., None, :, :]
        return (amp * (h[..., 0] * torch.sin(arg) + h[..., 1] * torch.cos(arg))).sum(-1)

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        """Upper bound of the path (px) during ``window``, ``[...]``, no gradient.

        ``|direction| * (TV(y_ss) + TV(y_tr))`` (Euclidean norm of ``direction``) over the part
        of the window after the delay: the sum of the tones' exact steady-state total
        variations, plus the transient's bound (:meth:`LTIResponse._transient_path_bound`)."""
        with torch.no_grad():
            t0, t1 = self._span_after_delay(window)
            dev = t0.device
            h = self._h0.to(dev)
            phase0 = torch.atan2(h[..., 1], h[..., 0]) + self.phase.to(dev) + math.pi * (self.amplitude.to(dev) < 0)
            amp = self.amplitude.to(dev).abs() * torch.linalg.vector_norm(h, dim=-1)  # [..., N] (a subclass's steady_state_amplitude may be [...])
            tv = _sine_path_bound(amp, self.omega.to(dev), phase0, t0[..., None], (t1 - t0)[..., None]).sum(-1)
            tv = tv + self._transient_path_bound(t0, t1)
            return tv * torch.linalg.vector_norm(self.direction.to(dev), dim=-1)

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        """``max_k omega_k * duration`` (the fastest tone); the transients' share of the nodes
        comes from their path (:meth:`path_length`)."""
        return self.omega.detach().abs().amax(-1).to(window.duration.device) * window.duration.detach()

    def __repr__(self) -> str:
        return f"LTIMultisineTrajectory(shape={tuple(self.shape)}, tones={self.n_tones}, order={self.plant.order}, method={self.method!r})"


class LTISineTrajectory(LTIMultisineTrajectory):
    """The exact response of a :class:`Plant` to ``u(t) = amplitude sin(omega t)`` applied
    from rest at t = 0, transient and delay included, mapped to the image as
    ``direction * y(t)``: the one-tone :class:`LTIMultisineTrajectory`.

    Args:
        plant: the :class:`Plant`.
        amplitude: command amplitude in input units, ``[...]``.
        omega: command frequency in rad/s, ``[...]``, > 0.
        direction, method: as :class:`LTIMultisineTrajectory`.

    Batch shape ``[...]`` = broadcast of amplitude, omega and direction's leading dims.

    Example:
        >>> p = Plant(num=(1.0,), den=(1e-3, 1.0))
        >>> traj = LTISineTrajectory(p, amplitude=torch.tensor([2.0, 3.0]), omega=2 * math.pi * 50)
        >>> traj.position(torch.zeros(2, 5, dtype=torch.float64)).shape
        torch.Size([2, 5, 2])
    """

    __slots__ = ()

    def __init__(self, plant: Plant, amplitude, omega, *, direction=(1.0, 0.0), method: str = "auto"):
        f64 = torch.float64
        amplitude = as_tensor(amplitude, "amplitude", dtype=f64)
        omega = as_tensor(omega, "omega", dtype=f64)
        super().__init__(plant, amplitude[..., None], omega[..., None], direction=direction, method=method)

    def steady_state_amplitude(self) -> torch.Tensor:
        """``|amplitude| |H(j omega)|`` (output units), ``[...]``."""
        return super().steady_state_amplitude()[..., 0]

    def steady_state_phase(self) -> torch.Tensor:
        """Phase (rad, in (-pi, pi]) of the steady-state y relative to u, delay included:
        ``angle(H(j omega))`` (plus pi for a negative amplitude), ``[...]``."""
        return super().steady_state_phase()[..., 0]

    def __repr__(self) -> str:
        return f"LTISineTrajectory(shape={tuple(self.shape)}, order={self.plant.order}, method={self.method!r})"
