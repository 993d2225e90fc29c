"""What a run takes, from its config alone, and the limits it is refused beyond: the frames,
memory, disk and bench time (:func:`estimate_run`, :func:`check_limits` against :data:`LIMITS`),
the calibration's frame counts and the latency scan's constants (which
:mod:`torchblur.identify.calibration` takes from here, so that the estimate counts what it
takes); a DM run's closed-form size bounds (:func:`dm_size_bounds`), its plan (:func:`dm_plan`)
and its frames (:func:`dm_sweep_size`), so that the size guard sees the real frame count (the
plan depends on the geometry alone, :func:`dm_geometry`; the run chooses its plan with the same function).
"""
from __future__ import annotations

import copy
import math
from dataclasses import replace

import numpy as np
import torch

from torchblur.config.schema import IdentifyConfig
from torchblur.design.windows import MIN_SEPARATION, alias_separation, dual_exposure_windows
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.plans import SPARSE_MARGIN, choose_plan
from torchblur.dm.shack_hartmann import ShackHartmann
from torchblur.dm.spot_fit import CHUNK_BYTES
from torchblur.errors import ConfigError, ParameterError

__all__ = ["LADDER_TEST_FRAMES", "LIMITS", "SATURATION_STEPS", "LATENCY_SCAN", "GEOMETRY_EVALUATIONS", "estimate_run", "check_limits",
           "check_dm_bounds", "dm_size_bounds", "calibration_frames", "latency_scan_times",
           "DM_DARK_FRAMES", "DM_STILL_FRAMES", "STILL_BYTES", "check_dm_exposures", "dm_geometry", "dm_ladder_plan", "dm_plan", "dm_still_frames",
           "dm_sweep_size", "dm_sensor"]

# A run beyond any of these is refused at validation, with the estimate (--force to go on).
LIMITS = {"frames": 100_000, "memory_bytes": 8 * 2**30, "disk_bytes": 20 * 2**30, "bench_s": 24 * 3600.0}
_CALIBRATION_FRAMES = 100  # dark, saturation ladder, PSF, latency scan, axis (about)


# What the calibration stage takes besides its dark and still frames (torchblur.identify.calibration
# takes these from here, so that estimate_run counts what it takes).
SATURATION_STEPS = 9  # one still frame per exposure of the saturation ladder
LATENCY_SCAN = {"exposure_s": 200e-6, "pulse_width_s": 20e-6, "max_latency_s": 200e-6, "step_s": 2e-6, "repeats": 2}


def latency_scan_times(trigger_delay_s: float, *, exposure_s: float, pulse_width_s: float, max_latency_s: float,
                       step_s: float):
    """The pulse times ``[n]`` (s after the trigger) of the latency calibration's scan: from
    ``-pulse_width_s`` past ``max_latency_s + trigger_delay_s + exposure_s / 2`` in steps of
    ``step_s`` (:func:`torchblur.identify.calibration.calibrate_latency`)."""
    return np.arange(-pulse_width_s, max_latency_s + trigger_delay_s + exposure_s / 2, step_s)


def calibration_frames(cfg: IdentifyConfig, *, n_dark: int, n_still: int) -> int:
    """Frames the calibration takes without the axis tracking (a run with spots, a DM run):
    ``n_dark`` dark, the saturation ladder, ``n_still`` still and the latency scan (each pulse
    time :data:`LATENCY_SCAN` ``repeats`` times)."""
    scan = {k: v for k, v in LATENCY_SCAN.items() if k != "repeats"}
    n_pulse = 0 if cfg.camera.latency_std_s is not None else (
        len(latency_scan_times(float(cfg.camera.trigger_delay_s), **scan)) * LATENCY_SCAN["repeats"])
    n_ptc = 8 * int(cfg.camera.ptc_frames)  # torchblur.identify.calibration.PTC_STEPS exposures
    return int(n_dark) + SATURATION_STEPS + int(n_still) + n_pulse + n_ptc


# A DM run's geometry matrix evaluates every actuator's influence at oversample^2 points of every
# subaperture; bounded by dm.n_across^2 x wfs.n_across^2 x wfs.oversample^2 evaluations (closed form,
# nothing computed). 700 actuators on 40 x 40 subapertures (1.5e9 by the bound) took 80 s here.
GEOMETRY_EVALUATIONS = 4e9
_DM_DEFAULTS = {"dm.n_across": 8.0, "wfs.n_across": 10.0, "wfs.pitch_px": 16.0, "wfs.oversample": 32.0}


