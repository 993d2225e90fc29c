"""The measured PSF on every route (issue 29): multisine, direct model and a 3x3 many-spot grid on
HCIPy diffraction spots, the PSF psf_from_still chooses (the kernel) beside a forced Gaussian.

Problems, optics and fits: ``tests/hcipy_routes.py`` (its docstring). Goals (the one-spot route's,
``benchmarks/bench_hcipy.py``): worst |M| error 1 % and worst |phase| error 1 deg (multisine tones,
every spot and axis of the grid); the direct model's resonance within 0.5 % (frequency) and 5 %
(damping); rms(error / std) between 0.8 and 1.3 (stds times ``StillPSF.kernel_noise_factor``);
no gross error (|error| > 5 std, a fit status other than 0, or |phase error| > 30 deg).

The Gaussian route's multisine fit skips the wider retry search that a fit far above its noise
triggers (``fit.multisine.RETRY_CHI2``; about 100 s a problem here, and its result is the same
model mismatch): its figures are its best case.

    python benchmarks/bench_hcipy_routes.py [--n 40] [--routes multisine,direct,spots] [--threads 1] [--seed0 1000]
    # the figures in docs/measured_psf.md: each route's 40 seeds in parts run in parallel, then merged
    python benchmarks/bench_hcipy_routes.py --routes spots --n 10 --seed0 1000 --save spots0.npz   # ... 1010, 1020, 1030
    python benchmarks/bench_hcipy_routes.py --merge multisine*.npz direct*.npz spots*.npz
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
    return (f"  {label:<22} {np.abs(out['err_M_pct']).max():8.3f} {np.abs(out['err_phi_deg']).max():9.3f} "
            f"{_rms(out['z_M']):8.3f} {_rms(out['z_phi']):8.3f} {int(gross.sum()):4d}/{gross.size:<4d} "
            f"{np.median(out['reduced_chi2']):8.3f} {float(out['wall']):8.1f}   chosen {sorted(set(out['kinds'].tolist()))}"
            + (f", kernel-noise factor {np.median(out['factor']):.3f}" if "factor" in out else ""))


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--routes", default="multisine,direct,spots")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed0", type=int, default=1000)
    ap.add_argument("--save", help="also save one route's results (npz) for --merge")
    ap.add_argument("--no-time-check", action="store_true", help="skip the check of the frames' time rule (two extra problems)")
    ap.add_argument("--merge", nargs="+", help="print the tables of saved runs (e.g. parts of the seeds run in parallel)")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge)
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
