"""What saving a run's figures costs: bode.png and residuals.png of a default identification.

Runs one identification in this process (the default config, or the README's fast-sweep
example with ``--fast``: ``sweep.f_max_hz=200000 sweep.n=6 sweep.images_per_point=1``), then
builds and saves each figure ``--repeat`` times exactly as ``torchblur identify`` does
(:func:`torchblur.identify.outputs.write_bode` and ``write_residuals``), and prints the
median wall and CPU time of each (s) and their ratios to the identification's own. With
``--out DIR`` the figures are left there to look at.

    python benchmarks/bench_plots.py [--fast] [--repeat 5] [--threads 1] [--out DIR]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchblur.identify import outputs
from torchblur.identify.assemble import mark_limited
from torchblur.config import load_config
from torchblur.identify.run import identify

FAST = ["sweep.f_max_hz=200000", "sweep.n=6", "sweep.images_per_point=1"]


def _timed(fn, repeat: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` (CPU time is what a loaded machine distorts least)."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fast", action="store_true", help="the README's fast-sweep example instead of the default run")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None, help="leave bode.png and residuals.png here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(None, FAST if args.fast else [])
    torch.manual_seed(cfg.seed)
    t0, c0 = time.perf_counter(), time.process_time()
    res = identify(cfg, progress=False)
    t_run, c_run = time.perf_counter() - t0, time.process_time() - c0
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_plots_"))
    out.mkdir(parents=True, exist_ok=True)
    stamp = f"torchblur bench_plots, seed {cfg.seed}"
    res.frf = mark_limited(res.frf.replace(meta={"output_unit": "px", "input_unit": "input unit", **res.frf.meta}), res.limited)
    t_bode = _timed(lambda: outputs.write_bode(cfg, res, out, stamp), args.repeat)
    t_res = _timed(lambda: outputs.write_residuals(res, out, stamp), args.repeat)
    sizes = {p.name: p.stat().st_size for p in (out / "bode.png", out / "residuals.png")}
    print(f"{'fast-sweep example' if args.fast else 'default run'}: {res.frf.omega.size} points, {args.threads} thread(s), "
          f"median of {args.repeat}")
    print(f"identification (simulated acquisition and fitting): {t_run:.2f} s wall, {c_run:.2f} s CPU")
    for name, (t, c) in (("bode.png", t_bode), ("residuals.png", t_res)):
        print(f"{name} built and saved: {t:.3f} s wall ({t / t_run:.3f} of the identification), {c:.3f} s CPU ({c / c_run:.3f})")
    print("file sizes: " + ", ".join(f"{k} {v / 1024:.0f} KiB" for k, v in sizes.items()))
    print(f"figures in {out}")


if __name__ == "__main__":
    main()
