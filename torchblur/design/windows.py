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
from typing import NamedTuple

import numpy as np
import torch

from torchblur.render.alias import MIN_SEPARATION, alias_separation, wrap_phase  # noqa: F401  (design names too)
from torchblur.render.alias import window_center_phase
from torchblur.errors import ParameterError, as_tensor, check_finite, check_positive, check_type
from torchblur.render.window import ExposureWindow

__all__ = ["DesignWarning", "dual_exposure_windows", "alias_separation", "check_design", "trigger_phase_for", "resolve_branches",
           "Continuity", "continuity_branches", "crossing_phase", "ANCHOR_STD_RAD", "CONTINUITY_Z", "MIN_SEPARATION"]

#: the continuity rule's std of the anchor (the phase expected at the sweep's lowest frequency), rad
ANCHOR_STD_RAD = math.radians(10.0)
#: the continuity rule decides a point only where its prediction lies this many of its stds from the branches' crossing
CONTINUITY_Z = 3.0


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


def check_design(omega, window: ExposureWindow, *, min_separation: float = 0.2, warn: bool = True) -> list[str]:
    """Problems of a design (omega ``[...]``, window ``[..., E]``) as messages; warned as
    :class:`DesignWarning` if ``warn``. Detects exposures of a whole number of periods
    (phase unidentifiable) and exposures whose centres coincide mod half a period (the
    alias is not resolved)."""
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
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
        msgs.append(_single_exposure_message(omega, window))
    if warn:
        for m in msgs:
            warnings.warn(m, DesignWarning, stacklevel=2)
    return msgs


def _single_exposure_message(omega, window: ExposureWindow) -> str:
    """The design check's words on one exposure per point: where the branches cross, and
    whether the lowest frequency's phase (near 0) can anchor the continuity rule."""
    x = torch.rad2deg(crossing_phase(omega, window[..., 0])).reshape(-1)
    lo = float(x[int(torch.argmin(omega.reshape(-1)))]) if omega.dim() else float(x[0])
    near = min(abs(math.remainder(lo, 180.0)), 180.0 - abs(math.remainder(lo, 180.0)))
    where = f"{lo:.0f} deg" if bool((x - x[0]).abs().max() < 1e-6) else f"{lo:.0f} deg at the lowest frequency (it moves along the sweep)"
    msg = (f"one exposure per point: the phase has two branches (the alias), crossing at {where} and 180 deg from it; the "
           f"continuity rule (continuity_branches) chooses them along the sweep and flags alias the points it cannot decide "
           f"(near a crossing, past a resonance, across a gap in the sweep): such a run is never trustworthy; use two "
           f"exposures (e.g. [0.3, 0.8]) or trigger_phase_for()")
    if near < 3 * math.degrees(ANCHOR_STD_RAD):
        msg += (f". The crossing lies {near:.0f} deg from the phase 0 expected at the lowest frequency: the rule cannot "
                f"anchor the sweep and will flag every point; choose another trigger phase")
    return msg


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
    the two previous points (smooth slope across crossings): the primary choice of
    :func:`continuity_branches`, which also says where the choice is uncertain.

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
    r = continuity_branches(omega, a, b, anchor_phase=anchor_phase, delay_s=delay_s, max_hypotheses=1)
    return wrap_phase(torch.as_tensor(r.phase, dtype=a.dtype, device=a.device))


def crossing_phase(omega, window: ExposureWindow) -> torch.Tensor:
    """Where a single exposure's two branches cross, rad ``[...]`` wrapped to (-pi, pi]:
    ``(pi - 2 c) / 2`` with ``c`` the phase at the window centre (PHYSICS.md, "Alias"); the
    branches also cross at this value plus pi. A point whose phase lies near it cannot be
    told from its alias by any rule; a resonance that carries the phase across it within a
    few points of the sweep makes continuity uncertain there."""
    return wrap_phase((math.pi - 2 * window_center_phase(omega, window)) / 2)


class Continuity(NamedTuple):
    """Result of :func:`continuity_branches`, each ``[F]`` in the sweep's order.

    Attributes:
        phase: the chosen phase (rad, wrapped to (-pi, pi]); NaN where the point is not valid.
        took_alias: the second candidate (``alias``) was chosen.
        decided: the rule decided the branch with confidence (also True where the two
            branches agree within the point's stds, and where the point is not valid).
        margin: the primary prediction's distance from the branches' crossing over its std
            (inf where the branches agree within the stds; NaN where not valid).
    """

    phase: np.ndarray
    took_alias: np.ndarray
    decided: np.ndarray
    margin: np.ndarray


