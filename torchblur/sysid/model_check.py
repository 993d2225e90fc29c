"""One rule that judges every model a run reports, by its reduced chi2 and degrees of freedom.

A model passes when ``reduced_chi2 <= max(MODEL_CHI2_FLOOR, 1 + 4 sqrt(2 / dof))`` (a chi2 test
at about 4 sigma, never tighter than 2: the data's stds are themselves estimates) and ``dof >=
MIN_MODEL_DOF``; a failed model's stds are multiplied by ``sqrt(reduced_chi2)`` (:func:`inflate`,
a scale, not a bound); :func:`disagreements` names the parameters on which two models of one
plant differ beyond :data:`DISAGREE_SIGMA` combined stds (conservative: both are fitted to the
same images). Which models, and why DM runs keep their own test: docs/reliability.md, "Every
model judged by one rule, with its uncertainty".
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from torchblur.losses import chi2_limit

__all__ = ["DISAGREE_SIGMA", "MIN_MODEL_DOF", "MODEL_CHI2_FLOOR", "ModelJudgement", "disagreements", "inflate", "judge_fit",
           "judge_model", "model_chi2_limit", "model_fails"]

#: the reduced chi2 limit is never below this (the data's stds are themselves estimates)
MODEL_CHI2_FLOOR = 2.0
#: fewer degrees of freedom than this: the chi2 test cannot tell a wrong model ("too few points")
MIN_MODEL_DOF = 3
#: two models disagree on a parameter beyond this many combined stds
DISAGREE_SIGMA = 3.0


def model_chi2_limit(dof) -> float:
    """The largest reduced chi2 a model with ``dof`` degrees of freedom may have:
    ``max(MODEL_CHI2_FLOOR, 1 + 4 sqrt(2 / dof))``."""
    return max(MODEL_CHI2_FLOOR, chi2_limit(dof, 4.0))


def model_fails(reduced_chi2, dof) -> bool:
    """Whether a model fails the rule (too few dof, or reduced chi2 above the limit); NaN chi2 fails."""
    dof = int(dof)
    return dof < MIN_MODEL_DOF or not float(reduced_chi2) <= model_chi2_limit(dof)


@dataclasses.dataclass(frozen=True)
class ModelJudgement:
    """The rule's judgement of one model.

    Attributes:
        name: which model (``"two-step"``, ``"two-step y from x"``, ``"direct"``, ``"modal"``).
        passed: the model passes the rule.
        reduced_chi2, dof: what was judged (None where unknown).
        limit: the reduced chi2 limit for ``dof`` (None where not judged).
        reason: why it failed (``""`` when it passed).
        std_factor: what its stds are multiplied by in the files (``sqrt(reduced_chi2)`` for a
            model above the limit, else 1).
    """

    name: str
    passed: bool
    reduced_chi2: float | None
    dof: int | None
    limit: float | None
    reason: str = ""
    std_factor: float = 1.0

    def to_dict(self) -> dict:
        """A strict-JSON dict, with the rule named."""
        d = dataclasses.asdict(self)
        d["rule"] = (f"reduced_chi2 <= max({MODEL_CHI2_FLOOR:g}, 1 + 4 sqrt(2 / dof)) and dof >= {MIN_MODEL_DOF} "
                     "(torchblur.sysid.model_check)")
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def judge_model(name: str, reduced_chi2, dof, noise_estimated: bool = False) -> ModelJudgement:
    """The rule applied to one model's ``reduced_chi2`` over ``dof`` degrees of freedom."""
    try:
        chi2, dof = float(reduced_chi2), int(dof)
    except (TypeError, ValueError):
        return ModelJudgement(name, False, None, None, None, "no fit statistics")
    if noise_estimated:
        return ModelJudgement(name, False, chi2, dof, None, "not judged: its noise scale was estimated from its own residuals")
    limit = model_chi2_limit(dof)
    if dof < MIN_MODEL_DOF:
        return ModelJudgement(name, False, chi2, dof, limit, f"too few points: {dof} degrees of freedom, fewer than {MIN_MODEL_DOF}")
    if not chi2 <= limit:
        factor = math.sqrt(chi2) if math.isfinite(chi2) else math.inf
        return ModelJudgement(name, False, chi2, dof, limit, f"reduced chi2 {chi2:.3g} over {dof} dof, above {limit:.3g}", factor)
    return ModelJudgement(name, True, chi2, dof, limit)


