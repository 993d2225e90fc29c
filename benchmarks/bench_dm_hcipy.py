"""Issue 23's first two "done when" items measured end to end on HCIPy Shack-Hartmann frames.

The DM route (``torchblur.identify`` with a DM config and its verdict, what ``torchblur identify`` runs) on
a user-written rig (tests/hcipy_sh_rig.py) whose frames HCIPy makes (tests/hcipy_sh.py: circular
pupil, HCIPy's DM of Gaussian influence functions, 52 actuators, 10 x 10 square lenslets with
diffraction and crosstalk, 80 valid, 16 px pitch, 160 x 160 px; each actuator's own second-order
dynamics and delay, actuator 20 dead, 33 at 0.4 gain; the motion integrated over each exposure
with Gauss-Legendre nodes; Poisson and read noise, ADU rounding), configs/identify_dm.yaml's
plan (Hadamard, 10 Hz-2 kHz, exposures 0.3 and 0.8 of the period). Two cases: the DM registered
to the lenslets, and misregistered (0.25 actuator pitch shift in x, 1.5 deg, 3 % magnification).

Printed per case: every live actuator's largest mode, damping and delay error; D0's rms error over
max |D0| against the fitted-shift truth (each spot's least-squares shift under a small static poke of
each actuator, tests/hcipy_sh.py ``shift_truth``, times the actuator's gain); rms(error/std) of
D(jw) (against ``shift_truth`` x H_j(jw), the linearised truth) and of every actuator parameter
(the DC gain's truth is the generator's gain g_j: actuator j's static surface per unit command at
its peak relative to HCIPy's own influence function, a Gaussian of peak 1 in the generator's
stroke; the same definition as ``dc_gain``, relative to the fitted influence function's peak);
the dead and weak actuators' status; the spot fits' reduced chi2 median; the verdict and its exit
code; the times. ``--quick``: 4 frequencies, one repeat (512 frames a case; the full plan is
configs/identify_dm.yaml's 16 frequencies x 2 repeats, 4096 frames).

    python benchmarks/bench_dm_hcipy.py --quick [--case aligned|misregistered|both|none] [--psf auto|kernel|gaussian] [--target-px 1.5]
                                        [--device cuda] [--jobs N]
    python benchmarks/bench_dm_hcipy.py --quick --case misregistered --record DIR   # recorded, outputs in DIR/misregistered
    python benchmarks/bench_dm_hcipy.py --load PREFIX_aligned.pkl   # a run saved with BENCH_DM_HCIPY_SAVE=PREFIX
    python benchmarks/bench_dm_hcipy.py --load PREFIX_aligned.pkl --reestimate   # its stage 4 again with this tree's code
    python benchmarks/bench_dm_hcipy.py --load A_aligned.pkl --against B_aligned.pkl   # two noise seeds (--set seed=N): no truth

``--device cuda``: the spot fits (every (pattern, frequency, spot) problem) run on that device
(the config's ``fit.device``; refused where there is none), and so does the generator's
propagation (its FFTs in torch, ``HcipySH.device``); ``--jobs N``: the frames' propagation on the CPU uses N threads (scipy.fft
workers, BLAS) and torch N threads (default 1: the 2-core machine's figures).

First the generator's checks (batched FFT vs HCIPy's own forward, the time integral's node
rule at the worst exposure, what thresholding the still frame finds).
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import hcipy_sh as hs  # noqa: E402
import hcipy_sh_rig as hr  # noqa: E402

from torchblur.identify.pipeline import identify  # noqa: E402
from torchblur.identify.verdict import final_verdict  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.config.budget import estimate_run  # noqa: E402
from torchblur.dm.plans import driven_spots  # noqa: E402

CASES = {"aligned": hs.SHOptics(),
         "misregistered": hs.SHOptics(shift=(0.25, 0.0), rotation_deg=1.5, magnification=1.03)}
DYNAMICS_SEED = 23


def _z_complex(err, cov):
    """rms of the Mahalanobis distance per complex point / sqrt(2): about 1 where the stds hold."""
    e = np.stack([err.real, err.imag], -1)[..., None]
    ok = np.isfinite(cov).all((-1, -2)) & np.isfinite(e[..., 0]).all(-1) & (np.abs(np.linalg.det(cov)) > 0)
    d2 = (np.swapaxes(e[ok], -1, -2) @ np.linalg.inv(cov[ok]) @ e[ok])[..., 0, 0]
    return float(np.sqrt(np.mean(d2) / 2)) if d2.size else math.nan


def figures(res, truth, dyn) -> dict:
    """The "done when" figures of one run against the generator's truth."""
    a = res.actuators
    live = ~dyn.dead
    out = {}
    for name, est, std, true in (("mode", a.mode_hz, a.mode_hz_std, dyn.mode_hz), ("damping", a.damping, a.damping_std, dyn.damping),
                                 ("dc_gain", a.dc_gain, a.dc_gain_std, dyn.gain)):
        rel = est[live] / true[live] - 1
        out[f"{name}_max_rel_error"] = float(np.nanmax(np.abs(rel)))
        out[f"{name}_rms_z"] = float(np.sqrt(np.nanmean(((est[live] - true[live]) / std[live]) ** 2)))
    dd = a.delay_s[live] - dyn.delay_s[live]
    out["delay_max_error_us"] = float(np.nanmax(np.abs(dd)) * 1e6)
    out["delay_rms_z"] = float(np.sqrt(np.nanmean((dd / a.delay_s_std[live]) ** 2)))
    D0 = truth["D0"]
    out["D0_rms_error_over_max"] = float(np.sqrt(np.mean((a.static_column - D0) ** 2)) / np.abs(D0).max())
    Dt = truth["shift_slopes"][:, :, None] * dyn.response(res.freq_hz)[None]  # [2M, N, F]
    out["D_rms_z"] = _z_complex(res.D[:, live] - Dt[:, live], res.D_cov[:, live])
    st = np.asarray(a.status)
    out["dead_status"] = [str(st[j]) for j in np.flatnonzero(dyn.dead)]
    weak = np.flatnonzero((dyn.gain > 0) & (dyn.gain < 0.7))
    out["weak_status"] = [str(st[j]) for j in weak]
    out["other_not_ok"] = [int(j) for j in np.flatnonzero(st != "ok") if j not in set(np.flatnonzero(dyn.dead)) | set(weak)]
    chi2 = res.spot_reduced_chi2
    out["spot_chi2_median"] = float(np.nanmedian(chi2)) if chi2 is not None else math.nan
    out["poor_fit_actuators"] = int(np.sum(a.poor_fit))
    return out


