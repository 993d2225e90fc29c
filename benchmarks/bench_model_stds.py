"""Do the two-step model's parameter stds hold? (issue 24's "done when")

Runs the default identification (configs/identify_default.yaml: the simulated 420 Hz mirror,
30 points, 1 Hz - 1 kHz) for ``--seeds`` seeds and compares each natural parameter of the model
(:attr:`~torchblur.sysid.tf_fit.TransferFunctionFit.param_names`: DC gain, the mode's omega_n
and damping, the real pole's rate, the delay) with the truth; the truth's parameters are those
of the same model structure fitted to the noise-free true response (exact to ~1e-9). Prints
per parameter the rms of (estimate - truth) / std over the seeds whose chosen order is the
true one (a std that holds gives 0.7-1.4 with 10 seeds most of the time: 95 % of the time the
rms of 10 N(0, 1) errors is within 0.57-1.43, the "chance range" printed for each count), the
largest |error| / std, and how many seeds chose another order.

    python benchmarks/bench_model_stds.py [--seeds 10] [--first 0] [--threads 1]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import scipy.stats
import torch

from torchblur.config import load_config
from torchblur.identify.run import identify, plant_of
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function


def true_parameters(cfg, omega, n_poles, n_zeros):
    """The natural parameters (names, values) of the true plant in the model's structure."""
    h = plant_of(cfg).frequency_response(omega)
    fit = fit_transfer_function(FrequencyResponse(omega, np.asarray(h).reshape(-1)), n_poles=n_poles, n_zeros=n_zeros,
                                weights="uniform")
    return fit.param_names, fit.params, fit.rms_relative_error


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="the first seed")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    z, other, t0 = {}, [], time.perf_counter()
    for seed in range(args.first, args.first + args.seeds):
        cfg = load_config(None, [f"seed={seed}"])
        res = identify(cfg, progress=False)
        m = res.model
        names, truth, exact = true_parameters(cfg, res.frf.omega, m.n_poles, m.n_zeros)
        if (m.n_poles, m.n_zeros) != (3, 0) or exact > 1e-6:
            other.append((seed, m.n_poles, m.n_zeros))
            continue
        for name, t in zip(names, truth):
            v, sd = m.parameter(name)
            z.setdefault(name, []).append((v - t) / sd)
        print(f"seed {seed}: " + ", ".join(f"{n} {(m.parameter(n)[0] - t) / m.parameter(n)[1]:+.2f}"
                                           for n, t in zip(names, truth)) + " (error / std)", flush=True)
    print(f"\n{args.seeds} seeds ({args.first}..{args.first + args.seeds - 1}) of the default run, threads={args.threads}, {time.perf_counter() - t0:.0f} s; "
          f"{len(other)} chose another order than 3 poles, 0 zeros: {other}")
    print(f"{'parameter':>12} {'rms(err/std)':>13} {'max |err/std|':>14} {'seeds':>6}  (holds: rms 0.7..1.4)  chance range")
    for name, v in z.items():
        v = np.asarray(v)
        rms = float(np.sqrt(np.mean(v * v)))
        lo, hi = (math.sqrt(scipy.stats.chi2.ppf(q, v.size) / v.size) for q in (0.025, 0.975))
        print(f"{name:>12} {rms:13.3f} {np.abs(v).max():14.2f} {v.size:6d}  {'holds' if 0.7 <= rms <= 1.4 else 'DOES NOT HOLD':13s}"
              f"  {lo:.2f}..{hi:.2f}")
    print("chance range: where the rms of that many N(0, 1) errors falls 95 % of the time (stds that hold: sqrt(chi2_n / n))")


if __name__ == "__main__":
    main()
