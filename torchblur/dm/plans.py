"""Excitation plans for a many-actuator mirror: which actuators move together in each pattern.

A plan is ``patterns [P, N]`` (in pattern p actuator j is commanded ``amplitude * patterns[p, j]
* sin(omega t)``) and ``support [2M, N]`` bool (the unknowns ``D[s, j]`` it measures; the others
are taken as 0): one at a time (``I_N``), sparse (0/1 rows from a greedy colouring, so that no
subaperture *sees* two active actuators, seen at ``threshold`` of the largest spot displacement)
and Hadamard (``H[:, :N]``, Sylvester, ``scipy.linalg.hadamard``). :func:`choose_plan` takes the
one with the smallest :func:`plan_cost`, ``P max_{s,j} [(P_s^T P_s)^-1]_jj / a^2``: the frames per
frequency and exposure for a given worst std of ``D``. The rule and its figures:
docs/deformable_mirrors.md, "The plans".
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchblur.errors import ParameterError, ShapeError, check_choice, check_int, check_real_scalar

__all__ = ["Plan", "PLAN_KINDS", "SPARSE_MARGIN", "choose_plan", "driven_spots", "hadamard_plan", "one_at_a_time_plan", "plan_cost", "seen_by",
           "sparse_plan", "static_motion_px"]

PLAN_KINDS = ("auto", "one_at_a_time", "sparse", "hadamard")

#: the sparse plan that ``dm_plan.kind=auto`` takes for the ladder's spots (:func:`~torchblur.config.budget.dm_ladder_plan`)
#: sees at this fraction of ``dm_plan.support_threshold``: its colouring and support then hold every pair a mirror misregistered
#: by 0.25 pitch, 1.5 deg and 3 % needs (HCIPy's quick run: 36 pairs missing at 1 x, 0 at 0.1 x; 20 patterns, not 18)
SPARSE_MARGIN = 0.1


@dataclass(frozen=True, eq=False)
class Plan:
    """An excitation plan (module docstring).

    Attributes:
        kind: ``"one_at_a_time"``, ``"sparse"`` or ``"hadamard"``.
        patterns: ``[P, N]`` float, ``patterns[p, j]`` = actuator j's command in pattern p per
            unit amplitude.
        support: ``[2M, N]`` bool, ``support[s, j]``: the plan measures ``D[s, j]``.
    """

    kind: str
    patterns: np.ndarray
    support: np.ndarray

    def __post_init__(self):
        p = np.array(self.patterns, dtype=np.float64)
        s = np.array(self.support, dtype=bool)
        if p.ndim != 2 or s.ndim != 2 or s.shape[1] != p.shape[1]:
            raise ShapeError(f"patterns, support: expected [P, N] and [2M, N], got {p.shape} and {s.shape}")
        p.setflags(write=False)
        s.setflags(write=False)
        object.__setattr__(self, "patterns", p)
        object.__setattr__(self, "support", s)

    @property
    def n_patterns(self) -> int:
        """P."""
        return int(self.patterns.shape[0])

    @property
    def n_actuators(self) -> int:
        """N."""
        return int(self.patterns.shape[1])

    def n_frames(self, n_freq: int, n_exposures: int, n_repeats: int) -> int:
        """Frames the plan takes: patterns x frequencies x exposures x repeats."""
        return self.n_patterns * check_int(n_freq, "n_freq", low=1) * check_int(n_exposures, "n_exposures", low=1) \
            * check_int(n_repeats, "n_repeats", low=1)

    def __repr__(self) -> str:
        return f"Plan({self.kind}, P={self.n_patterns}, N={self.n_actuators}, support {int(self.support.sum())}/{self.support.size})"


def _check_G(G) -> np.ndarray:
    G = np.asarray(G, dtype=np.float64)
    if G.ndim != 2 or G.shape[0] % 2 or not np.isfinite(G).all():
        raise ShapeError(f"G: expected a finite geometry matrix [2M, N], got shape {G.shape}")
    return G


def seen_by(G, threshold: float = 0.01) -> np.ndarray:
    """``[M, N]`` bool: subaperture m sees actuator j (module docstring: the rule)."""
    G = _check_G(G)
    t = check_real_scalar(threshold, "threshold", nonnegative=True)
    M = G.shape[0] // 2
    length = np.hypot(G[:M], G[M:])
    return length > t * length.max()


def one_at_a_time_plan(G) -> Plan:
    """``patterns = I_N``, support all."""
    G = _check_G(G)
    N = G.shape[1]
    return Plan("one_at_a_time", np.eye(N), np.ones(G.shape, dtype=bool))


def hadamard_plan(G) -> Plan:
    """The first N columns of the Sylvester Hadamard matrix of the next power of two >= N; support all."""
    from scipy.linalg import hadamard

    G = _check_G(G)
    N = G.shape[1]
    order = 1 << max(0, (N - 1).bit_length())
    return Plan("hadamard", hadamard(order).astype(np.float64)[:, :N], np.ones(G.shape, dtype=bool))


def sparse_plan(G, threshold: float = 0.01) -> Plan:
    """Greedy colouring of the actuators' conflict graph: one 0/1 pattern per colour."""
    seen = seen_by(G, threshold)
    N = seen.shape[1]
    conflict = (seen.T.astype(np.int64) @ seen.astype(np.int64)) > 0
    np.fill_diagonal(conflict, False)
    colour = np.full(N, -1)
    for j in sorted(range(N), key=lambda j: (-int(conflict[j].sum()), j)):
        used = set(colour[conflict[j]].tolist())
        colour[j] = next(c for c in range(N) if c not in used)
    patterns = (colour[None, :] == np.arange(colour.max() + 1)[:, None]).astype(np.float64)
    support = np.concatenate([seen, seen], 0)
    return Plan("sparse", patterns, support)