def _lit_rows() -> np.ndarray:
    """``[2M]`` bool: the slope rows of configs/identify_dm.yaml's fully lit subapertures."""
    from torchblur.config.budget import dm_sensor
    from torchblur.dm.registration import fully_lit

    return np.tile(fully_lit(dm_sensor(load_config("configs/identify_dm.yaml"))[1]), 2)


def _snr_bands(err, std, D0, rows) -> str:
    """rms(err/std) over the measured entries of ``rows``, then per band of ``|D0| / std``."""
    ok = np.isfinite(err) & np.isfinite(std) & (std > 0) & rows[:, None]
    z, snr = err[ok] / std[ok], np.abs(D0[ok]) / std[ok]
    bands = [f"{lo:g}-{hi:g} stds {np.sqrt(np.mean(z[(snr >= lo) & (snr < hi)] ** 2)):.2f} ({int(((snr >= lo) & (snr < hi)).sum())})"
             for lo, hi in ((0, 30), (30, 300), (300, np.inf)) if ((snr >= lo) & (snr < hi)).any()]
    return f"{np.sqrt(np.mean(z ** 2)):.2f} over {int(ok.sum())} entries; by |D0|/std: " + ", ".join(bands)


def _stds_without_common(res):
    """``[2M, N]`` the run's static-column stds less the ladder's common share
    (:mod:`torchblur.dm.common_noise`), or None for a run without a ladder."""
    if getattr(res, "slope_noise", None) is None:
        return None
    from torchblur.dm.common_noise import static_column_variance

    a = res.actuators
    var = static_column_variance(*res.slope_noise, res.plan.patterns, res.plan.support, a.static_column)
    return np.sqrt(np.maximum(a.static_column_std ** 2 - var, 0))


def d0_z_line(res, truth) -> str:
    """D0's rms(error/std) against the fitted-shift truth on the fully lit subapertures' rows, by the
    entries' size in stds, with and without the ladder's common share. The truth is each spot's
    unweighted least-squares shift, the run's the ladder's (``s``, a shot-noise-weighted fit, +0.2 %
    above the truth: docs/deformable_mirrors.md): a bias of their own at the brightest entries (the
    line says so), so this tests the stds only where it is small; :func:`seed_difference_lines` tests
    them without a truth."""
    a, rows = res.actuators, _lit_rows()
    err = a.static_column - truth["D0"]
    out = _snr_bands(err, a.static_column_std, a.static_column, rows)
    s0 = _stds_without_common(res)
    if s0 is not None:
        out += f"; without the ladder's common error {_snr_bands(err, s0, a.static_column, rows)}"
    return out + " (the brightest entries carry the truth's own convention bias, no std covers it)"


def seed_difference_lines(a, b) -> list[str]:
    """Two runs of one mirror under other noise (another ``seed``), compared without a truth: the
    difference of their D0 and actuator parameters over the two stds combined (about 1 where the
    stds hold; a bias the runs share cancels)."""
    ta, tb, rows = a.actuators, b.actuators, _lit_rows()
    diff = ta.static_column - tb.static_column
    lines = [f"D0 on the fully lit subapertures: rms(difference/std) "
             f"{_snr_bands(diff, np.hypot(ta.static_column_std, tb.static_column_std), ta.static_column, rows)}"]
    s0 = [_stds_without_common(r) for r in (a, b)]
    if s0[0] is not None and s0[1] is not None:
        lines.append(f"D0 on the fully lit subapertures, stds without the ladder's common error: rms(difference/std) "
                     f"{_snr_bands(diff, np.hypot(*s0), ta.static_column, rows)}")
    for name in ("dc_gain", "mode_hz", "damping", "delay_s"):
        z = (getattr(ta, name) - getattr(tb, name)) / np.hypot(getattr(ta, f"{name}_std"), getattr(tb, f"{name}_std"))
        lines.append(f"{name}: rms(difference/std) {np.sqrt(np.nanmean(z ** 2)):.2f} over {int(np.isfinite(z).sum())} actuators")
    return lines


