"""The identification end to end against the truth (issue 4's "done when").

For the default simulated mirror and plants it was not tuned for (an anti-resonance, a
high-Q resonance, a long delay, a well-damped 2nd-order system), from 1 Hz to 1 kHz with a
30 Hz camera and default settings, prints per plant: the largest |H| error (%), phase error
(deg) and error / reported std, the wall time of the whole run (simulated acquisition and
fitting, imports excluded), and the model's fit (order, reduced chi2, largest model-vs-data
deviation in stds).

    python benchmarks/bench_identify.py [--threads 2] [--n 30]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify.run import identify


def tf(*factors):
    num, den = np.array([1.0]), np.array([1.0])
    for n, d in factors:
        num, den = np.polymul(num, n), np.polymul(den, d)
    return num.tolist(), den.tolist()


def second(fn, z, gain=1.0):
    w = 2 * math.pi * fn
    return [gain * w * w], [1, 2 * z * w, w * w]


def zeros2(fz, z):
    w = 2 * math.pi * fz
    return [1 / (w * w), 2 * z / w, 1.0], [1.0]


def pole(fp):
    w = 2 * math.pi * fp
    return [w], [1, w]


PLANTS = {
    "default (420 Hz resonance, 30 us)": None,
    "anti-resonance 250 Hz + resonance 600 Hz, 60 us": (tf(zeros2(250, 0.04), second(600, 0.03, 12.0), pole(1500)), 60e-6),
    "high-Q resonance 310 Hz (zeta 0.02), 20 us": (tf(second(310, 0.02, 15.0), pole(3000)), 20e-6),
    "long delay 150 us, damped 2nd order 180 Hz": (tf(second(180, 0.5, 25.0)), 150e-6),
    "two resonances 120 Hz and 700 Hz": (tf(second(120, 0.08, 10.0), second(700, 0.05)), 10e-6),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--n", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    identify(load_config(None, ["sweep.freq_hz=[10]", "model.max_order=2"]), progress=False)  # warm-up: imports
    print(f"threads={args.threads}, {args.n} log-spaced points 1 Hz - 1 kHz, 30 Hz camera, default settings")
    for name, spec in PLANTS.items():
        over = [f"sweep.n={args.n}"]
        if spec is not None:
            (num, den), delay = spec
            over += [f"plant.num={num}", f"plant.den={den}", f"plant.delay_s={delay}"]
        cfg = load_config(None, over)
        t0 = time.perf_counter()
        res = identify(cfg, progress=False)
        dt = time.perf_counter() - t0
        t, f = res.truth, res.frf
        em = np.abs(f.magnitude[0, 0] - np.abs(t)) / np.abs(t)
        ep = np.abs(np.remainder(f.phase[0, 0] - np.angle(t) + np.pi, 2 * np.pi) - np.pi)
        z = np.maximum(np.abs(f.magnitude[0, 0] - np.abs(t)) / f.magnitude_std[0, 0], ep / f.phase_std[0, 0])
        m = res.model
        line = (f"{name:48s} |H| err max {em.max() * 100:5.3f}%  phase err max {np.degrees(ep.max()):5.3f} deg  "
                f"err/std max {z.max():4.2f}  time {dt:5.1f} s")
        if m is not None:
            meas = f.response[0, 0]
            sig = np.sqrt(f.magnitude_std[0, 0] ** 2 + (np.abs(meas) * f.phase_std[0, 0]) ** 2)
            dev = np.abs(m.frequency_response(f.omega) - meas) / sig
            line += f"  model {m.n_poles}p/{m.n_zeros}z delay {m.delay_s * 1e6:.1f} us chi2r {m.reduced_chi2:.2f} dev max {dev.max():.2f} std"
        print(line, flush=True)


if __name__ == "__main__":
    main()
