"""Is fit_sinusoid's amplitude biased at low light? (issue 24, item "low-light amplitude bias")

Renders a 6 px sine motion of a Gaussian spot (sigma 2 px, 40x40 frame, exposures 0.3 and 0.8 of
the period starting at phase pi/2, as identify's default), adds Poisson shot noise and 5 e- Gaussian
read noise, and fits ``--n`` images per case in one batch with
:func:`torchblur.fit.sinusoid.fit_sinusoid` given the camera's noise model (``noise=CameraNoise``:
loss l2 weighted by the noise of a first fit's model, and loss poisson). Prints per peak rate
(e-/s of the still spot's peak) and frequency: the mean amplitude (px) with the std of that mean,
the bias in units of the mean's std, the rms of (M - 6) / amplitude_std and of the phase's
error / phase_std, the mean reduced chi2 and how many items failed; then the same over the items
not flagged ``BRANCH_UNDECIDED`` (the exposures do not decide the phase branch at this light) and
how many were flagged.

    python benchmarks/bench_low_light.py [--n 200] [--threads 1]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

import torchblur as tb
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.fit.status import BRANCH_UNDECIDED
from torchblur.render.camera import CameraNoise

F64 = torch.float64
TRUE_M, PHASE, SIGMA, SIZE, READ = 6.0, 0.4, 2.0, 40, 5.0


def images(n: int, peak_rate: float, freq_hz: float, seed: int):
    """``(noisy [n, 2, H, W] e-, psf, window, omega)`` of the case."""
    om = 2 * math.pi * freq_hz
    period = 1.0 / freq_hz
    win = tb.ExposureWindow(torch.full((n, 2), (math.pi / 2) / om, dtype=F64), torch.tensor([[0.3 * period, 0.8 * period]] * n, dtype=F64))
    c = torch.full((n, 2), (SIZE - 1) / 2, dtype=F64)
    psf = tb.GaussianPSF(c, (SIGMA**2 * torch.eye(2, dtype=F64)).expand(n, 2, 2), torch.full((n,), peak_rate, dtype=F64))
    traj = tb.Sinusoid(torch.tensor([TRUE_M, 0.0], dtype=F64).expand(n, 1, 2), torch.full((n, 1, 2), PHASE, dtype=F64),
                       torch.full((n, 1), om, dtype=F64))
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None], psf.amplitude[:, None]), win,
                           height=SIZE, width=SIZE)
    g = torch.Generator().manual_seed(seed)
    noisy = torch.poisson(clean.clamp_min(0), generator=g) + READ * torch.randn(clean.shape, generator=g, dtype=F64)
    return noisy, psf, win, torch.full((n,), om, dtype=F64), float(clean.amax())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    noise = CameraNoise(gain_e_per_adu=1.0, offset_adu=0.0, read_noise_e=READ)
    t0 = time.perf_counter()
    print(f"true amplitude {TRUE_M} px, {args.n} images per case, read noise {READ} e-, threads={args.threads}")
    print(f"{'peak e-/s':>9} {'f Hz':>5} {'max e-/px':>9} {'loss':>7} {'items':>9} {'mean M px':>10} {'+- (mean)':>9} {'bias/std':>8} "
          f"{'rms zM':>6} {'rms zphi':>8} {'red chi2':>8} {'failed':>6}")
    for peak in (1000.0, 3000.0, 10000.0):
        for f in (10.0, 100.0):
            img, psf, win, om, top = images(args.n, peak, f, seed=int(peak + f))
            for loss in ("l2", "poisson"):
                fit = fit_sinusoid(img, psf, win, om, noise=noise, loss=loss, fit_scale=True)
                ok = fit.status == 0
                undecided = (fit.flags & BRANCH_UNDECIDED) != 0
                for what, use in (("all", ok), ("unflagged", ok & ~undecided)):
                    m = fit.amplitude[use].numpy()
                    if m.size < 2:
                        print(f"{peak:9.0f} {f:5.0f} {top:9.1f} {loss:>7} {what:>9}: {m.size} items")
                        continue
                    z = ((fit.amplitude - TRUE_M) / fit.amplitude_std)[use].numpy()
                    zp = (torch.remainder(fit.phase - PHASE + math.pi, 2 * math.pi) - math.pi)[use].numpy() / fit.phase_std[use].numpy()
                    sem = m.std(ddof=1) / math.sqrt(m.size)
                    chi2 = float(np.nanmean(fit.reduced_chi2[use].numpy()))
                    print(f"{peak:9.0f} {f:5.0f} {top:9.1f} {loss:>7} {what:>9} {m.mean():10.4f} {sem:9.4f} {(m.mean() - TRUE_M) / sem:+8.2f} "
                          f"{math.sqrt(float(np.mean(z * z))):6.2f} {math.sqrt(float(np.mean(zp * zp))):8.2f} {chi2:8.3f} "
                          f"{int((~ok).sum()):6d}" + (f"  ({int((undecided & ok).sum())} flagged branch undecided)" if what == "unflagged" else ""),
                          flush=True)
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