def driven_spots(plan: Plan) -> np.ndarray:
    """``[P, M]`` bool: pattern ``p`` moves an actuator that spot ``m`` sees (in the support of its
    x or its y slope). The other (pattern, spot) problems say nothing of ``D``: the demultiplexing
    leaves out a pattern that drives none of a row's support (:func:`~torchblur.dm.demux.demultiplex`),
    so a sweep does not fit them. Every pair on a Hadamard plan; on a sparse or one-at-a-time plan
    the pairs whose spot sees one of the pattern's actuators."""
    S, N = plan.support.shape
    seen = plan.support[:S // 2] | plan.support[S // 2:]  # [M, N]
    return ((plan.patterns != 0).astype(np.int64) @ seen.T.astype(np.int64)) > 0


def static_motion_px(plan: Plan, G) -> float:
    """The largest static spot motion (px) of any pattern per unit amplitude: ``max_p max_m
    hypot(x, y)`` of ``G @ patterns[p]``."""
    G = _check_G(G)
    M = G.shape[0] // 2
    s = G @ plan.patterns.T  # [2M, P]
    return float(np.hypot(s[:M], s[M:]).max())


def plan_cost(plan: Plan, G) -> float:
    """Frames per frequency and exposure for a given worst std of D (module docstring), in units
    of ``sigma_1^2 / std^2`` with the amplitude set by ``target_px = 1``."""
    G = _check_G(G)
    P = plan.patterns
    worst = 0.0
    for s in np.unique(plan.support, axis=0):
        cols = np.flatnonzero(s)
        if cols.size == 0:
            continue
        Ps = P[:, cols]
        gram = Ps.T @ Ps
        if np.linalg.matrix_rank(gram) < cols.size:
            return float("inf")
        worst = max(worst, float(np.diag(np.linalg.inv(gram)).max()))
    a = 1.0 / static_motion_px(plan, G)
    return plan.n_patterns * worst / (a * a)


_BUILDERS = {"one_at_a_time": lambda G, t: one_at_a_time_plan(G), "sparse": sparse_plan, "hadamard": lambda G, t: hadamard_plan(G)}


def choose_plan(kind: str, G, *, budget_frames: int | None, n_freq: int, n_exposures: int, threshold: float = 0.01,
                n_repeats: int | None = None) -> tuple[Plan, int, dict]:
    """The plan and its repeats per exposure.

    ``kind = "auto"`` takes the plan of the smallest :func:`plan_cost` (the fewest frames at equal
    accuracy); any other kind is that plan. The repeats are ``n_repeats`` when given, else the
    most that fit ``budget_frames`` (at least 1).

    Returns:
        ``(plan, n_repeats, info)``; ``info`` holds every plan's cost, pattern count and frames
        at the chosen repeats, and the ratio of the chosen plan's cost to one-at-a-time's.

    Raises:
        ParameterError: naming ``dm_plan.budget_frames`` when even one repeat of the chosen plan
            needs more frames than the budget.
    """
    check_choice(kind, "dm_plan.kind", PLAN_KINDS)
    G = _check_G(G)
    plans = {k: b(G, threshold) for k, b in _BUILDERS.items()}
    costs = {k: plan_cost(p, G) for k, p in plans.items()}
    chosen = min(costs, key=costs.get) if kind == "auto" else kind
    plan = plans[chosen]
    per_repeat = plan.n_frames(n_freq, n_exposures, 1)
    if n_repeats is None:
        if budget_frames is None:
            raise ParameterError("dm_plan.budget_frames: expected a frame budget when n_repeats is not given")
        n_repeats = check_int(budget_frames, "dm_plan.budget_frames", low=1) // per_repeat
        if n_repeats < 1:
            raise ParameterError(f"dm_plan.budget_frames: the {chosen} plan needs {per_repeat} frames for one repeat, "
                                 f"the budget is {budget_frames}")
    n_repeats = check_int(n_repeats, "n_repeats", low=1)
    info = {"costs": costs, "patterns": {k: p.n_patterns for k, p in plans.items()},
            "frames": {k: p.n_frames(n_freq, n_exposures, n_repeats) for k, p in plans.items()},
            "cost_ratio_to_one_at_a_time": costs[chosen] / costs["one_at_a_time"]}
    return plan, n_repeats, info