def _largest(cfg: IdentifyConfig, keys) -> str:
    """The key of ``keys`` (of :data:`_DM_DEFAULTS`) furthest above its usual value."""
    values = {"dm.n_across": cfg.dm.n_across, "wfs.n_across": cfg.wfs.n_across, "wfs.pitch_px": cfg.wfs.pitch_px,
              "wfs.oversample": cfg.wfs.oversample}
    return max(keys, key=lambda k: float(values[k]) / _DM_DEFAULTS[k])


def dm_size_bounds(cfg: IdentifyConfig) -> dict:
    """Closed-form bounds of a DM run's size from counts alone (no geometry, no plan; instant):
    ``frame_side`` px (``ceil(wfs.n_across * wfs.pitch_px)``), ``frames`` (the fewest sweep frames
    any plan takes: one pattern x frequencies x exposures x ``dm_plan.n_repeats``, or more than
    half of ``dm_plan.budget_frames``), ``memory_bytes`` and ``disk_bytes`` of those frames (as
    :func:`estimate_run` counts them) and ``geometry`` (the most influence evaluations of the
    geometry matrix: ``dm.n_across^2 wfs.n_across^2 wfs.oversample^2``), each with the ``key``
    that drives it."""
    s, w, p = cfg.sweep, cfg.wfs, cfg.dm_plan
    side = math.ceil(float(w.n_across) * float(w.pitch_px))
    n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
    per_pattern = n_freq * len(s.exposures)
    sweep_key = "sweep.freq_hz" if s.freq_hz is not None else "sweep.n"
    if p.n_repeats is not None:
        frames = per_pattern * int(p.n_repeats)
        frames_key = "dm_plan.n_repeats" if int(p.n_repeats) >= n_freq else sweep_key
    else:
        frames, frames_key = (int(p.budget_frames) + 1) // 2, "dm_plan.budget_frames"
        if per_pattern > frames:  # the sweep's own count dominates
            frames_key = sweep_key
    pixels = side * side
    return {"frame_side": side, "frame_key": _largest(cfg, ("wfs.n_across", "wfs.pitch_px")), "frames": frames,
            "frames_key": frames_key, "memory_bytes": 3 * 8 * frames * pixels, "disk_bytes": 2 * frames * pixels,
            "geometry": float(cfg.dm.n_across) ** 2 * float(w.n_across) ** 2 * float(w.oversample) ** 2,
            "geometry_key": _largest(cfg, ("dm.n_across", "wfs.n_across", "wfs.oversample"))}


def check_dm_bounds(cfg: IdentifyConfig) -> dict:
    """Refuse a DM run that :func:`dm_size_bounds` already shows beyond :data:`LIMITS` (or
    whose geometry would take more than :data:`GEOMETRY_EVALUATIONS`), before the geometry and
    the plan are computed; returns the bounds.

    Raises:
        ConfigError: starting with the key that makes the run large.
    """
    b = dm_size_bounds(cfg)
    tail = "refused before any work (--force to go on)"
    if b["frame_side"] > 65536 or b["frame_side"] ** 2 > 2**28:
        raise ConfigError(f"{b['frame_key']}: a {b['frame_side']} x {b['frame_side']} px sensor frame (wfs.n_across x "
                          f"wfs.pitch_px) is more than any camera delivers (2^28 pixels); {tail}")
    if b["frames"] > LIMITS["frames"]:
        raise ConfigError(f"{b['frames_key']}: the run is too large (at least {b['frames']:,} sweep frames; limit "
                          f"{LIMITS['frames']:,}); {tail}")
    for k in ("memory_bytes", "disk_bytes"):
        if b[k] > LIMITS[k]:
            raise ConfigError(f"{b['frame_key']}: the run is too large (at least {b['frames']:,} frames of "
                              f"{b['frame_side']} x {b['frame_side']} px: {_size(b[k])} of {k.split('_')[0]}; limit "
                              f"{_size(LIMITS[k])}); {tail}")
    if b["geometry"] > GEOMETRY_EVALUATIONS:
        raise ConfigError(f"{b['geometry_key']}: the mirror's geometry matrix is too large to compute (up to {b['geometry']:.3g} "
                          f"influence evaluations: dm.n_across^2 x wfs.n_across^2 x wfs.oversample^2; limit "
                          f"{GEOMETRY_EVALUATIONS:.3g}); {tail}")
    return b


