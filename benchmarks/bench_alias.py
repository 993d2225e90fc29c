"""One exposure per point (issue 24, part A): single-exposure sweeps of the default plant,
``torchblur identify "sweep.exposures=[0.3]" sweep.trigger_phase_rad=B`` at three trigger phases
(in-process, the simulated rig, seed 0, the default 30 points from 1 Hz to 1 kHz), then the
issue's reproductions (``sweep.n=6``; ``sweep.trigger_phase_rad=2.2``) and the default two-exposure
run as the baseline.

Prints per run: points, right branch (phase error within 5 of its stds of the truth; the
"error/std" of the report), flagged alias, wrong but flagged, wrong and unflagged (must be 0),
max |phase error| / std over the unflagged points, and the verdict (trustworthy or not; the
points and model beyond 5 std of the truth, the verdict's truth guard).

With ``--configs FILE ...`` (e.g. configs/identify_mimo.yaml configs/identify_spots.yaml) each
config is also run with one exposure (its channel points counted the same way; the spots config
takes about 6 minutes).

With ``--sweep N`` only single-exposure runs of the default plant: 8 trigger phases (0.1 + k pi/8
rad, k = 0..7: b and b + pi give the same branches) x seeds 0..N-1, one line each and the totals
(the phases whose crossing lies near 0 deg, about 0.5-0.9 rad, cannot anchor the rule: all flagged).

    python benchmarks/bench_alias.py [--phases 1.5708 2.2 3.0] [--configs FILE ...] [--sweep 3] [--threads 1]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import math
import sys
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify.run import identify
from torchblur.identify.verdict import TRUTH_BOUND, verdict
from torchblur.sysid.flags import ALIAS


def one_run(name: str, overrides: list, config: str | None = None) -> dict:
    """identify with ``overrides`` (on ``config``); the figures of the module docstring, over
    every channel point."""
    cfg = load_config(config, overrides)
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        res = identify(cfg, progress=False)
    frf = res.frf
    _, ep, z = frf.errors_against(res.truth)
    z, ep = z.reshape(-1), ep.reshape(-1)
    flagged = ((frf.flags & ALIAS) != 0).reshape(-1)
    wrong = ~(z <= TRUTH_BOUND)
    v = verdict(frf, cfg, model=res.model, truth=res.truth)
    ok = ~flagged
    return dict(name=name, points=z.size, right=int((~wrong).sum()), alias=int(flagged.sum()), wrong_flagged=int((wrong & flagged).sum()),
                wrong_unflagged=int((wrong & ~flagged).sum()), max_z_unflagged=float(np.nanmax(z[ok])) if ok.any() else float("nan"),
                max_phase_err_deg=float(np.degrees(np.nanmax(np.abs(ep)))), trustworthy=v.trustworthy, beyond=v.beyond_truth,
                model_beyond=v.model_beyond_truth, seconds=time.perf_counter() - t0, line=v.line)


def sweep(n_seeds: int) -> int:
    """Single-exposure runs of the default plant at 8 trigger phases x ``n_seeds`` seeds: per run
    the points, right, flagged, wrong-and-unflagged; then the totals."""
    tot = dict(points=0, right=0, alias=0, wrong_unflagged=0, runs=0, anchored=0)
    print(f"{'trigger rad':>11} {'seed':>4} {'pts':>4} {'right':>5} {'alias':>5} {'wrong,unflagged':>15} {'trustworthy':>11} {'s':>5}")
    for seed in range(n_seeds):
        for k in range(8):
            b = 0.1 + k * math.pi / 8
            r = one_run("", ["sweep.exposures=[0.3]", f"sweep.trigger_phase_rad={b!r}", f"seed={seed}"])
            print(f"{b:11.4f} {seed:4d} {r['points']:4d} {r['right']:5d} {r['alias']:5d} {r['wrong_unflagged']:15d} "
                  f"{str(r['trustworthy']):>11} {r['seconds']:5.1f}", flush=True)
            for key in ("points", "right", "alias", "wrong_unflagged"):
                tot[key] += r[key]
            tot["runs"] += 1
            tot["anchored"] += int(r["alias"] < r["points"])
    print(f"{tot['runs']} runs ({tot['anchored']} anchored: not every point flagged): {tot['points']} points, {tot['right']} right, "
          f"{tot['alias']} flagged alias, {tot['wrong_unflagged']} wrong and unflagged")
    return 1 if tot["wrong_unflagged"] else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phases", type=float, nargs="*", default=[math.pi / 2, 2.2, 3.0])
    ap.add_argument("--configs", nargs="*", default=[])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sweep", type=int, default=0, help="seeds of the 8-phase single-exposure sweep (0: the table instead)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.sweep:
        return sweep(args.sweep)
    runs = [(f"one exposure, trigger {b:.4g} rad", ["sweep.exposures=[0.3]", f"sweep.trigger_phase_rad={b!r}"], None) for b in args.phases]
    runs += [("issue repro: one exposure, sweep.n=6", ["sweep.exposures=[0.3]", "sweep.n=6"], None),
             ("baseline: default two exposures", [], None)]
    runs += [(f"one exposure, {c.rsplit('/', 1)[-1]}", ["sweep.exposures=[0.3]"], c) for c in args.configs]
    print(f"torch threads {args.threads}; default plant (420 Hz, zeta 0.12, 30 us), seed 0; 'right': phase and |H| within "
          f"{TRUTH_BOUND:g} std of the truth")
    head = f"{'run':40} {'pts':>4} {'right':>5} {'alias':>5} {'wrong+flag':>10} {'wrong,unflagged':>15} {'max z unfl':>10} " \
           f"{'max |ph err| deg':>16} {'trustworthy':>11} {'beyond':>6} {'model beyond':>12} {'s':>5}"
    print(head)
    bad = 0
    for name, ov, config in runs:
        r = one_run(name, ov, config)
        bad += r["wrong_unflagged"] + int(r["trustworthy"] and (r["beyond"] or 0) > 0)
        print(f"{r['name']:40} {r['points']:4d} {r['right']:5d} {r['alias']:5d} {r['wrong_flagged']:10d} {r['wrong_unflagged']:15d} "
              f"{r['max_z_unflagged']:10.2f} {r['max_phase_err_deg']:16.2f} {str(r['trustworthy']):>11} {r['beyond']!s:>6} "
              f"{r['model_beyond']!s:>12} {r['seconds']:5.1f}")
        print(f"    {r['line']}")
    print(f"confident wrong answers (a wrong point unflagged, or a trustworthy run beyond {TRUTH_BOUND:g} std): {bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
