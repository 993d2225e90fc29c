"""The measured PSF on every route (issue 29): multisine, direct model and a 3x3 many-spot grid on
HCIPy diffraction spots, the PSF psf_from_still chooses (the kernel) beside a forced Gaussian.

Problems, optics and fits: ``tests/hcipy_routes.py`` (its docstring). Goals (the one-spot route's,
``benchmarks/bench_hcipy.py``): worst |M| error 1 % and worst |phase| error 1 deg (multisine tones,
every spot and axis of the grid); the direct model's resonance within 0.5 % (frequency) and 5 %
(damping); rms(error / std) between 0.8 and 1.3 (the kernel's own noise in the stds: propagated
exactly on the multisine route, ``fit_multisine(kernel_var=)``, whose line also shows the scalar
rule ``StillPSF.kernel_noise_factor`` it replaced; that rule on the direct and many-spot routes);
no gross error (|error| > 5 std, a fit status other than 0, or |phase error| > 30 deg).

The Gaussian route's multisine fit skips the wider retry search that a fit far above its noise
triggers (``fit.multisine.RETRY_CHI2``; about 100 s a problem here, and its result is the same
model mismatch): its figures are its best case.

    python benchmarks/bench_hcipy_routes.py [--n 40] [--routes multisine,direct,spots] [--threads 1] [--seed0 1000]
    python benchmarks/bench_hcipy_routes.py --jobs 15     # the same figures, the seeds in parts over 15 processes
    # the figures in docs/measured_psf.md: --jobs 15 --save-dir parts (61 s on 16 cores), the grids of
    # seeds 1034-1035 again after the locate_spots fix, then merged
    python benchmarks/bench_hcipy_routes.py --routes spots --n 2 --seed0 1034 --save spots_1034.npz
    python benchmarks/bench_hcipy_routes.py --merge parts/direct_*.npz parts/multisine_*.npz parts/spots_10[0-2]*.npz \
        parts/spots_103[0268].npz spots_1034.npz

A grid where ``locate_spots`` does not find the 9 spots counts its 18 channels as gross errors.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import hcipy_routes as hr  # noqa: E402
import torchblur.fit.multisine as ms  # noqa: E402


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


LABELS = (("auto", "psf_from_still (auto)"), ("gaussian", "Gaussian (forced)"))
HEAD = (f"  {'PSF':<22} {'|M| %':>8} {'|phi| deg':>9} {'rms zM':>8} {'rms zphi':>8} {'gross':>9} {'chi2 med':>8} {'fit s':>8}")
HEAD_D = (f"  {'PSF':<22} {'|f| %':>8} {'|zeta| %':>9} {'rms zf':>8} {'rms zz':>8} {'gross':>9} {'chi2 med':>8} {'fit s':>8}")


def tone_line(label: str, out: dict) -> str:
    """One PSF's line of (M, phase) figures: multisine tones or every spot's two axes."""
    status = out["status"]
    status = np.broadcast_to(status.reshape(status.shape + (1,) * (out["z_M"].ndim - status.ndim)), out["z_M"].shape)
    gross = (np.abs(out["z_M"]) > 5) | (np.abs(out["z_phi"]) > 5) | (np.abs(out["err_phi_deg"]) > 30) | (status != 0)
    lost = int((out["found"] != 9).sum()) if "found" in out else 0  # grids whose spots were not all found: every channel gross
    gross_n, size = int(gross.sum()) + 18 * lost, gross.size + 18 * lost
    return (f"  {label:<22} {np.abs(out['err_M_pct']).max():8.3f} {np.abs(out['err_phi_deg']).max():9.3f} "
            f"{_rms(out['z_M']):8.3f} {_rms(out['z_phi']):8.3f} {gross_n:4d}/{size:<4d} "
            f"{np.median(out['reduced_chi2']):8.3f} {float(out['wall']):8.1f}   chosen {sorted(set(out['kinds'].tolist()))}"
            + (f"\n  {'':<22} ({lost} grid(s) where locate_spots found {sorted(set(out['found'][out['found'] != 9].tolist()))} "
               f"spots, not 9: their 18 channels counted gross)" if lost else "")
            + (f"\n  {'':<22} (the scalar rule instead: the data's stds times the kernel-noise factor, median "
               f"{np.median(out['factor']):.3f}: rms zM {_rms(out['zrule_M']):.3f}, zphi {_rms(out['zrule_phi']):.3f})"
               if "zrule_M" in out and np.median(out["factor"]) > 1 else ""))


def direct_line(label: str, out: dict) -> str:
    """One PSF's line of the direct model's resonance figures."""
    gross = (np.abs(out["z_f"]) > 5) | (np.abs(out["z_zeta"]) > 5) | ~out["converged"].astype(bool)
    return (f"  {label:<22} {np.abs(out['err_f_pct']).max():8.3f} {np.abs(out['err_zeta_pct']).max():9.3f} {_rms(out['z_f']):8.3f} "
            f"{_rms(out['z_zeta']):8.3f} {int(gross.sum()):4d}/{gross.size:<4d} {np.median(out['reduced_chi2']):8.3f} "
            f"{float(out['wall']):8.1f}   chosen {sorted(set(out['kinds'].tolist()))}")


def _arrays(d: dict, wall: float) -> dict:
    out = {k: np.asarray(v) for k, v in d.items()}
    out["wall"] = np.asarray(wall)
    return out


def fit_route(route: str, problems: list, kind: str) -> dict:
    """One route's fits of ``problems`` with ``psf_from_still(kind=kind)`` -> arrays (and the fit time)."""
    t = time.perf_counter()
    if route == "multisine":
        saved = ms.RETRY_CHI2
        ms.RETRY_CHI2 = math.inf if kind == "gaussian" else saved
        try:
            out = hr.fit_multisine_problems(problems, kind)
        finally:
            ms.RETRY_CHI2 = saved
    elif route == "spots":
        out = hr.fit_spots_problems(problems, kind)
    else:
        outs = [hr.fit_direct_problem(p, kind) for p in problems]
        out = {k: [o[k] for o in outs] for k in outs[0]}
        out["kinds"] = out.pop("kind")
    return _arrays(out, time.perf_counter() - t)


