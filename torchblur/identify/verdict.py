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
import dataclasses
from dataclasses import asdict, dataclass

import numpy as np

from torchblur.identify.assemble import timing_limit_hz
from torchblur.identify.model import model_exclusions
from torchblur.sysid.flags import ALIAS, FAILED, LIMITED, NO_MOTION, POOR_FIT, TIMING, UNTRUSTED, flag_names
from torchblur.sysid.model_check import DISAGREE_SIGMA, MODEL_CHI2_FLOOR, ModelJudgement, disagreements, judge_fit, model_chi2_limit

__all__ = ["EXIT_FLAGGED", "MODEL_CHI2_FLOOR", "TRUTH_BOUND", "Verdict", "judge_models", "listed", "model_chi2_limit", "report_lines",
           "timing_band_hz", "truth_disagreement", "verdict"]

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
        alias: points flagged alias (one exposure, branch not decided by continuity).
        beyond_truth, model_beyond_truth: with a known truth, the points (and the points where
            the model) lie more than :data:`TRUTH_BOUND` stds from it (None: no truth known).
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
    alias: int = 0
    beyond_truth: int | None = None
    model_beyond_truth: int | None = None
    models: tuple = ()  # ModelJudgement per model (and per channel) the run reports: judge_models
    disagree: tuple = ()  # "param: a +- sa vs b +- sb" where the two-step and direct models differ beyond their stds

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


def verdict(frf, cfg=None, *, motion_px=None, model=None, direct=None, expected=(), truth=None) -> Verdict:
    """The verdict on ``frf`` (its :attr:`~torchblur.sysid.frequency_response.FrequencyResponse.flags`).

    Args:
        frf: the run's response, flagged by the adequacy stage.
        cfg: the run's IdentifyConfig (``fit.poor_fit_chi2``, ``report.tolerance_deg``), or
            None (then ``frf.meta["adequacy"]``, else the defaults 1.5 and 1 deg).
        motion_px: optional [O, I, F] motion each point reached (px), named for limited points.
        model: the run's fitted model (a TransferFunctionFit), or None: a model whose reduced
            chi2 is above :func:`model_chi2_limit` makes the run untrustworthy (:func:`model_adequacy`).
        direct: the run's direct model (a DirectModelFit, ``model.direct``), or None. Every
            model (each channel of a MIMO one) is judged by one rule
            (:mod:`torchblur.sysid.model_check`): one that fails it makes the run
            untrustworthy and is named; so do a direct and a two-step model that disagree
            beyond their combined stds (:func:`judge_models`).
        expected: the models the run was to fit (``"two-step"``, ``"direct"``): one of them
            None (its fit failed: too few points, no valid channel) fails too.
        truth: the true response where it is known (a simulated rig), ``[O, I, F]`` or ``[F]``
            complex, or None: points or a model beyond :data:`TRUTH_BOUND` of their stds from it
            make the run untrustworthy, whatever the flags say (:func:`truth_disagreement`).

    Returns:
        :class:`Verdict`.
    """
    thr, tol_deg = _tolerances(frf, cfg)
    flags = frf.flags | np.where(frf.valid, 0, FAILED)  # a NaN point is a failed one, flagged or not
    has = {bit: (flags & bit) != 0 for bit in (POOR_FIT, TIMING, FAILED, LIMITED, NO_MOTION, ALIAS)}
    bad = (flags & UNTRUSTED) != 0
    n, k = int(flags.size), int(bad.sum())
    m_chi2, m_poor = model_adequacy(model)
    judged, disagree, models_part = judge_models(model, direct, expected)
    m_poor = m_poor or bool(models_part)
    band = timing_band_hz(frf, tol_deg)
    word = "points" if frf.is_siso else "channel points"
    limited = ""
    if has[LIMITED].any():
        limited = f"; {int(has[LIMITED].sum())} limited by the drive ({_freqs(frf, has[LIMITED], motion_px)})"
    beyond, m_beyond = truth_disagreement(frf, truth, model)
    t_bad = beyond is not None and bool(beyond.any() or m_beyond.any())
    model_part = (f"; the model does not explain the response (reduced chi2 {m_chi2:.3g} over {int(model.dof)} dof, above "
                  f"{model_chi2_limit(model.dof):.3g}): do not use model.json" if model_adequacy(model)[1] and direct is None
                  else models_part)
    model_part += _truth_part(frf, beyond, m_beyond) if t_bad else ""
    if not k and not m_poor and not t_bad:
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
        if has[ALIAS].any():
            parts.append(f"{int(has[ALIAS].sum())} alias ({_freqs(frf, has[ALIAS])}: one exposure, the phase branch not decided "
                         f"by continuity; use two exposures, e.g. sweep.exposures=[0.3,0.8])")
        head = f"verdict: {k} of {n} {word} flagged: {', '.join(parts)}" if k else f"verdict: all {n} {word} within tolerance"
        line = f"{head}{limited}{model_part}"
    ok = not k and not m_poor and not t_bad
    return Verdict(line=line, trustworthy=ok, exit_code=0 if ok else EXIT_FLAGGED, points=n, flagged=k,
                   poor_fit=int(has[POOR_FIT].sum()), timing=int(has[TIMING].sum()), failed=int(has[FAILED].sum()),
                   limited=int(has[LIMITED].sum()), timing_limit_hz=band, no_motion=int(has[NO_MOTION].sum()),
                   model_reduced_chi2=m_chi2, model_poor=m_poor, alias=int(has[ALIAS].sum()),
                   beyond_truth=None if beyond is None else int(beyond.sum()),
                   model_beyond_truth=None if m_beyond is None else int(m_beyond.sum()), models=judged, disagree=tuple(disagree))


