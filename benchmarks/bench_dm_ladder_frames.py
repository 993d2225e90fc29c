"""The DM run's errors against the simulated truth with the ladder spot model, by the frames held per
level (issue 23): does the ladder fit's DC gain depend on how noisy its held images are?

The small simulated mirror of the tests (tests/test_dm_run.py's ``SMALL``: 3 x 3 actuators, one dead,
a 4 x 4 lenslet sensor, a Hadamard plan, 8 frequencies 50 Hz-1.5 kHz) through ``torchblur.identify``
with ``dm_plan.spot_model=shifted`` (the reference: a shifted still is exact on torchblur's
Gaussian spots) and ``dm_plan.spot_model=ladder`` at each ``--frames`` count. Prints, over the live
actuators, each estimate's largest relative error and rms(error/std) (``truth_errors``), the spot
fits out of the ladder, and the wall time; with several ``--seeds``, each frame count's z's
(error/std of every live actuator's DC gain, mode and damping) pooled over the seeds: their rms
and the chi2 probability of their sum of squares (about uniform where the stds hold).

    python benchmarks/bench_dm_ladder_frames.py [--frames 4 16 32] [--seeds 0 1 2] [--no-shifted]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import time

import numpy as np
import torch
from scipy import stats

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from test_dm_run import SMALL  # noqa: E402

from torchblur.config import load_config  # noqa: E402
from torchblur.identify.dm_plan import truth_errors  # noqa: E402
from torchblur.identify.pipeline import identify  # noqa: E402


NAMES = (("dc_gain", "gain"), ("mode_hz", "mode_hz"), ("damping", "damping"))


def one(overrides: list, seed: int, pool: dict) -> str:
    """One run's line: DC gain, mode and damping errors (largest %, rms z), out-of-ladder fits,
    seconds; every live actuator's z appended to ``pool[name]``."""
    cfg = load_config(None, [*SMALL, "report.figures=false", f"seed={seed}", *overrides])
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        res = identify(cfg, progress=False)
    e = truth_errors(res)
    a, m = res.actuators, res.mirror
    for name, true in NAMES:
        z = (getattr(a, name) - getattr(m, true)) / getattr(a, name + "_std")
        pool.setdefault(name, []).extend(z[~m.dead].tolist())
    parts = [f"{k} {e[k + '_max_rel_error'] * 100:.3f} % (rms z {e[k + '_rms_z']:.2f})" for k in ("dc_gain", "mode_hz", "damping")]
    return (f"{', '.join(parts)}; spot model {res.spot_model}, {res.n_out_of_ladder} spot fits out of the ladder; "
            f"{time.perf_counter() - t0:.1f} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="*", default=[4, 16, 32])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0])
    ap.add_argument("--no-shifted", action="store_true", help="skip the shifted still's reference runs")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print("small simulated mirror (tests/test_dm_run.py SMALL); largest relative error over the live actuators; 1 thread")
    pools = {}
    for seed in args.seeds:
        if not args.no_shifted:
            print(f"seed {seed}, shifted          : {one(['dm_plan.spot_model=shifted'], seed, pools.setdefault('shifted', {}))}", flush=True)
        for n in args.frames:
            line = one(['dm_plan.spot_model=ladder', f'dm_plan.ladder_frames={n}'], seed, pools.setdefault(f"ladder, {n:3d} frames", {}))
            print(f"seed {seed}, ladder, {n:3d} frames: {line}", flush=True)
    if len(args.seeds) > 1:
        for key, pool in pools.items():
            parts = []
            for name, _ in NAMES:
                z = np.asarray(pool[name])
                z = z[np.isfinite(z)]
                parts.append(f"{name} rms z {np.sqrt(np.mean(z ** 2)):.2f} (chi2 p {stats.chi2.sf(np.sum(z ** 2), z.size):.2g}, {z.size} z's)")
            print(f"pooled over seeds {args.seeds}, {key}: {'; '.join(parts)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
