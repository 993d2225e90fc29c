"""The one-line verdict every run ends with, for every plan: one :class:`Verdict` type (the line,
trustworthy, the exit status, the report's lines on what was flagged) built one way
(:meth:`Verdict.judged`, then :meth:`Verdict.untrusted` for each guard that fails), and each
plan's rules (pure functions of the run's results and its config).

- Sine and multisine runs (:func:`verdict`, a :class:`ResponseVerdict`): the per-point flags
  and the line, docs/reliability.md, "Per-point flags and the verdict"; the rule behind each
  flag, :mod:`torchblur.identify.assemble`.
- DM runs (:func:`dm_verdict`, a :class:`DMVerdict`, then :data:`DM_GUARDS` by
  :func:`final_verdict`): the actuator flags ``poor fit`` and ``failed``
  (:func:`failed_actuators`, :data:`LOST_FRACTION`), the statuses dead and weak, the spot fits
  (:data:`POOR_SPOT_FRACTION`), docs/deformable_mirrors.md, "Verdict".
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from torchblur.dm.actuator_fit import PARAMS, POOR_FIT_P, ActuatorTable
from torchblur.dm.plans import driven_spots
from torchblur.dm.registration import support_line
from torchblur.errors import ParameterError, ShapeError, check_int, check_type
from torchblur.identify.assemble import timing_limit_hz
from torchblur.identify.model import model_exclusions
from torchblur.sysid.flags import ALIAS, FAILED, LIMITED, NO_MOTION, POOR_FIT, TIMING, UNTRUSTED, flag_names
from torchblur.sysid.model_check import (DISAGREE_SIGMA, MODEL_CHI2_FLOOR, ModelJudgement, disagreements, judge_fit, model_chi2_limit,
                                         model_fails)

__all__ = ["DMVerdict", "DM_GUARDS", "EXIT_FLAGGED", "LOST_FRACTION", "MODEL_CHI2_FLOOR", "POOR_SPOT_FRACTION", "ResponseVerdict",
           "TRUTH_BOUND", "Verdict", "dm_verdict", "failed_actuators", "final_verdict", "judge_models", "listed", "lost_fraction",
           "model_chi2_limit", "registration_guard", "ladder_guard", "ladder_on_hadamard", "LADDER_ON_HADAMARD", "report_lines",
           "run_verdict", "support_guard", "timing_band_hz",
           "truth_disagreement", "truth_disagreement_dm", "truth_guard", "verdict"]

#: exit status of a run that completed, results written, with points flagged poor_fit, timing or failed
#: (3 is taken: the rig stopped the run)
EXIT_FLAGGED = 4
#: the truth guard's bound: with the truth known (simulated rigs), a point whose error is more than
#: TRUTH_BOUND of its stds (``FrequencyResponse.errors_against``'s error/std), a model whose response is
#: that far from the truth at a swept point (in the point's stds), or an actuator that far from the
#: simulated mirror makes the run untrustworthy (docs/reliability.md, "The truth guard"). At 5 std an
#: honest Gaussian error exceeds it once in 1.7 million.
TRUTH_BOUND = 5.0
#: an actuator whose column ``D[:, j, :]`` has more than this fraction of its entries (on its
#: support) lost to failed spot fits is flagged failed
LOST_FRACTION = 0.1
#: more than this fraction of the spot fits above ``poor_fit_chi2``: the spot model does not explain the images
POOR_SPOT_FRACTION = 0.01

_LISTED = 6  # items named per kind before "..."
_LIVE_PARAMS = tuple(k for p in PARAMS for k in (p, p + "_std"))  # each parameter then its std (a dead actuator: the first two)


#: how a verdict line that every rule passed begins, and how it begins once a later rule fails (:meth:`Verdict.untrusted`)
TRUSTED_HEAD, UNTRUSTED_HEAD = "verdict: trustworthy", "verdict: not trustworthy"


@dataclass(frozen=True, kw_only=True)
class Verdict:
    """A run's verdict, whatever its plan (the plan's own counts in its subclass).

    Attributes:
        line: the one line (``"verdict: ..."``), the last of report.txt and of the terminal's.
        trustworthy: no rule of the plan failed.
        exit_code: 0 when trustworthy, else :data:`EXIT_FLAGGED`.
        details: the report's lines on what was flagged and why (before the verdict line).
    """

    line: str
    trustworthy: bool
    exit_code: int
    details: tuple = ()

    @classmethod
    def judged(cls, *, failing: bool, trusted_line: str, head: str, reasons=(), **fields):
        """The one way a verdict is made: trustworthy (exit 0, ``trusted_line``) when nothing is
        ``failing`` and no rule gave a reason; else ``head`` then ``"; reason"`` for each of
        ``reasons``, exit :data:`EXIT_FLAGGED`. ``fields``: the plan's counts."""
        ok = not failing and not reasons
        line = trusted_line if ok else head + "".join(f"; {r}" for r in reasons)
        return cls(line=line, trustworthy=ok, exit_code=0 if ok else EXIT_FLAGGED, **fields)

    def untrusted(self, reason: str, *details: str, **fields):
        """This verdict with one more rule failed: ``"; reason"`` appended to the line, ``details``
        to the report's lines, not trustworthy (exit :data:`EXIT_FLAGGED`); ``fields`` changed. A line
        that began ``verdict: trustworthy`` (every earlier rule held) begins ``verdict: not trustworthy``:
        its first words are what a reader takes in."""
        line = self.line
        if line.startswith(TRUSTED_HEAD):
            line = UNTRUSTED_HEAD + line[len(TRUSTED_HEAD):]
        return replace(self, line=f"{line}; {reason}", trustworthy=False, exit_code=EXIT_FLAGGED,
                       details=(*self.details, *details), **fields)

    def to_dict(self) -> dict:
        """The fields as a strict-JSON dict (tuples as lists, a non-finite float as null)."""
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else None if isinstance(v, float) and not math.isfinite(v) else v
                for k, v in d.items()}


