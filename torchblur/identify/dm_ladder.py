"""The DM run's spot model (``dm_plan.spot_model``, issue 23): each pattern held still at a ladder of
command levels (:meth:`~torchblur.rig.dm_contract.DMRig` ``pattern_ladder``), the images the
ladder spot fit (:mod:`torchblur.dm.ladder_fit`) describes a moving spot with.

On a real lenslet array a spot changes shape as a pattern moves it, and the run's shifted still
reads that as motion (a phase lead of 0.07 rad on HCIPy's spots, docs/deformable_mirrors.md). So:

- ``shifted``: every spot is its still, shifted (no static frames);
- ``ladder``: each pattern ``p`` held at ``dm_plan.ladder_levels`` levels ``u`` spanning
  ``+-U_p``, ``U_p = dm_plan.ladder_reach x min(excitation.target_px / m_p, limit / max|pattern_p|)``
  (``m_p`` the pattern's largest static spot motion per unit on the nominal G: the largest
  command the sweep expects of it), ``dm_plan.ladder_frames`` frames per level;
- ``auto``: first the two end levels of every pattern (one group,
  :data:`~torchblur.config.budget.LADDER_TEST_FRAMES` frames each); where a shifted still
  (:func:`~torchblur.dm.static_hold.fit_shifted_still`) explains the spots of them within their
  noise (:func:`~torchblur.dm.static_hold.chi2_threshold`; inside a rim of :data:`TEST_BORDER_PX`,
  where a neighbour's spot moved 1.3 x its sweep's motion enters the crop; at most :data:`FAIL_FRACTION` of the
  spot images, and one, may fail: the Fourier shift of a still sampled at ~1.2 px sigma leaves
  a few spot images of torchblur's own Gaussian spots just above the threshold, 1 of 384 at 1.40
  against 1.36, where on HCIPy's lenslet spots 99.6 % fail, median 20), ``shifted``, else the ladder.

Recording (the run's experiment, :mod:`torchblur.identify.dm_record`): the test is group
``dm_ladder/test``, each pattern's ladder ``dm_ladder/PPP`` (kind ``dm_ladder``): a resume or a
re-fit replays them (the decision is made again from the same frames, so it is the same).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from torchblur.config.budget import LADDER_TEST_FRAMES
from torchblur.dm.ladder_fit import PatternLadder, slope_covariance, with_slopes
from torchblur.dm.static_hold import chi2_threshold, fit_shifted_still
from torchblur.hardware.recording import ReplayRig
from torchblur.identify.record import LOGGER, run_stage
from torchblur.image.dark import subtract_dark
from torchblur.image.spots import crop_spots, crop_valid
from torchblur.render.camera import camera_noise_std

__all__ = ["LADDER_KIND", "TEST_KEY", "HoldImages", "hold_exposure", "hold_images", "ladder_key", "ladder_levels", "acquire_holds",
           "choose_spot_model", "ladder_holds", "pattern_ladder"]

LADDER_KIND = "dm_ladder"  #: the kind of the static holds' groups
TEST_KEY = "dm_ladder/test"  #: auto's test: every pattern at its two end levels
TEST_BORDER_PX = 2  #: auto's test leaves out this rim of every crop (module docstring)
FAIL_FRACTION = 0.005  #: auto keeps the shifted still where at most this fraction of the spot images (and one) fail
_F64 = torch.float64


def ladder_key(p: int) -> str:
    """The group of pattern ``p``'s ladder: ``dm_ladder/PPP``."""
    return f"dm_ladder/{int(p):03d}"


def ladder_levels(cfg, patterns: np.ndarray, G: np.ndarray, limit: float) -> np.ndarray:
    """``[P, K]`` the levels of every pattern's ladder (module docstring), increasing per row;
    ``limit``: the largest |command| (input units)."""
    M = G.shape[0] // 2
    s = G @ patterns.T  # [2M, P] static motion per unit
    motion = np.hypot(s[:M], s[M:]).max(0)  # [P]
    peak = np.abs(patterns).max(1)
    with np.errstate(divide="ignore"):
        u = np.minimum(float(cfg.excitation.target_px) / motion, limit / peak)
    U = np.minimum(float(cfg.dm_plan.ladder_reach) * u, limit / peak)  # never beyond the range
    return U[:, None] * np.linspace(-1.0, 1.0, int(cfg.dm_plan.ladder_levels))[None, :]


def hold_exposure(cfg, cal) -> float:
    """The static holds' exposure (s, at laser power 1): the still's brightest spot at
    ``camera.peak_fraction`` of the range, within ``camera.max_exposure_s``."""
    return float(min(cfg.camera.max_exposure_s, cfg.camera.peak_fraction * cal.full_adu * cal.gain / cal.peak_rate))


