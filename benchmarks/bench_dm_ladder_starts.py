"""Why ladder spot fits failed or left the ladder on HCIPy's lenslet frames (issue 23), and what the
fit's second start changed.

The quick aligned run of ``bench_dm_hcipy.py`` (seed 23, ``--quick``) lost spot fits two ways: some
failed (NOT_CONVERGED) and some fitted a shape command beyond the ladder's levels (OUT_OF_LADDER,
left out of D). Here the same rig is calibrated as the run does (``DMPlan.calibrate``), the ladders
of a few patterns held and their sweep frames taken at the quick plan's four frequencies (at the
amplitudes ``next_amplitude`` predicts from the nominal mirror: the run predicts its later
frequencies from its own fits, within 2 % of these), and their spot fits made as the run makes
them (``_fit_frequency`` itself),
first with the fit's own start only and 60 LM iterations (the fit before), then as the package fits
them (:func:`torchblur.dm.ladder_fit._starts`: a second start from the pattern's pooled centroids,
the lower cost kept; ``MAX_ITER``). Printed per frequency and in all: failed and out-of-ladder
counts, the spots' static shift per unit command (|s|) of those, how many problems the second start
ran on, and rms(error/std) of the kept responses against the linearised truth
(``shift_truth x H(jw) x pattern``); then how far the plan's commands reach into the ladders
(the largest live actuator's command over each pattern's top level).

    python benchmarks/bench_dm_ladder_starts.py [--patterns 48,0,32,54,4,6,38,52]

The default patterns are the eight with the most lost fits in the quick run of commit 81d9e2f.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from unittest import mock

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import hcipy_sh as hs  # noqa: E402
import hcipy_sh_rig as hr  # noqa: E402

import torchblur.dm.ladder_fit as lf  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.config.budget import dm_geometry, dm_plan  # noqa: E402
from torchblur.dm.plans import static_motion_px  # noqa: E402
from torchblur.identify.dm_ladder import acquire_holds, hold_exposure, ladder_key, ladder_levels, pattern_ladder  # noqa: E402
from torchblur.identify.dm_plan import DMPlan, _acquire_frequency, _fit_frequency, _fit_options, next_amplitude, nominal_growth  # noqa: E402


def acquire(patterns):
    """Calibration, the ladders of ``patterns`` and their sweep frames at the quick plan's frequencies."""
    cfg = load_config("configs/identify_dm.yaml", ["sweep.n=4", "dm_plan.budget_frames=512", "fit.psf=auto", "fit.device=cpu"])
    gen = hs.HcipySH(hs.SHOptics())
    dyn = hs.draw_dynamics(gen.n_actuators, 23)
    rig = hr.hcipy_dm_rig(cfg, gen, dyn)
    plan = DMPlan()
    with plan.open(cfg, rig, progress=False, record=None) as run:
        plan.calibrate(run)
        cal, G = run.cal, dm_geometry(cfg)
        pl, R, _ = dm_plan(cfg)
        limit = min(math.inf if cfg.dm.input_limit is None else float(cfg.dm.input_limit), cal.input_limit)
        levels = ladder_levels(cfg, pl.patterns, G, limit)
        sub = pl.patterns[patterns]
        holds = acquire_holds(rig, None, [ladder_key(p) for p in range(len(sub))], sub, levels[patterns], int(cfg.dm_plan.ladder_frames),
                              hold_exposure(cfg, cal), cal, plan.offset, plan.size)
        ladder = pattern_ladder(holds, cal, plan.offset, plan.size)
        sweeps = []
        for f in cfg.frequencies_hz():
            amp = next_amplitude(target_px=float(cfg.excitation.target_px), motion_per_unit=static_motion_px(pl, G) * nominal_growth(cfg.dm, f, None),
                                 input_limit=min(limit, cal.limit_at(f)), max_pattern=float(np.abs(pl.patterns).max()))
            te = [float(e) / f for e in cfg.sweep.exposures]
            power = cfg.camera.peak_fraction * cal.full_adu * cal.gain / (cal.peak_rate * max(te))
            frames, window = _acquire_frequency(rig, type("Sub", (), {"patterns": sub}), f, amp, te,
                                                float(cfg.sweep.trigger_phase_rad) / (2 * math.pi * f), R, cfg.sweep.settle_s, power,
                                                cal.latency_s, float(cfg.camera.trigger_delay_s))
            sweeps.append((f, amp, power, frames, window))
    return cfg, cal, plan, ladder, sweeps, sub, levels[patterns], dyn, rig.truth(None)["shift_slopes"]


