"""The alias of a sinusoid's phase (Proposition 3, with the sign of PHYSICS.md section 2).

Time reversal about the window centre maps ``M sin(w t + phi)`` to ``M sin(w t + phi2)``
with ``phi2 = pi - w (Te + 2 tcam) - phi = pi - 2 c - phi`` (mod 2 pi), where ``c`` is the
phase at the window centre. Both render exactly the same image; M has no alias.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import InputTypeError, as_tensor, check_finite, check_positive, check_type
from torchblur.render.window import ExposureWindow

__all__ = ["MIN_SEPARATION", "alias_phase", "alias_separation", "canonical_sines", "wrap_phase", "window_center_phase"]

#: alias_separation below this: the exposures of a point do not resolve the alias (one exposure, or centres that
#: coincide mod half a period); :func:`torchblur.design.windows.check_design` warns and the continuity rule decides the branch
MIN_SEPARATION = 0.2


def wrap_phase(phase: torch.Tensor) -> torch.Tensor:
    """Wrap radians to ``(-pi, pi]``, any shape (a tensor or a number; NaN stays NaN)."""
    if not isinstance(phase, torch.Tensor):
        phase = as_tensor(phase, "phase", dtype=torch.float64)
    elif phase.is_complex() or phase.dtype == torch.bool:
        raise InputTypeError(f"phase: expected a real tensor, got dtype {phase.dtype}")
    return math.pi - torch.remainder(math.pi - phase, 2 * math.pi)


def canonical_sines(theta: torch.Tensor, n: int) -> torch.Tensor:
    """``theta [..., P]`` (``n`` amplitudes, then their ``n`` phases in rad, then any other
    parameters) as a new tensor with every amplitude >= 0: ``(-M, phi)`` is the same sine as
    ``(M, phi + pi)``; the phases wrapped to ``(-pi, pi]``."""
    t = theta.clone()
    neg = t[..., :n] < 0
    t[..., :n] = t[..., :n].abs()
    t[..., n:2 * n] = wrap_phase(t[..., n:2 * n] + math.pi * neg)
    return t

def window_center_phase(omega, window: ExposureWindow) -> torch.Tensor:
    """``c = omega (tcam + Te / 2)`` (rad), broadcast of ``omega [...]`` and the window's ``[...]``."""
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
    omega = check_positive(as_tensor(omega, "omega", like=window.start), "omega")
    return omega * window.center


def alias_phase(phase, omega, window: ExposureWindow) -> torch.Tensor:
    """The other phase that renders the same single-exposure image.

    Args:
        phase: ``phi`` (rad), shape ``[...]`` (or ``[..., 2]`` per axis with ``omega [..., 1]``).
        omega: rad/s, ``[...]``, > 0.
        window: the exposure, batch ``[...]``.

    Returns:
        ``phi2 = pi - omega (Te + 2 tcam) - phi``, wrapped to ``(-pi, pi]``, broadcast shape.

    Example:
        >>> w = ExposureWindow(start=torch.tensor(0.25e-2), duration=0.5e-2)
        >>> alias_phase(torch.tensor(0.3), 2 * math.pi * 100, w)   # p = pi, b = pi/2: phi2 = -pi - phi
        tensor(2.8416)
    """
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
    phase = check_finite(as_tensor(phase, "phase", like=window.start), "phase")
    return wrap_phase(math.pi - 2 * window_center_phase(omega, window) - phase)


def alias_separation(omega, window: ExposureWindow) -> torch.Tensor:
    """How well the exposures of a point resolve the alias, ``[...]`` in [0, 1].

    ``max_{i<j} |sin(c_i - c_j)|`` over window centres ``c = omega (tcam + Te/2)`` of the
    last axis ``E`` (1: centres a quarter period apart, the best; 0: one exposure, or
    centres that coincide mod half a period, which resolve nothing). Also 0 where an
    exposure is a whole number of periods (that image carries no phase).
    """
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
    omega = check_positive(as_tensor(omega, "omega", like=window.start), "omega")
    c = omega[..., None] * window.center
    p = omega[..., None] * window.duration
    if c.shape[-1] < 2:
        return torch.zeros(c.shape[:-1], dtype=c.dtype, device=c.device)
    d = (c[..., :, None] - c[..., None, :]).sin().abs()
    d = d.flatten(-2).amax(-1)
    whole = (torch.sin(p / 2).abs() < 1e-3).any(-1)
    return torch.where(whole, torch.zeros_like(d), d)
