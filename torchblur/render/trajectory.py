"""Trajectories: the spot's displacement from its rest position over time.

Every trajectory maps times ``t`` (s, shape ``[..., S]``) to displacements (px, shape
``[..., S, 2]``, last axis (x, y)), is batched over leading dims and differentiable in its
parameters. Conventions (PHYSICS.md section 2): ``A sin(omega t + phase)``, t = 0 at an
upward zero crossing of the command, phases in radians, ``omega`` in rad/s.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor, broadcast_batch, check_finite, check_positive, check_trailing_shape
from torchblur.render.window import ExposureWindow

__all__ = ["Trajectory", "Sinusoid", "Multisine", "SplineTrajectory"]


class Trajectory:
    """Interface of a trajectory. Subclasses define :meth:`position` and :meth:`path_length`."""

    @property
    def shape(self) -> torch.Size:  # pragma: no cover - interface
        raise NotImplementedError

    def position(self, t: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """Displacement (px) ``[..., S, 2]`` at times ``t`` (s) ``[..., S]``."""
        raise NotImplementedError

    def path_length(self, window: ExposureWindow) -> torch.Tensor:  # pragma: no cover - interface
        """An upper bound of the path length (px) travelled during ``window``, ``[...]``,
        without gradient. The renderer chooses its time nodes from it."""
        raise NotImplementedError

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        """The phase (rad) the motion's fastest oscillation advances during ``window``,
        ``[...]``, without gradient. The renderer gives every panel of time nodes at most
        ``RenderSettings.panel_phase_rad`` of it, so a short path over a long time (a small
        motion over most of a period) is still integrated exactly. Default 0: the path
        length alone sets the nodes."""
        return torch.zeros(torch.broadcast_shapes(self.shape, window.shape), dtype=torch.float64)


def _abs_cos_integral(theta: torch.Tensor) -> torch.Tensor:
    """``G(theta) = integral_0^theta |cos u| du = 2k + (-1)^k sin(theta)``, ``k = floor((theta + pi/2) / pi)``."""
    k = torch.floor((theta + math.pi / 2) / math.pi)
    sign = 1 - 2 * torch.remainder(k, 2)
    return 2 * k + sign * torch.sin(theta)


def _sine_path_bound(amplitude, omega, phase, start, duration) -> torch.Tensor:
    """Per-axis path length (total variation) of ``A sin(w t + p)`` over ``[start, start + duration]``:
    ``|A| (G(w (start + duration) + p) - G(w start + p))``, exact."""
    th0 = omega * start + phase
    th1 = th0 + omega * duration
    return amplitude.abs() * (_abs_cos_integral(th1) - _abs_cos_integral(th0))


class Sinusoid(Trajectory):
    """``y_k(t) = amplitude_k sin(omega_k t + phase_k)`` per axis k in (x, y).

    Args:
        amplitude: px, ``[..., 2]`` (x, y). Use 0 on an axis that does not move.
        phase: rad, ``[..., 2]``.
        omega: rad/s, ``[...]`` (both axes) or ``[..., 2]`` (one per axis), > 0. A last dim
            of 2 is always read as one frequency per axis: for a batch of two items with one
            frequency each, pass ``omega[..., None].expand(..., 2)`` (or ``omega[:, None]``
            with ``amplitude`` ``[2, 1, 2]``).

    A tip-tilt mirror driven on both axes draws a Lissajous figure.
    """

    __slots__ = ("amplitude", "phase", "omega")

    def __init__(self, amplitude, phase, omega):
        amplitude = as_tensor(amplitude, "amplitude")
        phase = as_tensor(phase, "phase", like=amplitude)
        omega = as_tensor(omega, "omega", like=amplitude)
        check_trailing_shape(amplitude, "amplitude", (2,), "[..., 2] (x, y in px)")
        check_trailing_shape(phase, "phase", (2,), "[..., 2] (x, y in rad)")
        check_finite(amplitude, "amplitude")
        check_finite(phase, "phase")
        check_positive(omega, "omega")
        if omega.dim() == 0 or omega.shape[-1] != 2:
            omega = omega[..., None].expand(omega.shape + (2,))
        shape = broadcast_batch({"amplitude": amplitude.shape[:-1], "phase": phase.shape[:-1], "omega": omega.shape[:-1]})
        self.amplitude = amplitude.expand(shape + (2,))
        self.phase = phase.expand(shape + (2,))
        self.omega = omega.expand(shape + (2,))

    @property
    def shape(self) -> torch.Size:
        return self.amplitude.shape[:-1]

    def position(self, t: torch.Tensor) -> torch.Tensor:
        t = t[..., None]
        return self.amplitude[..., None, :] * torch.sin(self.omega[..., None, :] * t + self.phase[..., None, :])

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        s, d = window.start.detach()[..., None], window.duration.detach()[..., None]
        return _sine_path_bound(self.amplitude.detach(), self.omega.detach(), self.phase.detach(), s, d).sum(-1)

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        return self.omega.detach().abs().amax(-1) * window.duration.detach()

    def __getitem__(self, idx) -> "Sinusoid":
        return Sinusoid(self.amplitude[idx], self.phase[idx], self.omega[idx])

    def to(self, *args, **kwargs) -> "Sinusoid":
        return Sinusoid(*(v.to(*args, **kwargs) for v in (self.amplitude, self.phase, self.omega)))


class Multisine(Trajectory):
    """A sum of N tones: ``y_k(t) = sum_n amplitude_nk sin(omega_nk t + phase_nk)``.

    Args:
        amplitude: px, ``[..., N, 2]``.
        phase: rad, ``[..., N, 2]``.
        omega: rad/s, ``[..., N]`` or ``[..., N, 2]``, > 0.
    """

    __slots__ = ("amplitude", "phase", "omega")

    def __init__(self, amplitude, phase, omega):
        amplitude = as_tensor(amplitude, "amplitude")
        phase = as_tensor(phase, "phase", like=amplitude)
        omega = as_tensor(omega, "omega", like=amplitude)
        if amplitude.dim() < 2:
            raise ShapeError(f"amplitude: expected shape [..., N, 2], got {tuple(amplitude.shape)}")
        check_trailing_shape(amplitude, "amplitude", (amplitude.shape[-2], 2), "[..., N, 2]")
        check_trailing_shape(phase, "phase", tuple(amplitude.shape[-2:]), f"[..., {amplitude.shape[-2]}, 2]")
        check_finite(amplitude, "amplitude")
        check_finite(phase, "phase")
        check_positive(omega, "omega")
        if omega.dim() >= 2 and omega.shape[-2:] == amplitude.shape[-2:]:
            pass
        elif omega.dim() >= 1 and omega.shape[-1] == amplitude.shape[-2]:
            omega = omega[..., None].expand(omega.shape + (2,))
        else:
            raise ShapeError(
                f"omega: expected shape [..., {amplitude.shape[-2]}] or [..., {amplitude.shape[-2]}, 2], got {tuple(omega.shape)}"
            )
        shape = broadcast_batch({"amplitude": amplitude.shape[:-2], "phase": phase.shape[:-2], "omega": omega.shape[:-2]})
        tail = tuple(amplitude.shape[-2:])
        self.amplitude = amplitude.expand(shape + tail)
        self.phase = phase.expand(shape + tail)
        self.omega = omega.expand(shape + tail)

    @property
    def shape(self) -> torch.Size:
        return self.amplitude.shape[:-2]

    @property
    def n_tones(self) -> int:
        return self.amplitude.shape[-2]

    def position(self, t: torch.Tensor) -> torch.Tensor:
        t = t[..., :, None, None]  # [..., S, 1, 1]
        arg = self.omega[..., None, :, :] * t + self.phase[..., None, :, :]
        return (self.amplitude[..., None, :, :] * torch.sin(arg)).sum(-2)

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        s, d = window.start.detach()[..., None, None], window.duration.detach()[..., None, None]
        return _sine_path_bound(self.amplitude.detach(), self.omega.detach(), self.phase.detach(), s, d).sum((-1, -2))

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        return self.omega.detach().abs().amax((-1, -2)) * window.duration.detach()

    def to(self, *args, **kwargs) -> "Multisine":
        return Multisine(*(v.to(*args, **kwargs) for v in (self.amplitude, self.phase, self.omega)))


class SplineTrajectory(Trajectory):
    """A free-form trajectory: a natural cubic spline through knots (for learned models).

    Args:
        times: knot times in seconds, ``[..., K]``, strictly increasing, K >= 2.
        values: displacements at the knots in px, ``[..., K, 2]``.

    Outside ``[times[0], times[-1]]`` the spline holds its end values. Differentiable in
    ``values`` and ``times``.
    """

    __slots__ = ("times", "values", "_m")

    def __init__(self, times, values):
        values = as_tensor(values, "values")
        times = as_tensor(times, "times", like=values)
        if values.dim() < 2 or values.shape[-1] != 2 or values.shape[-2] < 2:
            raise ShapeError(f"values: expected shape [..., K, 2] with K >= 2, got {tuple(values.shape)}")
        if times.dim() < 1 or times.shape[-1] != values.shape[-2]:
            raise ShapeError(f"times: expected shape [..., {values.shape[-2]}] matching values, got {tuple(times.shape)}")
        check_finite(values, "values")
        check_finite(times, "times")
        if bool((times.detach().diff(dim=-1) <= 0).any()):
            raise ParameterError("times: expected strictly increasing knot times")
        shape = broadcast_batch({"times": times.shape[:-1], "values": values.shape[:-2]})
        K = values.shape[-2]
        self.times = times.expand(shape + (K,))
        self.values = values.expand(shape + (K, 2))
        self._m = self._second_derivatives()

    @property
    def shape(self) -> torch.Size:
        return self.times.shape[:-1]

    def _second_derivatives(self) -> torch.Tensor:
        """Second derivatives at the knots of the natural spline, ``[..., K, 2]``."""
        t, v = self.times, self.values
        K = t.shape[-1]
        if K == 2:
            return torch.zeros_like(v)
        h = t.diff(dim=-1)  # [..., K-1]
        dv = v.diff(dim=-2) / h[..., None]  # [..., K-1, 2]
        rhs = 6 * (dv[..., 1:, :] - dv[..., :-1, :])  # [..., K-2, 2]
        n = K - 2
        diag = 2 * (h[..., :-1] + h[..., 1:])
        M = torch.diag_embed(diag)
        if n > 1:
            off = h[..., 1:-1]
            M = M + torch.diag_embed(off, 1) + torch.diag_embed(off, -1)
        inner = torch.linalg.solve(M, rhs)
        z = torch.zeros_like(v[..., :1, :])
        return torch.cat([z, inner, z], -2)

    def position(self, t: torch.Tensor) -> torch.Tensor:
        knots = self.times
        K = knots.shape[-1]
        batch = torch.broadcast_shapes(t.shape[:-1], knots.shape[:-1])
        tk = knots.expand(batch + (K,))
        tq = t.expand(batch + t.shape[-1:])
        tc = torch.minimum(torch.maximum(tq, tk[..., :1]), tk[..., -1:])
        idx = torch.searchsorted(tk.detach().contiguous(), tc.detach().contiguous(), right=True) - 1
        idx = idx.clamp(0, K - 2)
        t0 = tk.gather(-1, idx)
        t1 = tk.gather(-1, idx + 1)
        vv = self.values.expand(batch + (K, 2))
        mm = self._m.expand(batch + (K, 2))
        i2 = idx[..., None].expand(idx.shape + (2,))
        v0, v1 = vv.gather(-2, i2), vv.gather(-2, i2 + 1)
        m0, m1 = mm.gather(-2, i2), mm.gather(-2, i2 + 1)
        h = (t1 - t0)[..., None]
        a = ((t1 - tc)[..., None]) / h
        b = 1 - a
        return a * v0 + b * v1 + ((a**3 - a) * m0 + (b**3 - b) * m1) * h * h / 6

    def to(self, *args, **kwargs) -> "SplineTrajectory":
        return SplineTrajectory(self.times.to(*args, **kwargs), self.values.to(*args, **kwargs))

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        with torch.no_grad():
            K = self.times.shape[-1]
            n = 16 * (K - 1) + 1
            u = torch.linspace(0, 1, n, dtype=self.times.dtype, device=self.times.device)
            t = window.start[..., None] + window.duration[..., None] * u
            p = self.position(t)
            return p.diff(dim=-2).norm(dim=-1).sum(-1) * 1.05 + 1e-3
