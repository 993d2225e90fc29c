"""Multisine against the sine sweep: images used for the same 3 frequency points (issue 6 part 4's "done when").

For groups of 3 frequencies of the default simulated mirror (64x64 frames, 30 Hz camera,
default noise), runs ``identify`` twice on the same rig settings and seed:

- ``excitation.kind=multisine``: one multisine of 3 tones, pilot frame(s) to set the amplitude,
  then the image set designed from the Fisher information (``excitation.target_std``);
- the sine sweep (``excitation.kind=sine``): 2 exposures x ``images_per_point`` = 4 frames per
  frequency, plus the frames of its amplitude retakes;

and prints per case and method: the frames the rig took for the sweep stage (calibration
excluded; pilots and retakes included), the frames fitted, the largest |H| error (%), phase
error (deg) and error / reported std against the truth, the mean reported std, and the wall
time of the run (calibration included).

Then (issue 6 part 5) one image against the alias: for random phases of a 6 px, 200 Hz sine,
a single plain exposure (half a period) and a single coded exposure of the same window (open
during 0-20 %, 45-55 % and 80-90 % of it, the laser power raised so both collect the same peak
exposure), noise as the camera's (read 5 e-, shot), fitted from one image each: how often the
fit lands on the wrong branch, the largest error / reported std on the right branch, the median
reported phase std, and the cost ratio alias / solution (min and median: the two branches meet
where phi = (pi - 2c) / 2 mod pi, so the min is 1 for any exposure).

    python benchmarks/bench_multisine.py [--threads 2] [--seeds 1] [--tone-px 6] [--coded 48]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify.run import build_simulated_rig, identify

CASES = {
    "150/200/250 Hz (below the resonance)": [150.0, 200.0, 250.0],
    "300/420/540 Hz (across the 420 Hz resonance)": [300.0, 420.0, 540.0],
    "12/16/20 Hz (low)": [12.0, 16.0, 20.0],
    "600/800/1000 Hz (roll-off)": [600.0, 800.0, 1000.0],
}


class CountingRig:
    """Forwards every call to a rig and counts the frames of the excitation calls."""

    def __init__(self, rig):
        self._rig = rig
        self.frames = 0

    def __getattr__(self, name):
        return getattr(self._rig, name)

    def _count(self, cap):
        self.frames += int(np.prod(cap.shape))
        return cap

    def sine(self, *a, **k):
        return self._count(self._rig.sine(*a, **k))

    def multisine(self, *a, **k):
        return self._count(self._rig.multisine(*a, **k))


def errors(res):
    t, f = res.truth, res.frf
    em = np.abs(f.magnitude[0, 0] - np.abs(t)) / np.abs(t)
    ep = np.abs(np.remainder(f.phase[0, 0] - np.angle(t) + np.pi, 2 * np.pi) - np.pi)
    z = np.maximum(np.abs(f.magnitude[0, 0] - np.abs(t)) / f.magnitude_std[0, 0], ep / f.phase_std[0, 0])
    return (100 * em.max(), np.degrees(ep.max()), z.max(), 100 * np.mean(f.magnitude_std[0, 0] / f.magnitude[0, 0]),
            np.degrees(np.mean(f.phase_std[0, 0])))


def run(keys):
    cfg = load_config(None, keys)
    rig = CountingRig(build_simulated_rig(cfg))
    t0 = time.perf_counter()
    res = identify(cfg, rig=rig, progress=False)
    wall = time.perf_counter() - t0
    fitted = res.images.shape[0] if res.images.dim() == 3 else res.images.shape[0] * res.images.shape[1]
    return res, rig.frames, fitted, wall


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--tone-px", type=float, default=None, help="excitation.tone_px (default: the config's, 0.75 target_px)")
    ap.add_argument("--coded", type=int, default=48, help="single-image trials of the coded exposure (0: skip)")
    ap.add_argument("--skip-sweeps", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch threads: {args.threads}; default plant (420 Hz resonance), 64x64 frames, sine: exposures 0.3/0.8 x 2 images "
          f"per point, target 8 px; multisine: 3 tones, tone_px {args.tone_px or 'default (6)'}")
    head = f"{'case':46} {'seed':>4} {'method':9} {'frames':>6} {'fitted':>6} {'|H| err %':>9} {'ph err deg':>10} {'err/std':>7} " \
           f"{'std %':>6} {'std deg':>7} {'wall s':>6}"
    print(head)
    totals = {"multisine": [], "sine": []}
    for name, freqs in ({} if args.skip_sweeps else CASES).items():
        for seed in range(args.seeds):
            base = [f"sweep.freq_hz=[{','.join(str(f) for f in freqs)}]", f"seed={seed}"]
            ms_keys = base + ["excitation.kind=multisine", "excitation.tones=3"]
            if args.tone_px is not None:
                ms_keys.append(f"excitation.tone_px={args.tone_px}")
            for method, keys in (("multisine", ms_keys), ("sine", base)):
                res, frames, fitted, wall = run(keys)
                em, ep, z, sm, sp = errors(res)
                totals[method].append((frames, em, ep, z))
                print(f"{name:46} {seed:4d} {method:9} {frames:6d} {fitted:6d} {em:9.3f} {ep:10.3f} {z:7.2f} {sm:6.3f} {sp:7.3f} "
                      f"{wall:6.1f}", flush=True)
    print()
    for method, rows in totals.items():
        if not rows:
            continue
        a = np.asarray(rows)
        print(f"{method:9}: frames per 3 points mean {a[:, 0].mean():.1f} (min {a[:, 0].min():.0f}, max {a[:, 0].max():.0f}); "
              f"worst |H| error {a[:, 1].max():.3f}%, worst phase error {a[:, 2].max():.3f} deg, worst error/std {a[:, 3].max():.2f}")

    if args.coded:
        coded_alias(args.coded)


def coded_alias(trials: int):
    import math

    from torchblur.render.camera import CameraModel
    from torchblur.fit.coded import fit_sinusoid_coded
    from torchblur.render.coded import render_coded
    from torchblur.fit.sinusoid import fit_sinusoid
    from torchblur.render.psf import GaussianPSF
    from torchblur.render.blur import render_blur
    from torchblur.render.window import ExposureWindow
    from torchblur.render.trajectory import Sinusoid

    d = torch.float64
    f = 200.0
    om, T = 2 * math.pi * f, 1 / f
    code = torch.tensor([[0.0, 0.2], [0.45, 0.55], [0.8, 0.9]], dtype=d)
    open_frac = float((code[:, 1] - code[:, 0]).sum())
    win = ExposureWindow(torch.full((trials,), 0.25 * T, dtype=d), torch.full((trials,), 0.5 * T, dtype=d))
    g = torch.Generator().manual_seed(0)
    phis = (torch.rand(trials, generator=g, dtype=d) * 2 - 1) * math.pi
    M = torch.full((trials,), 6.0, dtype=d)
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([phis, phis], -1), torch.tensor(om, dtype=d))
    cam = CameraModel(read_noise_e=5.0, dark_level_adu=0.0, bit_depth=16, full_well_e=1e9)
    peak_e = 2000.0
    rows = []
    for label, coded in (("plain", False), ("coded", True)):
        rate = peak_e / (0.5 * T * (open_frac if coded else 1.0))  # same still-spot peak exposure in both
        psf = GaussianPSF(torch.tensor([23.5, 11.5], dtype=d), 4 * torch.eye(2, dtype=d), torch.tensor(rate, dtype=d))
        img = render_coded(traj, psf, win, code, height=24, width=48) if coded else render_blur(traj, psf, win, height=24, width=48)
        noisy = cam.expose(img, generator=g)
        noise = torch.sqrt(25 + noisy.clamp_min(0))
        t0 = time.perf_counter()
        if coded:
            r = fit_sinusoid_coded(noisy, psf, win, code, om, noise_std=noise)
        else:
            r = fit_sinusoid(noisy[:, None], psf, win[:, None], torch.full((trials,), om, dtype=d), noise_std=noise[:, None])
        wall = time.perf_counter() - t0
        err = torch.remainder(r.phase - phis + math.pi, 2 * math.pi) - math.pi
        wrong = err.abs() > 0.2
        z = (err.abs() / r.phase_std)[~wrong]
        rows.append((label, int(wrong.sum()), float(z.max()) if z.numel() else float("nan"), math.degrees(float(r.phase_std.median())),
                     float((r.alias_cost / r.cost).min()), float((r.alias_cost / r.cost).median()), wall))
    print(f"\none image against the alias: {trials} random phases, 6 px at 200 Hz, window 0.25-0.75 T, code "
          f"{code.tolist()} (open {open_frac:.0%}), peak exposure {peak_e:.0f} e-, read noise 5 e-")
    print(f"{'exposure':8} {'wrong branch':>12} {'max err/std (right)':>19} {'median std deg':>14} {'alias/cost min':>14} "
          f"{'median':>7} {'fit s':>6}")
    for label, nw, zmax, sd, amin, amed, wall in rows:
        print(f"{label:8} {nw:5d} of {trials:<4d} {zmax:19.2f} {sd:14.3f} {amin:14.4f} {amed:7.3f} {wall:6.1f}")


if __name__ == "__main__":
    main()
