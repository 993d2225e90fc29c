"""One table of the status codes and flag bits every fitter reports per item.

``status`` says whether an estimate is usable (0) or why not; ``flags`` (bits, OR-ed) say
what was done to the data or noticed about it. A flagged item keeps its estimate; an item with
a non-zero status has NaN where nothing can be estimated.
"""
from __future__ import annotations

__all__ = [
    "STATUS", "OK", "DARK", "NOT_CONVERGED", "OUT_OF_FRAME", "SINGULAR", "NO_PIXELS", "POOR_FIT",
    "FLAGS", "MASKED", "SATURATED_MASKED", "OUTLIERS_MASKED", "PARTLY_OUT_OF_FRAME", "NO_MOTION",
]

OK = 0  #: the estimate is usable
DARK = 1  #: no signal above the noise (a dark frame)
NOT_CONVERGED = 2  #: the optimiser did not converge
OUT_OF_FRAME = 3  #: the spot is mostly outside the frame
SINGULAR = 4  #: the parameters are not identifiable (singular Fisher information)
NO_PIXELS = 5  #: every pixel is masked or saturated
POOR_FIT = 6  #: the model does not explain the data (reduced chi2 > 3 with the given noise, after a wider search)

#: status code -> what it means
STATUS = {
    OK: "ok",
    DARK: "no signal (dark frame)",
    NOT_CONVERGED: "not converged",
    OUT_OF_FRAME: "spot mostly outside the frame",
    SINGULAR: "unidentifiable (singular Fisher information)",
    NO_PIXELS: "no usable pixels (every pixel masked or saturated)",
    POOR_FIT: "poor fit (reduced chi2 > 3 with the given noise, after a wider search)",
}

MASKED = 1  #: the caller's ``mask`` excluded pixels of this item
SATURATED_MASKED = 2  #: pixels at or above ``saturation_level`` were excluded
OUTLIERS_MASKED = 4  #: the robust pass excluded pixels (hot pixels, cosmic rays): ``n_outliers``
PARTLY_OUT_OF_FRAME = 8  #: more than 0.1% of the fitted spot's light falls outside the frame
NO_MOTION = 16  #: the amplitude is below 3 standard deviations: no motion detected, the phase means nothing

#: flag bit -> what it means
FLAGS = {
    MASKED: "pixels masked by the caller",
    SATURATED_MASKED: "saturated pixels masked",
    OUTLIERS_MASKED: "outlier pixels masked",
    PARTLY_OUT_OF_FRAME: "spot partly out of frame",
    NO_MOTION: "no significant motion",
}