def d_error_lines(res, truth, dyn) -> list[str]:
    """Where D(jw)'s error against the linearised truth comes from, per frequency: its rms(error/std),
    the mean relative error of the large entries (over 0.3 of the column's largest) along the truth
    (gain) and across it (phase, rad) beside their median relative std (a bias shows as a mean
    beyond it), and the live actuators with the largest rms(error/std)."""
    live = np.flatnonzero(~dyn.dead)
    Dt = (truth["shift_slopes"][:, :, None] * dyn.response(res.freq_hz)[None])[:, live]
    D, C = res.D[:, live], res.D_cov[:, live]
    big = np.abs(Dt) > 0.3 * np.abs(Dt).max(0, keepdims=True)
    rel_std = np.sqrt(np.trace(C, axis1=-2, axis2=-1) / 2) / np.abs(Dt)
    r = (D - Dt) / Dt
    lines = []
    for k, f in enumerate(res.freq_hz):
        b = big[:, :, k]
        lines.append(f"{f:7.4g} Hz: rms(error/std) {_z_complex(D[:, :, k] - Dt[:, :, k], C[:, :, k]):.2f}; large entries: gain "
                     f"{np.nanmean(r[:, :, k][b].real) * 100:+.2f} %, phase {np.nanmean(r[:, :, k][b].imag):+.4f} rad (median "
                     f"relative std {np.nanmedian(rel_std[:, :, k][b]) * 100:.2f} %)")
    z = np.array([_z_complex(D[:, j] - Dt[:, j], C[:, j]) for j in range(len(live))])
    worst = np.argsort(-np.nan_to_num(z))[:5]
    lines.append("largest per actuator: " + ", ".join(f"{int(live[j])}: {z[j]:.2f}" for j in worst) + f" (median {np.nanmedian(z):.2f})")
    return lines


def pattern_scale_lines(res, truth, dyn) -> list[str]:
    """Per frequency, one complex scale ``1 + eps`` per pattern of its responses ``Y [P, 2M]`` against the
    linearised truth (weighted least squares over its entries with their covariance): the gains' mean
    and sd over the patterns and their rms(eps/std). A scale common to a pattern's spots is an error
    no entry's std shows; the demultiplexing hands it to every actuator."""
    pats = np.asarray(res.plan.patterns)
    Yt = np.einsum("pn,mnf->pmf", pats, truth["shift_slopes"][:, :, None] * dyn.response(res.freq_hz)[None])
    lines = []
    for k, fk in enumerate(res.freq_hz):
        g, z = [], []
        for p in range(pats.shape[0]):
            y, yt, c = res.Y[p, :, k], Yt[p, :, k], res.Y_cov[p, :, k]
            ok = np.isfinite(y) & np.isfinite(c).all((-1, -2))
            A = np.stack([np.stack([yt.real, -yt.imag], -1), np.stack([yt.imag, yt.real], -1)], -2)[ok]  # d(Re, Im) / d(eps)
            Wi = np.linalg.inv(c[ok])
            F = np.einsum("nia,nij,njb->ab", A, Wi, A)
            e = np.linalg.solve(F, np.einsum("nia,nij,nj->a", A, Wi, np.stack([(y - yt).real, (y - yt).imag], -1)[ok]))
            g.append(e[0])
            z.append(e / np.sqrt(np.diag(np.linalg.inv(F))))
        g, z = np.asarray(g), np.asarray(z)
        lines.append(f"{fk:7.4g} Hz: gain {g.mean() * 100:+.3f} % (sd {g.std() * 100:.3f} % over {len(g)} patterns), rms(error/std) "
                     f"gain {np.sqrt(np.mean(z[:, 0] ** 2)):.2f}, phase {np.sqrt(np.mean(z[:, 1] ** 2)):.2f}")
    return lines


def row_scale_line(res, truth) -> str:
    """The slope rows' scales of the measured D0 against the fitted-shift truth's (:func:`~torchblur.dm.slope_gains.slope_gains`
    with the truth as the geometry and unit gains): their sd and their scatter beyond their stds (``tau``), fully lit
    and edge rows apart. The run's own ``dm slope gains`` line measures them against its fitted geometry, where the
    actuators' own gains absorb part of them."""
    from torchblur.dm.registration import fully_lit
    from torchblur.dm.slope_gains import slope_gains
    from torchblur.rig.factory import build_dm

    a = res.actuators
    lit = np.tile(fully_lit(build_dm(load_config("configs/identify_dm.yaml"))[1]), 2)
    g = slope_gains(a.static_column, a.static_column_std, truth["D0"], np.ones(a.static_column.shape[1]), lit)
    return "; ".join(f"{name} rows sd {np.nanstd(g.gain[sel]) * 100:.3f} %, tau {g.tau[name] * 100:.3f} % (median std "
                     f"{np.nanmedian(g.gain_std[sel]) * 100:.3f} %)" for name, sel in (("lit", lit), ("edge", ~lit)))


def dc_gain_lines(res, dyn) -> list[str]:
    """The live actuators' DC gain errors against the generator's gains, apart for those whose gain
    rests on the edge subapertures (the registration's edge test: ``gains_unverified``, stds flagged)
    and the others: the mean relative error and rms(error/std) with its mean (a gain common to every
    pattern moves the inner ones' mean)."""
    a, live = res.actuators, np.flatnonzero(~dyn.dead)
    e = getattr(res.registration, "edge_test", None) or {}
    edge = np.isin(live, np.asarray(e.get("gains_unverified", []), dtype=int))
    rel, z = a.dc_gain[live] / dyn.gain[live] - 1, (a.dc_gain[live] - dyn.gain[live]) / a.dc_gain_std[live]
    return [f"{name} ({int(sel.sum())}): error mean {np.nanmean(rel[sel]) * 100:+.3f} % (sd {np.nanstd(rel[sel]) * 100:.3f} %), rms(error/std) "
            f"{np.sqrt(np.nanmean(z[sel] ** 2)):.2f} (mean {np.nanmean(z[sel]):+.2f})"
            for name, sel in (("on the edge subapertures", edge), ("inside", ~edge)) if sel.any()]


