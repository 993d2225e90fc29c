"""The one table of per-point flags a :class:`~torchblur.sysid.frequency_response.FrequencyResponse`
carries: bits, OR-ed into an int mask ``flags[o, i, f]`` (0 = none), saying why a point is not
to be taken at its stated uncertainty (the rule that sets each is in
:func:`torchblur.identify.assemble.adequacy` and docs/reliability.md).

In files (frf.csv's ``flags`` column, the report) a mask is written as its names joined by
``|`` (``"poor_fit|timing"``; empty for 0): :func:`flag_names` and :func:`parse_flags`.
"""
from __future__ import annotations

from torchblur.errors import ParameterError

__all__ = ["POOR_FIT", "TIMING", "LIMITED", "FAILED", "NO_MOTION", "ALIAS", "POINT_FLAGS", "UNTRUSTED", "flag_names", "parse_flags"]

POOR_FIT = 1  #: the model does not explain the images: reduced chi2 > ``fit.poor_fit_chi2`` (stds inflated)
TIMING = 2  #: the timing terms alone (trigger jitter, latency std) exceed ``report.tolerance_deg``
LIMITED = 4  #: the drive limit cut the motion: the point was fitted at a smaller motion than its target
FAILED = 8  #: the fit failed: the response is NaN
NO_MOTION = 16  #: the image fit found no significant motion (amplitude below 3 std): the value is not a measurement
#: one exposure per point (the alias, PHYSICS.md Proposition 3): the continuity rule could not decide the
#: point's phase branch (:func:`torchblur.design.windows.continuity_branches`); its phase may be the alias
ALIAS = 32

#: bit -> name (the names frf.csv and the report use)
POINT_FLAGS = {POOR_FIT: "poor_fit", TIMING: "timing", LIMITED: "limited", FAILED: "failed", NO_MOTION: "no_motion", ALIAS: "alias"}

#: the bits that make a run's verdict untrustworthy (LIMITED alone does not: the point is honest, just smaller)
UNTRUSTED = POOR_FIT | TIMING | FAILED | NO_MOTION | ALIAS

_ALL = sum(POINT_FLAGS)


def flag_names(mask: int) -> str:
    """``"poor_fit|timing"`` for ``POOR_FIT | TIMING``; ``""`` for 0; unknown bits as ``bit<N>``."""
    mask = int(mask)
    names = [name for bit, name in POINT_FLAGS.items() if mask & bit]
    names += [f"bit{b}" for b in range(63) if (mask >> b) & 1 and not (1 << b) & _ALL]
    return "|".join(names)


def parse_flags(text: str) -> int:
    """Inverse of :func:`flag_names` (spaces ignored); ParameterError naming an unknown name."""
    by_name = {name: bit for bit, name in POINT_FLAGS.items()}
    mask = 0
    for part in str(text).split("|"):
        part = part.strip()
        if not part:
            continue
        if part in by_name:
            mask |= by_name[part]
        elif part.startswith("bit") and part[3:].isdigit() and int(part[3:]) < 63:
            mask |= 1 << int(part[3:])
        else:
            raise ParameterError(f"flags: unknown flag {part!r}; expected names from {sorted(by_name)} joined by '|'")
    return mask
