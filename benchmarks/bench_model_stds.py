"""Do the two-step model's parameter stds hold? (issue 24's "done when")

Runs the default identification (configs/identify_default.yaml: the simulated 420 Hz mirror,
30 points, 1 Hz - 1 kHz) for ``--seeds`` seeds and compares each natural parameter of the model
(:attr:`~torchblur.sysid.tf_fit.TransferFunctionFit.param_names`: DC gain, the mode's omega_n
and damping, the real pole's rate, the delay) with the truth; the truth's parameters are those
of the same model structure fitted to the noise-free true response (exact to ~1e-9). Prints
per parameter the rms of (estimate - truth) / std over the seeds whose chosen order is the
true one (a std that holds gives 0.7-1.4 with 10 seeds most of the time: 95 % of the time the
rms of 10 N(0, 1) errors is within 0.57-1.43, the "chance range" printed for each count), the
largest |error| / std, and how many seeds chose another order; and per parameter the chi2 test
of the seeds' errors: ``sum (error/std)^2`` against chi2 with one degree of freedom per seed
(two-sided p: a small p says the stds are too small or too large, beyond chance).

With ``--profile`` it also asks whether the delay's linearised std (Gauss-Newton, the delta
method) is right where the delay and the real pole above the band are strongly correlated: for
each seed the delay is fixed on a grid around the estimate and every other parameter refitted
(the profile likelihood, chi2 of the whitened residuals, ``common_delay_std_s=0`` on both sides
so that only the linearisation differs); printed: the linearised std, the half-widths of the
profile's ``delta chi2 <= 1`` interval below and above over that std (1 and 1 where the
linearisation holds), and the error of the estimate in both measures: ``(estimate - truth) /
std`` and the signed ``sqrt(chi2(truth) - chi2_min)`` (the likelihood-ratio z at the true delay).

With ``--common`` it asks whether the points' errors share a common-mode term the stds leave out
(a timing error common to all points, a shared PSF error): per seed, from the 30 points' errors
against the truth, the weighted mean phase error over its std (a common phase), the weighted
slope of the phase error in omega through 0 over its std (a common delay error; the latency
calibration's share, which the stds hold fully correlated, is tiny: 0.078 us against 0.64 us),
and the weighted mean relative magnitude error over its std (a common gain). With independent
errors of the stds given each is N(0, 1): printed, their rms over the seeds with the chance range,
and the rms of every point's error / std (phase, magnitude).

    python benchmarks/bench_model_stds.py [--seeds 10] [--first 0] [--threads 1] [--profile] [--common]
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


def delay_profile(frf, m, truth_delay, n_poles, n_zeros, k=(-2.0, -1.0, -0.5, 0.5, 1.0, 2.0)):
    """``(std, lower / std, upper / std, z_lin, z_profile)`` of the delay of ``frf``'s model in
    ``m``'s structure, with no common timing term (see the module docstring)."""
    kw = dict(n_poles=n_poles, n_zeros=n_zeros)
    m0 = fit_transfer_function(frf, **kw)
    d0, s0 = m0.parameter("delay_s")
    ds = [d0 + s0 * x for x in k]
    chi = np.array([fit_transfer_function(frf, delay_s=max(d, 0.0), **kw).chi2 - m0.chi2 for d in ds])
    x = np.asarray(k)
    half = []
    for sign in (-1.0, 1.0):  # the delta chi2 = 1 crossing of a parabola through the minimum and that side's points
        side = np.sign(x) == sign
        a, b, c = np.polyfit(np.r_[0.0, x[side]], np.r_[0.0, chi[side]], 2)
        r = np.roots([a, b, c - 1.0])
        r = r[np.isreal(r)].real
        r = r[np.sign(r) == sign]
        half.append(float(np.min(np.abs(r))) if r.size else float("nan"))
    dt = fit_transfer_function(frf, delay_s=max(truth_delay, 0.0), **kw).chi2 - m0.chi2
    return s0, half[0], half[1], (d0 - truth_delay) / s0, math.copysign(math.sqrt(max(dt, 0.0)), d0 - truth_delay)