def projected_responses(res, truth, dyn):
    """``(h [N, F], h_cov [N, F, 2, 2], h_true [N, F])``: every actuator's response ``h_j`` (D's column
    projected on the run's G, :func:`~torchblur.dm.actuator_fit.project_columns`) and the linearised
    truth's, projected the same way."""
    from torchblur.dm.actuator_fit import project_columns

    h, h_cov = project_columns(res.D, res.D_cov, res.G)
    h_true = project_columns(truth["shift_slopes"][:, :, None] * dyn.response(res.freq_hz)[None], res.D_cov, res.G)[0]
    return h, h_cov, h_true


def _pull(dev, err) -> complex:
    """The least-squares complex ``b`` of ``err = b dev`` (``[J]`` each): how far errors follow the
    actuators' relative distance from their mean response (``b = -1``: every one reported as the mean)."""
    return np.vdot(dev, err) / np.vdot(dev, dev)


def shrink_lines(res, truth, dyn, proj=None) -> list[str]:
    """Per frequency, how the live actuators' responses ``h_j`` (D's columns projected on the run's G) err
    against the linearised truth's, relative to how far each actuator's own ``H_j`` lies from the live
    mean: the least-squares ``b`` of ``h_j / h_true_j - 1 = b (H_j / mean H - 1)`` (``b = -1``: every
    actuator reported as the mean; 0: no pull) and the share of the errors' variance about their mean it
    explains. A pull toward the common response is a spot model that ties a spot's change of shape to
    the pattern's common command (the ladder) where the actuators under it move differently. ``proj``:
    :func:`projected_responses`, computed here when not given."""
    live = np.flatnonzero((dyn.gain > 0.7 * np.median(dyn.gain)))
    f = res.freq_hz
    h, _, ht = proj or projected_responses(res, truth, dyn)
    h, ht = h[live], ht[live]
    lines = []
    for k in range(len(f)):
        H = dyn.response(f[k])[live]
        dev, err = H / H.mean() - 1, h[:, k] / ht[:, k] - 1
        b = _pull(dev, err)
        left = err - b * dev
        share = 1 - np.mean(np.abs(left - left.mean()) ** 2) / np.mean(np.abs(err - err.mean()) ** 2)
        lines.append(f"{f[k]:7.4g} Hz: actuators' |H_j / mean - 1| rms {np.sqrt(np.mean(np.abs(dev) ** 2)) * 100:.2f} %, error "
                     f"rms {np.sqrt(np.mean(np.abs(err) ** 2)) * 100:.3f} %, b {b.real:+.3f} {b.imag:+.3f}i ({share:.2f} of the "
                     f"error variance)")
    return lines


def spot_pull_lines(res, truth, dyn) -> list[str]:
    """Per frequency, the pull at the spot level: the least-squares complex ``b`` of the pattern
    responses' errors ``Y - Yt`` (a common scale removed first) on ``Yt - Yc``, ``Yt`` the linearised
    truth ``sum_j pattern_j shift_slopes_j H_j`` and ``Yc`` the same with every live actuator at the
    live mean response; then the actuators' ``b`` of :func:`shrink_lines` left once that pull is taken
    out of ``Y`` (demultiplexed and projected as the run does). A spot model that ties a spot's shape
    to its pattern's common command shows here first, on a plan whose patterns move several of the
    actuators a spot sees (Hadamard); where each spot sees one actuator of a pattern (sparse, one at a
    time) that command is the actuator's own, and ``b`` has no such cause."""
    from torchblur.dm.actuator_fit import project_columns
    from torchblur.dm.demux import demultiplex

    P, S = np.asarray(res.plan.patterns, dtype=float), truth["shift_slopes"]
    live = np.flatnonzero(dyn.gain > 0.7 * np.median(dyn.gain))
    lines = []
    for k, f in enumerate(res.freq_hz):
        H = dyn.response(f)
        Hc = H.copy()
        Hc[live] = H[live].mean()
        Yt, Yc, Y = (P * H[None]) @ S.T, (P * Hc[None]) @ S.T, res.Y[:, :, k]
        ok = np.isfinite(Y) & (Yt != Yc)
        if ok.sum() < 2:
            lines.append(f"{f:7.4g} Hz: every live actuator has the mean response (Yt = Yc): nothing to pull toward")
            continue
        e = Y - Yt
        a = np.vdot(Yt[ok], e[ok]) / np.vdot(Yt[ok], Yt[ok])
        x = Yt - Yc
        b = np.vdot(x[ok], e[ok] - a * Yt[ok]) / np.vdot(x[ok], x[ok])
        D = demultiplex(np.where(ok, Y - b * x, Y)[..., None], res.Y_cov[:, :, k:k + 1], P, res.plan.support)[0]
        h, ht = (project_columns(d, res.D_cov[:, :, k:k + 1], res.G)[0][live, 0] for d in (D, (S * H[None])[..., None]))
        dev = H[live] / H[live].mean() - 1
        b_act = _pull(dev, h / ht - 1)
        lines.append(f"{f:7.4g} Hz: b {b.real:+.4f} {b.imag:+.4f}i over {int(ok.sum())} responses (|Yt - Yc| / |Yt| rms "
                     f"{np.sqrt(np.mean(np.abs(x[ok]) ** 2) / np.mean(np.abs(Yt[ok]) ** 2)) * 100:.2f} %); the actuators' b with it "
                     f"taken out {b_act.real:+.4f} {b_act.imag:+.4f}i")
    return lines


