"""Issue 26's figures: untrusted input refused before any work.

Prints (1) the time each absurd DM size takes to be refused and the key it names (in this
process, after the imports: the closed-form bounds, no geometry computed); (2) each TIFF header
bomb's refusal time and the peak memory Python and numpy allocated before it (tracemalloc);
(3) the peak memory of reading a clean 2 MiB TIFF with a 4 GiB limit (the old reader reserved
limit + 1 bytes) and whether a clean outside recording reads under a 4.5 GB address-space cap (a
child process); (4) the battery's cases per surface (tests/test_untrusted_battery.py), run with
pytest, and its outcome. One thread.

    python benchmarks/bench_untrusted.py
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import tifffile
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
torch.set_num_threads(1)

ABSURD = [["dm.n_across=64", "wfs.n_across=128"], ["dm.n_across=16", "wfs.n_across=32"], ["wfs.pitch_px=1e6"],
          ["dm_plan.n_repeats=1e9"], ["dm_plan.budget_frames=1e9"], ["sweep.n=1e12", "dm_plan.n_repeats=1"]]


def sizes() -> None:
    from torchblur.errors import ConfigError
    from torchblur.config import load_config

    load_config(None)  # imports and OmegaConf warmed up
    print("1. absurd DM sizes (configs/identify_dm.yaml + overrides): refusal time, key named")
    for o in ABSURD:
        t0 = time.perf_counter()
        try:
            load_config(str(ROOT / "configs" / "identify_dm.yaml"), o)
            msg = "ACCEPTED"
        except ConfigError as exc:
            msg = str(exc).split(":")[0]
        print(f"   {' '.join(o):45s} {time.perf_counter() - t0:6.3f} s  -> {msg}")


def bombs(tmp: Path) -> None:
    from test_untrusted_battery import BOMBS

    from torchblur.hardware.recording import decode_tiff

    print("2. TIFF header bombs: refusal time, peak allocation before the refusal")
    for name, make in BOMBS.items():
        p = tmp / "bomb.tif"
        make(p)
        data = p.read_bytes()
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            decode_tiff(data, "bomb.tif")
            msg = "DECODED"
        except Exception as exc:  # noqa: BLE001 - printed
            msg = f"{type(exc).__name__}: {str(exc)[:70]}"
        dt = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        print(f"   {name:32s} {len(data):6d} B  {dt * 1e3:7.1f} ms  peak {peak / 2**20:6.2f} MiB  {msg}")


def reads(tmp: Path) -> None:
    from torchblur.files import read_bounded

    p = tmp / "clean.tif"
    tifffile.imwrite(p, np.random.default_rng(0).integers(0, 4096, (16, 256, 256), dtype=np.uint16), photometric="minisblack")
    tracemalloc.start()
    read_bounded(p, 4 * 1024**3, "clean.tif")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"3. read_bounded of a clean {p.stat().st_size / 2**20:.1f} MiB TIFF, limit 4 GiB: peak {peak / 2**20:.2f} MiB")
    from outside_folder import write_outside

    rng = np.random.default_rng(1)
    fr = lambda n: np.round(100 + 5 * rng.standard_normal((n, 64, 64)))  # noqa: E731
    folder = write_outside(tmp / "rec", dark=fr(4), still=fr(2), still_exposure_s=1e-3,
                           points=[{"freq_hz": 37.0, "amplitude": 0.5, "frames": fr(2), "start_s": np.zeros(2),
                                    "duration_s": np.array([0.3, 0.8]) / 37.0}], camera={"gain_e_per_adu": 2.0}, dtype=np.uint16)
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (4_500_000_000, 4_500_000_000)); "
            "from torchblur.hardware.outside import read_outside_recording; "
            f"r = read_outside_recording({str(folder)!r}); print(r.n_frames)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                         timeout=300)
    tail = (res.stdout.strip() or res.stderr.strip().splitlines()[-1] if (res.stdout or res.stderr) else "")
    print(f"   a clean outside recording under a 4.5 GB address-space cap: exit {res.returncode}, {tail[:100]}")


def battery() -> None:
    from collections import Counter

    res = subprocess.run([sys.executable, "-m", "pytest", str(ROOT / "tests" / "test_untrusted_battery.py"), "-p", "no:randomly",
                          "-q", "--collect-only", "-o", "addopts="], capture_output=True, text=True, cwd=ROOT, timeout=600)
    ids = [ln.split("::")[1].split("[")[0] for ln in res.stdout.splitlines() if "::" in ln]
    print(f"4. the battery: {len(ids)} cases")
    for name, n in Counter(ids).most_common():
        print(f"   {n:4d}  {name}")
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "pytest", str(ROOT / "tests" / "test_untrusted_battery.py"), "-p", "no:randomly"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    last = [ln for ln in run.stdout.splitlines() if "passed" in ln or "failed" in ln]
    print(f"   pytest: {last[-1] if last else run.stdout[-300:]} ({time.perf_counter() - t0:.1f} s with the imports); every "
          f"passing case counts 0 reads outside, 0 contents echoed, 0 hangs > 10 s, 0 tracebacks, 0 allocations beyond 64 MiB "
          f"before refusal, 0 silent wrong results, 0 frames lost")


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as d:
        sizes()
        bombs(Path(d))
        reads(Path(d))
    battery()