def _np(x, name: str, n: int | None = None) -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x, dtype=np.float64)
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        raise ParameterError(f"{name}: expected a 1-D array of {n if n is not None else 'F'} values, got shape {a.shape}")
    return a


def _wrap(x):
    """Radians wrapped to (-pi, pi] (numpy; :func:`~torchblur.render.alias.wrap_phase` for tensors)."""
    return math.pi - np.remainder(math.pi - np.asarray(x, dtype=np.float64), 2 * math.pi)


def _predict(nodes, w: float, delay_s: float, anchor_std: float) -> tuple[float, float]:
    """Prediction (rad, unwrapped) and its std at ``w`` from the last nodes ``(omega, phase, std)``
    of a branch history (the first node is the anchor at omega 0, std 0: the DC phase is exact):
    the straight line through the last two nodes; its std holds their stds carried along the
    line and the gap to the parabola through the last three (how fast the slope was changing,
    less twice that change's own noise).
    The first point's prediction is the anchor less the delay's phase, std ``anchor_std``."""
    (wb, fb, sb) = nodes[-1]
    if len(nodes) == 1:  # the anchor alone: its phase less the delay's
        return fb - w * delay_s, anchor_std
    (wa, fa, sa) = nodes[-2]
    r = (w - wb) / (wb - wa)
    p = fb + (fb - fa) * r
    u2 = (sb * (1 + r)) ** 2 + (sa * r) ** 2
    if len(nodes) >= 3:
        (wc, fc, sc) = nodes[-3]
        s1, s0 = (fb - fa) / (wb - wa), (fa - fc) / (wa - wc)
        # the slope's change beyond twice its own noise (noisy phases near the anchor fake a bend)
        noise = math.sqrt((sb / (wb - wa)) ** 2 + (sa * (1 / (wb - wa) + 1 / (wa - wc))) ** 2 + (sc / (wa - wc)) ** 2)
        bend = max(abs(s1 - s0) - 2 * noise, 0.0)
        u2 += ((bend / (wb - wc)) * (w - wa) * (w - wb)) ** 2
    return p, math.sqrt(u2)


def _bode_std(om: np.ndarray, mag: np.ndarray | None, ks: list, k: int) -> float:
    """The phase change the magnitude announces between the previous valid points ``ks[-2:]``
    and ``k``: pi/2 times the change of the slope of ln|H| over ln omega (Bode's gain-phase
    relation of a minimum-phase system: a resonance between two points shows in the magnitude
    though the phase cannot be followed across it). 0 without magnitudes or two points before."""
    if mag is None or len(ks) < 2:
        return 0.0
    a, b = ks[-2], ks[-1]
    lm, lw = np.log(mag[[a, b, k]]), np.log(om[[a, b, k]])
    if not np.isfinite(lm).all():
        return 0.0
    return 0.5 * math.pi * abs((lm[2] - lm[1]) / (lw[2] - lw[1]) - (lm[1] - lm[0]) / (lw[1] - lw[0]))