def mode_pull_line(res, dyn) -> str:
    """The live actuators' mode errors against how far each actuator's mode lies from the live mean:
    the least-squares slope of ``mode / true - 1`` on ``true / mean - 1`` (``-1``: every mode reported
    as the mean) and rms(error/std) before and after that line is taken out. A pull toward the mean
    response at the frequencies above the modes shows here as a negative slope."""
    a, live = res.actuators, np.flatnonzero(~dyn.dead)
    t, est, std = dyn.mode_hz[live], a.mode_hz[live], a.mode_hz_std[live]
    dev, err = t / t.mean() - 1, est / t - 1
    slope = float(np.dot(dev, err) / np.dot(dev, dev))
    z, z_left = (est - t) / std, (err - slope * dev) * t / std
    return (f"slope {slope:+.4f} over a spread of {np.std(dev) * 100:.2f} %; rms(error/std) {np.sqrt(np.mean(z ** 2)):.2f}, with the "
            f"slope taken out {np.sqrt(np.mean(z_left ** 2)):.2f}")


def demux_chi2(res) -> np.ndarray:
    """``[F]``: the demultiplexing's residual chi2 per degree of freedom at each frequency, the pattern
    responses ``Y`` against ``patterns D`` with their covariances, pooled over the slope rows (the
    plan's support's actuators fitted per row; a row with an entry the lost fits left undetermined is
    left out at that frequency): about 1 where ``Y`` agree with one ``D`` within their stds, NaN where
    the plan has no more patterns than a row's unknowns (one at a time, sparse)."""
    pat, sup = np.asarray(res.plan.patterns, float), np.asarray(res.plan.support, bool)
    r = res.Y - np.einsum("pn,snf->psf", pat, np.nan_to_num(res.D))
    ok = np.isfinite(r) & np.isfinite(res.Y_cov).all((-1, -2)) & ~np.isnan(res.D).any(1)[None]
    e = np.stack([r.real, r.imag], -1)[ok]
    d2 = np.zeros(r.shape)
    d2[ok] = np.einsum("ka,kab,kb->k", e, np.linalg.inv(res.Y_cov[ok]), e)
    dof = 2 * (ok.sum(0) - sup.sum(1)[:, None])  # [2M, F]
    dof = np.where(ok.any(0), np.maximum(dof, 0), 0).sum(0)
    return np.where(dof > 0, d2.sum((0, 1)) / np.maximum(dof, 1), np.nan)


def lost_entries_line(res) -> str:
    """How many entries of ``D`` the failed spot fits left undetermined (NaN, :func:`~torchblur.dm.demux.demultiplex`),
    on how many (slope row, frequency) items, and the driven patterns whose fits were lost on the item with the most."""
    lost = np.isnan(res.D)  # [2M, N, F]
    per_item = lost.sum(1)  # [2M, F]
    if not per_item.any():
        return "D entries the failed spot fits left undetermined: none"
    r, k = np.unravel_index(np.argmax(per_item), per_item.shape)
    M = res.Y.shape[1] // 2
    gone = np.flatnonzero(~np.isfinite(res.Y[:, r, k]) & driven_spots(res.plan)[:, r % M])  # not the pairs left unfitted by design
    return (f"D entries the failed spot fits left undetermined: {int(lost.sum())} on {int((per_item > 0).sum())} (slope row, "
            f"frequency) items, at most {int(per_item.max())} of {lost.shape[1]} on one (row {r} at {res.freq_hz[k]:.4g} Hz, "
            f"patterns {', '.join(str(int(p)) for p in gone)} lost there)")

def mode_driver_line(res, truth, dyn, proj=None) -> str:
    """Which frequency the live actuators' mode errors follow: the correlation over the actuators of
    each mode's error/std with its response's gain error/std at each frequency (each actuator's mean
    gain error over the frequencies taken out: a static gain does not move a mode), the largest; that
    frequency's gain errors over their stds; and what the run's own residuals show there (the spot
    fits' reduced chi2 median, :func:`demux_chi2`) against every frequency's: a spot model's error
    that leaves them at their noise grows no std."""
    a, live = res.actuators, np.flatnonzero(~dyn.dead)
    h, hc, ht = proj or projected_responses(res, truth, dyn)
    h, hc, ht = h[live], hc[live], ht[live]
    sd = np.sqrt((hc[..., 0, 0] + hc[..., 1, 1]) / 2) / np.abs(ht)
    zg = ((h - ht) / ht).real / sd
    zg = zg - np.nanmean(zg, 1, keepdims=True)
    zm = (a.mode_hz[live] - dyn.mode_hz[live]) / a.mode_hz_std[live]
    corr = np.array([np.corrcoef(zm, zg[:, k])[0, 1] for k in range(zg.shape[1])])
    k = int(np.nanargmax(np.abs(corr)))
    chi2 = np.nanmedian(np.asarray(res.spot_reduced_chi2), axis=(0, 1))
    dmx = demux_chi2(res)
    return (f"mode errors follow the gain errors at {res.freq_hz[k]:.4g} Hz (correlation {corr[k]:+.2f} over {len(live)} live "
            f"actuators, modes {dyn.mode_hz[live].min():.0f}..{dyn.mode_hz[live].max():.0f} Hz), where the gain errors are "
            f"{np.sqrt(np.nanmean(zg[:, k] ** 2)):.2f} of their stds (each actuator's mean over frequency taken out); there the "
            f"spot fits' reduced chi2 median is {chi2[k]:.3f} (every frequency {chi2.min():.3f}..{chi2.max():.3f}) and " + (
                f"the demultiplexing's chi2/dof {dmx[k]:.3f} ({np.nanmin(dmx):.3f}..{np.nanmax(dmx):.3f})" if np.isfinite(dmx).any()
                else "the demultiplexing has no pattern beyond a row's unknowns to check"))