def _estimate_dm(cfg: IdentifyConfig) -> dict:
    """:func:`estimate_run` of a DM run (``dm.n_across`` > 0): the plan's sweep frames
    (:func:`dm_sweep_size`), the DM calibration's and the spot model's static holds
    (``hold_frames``), on the sensor's frame. With ``dm_plan.spot_model`` auto the run takes one of
    two: the shifted still (its test's holds only, ``patterns x 2 x`` :data:`LADDER_TEST_FRAMES`) or
    the ladder (the test's and ``patterns x ladder_levels x ladder_frames`` more, on the ladder's plan,
    :func:`dm_ladder_plan`: on ``kind=auto`` a sparse one where auto chose Hadamard); the estimate is
    the larger, the most the run may take, and ``by_spot_model`` holds each (``frames``,
    ``sweep_frames``, ``hold_frames``). ``memory_bytes`` adds the spot fits' largest chunk
    (:data:`~torchblur.dm.spot_fit.CHUNK_BYTES`) to the frames'; a rig's own memory (a simulator's) is
    not in it."""
    p = cfg.dm_plan
    size = dm_sweep_size(cfg)
    test = size["patterns"] * 2 * LADDER_TEST_FRAMES if p.spot_model == "auto" else 0  # one recorded group, held at once
    branches = {}
    if p.spot_model in ("auto", "shifted"):
        branches["shifted"] = (size, test, test)
    if p.spot_model in ("auto", "ladder"):
        lad = dm_sweep_size(cfg, ladder=True)
        per_pattern = int(p.ladder_levels) * int(p.ladder_frames)  # one group per pattern, reduced before the next is held
        branches["ladder"] = (lad, test + lad["patterns"] * per_pattern, max(test, per_pattern))
    each = {}
    for name, (sz, holds, held) in branches.items():
        n_still = dm_still_frames(sz["frames"], sz["frame_shape"])
        frames = sz["frames"] + calibration_frames(cfg, n_dark=DM_DARK_FRAMES, n_still=n_still) + holds
        each[name] = _estimate(cfg, frames, sz["frame_shape"], n_drives=sz["patterns"], repeats=sz["repeats"], holds=holds,
                               held=held)
        each[name]["memory_bytes"] += CHUNK_BYTES  # the spot fits' working set: one chunk at a time, on the sweep's one worker
        each[name]["sweep_frames"], each[name]["hold_frames"] = sz["frames"], holds
    est = dict(max(each.values(), key=lambda e: e["frames"]))
    if len(each) > 1:
        est["by_spot_model"] = {k: {key: e[key] for key in ("frames", "sweep_frames", "hold_frames")} for k, e in each.items()}
    return est


def _estimate(cfg: IdentifyConfig, frames: int, frame_px: tuple, *, n_drives: int, repeats: int, holds: int = 0,
              held: int | None = None) -> dict:
    """:func:`estimate_run`'s dict for ``frames`` of ``frame_px`` ``(H, W)``, the sweep driving
    ``n_drives`` inputs (or DM patterns) at every frequency, ``repeats`` frames per exposure;
    ``holds`` of the frames are a DM spot model's static holds, a camera cycle each, of which ``held``
    (default all) are in memory at once, raw until each level's mean (8 bytes a pixel, not 24: the
    ladder's are reduced one pattern at a time, :func:`~torchblur.identify.dm_ladder.acquire_holds`)."""
    s, c = cfg.sweep, cfg.camera
    pixels = int(frame_px[0]) * int(frame_px[1])
    bench = float("nan")
    if frames <= LIMITS["frames"]:
        f = np.asarray(cfg.frequencies_hz(), dtype=float)
        cycle = np.maximum(1.0 / c.frame_rate_hz, 1.0 / f)
        frame_s = sum(np.maximum(cycle, e / f + c.readout_s) for e in s.exposures) * int(repeats)
        bench = float(n_drives * np.sum(frame_s + (s.settle_s or 0.0) + 2.0 / f)) + holds / float(c.frame_rate_hz)
    held = holds if held is None else held
    return {"frames": frames, "memory_bytes": 8 * (3 * (frames - holds) + held) * pixels, "disk_bytes": 2 * frames * pixels,
            "bench_s": bench, "motion_px": 1.33 * float(cfg.excitation.target_px), "frame_px": (int(frame_px[0]), int(frame_px[1]))}


