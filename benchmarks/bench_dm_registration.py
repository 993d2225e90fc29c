"""The registration fit on a D0 torchblur did not make (issue 23 part C).

The static interaction matrix D0 of a misregistered mirror is built here by an independent
route: for every valid subaperture (the sensor's layout: 10 x 10 subapertures of 0.8 actuator
pitch on an 8-pitch pupil, 80 valid) and actuator (8 across, 52), the mean x slope of the
actuator's Gaussian surface over the lit part of the square (square and pupil disc) is, by the
fundamental theorem of calculus, the integral over y of ``phi(x_right(y), y) - phi(x_left(y),
y)`` divided by the lit area, each integral by ``scipy.integrate.quad`` (the y slope likewise
over x). No gradient, no midpoint grid, nothing of torchblur.dm.shack_hartmann's mean_slopes
or torchblur.dm.registration's transform: the positions ``m R(a) x_j + t`` and the width
``m w`` are written out here. torchblur's midpoint model differs from it by its quadrature
error (printed), which the fit must live with.

Per seed: per-actuator gains (2 % spread, one dead, one at 0.3), Gaussian noise of
``--noise`` times the largest |D0| on every entry; :func:`torchblur.dm.registration.fit_registration`
from the nominal registration. Printed: each seed's errors; over the seeds the largest error
of shift (pitches), rotation (deg), magnification (relative), coupling, and rms(error/std) per
parameter (the stds hold where it is 0.8-1.3), the reduced chi2, rms(gain error/std).

    python benchmarks/bench_dm_registration.py [--seeds 12] [--noise 5e-4] [--shift 0.25 -0.25] [--rotation 1.5] [--magnification 1.03]
    python benchmarks/bench_dm_registration.py --hcipy [--seeds 4] [--noise 1e-3] [--shift 0.25 0] ...

``--hcipy``: D0 from an independent optics engine instead, HCIPy's Shack-Hartmann
(tests/hcipy_sh.py ``shift_truth``: each spot's least-squares shift under a small static poke;
square lenslets with their diffraction spots and crosstalk, HCIPy's Gaussian influence functions
of coupling 0.15, the mirror at ``--shift``/``--rotation``/``--magnification``), the true
coupling 0.15 and the gains' truth relative to HCIPy's influence functions' peak. The sensor
weighting (``diffraction_weight``) is printed; its truth is not known there (about 1).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
from scipy import integrate

from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.registration import Registration, fit_registration
from torchblur.dm.shack_hartmann import ShackHartmann


def lit_interval(c: float, half: float, other: float, radius: float):
    """The lit part ``[lo, hi]`` of the square's side ``[c - half, c + half]`` on the line at
    ``other`` (the other coordinate) inside the pupil disc, or None."""
    if abs(other) >= radius:
        return None
    h = math.sqrt(radius * radius - other * other)
    lo, hi = max(c - half, -h), min(c + half, h)
    return (lo, hi) if hi > lo else None


def quad_column(centre, side, radius, p, W):
    """Mean (x, y) slope of ``exp(-|u - p|^2 / 2 W^2)`` over the lit part of one subaperture."""
    cx, cy = centre
    half = side / 2

    def phi(x, y):
        return math.exp(-((x - p[0]) ** 2 + (y - p[1]) ** 2) / (2 * W * W))

    def along(axis):
        def f(t):  # t: the other coordinate
            iv = lit_interval(cx if axis == 0 else cy, half, t, radius)
            if iv is None:
                return 0.0
            return phi(iv[1], t) - phi(iv[0], t) if axis == 0 else phi(t, iv[1]) - phi(t, iv[0])
        c_other = cy if axis == 0 else cx
        return integrate.quad(f, c_other - half, c_other + half, epsabs=1e-13, epsrel=1e-11, limit=200)[0]

    def length(t):
        iv = lit_interval(cx, half, t, radius)
        return 0.0 if iv is None else iv[1] - iv[0]

    area = integrate.quad(length, cy - half, cy + half, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
    return along(0) / area, along(1) / area


def independent_G(wfs, actuator_xy, shift, rotation_deg, magnification, coupling, slope_px=1.0):
    a = math.radians(rotation_deg)
    c, s = math.cos(a), math.sin(a)
    W = magnification / math.sqrt(-2 * math.log(coupling))
    M, N = wfs.n_valid, len(actuator_xy)
    G = np.zeros((2 * M, N))
    for j, (x, y) in enumerate(actuator_xy):
        p = (magnification * (c * x - s * y) + shift[0], magnification * (s * x + c * y) + shift[1])
        for m, centre in enumerate(wfs.centres):
            G[m, j], G[M + m, j] = quad_column(centre, wfs.side, wfs.pupil_diameter / 2, p, W)
    return slope_px * G


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--noise", type=float, default=5e-4, help="noise std of every D0 entry over the largest |D0|")
    ap.add_argument("--shift", type=float, nargs=2, default=[0.25, -0.25])
    ap.add_argument("--rotation", type=float, default=1.5)
    ap.add_argument("--magnification", type=float, default=1.03)
    ap.add_argument("--coupling", type=float, default=0.16, help="the mirror's true coupling (nominal 0.15)")
    ap.add_argument("--hcipy", action="store_true", help="D0 from HCIPy's Shack-Hartmann (module docstring)")
    args = ap.parse_args(argv)
    mirror = DeformableMirror.build(8, coupling=0.15)
    wfs = ShackHartmann(n_across=10, pupil_diameter=8.0)
    t0 = time.perf_counter()
    if args.hcipy:
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
        import hcipy_sh as hs

        gen = hs.HcipySH(hs.SHOptics(shift=tuple(args.shift), rotation_deg=args.rotation, magnification=args.magnification))
        G_true, args.coupling = gen.shift_truth(), gen.optics.coupling
    else:
        G_true = independent_G(wfs, mirror.actuator_xy, args.shift, args.rotation, args.magnification, args.coupling)
    t_quad = time.perf_counter() - t0
    truth = Registration(shift_x=args.shift[0], shift_y=args.shift[1], rotation_deg=args.rotation, magnification=args.magnification,
                         coupling=args.coupling)
    scale = np.abs(G_true).max()
    print(f"independent D0 ({'HCIPy shift_truth' if args.hcipy else 'scipy quad'}, {t_quad:.1f} s): {wfs.n_valid} subapertures x {mirror.n_actuators} actuators; noise {args.noise:g} "
          f"of its largest element")
    for q in () if args.hcipy else (8, 16, 32):
        G_model = ShackHartmann(n_across=10, pupil_diameter=8.0, oversample=q).geometry_matrix(mirror, registration=truth)
        print(f"  torchblur's G (shack_hartmann.mean_slopes, oversample {q}) at the true registration: largest difference "
              f"{np.abs(G_model - G_true).max() / scale:.2e} of the largest element, rms {np.sqrt(np.mean((G_model - G_true) ** 2)) / scale:.2e}")
    names = ("shift_x", "shift_y", "rotation_deg", "magnification", "coupling")
    true = np.array([truth.shift_x, truth.shift_y, truth.rotation_deg, truth.magnification, args.coupling])
    errs, zs, chi2, gz, times, betas, ratio = [], [], [], [], [], [], []
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        gain = 1 + 0.02 * rng.standard_normal(mirror.n_actuators)
        gain[20], gain[33] = 0.0, 0.3 * gain[33]
        std = np.full_like(G_true, args.noise * scale)
        D0 = G_true * gain + std * rng.standard_normal(G_true.shape)
        t0 = time.perf_counter()
        fit = fit_registration(D0, std, wfs, mirror.actuator_xy, coupling=0.15)
        times.append(time.perf_counter() - t0)
        r = fit.registration
        e = np.array([getattr(r, k) for k in names]) - true
        z = e / np.array([fit.std[k] for k in names])
        errs.append(e), zs.append(z), chi2.append(fit.reduced_chi2)
        betas.append((fit.diffraction_weight, fit.std["diffraction_weight"]))
        live = gain > 0
        ratio.append(np.median(fit.gain[live] / gain[live]))
        gz.append((fit.gain - gain)[live] / np.sqrt(std[0, 0] ** 2 / (fit.G[:, live] ** 2).sum(0) + fit.gain_var_registration[live]))
        print(f"seed {seed:2d}: error shift {e[0]:+.5f} {e[1]:+.5f} pitch, rotation {e[2]:+.4f} deg, magnification {e[3] / true[3] * 100:+.4f} %,"
              f" coupling {e[4]:+.5f}; z {' '.join(f'{v:+.2f}' for v in z)}; sensor weighting {betas[-1][0]:.3f} +- "
              f"{betas[-1][1]:.3f}; reduced chi2 {fit.reduced_chi2:.3f}{' (inflated)' if fit.inflated else ''}")
    errs, zs = np.array(errs), np.array(zs)
    rms = np.sqrt(np.mean(zs**2, 0))
    print(f"over {args.seeds} seeds (fit {np.median(times):.2f} s each, median): largest |error| shift {np.abs(errs[:, :2]).max():.5f} pitch "
          f"(bound 0.02), rotation {np.abs(errs[:, 2]).max():.4f} deg (0.1), magnification {np.abs(errs[:, 3]).max() / true[3] * 100:.4f} % (0.3), "
          f"coupling {np.abs(errs[:, 4]).max():.5f}")
    print("rms(error/std): " + ", ".join(f"{k} {v:.2f}" for k, v in zip(names, rms)) + f"; all: {np.sqrt(np.mean(zs**2)):.2f} "
          f"(honest: 0.8-1.3); reduced chi2 median {np.median(chi2):.3f}; rms(gain error/std) {np.sqrt(np.mean(np.square(gz))):.2f}; "
          f"fitted/true gain, median over the live actuators {min(ratio):.4f}..{max(ratio):.4f} over the seeds")
    ok = (np.abs(errs[:, :2]).max() < 0.02 and np.abs(errs[:, 2]).max() < 0.1 and np.abs(errs[:, 3]).max() / true[3] < 0.003
          and 0.8 <= np.sqrt(np.mean(zs**2)) <= 1.3)
    print(f"done-when (0.02 pitch, 0.1 deg, 0.3 %, rms(error/std) 0.8-1.3): {'holds' if ok else 'FAILS'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