def actuator_gain_lines(res, truth, dyn, proj=None) -> list[str]:
    """The live actuators' responses ``h_j`` (D's columns projected on the run's G) against the linearised
    truth's, their errors split along ``h_j`` (gain) and across it (phase), each over its std: the rms per
    frequency, and how the gain errors of an actuator correlate between frequencies (mean over frequency
    pairs of the correlation over actuators). A frequency-independent error per actuator (a static slope,
    a spot's shift convention) shows as a correlation near 1 that no single frequency's stds reveal; the
    model fit, taking the frequencies as independent, then gives DC gains (and modes) too small a std.
    ``proj``: :func:`projected_responses`, computed here when not given."""
    live = np.flatnonzero(~dyn.dead)
    f = res.freq_hz
    h, hc, ht = proj or projected_responses(res, truth, dyn)
    h, hc, ht = h[live], hc[live], ht[live]  # the dead actuator's truth is 0
    rel = (h - ht) / ht
    sd = np.sqrt((hc[..., 0, 0] + hc[..., 1, 1]) / 2) / np.abs(ht)  # [J, F] relative
    zg, zp = rel.real / sd, rel.imag / sd

    def corr(z):
        c = np.corrcoef(z.T)
        return (np.nansum(c) - len(f)) / (len(f) * (len(f) - 1))
    rms = lambda z: " ".join(f"{v:.2f}" for v in np.sqrt(np.nanmean(z**2, 0)))  # noqa: E731
    return [f"gain rms(error/std) per frequency {rms(zg)}", f"phase rms(error/std) per frequency {rms(zp)}",
            f"mean correlation between frequencies of an actuator's error/std: gain {corr(zg):.2f}, phase {corr(zp):.2f}"]


def physics_checks() -> None:
    """The generator's checks at the benchmark's worst exposure, and what thresholding sees."""
    import torch

    from torchblur.image.detection import find_spots
    from torchblur.render.camera import camera_noise_std

    gen = hs.HcipySH()
    peak = gen._if.max(1) / gen.stroke  # each HCIPy influence function's largest sample per unit command (stroke units)
    print(f"  HCIPy's influence functions (the DC gain's reference): Gaussian, peak 1 stroke per unit command (sampled peaks "
          f"{peak.min():.4f}..{peak.max():.4f}), {gen.optics.coupling:g} at one pitch")
    rng = np.random.default_rng(11)
    still = gen.still() * 3000.0  # a 3000 e- peak, 20 e- background, 3 e- read noise
    img = rng.poisson(still + 20.0).astype(float) - 20.0 + 3.0 * rng.standard_normal(still.shape)
    found = find_spots(torch.as_tensor(img), noise_std=camera_noise_std(float(img.max()), 3.0) / 4)[0]
    corner = gen.still()[16:144:16, 16:144:16]
    print(f"  thresholding (find_spots, the calibration's old spot finder) on a noisy still: {len(found)} connected component(s) "
          f"for {gen.valid.size} spots; floor at the corners between spots {np.median(corner) * 100:.3f} % of the peak")
    cmd = np.random.default_rng(3).normal(size=gen.n_actuators)
    ours = gen.intensity(cmd[None])[0]
    print(f"  batched FFT vs HCIPy's DeformableMirror + MicroLensArray + FresnelPropagator forward: "
          f"{np.abs(ours - gen.reference_intensity(cmd)).max() / ours.max():.1e} of the peak")
    f = 900.0
    omega, T = 2 * math.pi * f, 1 / f
    S = gen.shift_truth()
    amp = np.zeros(gen.n_actuators)
    amp[27] = 3.0 / np.abs(S[:, 27]).max()
    n = gen.node_count(3.0, omega, 0.8 * T)
    a = gen.blurred(amp, np.full(gen.n_actuators, 0.3), omega, [0.05 * T], [0.8 * T], n)
    b = gen.blurred(amp, np.full(gen.n_actuators, 0.3), omega, [0.05 * T], [0.8 * T], 2 * n)
    print(f"  time integral, 3 px motion over 0.8 of a 900 Hz period: {n} vs {2 * n} Gauss-Legendre nodes differ by "
          f"{np.abs(a - b).max() / b.max():.1e} of the peak")
    sys.stdout.flush()


