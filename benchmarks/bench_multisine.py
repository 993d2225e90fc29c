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

    python benchmarks/bench_multisine.py [--threads 2] [--seeds 1] [--tone-px 6]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify import build_simulated_rig, identify

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
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch threads: {args.threads}; default plant (420 Hz resonance), 64x64 frames, sine: exposures 0.3/0.8 x 2 images "
          f"per point, target 8 px; multisine: 3 tones, tone_px {args.tone_px or 'default (6)'}")
    head = f"{'case':46} {'seed':>4} {'method':9} {'frames':>6} {'fitted':>6} {'|H| err %':>9} {'ph err deg':>10} {'err/std':>7} " \
           f"{'std %':>6} {'std deg':>7} {'wall s':>6}"
    print(head)
    totals = {"multisine": [], "sine": []}
    for name, freqs in CASES.items():
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
        a = np.asarray(rows)
        print(f"{method:9}: frames per 3 points mean {a[:, 0].mean():.1f} (min {a[:, 0].min():.0f}, max {a[:, 0].max():.0f}); "
              f"worst |H| error {a[:, 1].max():.3f}%, worst phase error {a[:, 2].max():.3f} deg, worst error/std {a[:, 3].max():.2f}")


if __name__ == "__main__":
    main()
