"""Acquisition design against the alias (PHYSICS.md section 2, "Alias").

With one exposure the phase has two branches, ``phi`` and ``pi - 2 c - phi`` (c: the phase
at the window centre). Two exposures whose centres differ resolve it; they are best a
quarter period apart (mod half a period), e.g. 30% and 80% of the period from a shared
start. With one exposure per point, either resolve the branches by continuity along the
sweep (:func:`resolve_branches`) or choose the trigger so the alias lies far from the
expected phase (:func:`trigger_phase_for`).
"""
from __future__ import annotations

import math
import warnings

import torch

from torchblur.render.alias import wrap_phase
from torchblur.errors import InputTypeError, ParameterError, as_tensor, check_finite, check_positive
from torchblur.render.window import ExposureWindow

__all__ = ["DesignWarning", "dual_exposure_windows", "alias_separation", "check_design", "trigger_phase_for", "resolve_branches"]


class DesignWarning(UserWarning):
    """An acquisition design that cannot identify the phase (or only poorly)."""


def dual_exposure_windows(omega, *, fractions=(0.3, 0.8), trigger_phase=math.pi / 2) -> ExposureWindow:
    """Exposure windows sharing a start, with durations as fractions of the period.

    Args:
        omega: rad/s, ``[...]``.
        fractions: exposure durations as fractions of the period (E of them); the default
            (0.3, 0.8) puts the two window centres a quarter period apart.
        trigger_phase: ``omega * tcam`` (rad), ``[...]`` or a number.

    Returns:
        :class:`ExposureWindow` with batch ``[..., E]``.
    """
    omega = check_positive(as_tensor(omega, "omega", dtype=torch.float64 if not isinstance(omega, torch.Tensor) else None), "omega")
    fr = check_positive(as_tensor(list(fractions), "fractions", like=omega), "fractions")
    b = check_finite(as_tensor(trigger_phase, "trigger_phase", like=omega), "trigger_phase")
    period = 2 * math.pi / omega
    start = (torch.remainder(b, 2 * math.pi) / omega)[..., None]
    return ExposureWindow(start.expand(start.shape[:-1] + fr.shape), period[..., None] * fr)


def alias_separation(omega, window: ExposureWindow) -> torch.Tensor:
    """How well the exposures of a point resolve the alias, ``[...]`` in [0, 1].

    ``max_{i<j} |sin(c_i - c_j)|`` over window centres ``c = omega (tcam + Te/2)`` of the
    last axis ``E`` (1: centres a quarter period apart, the best; 0: one exposure, or
    centres that coincide mod half a period, which resolve nothing). Also 0 where an
    exposure is a whole number of periods (that image carries no phase).
    """
    if not isinstance(window, ExposureWindow):
        raise InputTypeError(f"window: expected an ExposureWindow, got {type(window).__name__}")
    omega = check_positive(as_tensor(omega, "omega", like=window.start), "omega")
    c = omega[..., None] * window.center
    p = omega[..., None] * window.duration
    if c.shape[-1] < 2:
        return torch.zeros(c.shape[:-1], dtype=c.dtype, device=c.device)
    d = (c[..., :, None] - c[..., None, :]).sin().abs()
    d = d.flatten(-2).amax(-1)
    whole = (torch.sin(p / 2).abs() < 1e-3).any(-1)
    return torch.where(whole, torch.zeros_like(d), d)


