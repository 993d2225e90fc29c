"""Ctrl-C at random moments of a run: one line each time, and what it says to run next finishes.

    python benchmarks/bench_ctrl_c.py [--n 20] [--seed 0] [--small] [--clock process|work|cpu] [--warmup 1] [--total T] [--jobs 1] [--only K ...] [key=value ...]

Runs ``torchblur identify --out DIR --quiet`` (the console script; the default run; ``--small``: 4 frequencies)
once uninterrupted to warm up (the first run in a tree compiles its bytecode and reads cold files: with
``--clock cpu`` it used ~40 % more CPU than the later runs, so 8 of 20 moments drawn from it fell after
those runs had finished), then once more to time it (T, the smaller of the two), then ``--n`` times sends SIGINT at a moment drawn uniformly
in [0, T] (seeded; ``--clock work``: T and the moments counted from when the run made its output
folder; ``--clock cpu``: T is the run's CPU time and each signal goes when the run has used the
drawn CPU seconds, so that on a loaded machine the moments still cover the run's work), and checks: the exit status is 130, stderr holds exactly one line and no
traceback, and the command that line names (``resume with: ...``, or the same command again
when nothing was recorded) finishes with exit 0 or 4 and a report.txt whose last line is the
verdict; a second ``--resume`` of the finished run says so and changes nothing. Prints the
counts; exit status 1 if any check failed.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import os
import random
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["sweep.freq_hz=[20,150,300,600]"]


def _env():
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _cmd(*argv):
    """The ``torchblur`` console script beside this Python (what a user runs), else ``-m``."""
    script = Path(sys.executable).parent / "torchblur"
    return [str(script), *argv] if script.is_file() else [sys.executable, "-m", "torchblur.cli", *argv]


def _run(argv, timeout=900):
    return subprocess.run(_cmd(*argv), capture_output=True, text=True, env=_env(), timeout=timeout)


def _started(proc, out: Path | None) -> None:
    """Wait until the run has made its output folder ``out`` (torchblur's work began: the
    interpreter and the imports are behind it) or has exited; no wait for ``out=None``."""
    while out is not None and not out.exists() and proc.poll() is None:
        time.sleep(0.02)


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system, all threads) the process ``pid`` has used so far (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("inf")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _interrupt(argv, after_s: float, out: Path | None = None, cpu: bool = False):
    """Start ``argv``, SIGINT it ``after_s`` after its start (with ``out``: after the folder
    ``out`` appeared; with ``cpu``: once it has used ``after_s`` CPU seconds) -> (exit status,
    stderr lines, signalled)."""
    proc = subprocess.Popen(_cmd(*argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(),
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    if cpu:
        while proc.poll() is None and _cpu_s(proc.pid) < after_s:
            time.sleep(0.01)
    else:
        _started(proc, out)
        time.sleep(after_s)
    signalled = proc.poll() is None
    if signalled:
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=600)
    return proc.returncode, [ln for ln in err.splitlines() if ln.strip()], signalled


def _next_command(line: str, argv: list) -> list | None:
    """The command the interruption line says to run next (argv without the program)."""
    if "resume with: torchblur " in line:
        return shlex.split(line.split("resume with: torchblur ", 1)[1]) + ["--quiet"]
    if "run the same command again" in line:
        return list(argv)
    return None


def _finished(out: Path) -> bool:
    report = out / "report.txt"
    return report.is_file() and report.read_text().rstrip().splitlines()[-1].startswith("verdict:")


def trial(k: int, after_s: float, base: list, tmp: Path, clock: str = "process") -> dict:
    out = tmp / f"run{k}"
    argv = ["identify", "--out", str(out), "--quiet", *base]
    rc, lines, signalled = _interrupt(argv, after_s, out if clock == "work" else None, cpu=clock == "cpu")
    row = {"k": k, "after_s": after_s, "rc": rc, "signalled": signalled, "lines": len(lines),
           "traceback": any("Traceback" in ln for ln in lines), "line": lines[-1] if lines else ""}
    if row["traceback"] and not any("/torchblur/" in ln for ln in lines):  # before any torchblur code: Python's own start
        row.update(ok=False, what="during the interpreter's start, before torchblur's code ran (Python's traceback)")
        return row
    if rc != 130:  # finished before the signal arrived, or as it exited (then ignored: the work was done), or failed
        row["ok"] = rc in (0, 4) and _finished(out) and not lines
        what = "finished as the signal came (ignored: the run was done)" if signalled else "finished before the signal"
        row["what"] = what if row["ok"] else f"exit {rc}: {' | '.join(lines[-3:])}"
        return row
    nxt = _next_command(lines[-1] if lines else "", argv)
    if nxt is None:
        row.update(ok=False, what=f"no command to run next in: {row['line']}")
        return row
    r2 = _run(nxt)
    before = sorted(p.name for p in out.iterdir()) if out.exists() else []
    r3 = _run(["identify", "--resume", str(out), "--quiet"])  # a finished run: says so, does nothing
    after = sorted(p.name for p in out.iterdir()) if out.exists() else []
    row.update(resume_rc=r2.returncode, finished=_finished(out), second_resume_rc=r3.returncode,
               second_resume_says="finished run" in r3.stderr and before == after)
    row["ok"] = (len(lines) == 1 and not row["traceback"] and r2.returncode in (0, 4) and row["finished"]
                 and r3.returncode == 0 and row["second_resume_says"])
    row["what"] = "interrupted, resumed" if row["ok"] else f"resume exit {r2.returncode}: {r2.stderr.strip()[-300:]}"
    return row


def _reference(base: list, out: Path, clock: str):
    """One uninterrupted run into ``out`` -> (its duration on ``clock``, CompletedProcess with its stderr)."""
    with open(out.with_suffix(".err"), "w+") as err:
        proc = subprocess.Popen(_cmd("identify", "--out", str(out), "--quiet", *base), stdout=subprocess.DEVNULL,
                                stderr=err, text=True, env=_env())
        if clock == "work":
            _started(proc, out)
        t0 = time.perf_counter()
        _, status, usage = os.wait4(proc.pid, 0)
        total = usage.ru_utime + usage.ru_stime if clock == "cpu" else time.perf_counter() - t0
        err.seek(0)
        return total, subprocess.CompletedProcess(proc.args, os.waitstatus_to_exitcode(status), "", err.read())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true", help="4 frequencies instead of the default 30")
    ap.add_argument("--clock", choices=("process", "work", "cpu"), default="process",
                    help="process: moments from the process's start (the interpreter's start and imports included); work: "
                         "from the moment the run made its output folder, uniform over the reference run's time from there; "
                         "cpu: at a CPU time of the run uniform over the reference run's (the same moments of the work "
                         "whatever the machine's load)")
    ap.add_argument("--warmup", type=int, default=1, help="uninterrupted runs before the timed one (T: the smallest of all)")
    ap.add_argument("--total", type=float, default=None, help="T measured before (on --clock): no uninterrupted run")
    ap.add_argument("--jobs", type=int, default=1, help="trials at a time (with --clock cpu the moments do not move with the load)")
    ap.add_argument("--only", type=int, nargs="*", default=None, help="run only these trials (the same moments as in the full run)")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    base = (SMALL if args.small else []) + list(args.overrides)
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        totals = [] if args.total is None else [args.total]
        for r in range(args.warmup + 1 if args.total is None else 0):
            total, ref = _reference(base, tmp / f"ref{r}", args.clock)
            if ref.returncode not in (0, 4):
                print(f"the uninterrupted run failed (exit {ref.returncode}): {ref.stderr[-500:]}")
                return 1
            totals.append(total)
        total = min(totals)
        since = {"process": "s from its start", "work": "s from when its output folder appeared", "cpu": "CPU seconds"}[args.clock]
        print(f"uninterrupted runs: {', '.join(f'{t:.1f}' for t in totals)} {since}"
              f"{' (given: --total)' if args.total is not None else ''}; {args.n} interruptions uniform in [0, {total:.1f}] {since} "
              f"(the smallest), {args.jobs} at a time")
        moments = [rng.uniform(0.0, total) for _ in range(args.n)]

        def one(k):
            row = trial(k, moments[k], base, tmp, args.clock)
            print(f"  {k:2d}: SIGINT at {row['after_s']:5.1f} s: exit {row['rc']}, {row['lines']} line(s): "
                  f"{row['what']}; {row['line'][:110]}", flush=True)
            return row

        with concurrent.futures.ThreadPoolExecutor(max(args.jobs, 1)) as pool:
            rows = list(pool.map(one, range(args.n) if args.only is None else args.only))
    interrupted = [r for r in rows if r["rc"] == 130]
    one = sum(r["lines"] == 1 and not r["traceback"] for r in interrupted)
    resumed = sum(r.get("finished", False) and r.get("resume_rc") in (0, 4) for r in interrupted)
    second = sum(r.get("second_resume_says", False) for r in interrupted)
    early = sum(r["rc"] != 130 and r["ok"] for r in rows)
    start = sum("interpreter's start" in r["what"] for r in rows)
    bad = [r for r in rows if not r["ok"]]
    print(f"interrupted {len(interrupted)} of {len(rows)} (the others finished before the signal: {early}); "
          f"one line and no traceback: {one} of {len(interrupted)}; the named command finished: {resumed} of "
          f"{len(interrupted)}; a second --resume said 'finished' and did nothing: {second} of {len(interrupted)}; "
          f"in the interpreter's start (before torchblur's code): {start}; failed checks: {len(bad)}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
