"""What the figures cost a run: ``report.figures=true`` (the default) against ``false``.

One identification of the simulated default rig (in-process, seed 0; the test suite's small run,
``sweep.freq_hz=[20,150,300,600]``, unless ``--overrides`` says otherwise), then its outputs
written ``--repeats`` times each way (``torchblur.identify.outputs.write_outputs``, the command's own
writer, into temporary folders). Prints the run's time, the writer's median time with and without
figures, the difference (what ``report.figures=false`` saves a run) and the files each way.

    python benchmarks/bench_figures.py [--repeats 3] [--threads N] [--overrides key=value ...]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchblur.identify.outputs import write_outputs
from torchblur.config import load_config
from torchblur.identify.pipeline import identify


def _write_times(res, overrides, figures: bool, repeats: int) -> tuple[list[float], list[str]]:
    cfg = load_config(None, [*overrides, f"report.figures={str(figures).lower()}"])
    times, names = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d, contextlib.redirect_stdout(io.StringIO()):
            t0 = time.perf_counter()
            write_outputs(cfg, res, Path(d), 1.0, "bench")
            times.append(time.perf_counter() - t0)
            names = sorted(p.name for p in Path(d).iterdir())
    return times, names


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's own)")
    ap.add_argument("--overrides", nargs="*", default=["sweep.freq_hz=[20,150,300,600]"])
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    res = identify(load_config(None, args.overrides), progress=False)
    run_s = time.perf_counter() - t0
    print(f"torch threads {torch.get_num_threads()}; overrides {' '.join(args.overrides)}")
    print(f"identify (in-process, the first run: lazy imports included): {run_s:.2f} s")
    _write_times(res, args.overrides, True, 1)  # warm-up: matplotlib's first import and font cache
    with_s, with_names = _write_times(res, args.overrides, True, args.repeats)
    without_s, without_names = _write_times(res, args.overrides, False, args.repeats)
    w, wo = statistics.median(with_s), statistics.median(without_s)
    print(f"outputs with figures:    {w:.2f} s (median of {args.repeats}): {', '.join(with_names)}")
    print(f"outputs without figures: {wo:.2f} s (median of {args.repeats}): {', '.join(without_names)}")
    print(f"report.figures=false saves {w - wo:.2f} s per run ({(w - wo) / (run_s + w):.0%} of identify + outputs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
