"""Which PSF each shipped identify config's calibration chooses now that every route takes the
measured kernel (issue 29), and what the per-spot choice costs (``identify.calibration.spot_kernels``).

For configs/identify_*.yaml except identify_dm.yaml (the DM keeps its Gaussian spots: issue 23):
the calibration on the config's simulated rig, its ``psf:`` / ``spots psf:`` lines, and its wall
time; for the many-spot config the calibration again without the per-spot choice
(``spot_psfs=False``, the code path before issue 29), alternating, best of ``--repeats``.
Where a config's calibration keeps the Gaussian, its run fits exactly as before.

With ``--runs``: every such config's whole identification (``identify``, simulated rig, no
figures written) with ``fit.psf=auto`` (the default) and with ``fit.psf=gaussian`` (the code
path before issue 29), alternating in one process, best of ``--repeats``: the PSF chosen, the
largest |H| error (%), phase error (deg) and error/std against the rig's truth, the points, and
the time ratio auto / gaussian. The other configs/*.yaml (fig*, beyond_precision,
learned_deblur) drive experiments/ scripts with their own Gaussian spot model: no ``fit.psf``.

    python benchmarks/bench_config_psf.py [--threads 1] [--repeats 2] [--runs [--only spots]]
"""
from __future__ import annotations

import argparse
import glob
import math
import time

import numpy as np
import torch

from torchblur.identify.calibration import calibrate
from torchblur.identify.record import collect_log
from torchblur.config import load_config
from torchblur.identify.run import build_simulated_rig, identify


def _calibrate(path: str, spot_psfs: bool):
    cfg = load_config(path)
    torch.manual_seed(int(cfg.seed))
    t = time.perf_counter()
    with collect_log() as log:
        cal = calibrate(cfg, build_simulated_rig(cfg), spot_psfs=spot_psfs)
    return time.perf_counter() - t, cal, [line for line in log if line.startswith(("psf:", "spots psf:"))]


def _identify(path: str, psf: str) -> tuple:
    """One run of the config with ``fit.psf=psf`` -> ``(wall s, the run's psf record, figures)``."""
    cfg = load_config(path, [f"fit.psf={psf}"])
    t = time.perf_counter()
    res = identify(cfg, progress=False)
    wall = time.perf_counter() - t
    frf = res.frf
    em, ep, z = frf.errors_against(res.truth)
    ok = np.isfinite(em)
    figs = (f"points {int(frf.valid.sum())}/{frf.valid.size}, max |H| error {100 * np.abs(em[ok]).max():.3f} %, "
            f"phase {np.degrees(np.abs(ep[ok])).max():.3f} deg, error/std {np.nanmax(z[ok]):.2f}")
    return wall, frf.meta.get("psf"), figs


def runs(repeats: int, only: str = "") -> None:
    """Every identify config (the DM's aside; with ``only``, those whose path holds it) with
    fit.psf=auto and fit.psf=gaussian, alternating."""
    identify(load_config(None, ["sweep.freq_hz=[10]", "model.max_order=2"]), progress=False)  # warm-up: imports, first calls
    for path in sorted(glob.glob("configs/identify_*.yaml")):
        if path.endswith("identify_dm.yaml") or only not in path:
            continue
        best, out = {"auto": math.inf, "gaussian": math.inf}, {}
        for _ in range(repeats):
            for psf in ("auto", "gaussian"):
                wall, rec, figs = _identify(path, psf)
                best[psf] = min(best[psf], wall)
                out[psf] = (rec, figs)
        print(f"{path}: auto {best['auto']:.1f} s, gaussian {best['gaussian']:.1f} s (ratio {best['auto'] / best['gaussian']:.2f})")
        for psf in ("auto", "gaussian"):
            print(f"    {psf:<8} psf {str(out[psf][0])[:70]}; {out[psf][1]}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--runs", action="store_true", help="whole runs, fit.psf=auto vs gaussian (else the calibrations)")
    ap.add_argument("--only", default="", help="only the configs whose path holds this")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch threads {args.threads}")
    if args.runs:
        runs(args.repeats, args.only)
        return
    _calibrate("configs/identify_default.yaml", False)  # warm-up: the process's imports and first calls
    for path in sorted(glob.glob("configs/identify_*.yaml")):
        if path.endswith("identify_dm.yaml") or args.only not in path:
            continue
        spots = load_config(path).spots.enabled
        best = {True: math.inf, False: math.inf}
        for _ in range(args.repeats):
            for flag in ((True, False) if spots else (True,)):
                wall, cal, lines = _calibrate(path, flag)
                best[flag] = min(best[flag], wall)
                if flag:
                    shown = lines
        extra = f"; without the per-spot choice {best[False]:.1f} s" if spots else ""
        print(f"{path}: calibration {best[True]:.1f} s{extra}")
        for line in shown:
            print(f"    {line[:160]}")


if __name__ == "__main__":
    main()
