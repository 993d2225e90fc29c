"""One table of the status codes and flag bits every fitter reports per item.

``status`` says whether an estimate is usable (0) or why not; ``flags`` (bits, OR-ed) say
what was done to the data or noticed about it. A flagged item keeps its estimate; an item with
a non-zero status has NaN where nothing can be estimated.
"""
from __future__ import annotations

import math

import torch

__all__ = [
    "STATUS", "OK", "DARK", "NOT_CONVERGED", "OUT_OF_FRAME", "SINGULAR", "NO_PIXELS", "POOR_FIT", "NOT_FITTED",
    "FLAGS", "MASKED", "SATURATED_MASKED", "OUTLIERS_MASKED", "PARTLY_OUT_OF_FRAME", "NO_MOTION", "POOR_FIT_FLAG",
    "POOR_FIT_CHI2", "POOR_FIT_STATUS_CHI2", "item_status", "above_chi2", "flag_poor_fit", "BRANCH_UNDECIDED", "BRANCH_CHI2",
    "flag_branch_undecided", "OUT_OF_LADDER",
]

OK = 0  #: the estimate is usable
DARK = 1  #: no signal above the noise (a dark frame)
NOT_CONVERGED = 2  #: the optimiser did not converge
OUT_OF_FRAME = 3  #: the spot is mostly outside the frame
SINGULAR = 4  #: the parameters are not identifiable (singular Fisher information)
NO_PIXELS = 5  #: every pixel is masked or saturated
POOR_FIT = 6  #: the model does not explain the data (reduced chi2 > :data:`POOR_FIT_STATUS_CHI2` with the given noise, after a wider search)
NOT_FITTED = 7  #: left out by the caller (``only``): a DM spot that its pattern does not move, whose response no estimate uses

#: the bound of the status :data:`POOR_FIT`, in reduced chi2 (the cost per degree of freedom, pixels used
#: minus fitted parameters, with the noise given): set by a fitter that searches again from wider starts
#: when its first fit is far above the noise (:func:`~torchblur.fit.multisine.fit_multisine`), where the
#: fit is still this far above it after that search: its estimate is not reported as usable. Above
#: :data:`POOR_FIT_CHI2`, the flag's bound (a fit between the two is flagged but usable); a fitter
#: without a wider search (:func:`~torchblur.fit.sinusoid.fit_sinusoid`) only flags.
POOR_FIT_STATUS_CHI2 = 3.0

#: status code -> what it means
STATUS = {
    OK: "ok",
    DARK: "no signal (dark frame)",
    NOT_CONVERGED: "not converged",
    OUT_OF_FRAME: "spot mostly outside the frame",
    SINGULAR: "unidentifiable (singular Fisher information)",
    NO_PIXELS: "no usable pixels (every pixel masked or saturated)",
    POOR_FIT: f"poor fit (reduced chi2 > {POOR_FIT_STATUS_CHI2:g} with the given noise, after a wider search)",
    NOT_FITTED: "not fitted (left out by the caller)",
}

MASKED = 1  #: the caller's ``mask`` excluded pixels of this item
SATURATED_MASKED = 2  #: pixels at or above ``saturation_level`` were excluded
OUTLIERS_MASKED = 4  #: the robust pass excluded pixels (hot pixels, cosmic rays): ``n_outliers``
PARTLY_OUT_OF_FRAME = 8  #: more than 0.1% of the fitted spot's light falls outside the frame
NO_MOTION = 16  #: the amplitude is below 3 standard deviations: no motion detected, the phase means nothing
POOR_FIT_FLAG = 32  #: reduced chi2 above :data:`POOR_FIT_CHI2` with the noise given: the model does not explain the item

#: with the noise given and exposures that resolve the alias (two or more, their centres apart), the
#: alias branch's cost is within :data:`BRANCH_CHI2` of the fit's: at this light the images do not
#: decide the phase branch (the fit may sit on the wrong one with a small local std)
BRANCH_UNDECIDED = 64