@dataclass(frozen=True, kw_only=True)
class ResponseVerdict(Verdict):
    """A sine or multisine run's verdict (:func:`verdict`).

    Attributes:
        points: the response's points (channel points [O, I, F] of a MIMO response).
        flagged: points with a poor_fit, timing or failed flag.
        poor_fit, timing, failed, limited: points with each flag (a point may have several).
        timing_limit_hz: the frequency above which the timing terms exceed the tolerance (inf:
            never; None: unknown, the response has no ``timing`` meta).
        alias: points flagged alias (one exposure, branch not decided by continuity).
        beyond_truth, model_beyond_truth: with a known truth, the points (and the points where
            the model) lie more than :data:`TRUTH_BOUND` stds from it (None: no truth known).
    """

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


@dataclass(frozen=True, kw_only=True)
class DMVerdict(Verdict):
    """A DM run's verdict (:func:`dm_verdict`; ``details``: one line per flagged actuator, why).

    Attributes:
        actuators: N.
        flagged: actuators flagged poor fit or failed (an actuator may be both).
        poor_fit, failed: the actuators (indices) with each flag.
        ok, weak, dead: the actuators (indices) with each status.
        failed_spot_fits, spot_problems: failed spot fits, of how many.
        max_reduced_chi2: the largest finite model reduced chi2 (None: none).
        poor_spot_fits: spot fits above ``poor_fit_chi2``; spot_model_fails: more than
            :data:`POOR_SPOT_FRACTION` of them (the run is then untrustworthy).
        beyond_truth: with the simulated truth known, the actuators whose parameters lie more than
            :data:`TRUTH_BOUND` stds from it or whose status is wrong (:func:`truth_guard`); None
            without a truth.
    """

    actuators: int
    flagged: int
    poor_fit: tuple
    failed: tuple
    ok: tuple
    weak: tuple
    dead: tuple
    failed_spot_fits: int
    spot_problems: int
    max_reduced_chi2: float | None
    poor_spot_fits: int = 0
    spot_model_fails: bool = False
    beyond_truth: tuple | None = None


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


# -- sine and multisine runs: the response's points, the models, the truth ------------------------------