def run_case(name: str, quick: bool, psf: str = "auto", jobs: int = 1, extra=(), progress: bool = False, device: str = "cpu",
             target_px: float | None = None, record: str | None = None, force: bool = False) -> None:
    over = (["sweep.n=4", "dm_plan.budget_frames=512"] if quick else []) + [f"fit.psf={psf}"] + list(extra)
    over += ([] if target_px is None else [f"excitation.target_px={target_px}"]) + [f"fit.device={device}"]
    cfg = load_config("configs/identify_dm.yaml", over, force=force)
    est = estimate_run(cfg)
    print(f"  {name}: the run-size estimate (config.budget.estimate_run): {est['frames']:,} frames, {est['memory_bytes'] / 2**30:.3g} GiB "
          f"of memory, {est['disk_bytes'] / 2**30:.3g} GiB on disk")
    t0 = time.perf_counter()
    gen = hs.HcipySH(CASES[name])
    gen.workers = jobs
    gen.device = None if device == "cpu" else device
    dyn = hs.draw_dynamics(gen.n_actuators, DYNAMICS_SEED)
    rig = hr.hcipy_dm_rig(cfg, gen, dyn)
    truth = rig.truth(None)
    t_gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = None if record is None else Path(record) / name
    res = identify(cfg, rig, progress=progress, record=None if out is None else out / "experiment")
    t_run = time.perf_counter() - t0
    if out is not None:  # the run's outputs beside its recording: benchmarks/bench_dm_outside.py --run OUT --refit
        from torchblur.config import config_to_yaml
        from torchblur.identify.outputs import write_outputs

        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        (out / "config.yaml").write_text(f"# {stamp}\n" + config_to_yaml(cfg))  # as `torchblur identify` writes it
        write_outputs(cfg, res, out, t_run, stamp)
    if os.environ.get("BENCH_DM_HCIPY_SAVE"):  # keep the run (re-read the figures without re-running)
        import pickle

        with open(f"{os.environ['BENCH_DM_HCIPY_SAVE']}_{name}.pkl", "wb") as fh:
            pickle.dump({"res": res, "truth": truth, "dyn": dyn, "cfg_poor_fit_chi2": float(cfg.fit.poor_fit_chi2)}, fh)
    print(f"== {name}: {gen.optics}; fit.psf={psf}; excitation.target_px={cfg.excitation.target_px:g}")
    for line in res.log:
        if line.startswith(("spots:", "latency:", "dm plan:", "dm slope gains:", "dm ladder common error:")):
            print("  " + line)
    print(f"  {res.n_frames} sweep frames ({len(res.freq_hz)} frequencies {res.freq_hz[0]:.4g}..{res.freq_hz[-1]:.4g} Hz), generator set-up "
          f"{t_gen:.1f} s, run {t_run:.1f} s = {t_run / res.n_frames * 1e3:.0f} ms a sweep frame ({', '.join(f'{k} {v:.1f} s' for k, v in res.timing_s.items())}); mean Gauss-Legendre "
          f"nodes per frame {np.mean(rig.nodes_used):.1f}")
    print(f"  peak resident memory of this process so far: {peak_rss_gb():.2f} GB (the generator's included; against the run-size "
          f"estimate above)")
    report(res, truth, dyn, float(cfg.fit.poor_fit_chi2))


