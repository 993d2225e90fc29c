"""What a DM run takes, from its config alone: the plan (:func:`dm_plan`) and its frames
(:func:`dm_sweep_size`), counted by :func:`torchblur.identify.config.estimate_run` before any
work so that the size guard sees the real frame count.

The plan depends only on the geometry: the mirror's actuator grid and influence functions
(``dm.n_across``, ``dm.coupling``) and the sensor (``wfs``), through the nominal geometry
matrix G, never on the dynamics (so ``dm.actuator_table`` is not read here). The run
(:class:`torchblur.identify.dm_plan.DMPlan`) chooses its plan with the same function.

A leaf of the DM package: it imports nothing of ``torchblur.identify`` (the settings module
imports it).
"""
from __future__ import annotations

import copy
from dataclasses import replace

import math

import numpy as np
import torch

from torchblur.design.windows import MIN_SEPARATION, alias_separation, dual_exposure_windows
from torchblur.errors import ConfigError, ParameterError
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.plans import choose_plan
from torchblur.dm.shack_hartmann import ShackHartmann

__all__ = ["DM_DARK_FRAMES", "DM_STILL_FRAMES", "STILL_BYTES", "check_dm_exposures", "dm_geometry", "dm_plan", "dm_still_frames",
           "dm_sweep_size", "dm_sensor"]

# The DM run's stds are small (0.03 % on a DC gain): each spot's PSF, fitted from the still frames
# and held fixed, and the dark mean subtracted from every frame must be known better than that.
DM_DARK_FRAMES = 256
DM_STILL_FRAMES = 128  #: the fewest still frames a DM run takes (dm_still_frames)
STILL_BYTES = 1 << 28  #: the still frames a DM run holds at once (float64), at most this many bytes


def dm_still_frames(sweep_frames: int, frame_shape) -> int:
    """The still frames a DM calibration takes: a quarter of the sweep's frames, at least
    :data:`DM_STILL_FRAMES`, and no more than :data:`STILL_BYTES` of float64 frames of
    ``frame_shape`` ``(H, W)`` hold (but never fewer than the least).

    Why: every fit of a spot holds its PSF fixed, so the PSF's error is common to every pattern
    and frequency of that spot and no fit's std counts it; an actuator's DC gain, which averages
    its spots over the whole sweep, then carries it at full size. Measured on
    configs/identify_dm.yaml (4096 sweep frames): rms(DC gain error / std) over the 51 live
    actuators 1.77 with 128 still frames, 1.24 with 1024 (a quarter), 1.30 with 2048, and 1.22
    with 2048 dark frames as well (the dark frames are not the limit: 256 kept)."""
    H, W = (int(v) for v in frame_shape)
    cap = max(DM_STILL_FRAMES, STILL_BYTES // (8 * H * W))
    return int(min(cap, max(DM_STILL_FRAMES, -(-int(sweep_frames) // 4))))


def dm_sensor(cfg) -> tuple[DeformableMirror, ShackHartmann]:
    """The nominal mirror (geometry only: no actuator table) and the sensor of a DM config."""
    mirror = DeformableMirror.from_config(replace(cfg.dm, actuator_table=None), seed=int(cfg.seed))
    return mirror, ShackHartmann.from_config(cfg.wfs, mirror)


# G and the plan take minutes on a big mirror (700 actuators: 80 s and 23 s); estimate_run (at every
# config load) and the run share them through these memos of pure functions, keyed by the config's
# sections they depend on.
_MEMO: dict = {}
_MEMO_SIZE = 8


def _memo(key, compute):
    if key not in _MEMO:
        while len(_MEMO) >= _MEMO_SIZE:
            _MEMO.pop(next(iter(_MEMO)))
        _MEMO[key] = compute()
    return _MEMO[key]


def _geometry_key(cfg) -> str:
    return repr((replace(cfg.dm, actuator_table=None), cfg.wfs, int(cfg.seed)))


def dm_geometry(cfg) -> np.ndarray:
    """The nominal geometry matrix G ``[2M, N]`` (px per input unit) of a DM config (``dm``
    geometry and ``wfs``; the dynamics and the actuator table play no part). A new array each call."""
    def compute():
        mirror, wfs = dm_sensor(cfg)
        return wfs.geometry_matrix(mirror)

    return _memo(("G", _geometry_key(cfg)), compute).copy()


def dm_plan(cfg):
    """``(plan, n_repeats, info)`` of a DM config on its geometry :func:`dm_geometry`
    (:func:`~torchblur.dm.plans.choose_plan` with the ``dm_plan`` and ``sweep`` sections).

    Raises:
        ParameterError: naming ``dm_plan.budget_frames`` when one repeat of the plan needs more.
    """
    n_freq, n_exp = len(cfg.frequencies_hz()), len(cfg.sweep.exposures)

    def compute():
        return choose_plan(cfg.dm_plan.kind, dm_geometry(cfg), budget_frames=cfg.dm_plan.budget_frames, n_freq=n_freq,
                           n_exposures=n_exp, threshold=float(cfg.dm_plan.support_threshold), n_repeats=cfg.dm_plan.n_repeats)

    plan, R, info = _memo(("plan", _geometry_key(cfg), repr(cfg.dm_plan), n_freq, n_exp), compute)
    return plan, R, copy.deepcopy(info)


def dm_sweep_size(cfg) -> dict:
    """A DM config's sweep: ``frames`` (patterns x frequencies x exposures x repeats),
    ``patterns``, ``repeats`` and the sensor camera's ``frame_shape`` ``(H, W)`` px.

    Raises:
        ConfigError: naming ``dm_plan.budget_frames`` when one repeat of the plan needs more;
            naming ``sweep.exposures`` when they do not resolve the alias (:func:`check_dm_exposures`).
    """
    check_dm_exposures(cfg.sweep.exposures)
    try:
        plan, R, _ = dm_plan(cfg)
    except ParameterError as exc:
        raise ConfigError(str(exc)) from None
    frames = plan.n_frames(len(cfg.frequencies_hz()), len(cfg.sweep.exposures), R)
    shape = tuple(int(v) for v in dm_sensor(cfg)[1].frame_shape)
    return {"frames": frames, "patterns": plan.n_patterns, "repeats": R, "frame_shape": shape}


def check_dm_exposures(exposures) -> None:
    """Refuse a DM sweep whose exposures (fractions of the period, from one trigger) do not
    resolve the alias (:func:`~torchblur.design.windows.alias_separation` below
    :data:`~torchblur.design.windows.MIN_SEPARATION`): one exposure, or centres that coincide
    mod half a period. The DM route fits every spot at every frequency on its own and has no
    continuity rule for the branch (a sine run's :func:`~torchblur.identify.assemble.alias_stage`),
    so it would give the alias as often as the phase. ConfigError naming ``sweep.exposures``."""
    win = dual_exposure_windows(torch.tensor(2 * math.pi, dtype=torch.float64), fractions=[float(e) for e in exposures])
    sep = float(alias_separation(torch.tensor(2 * math.pi, dtype=torch.float64), win))
    if sep < MIN_SEPARATION:
        why = "one exposure" if len(exposures) < 2 else "centres that coincide mod half a period"
        raise ConfigError(f"sweep.exposures: {list(exposures)} do not resolve the alias of a DM run (alias separation {sep:.3g}, "
                          f"below {MIN_SEPARATION}: {why}); "
                          f"each spot's phase would be its alias as often as not. Use two exposures whose centres are a quarter "
                          f"period apart, e.g. sweep.exposures=[0.3,0.8]")
