"""Does the latency calibration's std hold? (issue 24: the delay's std carries it)

For seeds ``FIRST..LAST-1`` of the default run (configs/identify_default.yaml, the simulated rig's
true latency ``camera.latency_s``) runs the calibration (:func:`torchblur.identify.calibration.calibrate`)
and compares the scanned latency with the truth, by the current rule
(:func:`~torchblur.identify.calibration.latency_from_scan`: the plateau's median) and by the
previous one (the median of the highest tenth of the scan, the noise's top), on the same scan.
Prints per seed the errors and stds, then the mean and rms of error / std (a std that holds: mean
about 0, rms about 1).

    python benchmarks/bench_latency.py [FIRST LAST]   (default 0 30)
"""
from __future__ import annotations

import math
import sys

import numpy as np
import torch

import torchblur.identify.calibration as C
from torchblur.config import load_config
from torchblur.identify.run import build_simulated_rig

_scan = {}
_current = C.latency_from_scan


def _spy(times, light, **kw):
    """The current rule, keeping the scan for the previous one."""
    _scan.update(t=times, light=light, kw=kw)
    return _current(times, light, **kw)


def previous_rule(times, light, pulse_width_s, trigger_delay_s=0.0):
    """The rule before issue 24's fix: ``top`` = the median of the highest tenth of the scan."""
    light = np.asarray(light)
    top = np.median(np.sort(light)[-max(3, len(light) // 10):])
    idx = np.nonzero((light > 0.1 * top) & (light < 0.9 * top))[0]
    idx = idx[idx < np.nonzero(light >= 0.9 * top)[0][0]]
    A = np.stack([times[idx], np.ones(idx.size)], 1)
    coef = np.linalg.lstsq(A, light[idx], rcond=None)[0]
    slope, intercept = coef
    t_half = (0.5 * top - intercept) / slope
    resid = light[idx] - A @ coef
    s2 = float(resid @ resid) / max(1, idx.size - 2)
    cov = s2 * np.linalg.inv(A.T @ A)
    g = np.array([-(0.5 * top - intercept) / slope**2, -1 / slope])
    std = math.sqrt(max(float(g @ cov @ g), 0.0) + (0.5 * math.sqrt(s2) / abs(slope)) ** 2 / max(1, len(light) // 10))
    return t_half + pulse_width_s / 2 - trigger_delay_s, std


def main():
    torch.set_num_threads(1)
    first, last = (int(a) for a in sys.argv[1:3]) if len(sys.argv) > 2 else (0, 30)
    C.latency_from_scan = _spy
    z_old, z_new = [], []
    for seed in range(first, last):
        cfg = load_config(None, [f"seed={seed}"])
        cal = C.calibrate(cfg, build_simulated_rig(cfg))
        lo, so = previous_rule(_scan["t"], _scan["light"], **_scan["kw"])
        truth = cfg.camera.latency_s
        z_old.append((lo - truth) / so)
        z_new.append((cal.latency_s - truth) / cal.latency_std_s)
        print(f"seed {seed}: previous {(lo - truth) * 1e9:+.0f} +- {so * 1e9:.0f} ns; current "
              f"{(cal.latency_s - truth) * 1e9:+.0f} +- {cal.latency_std_s * 1e9:.0f} ns", flush=True)
    for name, z in (("previous", z_old), ("current", z_new)):
        z = np.asarray(z)
        print(f"{name}: mean error/std {z.mean():+.2f}, rms {math.sqrt(float(np.mean(z * z))):.2f} ({z.size} seeds, threads=1)")


if __name__ == "__main__":
    main()