#: the truth guard's bound: with the truth known (simulated rigs), a point whose error is more than
#: TRUTH_BOUND of its stds (``FrequencyResponse.errors_against``'s error/std), or a model whose response is
#: that far from the truth at a swept point (in the point's stds), makes the run untrustworthy
#: (docs/reliability.md, "The truth guard"). At 5 std an honest Gaussian error exceeds it once in 1.7 million.
TRUTH_BOUND = 5.0


def truth_disagreement(frf, truth, model=None, bound: float = TRUTH_BOUND):
    """The truth guard: ``(points [O, I, F], model_points [O, I, F])`` bool masks where the
    response, and the model's response, lie more than ``bound`` of the point's stds from the
    known ``truth`` (complex ``[O, I, F]`` or ``[F]``); ``(None, None)`` without a truth.
    Points where the truth is 0 or a std is unknown are not judged (NaN error/std); a model
    that has no ``frequency_response`` (or a MIMO one of another shape) is not judged."""
    if truth is None:
        return None, None
    t = np.asarray(truth, dtype=complex)
    if t.ndim == 1:
        t = np.broadcast_to(t, frf.response.shape)
    _, _, z = frf.errors_against(t)
    with np.errstate(invalid="ignore"):
        beyond = np.isfinite(z) & (z > bound)
    m_beyond = np.zeros_like(beyond)
    try:
        h = np.asarray(model.frequency_response(frf.omega), dtype=complex)
    except (AttributeError, TypeError, ValueError):
        h = None
    if h is not None and h.size == frf.response.size:
        _, _, zm = frf.replace(response=h.reshape(frf.response.shape)).errors_against(t)
        with np.errstate(invalid="ignore"):
            m_beyond = np.isfinite(zm) & (zm > bound) & frf.valid
    return beyond, m_beyond


def _truth_part(frf, beyond, m_beyond) -> str:
    """The verdict's words on the truth guard: the points (and model points) beyond the bound."""
    parts = []
    if beyond.any():
        parts.append(f"{int(beyond.sum())} point(s) beyond {TRUTH_BOUND:g} std of the known truth ({_freqs(frf, beyond)})")
    if m_beyond.any():
        parts.append(f"the model beyond {TRUTH_BOUND:g} std of the known truth at {int(m_beyond.sum())} point(s) "
                     f"({_freqs(frf, m_beyond)})")
    return "; " + " and ".join(parts) + ": not trustworthy whatever the flags say"