def estimate_run(cfg: IdentifyConfig) -> dict:
    """What a run will take, estimated from its config alone (no work): ``frames`` (one
    attempt per sweep point, calibration included), ``memory_bytes`` (the frames held as
    float64, raw and in electrons, with a model per frame), ``disk_bytes`` (the recording,
    16-bit pixels), ``bench_s`` (camera time: per point the settling and every frame at
    least a camera cycle and a period apart; only when ``frames`` is within
    :data:`LIMITS`, else NaN) and ``motion_px`` (the largest spot motion, 1.33 target_px).
    A DM run (``dm.n_across`` > 0) counts its plan's sweep frames (patterns x frequencies x
    exposures x repeats, also ``sweep_frames``) and its calibration's exactly, on the sensor's
    frame (:func:`_estimate_dm`)."""
    if cfg.dm.enabled:
        return _estimate_dm(cfg)
    s, c = cfg.sweep, cfg.camera
    n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
    n_inputs = 2 if cfg.plant.is_mimo else 1
    per_point = len(s.exposures) * int(s.images_per_point)
    frames = n_inputs * n_freq * per_point + _CALIBRATION_FRAMES
    return _estimate(cfg, frames, (c.height, c.width), n_drives=n_inputs, repeats=int(s.images_per_point))


def _size(b: float) -> str:
    return f"{b / 2**30:.3g} GiB" if b >= 2**30 else f"{b / 2**20:.3g} MiB"


def check_limits(cfg: IdentifyConfig) -> dict:
    """Refuse a run beyond :data:`LIMITS` (or whose spot motion exceeds the frame) with the
    estimate of :func:`estimate_run`, which it returns.

    Raises:
        ConfigError: starting with the key that makes the run large, naming the estimate.
    """
    if cfg.dm.enabled:
        check_dm_bounds(cfg)  # closed form, before the geometry and the plan that estimate_run computes
    est = estimate_run(cfg)
    s, c = cfg.sweep, cfg.camera
    bench = f"{est['bench_s'] / 3600:.3g} h" if math.isfinite(est["bench_s"]) else "not estimated (too many frames)"
    summary = (f"estimate: {est['frames']:,} frames, {_size(est['memory_bytes'])} of memory, {_size(est['disk_bytes'])} "
               f"on disk, bench time {bench}")
    over = [k for k in ("frames", "memory_bytes", "disk_bytes", "bench_s") if est[k] > LIMITS[k]]
    if over:
        n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
        drivers = {"camera.height": int(c.height), "camera.width": int(c.width)} if over == ["memory_bytes"] or \
            int(c.height) * int(c.width) > 2**22 else {}
        drivers = drivers or {"sweep.freq_hz" if s.freq_hz is not None else "sweep.n": n_freq,
                              "sweep.images_per_point": int(s.images_per_point), "sweep.exposures": len(s.exposures)}
        key = max(drivers, key=drivers.get)
        if cfg.dm.enabled:  # the sensor's frame and the plan's frames, not camera.* or sweep.images_per_point
            b = dm_size_bounds(cfg)
            key = b["frame_key"] if over == ["memory_bytes"] or over == ["disk_bytes"] else b["frames_key"]
        shown = {"frames": f"{LIMITS['frames']:,} frames", "memory_bytes": f"memory {_size(LIMITS['memory_bytes'])}",
                 "disk_bytes": f"disk {_size(LIMITS['disk_bytes'])}", "bench_s": f"bench time {LIMITS['bench_s'] / 3600:g} h"}
        limits = ", ".join(shown[k] for k in over)
        raise ConfigError(f"{key}: the run is too large ({summary}; limits: {limits}); refused before any work "
                          f"(--force to go on)")
    if est["motion_px"] > max(est["frame_px"]):
        raise ConfigError(f"excitation.target_px: a spot motion of up to {est['motion_px']:.4g} px (1.33 x target_px) does not "
                          f"fit a {est['frame_px'][0]}x{est['frame_px'][1]} frame ({summary}); refused before any work "
                          f"(--force to go on)")
    return est