def check_design(omega, window: ExposureWindow, *, min_separation: float = 0.2, warn: bool = True) -> list[str]:
    """Problems of a design (omega ``[...]``, window ``[..., E]``) as messages; warned as
    :class:`DesignWarning` if ``warn``. Detects exposures of a whole number of periods
    (phase unidentifiable) and exposures whose centres coincide mod half a period (the
    alias is not resolved)."""
    if not isinstance(window, ExposureWindow):
        raise InputTypeError(f"window: expected an ExposureWindow, got {type(window).__name__}")
    omega = check_positive(as_tensor(omega, "omega", like=window.start), "omega")
    msgs = []
    p = omega[..., None] * window.duration
    whole = torch.sin(p / 2).abs() < 1e-3
    if bool(whole.any()):
        msgs.append(f"{int(whole.sum())} exposure(s) last a whole number of periods: the image carries no phase")
    if window.shape and window.shape[-1] >= 2:
        sep = alias_separation(omega, window)
        poor = sep < min_separation
        if bool(poor.any()):
            msgs.append(f"{int(poor.sum())} point(s) have exposures whose centres nearly coincide mod half a period "
                        f"(separation {float(sep.min()):.3f} < {min_separation}): the alias is not resolved; "
                        "use centres a quarter period apart, e.g. dual_exposure_windows(omega, fractions=(0.3, 0.8))")
    else:
        msgs.append("one exposure per point: the phase has two branches; resolve them with resolve_branches() "
                    "or trigger_phase_for(), or use two exposures")
    if warn:
        for m in msgs:
            warnings.warn(m, DesignWarning, stacklevel=2)
    return msgs


def trigger_phase_for(expected_phase, exposure_fraction) -> torch.Tensor:
    """Trigger phase ``b = omega tcam`` (rad, in [0, 2 pi)) that puts the alias of a single
    exposure pi away from ``expected_phase`` (rad): the window centre's phase is
    ``c = -expected_phase (mod pi)``. ``exposure_fraction``: Te as a fraction of the period."""
    phi = check_finite(as_tensor(expected_phase, "expected_phase", dtype=None if isinstance(expected_phase, torch.Tensor) else torch.float64), "expected_phase")
    frac = check_positive(as_tensor(exposure_fraction, "exposure_fraction", like=phi), "exposure_fraction")
    p = 2 * math.pi * frac
    return torch.remainder(-phi - p / 2, math.pi)


def resolve_branches(omega, phase, alias, *, anchor_phase=0.0, delay_s=0.0) -> torch.Tensor:
    """Pick one branch per frequency along a sweep (single-exposure continuity).

    Plain nearest-neighbour continuity fails after each branch crossing (with the paper's
    settings, at -90 degrees, right at a resonance). Here the first point is anchored at
    the expected low-frequency phase ``anchor_phase - omega delay_s``, and each later
    point takes the branch nearest to the linear extrapolation of the unwrapped phase of
    the two previous points (smooth slope across crossings).

    Args:
        omega: rad/s, ``[F]``, increasing.
        phase, alias: the two candidates per frequency (rad), ``[F]``.

    Returns:
        the chosen phase ``[F]`` (wrapped to (-pi, pi]).
    """
    omega = check_positive(as_tensor(omega, "omega", dtype=torch.float64), "omega")
    a = check_finite(as_tensor(phase, "phase", like=omega), "phase")
    b = check_finite(as_tensor(alias, "alias", like=omega), "alias")
    if not (omega.dim() == a.dim() == b.dim() == 1 and omega.shape == a.shape == b.shape):
        raise ParameterError(f"phase: expected 1-D tensors of the same length as omega {tuple(omega.shape)}")
    if bool((omega.diff() <= 0).any()):
        raise ParameterError("omega: expected strictly increasing frequencies")
    F = omega.numel()
    out = torch.empty_like(a)
    unwrapped = []
    for k in range(F):
        if k == 0:
            pred = anchor_phase - float(omega[0]) * delay_s
        elif k == 1:
            pred = unwrapped[0] - (float(omega[1]) - float(omega[0])) * delay_s
        else:
            slope = (unwrapped[-1] - unwrapped[-2]) / float(omega[k - 1] - omega[k - 2])
            pred = unwrapped[-1] + slope * float(omega[k] - omega[k - 1])
        cands = torch.stack([a[k], b[k]])
        dist = wrap_phase(cands - pred).abs()
        choice = cands[int(dist.argmin())]
        out[k] = choice
        unwrapped.append(pred + float(wrap_phase(choice - pred)))
    return wrap_phase(out)