class HoldImages:
    """Static holds cropped at the spots: ``images`` ``[P, K, M, h, w]`` e-/s at power 1 (dark
    subtracted, gain applied, mean of the frames), ``variance`` (of that mean, (e-/s)^2, the
    camera noise model), ``levels`` ``[P, K]`` input units."""

    def __init__(self, images, variance, levels):
        self.images, self.variance, self.levels = images, variance, levels


def acquire_holds(rig, exp, keys, patterns, levels, n: int, exposure_s: float, cal, offset, size) -> HoldImages:
    """Every pattern held at its ``levels`` (``[P, K]``), ``n`` frames per level at ``exposure_s``
    and laser power 1, through :func:`~torchblur.identify.record.run_stage` (from the recording
    where it holds them): one group ``keys`` (a str) for all, or one per pattern (``keys[p]``).
    With one group per pattern, each pattern's frames are reduced to their cropped mean and variance
    (:func:`hold_images`) before the next pattern is held: the run holds one pattern's raw frames at
    a time, not the whole ladder's (the recording keeps every frame)."""

    def hold(r, p):
        return r.pattern_ladder(pattern=patterns[p].tolist(), levels=levels[p].tolist(), n=int(n), exposure_s=float(exposure_s),
                                power=1.0).frames

    P = len(patterns)
    if isinstance(keys, str):
        frames = run_stage(exp, keys, LADDER_KIND, rig, lambda r: [hold(r, p) for p in range(P)], labels={"n_patterns": P})
    else:
        frames = (run_stage(exp, keys[p], LADDER_KIND, rig, lambda r, p=p: hold(r, p), labels={"pattern": p}) for p in range(P))
    return hold_images(frames, levels, exposure_s, cal, offset, size)


def hold_images(frames, levels, exposure_s: float, cal, offset, size, power: float = 1.0) -> HoldImages:
    """:class:`HoldImages` of held frames (one per pattern ``[K, n, H, W]`` ADU, at ``levels``
    ``[P, K]``, ``exposure_s`` and laser ``power``): dark subtracted, gain applied, the mean per
    level per second at power 1 and its variance from the camera noise model, cropped at the spots
    (``offset`` ``[M, 2]``, ``size``). One function for a live run and an outside recording.
    ``frames`` may be an iterator: each pattern's frames are reduced and dropped before the next is
    taken (:func:`acquire_holds`)."""
    imgs, var = [], []
    for fr in frames:
        e = subtract_dark(torch.as_tensor(fr, dtype=_F64), cal.dark) * cal.gain
        mean = e.mean(1)
        scale = exposure_s * power
        imgs.append(crop_spots(mean / scale, offset, size))
        var.append(crop_spots(camera_noise_std(mean, cal.read_noise_e) ** 2 / (e.shape[1] * scale**2), offset, size))
        del fr, e, mean  # before the iterator takes the next pattern's frames
    return HoldImages(torch.stack(imgs), torch.stack(var), torch.as_tensor(np.asarray(levels), dtype=_F64))


def _still_crops(cal, offset, size):
    """The still's crops ``[M, h, w]`` and their variance (e-/s at power 1)."""
    return crop_spots(cal.still_rate, offset, size), crop_spots(cal.still_rate_var, offset, size)


def _shifted_test(holds: HoldImages, cal, offset, size, inside) -> dict:
    """Does a shifted still explain every spot held at the end levels? Its figures."""
    still, still_var = _still_crops(cal, offset, size)
    H, W = cal.dark.mean.shape[-2:]
    mask = crop_valid((H, W), offset, size) & ~crop_spots(cal.dark.hot_pixels, offset, size)
    b = TEST_BORDER_PX  # the crop's rim left out: there the neighbours' light enters at the test's reach, not this spot's shape
    mask[:, :b], mask[:, -b:], mask[:, :, :b], mask[:, :, -b:] = False, False, False, False
    red, _, _, dof = fit_shifted_still(holds.images, holds.variance, still, still_var, mask=mask)
    red = red[:, :, inside]  # [P, 2, M'] the spots mostly in the frame
    thr = chi2_threshold(dof, red.numel())
    fail = ~(red <= thr)
    return {"median": float(red.nanmedian()), "worst": float(red.nan_to_num(math.inf).max()), "threshold": thr, "dof": dof,
            "failed": int(fail.sum()), "tests": int(red.numel()), "patterns_failed": int(fail.flatten(1).any(1).sum())}