# The DM run's stds are small (0.03 % on a DC gain): each spot's PSF, fitted from the still frames
# and held fixed, and the dark mean subtracted from every frame must be known better than that.
DM_DARK_FRAMES = 256
#: frames per level of the spot model's auto test (every pattern at its two end levels: whether a
#: shifted still explains the held spots; :mod:`torchblur.identify.dm_ladder`)
LADDER_TEST_FRAMES = 4
DM_STILL_FRAMES = 128  #: the fewest still frames a DM run takes (dm_still_frames)
STILL_BYTES = 1 << 28  #: the still frames a DM run holds at once (float64), at most this many bytes


def dm_still_frames(sweep_frames: int, frame_shape) -> int:
    """The still frames a DM calibration takes: a quarter of the sweep's frames, at least
    :data:`DM_STILL_FRAMES`, and no more than :data:`STILL_BYTES` of float64 frames of
    ``frame_shape`` ``(H, W)`` hold (but never fewer than the least). Why (each spot's PSF error is
    common to all its fits) and the measured effect on the DC gains' stds: docs/deformable_mirrors.md,
    "The DC gain's std"."""
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


def dm_plan(cfg, kind: str | None = None, threshold: float | None = None):
    """``(plan, n_repeats, info)`` of a DM config on its geometry :func:`dm_geometry`
    (:func:`~torchblur.dm.plans.choose_plan` with the ``dm_plan`` and ``sweep`` sections; ``kind``,
    ``threshold``: that plan and support threshold instead of ``dm_plan.kind``'s and ``dm_plan.support_threshold``'s).

    Raises:
        ParameterError: naming ``dm_plan.budget_frames`` when one repeat of the plan needs more.
    """
    n_freq, n_exp = len(cfg.frequencies_hz()), len(cfg.sweep.exposures)

    kind = cfg.dm_plan.kind if kind is None else kind
    threshold = float(cfg.dm_plan.support_threshold if threshold is None else threshold)

    def compute():
        return choose_plan(kind, dm_geometry(cfg), budget_frames=cfg.dm_plan.budget_frames, n_freq=n_freq,
                           n_exposures=n_exp, threshold=threshold, n_repeats=cfg.dm_plan.n_repeats)

    plan, R, info = _memo(("plan", _geometry_key(cfg), repr(cfg.dm_plan), kind, threshold, n_freq, n_exp), compute)
    return plan, R, copy.deepcopy(info)


def dm_ladder_plan(cfg):
    """``(plan, n_repeats, info, threshold)`` of a DM run whose spots take the ladder: with ``dm_plan.kind=auto``
    where auto chose Hadamard (every pattern moves every actuator a spot sees, so the ladder would tie a spot's
    shape to their common command), the sparse plan seen at :data:`~torchblur.dm.plans.SPARSE_MARGIN` x
    ``dm_plan.support_threshold`` (a misregistered mirror's pairs all in it), at that threshold; else
    :func:`dm_plan`'s at ``dm_plan.support_threshold``."""
    plan, R, info = dm_plan(cfg)
    threshold = float(cfg.dm_plan.support_threshold)
    if cfg.dm_plan.kind == "auto" and plan.kind == "hadamard":
        threshold *= SPARSE_MARGIN
        plan, R, info = dm_plan(cfg, kind="sparse", threshold=threshold)
    return plan, R, info, threshold


def dm_sweep_size(cfg, ladder: bool = False) -> dict:
    """A DM config's sweep: ``frames`` (patterns x frequencies x exposures x repeats),
    ``patterns``, ``repeats`` and the sensor camera's ``frame_shape`` ``(H, W)`` px (``ladder``: the
    sweep the ladder spot model takes, on :func:`dm_ladder_plan`'s plan).

    Raises:
        ConfigError: naming ``dm_plan.budget_frames`` when one repeat of the plan needs more;
            naming ``sweep.exposures`` when they do not resolve the alias (:func:`check_dm_exposures`).
    """
    check_dm_exposures(cfg.sweep.exposures)
    try:
        plan, R = (dm_ladder_plan(cfg) if ladder else dm_plan(cfg))[:2]
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
