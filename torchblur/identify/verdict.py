"""The one-line verdict every identify and ``torchblur fit`` run ends with, and the report's
lines on the run's tolerance (pure: from the FrequencyResponse's flags and the config).

``verdict: trustworthy: all N points ...`` when no point is flagged ``poor_fit``, ``timing``
or ``failed`` (exit status 0); else ``verdict: K of N points flagged: ...`` naming the
frequencies of each kind (exit status :data:`EXIT_FLAGGED`). Points flagged ``limited`` (the
drive limit cut their motion) are named with the motion they reached, but do not by
themselves make a run untrustworthy: their stds hold at the smaller motion. The rule behind
each flag: :mod:`torchblur.identify.assemble` and docs/reliability.md ("Per-point flags").
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from torchblur.identify.assemble import timing_limit_hz
from torchblur.identify.model import model_exclusions
from torchblur.sysid.flags import FAILED, LIMITED, NO_MOTION, POOR_FIT, TIMING, UNTRUSTED, flag_names

__all__ = ["EXIT_FLAGGED", "Verdict", "listed", "report_lines", "timing_band_hz", "verdict"]

#: exit status of a run that completed, results written, with points flagged poor_fit, timing or failed
#: (3 is taken: the rig stopped the run)
EXIT_FLAGGED = 4

_LISTED = 6  # frequencies named per kind before "..."


@dataclass(frozen=True)
class Verdict:
    """A run's verdict.

    Attributes:
        line: the one line (``"verdict: ..."``).
        trustworthy: no point flagged poor_fit, timing or failed.
        exit_code: 0 when trustworthy, else :data:`EXIT_FLAGGED`.
        points: the response's points (channel points [O, I, F] of a MIMO response).
        flagged: points with a poor_fit, timing or failed flag.
        poor_fit, timing, failed, limited: points with each flag (a point may have several).
        timing_limit_hz: the frequency above which the timing terms exceed the tolerance (inf:
            never; None: unknown, the response has no ``timing`` meta).
    """

    line: str
    trustworthy: bool
    exit_code: int
    points: int
    flagged: int
    poor_fit: int
    timing: int
    failed: int
    limited: int
    timing_limit_hz: float | None
    no_motion: int = 0
    model_reduced_chi2: float | None = None
    model_poor: bool = False

    def to_dict(self) -> dict:
        """The fields as a strict-JSON dict (an infinite ``timing_limit_hz`` as null)."""
        d = asdict(self)
        if d["timing_limit_hz"] is not None and not math.isfinite(d["timing_limit_hz"]):
            d["timing_limit_hz"] = None
        return d


def _hz(f: float) -> str:
    return f"{f / 1e3:.3g} kHz" if f >= 1e3 else f"{f:.4g} Hz"


def _freqs(frf, mask, motion_px=None) -> str:
    """The frequencies where ``mask [O, I, F]`` holds, e.g. ``"40 Hz, 12.6 kHz"`` (with the
    reached motion where ``motion_px`` is given: ``"20 kHz: 1.2 px"``)."""
    ks = np.flatnonzero(mask.any(axis=(0, 1)))
    items = []
    for k in ks[:_LISTED]:
        item = _hz(float(frf.freq_hz[k]))
        if motion_px is not None:
            m = np.asarray(motion_px, dtype=np.float64)[..., k][mask[..., k]]
            m = m[np.isfinite(m)]
            if m.size:
                item += f": {m.max():.3g} px"
        items.append(item)
    return listed(items, len(ks))


def listed(items, total: int | None = None) -> str:
    """``items`` (strings, the first ``_LISTED`` of ``total``, default ``len(items)``) joined by
    ``", "``, with ``"... K more"`` for the ones left out: ``"40 Hz, 12.6 kHz"``, ``"1, 2, 3, 4, 5,
    6, ... 2 more"``."""
    items = [str(x) for x in items]
    total = len(items) if total is None else int(total)
    shown = items[:_LISTED]
    if total > len(shown):
        shown.append(f"... {total - len(shown)} more")
    return ", ".join(shown)