def choose_spot_model(cfg, rig, exp, patterns: np.ndarray, G: np.ndarray, cal, offset, size, inside, limit: float) -> str:
    """The spot model of the sweep's fits (module docstring): ``shifted`` or ``ladder``. ``patterns``
    ``[P, N]``: the plan's whose two end levels ``auto`` holds; ``offset`` ``[M, 2]``, ``size``: the
    spots' crops; ``inside`` ``[M]`` bool, the spots mostly in the frame (the others are not tested);
    ``limit`` the largest |command|. The decision and its figures go to the log (report.txt's dm
    lines); the holds themselves are :func:`ladder_holds`'."""
    choice = cfg.dm_plan.spot_model
    has = callable(getattr(rig, "pattern_ladder", None)) and (not isinstance(rig, ReplayRig) or _recorded(exp))
    if choice == "shifted" or (choice == "auto" and not has):
        why = "dm_plan.spot_model=shifted" if choice == "shifted" else f"auto, and a {type(rig).__name__} holds no pattern_ladder"
        LOGGER.info(f"dm spot model: shifted ({why}): every spot its still, shifted by its motion")
        return "shifted"
    if choice == "auto":
        levels = ladder_levels(cfg, patterns, G, limit)
        test = acquire_holds(rig, exp, TEST_KEY, patterns, levels[:, [0, -1]], LADDER_TEST_FRAMES, hold_exposure(cfg, cal), cal, offset,
                             size)
        t = _shifted_test(test, cal, offset, size, torch.as_tensor(inside, dtype=torch.bool))
        figures = (f"{t['tests']} spot images of {len(patterns)} patterns held at +-their end levels, {LADDER_TEST_FRAMES} frames each: "
                   f"reduced chi2 "
                   f"median {t['median']:.3g}, worst {t['worst']:.3g}, threshold {t['threshold']:.3g} (dof {t['dof']})")
        if t["failed"] <= max(1, int(FAIL_FRACTION * t["tests"])):
            LOGGER.info(f"dm spot model: shifted (auto: a shifted still explains the spots held still, {t['failed']} spot images "
                        f"above the threshold; {figures})")
            return "shifted"
        LOGGER.info(f"dm spot model: ladder (auto: {t['failed']} spot images of {t['patterns_failed']} patterns are not a shifted "
                    f"still within their noise; {figures})")
    return "ladder"


def ladder_holds(cfg, rig, exp, patterns: np.ndarray, G: np.ndarray, cal, offset, size, limit: float) -> HoldImages:
    """Every pattern of ``patterns`` ``[P, N]`` held at its :func:`ladder_levels`
    (``dm_plan.ladder_frames`` frames each, one recorded group per pattern), cropped at the spots."""
    levels = ladder_levels(cfg, patterns, G, limit)
    n, te = int(cfg.dm_plan.ladder_frames), hold_exposure(cfg, cal)
    holds = acquire_holds(rig, exp, [ladder_key(p) for p in range(len(patterns))], patterns, levels, n, te, cal, offset, size)
    LOGGER.info(f"dm spot model: ladder of {len(patterns)} patterns x {levels.shape[1]} levels x {n} frames at {te * 1e3:.3g} ms "
                f"(levels up to +-{np.abs(levels).max(1).min():.4g}..{np.abs(levels).max():.4g} input units: dm_plan.ladder_reach "
                f"{cfg.dm_plan.ladder_reach:g} x the largest command the sweep expects)")
    return holds


def _recorded(exp) -> bool:
    """A re-fit (a :class:`ReplayRig`) replays the holds the recording has."""
    return exp is not None and (exp.has(TEST_KEY) or exp.has(ladder_key(0)))


def pattern_ladder(holds: HoldImages, cal, offset, size):
    """The :class:`~torchblur.dm.ladder_fit.PatternLadder` of ``holds`` with the calibration's still
    (``cal.still_rate``) cropped like them, its static shifts computed once for every frequency
    (:func:`~torchblur.dm.ladder_fit.with_slopes`)."""
    return with_slopes(PatternLadder(levels=holds.levels, images=holds.images, variance=holds.variance,
                                     still=crop_spots(cal.still_rate, offset, size)))


def slope_noise(ladder: PatternLadder | None):
    """``(slope [P, M, 2], slope_cov [P, M, 2, 2])`` float64 numpy of ``ladder`` (its static shifts
    and their noise, :func:`~torchblur.dm.ladder_fit.slope_covariance`: stage 4's common error,
    :mod:`torchblur.dm.common_noise`); None without a ladder (the shifted still)."""
    if ladder is None:
        return None
    return (ladder.slope.detach().cpu().double().numpy(), slope_covariance(ladder).detach().cpu().double().numpy())
