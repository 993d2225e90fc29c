"""A DM run's frames written as an outside DM recording and fitted by ``torchblur fit FOLDER``
give the live run's result (issue 23 part D; docs/outside_recordings.md, "Deformable-mirror
recordings"), and the memory each step takes.

Runs ``torchblur identify`` on a DM config (default: a 9-actuator mirror under 4 x 4
subapertures, the suite's tests/test_dm_run.py size; ``--config configs/identify_dm.yaml`` for the
shipped 52-actuator one), exports its recording (:func:`torchblur.identify.export_dm_recording`), fits
the folder with ``torchblur fit`` (with the run's ``fit.*`` settings) and prints: the largest relative difference of every actuator
column (actuators.csv, 9 significant digits), of D0 (interaction_matrix.npy) and of D(jw)
(frf.json) between the two, the largest over every csv/json/npy file of ``dm/`` (benchmarks/compare_runs.py's
comparison), the folder's size, the wall time and peak resident memory of each step (each runs in its own
process: ``os.wait4``'s ``ru_maxrss``; threads: torch's default; times are for this machine only), and each fit's
``dm fit pace:`` line (its spot fits' seconds per frequency against the camera's frames).

    python benchmarks/bench_dm_outside.py [--config FILE] [--keep DIR] [--baseline SRC] [overrides ...]
    python benchmarks/bench_dm_outside.py --run RUN [--refit]   # a run recorded on any rig (torchblur.identify(cfg, rig, record=RUN/experiment))
    python benchmarks/bench_dm_outside.py --read FOLDER [--baseline SRC] [fit.* overrides]   # an outside DM recording read, no fit
    python benchmarks/bench_dm_outside.py --export RUN --baseline SRC [--keep DIR]   # a recorded DM run exported by both trees, no fit

With ``--run`` the reference is the run's own outputs (a run on a lab's or a test's rig, an HCIPy Shack-Hartmann
rig, is compared the same way); with ``--refit`` it is ``torchblur fit RUN`` (a re-fit of the recording, by this
tree), itself compared with the run's outputs (live against re-fit). ``--baseline SRC``: a source tree of torchblur (e.g. ``mkdir SRC; git archive
81d9e2f | tar -x -C SRC``) whose ``torchblur fit FOLDER`` also fits the exported folder: its peak memory and its result against
this tree's (the reader's memory before and after a change), and exports the recording too: the two exports' times
(the call alone, in its process, and the process) and whether every file of the two folders is the same byte for byte.
``--read FOLDER``: only the peak memory and time of
what the fit of an outside DM recording does before its spot fits (read and check the folder, the calibration,
the held patterns' images, every frequency's frames as the fit takes them), by this tree and ``--baseline``'s.
``--export RUN``: only the exports of the recorded run ``RUN`` by this tree and ``--baseline``'s (times, bytes).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from compare_runs import _read, compare_values  # noqa: E402

SMALL = ["dm.n_across=3", "dm.mode_hz=600.0", "dm.damping=0.1", "dm.mode_spread=0.05", "dm.dead=[2]", "dm.input_limit=10.0",
         "wfs.n_across=4", "wfs.pitch_px=16.0", "wfs.sigma_px=1.2", "dm_plan.kind=hadamard", "dm_plan.budget_frames=null",
         "dm_plan.n_repeats=1", "sweep.f_min_hz=50.0", "sweep.f_max_hz=1500.0", "sweep.n=8", "sweep.exposures=[0.3,0.8]",
         "excitation.target_px=3.0"]
COLUMNS = ("dc_gain", "dc_gain_std", "mode_hz", "mode_hz_std", "damping", "damping_std", "delay_s", "delay_s_std")
HERE = Path(__file__).resolve().parents[1]
EXPORT = """import sys, time
from pathlib import Path
from torchblur.identify import export_dm_recording
t0 = time.perf_counter()
export_dm_recording(sys.argv[1], sys.argv[2])
Path(sys.argv[3]).write_text(repr(time.perf_counter() - t0))
"""
READ = """import sys, torch
from torchblur.config.budget import dm_sensor
from torchblur.identify.dm_ladder import hold_images
from torchblur.identify.dm_outside import dm_recording_config, read_dm_recording, recording_calibration
rec = read_dm_recording(sys.argv[1])
cfg = dm_recording_config(rec, sys.argv[2:])
cal, psf, offset, size = recording_calibration(rec, cfg, dm_sensor(cfg)[1])
if rec.ladder_levels is not None:
    hold_images(rec.ladder_frames, rec.ladder_levels, float(rec.ladder_exposure_s), cal, offset, size, float(rec.ladder_power))
for k in range(len(rec.frames)):
    torch.as_tensor(rec.frames[k]).to(torch.float64)
