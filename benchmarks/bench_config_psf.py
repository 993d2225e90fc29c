"""Which PSF each shipped identify config's calibration chooses now that every route takes the
measured kernel (issue 29), and what the per-spot choice costs (``identify.calibration.spot_kernels``).

For configs/identify_*.yaml except identify_dm.yaml (the DM keeps its Gaussian spots: issue 23):
the calibration on the config's simulated rig, its ``psf:`` / ``spots psf:`` lines, and its wall
time; for the many-spot config the calibration again without the per-spot choice
(``spot_psfs=False``, the code path before issue 29), alternating, best of ``--repeats``.
Where a config's calibration keeps the Gaussian, its run fits exactly as before.

    python benchmarks/bench_config_psf.py [--threads 1] [--repeats 2]
"""
from __future__ import annotations

import argparse
import glob
import math
import time

import torch

from torchblur.identify.calibration import calibrate
from torchblur.identify.config import load_config
from torchblur.identify.run import build_simulated_rig


def _calibrate(path: str, spot_psfs: bool):
    cfg = load_config(path)
    torch.manual_seed(int(cfg.seed))
    log = []
    t = time.perf_counter()
    cal = calibrate(cfg, build_simulated_rig(cfg), log=log, spot_psfs=spot_psfs)
    return time.perf_counter() - t, cal, [line for line in log if line.startswith(("psf:", "spots psf:"))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch threads {args.threads}")
    for path in sorted(glob.glob("configs/identify_*.yaml")):
        if path.endswith("identify_dm.yaml"):
            continue
        spots = load_config(path).spots.enabled
        best = {True: math.inf, False: math.inf}
        for _ in range(args.repeats):
            for flag in ((True, False) if spots else (True,)):
                wall, cal, lines = _calibrate(path, flag)
                best[flag] = min(best[flag], wall)
                if flag:
                    shown = lines
        extra = f"; without the per-spot choice {best[False]:.1f} s" if spots else ""
        print(f"{path}: calibration {best[True]:.1f} s{extra}")
        for line in shown:
            print(f"    {line[:160]}")


if __name__ == "__main__":
    main()
