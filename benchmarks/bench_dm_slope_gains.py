"""The slope rows' own gains (torchblur.dm.slope_gains) on a mirror whose rows are scaled: do the DC gains' stds hold?

A 12-actuator mirror on 21 subapertures (``tests/test_dm_slope_gains.py``'s ``_run``: every slope row scaled by
its own gain at every frequency, D(jw) with 1e-3 noise, the run's stage 4) for rows scaled by 0.5 %, 0.2 % and
not at all, over ``--seeds`` seeds: the live DC gains' rms(error/std) with the frequencies' stds alone and with
the rows' scatter (``tau``, measured from D0) added, and the median ``tau`` over the fully lit rows.

    python benchmarks/bench_dm_slope_gains.py [--seeds 8]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from test_dm_slope_gains import _run  # noqa: E402


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=8)
    args = p.parse_args(argv)
    for row_sd in (5e-3, 2e-3, 0.0):
        z0, z1, tau = [], [], []
        for seed in range(args.seeds):
            mirror, before, after, gains = _run(seed, row_sd)
            live = ~mirror.dead
            z0.append((before.dc_gain - mirror.gain)[live] / before.dc_gain_std[live])
            z1.append((after.dc_gain - mirror.gain)[live] / after.dc_gain_std[live])
            tau.append(gains.tau["lit"])
        rms = lambda z: float(np.sqrt(np.mean(np.square(z))))  # noqa: E731
        print(f"rows scaled {row_sd * 100:.1f} %: DC gain rms(error/std) {rms(z0):.2f} without the rows' scatter, {rms(z1):.2f} with it; "
              f"tau (fully lit rows) median {np.median(tau) * 100:.3f} % over {args.seeds} seeds")


if __name__ == "__main__":
    main()
