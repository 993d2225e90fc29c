"""MIMO tip-tilt and many spots against the truth (issue 6 parts 1 and 2, "done when").

Runs the full configs on the simulated rig (1 Hz - 1 kHz, 30 Hz camera) and prints, per
channel (output from input), the largest |H| relative error (%), the largest phase error
(deg) and the largest |error| / reported std (magnitude or phase), and the wall time.

    python benchmarks/bench_mimo.py [--threads 2] [--which mimo,spots] [key=value ...]

``configs/identify_mimo.yaml``: a 2x2 tip-tilt mirror with 13-26 % cross-coupling (goal: every
channel within 2 % and 2 deg). ``configs/identify_spots.yaml``: a 3x3 Shack-Hartmann grid
on a 96x96 frame, each spot with its own PSF and response (per-spot errors reported).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify.run import identify

CONFIGS = {"mimo": "configs/identify_mimo.yaml", "spots": "configs/identify_spots.yaml"}


def channel_errors(res):
    """Per channel [O, I]: max |H| relative error, max phase error (deg), max err/std."""
    f, t = res.frf, res.truth
    if t.ndim == 1:
        t = t[None, None]
    em = np.abs(f.magnitude - np.abs(t)) / np.abs(t)
    ep = np.abs(np.remainder(f.phase - np.angle(t) + np.pi, 2 * np.pi) - np.pi)
    z = np.maximum(np.abs(f.magnitude - np.abs(t)) / f.magnitude_std, ep / f.phase_std)
    return np.nanmax(em, -1), np.degrees(np.nanmax(ep, -1)), np.nanmax(z, -1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--which", default="mimo,spots", help="comma-separated: mimo, spots")
    ap.add_argument("overrides", nargs="*", help="config overrides for every run, e.g. sweep.n=10")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"threads={args.threads}, overrides={args.overrides}")
    for name in args.which.split(","):
        cfg = load_config(CONFIGS[name], args.overrides)
        t0 = time.perf_counter()
        res = identify(cfg, progress=False)
        dt = time.perf_counter() - t0
        f = res.frf
        em, ep, z = channel_errors(res)
        print(f"\n{name}: {CONFIGS[name]}, {len(f.omega)} points {f.freq_hz[0]:.3g}-{f.freq_hz[-1]:.4g} Hz, "
              f"{cfg.camera.frame_rate_hz:g} Hz camera, target_px={cfg.excitation.target_px}, "
              f"images_per_point={cfg.sweep.images_per_point}, {f.n_outputs}x{f.n_inputs} channels, time {dt:.1f} s")
        n_bad = int((~f.valid).sum())
        print(f"  converged channel points: {f.valid.size - n_bad} of {f.valid.size}")
        if res.spots is not None:  # one line per spot: its direct channels (x from x, y from y) and its cross channels
            t = np.abs(res.truth)
            for k in range(len(res.spots)):
                d, c = [(2 * k, 0), (2 * k + 1, 1)], [(2 * k, 1), (2 * k + 1, 0)]
                pick = lambda a, idx: max(a[o, i] for o, i in idx)  # noqa: E731
                ratio = [np.min(t[o, i] / t[2 * k + i, i]) for o, i in c] + [np.max(t[o, i] / t[2 * k + i, i]) for o, i in c]
                cx, cy = res.spots.psf.center[k].tolist()
                print(f"  s{k} at ({cx:5.1f}, {cy:5.1f}) px: direct |H| err max {pick(em, d) * 100:6.3f}%  phase {pick(ep, d):6.3f} deg; "
                      f"cross ({min(ratio) * 100:.0f}-{max(ratio) * 100:.0f}% of direct) |H| err max {pick(em, c) * 100:6.3f}%  "
                      f"phase {pick(ep, c):6.3f} deg; err/std max {max(pick(z, d), pick(z, c)):4.2f}")
        for o in range(f.n_outputs if res.spots is None else 0):
            for i in range(f.n_inputs):
                ratio = ""
                if name == "mimo" and o != i:
                    t = res.truth
                    ratio = f"  (|H| {np.min(np.abs(t[o, i]) / np.abs(t[i, i])) * 100:.0f}-{np.max(np.abs(t[o, i]) / np.abs(t[i, i])) * 100:.0f}% of the diagonal)"
                print(f"  {f.output_labels[o]:>5s} from {f.input_labels[i]}: |H| err max {em[o, i] * 100:6.3f}%  "
                      f"phase err max {ep[o, i]:6.3f} deg  err/std max {z[o, i]:5.2f}{ratio}")
        print(f"  worst channel: |H| {np.nanmax(em) * 100:.3f}% (goal 2%), phase {np.nanmax(ep):.3f} deg (goal 2 deg), "
              f"err/std {np.nanmax(z):.2f}")
        if res.model is not None and not res.model.is_siso and f.n_outputs <= 2:
            m = res.model
            for o in range(f.n_outputs):
                for i in range(f.n_inputs):
                    modes = m.modal_parameters()[o][i]
                    md = ", ".join(f"{d['freq_hz']:.1f} Hz zeta {d['zeta']:.3f}" for d in modes)
                    print(f"  model {f.output_labels[o]} from {f.input_labels[i]}: {m.n_poles[o][i]} poles, {m.n_zeros[o][i]} zeros, "
                          f"reduced chi2 {m.reduced_chi2[o][i]:.2f}; modes {md}")


if __name__ == "__main__":
    main()