"""


def _rel(a, b) -> float:
    """The largest |a - b| over the largest |b| (NaN where only one of them is NaN: a dead actuator's are NaN in both)."""
    a, b = np.asarray(a), np.asarray(b)
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        return float("nan")
    ok = ~np.isnan(b)
    scale = np.abs(b[ok]).max() if ok.any() else 0.0
    d = float(np.abs(a[ok] - b[ok]).max()) if ok.any() else 0.0
    return d / scale if scale > 0 else d


def _step(args: list, src: Path = HERE) -> tuple[int, float, float]:
    """``(exit status, seconds, peak resident GB)`` of ``python args`` run in ``src`` (``-c`` and ``-m`` put the
    working folder first on the path: its torchblur is the one run; paths in ``args`` absolute)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *args], env=env, stdout=subprocess.DEVNULL, cwd=src)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, time.perf_counter() - t0, usage.ru_maxrss * 1024 / 1e9  # ru_maxrss: kB on Linux


def _fit_settings(run: Path) -> list:
    """The ``fit.*`` settings of the run in folder ``run`` (its ``config.yaml``) as overrides: an outside recording
    does not carry them, and ``torchblur fit FOLDER`` takes them (docs/outside_recordings.md)."""
    from dataclasses import asdict

    from torchblur import load_config

    cfg = load_config(str(run / "config.yaml"), trusted=False, force=True)
    return [f"fit.{k}={json.dumps(v)}" for k, v in asdict(cfg.fit).items()]


def _worst(a: Path, b: Path) -> float:
    """The largest relative difference of any value of the csv/json/npy files under ``a/dm`` and ``b/dm`` (compare_runs)."""
    worst = 0.0
    for p in sorted((a / "dm").rglob("*")):
        if p.suffix in (".csv", ".json", ".npy"):
            worst = max(worst, compare_values(_read(p), _read(b / "dm" / p.relative_to(a / "dm")), p.name, 0.0, 0.0, []))
    return worst


def _compare(ref: Path, fit: Path, rc: tuple) -> None:
    from torchblur.identify.dm_outputs import read_actuators_csv
    from torchblur.sysid.frequency_response import FrequencyResponse

    a, b = (read_actuators_csv(k / "dm" / "actuators.csv") for k in (ref, fit))
    print(f"exit status: reference {rc[0]}, fit of the outside recording {rc[1]}")
    print(f"actuators: {len(a['actuator'])}; status identical: {list(a['status']) == list(b['status'])}")
    for col in COLUMNS:
        print(f"  {col}: largest |fit - reference| / max|reference| = {_rel(b[col], a[col]):.2e} (actuators.csv: 9 significant digits)")
    D0 = [np.load(k / "dm" / "interaction_matrix.npy") for k in (ref, fit)]
    D = [FrequencyResponse.from_json(k / "dm" / "frf.json").response for k in (ref, fit)]
    print(f"D0 (interaction_matrix.npy): {_rel(D0[1], D0[0]):.2e}; D(jw) (frf.json): {_rel(D[1], D[0]):.2e} (relative to the largest "
          f"element); bit for bit: {np.array_equal(D0[0], D0[1]) and np.array_equal(D[0], D[1])}")
    print(f"every value of dm/*.csv, *.json, *.npy: largest relative difference {_worst(ref, fit):.2e}")


def _export_against(recorded: str, root: Path, baseline: Path, steps: dict) -> None:
    """Export ``recorded`` with the ``baseline`` tree too (into ``root/outside_baseline``; its step added to ``steps``) and print
    both exports' times (each in its own process, one after the other: the call alone and the whole process) and whether
    every file of the two folders is the same byte for byte."""
    out = root / "outside_baseline"
    steps[f"export ({baseline})"] = run = _step(["-c", EXPORT, recorded, str(out), str(root / "export_baseline_s")], baseline)
    if run[0] != 0 or steps["export"][0] != 0:
        print(f"export: exit status {steps['export'][0]} (this tree), {run[0]} (baseline {baseline}); not compared")
        return
    names = sorted(p.name for p in (root / "outside").iterdir())
    same = names == sorted(p.name for p in out.iterdir()) and all(
        (root / "outside" / n).read_bytes() == (out / n).read_bytes() for n in names)
    t, tb = (float((root / n).read_text()) for n in ("export_s", "export_baseline_s"))
    print(f"export (two processes, one after the other): this tree {t:.2f} s, baseline {baseline} {tb:.2f} s (the call; "
          f"ratio {t / tb:.2f}; the processes {steps['export'][1]:.1f} s and {run[1]:.1f} s); the {len(names)} files "
          f"({', '.join(names)}) byte for byte the same: {same}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=None)
    ap.add_argument("--keep", default=None, help="keep the run, the recording and the fit in this folder")
    ap.add_argument("--run", default=None, help="a recorded DM run (its folder holds experiment/): its outputs are the reference")
    ap.add_argument("--refit", action="store_true", help="with --run: the reference is torchblur fit RUN")
    ap.add_argument("--baseline", default=None, help="a torchblur source tree whose `torchblur fit FOLDER` is measured too")
    ap.add_argument("--read", default=None, help="an outside DM recording: only what its fit does before the spot fits, measured")
    ap.add_argument("--export", default=None, help="a recorded DM run: only its export, by this tree and --baseline's")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    for name in ("config", "keep", "run", "baseline", "read", "export"):
        if getattr(args, name):
            setattr(args, name, str(Path(getattr(args, name)).resolve()))
    if args.read:
        for src in [HERE] + ([Path(args.baseline)] if args.baseline else []):
            rc, t, peak = _step(["-c", READ, args.read, *args.overrides], src)
            print(f"{src}: read {args.read}, calibrated, held images, every frequency's frames: exit status {rc}, {t:.1f} s, peak {peak:.2f} GB")
        return 0
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_dm_outside_"))
    for sub in ("live", "outside", "fit", "fit_baseline", "outside_baseline"):
        shutil.rmtree(root / sub, ignore_errors=True)
    if args.export:
        if not args.baseline:
            ap.error("--export needs --baseline SRC")
        steps = {"export": _step(["-c", EXPORT, args.export, str(root / "outside"), str(root / "export_s")])}
        _export_against(args.export, root, Path(args.baseline), steps)
        print(f"outside recording: {sum(p.stat().st_size for p in (root / 'outside').glob('*')) / 1e6:.2f} MB; peak: "
              + "; ".join(f"{k}: {m:.2f} GB" for k, (_, _, m) in steps.items()))
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
        return max(s[0] for s in steps.values())
    base = (["--config", args.config] if args.config else []) + (list(args.overrides) if args.config else SMALL + list(args.overrides))
    cli = ["-m", "torchblur.cli"]
    steps = {}
    ref = root / "live" if args.run is None or args.refit else Path(args.run)
    if args.run is None:
        steps["live run"] = _step(cli + ["identify", "--out", str(ref), "--quiet", *base])
    elif args.refit:
        steps["re-fit of the run"] = _step(cli + ["fit", str(args.run), "--out", str(ref), "--quiet"])
    recorded = str(root / "live" if args.run is None else args.run)
    steps["export"] = _step(["-c", EXPORT, recorded, str(root / "outside"), str(root / "export_s")])
    own = _fit_settings(root / "live" if args.run is None else Path(args.run))  # the run's fit.* (psf, loss, ...)
    steps["torchblur fit FOLDER"] = _step(cli + ["fit", str(root / "outside"), "--out", str(root / "fit"), "--quiet", *own])
    if args.baseline:
        steps[f"torchblur fit FOLDER ({args.baseline})"] = _step(cli + ["fit", str(root / "outside"), "--out", str(root / "fit_baseline"),
                                                                         "--quiet", *own], Path(args.baseline))
        _export_against(recorded, root, Path(args.baseline), steps)
    rc = {k: s[0] for k, s in steps.items()}
    if args.refit:
        print(f"live run {args.run} against its re-fit: every value of dm/ within {_worst(Path(args.run), ref):.2e} (relative)")
    _compare(ref, root / "fit", (rc.get("live run", rc.get("re-fit of the run", "(recorded)")), rc["torchblur fit FOLDER"]))
    if args.baseline:
        print(f"baseline {args.baseline}'s fit of the folder against this tree's: every value of dm/ within "
              f"{_worst(root / 'fit', root / 'fit_baseline'):.2e} (relative), exit status {rc[f'torchblur fit FOLDER ({args.baseline})']}")
    size = sum(p.stat().st_size for p in (root / "outside").iterdir())
    print(f"outside recording: {size / 1e6:.2f} MB in {root / 'outside'}")
    print("steps (each its own process): " + "; ".join(f"{k}: {t:.1f} s, peak {m:.2f} GB" for k, (_, t, m) in steps.items()))
    for name, out in (("the re-fit" if args.refit else "the run", ref), ("the folder's fit", root / "fit")):
        report = out / "report.txt"
        pace = [ln for ln in report.read_text().splitlines() if ln.startswith("dm fit pace:")] if report.is_file() else []
        print(f"{name}: {pace[0] if pace else 'no dm fit pace line'}")  # each frequency's spot-fit seconds against the camera
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if rc.get("live run", rc.get("re-fit of the run")) in (None, rc["torchblur fit FOLDER"]) else 1


if __name__ == "__main__":
    sys.exit(main())
