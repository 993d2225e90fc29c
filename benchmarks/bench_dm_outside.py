"""A DM run's frames written as an outside DM recording and fitted by ``torchblur fit FOLDER``
give the live run's result (issue 23 part D; docs/outside_recordings.md, "Deformable-mirror
recordings").

Runs ``torchblur identify`` on a DM config (default: a 9-actuator mirror under 4 x 4
subapertures, the suite's tests/test_dm_run.py size; ``--config configs/identify_dm.yaml`` for the
shipped 52-actuator one), exports its recording (:func:`torchblur.identify.export_dm_recording`), fits
the folder with ``torchblur fit`` and prints: the largest relative difference of every actuator
column (actuators.csv, 9 significant digits), of D0 (interaction_matrix.npy) and of D(jw)
(frf.json) between the two, the folder's size, and the wall time of each step (threads: torch's
default; times are for this machine only).

    python benchmarks/bench_dm_outside.py [--config FILE] [--keep DIR] [overrides ...]
    python benchmarks/bench_dm_outside.py --run RUN     # a run recorded on any rig (torchblur.identify(cfg, rig, record=RUN/experiment))

With ``--run`` the reference is ``torchblur fit RUN`` (a re-fit of the recording gives the live
run's table bit for bit: docs/deformable_mirrors.md), so a run on a lab's or a test's rig (an HCIPy
Shack-Hartmann rig) is compared the same way.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

SMALL = ["dm.n_across=3", "dm.mode_hz=600.0", "dm.damping=0.1", "dm.mode_spread=0.05", "dm.dead=[2]", "dm.input_limit=10.0",
         "wfs.n_across=4", "wfs.pitch_px=16.0", "wfs.sigma_px=1.2", "dm_plan.kind=hadamard", "dm_plan.budget_frames=null",
         "dm_plan.n_repeats=1", "sweep.f_min_hz=50.0", "sweep.f_max_hz=1500.0", "sweep.n=8", "sweep.exposures=[0.3,0.8]",
         "excitation.target_px=3.0"]
COLUMNS = ("dc_gain", "dc_gain_std", "mode_hz", "mode_hz_std", "damping", "damping_std", "delay_s", "delay_s_std")


def _rel(a, b) -> float:
    """The largest |a - b| over the largest |b| (NaN where only one of them is NaN: a dead actuator's are NaN in both)."""
    a, b = np.asarray(a), np.asarray(b)
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        return float("nan")
    ok = ~np.isnan(b)
    scale = np.abs(b[ok]).max() if ok.any() else 0.0
    d = float(np.abs(a[ok] - b[ok]).max()) if ok.any() else 0.0
    return d / scale if scale > 0 else d


def main(argv=None) -> int:
    from torchblur.identify import export_dm_recording
    from torchblur.identify.dm_outputs import read_actuators_csv
    from torchblur.cli import main as cli
    from torchblur.sysid.frequency_response import FrequencyResponse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=None)
    ap.add_argument("--keep", default=None, help="keep the run, the recording and the fit in this folder")
    ap.add_argument("--run", default=None, help="a recorded DM run (its folder holds experiment/): re-fitted as the reference")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_dm_outside_"))
    for sub in ("live", "outside", "fit"):
        shutil.rmtree(root / sub, ignore_errors=True)
    base = (["--config", args.config] if args.config else []) + (list(args.overrides) if args.config else SMALL + list(args.overrides))
    t = {}
    t0 = time.perf_counter()
    if args.run is None:
        rc_live = cli(["identify", "--out", str(root / "live"), "--quiet", *base])
        t["live run"] = time.perf_counter() - t0
    else:
        rc_live = cli(["fit", str(args.run), "--out", str(root / "live"), "--quiet"])
        t["re-fit of the run"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    export_dm_recording(root / "live" if args.run is None else args.run, root / "outside")
    t["export"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rc_fit = cli(["fit", str(root / "outside"), "--out", str(root / "fit"), "--quiet"])
    t["torchblur fit FOLDER"] = time.perf_counter() - t0
    a, b = (read_actuators_csv(root / k / "dm" / "actuators.csv") for k in ("live", "fit"))
    print(f"exit status: live {rc_live}, fit of the outside recording {rc_fit}; torch threads {torch.get_num_threads()}")
    print(f"actuators: {len(a['actuator'])}; status identical: {list(a['status']) == list(b['status'])}")
    for col in COLUMNS:
        print(f"  {col}: largest |fit - live| / max|live| = {_rel(b[col], a[col]):.2e} (actuators.csv: 9 significant digits)")
    D0 = [np.load(root / k / "dm" / "interaction_matrix.npy") for k in ("live", "fit")]
    D = [FrequencyResponse.from_json(root / k / "dm" / "frf.json").response for k in ("live", "fit")]
    print(f"D0 (interaction_matrix.npy): {_rel(D0[1], D0[0]):.2e}; D(jw) (frf.json): {_rel(D[1], D[0]):.2e} (relative to the largest element)")
    size = sum(p.stat().st_size for p in (root / "outside").iterdir())
    print(f"outside recording: {size / 1e6:.2f} MB in {root / 'outside'}")
    print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()))
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if rc_live == rc_fit else 1


if __name__ == "__main__":
    sys.exit(main())
