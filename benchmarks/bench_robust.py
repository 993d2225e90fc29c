"""Reliability (issue 8): the bad-input contract and robust fits with injected defects.

Prints, measured in one run:
- the contract: how many distinct bad inputs (tests/test_bad_input.py and
  tests/test_bad_input_contract.py) raise the contracted exception, naming the argument,
  from torchblur's own check; how many degenerate items are flagged;
- for each defect (hot pixels with and without a dark-frame map, cosmic rays, partial
  saturation, a stray-light plane, a spot partly out of the frame), over ``--seeds`` seeds of
  6 dual-exposure designs each (28x36 frames, 1% noise): the largest |error| / reported std
  of (M, phi) with the robust option and without it, the share of items flagged, and the
  time of the robust fit relative to a clean fit of the same designs.

    python benchmarks/bench_robust.py [--seeds 4] [--threads 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_robust_fit import N, add_cosmic_rays, hot_pixel_scene, make, zmax  # noqa: E402

from torchblur.fit.sinusoid import fit_sinusoid  # noqa: E402
from torchblur.fit.status import MASKED, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED  # noqa: E402


def contract():
    import test_bad_input
    import test_bad_input_contract as c

    ok = total = 0
    for table in (test_bad_input.CASES, c.BAD):
        for case in table:
            _, fn, exc, name = case
            total += 1
            try:
                fn()
            except exc as e:
                ok += int(type(e) is exc and name in str(e) and c._raised_in_torchblur(e))
            except Exception:  # noqa: BLE001 - counted as a failure of the contract
                pass
    beyond = sum(1 for b in c.BAD if not b[0].startswith("fit ")) + len(test_bad_input.CASES)
    print(f"contract: {ok}/{total} bad inputs raise the contracted error from torchblur's own check "
          f"({beyond} outside the fitter); {len(c.DEGENERATE)} degenerate cases are flagged in tests/test_bad_input_contract.py")


def scenes(seed):
    """(name, data, robust options, plain options, flag the robust fit must set)."""
    d = hot_pixel_scene(seed)
    yield "hot pixels, dark-frame map", d, dict(noise_std=d["sigma"], mask=~d["dark"].hot_pixels), dict(noise_std=d["sigma"]), MASKED
    yield "hot pixels, no map", d, dict(noise_std=d["sigma"], outliers="reject"), dict(noise_std=d["sigma"]), OUTLIERS_MASKED
    d = add_cosmic_rays(make(seed + 100))
    yield "cosmic rays (noise given)", d, dict(noise_std=d["sigma"], outliers="reject"), dict(noise_std=d["sigma"]), OUTLIERS_MASKED
    yield "cosmic rays (noise estimated)", d, dict(outliers="reject"), dict(), OUTLIERS_MASKED
    d = make(seed + 200)
    level = 0.6 * d["peak"]
    d["images"] = torch.minimum(d["images"], level[:, None, None, None])
    yield "saturated core (60% of peak)", d, dict(noise_std=d["sigma"], saturation_level=level), dict(noise_std=d["sigma"]), SATURATED_MASKED
    d = make(seed + 300)
    H, W = d["images"].shape[-2:]
    y = torch.arange(H, dtype=torch.float64)[:, None]
    x = torch.arange(W, dtype=torch.float64)[None, :]
    d["images"] = d["images"] + d["peak"][:, None, None, None] * (0.1 + 0.01 * (x - 10) + 0.004 * (y - 5))
    yield "stray-light plane", d, dict(noise_std=d["sigma"], fit_gradient=True), dict(noise_std=d["sigma"], fit_background=True), 0
    d = make(seed + 400, center=(2.5, 13.5), M_range=(4.0, 7.0))
    yield "spot partly out of frame", d, dict(noise_std=d["sigma"]), None, PARTLY_OUT_OF_FRAME


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.seeds} seeds x {N} designs per defect")
    contract()
    rows = {}
    for seed in range(args.seeds):
        clean = make(seed + 500)
        t = time.perf_counter()
        fit_sinusoid(clean["images"], clean["psf"], clean["win"], clean["om"], noise_std=clean["sigma"])
        t_clean = time.perf_counter() - t
        for name, d, robust, plain, flag in scenes(seed):
            r = rows.setdefault(name, dict(z=0.0, z_plain=0.0, flagged=0, n=0, t=0.0, t_clean=0.0, status_ok=0, flag=flag))
            t = time.perf_counter()
            res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], **robust)
            r["t"] += time.perf_counter() - t
            r["t_clean"] += t_clean
            r["z"] = max(r["z"], float(zmax(res, d).max()))
            r["flagged"] += int(((res.flags & flag) != 0).sum())
            r["status_ok"] += int((res.status == 0).sum())
            r["n"] += N
            if plain is not None:
                p = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], **plain)
                r["z_plain"] = max(r["z_plain"], float(torch.nan_to_num(zmax(p, d), nan=float("inf")).max()))
    print(f"{'defect':34s} {'max|err|/std':>12s} {'without':>10s} {'flagged':>9s} {'status 0':>9s} {'time/clean':>10s}")
    for name, r in rows.items():
        without = f"{r['z_plain']:10.1f}" if r["z_plain"] else f"{'-':>10s}"
        flagged = f"{r['flagged']:4d}/{r['n']:<4d}" if r["flag"] else f"{'-':>9s}"
        print(f"{name:34s} {r['z']:12.2f} {without} {flagged} {r['status_ok']:4d}/{r['n']:<4d} {r['t'] / r['t_clean']:10.2f}")


if __name__ == "__main__":
    main()