def peak_rss_gb() -> float:
    """The process's peak resident set size (GB, 1e9 bytes): ``ru_maxrss`` (kB on Linux), as the other benchmarks read it."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def report(res, truth, dyn, poor_fit_chi2: float) -> None:
    """Print one run's "done when" figures against the generator's truth (a fresh run's or a saved one's)."""
    v = final_verdict(res, poor_fit_chi2)
    f = figures(res, truth, dyn)
    print(f"  live actuators, largest error: mode {f['mode_max_rel_error'] * 100:.3f} % (done when <= 0.5 %), damping "
          f"{f['damping_max_rel_error'] * 100:.2f} % (<= 5 %), delay {f['delay_max_error_us']:.2f} us (<= 2 us), DC gain "
          f"{f['dc_gain_max_rel_error'] * 100:.3f} %")
    print(f"  D0 rms error / max|D0| against the fitted-shift truth: {f['D0_rms_error_over_max'] * 100:.3f} % (<= 1 %)")
    print(f"  D0 rms(error/std) against the fitted-shift truth, fully lit subapertures: {d0_z_line(res, truth)}")
    print(f"  rms(error/std) (0.8..1.3): D(jw) {f['D_rms_z']:.2f}; mode {f['mode_rms_z']:.2f}, damping {f['damping_rms_z']:.2f}, "
          f"delay {f['delay_rms_z']:.2f}, DC gain {f['dc_gain_rms_z']:.2f}")
    for line in d_error_lines(res, truth, dyn):
        print(f"  D(jw) error, {line}")
    for line in pattern_scale_lines(res, truth, dyn):
        print(f"  one scale per pattern, {line}")
    for line in dc_gain_lines(res, dyn):
        print(f"  DC gain of the live actuators whose gain rests {line}")
    print(f"  the slope rows' scales of D0 against the truth: {row_scale_line(res, truth)}")
    proj = projected_responses(res, truth, dyn)
    for line in shrink_lines(res, truth, dyn, proj):
        print(f"  pull toward the mean response, {line}")
    for line in actuator_gain_lines(res, truth, dyn, proj):
        print(f"  actuators' responses h_j, {line}")
    for line in spot_pull_lines(res, truth, dyn):
        print(f"  pull of the pattern responses toward their pattern's common response, {line}")
    print(f"  modes against their deviation from the live mean: {mode_pull_line(res, dyn)}")
    print(f"  {mode_driver_line(res, truth, dyn, proj)}")
    print(f"  {lost_entries_line(res)}")
    print(f"  dead actuator status {f['dead_status']} (want dead), weak {f['weak_status']} (want weak), other live actuators not ok: "
          f"{f['other_not_ok']}")
    print(f"  spot fits' reduced chi2 median {f['spot_chi2_median']:.3g} (<= 1.2); poor_fit actuators {f['poor_fit_actuators']}")
    if res.registration is not None:
        print(f"  registration fitted to D0 (torchblur's mirror model, its own frame): {res.registration.line()}")
    print(f"  {v.line}")
    print(f"  exit {v.exit_code} (want 0)")
    sys.stdout.flush()


def reestimate(res):
    """``res`` with stage 4 (``D (jw)``, the actuators, the registration, the slope rows' gains:
    :func:`~torchblur.identify.dm_plan.estimate_mirror`) run again by this tree's code on its saved
    pattern responses ``Y``, and the stage's log lines."""
    from dataclasses import replace

    from torchblur.identify.dm_plan import estimate_mirror
    from torchblur.identify.record import collect_log
    from torchblur.rig.factory import build_dm

    cfg = load_config("configs/identify_dm.yaml")  # stage 4 reads dm.coupling and dm_plan.support_threshold: not --quick's keys
    with collect_log() as log:
        D, D_cov, table, reg, support = estimate_mirror(cfg, res.freq_hz, res.Y, res.Y_cov, res.plan, res.G_nominal,
                                                        build_dm(cfg)[1], res.actuator_xy, slope_noise=getattr(res, "slope_noise", None))
    return replace(res, D=D, D_cov=D_cov, actuators=table, G=reg.G, registration=reg, support_check=support), log


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="4 frequencies, one repeat (512 frames per case)")
    p.add_argument("--case", choices=["aligned", "misregistered", "both", "none"], default="both",
                   help="none: only the generator's checks")
    p.add_argument("--psf", choices=["auto", "kernel", "gaussian"], default="auto",
                   help="fit.psf (auto: each spot's kernel where its Gaussian fails the still's test, as on a real camera)")
    p.add_argument("--target-px", type=float, default=None,
                   help="excitation.target_px (default: the config's 3 px; the spots change shape under the DM's curvature, "
                        "a bias that grows faster than the motion: benchmarks/bench_dm_spot_causes.py)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override after --quick's (e.g. sweep.n=2 for a smoke test)")
    p.add_argument("--progress", action="store_true", help="the run's log lines as it goes (stderr)")
    p.add_argument("--no-checks", action="store_true", help="skip the generator's checks")
    p.add_argument("--device", default="cpu", help="where the spot fits run (the config's fit.device) and the generator's propagation")
    p.add_argument("--jobs", type=int, default=1, help="threads of the frames' propagation (scipy.fft, BLAS) and of torch")
    p.add_argument("--record", metavar="DIR", help="record each case's run in DIR/CASE/experiment and write its outputs in DIR/CASE "
                   "(then: benchmarks/bench_dm_outside.py --run DIR/CASE --refit, the outside recording's route)")
    p.add_argument("--force", action="store_true", help="run past the size guard (config.budget.check_limits), for a grid "
                   "beyond its limits")
    p.add_argument("--load", metavar="PKL", help="print the figures of a run saved with BENCH_DM_HCIPY_SAVE (no run)")
    p.add_argument("--against", metavar="PKL2", help="with --load: another run of the same mirror under other noise "
                   "(--set seed=N): the two runs' differences over their stds, no truth")
    p.add_argument("--reestimate", action="store_true",
                   help="with --load: stage 4 (D, the actuators, the registration, the slope rows' gains) run again by this "
                        "tree's code on the saved pattern responses, then the figures")
    args = p.parse_args(argv)
    if args.load:
        import pickle

        with open(args.load, "rb") as fh:
            d = pickle.load(fh)
        print(f"== {args.load}" + (" (stage 4 re-estimated by this tree)" if args.reestimate else ""))
        res, log = reestimate(d["res"]) if args.reestimate else (d["res"], d["res"].log)
        saved = [ln for ln in d["res"].log if not ln.startswith("dm slope gains:")] if args.reestimate else []  # stage 4's: re-estimated
        for line in saved + log:
            if line.startswith(("spots:", "dm plan:", "dm spot model:", "dm slope gains:", "dm ladder common error:")):
                print("  " + line)
        report(res, d["truth"], d["dyn"], d["cfg_poor_fit_chi2"])
        if args.against:
            with open(args.against, "rb") as fh:
                other = pickle.load(fh)["res"]
            print(f"  against {args.against} (the same mirror, other noise):")
            for line in seed_difference_lines(res, reestimate(other)[0] if args.reestimate else other):
                print(f"    {line}")
        return
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(args.jobs)
    if args.progress:
        import logging

        logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(relativeCreated)9.0f ms  %(message)s")
    print(f"torch threads {args.jobs}, BLAS and scipy.fft threads {args.jobs}; spot fits on {args.device}; "
          f"{'quick' if args.quick else 'full'} plan{''.join(' ' + o for o in args.set)}; HCIPy dynamics seed {DYNAMICS_SEED}")
    with threadpool_limits(limits=args.jobs):
        if not args.no_checks:
            physics_checks()
        for name in {"both": ["aligned", "misregistered"], "none": []}.get(args.case, [args.case]):
            run_case(name, args.quick, args.psf, args.jobs, args.set, args.progress, args.device, args.target_px, args.record,
                     args.force)


if __name__ == "__main__":
    main()