def timing_band_hz(frf, tolerance_deg: float) -> float | None:
    """The frequency (Hz) above which the timing terms alone exceed ``tolerance_deg``, from
    ``frf.meta["timing"]`` (the adequacy stage's ``jitter_s``, ``latency_std_s``,
    ``frames_per_point``): :func:`~torchblur.identify.assemble.timing_limit_hz`. None when
    the meta does not hold them; inf when there are no timing terms."""
    t = frf.meta.get("timing")
    if not isinstance(t, dict) or not all(k in t for k in ("jitter_s", "latency_std_s", "frames_per_point")):
        return None
    return timing_limit_hz(math.radians(tolerance_deg), float(t["jitter_s"]), float(t["latency_std_s"]),
                           max(1, int(t["frames_per_point"])))


def _tolerances(frf, cfg) -> tuple[float, float]:
    """(poor_fit_chi2, tolerance_deg): the config's, else the response's meta, else the defaults."""
    if cfg is not None:
        return float(cfg.fit.poor_fit_chi2), float(cfg.report.tolerance_deg)
    a = frf.meta.get("adequacy", {}) if isinstance(frf.meta.get("adequacy"), dict) else {}
    return float(a.get("poor_fit_chi2", 1.5)), float(a.get("tolerance_deg", 1.0))


def verdict(frf, cfg=None, *, motion_px=None, model=None) -> Verdict:
    """The verdict on ``frf`` (its :attr:`~torchblur.sysid.frequency_response.FrequencyResponse.flags`).

    Args:
        frf: the run's response, flagged by the adequacy stage.
        cfg: the run's IdentifyConfig (``fit.poor_fit_chi2``, ``report.tolerance_deg``), or
            None (then ``frf.meta["adequacy"]``, else the defaults 1.5 and 1 deg).
        motion_px: optional [O, I, F] motion each point reached (px), named for limited points.
        model: the run's fitted model (a TransferFunctionFit), or None: a model whose reduced
            chi2 is above :func:`model_chi2_limit` makes the run untrustworthy (:func:`model_adequacy`).

    Returns:
        :class:`Verdict`.
    """
    thr, tol_deg = _tolerances(frf, cfg)
    flags = frf.flags | np.where(frf.valid, 0, FAILED)  # a NaN point is a failed one, flagged or not
    has = {bit: (flags & bit) != 0 for bit in (POOR_FIT, TIMING, FAILED, LIMITED, NO_MOTION)}
    bad = (flags & UNTRUSTED) != 0
    n, k = int(flags.size), int(bad.sum())
    m_chi2, m_poor = model_adequacy(model)
    band = timing_band_hz(frf, tol_deg)
    word = "points" if frf.is_siso else "channel points"
    limited = ""
    if has[LIMITED].any():
        limited = f"; {int(has[LIMITED].sum())} limited by the drive ({_freqs(frf, has[LIMITED], motion_px)})"
    model_part = (f"; the model does not explain the response (reduced chi2 {m_chi2:.3g} over {int(model.dof)} dof, above "
                  f"{model_chi2_limit(model.dof):.3g}): do not use model.json" if m_poor else "")
    if not k and not m_poor:
        unknown = int((~np.isfinite(frf.reduced_chi2) & frf.valid).sum())
        chi2 = f"reduced chi2 <= {thr:g}" + (f" ({unknown} unknown: not checked)" if unknown else "")
        timing = f"timing within {tol_deg:g} deg"
        if band is not None:
            timing += " (no timing terms)" if math.isinf(band) else f" up to {_hz(band)}"
        line = f"verdict: trustworthy: all {n} {word} within tolerance: {chi2}, {timing}{limited}"
    else:
        parts = []
        if has[POOR_FIT].any():
            parts.append(f"{int(has[POOR_FIT].sum())} poor fit ({_freqs(frf, has[POOR_FIT])})")
        if has[TIMING].any():
            where = f"above {_hz(band)}" if band is not None and math.isfinite(band) else _freqs(frf, has[TIMING])
            parts.append(f"{int(has[TIMING].sum())} timing ({where}, beyond {tol_deg:g} deg)")
        if has[FAILED].any():
            parts.append(f"{int(has[FAILED].sum())} failed ({_freqs(frf, has[FAILED])})")
        if has[NO_MOTION].any():
            parts.append(f"{int(has[NO_MOTION].sum())} no significant motion ({_freqs(frf, has[NO_MOTION])}: not a measurement)")
        head = f"verdict: {k} of {n} {word} flagged: {', '.join(parts)}" if k else f"verdict: all {n} {word} within tolerance"
        line = f"{head}{limited}{model_part}"
    ok = not k and not m_poor
    return Verdict(line=line, trustworthy=ok, exit_code=0 if ok else EXIT_FLAGGED, points=n, flagged=k,
                   poor_fit=int(has[POOR_FIT].sum()), timing=int(has[TIMING].sum()), failed=int(has[FAILED].sum()),
                   limited=int(has[LIMITED].sum()), timing_limit_hz=band, no_motion=int(has[NO_MOTION].sum()),
                   model_reduced_chi2=m_chi2, model_poor=m_poor)