def continuity_branches(omega, phase, alias, phase_std=None, *, magnitude=None, valid=None, anchor_phase: float = 0.0, delay_s: float = 0.0,
                        z: float = CONTINUITY_Z, anchor_std: float = ANCHOR_STD_RAD, max_hypotheses: int = 16) -> Continuity:
    """Choose each point's phase branch along a single-exposure sweep, and say where the
    choice is not certain (the continuity rule of docs/reliability.md, "One exposure per point").

    The rule. Points are taken in frequency order from an anchor: phase ``anchor_phase`` at
    omega 0 (a plant with a positive DC gain), std ``anchor_std``. Each point's phase is
    predicted by the straight line through the two previous chosen phases (the first point:
    through the anchor with slope ``-delay_s``; the second: through the anchor and the first),
    with a std that holds the stds of those phases, the gap to the parabola through the
    last three (how fast the slope is changing, beyond twice the noise of that change) and, with ``magnitude``, pi/2 times the change
    of the log-log slope of the magnitude from the two previous points to this one (Bode's
    gain-phase relation: a resonance between points shows in the magnitude, which has no
    alias, though the phase cannot be followed across it). The point takes the branch nearer the
    prediction. The choice is *decided* when the prediction lies at least ``z`` of its stds
    from the branches' crossing (the phase equally far from both), or when the two branches
    agree within the point's phase std (either is then right within it). Where it is not
    decided both branches are followed as hypotheses (the nearer one first, as the primary);
    a later point is decided only when every hypothesis alive takes the same branch there,
    decidedly. Hypotheses whose last three choices agree merge. Past ``max_hypotheses`` no
    later point is decided.

    Args:
        omega: rad/s ``[F]``, strictly increasing over the valid points.
        phase, alias: the two candidates of each point (rad) ``[F]``; a point whose exposures
            resolved the alias passes its phase as both.
        phase_std: ``[F]`` rad (None: 0).
        magnitude: ``[F]`` |H| (None: the Bode term is left out).
        valid: bool ``[F]`` (None: where phase and alias are finite); other points are skipped.
        anchor_phase, delay_s: the anchor (rad at omega 0) and its slope (s).
        z, anchor_std, max_hypotheses: the rule's constants (rad for ``anchor_std``).

    Returns:
        :class:`Continuity`.
    """
    om = _np(omega, "omega")
    F = om.shape[0]
    a, b = _np(phase, "phase", F), _np(alias, "alias", F)
    mag = None if magnitude is None else np.abs(_np(magnitude, "magnitude", F))
    sd = np.zeros(F) if phase_std is None else np.nan_to_num(_np(phase_std, "phase_std", F), nan=0.0)
    ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(om)
    if valid is not None:
        ok &= np.broadcast_to(np.asarray(valid, dtype=bool), (F,))
    if bool((np.diff(om[ok]) <= 0).any()):
        raise ParameterError("omega: expected strictly increasing frequencies over the valid points")
    if not (z > 0 and anchor_std > 0):
        raise ParameterError(f"z, anchor_std: expected positive numbers, got {z}, {anchor_std}")
    out = Continuity(np.full(F, np.nan), np.zeros(F, dtype=bool), np.ones(F, dtype=bool), np.full(F, np.nan))
    states = [[(0.0, float(anchor_phase), 0.0)]]  # each: the nodes of one branch history
    overflow, ks = False, []
    for k in np.flatnonzero(ok):
        u_bode = _bode_std(om, mag, ks, k)
        ks.append(k)
        cand = np.array([a[k], b[k]])
        agree = abs(float(_wrap(a[k] - b[k]))) <= 2 * sd[k]
        mid = math.atan2(math.sin(a[k]) + math.sin(b[k]), math.cos(a[k]) + math.cos(b[k]))
        new, chosen, picks, margins = [], [], set(), []
        for nodes in states:
            p, u = _predict(nodes, float(om[k]), delay_s, anchor_std)
            u = math.hypot(u, u_bode)
            d = np.abs(_wrap(cand - p))
            near = int(d[1] < d[0])
            dm = abs(float(_wrap(p - mid)))
            margin = math.inf if agree else min(dm, math.pi - dm) / max(u, 1e-12)
            margins.append(margin)
            sure = margin >= z
            for c in ([near] if sure else [near, 1 - near]):
                new.append(nodes[-2:] + [(float(om[k]), p + float(_wrap(cand[c] - p)), float(sd[k]))])
                chosen.append(c)
                picks.add(c if sure else -1)
        out.phase[k], out.took_alias[k], out.margin[k] = _wrap(cand[chosen[0]]), chosen[0] == 1, margins[0]
        out.decided[k] = not overflow and len(picks) == 1 and -1 not in picks
        states = _merge(new)
        if len(states) > max_hypotheses:
            overflow, states = True, states[:max_hypotheses]
    return out


def _merge(states: list) -> list:
    """The branch histories with the same last three choices (the same future predictions) as one, first kept."""
    seen, out = set(), []
    for nodes in states:
        key = tuple((w, round(float(_wrap(f)), 9), round(f - nodes[-1][1], 9)) for w, f, _ in nodes[-3:])
        if key not in seen:
            seen.add(key)
            out.append(nodes)
    return out