def common_mode(frf, truth) -> tuple[float, float, float, np.ndarray, np.ndarray]:
    """``(z_phase, z_delay, z_gain, phase z [F], magnitude z [F])`` of one SISO run against its
    truth (see the module docstring)."""
    em, ep, _ = frf.errors_against(truth)
    em, ep = em[0, 0], ep[0, 0]
    sp, sm = frf.phase_std[0, 0], frf.magnitude_std[0, 0] / np.abs(np.asarray(truth).reshape(-1))
    w, wm, om = 1 / sp**2, 1 / sm**2, frf.omega
    return (float(np.sum(w * ep) / math.sqrt(np.sum(w))), float(np.sum(w * om * ep) / math.sqrt(np.sum(w * om**2))),
            float(np.sum(wm * em) / math.sqrt(np.sum(wm))), ep / sp, em / sm)


def print_common(rows):
    """The ``--common`` table over the seeds' :func:`common_mode` rows."""
    n = len(rows)
    lo, hi = (math.sqrt(scipy.stats.chi2.ppf(q, n) / n) for q in (0.025, 0.975))
    print(f"\ncommon-mode errors over {n} seeds (each N(0, 1) if the points' errors are independent with their stds; "
          f"chance range of the rms {lo:.2f}..{hi:.2f}):")
    for k, name in enumerate(("common phase", "common delay (phase slope in omega)", "common gain")):
        v = np.array([r[k] for r in rows])
        print(f"  {name:>36}: rms {np.sqrt(np.mean(v * v)):.3f}, mean {v.mean():+.2f}, max |z| {np.abs(v).max():.2f}")
    zp, zm = np.array([r[3] for r in rows]), np.array([r[4] for r in rows])  # [seeds, F]
    print(f"  every point: rms(phase error / std) {np.sqrt(np.mean(zp * zp)):.3f}, rms(magnitude error / std) "
          f"{np.sqrt(np.mean(zm * zm)):.3f} over {zp.size} points; by thirds of the band (low, mid, high): phase "
          + ", ".join(f"{np.sqrt(np.mean(b * b)):.3f}" for b in np.array_split(zp, 3, axis=1)) + "; magnitude "
          + ", ".join(f"{np.sqrt(np.mean(b * b)):.3f}" for b in np.array_split(zm, 3, axis=1)))