# MODEL_CHI2_FLOOR and model_chi2_limit (the rule's limit: a chi2 test at about 4 sigma, never below 2)
# live in torchblur.sysid.model_check, the one rule every model of a run is judged by; imported above.


def _none_passed(bad) -> str:
    """The verdict's words when no model passed (model.json's ``model_passed`` is false)."""
    inflated = any(j.std_factor != 1.0 for j in bad)
    return "no model passed" + (": model.json's stds are inflated by sqrt(reduced chi2) where the chi2 failed" if inflated else
                                ": model.json says so (model_passed false)")


def judge_models(model, direct=None, expected=()) -> tuple[tuple, list[str], str]:
    """Every model of the run judged by one rule (:func:`torchblur.sysid.model_check.judge_model`):
    ``(judgements, disagreements, verdict text)``. The two-step ``model`` (a TransferFunctionFit,
    each channel of a MIMO one) and the ``direct`` one (a DirectModelFit: named ``"direct"``, or
    ``"modal"`` for that form); the text (``""`` when all pass and agree) names each model that
    fails and why, the model the run's model.json then holds, and the parameters on which the
    direct and two-step models disagree beyond
    :data:`~torchblur.sysid.model_check.DISAGREE_SIGMA` combined stds."""
    if model is not None and not hasattr(model, "is_siso"):
        return (), [], ""  # a bare (reduced_chi2, dof) record: model_adequacy judges it
    two = judge_fit(model, "two-step")
    d_name = "modal" if getattr(direct, "form", "") == "modal" else "direct"
    dj = judge_fit(direct, d_name)
    disagree = disagreements(direct, model) if model is not None and model.is_siso and direct is not None else []
    if disagree and dj and dj[0].passed and all(j.passed for j in two):
        # Both explain their data, yet differ beyond their stds: the two-step points were each
        # tested against their images (and fitted with the measured kernel where the still asked
        # for it), the direct model with the Gaussian only: the direct model is the one set aside.
        dj = (dataclasses.replace(dj[0], passed=False, reason=f"it disagrees with the two-step model beyond "
                                  f"{DISAGREE_SIGMA:g} combined stds"),)
    missing = tuple(ModelJudgement(name, False, None, None, None, "its fit failed: no model (see the log)")
                    for name, m in (("two-step", model), ("direct", direct)) if name in expected and m is None)
    judged = two + dj + missing
    bad = [j for j in judged if not j.passed]
    parts = [f"the {j.name} model fails ({j.reason})" for j in bad]
    if bad and (direct is not None or "direct" in expected):
        keep = "the direct model" if dj and dj[0].passed else "the two-step model" if two and all(j.passed for j in two) else None
        parts.append(f"model.json holds {keep}" if keep else _none_passed(bad))
    elif bad:
        parts.append(_none_passed(bad))
    if disagree:
        parts.append(f"the {d_name} and two-step models disagree beyond {DISAGREE_SIGMA:g} combined stds on "
                     f"{'; '.join(disagree)}")
    return judged, disagree, "".join(f"; {p}" for p in parts)


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
        if frf.flags[o, i, k] & ALIAS and left_out[o, i, k]:
            extra += ", left out of the model fit (its phase may be the alias)"
        elif frf.flags[o, i, k] & POOR_FIT:
            extra += f", stds x{math.sqrt(chi2):.3g}, " + ("left out of the model fit" if left_out[o, i, k] else
                                                         "kept in the model fit (too few points without it)")
        lines.append(f"  flagged {_hz(float(frf.freq_hz[k]))}{where}: {flag_names(frf.flags[o, i, k])}{extra}")
    return lines
