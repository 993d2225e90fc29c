"""A single-exposure sweep: each point's phase branch (measured or alias) chosen with a model.

With one exposure window per point (Proposition 3) every phase has an alias that renders the
same image. :func:`model_branches` decides the points the continuity rule left undecided with one
model of the decided points and the undecided points' magnitudes (which have no alias);
:func:`resolve_alias_with_model` fits a transfer function to every branch choice it visits and
keeps the one with the smallest chi2 (a start for :func:`~torchblur.sysid.direct.fit_direct`).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from torchblur.design.windows import CONTINUITY_Z
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.model_check import model_fails
from torchblur.sysid.tf_fit import fit_transfer_function

__all__ = ["AliasResolution", "MODEL_BRANCH_Z_OUT", "model_branches", "resolve_alias_with_model"]

#: :func:`model_branches` decides a point only where the other branch lies at least this many
#: stds from the model's phase (the kept one within ``CONTINUITY_Z``)
MODEL_BRANCH_Z_OUT = 10.0


def model_branches(frf, other_phase, undecided, *, max_order: int = 6, z_in: float = CONTINUITY_Z,
                   z_out: float = MODEL_BRANCH_Z_OUT, max_rounds: int = 10):
    """Decide, with a model, the phase branch of the points a single-exposure sweep's continuity
    rule left undecided (docs/reliability.md, "One exposure per point", step 5).

    The rule. A transfer function (order by BIC up to 4 poles, then up to ``max_order`` if no
    model qualifies; :func:`~torchblur.sysid.tf_fit.fit_transfer_function`) is fitted to the decided points and to the undecided points' magnitudes alone
    (``magnitude_only``: |H| has no alias, so a resonance past the branches' crossing still pins
    the model). It is used only where it passes the model rule
    (:func:`~torchblur.sysid.model_check.model_fails`), its parameters' covariance is known, and the
    decided points' real observations alone outnumber its parameters; else the next two orders by
    BIC are tried, then nothing is decided (the refits keep the order found first). An undecided point takes the branch whose phase lies
    within ``z_in`` stds of the model's (the std: the point's and the model's prediction's,
    :meth:`~torchblur.sysid.tf_fit.TransferFunctionFit.phase_std`, in quadrature) when the other
    lies beyond ``z_out``; the model is refitted with the points so decided and the step repeated
    until nothing changes.

    Args:
        frf: SISO FrequencyResponse, each point on its current branch (its covariance weights the fit).
        other_phase: ``[F]`` the other branch of each point (rad).
        undecided: bool ``[F]``: the points whose branch is not decided (the others are fitted
            with their phase; invalid points are skipped).
        max_order, z_in, z_out, max_rounds: the model's largest order (the config's default), the
            rule's constants, the refits at most.

    Returns:
        ``(frf, undecided)``: the response with the branches chosen (where the other is taken
        the magnitude-phase covariance changes sign) and bool ``[F]``, the points still undecided.
    """
    if not isinstance(frf, FrequencyResponse) or not frf.is_siso:
        raise InputTypeError(f"frf: expected a SISO FrequencyResponse, got {type(frf).__name__}")
    F = frf.omega.size
    other, und = np.array(other_phase, dtype=np.float64), np.array(undecided, dtype=bool)
    if other.shape != (F,) or und.shape != (F,):
        raise ShapeError(f"other_phase, undecided: expected shape [F] = [{F}], got {other.shape}, {und.shape}")
    und &= frf.valid[0, 0] & np.isfinite(other)
    order = None
    for _ in range(max_rounds):
        model = _branch_model(frf, und, max_order, order) if und.any() else None
        if model is None:
            break
        order = (model.n_poles, model.n_zeros)
        h = frf.response[0, 0]
        pred = np.angle(model.frequency_response(frf.omega))
        sd = np.sqrt(frf.phase_std[0, 0] ** 2 + model.phase_std(frf.omega) ** 2)
        z = np.abs(np.angle(np.exp(1j * (np.stack([np.angle(h), other]) - pred)))) / sd  # [2, F]
        near = z[1] < z[0]
        sure = und & (z.min(0) <= z_in) & (z.max(0) >= z_out)
        if not sure.any():
            break
        flip = sure & near
        frf = frf.with_branch(flip, other)
        other = np.where(flip, np.angle(h), other)
        und &= ~sure
    return frf, und


def _branch_model(frf, undecided: np.ndarray, max_order: int, order=None):
    """The model :func:`model_branches` decides with, of the order ``(n_poles, n_zeros)`` or by
    BIC (None: none qualifies)."""
    n_decided = int((frf.valid[0, 0] & ~undecided).sum())
    if 2 * n_decided < 4:  # fewer real observations with a phase than the smallest model with a delay has parameters
        return None
    scans = [dict(n_poles=order[0], n_zeros=order[1])] if order else [dict(max_order=k) for k in sorted({min(4, max_order), max_order})]
    for kw in scans:  # orders to 4 first (a scan to 6 costs 3x): the larger scan only where none qualifies
        try:
            best = fit_transfer_function(frf, magnitude_only=undecided, **kw)
        except (ValueError, np.linalg.LinAlgError):
            continue
        for row in sorted(best.candidates, key=lambda r: r["bic"])[:3]:
            try:
                m = best if row["chosen"] else fit_transfer_function(frf, magnitude_only=undecided, n_poles=row["n_poles"],
                                                                     n_zeros=row["n_zeros"])
            except (ValueError, np.linalg.LinAlgError):
                continue
            if (not model_fails(m.reduced_chi2, m.dof) and 2 * n_decided > len(m.param_names)
                    and np.isfinite(m.phase_std(frf.omega[undecided])).all()):
                return m
    return None


class AliasResolution(NamedTuple):
    """Result of :func:`resolve_alias_with_model`."""

    frf: Any
    model: Any
    flipped: np.ndarray
    candidates: list


def resolve_alias_with_model(frf, alias_phase, *, n_poles: int | None = None, n_zeros: int | None = None,
                             delay_s: float | None = None, max_order: int = 8, max_rounds: int = 20,
                             n_candidates: int = 4) -> AliasResolution:
    """Pick each point's phase branch (measured or alias) with a model: a single-exposure start.

    With one exposure window per point (Proposition 3) every phase has an alias that renders
    the same image, so a per-point fit picks its branch by chance under noise. A model over
    all points tells them apart. From each of three initial choices (as measured; continuity
    from the lowest frequency, each point taking the branch nearest the previous point's
    phase; all aliases) the model is fitted, every point then takes the branch nearer the
    model (in units of its std), and so on until no point changes; then single points and
    pairs of neighbours of the best choice are flipped and the descent repeated while that
    lowers the chi2. The choice with the smallest chi2 wins.

    Args:
        frf: SISO :class:`~torchblur.sysid.frequency_response.FrequencyResponse` of the per-point fits
            (its covariance weights the fits).
        alias_phase: [F] the other branch of each point (``SinusoidFit.alias_phase``), rad.
        n_poles, n_zeros, delay_s, max_order: passed to
            :func:`~torchblur.sysid.tf_fit.fit_transfer_function` (fixed orders are much faster).
        max_rounds: rounds of re-assignment at most per initial choice.
        n_candidates: how many of the best branch choices' models to return as ``candidates``.

    Returns:
        :class:`AliasResolution` ``(frf, model, flipped, candidates)``: the response with the
        chosen branches (an alias point's magnitude-phase correlation changes sign: the alias
        moves opposite to the phase), the TransferFunctionFit on it, bool [F] where the alias
        was taken, and the models of the best branch choices (lowest chi2 first; pass them
        all as ``start`` to :func:`~torchblur.sysid.direct.fit_direct`, which keeps the one that fits the images best).
    """
    if not isinstance(frf, FrequencyResponse) or not frf.is_siso:
        raise InputTypeError(f"frf: expected a SISO FrequencyResponse, got {type(frf).__name__}")
    alias = np.asarray(alias_phase.detach().cpu().numpy() if isinstance(alias_phase, torch.Tensor) else alias_phase, dtype=np.float64)
    F = frf.omega.size
    if alias.shape != (F,):
        raise ShapeError(f"alias_phase: expected shape [F] = [{F}], got {alias.shape}")
    search = _BranchSearch(frf, alias, dict(n_poles=n_poles, n_zeros=n_zeros, delay_s=delay_s, max_order=max_order), max_rounds)
    for choice in _initial_choices(search.branches, search.ok):
        search.descend(choice)
    if not search.tried:
        raise ParameterError("frf: no model could be fitted to any branch choice")
    search.flip_neighbours()
    tried = sorted(search.tried, key=lambda t: t[0])
    _, choice, model = tried[0]
    return AliasResolution(search.frf_of(choice), model, choice, [t[2] for t in tried[:n_candidates]])


def _initial_choices(branches: np.ndarray, ok: np.ndarray) -> list[np.ndarray]:
    """Three branch choices bool ``[F]`` (True: the alias) to descend from: as measured;
    continuity from the lowest frequency (each point the branch nearest the previous point's
    phase); every alias."""
    F = branches.shape[1]
    cont = np.zeros(F, dtype=bool)
    prev = None
    for k in range(F):
        if not ok[k]:
            continue
        ph = np.angle(branches[:, k])
        if prev is not None:
            d = np.abs(np.angle(np.exp(1j * (ph - prev))))
            cont[k] = bool(d[1] < d[0])
        prev = ph[int(cont[k])]
    return [np.zeros(F, dtype=bool), cont, np.ones(F, dtype=bool) & ok]


class _BranchSearch:
    """The branch choices visited, each with its model: ``tried`` lists ``(chi2, choice, model)``.

    ``branches [2, F]`` complex: the measured response and its alias (same magnitude, the alias
    phase); an alias point's covariance has its magnitude-phase correlation negated.
    """

    def __init__(self, frf, alias: np.ndarray, fit_kw: dict, max_rounds: int):
        self.frf, self.alias, self.fit_kw, self.max_rounds = frf, alias, fit_kw, max_rounds
        h = frf.response[0, 0]
        self.ok = np.isfinite(h) & np.isfinite(alias)
        mag = np.abs(h)
        self.branches = np.stack([h, mag * np.exp(1j * alias)])  # [2, F]
        cov = frf.cov[0, 0]
        sig = np.sqrt(np.nan_to_num(cov[:, 0, 0]) + mag**2 * np.nan_to_num(cov[:, 1, 1]))
        self.sig = np.where(sig > 0, sig, np.maximum(mag, 1e-300))  # a point's std (distance unit)
        self.tried: list = []
        self.seen: set = set()

    def frf_of(self, choice: np.ndarray):
        """The response with the branches of ``choice`` (bool [F], True: the alias;
        :meth:`~torchblur.sysid.frequency_response.FrequencyResponse.with_branch`)."""
        return self.frf.with_branch(choice, self.alias)

    def descend(self, choice: np.ndarray) -> None:
        """Fit, re-assign every point to the nearer branch, repeat until nothing changes."""
        for _ in range(self.max_rounds):
            key = choice.tobytes()
            if key in self.seen:
                return
            self.seen.add(key)
            try:
                model = fit_transfer_function(self.frf_of(choice), **self.fit_kw)
            except (ValueError, np.linalg.LinAlgError):
                return
            self.tried.append((model.chi2, choice.copy(), model))
            pred = model.frequency_response(self.frf.omega)
            dist = np.abs(self.branches - pred[None]) / self.sig[None]
            new = (dist[1] < dist[0]) & self.ok
            if np.array_equal(new, choice):
                return
            choice = new

    def flip_neighbours(self) -> None:
        """Local search: flip one point, or two neighbours, of the best choice, and descend
        again, until no such move finds a smaller chi2 (a wrong branch at a few points can trap
        the re-assignment: the model bends toward them)."""
        F = self.ok.size
        for _ in range(self.max_rounds):
            best_chi2 = min(t[0] for t in self.tried)
            base = min(self.tried, key=lambda t: t[0])[1]
            moves = [[k] for k in range(F)] + [[k, k + 1] for k in range(F - 1)]
            for mv in moves:
                c = base.copy()
                c[mv] = ~c[mv]
                self.descend(c & self.ok)
            if min(t[0] for t in self.tried) >= best_chi2:
                break