MAKE = {"multisine": hr.multisine_problem, "direct": hr.direct_problem, "spots": hr.spots_problem}
WHAT = {"multisine": "problems x 3 tones, 12 frames each", "direct": f"sweeps of {hr.N_POINTS} points x 2 exposures",
        "spots": f"grids of 3x3 spots x 2 axes, {2 * hr.REPEATS} frames each"}
GOALS = {"multisine": "|M| 1 %, |phi| 1 deg", "spots": "|M| 1 %, |phi| 1 deg", "direct": "|f| 0.5 %, |zeta| 5 %"}


def report(route: str, results: dict, n: int) -> None:
    print(f"{route}: {n} {WHAT[route]}")
    print(HEAD_D if route == "direct" else HEAD)
    for kind, label in LABELS:
        print((direct_line if route == "direct" else tone_line)(label, results[kind]))
    print(f"  goals: {GOALS[route]}, rms z 0.8-1.3, no gross error", flush=True)


def merge(files: list) -> None:
    """Print the tables of runs saved with ``--save`` (problems concatenated, fit times added)."""
    by_route = {}
    for f in files:
        z = np.load(f, allow_pickle=False)
        route, n = str(z["route"]), int(z["n"])
        cur = by_route.setdefault(route, {"n": 0, "res": {k: {} for k, _ in LABELS}})
        cur["n"] += n
        for kind, _ in LABELS:
            for key in [k[len(kind) + 1:] for k in z.files if k.startswith(kind + "/")]:
                v = z[f"{kind}/{key}"]
                old = cur["res"][kind].get(key)
                cur["res"][kind][key] = v if old is None else (old + v if key == "wall" else np.concatenate([old, v]))
    for route, cur in by_route.items():
        report(route, cur["res"], cur["n"])
        print()


