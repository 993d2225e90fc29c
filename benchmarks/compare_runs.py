"""Compare the machine-readable outputs of two run folders, number by number.

    python benchmarks/compare_runs.py RUN_A RUN_B [--rtol 1e-12]

Reads every ``*.csv``, ``*.json`` and ``*.npy`` in both folders (the recording under experiment/ left out) (a run's frf.csv, frf.json,
model.json, actuators.csv, registration.json, ...), and compares them value by value: numbers within
``rtol`` of the larger magnitude (or both within ``atol`` of zero), everything else equal. Keys that
hold the clock (elapsed times, dates, stamps) are skipped. Prints one line per file with the
largest relative difference found and exits 1 if any file differs, is missing on one side, or has a
different structure. Used to check that a restructure leaves the shipped configs' outputs unchanged.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

CLOCK_WORDS = ("elapsed", "time_s", "seconds", "stamp", "date", "created", "wall")


def _is_clock(key: str) -> bool:
    k = key.lower()
    return any(w in k for w in CLOCK_WORDS)


def _number(v):
    if isinstance(v, bool):
        return None
    if isinstance(v, (int, float)):
        return float(v)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return None
    return None


def compare_values(a, b, where: str, rtol: float, atol: float, out: list) -> float:
    """Largest relative difference between ``a`` and ``b``; mismatches appended to ``out``."""
    if isinstance(a, dict) and isinstance(b, dict):
        worst = 0.0
        for k in sorted(set(a) | set(b)):
            if _is_clock(str(k)):
                continue
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only in {'B' if k not in a else 'A'}")
                continue
            worst = max(worst, compare_values(a[k], b[k], f"{where}.{k}", rtol, atol, out))
        return worst
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{where}: length {len(a)} against {len(b)}")
            return math.inf
        return max([compare_values(x, y, f"{where}[{i}]", rtol, atol, out)
                    for i, (x, y) in enumerate(zip(a, b))] or [0.0])
    x, y = _number(a), _number(b)
    if x is not None and y is not None:
        if math.isnan(x) and math.isnan(y):
            return 0.0
        scale = max(abs(x), abs(y))
        diff = abs(x - y)
        if diff <= atol:
            return 0.0
        rel = diff / scale if scale > 0 else math.inf
        if rel > rtol:
            out.append(f"{where}: {a!r} against {b!r} (relative {rel:.2e})")
        return rel
    if a != b:
        out.append(f"{where}: {a!r} against {b!r}")
        return math.inf
    return 0.0


def _read(path: Path):
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".npy":
        import numpy as np
        return np.load(path, allow_pickle=False).tolist()
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if rows and rows[0]:
        keep = [i for i, h in enumerate(rows[0]) if not _is_clock(h)]
        rows = [[r[i] for i in keep if i < len(r)] for r in rows]
    return rows


def compare_runs(run_a: Path, run_b: Path, rtol: float = 1e-12, atol: float = 1e-300) -> int:
    names = sorted({str(p.relative_to(d)) for d in (run_a, run_b) for p in d.rglob("*")
                    if p.is_file() and p.suffix in (".csv", ".json", ".npy")
                    and "experiment" not in p.relative_to(d).parts})
    failed = 0
    for name in names:
        pa, pb = run_a / name, run_b / name
        if not pa.exists() or not pb.exists():
            print(f"{name}: only in {'A' if pa.exists() else 'B'}")
            failed += 1
            continue
        problems: list = []
        worst = compare_values(_read(pa), _read(pb), name, rtol, atol, problems)
        status = "same" if not problems else f"DIFFERS ({len(problems)} values)"
        print(f"{name}: {status}, largest relative difference {worst:.2e}")
        for p in problems[:5]:
            print(f"    {p}")
        failed += bool(problems)
    return 1 if failed else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    ap.add_argument("--rtol", type=float, default=1e-12)
    args = ap.parse_args(argv)
    for d in (args.run_a, args.run_b):
        if not d.is_dir():
            print(f"run folder {d} does not exist", file=sys.stderr)
            return 2
    return compare_runs(args.run_a, args.run_b, args.rtol)


if __name__ == "__main__":
    sys.exit(main())
