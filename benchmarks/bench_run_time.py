"""The time and memory a whole ``torchblur identify`` command takes, in figures that do not hang on
the machine's load where that is possible (the CPU seconds) and beside them the ones that do (wall).

    python benchmarks/bench_run_time.py [--config configs/identify_dm.yaml] [key=value ...]

Runs ``torchblur identify --config CONFIG --out TMP --quiet [key=value ...]`` (the console script,
from a temporary folder) once and prints: the CPU seconds of the whole command (user + system of
every thread, from the child's resource usage: what the work costs, much less dependent on other
work on the machine than the wall time, which on a busy machine is several times the idle one); its
wall seconds; their ratio; the peak
resident memory; the torch / OpenMP threads it ran with; the 1-minute load average before and
after (a wall time is an idle machine's figure only where these are below the core count); and the
run's own timing line (``time:`` of a DM run, ``elapsed`` of a sine run). Exit status: the run's.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _cmd(*argv):
    """The ``torchblur`` console script beside this Python (what a user runs), else ``-m``."""
    script = Path(sys.executable).parent / "torchblur"
    return [str(script), *argv] if script.is_file() else [sys.executable, "-m", "torchblur.cli", *argv]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/identify_dm.yaml")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        with open(Path(tmp) / "log", "w+") as log:
            proc = subprocess.Popen(_cmd("identify", "--config", str(ROOT / args.config), "--out", str(out), "--quiet", *args.overrides),
                                    stdout=log, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp)
            _, status, usage = os.wait4(proc.pid, 0)  # the child's own resource usage, every thread
            wall = time.perf_counter() - t0
            log.seek(0)
            text = log.read()
        rc = os.waitstatus_to_exitcode(status)
        load1 = os.getloadavg()[0]
        report = out / "report.txt"
        lines = report.read_text().splitlines() if report.is_file() else text.splitlines()
    cpu = usage.ru_utime + usage.ru_stime
    own = [ln.strip() for ln in lines if re.match(r"\s*(time: |elapsed )", ln)]
    print(f"torchblur identify --config {args.config} {' '.join(args.overrides)}: exit {rc}")
    print(f"CPU {cpu:.1f} s (user {usage.ru_utime:.1f} + system {usage.ru_stime:.1f}, every thread), wall {wall:.1f} s, "
          f"CPU/wall {cpu / wall:.2f}, peak memory {usage.ru_maxrss / 1024 ** 2:.2f} GB")
    print(f"threads: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, {os.cpu_count()} cores; 1-minute load "
          f"average {load0:.1f} before, {load1:.1f} after (the wall time is an idle machine's only below {os.cpu_count()})")
    for ln in own:
        print(f"the run's own line: {ln}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
