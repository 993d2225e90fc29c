"""The DM run's errors against the simulated truth with the ladder spot model, by the frames held per
level (issue 23): does the ladder fit's DC gain depend on how noisy its held images are?

The small simulated mirror of the tests (tests/test_dm_run.py's ``SMALL``: 3 x 3 actuators, one dead,
a 4 x 4 lenslet sensor, a Hadamard plan, 8 frequencies 50 Hz-1.5 kHz) through ``torchblur.identify``
with ``dm_plan.spot_model=shifted`` (the reference: a shifted still is exact on torchblur's
Gaussian spots) and ``dm_plan.spot_model=ladder`` at each ``--frames`` count. Prints, over the live
actuators, each estimate's largest relative error and rms(error/std) (``truth_errors``), the spot
fits out of the ladder, and the wall time.

    python benchmarks/bench_dm_ladder_frames.py [--frames 4 16 32] [--seed 0]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from test_dm_run import SMALL  # noqa: E402

from torchblur.config import load_config  # noqa: E402
from torchblur.identify.dm_plan import truth_errors  # noqa: E402
from torchblur.identify.pipeline import identify  # noqa: E402


def one(overrides: list, seed: int) -> str:
    """One run's line: DC gain, mode and damping errors (largest %, rms z), out-of-ladder fits, seconds."""
    cfg = load_config(None, [*SMALL, "report.figures=false", f"seed={seed}", *overrides])
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        res = identify(cfg, progress=False)
    e = truth_errors(res)
    parts = [f"{k} {e[k + '_max_rel_error'] * 100:.3f} % (rms z {e[k + '_rms_z']:.2f})" for k in ("dc_gain", "mode_hz", "damping")]
    return (f"{', '.join(parts)}; spot model {res.spot_model}, {res.n_out_of_ladder} spot fits out of the ladder; "
            f"{time.perf_counter() - t0:.1f} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="*", default=[4, 16, 32])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print(f"small simulated mirror (tests/test_dm_run.py SMALL), seed {args.seed}; largest relative error over the live actuators")
    print(f"shifted          : {one(['dm_plan.spot_model=shifted'], args.seed)}", flush=True)
    for n in args.frames:
        print(f"ladder, {n:3d} frames: {one(['dm_plan.spot_model=ladder', f'dm_plan.ladder_frames={n}'], args.seed)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