def verdict(frf, cfg=None, *, motion_px=None, model=None, direct=None, expected=(), truth=None) -> ResponseVerdict:
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
    """
    thr, tol_deg = _tolerances(frf, cfg)
    flags = frf.flags | np.where(frf.valid, 0, FAILED)  # a NaN point is a failed one, flagged or not
    has = {bit: (flags & bit) != 0 for bit in (POOR_FIT, TIMING, FAILED, LIMITED, NO_MOTION, ALIAS)}
    n, k = int(flags.size), int(((flags & UNTRUSTED) != 0).sum())
    m_chi2, m_poor = model_adequacy(model)
    judged, disagree, reasons = judge_models(model, direct, expected)
    if m_poor and direct is None:
        reasons = [f"the model does not explain the response (reduced chi2 {m_chi2:.3g} over {int(model.dof)} dof, above "
                   f"{model_chi2_limit(model.dof):.3g}): do not use model.json"]
    m_poor = m_poor or bool(reasons)
    band = timing_band_hz(frf, tol_deg)
    word = "points" if frf.is_siso else "channel points"
    limited = ""
    if has[LIMITED].any():
        limited = f"; {int(has[LIMITED].sum())} limited by the drive ({_freqs(frf, has[LIMITED], motion_px)})"
    beyond, m_beyond = truth_disagreement(frf, truth, model)
    if beyond is not None and bool(beyond.any() or m_beyond.any()):
        reasons = [*reasons, _truth_reason(frf, beyond, m_beyond)]
    unknown = int((~np.isfinite(frf.reduced_chi2) & frf.valid).sum())
    timing = f"timing within {tol_deg:g} deg"
    if band is not None:
        timing += " (no timing terms)" if math.isinf(band) else f" up to {_hz(band)}"
    trusted = (f"verdict: trustworthy: all {n} {word} within tolerance: reduced chi2 <= {thr:g}"
               + (f" ({unknown} unknown: not checked)" if unknown else "") + f", {timing}{limited}")
    head = (f"verdict: {k} of {n} {word} flagged: {', '.join(_flag_parts(frf, has, band, tol_deg))}" if k
            else f"verdict: all {n} {word} within tolerance")
    return ResponseVerdict.judged(
        failing=bool(k) or m_poor, trusted_line=trusted, head=head + limited, reasons=reasons, points=n, flagged=k,
        poor_fit=int(has[POOR_FIT].sum()), timing=int(has[TIMING].sum()), failed=int(has[FAILED].sum()),
        limited=int(has[LIMITED].sum()), timing_limit_hz=band, no_motion=int(has[NO_MOTION].sum()), model_reduced_chi2=m_chi2,
        model_poor=m_poor, alias=int(has[ALIAS].sum()), beyond_truth=None if beyond is None else int(beyond.sum()),
        model_beyond_truth=None if m_beyond is None else int(m_beyond.sum()), models=judged, disagree=tuple(disagree))


def _flag_parts(frf, has: dict, band: float | None, tol_deg: float) -> list[str]:
    """The flagged line's words per flag kind (``has``: {flag bit: [O, I, F] mask})."""
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
    return parts


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


def _truth_reason(frf, beyond, m_beyond) -> str:
    """The verdict's words on the truth guard: the points (and model points) beyond the bound."""
    parts = []
    if beyond.any():
        parts.append(f"{int(beyond.sum())} point(s) beyond {TRUTH_BOUND:g} std of the known truth ({_freqs(frf, beyond)})")
    if m_beyond.any():
        parts.append(f"the model beyond {TRUTH_BOUND:g} std of the known truth at {int(m_beyond.sum())} point(s) "
                     f"({_freqs(frf, m_beyond)})")
    return " and ".join(parts) + ": not trustworthy whatever the flags say"


def _none_passed(bad) -> str:
    """The verdict's words when no model passed (model.json's ``model_passed`` is false)."""
    inflated = any(j.std_factor != 1.0 for j in bad)
    return "no model passed" + (": model.json's stds are inflated by sqrt(reduced chi2) where the chi2 failed" if inflated else
                                ": model.json says so (model_passed false)")