#: the fitted motion leaves the range of the static frames its model is built from (the DM ladder fit,
#: :mod:`torchblur.dm.ladder_fit`: the command ``u`` beyond the ladder's levels during an exposure,
#: where the spline extrapolates its end cubics)
OUT_OF_LADDER = 128

#: the bound of :data:`BRANCH_UNDECIDED`, in chi2 (cost) units: a likelihood ratio below e^2 (7.4)
#: between the two branches (bench_low_light.py: at a 3000 e-/s peak, 100 Hz, 9 of the 14 items of
#: 200 with a phase beyond 3 std were below it, 1 % of the right ones)
BRANCH_CHI2 = 4.0

#: the bound of :data:`POOR_FIT_FLAG`, the same as identify's ``fit.poor_fit_chi2`` default (there the
#: point is flagged ``poor_fit`` and its stds inflated): a wrong omega (Hz for rad/s), PSF or noise shows here
POOR_FIT_CHI2 = 1.5

#: flag bit -> what it means
FLAGS = {
    MASKED: "pixels masked by the caller",
    SATURATED_MASKED: "saturated pixels masked",
    OUTLIERS_MASKED: "outlier pixels masked",
    PARTLY_OUT_OF_FRAME: "spot partly out of frame",
    NO_MOTION: "no significant motion",
    POOR_FIT_FLAG: "poor fit (reduced chi2 above 1.5: the model does not explain the images)",
    BRANCH_UNDECIDED: "phase branch undecided (the alias's cost within 4 of the fit's: too little light)",
    OUT_OF_LADDER: "the motion leaves the ladder's levels (the model extrapolated)",
}


def item_status(converged, singular, dark, *, poor=None, out_of_frame=None) -> torch.Tensor:
    """Status codes ``[N]`` (:data:`STATUS`) from bool ``[N]`` masks: :data:`NOT_CONVERGED` where not
    ``converged``, :data:`POOR_FIT` where ``poor``, :data:`SINGULAR`, :data:`OUT_OF_FRAME` where
    ``out_of_frame``, :data:`DARK`; later codes win."""
    status = torch.zeros(converged.shape, dtype=torch.long, device=converged.device)
    status[~converged] = NOT_CONVERGED
    if poor is not None:
        status[poor] = POOR_FIT
    status[singular] = SINGULAR
    if out_of_frame is not None:
        status[out_of_frame] = OUT_OF_FRAME
    status[dark] = DARK
    return status


def above_chi2(reduced_chi2, threshold: float) -> torch.Tensor:
    """Bool ``[...]``: where ``reduced_chi2`` (``[...]``, per degree of freedom; NaN where unknown,
    the noise not given: never above) is above ``threshold``: with :data:`POOR_FIT_CHI2` the
    items :func:`flag_poor_fit` flags, with :data:`POOR_FIT_STATUS_CHI2` the ``poor`` mask of
    :func:`item_status`."""
    return torch.nan_to_num(reduced_chi2, nan=0.0) > threshold


def flag_poor_fit(flags, reduced_chi2, threshold: float = POOR_FIT_CHI2):
    """``flags`` (an int tensor ``[...]``, or None for none yet) with :data:`POOR_FIT_FLAG` set
    where ``reduced_chi2`` (``[...]``, NaN where unknown: never flagged) is above ``threshold``."""
    poor = above_chi2(reduced_chi2, threshold)
    if flags is None:
        flags = torch.zeros(poor.shape, dtype=torch.long, device=poor.device)
    return flags | (POOR_FIT_FLAG * poor.long())


def flag_branch_undecided(flags, delta_cost, resolving):
    """``flags`` (int ``[...]``) with :data:`BRANCH_UNDECIDED` set where ``delta_cost`` (the
    alias's cost less the fit's, chi2 units; NaN where unknown: never flagged) is below
    :data:`BRANCH_CHI2` and ``resolving`` (bool ``[...]``: the item's exposures resolve the alias)."""
    undecided = (torch.nan_to_num(delta_cost, nan=math.inf) < BRANCH_CHI2) & resolving
    return flags | (BRANCH_UNDECIDED * undecided.long())
