"""psf_from_still + fit_sinusoid on diffraction-limited spots from HCIPy (issue 15).

Each problem (``tests/hcipy_frames.make_problem``, seeded): a circular aperture with 0.035
wave rms of astigmatism and 0.035 of coma (0.05 wave rms), sampled at 2.5 px per lambda/D
(Airy core FWHM ~2.6 px) in a 48x64 frame; 20-800 Hz, M 3-10 px, random phase and trigger
phase; two exposures of 0.3 and 0.8 of the period from one start
(``design.dual_exposure_windows``); the motion along x (even seeds) or along 0.5 rad from x
(odd seeds), integrated with 2000 midpoint samples per exposure; the still spot averaged over
``--n-still`` frames (32 by default: half a second of a 60 fps camera) of peak 3000 e-; the
source set for a peak of 4000 e- in the longer exposure; background 20 e-/px, Poisson noise
and 3 e- read noise. Every frame in electrons.

Routes, each with the noise model (``var = c0 + c1 * value``) the still frames measured,
fitted twice (weights from the first fit's model): ``kind="auto"`` (the PSF psf_from_still
chooses: the kernel on these spots), and ``kind="gaussian"`` (a 2-D Gaussian fitted to the
same still, point-sampled pixels) for contrast. Prints worst |M| error (%), worst |phase|
error (deg), rms(error / std) of M and phi (also with the std times
``StillPSF.kernel_noise_factor``, the rule for the kernel's own noise), gross errors
(|error| > 5 std, a status other than 0, or |phase error| > 30 deg) and the PSF choice.

    python benchmarks/bench_hcipy.py [--n 40] [--n-still 32] [--n-time 2000] [--light 1] [--known-background] [--threads 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import hcipy_frames as hf  # noqa: E402


def summary(out: dict) -> str:
    """The benchmark's figures of one route, one block of lines."""
    gross = (np.abs(out["z_M"]) > 5) | (np.abs(out["z_phi"]) > 5) | (out["status"] != 0) | (np.abs(out["err_phi_deg"]) > 30)
    kinds = {k: out["kinds"].count(k) for k in sorted(set(out["kinds"]))}
    return "\n".join([
        f"  worst |M| error      {np.abs(out['err_M_pct']).max():.3f} %   (rms {np.sqrt(np.mean(out['err_M_pct'] ** 2)):.3f} %)",
        f"  worst |phase| error  {np.abs(out['err_phi_deg']).max():.3f} deg (rms {np.sqrt(np.mean(out['err_phi_deg'] ** 2)):.3f} deg)",
        f"  rms(error/std)       M {np.sqrt(np.mean(out['z_M'] ** 2)):.3f}   phi {np.sqrt(np.mean(out['z_phi'] ** 2)):.3f}",
        f"  with the kernel-noise factor (median {np.median(out['factor']):.3f}): rms(error/std) "
        f"M {np.sqrt(np.mean((out['z_M'] / out['factor']) ** 2)):.3f}   phi {np.sqrt(np.mean((out['z_phi'] / out['factor']) ** 2)):.3f}",
        f"  fit reduced chi2     median {np.median(out['reduced_chi2']):.3f}  (range {out['reduced_chi2'].min():.3f}-{out['reduced_chi2'].max():.3f}; "
        f"{int((out['reduced_chi2'] > 1.5).sum())} above 1.5)",
        f"  gross errors         {int(gross.sum())} of {gross.size}",
        f"  PSF chosen           {kinds}; reduced chi2 of the still: Gaussian median {np.median(out['chi2_gaussian']):.3g}, "
        f"kernel (light left out) median {np.median(out['chi2_kernel']):.3g}",
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--n-still", type=int, default=32)
    ap.add_argument("--n-time", type=int, default=2000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--known-background", action="store_true", help="give psf_from_still the 20 e- level (bright spots fill the frame)")
    ap.add_argument("--light", type=float, default=1.0, help="scale both peaks (3000 e- still, 4000 e- blurred): the model's floor")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    problems = [hf.make_problem(args.seed + k, rotated=bool(k % 2), n_still=args.n_still, n_time=args.n_time,
                                still_peak=3000.0 * args.light, blur_peak=4000.0 * args.light) for k in range(args.n)]
    t1 = time.perf_counter()
    freqs = np.array([p["freq_hz"] for p in problems])
    amps = np.array([p["M"] for p in problems])
    print(f"{args.n} HCIPy problems ({freqs.min():.0f}-{freqs.max():.0f} Hz, M {amps.min():.2f}-{amps.max():.2f} px, half along x, "
          f"half along 0.5 rad), light x{args.light:g}, {args.n_still} still frames each, {args.n_time} time samples per exposure; "
          f"rendered in {t1 - t0:.0f} s; torch threads {args.threads}")
    for kind, label in (("auto", "psf_from_still (kind='auto')"), ("gaussian", "Gaussian route (kind='gaussian')")):
        t = time.perf_counter()
        out = hf.fit_problems(problems, kind, background=20.0 if args.known_background else None)
        print(f"{label}: fitted in {time.perf_counter() - t:.1f} s")
        print(summary(out))


if __name__ == "__main__":
    main()
