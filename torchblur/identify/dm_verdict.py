"""The one-line verdict a DM run ends with (pure: from the actuator table, the demultiplexed
``D`` and the count of failed spot fits).

Per actuator (:class:`~torchblur.dm.actuator_fit.ActuatorTable`), two flags make a run
untrustworthy (exit status :data:`~torchblur.identify.verdict.EXIT_FLAGGED`):

- **poor fit**: the actuator's ``poor_fit`` (its parametric model fails the chi2 test, survival
  probability below :data:`~torchblur.dm.actuator_fit.POOR_FIT_P`: the stds were inflated by
  ``sqrt(reduced chi2)``, the numbers are not to be trusted at their nominal precision). Kept
  for a dead actuator too: a column the model could not explain that is then called dead is
  a call to check.
- **failed** (:func:`failed_actuators`): a live actuator (ok or weak) whose ``dc_gain``,
  ``mode_hz``, ``damping``, ``delay_s`` or one of their stds is not finite; a dead one whose
  ``dc_gain`` or ``dc_gain_std`` is not finite; or any actuator whose column lost its data to
  failed spot fits: a slope of its support left without a static column entry (``D0`` not
  finite: the interaction matrix would have a hole), or more than :data:`LOST_FRACTION` of its
  column's entries ``D[s, j, f]`` (the slopes of its support times the frequencies) NaN.

Dead and weak are statuses, not flags: a dead actuator reported dead is a correct
measurement; the line names them. Failed spot fits are counted (``k of n spot fits failed``)
and make the run untrustworthy only through the rule above: :func:`~torchblur.dm.demux.demultiplex`
leaves a failed fit's pattern out, so the data left still give an unbiased ``D`` with honest
(larger) stds, until the column loses so much that it is no longer measured as planned.

The spot fits themselves (``spot_reduced_chi2``, when given): every spot is fitted with a
Gaussian PSF from the still frames and the camera's noise model; a fit whose reduced chi2 is
above ``poor_fit_chi2`` (``fit.poor_fit_chi2``, 1.5) does not explain its images. One such fit in
a thousand is a stray (a cosmic ray, a hot pixel); more than :data:`POOR_SPOT_FRACTION` of them
means the model does not describe these spots (a real lenslet's spot is not a Gaussian, a camera
not in the noise model), every std of the run is too small and the figures may be biased: the
run is untrustworthy and the line says so.

Lines::

    verdict: trustworthy: all 52 actuators within tolerance: 50 ok, 1 weak (33), 1 dead (20); model reduced chi2 <= 1.48 (chi2 test p >= 0.001); 0 of 81920 spot fits failed
    verdict: 3 of 52 actuators flagged: 2 poor fit (12, 40), 1 failed (7); status 50 ok, 1 weak (33), 1 dead (20); 96 of 81920 spot fits failed
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from torchblur.dm.actuator_fit import POOR_FIT_P, ActuatorTable
from torchblur.dm.registration import support_line
from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_int
from torchblur.identify.verdict import EXIT_FLAGGED, TRUTH_BOUND, listed
from torchblur.sysid.model_check import model_chi2_limit, model_fails

__all__ = ["DMVerdict", "dm_verdict", "failed_actuators", "lost_fraction", "run_verdict", "truth_guard", "truth_disagreement_dm", "support_guard", "registration_guard", "ladder_guard", "final_verdict",
           "LOST_FRACTION", "POOR_SPOT_FRACTION"]

#: an actuator whose column ``D[:, j, :]`` has more than this fraction of its entries (on its
#: support) lost to failed spot fits is flagged failed
LOST_FRACTION = 0.1
#: more than this fraction of the spot fits above ``poor_fit_chi2``: the spot model does not explain the images
POOR_SPOT_FRACTION = 0.01

_LIVE_PARAMS = ("dc_gain", "dc_gain_std", "mode_hz", "mode_hz_std", "damping", "damping_std", "delay_s", "delay_s_std")


@dataclass(frozen=True)
class DMVerdict:
    """A DM run's verdict.

    Attributes:
        line: the one line (``"verdict: ..."``).
        trustworthy: no actuator flagged poor fit or failed.
        exit_code: 0 when trustworthy, else :data:`~torchblur.identify.verdict.EXIT_FLAGGED`.
        actuators: N.
        flagged: actuators flagged poor fit or failed (an actuator may be both).
        poor_fit, failed: the actuators (indices) with each flag.
        ok, weak, dead: the actuators (indices) with each status.
        failed_spot_fits, spot_problems: failed spot fits, of how many.
        max_reduced_chi2: the largest finite model reduced chi2 (None: none).
        poor_spot_fits: spot fits above ``poor_fit_chi2``; spot_model_fails: more than
            :data:`POOR_SPOT_FRACTION` of them (the run is then untrustworthy).
        details: one line per flagged actuator (why), for the report.
        beyond_truth: with the simulated truth known, the actuators whose parameters lie more than
            :data:`~torchblur.identify.verdict.TRUTH_BOUND` stds from it or whose status is wrong
            (:func:`truth_guard`); None without a truth.
    """

    line: str
    trustworthy: bool
    exit_code: int
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
    details: tuple = ()
    poor_spot_fits: int = 0
    spot_model_fails: bool = False
    beyond_truth: tuple | None = None

    def to_dict(self) -> dict:
        """The fields as a strict-JSON dict (index tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


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
    """``{j: reason}`` for every actuator flagged failed (module rules), ``D`` ``[2M, N, F]``."""
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
    if not isinstance(table, ActuatorTable):
        raise InputTypeError(f"table: expected an ActuatorTable, got {type(table).__name__}")
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
    """The verdict on a DM run (module rules).

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
    fits = f"{n_failed} of {n_problems} spot fits failed"
    poor_spots, spots_fail, spots = _spot_fits(spot_reduced_chi2, poor_fit_chi2, n_problems)
    fits += spots
    if not flagged and not spots_fail:
        model = (f"model reduced chi2 <= {max_chi2:.3g} (chi2 test p >= {POOR_FIT_P:g})" if max_chi2 is not None
                 else "no actuator model to test")
        line = f"verdict: trustworthy: all {n} actuators within tolerance: {statuses}; {model}; {fits}"
    elif flagged:
        kinds = [f"{len(ix)} {word} ({listed(ix)})" for word, ix in (("poor fit", poor), ("failed", failed)) if ix]
        line = f"verdict: {len(flagged)} of {n} actuators flagged: {', '.join(kinds)}; status {statuses}; {fits}"
    else:
        line = f"verdict: untrustworthy: the spot model does not explain the images; status {statuses}; {fits}"
    details = tuple(_detail(j, status[j], chi2[j] if j in poor else None, failed_why.get(j)) for j in flagged)
    good = not flagged and not spots_fail
    return DMVerdict(line=line, trustworthy=good, exit_code=0 if good else EXIT_FLAGGED, actuators=n,
                     flagged=len(flagged), poor_fit=poor, failed=failed, ok=ok, weak=weak, dead=dead, failed_spot_fits=n_failed,
                     spot_problems=n_problems, max_reduced_chi2=max_chi2, details=details, poor_spot_fits=poor_spots,
                     spot_model_fails=spots_fail)


def _spot_fits(chi2, threshold: float, n_problems: int) -> tuple[int, bool, str]:
    """``(poor spot fits, too many, the line's words)`` of the spot fits' reduced chi2 (module rule)."""
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
    """:func:`dm_verdict` of a :class:`~torchblur.identify.dm_plan.DMResult` (``P * F * M`` spot problems,
    their reduced chi2 judged against ``poor_fit_chi2``, the run's ``fit.poor_fit_chi2``)."""
    n_problems = int(res.plan.n_patterns) * len(res.freq_hz) * (int(np.shape(res.G)[0]) // 2)
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
    line = (f"{v.line}; {len(beyond)} actuator(s) beyond {bound:g} std of the simulated truth or with a wrong status "
            f"({listed(beyond)}): not trustworthy whatever the flags say")
    return replace(v, line=line, trustworthy=False, exit_code=EXIT_FLAGGED, beyond_truth=beyond)


def support_guard(v, info: dict | None):
    """The DM verdict ``v`` made untrustworthy (exit :data:`~torchblur.identify.verdict.EXIT_FLAGGED`)
    when the fitted geometry needs support the plan lacks (:func:`~torchblur.dm.registration.support_check`); else ``v``."""
    line = support_line(info)
    if line is None:
        return v
    return replace(v, line=f"{v.line}; the plan's support lacks {info['n_missing']} pair(s) the fitted geometry needs: not trustworthy",
                   trustworthy=False, exit_code=EXIT_FLAGGED, details=(*v.details, line))


def registration_guard(v, reg):
    """The DM verdict ``v`` made untrustworthy when the mirror model fails the one model rule
    (:func:`~torchblur.sysid.model_check.model_fails`) on the static columns it was registered to:
    its registration's stds and the reference ``dc_gain`` is relative to do not hold (a mirror
    whose influence functions the model's Gaussian does not describe); else ``v``."""
    if reg is None or not reg.ok or not model_fails(reg.reduced_chi2, reg.dof):
        return v
    line = (f"dm registration: the mirror model does not explain D0 (reduced chi2 {reg.reduced_chi2:.3g} over {reg.dof} dof, "
            f"limit {model_chi2_limit(reg.dof):.3g}): the registration's stds and dc_gain's reference do not hold")
    return replace(v, line=f"{v.line}; the mirror model does not explain D0 (registration reduced chi2 {reg.reduced_chi2:.3g}): "
                           f"not trustworthy", trustworthy=False, exit_code=EXIT_FLAGGED, details=(*v.details, line))


def ladder_guard(v, n_out: int):
    """The DM verdict ``v`` saying how many spot fits' motion left the ladder's levels
    (``dm_plan.spot_model`` ladder: their responses extrapolate the held images), untrustworthy
    where more than :data:`POOR_SPOT_FRACTION` of the spot fits did; ``v`` where none did."""
    if not n_out:
        return v
    many = n_out > POOR_SPOT_FRACTION * max(v.spot_problems, 1)
    line = f"{v.line}; {n_out} spot fits' motion left the ladder's levels (extrapolated; raise dm_plan.ladder_reach)"
    return replace(v, line=line + (": not trustworthy" if many else ""), trustworthy=v.trustworthy and not many,
                   exit_code=EXIT_FLAGGED if many else v.exit_code)


def final_verdict(res, poor_fit_chi2: float):
    """A DM run's verdict with every guard: :func:`run_verdict`, then :func:`truth_guard`,
    :func:`support_guard`, :func:`registration_guard` and :func:`ladder_guard` (one place for the
    run, a re-fit and an outside recording)."""
    v = truth_guard(run_verdict(res, poor_fit_chi2=poor_fit_chi2), res)
    return ladder_guard(registration_guard(support_guard(v, res.support_check), res.registration), getattr(res, "n_out_of_ladder", 0))