def _part(route: str, seed0: int, n: int) -> tuple:
    """One part of a run (a worker process, 1 torch thread): ``(route, n, {kind: arrays})``."""
    torch.set_num_threads(1)
    problems = [MAKE[route](s) for s in range(seed0, seed0 + n)]
    return route, n, {kind: fit_route(route, problems, kind) for kind, _ in LABELS}


def run_parallel(routes: list, n: int, seed0: int, jobs: int, save_dir: str | None = None) -> None:
    """Every route's ``n`` problems in parts of a few seeds over ``jobs`` worker processes (the
    longest parts first), then each route's table as :func:`merge` prints it (fit times added);
    each part also saved in ``save_dir`` (for ``--merge``) as it ends, if given."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    chunk = {"spots": 2, "multisine": 4, "direct": 8}
    parts = [(r, s, min(chunk[r], seed0 + n - s)) for r in routes for s in range(seed0, seed0 + n, chunk[r])]
    by_route = {r: {"n": 0, "res": {k: {} for k, _ in LABELS}} for r in routes}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(jobs) as pool:
        futures = {pool.submit(_part, *p): p for p in parts}
        for fut in as_completed(futures):
            route, m, res = fut.result()
            print(f"  (part {route} seeds {futures[fut][1]}+{m} done at {time.perf_counter() - t0:.0f} s)", flush=True)
            if save_dir:
                np.savez(Path(save_dir) / f"{route}_{futures[fut][1]}.npz", route=route, n=m,
                         **{f"{k}/{key}": v for k, r in res.items() for key, v in r.items()})
            cur = by_route[route]
            cur["n"] += m
            for kind, arrays in res.items():
                for key, v in arrays.items():
                    old = cur["res"][kind].get(key)
                    cur["res"][kind][key] = v if old is None else (old + v if key == "wall" else np.concatenate([old, v]))
    for route in routes:
        report(route, by_route[route]["res"], by_route[route]["n"])
        print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--routes", default="multisine,direct,spots")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed0", type=int, default=1000)
    ap.add_argument("--save", help="also save one route's results (npz) for --merge")
    ap.add_argument("--no-time-check", action="store_true", help="skip the check of the frames' time rule (two extra problems)")
    ap.add_argument("--merge", nargs="+", help="print the tables of saved runs (e.g. parts of the seeds run in parallel)")
    ap.add_argument("--save-dir", help="with --jobs: save every part (npz) in this folder as it ends, for --merge")
    ap.add_argument("--jobs", type=int, default=0, help="run the routes' seeds in parts over this many processes (1 thread each)")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge)
        return
    if args.jobs:
        print(f"{args.jobs} worker processes, 1 torch thread each; seeds {args.seed0}..{args.seed0 + args.n - 1}; fit s: summed over parts")
        run_parallel(args.routes.split(","), args.n, args.seed0, args.jobs, args.save_dir)
        return
    torch.set_num_threads(args.threads)
    check = "" if args.no_time_check else (f"; time rule: a multisine frame changes by {hr.time_convergence(args.seed0):.1e} of "
                                           f"peak with twice the panels")
    print(f"torch threads {args.threads}; seeds {args.seed0}..{args.seed0 + args.n - 1}{check}")
    for route in args.routes.split(","):
        t = time.perf_counter()
        problems = [MAKE[route](s) for s in range(args.seed0, args.seed0 + args.n)]
        print(f"  ({route}: problems made in {time.perf_counter() - t:.0f} s)")
        results = {kind: fit_route(route, problems, kind) for kind, _ in LABELS}
        report(route, results, len(problems))
        if args.save:
            np.savez(args.save, route=route, n=len(problems), **{f"{k}/{key}": v for k, r in results.items() for key, v in r.items()})
        print(f"  ({route}: {time.perf_counter() - t:.0f} s in all)\n", flush=True)


if __name__ == "__main__":
    main()
