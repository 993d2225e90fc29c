"""The DM spot fitter on lenslet-like spots (issue 23): measured/true of the blur fit's amplitude
against the motion's size, with each spot's measured kernel (psf_from_still's choice) beside the
Gaussian fitted to the same still.

Frames (tests/sinc_spots.py): a 3x3 grid of sinc^2 spots (first zero 3 px, 16 px pitch, wings
crossing into the neighbouring subapertures: a crosstalk floor of about 1.4 % of the peak between
spots), every spot moving on its own sine per axis, motions of 0.5, 1, 2 and 3 px, 2 exposures
(0.3 and 0.8 periods), shot + 3 e- read noise at a 2000 e- peak; the still of ``--still`` frames.
Each spot's PSF from :func:`~torchblur.image.psf_from_still.psf_from_still` on its crop of the
still; all problems through :func:`~torchblur.dm.spot_fit.fit_spot_problems` with the kernels
(their own noise in the stds) and with the Gaussians. Printed per motion size: the mean of
measured/true with its standard error, rms(error/std) and the median spot-fit reduced chi2.

With ``--run``, instead: the 9-actuator test mirror of tests/test_dm_run.py (simulated
point-sampled Gaussian spots) identified end to end with ``fit.psf=auto`` (each spot's kernel where
its Gaussian fails its still's test) and with ``fit.psf=gaussian``: how many spots chose the
kernel, the errors against the simulated truth and the stages' times.

    python benchmarks/bench_dm_kernel.py [--points 6] [--still 256] [--seed 0]
    python benchmarks/bench_dm_kernel.py --run
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sinc_spots import sinc2_case  # noqa: E402

from torchblur.dm.spot_fit import fit_spot_problems  # noqa: E402
from torchblur.image.psf_from_still import psf_from_still  # noqa: E402
from torchblur.render.camera import camera_noise_std  # noqa: E402
from torchblur.render.psf import GaussianPSF, KernelPSF  # noqa: E402

MOTIONS = (0.5, 1.0, 2.0, 3.0)


def small_runs() -> None:
    """``--run``: the test mirror, fit.psf auto and gaussian (module docstring)."""
    from test_dm_run import SMALL

    from torchblur.identify.dm_plan import truth_errors
    from torchblur.identify.pipeline import identify
    from torchblur.config import load_config

    base = [k for k in SMALL if not k.startswith("fit.psf=")]
    for psf in ("auto", "gaussian"):
        t0 = time.perf_counter()
        res = identify(load_config(None, base + [f"fit.psf={psf}"]), progress=False)
        wall = time.perf_counter() - t0
        e = truth_errors(res)
        chose = [line for line in res.log if line.startswith("dm spots psf")] or ["dm spots psf: the Gaussian for every spot"]
        print(f"fit.psf={psf}: {chose[0]}")
        print(f"  mode {e['mode_hz_max_rel_error'] * 100:.3f} %, damping {e['damping_max_rel_error'] * 100:.2f} %, DC gain "
              f"{e['dc_gain_max_rel_error'] * 100:.3f} %, D0 {e['D0_rms_error_over_max'] * 100:.3f} % rms of max; rms(error/std) mode "
              f"{e['mode_hz_rms_z']:.2f}, damping {e['damping_rms_z']:.2f}, DC gain {e['dc_gain_rms_z']:.2f}; dead dead: "
              f"{e['dead_reported_dead']}; status {res.actuators.status}")
        print(f"  {wall:.1f} s wall ({', '.join(f'{k} {v:.1f} s' for k, v in res.timing_s.items())}), spot-fit reduced chi2 median "
              f"{float(torch.as_tensor(res.spot_reduced_chi2).nanmedian()):.3f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=6, help="points (frequencies) per motion size")
    ap.add_argument("--still", type=int, default=256, help="still frames")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--run", action="store_true", help="the 9-actuator test mirror end to end, fit.psf auto and gaussian")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.run:
        small_runs()
        return
    motions = [m for m in MOTIONS for _ in range(a.points)]
    c = sinc2_case(motions, n_still=a.still, seed=a.seed, freq_hz=torch.linspace(40.0, 1500.0, len(motions)))
    M = c["offset"].shape[0]
    still = [psf_from_still(c["still_crops"][:, m], c["still_s"], camera_noise_std(c["still_crops"][:, m].mean(0), 3.0), background=0.0)
             for m in range(M)]
    print(f"sinc^2 spots, 3x3 grid, {a.still} still frames, {a.points} points per motion size, {a.threads} thread(s), seed {a.seed}")
    print(f"psf_from_still per spot: {[s.kind for s in still].count('kernel')} of {M} chose the kernel (Gaussian reduced chi2 "
          f"{min(float(s.chi2_gaussian) for s in still):.3g}..{max(float(s.chi2_gaussian) for s in still):.3g}, threshold "
          f"{still[0].chi2_threshold:.3g})")
    g = [s.gaussian.psf for s in still]
    gauss = GaussianPSF(torch.stack([p.center for p in g]), torch.stack([p.cov for p in g]), torch.stack([p.amplitude for p in g]))
    kern = KernelPSF(torch.stack([s.kernel.kernel for s in still]))
    factor = still[0].kernel_noise_factor(c["window"].duration)[..., None]
    print(f"{'PSF':>8} {'motion px':>9} | {'measured/true':>18} | {'rms(err/std)':>12} {'mean(err/std)':>13} | {'chi2 median':>11}")
    for name, psf, kn in (("kernel", kern, factor), ("Gaussian", gauss, None)):
        t0 = time.perf_counter()
        fits = fit_spot_problems(c["crops"], psf, c["window"], c["omega"], noise_std=c["noise"], kernel_noise=kn)
        dt = time.perf_counter() - t0
        std = torch.stack([fits.covariance[0, ..., 0, 0], fits.covariance[0, ..., 2, 2]], -1).sqrt()
        z = ((fits.amplitude[0] - c["amplitude"]) / std).unflatten(0, (len(MOTIONS), a.points))
        r = (fits.amplitude[0] / c["amplitude"]).unflatten(0, (len(MOTIONS), a.points))
        chi = fits.reduced_chi2[0].unflatten(0, (len(MOTIONS), a.points))
        for i, m in enumerate(MOTIONS):
            ri = r[i].reshape(-1)
            print(f"{name:>8} {m:>9.1f} | {float(ri.mean()):.4f} +- {float(ri.std() / math.sqrt(ri.numel())):.4f} | "
                  f"{float(z[i].square().mean().sqrt()):>12.2f} {float(z[i].mean()):>13.2f} | {float(chi[i].median()):>11.2f}")
        print(f"{name:>8}: {fits.status.numel()} problems in {dt:.1f} s ({int((fits.status != 0).sum())} failed)")


if __name__ == "__main__":
    main()