def fit(cal, plan, ladder, sweep, cfg):
    """``(Y [P, 2M], Y_cov, failed, out of the ladder)`` of one frequency: the run's own ``_fit_frequency``."""
    f, amp, power, frames, window = sweep
    r = _fit_frequency(frames, window, 2 * math.pi * f, amp, power, cal, plan.psf, plan.offset, plan.size, float(cfg.camera.jitter_s),
                       _fit_options(cfg), ladder)
    return r.Y, r.Y_cov, r.failed, r.out_of_ladder


def one_pass(name, cal, plan, ladder, sweeps, cfg, dyn, S, pats, snorm, starts) -> None:
    """One pass of the fits over ``sweeps`` (as the ladder module is set now), printed per frequency and in all."""
    tot = np.zeros(4)
    z2 = []
    for f, amp, power, frames, window in sweeps:
        starts.update(own=0, second=0)
        Y, Yc, failed, out = fit(cal, plan, ladder, (f, amp, power, frames, window), cfg)
        M = Y.shape[1] // 2
        err = Y - (S @ (dyn.response(f)[:, None] * pats.T)).T
        ev = np.stack([err.real, err.imag], -1)[..., None]
        ok = np.isfinite(ev).all((-1, -2)) & np.isfinite(Yc).all((-1, -2))  # NaN: failed or out of the ladder
        C = np.where(ok[..., None, None], Yc, np.eye(2))
        z2.append(((np.swapaxes(ev, -1, -2) @ np.linalg.inv(C) @ np.where(ok[..., None, None], ev, 0))[..., 0, 0] / 2)[ok])
        lost = torch.as_tensor(~(ok[:, :M] & ok[:, M:]))
        tot += [failed, out, starts["second"], int(ok.sum())]
        print(f"  {name}, {f:7.4g} Hz: failed {failed}, out of the ladder {out} (their |s| "
              f"{', '.join(f'{v:.2g}' for v in sorted(snorm[lost].tolist())) or '-'}); second start on {starts['second']} of {starts['own']} problems")
    z2 = np.concatenate(z2)
    print(f"{name}: failed {int(tot[0])}, out of the ladder {int(tot[1])} of {4 * snorm.numel()} fits; second start on {int(tot[2])}; "
          f"kept responses {int(tot[3])}, rms(error/std) {np.sqrt(z2.mean()):.3f} against the linearised truth, above 3: {int((z2 > 9).sum())}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--patterns", default="48,0,32,54,4,6,38,52")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    patterns = [int(x) for x in a.patterns.split(",")]
    cfg, cal, plan, ladder, sweeps, pats, levels, dyn, S = acquire(patterns)
    starts = {"own": 0, "second": 0, "pending": False}  # problems fitted from their own start, from the pooled one
    lm, best = lf.levenberg_marquardt, lf._best_start

    def first_of_each(*a, **kw):  # _best_start's first LM is every problem's own start, a second one the pooled start
        starts["pending"] = True
        return best(*a, **kw)

    def counting(model_fn, theta0, data, **kw):
        starts["own" if starts["pending"] else "second"] += theta0.shape[0]
        starts["pending"] = False
        return lm(model_fn, theta0, data, **kw)
    snorm = ladder.slope.norm(dim=-1)  # [P, M] px per unit command
    print(f"patterns {patterns}: {len(pats)} x {snorm.shape[1]} spots; |s| median {float(snorm.median()):.3g} px per unit")
    passes = (("own start only, 60 LM iterations (before)", math.inf, 60), ("package", lf.SECOND_START, lf.MAX_ITER))
    with mock.patch.object(lf, "levenberg_marquardt", counting), mock.patch.object(lf, "_best_start", first_of_each):  # restored on leaving
        for name, second, iters in passes:
            with mock.patch.multiple(lf, SECOND_START=second, MAX_ITER=iters):
                one_pass(name, cal, plan, ladder, sweeps, cfg, dyn, S, pats, snorm, starts)
    for f, amp, *_ in sweeps:
        H = np.abs(dyn.response(f))
        live = H > 0.5 * np.median(H)
        print(f"  {f:7.4g} Hz: amplitude {amp:.4g}; the largest live actuator's command over each pattern's top level: at most "
              f"{(amp * H[live].max() * np.abs(pats).max(1) / np.abs(levels).max(1)).max():.3f}")


if __name__ == "__main__":
    main()
