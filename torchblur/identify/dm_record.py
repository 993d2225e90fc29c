"""A DM run recorded as it goes, resumed after a crash and re-fitted offline, in the one-spot
run's experiment directory (:class:`~torchblur.hardware.recording.Experiment`, ``OUT/experiment/``;
no second format): the calibration groups, one group ``dm_sweep/NNN`` per swept frequency
(:func:`sweep_key`, kind :data:`SWEEP_KIND`), the spot model's static holds ``dm_ladder/*`` and
the plan in ``experiment.json`` (:data:`PLAN_KEY`, stored before the first sweep group). What each
group holds, what a resume reuses and what a re-fit may change: docs/deformable_mirrors.md,
"Recording, resume and re-fit".
"""
from __future__ import annotations

import hashlib
import math
import os
import numpy as np

from torchblur.dm.plans import Plan, seen_by
from torchblur.errors import ConfigError
from torchblur.files import read_bounded
from torchblur.hardware.errors import RecordingError
from torchblur.identify.record import LOGGER
from torchblur.rig.base import within_drive

__all__ = ["PLAN_KEY", "SWEEP_KIND", "TABLE_KEY", "check_recorded_commands", "plan_document", "plan_from_document", "plan_support",
           "recorded_labels", "recorded_on_simulation", "recorded_plan", "resume_seed", "same_table", "simulated_frames", "sweep_key",
           "table_digest"]

PLAN_KEY = "dm_plan"  # experiment.json: the plan of a DM run
SWEEP_KIND = "dm_sweep"  # the kind of a swept frequency's group
_PLAN_KINDS = ("one_at_a_time", "sparse", "hadamard")


def sweep_key(k: int) -> str:
    """The group of the k-th swept frequency: ``dm_sweep/NNN``."""
    return f"dm_sweep/{int(k):03d}"


# ---------------------------------------------------------------------- the plan


def plan_document(plan: Plan, n_repeats: int, threshold: float) -> dict:
    """The plan as ``experiment.json`` holds it: ``patterns`` ``[P, N]``, ``support`` 2M strings of N characters 0/1."""
    return {"kind": plan.kind, "support_threshold": float(threshold), "n_repeats": int(n_repeats),
            "patterns": plan.patterns.tolist(), "support": ["".join("1" if v else "0" for v in row) for row in plan.support]}


def plan_from_document(doc, G: np.ndarray, where: str) -> tuple[Plan, int, float]:
    """``(plan, n_repeats, support_threshold)`` of a recorded plan document (untrusted: every
    field checked against the geometry ``G`` ``[2M, N]``).

    Raises:
        RecordingError: naming ``where`` and the field.
    """
    S, N = G.shape
    try:
        if not isinstance(doc, dict) or doc.get("kind") not in _PLAN_KINDS:
            raise ValueError(f"kind: expected one of {_PLAN_KINDS}")
        R, t = doc.get("n_repeats"), doc.get("support_threshold")
        if isinstance(R, bool) or not isinstance(R, int) or R < 1:
            raise ValueError(f"n_repeats: expected an integer >= 1, got {R!r:.40}")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 <= t <= 1:
            raise ValueError(f"support_threshold: expected a number in [0, 1], got {t!r:.40}")
        rows = doc.get("patterns")
        if not isinstance(rows, list) or not rows or not all(isinstance(r, list) and len(r) == N for r in rows):
            raise ValueError(f"patterns: expected [P, N={N}] numbers")
        patterns = np.array(rows, dtype=np.float64) if all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                            for r in rows for v in r) else None
        if patterns is None or not np.isfinite(patterns).all():
            raise ValueError("patterns: expected finite numbers")
        sup = doc.get("support")
        if not isinstance(sup, list) or len(sup) != S or not all(isinstance(r, str) and len(r) == N and set(r) <= {"0", "1"}
                                                                 for r in sup):
            raise ValueError(f"support: expected {S} strings of {N} characters 0/1")
    except ValueError as exc:
        raise RecordingError(f"{where}: {PLAN_KEY}.{exc} (the recording's plan does not fit this mirror)") from None
    support = np.array([[c == "1" for c in r] for r in sup], dtype=bool)
    return Plan(doc["kind"], patterns, support), R, float(t)


def plan_support(kind: str, G: np.ndarray, threshold: float) -> np.ndarray:
    """``[2M, N]`` bool, the unknowns a plan of ``kind`` measures at ``threshold``: the seen pairs
    for a sparse plan (:func:`~torchblur.dm.plans.seen_by`, both slope rows), else all."""
    if kind != "sparse":
        return np.ones(np.shape(G), dtype=bool)
    seen = seen_by(G, threshold)
    return np.concatenate([seen, seen], 0)