def judge_models(model, direct=None, expected=()) -> tuple[tuple, list[str], list[str]]:
    """Every model of the run judged by one rule (:func:`torchblur.sysid.model_check.judge_model`):
    ``(judgements, disagreements, the verdict's reasons)``. The two-step ``model`` (a TransferFunctionFit,
    each channel of a MIMO one) and the ``direct`` one (a DirectModelFit: named ``"direct"``, or
    ``"modal"`` for that form); the reasons (none when all pass and agree) name each model that
    fails and why, the model the run's model.json then holds, and the parameters on which the
    direct and two-step models disagree beyond
    :data:`~torchblur.sysid.model_check.DISAGREE_SIGMA` combined stds."""
    if model is not None and not hasattr(model, "is_siso"):
        return (), [], []  # a bare (reduced_chi2, dof) record: model_adequacy judges it
    two = judge_fit(model, "two-step")
    d_name = "modal" if getattr(direct, "form", "") == "modal" else "direct"
    dj = judge_fit(direct, d_name)
    disagree = disagreements(direct, model) if model is not None and model.is_siso and direct is not None else []
    if disagree and dj and dj[0].passed and all(j.passed for j in two):
        # Both explain their data, yet differ beyond their stds: the two-step points were each
        # tested against their images (and fitted with the measured kernel where the still asked
        # for it), the direct model with the Gaussian only: the direct model is the one set aside.
        dj = (replace(dj[0], passed=False, reason=f"it disagrees with the two-step model beyond "
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
    return judged, disagree, parts


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


# -- DM runs: the actuators, the spot fits, the guards ---------------------------------------------------

def lost_fraction(D) -> np.ndarray:
    """``[N]``: per actuator the fraction of its column's entries ``D[s, j, f]`` that are NaN
    (lost to failed spot fits), over the entries of its support: the slopes where ``D[s, j, :]``
    is not exactly 0 at every frequency (:func:`~torchblur.dm.demux.demultiplex` writes exact
    zeros off a sparse plan's support); 0 for a column with no support.

    Args:
        D: ``[2M, N, F]`` complex.
    """
    D = np.asarray(D)
    n = _support(D).sum(0) * D.shape[-1]
    return np.where(n > 0, np.isnan(D).sum((0, 2)) / np.maximum(n, 1), 0.0)


def _support(D) -> np.ndarray:
    """``[2M, N]`` bool: ``D[s, j, :]`` is not exactly 0 at every frequency (a NaN entry is not 0:
    a lost slope stays on the support)."""
    return np.any(np.asarray(D) != 0, axis=-1)


def failed_actuators(table: ActuatorTable, D) -> dict:
    """``{j: reason}`` for every actuator flagged failed, ``D`` ``[2M, N, F]``: a live actuator
    (ok or weak) with ``dc_gain``, ``mode_hz``, ``damping``, ``delay_s`` or a std not finite, a
    dead one with ``dc_gain`` or its std not finite, or one whose column lost its data to failed
    spot fits (a slope of its support without a finite ``D0``, or more than
    :data:`LOST_FRACTION` of its entries NaN: :func:`lost_fraction`)."""
    dead = np.array([s == "dead" for s in table.status], dtype=bool)
    names = np.array(_LIVE_PARAMS)
    est = np.stack([np.asarray(getattr(table, k), dtype=np.float64) for k in _LIVE_PARAMS], 1)  # [N, 8]
    bad = ~np.isfinite(est)
    bad[dead, 2:] = False  # a dead actuator reports dc_gain and dc_gain_std only (the first two)
    hole = _support(D) & ~np.isfinite(np.asarray(table.static_column, dtype=np.float64))  # [2M, N]
    frac = lost_fraction(D)
    out = {}
    for j in range(len(table)):
        why = []
        if bad[j].any():
            why.append(f"{', '.join(names[bad[j]])} not finite")
        if hole[:, j].any():
            why.append(f"no static column entry at {int(hole[:, j].sum())} slope(s) (no data left there)")
        if frac[j] > LOST_FRACTION:
            why.append(f"{frac[j] * 100:.3g} % of its column lost to failed spot fits (more than {LOST_FRACTION * 100:g} %)")
        if why:
            out[j] = "; ".join(why)
    return out


def _check(table, D, n_failed_spot_fits, n_spot_problems):
    check_type(table, "table", ActuatorTable, "an ActuatorTable")
    D = np.asarray(D)
    want = (np.shape(table.static_column)[0], len(table), len(table.freq_hz))
    if D.shape != want:
        raise ShapeError(f"D: expected [2M, N, F] = {list(want)} (the table's), got shape {D.shape}")
    n_problems = check_int(n_spot_problems, "n_spot_problems", low=0)
    n_failed = check_int(n_failed_spot_fits, "n_failed_spot_fits", low=0)
    if n_failed > n_problems:
        raise ParameterError(f"n_failed_spot_fits: expected at most n_spot_problems = {n_problems}, got {n_failed}")
    return D, n_failed, n_problems


def _status_part(ok, weak, dead) -> str:
    """``"50 ok, 1 weak (33), 1 dead (20)"`` (weak and dead named, each only when there are some)."""
    parts = [f"{len(ok)} ok"] + [f"{len(ix)} {word} ({listed(ix)})" for word, ix in (("weak", weak), ("dead", dead)) if ix]
    return ", ".join(parts)


def _detail(j: int, status: str, poor_chi2: float | None, failed_why: str | None) -> str:
    """The report's line on flagged actuator ``j`` (``poor_chi2``: its reduced chi2 when poor fit, else None)."""
    why = []
    if poor_chi2 is not None:
        why.append(f"poor fit (reduced chi2 {poor_chi2:.3g}, stds x{np.sqrt(poor_chi2):.3g})" if np.isfinite(poor_chi2) else "poor fit")
    if failed_why is not None:
        why.append(f"failed: {failed_why}")
    return f"  flagged actuator {j} ({status}): {'; '.join(why)}"


def dm_verdict(table: ActuatorTable, *, D, n_failed_spot_fits: int, n_spot_problems: int, spot_reduced_chi2=None,
               poor_fit_chi2: float = 1.5) -> DMVerdict:
    """The verdict on a DM run (docs/deformable_mirrors.md, "Verdict"): flagged actuators
    (``poor_fit``, :func:`failed_actuators`) or too many poor spot fits make it untrustworthy.

    Args:
        table: the run's :class:`~torchblur.dm.actuator_fit.ActuatorTable` (N actuators).
        D: ``[2M, N, F]`` complex, the demultiplexed dynamic interaction matrix (NaN where
            failed spot fits left an entry undetermined).
        n_failed_spot_fits: spot problems whose fit failed.
        n_spot_problems: spot problems fitted in all (patterns x frequencies x spots).
        spot_reduced_chi2: every spot fit's reduced chi2 (any shape; NaN for failed fits), or None
            (not judged).
        poor_fit_chi2: the reduced chi2 above which a spot fit does not explain its images.

    Returns:
        :class:`DMVerdict`.

    Raises:
        InputTypeError: ``table`` is not an ActuatorTable. ShapeError: ``D`` does not match the
            table. ParameterError: a count is negative, or more fits failed than there were.
    """
    D, n_failed, n_problems = _check(table, D, n_failed_spot_fits, n_spot_problems)
    status = np.asarray(table.status)
    ok, weak, dead = (tuple(int(j) for j in np.flatnonzero(status == s)) for s in ("ok", "weak", "dead"))
    poor = tuple(int(j) for j in np.flatnonzero(np.asarray(table.poor_fit, dtype=bool)))
    failed_why = failed_actuators(table, D)
    failed = tuple(sorted(failed_why))
    flagged = sorted(set(poor) | set(failed))
    chi2 = np.asarray(table.reduced_chi2, dtype=np.float64)
    max_chi2 = float(np.max(chi2[np.isfinite(chi2)])) if np.isfinite(chi2).any() else None
    n = len(table)
    statuses = _status_part(ok, weak, dead)
    poor_spots, spots_fail, spots = _spot_fits(spot_reduced_chi2, poor_fit_chi2, n_problems)
    fits = f"{n_failed} of {n_problems} spot fits failed{spots}"
    model = (f"model reduced chi2 <= {max_chi2:.3g} (chi2 test p >= {POOR_FIT_P:g} over the run's actuators)" if max_chi2 is not None
             else "no actuator model to test")
    kinds = [f"{len(ix)} {word} ({listed(ix)})" for word, ix in (("poor fit", poor), ("failed", failed)) if ix]
    head = (f"verdict: {len(flagged)} of {n} actuators flagged: {', '.join(kinds)}" if flagged
            else "verdict: untrustworthy: the spot model does not explain the images")
    return DMVerdict.judged(
        failing=bool(flagged) or spots_fail, trusted_line=f"verdict: trustworthy: all {n} actuators within tolerance: {statuses}; "
        f"{model}; {fits}", head=f"{head}; status {statuses}; {fits}", actuators=n, flagged=len(flagged), poor_fit=poor,
        failed=failed, ok=ok, weak=weak, dead=dead, failed_spot_fits=n_failed, spot_problems=n_problems, max_reduced_chi2=max_chi2,
        details=tuple(_detail(j, status[j], chi2[j] if j in poor else None, failed_why.get(j)) for j in flagged),
        poor_spot_fits=poor_spots, spot_model_fails=spots_fail)


def _spot_fits(chi2, threshold: float, n_problems: int) -> tuple[int, bool, str]:
    """``(poor spot fits, too many, the line's words)`` of the spot fits' reduced chi2:
    more than :data:`POOR_SPOT_FRACTION` of them above ``threshold`` is too many."""
    if chi2 is None:
        return 0, False, ""
    c = np.asarray(chi2, dtype=np.float64).ravel()
    c = c[np.isfinite(c)]
    k = int((c > threshold).sum())
    fails = k > POOR_SPOT_FRACTION * max(n_problems, 1)
    words = f", {k} above reduced chi2 {threshold:g} (median {float(np.median(c)) if c.size else float('nan'):.3g})"
    if fails:
        words += (f": more than {POOR_SPOT_FRACTION:.0%} of the spot fits do not explain their images (the spots' Gaussian PSF "
                  f"or the camera's noise model does not fit them): every std is too small")
    return k, fails, words


def run_verdict(res, *, poor_fit_chi2: float = 1.5) -> DMVerdict:
    """:func:`dm_verdict` of a :class:`~torchblur.identify.dm_plan.DMResult` (the spot problems its plan measures,
    :func:`~torchblur.dm.plans.driven_spots` at every frequency, their reduced chi2 judged against
    ``poor_fit_chi2``, the run's ``fit.poor_fit_chi2``)."""
    n_problems = int(driven_spots(res.plan).sum()) * len(res.freq_hz)
    return dm_verdict(res.actuators, D=res.D, n_failed_spot_fits=int(res.n_failed), n_spot_problems=n_problems,
                      spot_reduced_chi2=getattr(res, "spot_reduced_chi2", None), poor_fit_chi2=poor_fit_chi2)


def truth_disagreement_dm(actuators: ActuatorTable, mirror, bound: float = TRUTH_BOUND) -> tuple:
    """The actuators (indices) that disagree with the simulated ``mirror`` (a
    :class:`~torchblur.dm.mirror.DeformableMirror`): a live one whose ``dc_gain``, ``mode_hz``
    or ``damping`` lies more than ``bound`` of its std from the truth (or is not finite), a dead
    one not reported dead, or a live one reported dead."""
    dead = np.asarray(mirror.dead, dtype=bool)
    status = np.asarray(actuators.status)
    bad = dead != (status == "dead")
    with np.errstate(invalid="ignore", divide="ignore"):
        for est, std, true in ((actuators.dc_gain, actuators.dc_gain_std, mirror.gain), (actuators.mode_hz, actuators.mode_hz_std,
                                                                                        mirror.mode_hz),
                               (actuators.damping, actuators.damping_std, mirror.damping)):
            z = np.abs(np.asarray(est, dtype=np.float64) - np.asarray(true, dtype=np.float64)) / np.asarray(std, dtype=np.float64)
            bad |= ~dead & ~(z <= bound)
    return tuple(int(j) for j in np.flatnonzero(bad))


def truth_guard(v: DMVerdict, res, bound: float = TRUTH_BOUND) -> DMVerdict:
    """``v`` with the truth guard of a simulated run (``res.mirror``, the truth; None on a real
    rig: ``v`` unchanged): actuators beyond ``bound`` stds of the truth (:func:`truth_disagreement_dm`)
    make the run untrustworthy whatever its flags, and the line names them (docs/reliability.md,
    "The truth guard")."""
    mirror = getattr(res, "mirror", None)
    if mirror is None:
        return v
    beyond = truth_disagreement_dm(res.actuators, mirror, bound)
    if not beyond:
        return replace(v, beyond_truth=())
    return v.untrusted(f"{len(beyond)} actuator(s) beyond {bound:g} std of the simulated truth or with a wrong status "
                       f"({listed(beyond)}): not trustworthy whatever the flags say", beyond_truth=beyond)


def support_guard(v, info: dict | None):
    """The DM verdict ``v`` made untrustworthy (exit :data:`EXIT_FLAGGED`)
    when the fitted geometry needs support the plan lacks (:func:`~torchblur.dm.registration.support_check`); else ``v``."""
    line = support_line(info)
    if line is None:
        return v
    return v.untrusted(f"the plan's support lacks {info['n_missing']} pair(s) the fitted geometry needs: not trustworthy", line)


def registration_guard(v, reg):
    """The DM verdict ``v`` made untrustworthy when the mirror model fails the one model rule
    (:func:`~torchblur.sysid.model_check.model_fails`) on the static columns it was registered to:
    its registration's stds and the reference ``dc_gain`` is relative to do not hold (a mirror
    whose influence functions the model's Gaussian does not describe); else ``v``."""
    if reg is None or not reg.ok or not model_fails(reg.reduced_chi2, reg.dof):
        return v
    line = (f"dm registration: the mirror model does not explain D0 (reduced chi2 {reg.reduced_chi2:.3g} over {reg.dof} dof, "
            f"limit {model_chi2_limit(reg.dof):.3g}): the registration's stds and dc_gain's reference do not hold")
    return v.untrusted(f"the mirror model does not explain D0 (registration reduced chi2 {reg.reduced_chi2:.3g}): not trustworthy",
                       line)


#: why a ladder run on a Hadamard plan is not trustworthy (:func:`ladder_guard`; the run warns with it as soon as
#: the plan and the spot model are both known, :func:`ladder_on_hadamard`)
LADDER_ON_HADAMARD = ("the ladder spot model on a Hadamard plan pulls each actuator's response toward its neighbours' (their stds "
                      "do not hold on HCIPy's lenslet frames, benchmarks/bench_dm_hcipy.py; dm_plan.kind=auto takes a sparse plan "
                      "for the ladder): D(jw) and its stds stand, the actuators' stds do not: not trustworthy")


def ladder_on_hadamard(spot_model: str, plan_kind: str) -> bool:
    """A DM run whose spots take the ladder (``spot_model``) on a plan of kind ``plan_kind`` whose
    patterns move several of the actuators a spot sees: what :func:`ladder_guard` makes untrustworthy."""
    return spot_model == "ladder" and plan_kind == "hadamard"


def ladder_guard(v, res):
    """The DM verdict ``v`` of a run fitted with the ladder spot model (``res.spot_model``;
    ``v`` unchanged for the shifted still): how many spot fits' motion left the ladder's levels
    (``res.n_out_of_ladder``: the end cubics extrapolated, those responses left out of ``D``;
    more than :data:`POOR_SPOT_FRACTION` of the spot fits is a reason of its own), and, on a plan
    whose patterns move several of the actuators a spot sees (Hadamard), not trustworthy: there the
    ladder ties a spot's shape to the pattern's common command and pulls each actuator's response
    toward its neighbours', and on HCIPy's lenslet frames the actuators' stds do not hold (the whole
    grid, aligned and misregistered: modes' rms(error/std) 1.98 and 2.17, dampings' 1.40 and 1.63;
    the modes' errors follow the responses at the frequency just above them, where the actuators
    differ most, and neither the spot fits' chi2 nor the demultiplexing's residuals show it there, so
    no std can be grown from the data: docs/deformable_mirrors.md, "The whole frequency grid"). On a sparse or one-at-a-time plan (where each spot
    sees one actuator of a pattern: what ``dm_plan.kind=auto`` takes for the ladder) they hold on
    both whole grids of HCIPy's lenslet frames (``benchmarks/bench_dm_hcipy.py``, the figures in
    docs/deformable_mirrors.md, "The plans"), and the run is judged by the other rules."""
    if getattr(res, "spot_model", "shifted") != "ladder":
        return v
    n_out = int(getattr(res, "n_out_of_ladder", 0) or 0)
    if n_out:
        note = f"{n_out} spot fits' motion left the ladder's levels (left out of D; raise dm_plan.ladder_reach)"
        v = v.untrusted(note) if n_out > POOR_SPOT_FRACTION * max(v.spot_problems, 1) else replace(v, line=f"{v.line}; {note}")
    if not ladder_on_hadamard("ladder", getattr(getattr(res, "plan", None), "kind", "hadamard")):
        return v
    return v.untrusted(LADDER_ON_HADAMARD)


#: the DM's guards, applied in order after :func:`run_verdict` by :func:`final_verdict`: each
#: ``(verdict, DMResult) -> verdict``, the verdict unchanged when its rule holds, else
#: :meth:`Verdict.untrusted` (a new DM rule is one more function here)
DM_GUARDS = (truth_guard, lambda v, res: support_guard(v, res.support_check), lambda v, res: registration_guard(v, res.registration),
             ladder_guard)


def final_verdict(res, poor_fit_chi2: float) -> DMVerdict:
    """A DM run's verdict with every guard: :func:`run_verdict`, then each of :data:`DM_GUARDS` (one
    place for the run, a re-fit and an outside recording)."""
    v = run_verdict(res, poor_fit_chi2=poor_fit_chi2)
    for guard in DM_GUARDS:
        v = guard(v, res)
    return v