def judge_fit(model, name: str) -> tuple[ModelJudgement, ...]:
    """The judgements of a TransferFunctionFit (one per channel: ``"NAME OUT from IN"`` for a
    MIMO fit) or a DirectModelFit (one, ``name``); ``()`` for None."""
    if model is None:
        return ()
    if hasattr(model, "noise_estimated"):  # a DirectModelFit
        return (judge_model(name, model.reduced_chi2, model.dof, bool(model.noise_estimated)),)
    if model.is_siso:
        return (judge_model(name, model.reduced_chi2, model.dof),)
    return tuple(judge_model(f"{name} {out} from {inp}", model.reduced_chi2[o][i], model.dof[o][i])
                 for o, out in enumerate(model.output_labels) for i, inp in enumerate(model.input_labels))


def inflate(model, judgements):
    """``model`` with the covariance and stds of every failed channel multiplied by its
    ``std_factor`` squared (and once); the same object when nothing is inflated."""
    factors = [j.std_factor for j in judgements]
    if model is None or all(f == 1.0 for f in factors):
        return model
    if hasattr(model, "noise_estimated"):  # a DirectModelFit
        f = factors[0]
        return dataclasses.replace(model, covariance=model.covariance * f * f, std=model.std * f)
    if model.params is None:
        return model
    if model.is_siso:
        f = factors[0]
        return dataclasses.replace(model, covariance=np.asarray(model.covariance) * f * f, std=np.asarray(model.std) * f)
    n_i = len(model.input_labels)
    cov = [[np.asarray(c) * factors[o * n_i + i] ** 2 for i, c in enumerate(row)] for o, row in enumerate(model.covariance)]
    std = [[np.asarray(s) * factors[o * n_i + i] for i, s in enumerate(row)] for o, row in enumerate(model.std)]
    return dataclasses.replace(model, covariance=cov, std=std)


def _parameters(model) -> dict[str, tuple[float, float]]:
    """``{name: (value, std)}`` of a SISO model: its delay and each resonance's ``mode{k}_hz``
    and ``mode{k}_zeta`` (sorted by frequency)."""
    out = {}
    if hasattr(model, "noise_estimated"):  # DirectModelFit: its delay is a named parameter when fitted
        names = list(model.param_names)
        if "delay_s" in names:
            k = names.index("delay_s")
            out["delay_s"] = (float(model.params[k]), float(model.std[k]))
    elif model.delay_estimated:
        out["delay_s"] = model.parameter("delay_s")
    for k, m in enumerate(model.modal_parameters(), start=1):
        out[f"mode{k}_hz"] = (m["freq_hz"], m.get("freq_hz_std", math.nan))
        out[f"mode{k}_zeta"] = (m["zeta"], m.get("zeta_std", math.nan))
    return out


def disagreements(a, b, sigma: float = DISAGREE_SIGMA) -> list[str]:
    """The parameters (delay, each mode's frequency and damping) on which two SISO models of
    the same plant differ by more than ``sigma`` combined stds, e.g. ``["delay_s: 17.95 +-
    0.2 us vs 25.1 +- 0.3 us"]``. Modes are compared in order of frequency when both models
    have the same number; parameters without a finite std on both sides are not compared."""
    if a is None or b is None:
        return []
    pa, pb = _parameters(a), _parameters(b)
    out = []
    for name in pa:
        if name not in pb:
            continue
        (va, sa), (vb, sb) = pa[name], pb[name]
        s = math.hypot(sa, sb)
        if not (math.isfinite(s) and s > 0 and math.isfinite(va) and math.isfinite(vb)):
            continue
        if abs(va - vb) > sigma * s:
            scale, unit = (1e6, " us") if name == "delay_s" else (1.0, " Hz" if name.endswith("_hz") else "")
            out.append(f"{name}: {va * scale:.4g} +- {sa * scale:.2g}{unit} vs {vb * scale:.4g} +- {sb * scale:.2g}{unit}")
    return out