def print_blocks(z: dict, kept: np.ndarray, first: int, size: int) -> None:
    """Each consecutive block of ``size`` seeds (those that chose 3 poles, 0 zeros): every
    parameter's rms(error/std) and whether it is within 0.7..1.4; the share of blocks within,
    per parameter and for all parameters at once, against the share honest N(0, 1) errors give
    (per parameter: chi2 with the block's count; all at once: simulated with the parameters'
    correlation over the seeds, since the model's parameters are correlated)."""
    block = (kept - first) // size
    names = list(z)
    Z = np.column_stack([np.asarray(z[n]) for n in names])  # [seeds kept, parameters]
    print(f"\nblocks of {size} seeds: rms(error/std) per parameter ('*': outside 0.7..1.4)")
    print(f"{'seeds':>9} {'n':>3} " + " ".join(f"{n:>11}" for n in names) + "  all within")
    inside = []
    for b in np.unique(block):
        zb = Z[block == b]
        rms = np.sqrt(np.mean(zb * zb, axis=0))
        ok = (rms >= 0.7) & (rms <= 1.4)
        inside.append(ok)
        lo = first + int(b) * size
        print(f"{lo:>4}..{lo + size - 1:<4} {len(zb):3d} " + " ".join(f"{r:10.2f}{' ' if o else '*'}" for r, o in zip(rms, ok))
              + f"  {'yes' if ok.all() else 'no'}")
    inside = np.asarray(inside)
    p_one = scipy.stats.chi2.cdf(1.4 ** 2 * size, size) - scipy.stats.chi2.cdf(0.7 ** 2 * size, size)
    rng = np.random.default_rng(0)
    corr = np.corrcoef(Z, rowvar=False)
    sim = rng.multivariate_normal(np.zeros(len(names)), corr, size=(20000, size))  # honest errors with the seeds' correlation
    srms = np.sqrt(np.mean(sim * sim, axis=1))
    p_all = float(np.mean(np.all((srms >= 0.7) & (srms <= 1.4), axis=1)))
    print("share of blocks within 0.7..1.4, per parameter: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, inside.mean(0)))
          + f" (honest stds: {p_one:.2f} each); all parameters at once: {int(inside.all(1).sum())} of {len(inside)} blocks "
          f"(honest stds, with the parameters' correlation over these seeds: {p_all:.2f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="the first seed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--profile", action="store_true", help="the delay's profile likelihood against its linearised std")
    ap.add_argument("--common", action="store_true", help="test the points' errors for a common-mode term")
    ap.add_argument("--block", type=int, default=0, help="also judge consecutive blocks of this many seeds (10: the issue's test)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    z, other, prof, common, kept, t0 = {}, [], [], [], [], time.perf_counter()
    for seed in range(args.first, args.first + args.seeds):
        cfg = load_config(None, [f"seed={seed}"])
        res = identify(cfg, progress=False)
        m = res.model
        if args.common:
            common.append(common_mode(res.frf, res.truth))
        names, truth, exact = true_parameters(cfg, res.frf.omega, m.n_poles, m.n_zeros)
        if (m.n_poles, m.n_zeros) != (3, 0) or exact > 1e-6:
            other.append((seed, m.n_poles, m.n_zeros))
            continue
        kept.append(seed)
        for name, t in zip(names, truth):
            v, sd = m.parameter(name)
            z.setdefault(name, []).append((v - t) / sd)
        print(f"seed {seed}: " + ", ".join(f"{n} {(m.parameter(n)[0] - t) / m.parameter(n)[1]:+.2f}"
                                           for n, t in zip(names, truth)) + " (error / std)", flush=True)
        if args.profile:
            prof.append(delay_profile(res.frf, m, float(truth[list(names).index("delay_s")]), m.n_poles, m.n_zeros))
            print("    delay, no common term: std {:.3g} us, profile half-widths {:.3f} below, {:.3f} above (x std); "
                  "z linearised {:+.2f}, z profile {:+.2f}".format(prof[-1][0] * 1e6, *prof[-1][1:]), flush=True)
    print(f"\n{args.seeds} seeds ({args.first}..{args.first + args.seeds - 1}) of the default run, threads={args.threads}, {time.perf_counter() - t0:.0f} s; "
          f"{len(other)} chose another order than 3 poles, 0 zeros: {other}")
    print(f"{'parameter':>12} {'rms(err/std)':>13} {'max |err/std|':>14} {'seeds':>6}  (holds: rms 0.7..1.4)  chance range  "
          f"chi2 test p  mean(err/std)")
    for name, v in z.items():
        v = np.asarray(v)
        rms = float(np.sqrt(np.mean(v * v)))
        lo, hi = (math.sqrt(scipy.stats.chi2.ppf(q, v.size) / v.size) for q in (0.025, 0.975))
        c = scipy.stats.chi2(v.size)
        p = 2 * min(c.cdf(float(v @ v)), c.sf(float(v @ v)))
        print(f"{name:>12} {rms:13.3f} {np.abs(v).max():14.2f} {v.size:6d}  {'holds' if 0.7 <= rms <= 1.4 else 'DOES NOT HOLD':13s}"
              f"  {lo:.2f}..{hi:.2f}    {p:9.3f}  {v.mean():+.2f}")
    print("chance range: where the rms of that many N(0, 1) errors falls 95 % of the time (stds that hold: sqrt(chi2_n / n)); "
          "chi2 test p: two-sided, sum (err/std)^2 against chi2 with one degree of freedom per seed")
    if args.block:
        print_blocks(z, np.asarray(kept), args.first, args.block)
    if common:
        print_common(common)
    if prof:
        a = np.asarray(prof)
        zl, zp = a[:, 3], a[:, 4]
        print(f"delay profile over {len(a)} seeds: half-width / linearised std below {np.nanmean(a[:, 1]):.3f} "
              f"({np.nanmin(a[:, 1]):.3f}..{np.nanmax(a[:, 1]):.3f}), above {np.nanmean(a[:, 2]):.3f} ({np.nanmin(a[:, 2]):.3f}.."
              f"{np.nanmax(a[:, 2]):.3f}); rms z linearised {np.sqrt(np.mean(zl ** 2)):.3f}, profile {np.sqrt(np.mean(zp ** 2)):.3f}; "
              f"largest |z_lin - z_profile| {np.max(np.abs(zl - zp)):.3f}")


if __name__ == "__main__":
    main()