def recorded_plan(exp, plan: Plan, n_repeats: int, G: np.ndarray, threshold: float) -> tuple[Plan, int]:
    """The plan a run uses: ``plan`` without a recording; with one, the recorded plan (a resume
    or a re-fit; a re-fit at another ``threshold`` takes the support of the recorded patterns at
    that threshold, :func:`plan_support`); a new recording stores ``plan`` now.

    Raises:
        RecordingError: a read-only recording (a re-fit) without a plan.
    """
    if exp is None:
        return plan, n_repeats
    doc = exp.meta.get(PLAN_KEY)
    if doc is None:
        if not exp.writable:
            raise RecordingError(f"{exp.path}: holds no {PLAN_KEY} (the run stopped before its plan was chosen); resume it first")
        exp.set_meta(PLAN_KEY, plan_document(plan, n_repeats, threshold))
        return plan, n_repeats
    recorded, R, t = plan_from_document(doc, G, str(exp.path / "experiment.json"))
    if t != threshold and not exp.writable:
        recorded = Plan(recorded.kind, recorded.patterns, plan_support(recorded.kind, G, threshold))
        LOGGER.info(f"dm plan: the recorded {recorded.kind} patterns with the support at dm_plan.support_threshold={threshold:g} "
                    f"(recorded at {t:g}): {int(recorded.support.sum())} unknowns")
    if (recorded.kind, recorded.n_patterns, R) != (plan.kind, plan.n_patterns, n_repeats):
        LOGGER.info(f"dm plan: the recording's ({recorded.kind}, {recorded.n_patterns} patterns x {R} repeats) is used, not the "
                    f"config's choice now ({plan.kind}, {plan.n_patterns} x {n_repeats})")
    return recorded, R


# ---------------------------------------------------------------------- the sweep groups


def recorded_labels(exp, key: str) -> dict | None:
    """The first manifest line of group ``key`` (its labels: ``amplitude``, ``power``,
    ``trigger_delay_s``, ...), or None when the recording does not hold it (or there is none)."""
    if exp is None or not exp.has(key):
        return None
    line = exp.groups[key][0]
    for k in ("amplitude", "trigger_delay_s"):
        v = line.get(k)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise RecordingError(f"{key}: {k}: expected a finite number, got {v!r:.40}")
    if line.get("kind") != SWEEP_KIND:
        raise RecordingError(f"{key}: a {line.get('kind')!r} group, expected {SWEEP_KIND!r}")
    return line


def check_recorded_commands(exp, limit: float) -> None:
    """Refuse to resume a recording whose recorded DM commands exceed ``limit`` (input units):
    every ``pattern_sine`` call's ``amplitude * max |pattern|``.

    Raises:
        RecordingError: naming the first group beyond it.
    """
    if exp is None or not math.isfinite(limit):
        return
    for ln in exp.lines:
        if ln.get("method") != "pattern_sine" or ln.get("index") != 0:
            continue
        a = ln["args"]
        peak = abs(float(a.get("amplitude", math.nan))) * max(abs(float(v)) for v in a["pattern"])
        if not within_drive(peak, limit):
            raise RecordingError(f"{ln['group']}: recorded with a command of peak {peak:.6g} input units, beyond dm.input_limit "
                                 f"{limit:.6g}; refused")


# ---------------------------------------------------------------------- sessions


TABLE_KEY = "dm_actuator_table_sha256"  # a session's note of the simulated mirror's actuator table


def table_digest(cfg, base_dir: str | None = None) -> str | None:
    """The SHA-256 of the file ``dm.actuator_table`` names (relative to ``base_dir`` as
    :meth:`~torchblur.dm.mirror.DeformableMirror.from_config` reads it), or None without one:
    the recorded config holds only the path, and the simulated mirror is built from the file."""
    path = cfg.dm.actuator_table
    if not path:
        return None
    if base_dir is not None and not os.path.isabs(path):
        path = os.path.join(base_dir, path)
    return hashlib.sha256(read_bounded(path, 1 << 20, f"dm.actuator_table: {path}", error=ConfigError)).hexdigest()


def same_table(exp, table_sha256: str | None) -> bool:
    """Every session of the recording ``exp`` simulated the mirror from the same actuator table
    (digest ``table_sha256``, :func:`table_digest`)."""
    return all((s.get("rig") or {}).get(TABLE_KEY) == table_sha256 for s in exp.meta.get("sessions") or [] if isinstance(s, dict))


def recorded_on_simulation(exp) -> bool:
    """Every session of the recording ``exp`` ran on the simulated DM rig (so the config's
    simulated mirror is the truth of its frames)."""
    sessions = exp.meta.get("sessions") or []
    return bool(sessions) and all(isinstance(s, dict) and str((s.get("rig") or {}).get("rig", "")).startswith("SimulatedDMRig(")
                                  for s in sessions)


def simulated_frames(live_is_simulated: bool, exp) -> bool:
    """Whether every frame of a run comes from the config's simulated DM rig (its truth is then
    the config's simulated mirror): without a recording, the live rig is simulated; a re-fit
    (read-only ``exp``), every recorded session was; a new or resumed recording, both (the
    sessions before this one)."""
    if exp is None:
        return live_is_simulated
    if not exp.writable:
        return recorded_on_simulation(exp)
    return live_is_simulated and (not exp.meta.get("sessions") or recorded_on_simulation(exp))


def resume_seed(seed: int, session: int) -> int:
    """The simulated rig's seed in session ``session`` of a run of ``seed``: ``seed`` itself in
    the first; a resumed session draws a stream of its own (from ``(seed, session)``), so its
    frames do not repeat the noise the first session's calibration frames drew."""
    if session == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(session)]).generate_state(1)[0])
