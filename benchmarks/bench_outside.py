"""HCIPy diffraction spots written as outside recordings and run through `torchblur fit FOLDER`
(issue 15, "Outside recordings": the same frames give the same figures as the direct route).

The problems are benchmarks/bench_hcipy.py's (``tests/hcipy_frames.make_problem``, seeded: a
circular aperture with 0.05 wave rms of astigmatism and coma at 2.5 px per lambda/D, 20-800 Hz,
M 3-10 px, random phase and trigger phase, two exposures of 0.3 and 0.8 of the period, half
along x and half along 0.5 rad; background 20 e-/px, Poisson noise, 3 e- read noise; frames in
electrons). Two routes on the same frames:

- direct: ``psf_from_still(kind="auto")`` + ``fit_sinusoid`` along the true direction, noise
  model from the still frames, two passes (``hcipy_frames.fit_problems``, bench_hcipy's route);
  its std times ``StillPSF.kernel_noise_factor``;
- outside: each problem written as an outside recording (``tests/outside_folder.write_outside``:
  float TIFF stacks, ``--n-dark`` dark frames of the same background and noise (128 by default: 4
  per still frame, as docs/outside_recordings.md asks; 16 shows the dark's own noise), gain 1 e-/ADU,
  amplitude 1 input unit so that |H| is M in px), then ``torchblur fit FOLDER --out OUT``
  in-process (``torchblur.cli.main``) with the default settings: ``fit.psf=auto`` and
  ``fit.axis=measure`` (the direction from the sweep frames' second moments), or with
  ``--given-axis`` the true direction as ``fit.axis``.

Prints, per route: worst |M| error (%), worst |phase| error (deg), rms(error / std) of M and
phi, gross errors (|error| > 5 std, a status other than 0, or |phase error| > 30 deg); then the
largest difference between the routes (%, deg, and in the direct route's std).

    python benchmarks/bench_outside.py [--n 40] [--n-still 32] [--n-dark 128] [--n-time 2000] [--given-axis] [--threads 1]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import hcipy_frames as hf  # noqa: E402
from outside_folder import write_outside  # noqa: E402

from torchblur.cli import main as cli_main  # noqa: E402
from torchblur.sysid.frequency_response import FrequencyResponse  # noqa: E402


def fit_outside(problems: list, n_dark: int, given_axis: bool, seed: int) -> dict:
    """Each problem through `torchblur fit FOLDER`: arrays like ``hf.fit_problems``'s (the std
    already holds the kernel-noise factor) and the measured directions (rad)."""
    n = len(problems)
    amp, ph, amp_std, ph_std, angle = (np.full(n, np.nan) for _ in range(5))
    status = np.zeros(n)
    with tempfile.TemporaryDirectory(prefix="bench_outside_") as tmp:
        for k, p in enumerate(problems):
            rng = np.random.default_rng(10_000 + seed + k)
            dark = hf.camera_noise(np.zeros((n_dark,) + p["frames"].shape[-2:]), rng)
            folder = write_outside(Path(tmp) / f"rec{k}", dark=dark, still=p["still"], still_exposure_s=p["still_exposure"],
                                   camera=dict(gain_e_per_adu=1.0),
                                   points=[dict(freq_hz=p["freq_hz"], amplitude=1.0, frames=p["frames"],
                                                start_s=p["window"].start.numpy(), duration_s=p["window"].duration.numpy())])
            out = Path(tmp) / f"out{k}"
            argv = ["fit", str(folder), "--out", str(out), "--quiet", "--json"]
            if given_axis:
                argv.append(f"fit.axis=[{p['direction'][0]!r},{p['direction'][1]!r}]")
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
                rc = cli_main(argv)
            if rc != 0:
                print(f"  problem {k}: torchblur fit exited {rc}: {err.getvalue().strip()[-300:]}")
                status[k] = -1
                continue
            frf = FrequencyResponse.from_json(out / "frf.json")
            amp[k], ph[k] = frf.magnitude[0, 0, 0], frf.phase[0, 0, 0]
            amp_std[k], ph_std[k] = frf.magnitude_std[0, 0, 0], frf.phase_std[0, 0, 0]
            d = frf.meta["direction"]
            angle[k] = math.atan2(d[1], d[0])
            if not np.isfinite(amp[k]):
                status[k] = -1
    M = np.array([p["M"] for p in problems])
    dphi = np.angle(np.exp(1j * (ph - np.array([p["phi"] for p in problems]))))
    return dict(amp=amp, phase=ph, amp_std=amp_std, phase_std=ph_std, angle=angle, status=status, err_M_pct=100 * (amp - M) / M,
                err_phi_deg=np.degrees(dphi), z_M=(amp - M) / amp_std, z_phi=dphi / ph_std)


def figures(err_M_pct, err_phi_deg, z_M, z_phi, status) -> str:
    """One route's figures, one block of lines."""
    gross = (np.abs(z_M) > 5) | (np.abs(z_phi) > 5) | (status != 0) | (np.abs(err_phi_deg) > 30) | ~np.isfinite(z_M)
    return "\n".join([
        f"  worst |M| error      {np.nanmax(np.abs(err_M_pct)):.3f} %   (rms {np.sqrt(np.nanmean(err_M_pct ** 2)):.3f} %)",
        f"  worst |phase| error  {np.nanmax(np.abs(err_phi_deg)):.3f} deg (rms {np.sqrt(np.nanmean(err_phi_deg ** 2)):.3f} deg)",
        f"  rms(error/std)       M {np.sqrt(np.nanmean(z_M ** 2)):.3f}   phi {np.sqrt(np.nanmean(z_phi ** 2)):.3f}",
        f"  gross errors         {int(gross.sum())} of {gross.size}",
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--n-still", type=int, default=32)
    ap.add_argument("--n-dark", type=int, default=128)
    ap.add_argument("--n-time", type=int, default=2000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--given-axis", action="store_true", help="give the true direction as fit.axis (default: fit.axis=measure)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    problems = [hf.make_problem(args.seed + k, rotated=bool(k % 2), n_still=args.n_still, n_time=args.n_time) for k in range(args.n)]
    freqs, amps = np.array([p["freq_hz"] for p in problems]), np.array([p["M"] for p in problems])
    print(f"{args.n} HCIPy problems ({freqs.min():.0f}-{freqs.max():.0f} Hz, M {amps.min():.2f}-{amps.max():.2f} px, half along x, "
          f"half along 0.5 rad), {args.n_still} still and {args.n_dark} dark frames each, {args.n_time} time samples per exposure; "
          f"rendered in {time.perf_counter() - t0:.0f} s; torch threads {args.threads}")
    t = time.perf_counter()
    d = hf.fit_problems(problems, "auto")
    z_M, z_phi = d["z_M"] / d["factor"], d["z_phi"] / d["factor"]  # the std with the kernel's own noise, as identify reports it
    print(f"direct (psf_from_still kind='auto' + fit_sinusoid, true direction): {time.perf_counter() - t:.1f} s")
    print(figures(d["err_M_pct"], d["err_phi_deg"], z_M, z_phi, d["status"]))
    t = time.perf_counter()
    o = fit_outside(problems, args.n_dark, args.given_axis, args.seed)
    axis = "fit.axis = the true direction" if args.given_axis else "fit.axis=measure"
    print(f"outside recording through `torchblur fit FOLDER` ({axis}, fit.psf=auto): {time.perf_counter() - t:.1f} s")
    print(figures(o["err_M_pct"], o["err_phi_deg"], o["z_M"], o["z_phi"], o["status"]))
    if not args.given_axis:
        true = np.array([math.atan2(p["direction"][1], p["direction"][0]) for p in problems])
        print(f"  measured axis        worst error {np.degrees(np.nanmax(np.abs(o['angle'] - true))):.3f} deg")
    M = np.array([p["M"] for p in problems])
    amp_d = M * (1 + d["err_M_pct"] / 100)
    dm = np.abs(o["amp"] - amp_d)
    dp = np.abs(np.angle(np.exp(1j * (o["phase"] - np.array([p["phi"] for p in problems]) - np.radians(d["err_phi_deg"])))))
    std_m = np.abs((amp_d - M) / d["z_M"]) * d["factor"]  # the direct route's std of M (error / (error / std))
    std_p = np.abs(np.radians(d["err_phi_deg"]) / d["z_phi"]) * d["factor"]
    print("difference between the routes (outside - direct):")
    print(f"  worst |M| difference     {np.nanmax(100 * dm / M):.3f} %   ({np.nanmax(dm / std_m):.3f} direct std)")
    print(f"  worst |phase| difference {np.degrees(np.nanmax(dp)):.3f} deg ({np.nanmax(dp / std_p):.3f} direct std)")


if __name__ == "__main__":
    main()