#: a model whose reduced chi2 is above max(MODEL_CHI2_FLOOR, 1 + 4 sqrt(2 / dof)) does not explain the
#: response it was fitted to (a chi2 test at about 4 sigma, and never below 2: the points' stds are
#: estimates): the verdict says so and the run is not trustworthy.
MODEL_CHI2_FLOOR = 2.0


def model_chi2_limit(dof) -> float:
    """The largest reduced chi2 a model with ``dof`` degrees of freedom may have (see :data:`MODEL_CHI2_FLOOR`)."""
    return max(MODEL_CHI2_FLOOR, 1.0 + 4.0 * math.sqrt(2.0 / max(int(dof), 1)))


def model_adequacy(model) -> tuple[float | None, bool]:
    """``(reduced chi2, poor)`` of a fitted SISO model (a TransferFunctionFit: ``reduced_chi2``,
    ``dof``); ``(None, False)`` for none, a MIMO model or one without a finite chi2."""
    chi2, dof = getattr(model, "reduced_chi2", None), getattr(model, "dof", None)
    try:
        chi2, dof = float(chi2), int(dof)
    except (TypeError, ValueError):
        return None, False
    if not math.isfinite(chi2) or dof < 1:
        return None, False
    return chi2, chi2 > model_chi2_limit(dof)


def report_lines(frf, cfg) -> list[str]:
    """The report's lines on the run's tolerance and its flagged points: the frequency above
    which the timing terms exceed ``report.tolerance_deg`` (or that the whole band is within
    it), how many points have stds within ``report.tolerance_rel`` and ``tolerance_deg``, and
    one line per flagged point (frequency, channel, flags, reduced chi2; for a poor-fit
    point its std factor and whether the model fit left it out)."""
    thr, tol_deg = _tolerances(frf, cfg)
    tol_rel = float(cfg.report.tolerance_rel) if cfg is not None else 0.01
    lines = []
    band = timing_band_hz(frf, tol_deg)
    f_top = float(frf.freq_hz[-1])
    if band is not None:
        t = frf.meta["timing"]
        terms = (f"trigger jitter {t['jitter_s'] * 1e6:.3g} us per frame over {t['frames_per_point']} frames, latency std "
                 f"{t['latency_std_s'] * 1e6:.3g} us" + (f" ({frf.meta['latency_source']})" if "latency_source" in frf.meta else ""))
        if band > f_top:
            reach = "never" if math.isinf(band) else f"only above {_hz(band)}"
            lines.append(f"timing: the whole band (to {_hz(f_top)}) is within the tolerance of {tol_deg:g} deg ({terms}: "
                         f"they reach it {reach})")
        else:
            lines.append(f"timing: above {_hz(band)} the timing terms alone exceed the tolerance of {tol_deg:g} deg ({terms}); "
                         f"those points are flagged timing")
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = frf.magnitude_std / frf.magnitude
        ok = (rel <= tol_rel) & (np.degrees(frf.phase_std) <= tol_deg)
    lines.append(f"precision: {int(ok.sum())} of {ok.size} points have a 1-sigma within {tol_rel * 100:g}% of |H| and "
                 f"{tol_deg:g} deg (report.tolerance_rel, report.tolerance_deg)")
    left_out = model_exclusions(frf, cfg)[0] if cfg is not None else np.zeros(frf.flags.shape, dtype=bool)
    for o, i, k in zip(*np.nonzero(frf.flags)):
        where = "" if frf.is_siso else f" ({frf.output_labels[o]} from {frf.input_labels[i]})"
        chi2 = frf.reduced_chi2[o, i, k]
        extra = f", reduced chi2 {chi2:.3g}" if np.isfinite(chi2) else ""
        if frf.flags[o, i, k] & POOR_FIT:
            extra += f", stds x{math.sqrt(chi2):.3g}, " + ("left out of the model fit" if left_out[o, i, k] else
                                                         "kept in the model fit (too few points without it)")
        lines.append(f"  flagged {_hz(float(frf.freq_hz[k]))}{where}: {flag_names(frf.flags[o, i, k])}{extra}")
    return lines
