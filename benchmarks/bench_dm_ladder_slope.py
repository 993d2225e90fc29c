"""The ladder's static shift ``s`` on noiseless HCIPy lenslet spots against the fitted-shift truth (issue 23).

``torchblur.dm.ladder_fit.static_slope`` turns every pattern's held images into ``s`` (px per unit
command): the slope at 0 of a cubic through the still's least-squares shift to each level. A run's
pattern responses are ``s G``, so an error of ``s`` common to a pattern's spots is a gain error of
that pattern, which the Hadamard demultiplexing hands to every actuator. Here, per Hadamard pattern
of ``configs/identify_dm.yaml``'s quick plan (64 patterns, 13 levels spanning +-1.3 x the command
the sweep expects, tests/hcipy_sh.py's optics and seed 23's gains, noiseless), the one scale ``eps``
of ``s`` against ``shift_truth x pattern x gain`` (least squares over the pattern's 80 spots), for:

- ``static_slope`` as the run computes it (Gauss-Newton to convergence), with the former 6 fixed
  steps, and with a quintic instead of the cubic;
- the ladder spline's ``dL/du`` at 0 on the still's Fourier shift derivatives (``s`` before issue
  23's cause 2);
- a +-0.01 poke of the pattern (its image change per unit command) on the still's Fourier shift
  derivatives (the renderer's, on the crop: the small-signal slope the library can form), and on
  the truth's own whole-pupil tilt derivatives (the truth's convention at a smaller poke of the
  whole pattern: what is left is the truth's own +-0.05 single-actuator poke).

Then where the differences come from:

- ``--secant-patterns``: the shift curve of a pattern, the least-squares shift to its images at
  +-u over u (one scale against the truth), in the truth's own convention (each spot fitted by the
  generator's still under a whole-pupil tilt, Gauss-Newton from the Fourier fit) and with the
  still's Fourier shift, at 1/6 (one level's spacing) and 1/2 of the ladder's reach;
- a pure whole-pupil tilt of t px read by the still's Fourier-shift fit (the crop's Fourier
  interpolation of a point-sampled coherent image);
- ``--noise-pattern``: the noise of ``s`` per spot from the run's ladder (``dm_plan.ladder_frames``
  frames per level, the still's brightest peak at ``camera.peak_fraction`` of the range, Poisson and
  read noise), cubic against the spline's ``dL/du`` at 0.

    python benchmarks/bench_dm_ladder_slope.py [--patterns 16] [--secant-patterns 9,33] [--noise-pattern 9]
"""
from __future__ import annotations

import argparse
import itertools
import os
import sys

import numpy as np
import torch
from scipy.interpolate import CubicSpline

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import hcipy_sh as hs  # noqa: E402

import torchblur.dm.ladder_fit as lf  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.config.budget import dm_geometry, dm_plan  # noqa: E402
from torchblur.identify.dm_ladder import ladder_levels  # noqa: E402

F64 = torch.float64
POKE = 0.01  #: the small poke of a whole pattern (input units)
TILT_STEP = 0.02  #: px: the tilts' central differences of the truth-convention Gauss-Newton steps
TILT_ITER = 2  #: its Gauss-Newton steps from the Fourier fit (one step left the secant at 2 px 0.06 % below two steps)


class Bench:
    """The generator, the run's ladder levels and the spots' crops, stills and derivative projections."""

    def __init__(self):
        cfg = load_config("configs/identify_dm.yaml", ["sweep.n=4", "dm_plan.budget_frames=512"])
        self.cfg, self.pats = cfg, np.asarray(dm_plan(cfg)[0].patterns)
        self.gen = gen = hs.HcipySH()
        self.gain = hs.draw_dynamics(gen.n_actuators, 23).gain
        self.levels = ladder_levels(cfg, self.pats, dm_geometry(cfg), 5.0)
        self.S, self.M, self.p = gen.shift_truth(), gen.valid.size, gen.optics.pitch_px
        self.rc = np.divmod(gen.valid, gen.optics.n_lenslets)
        self.still = self.crops(gen.still())
        self.proj_f = self._projector(lf.shift_derivatives(self.still))  # the still's Fourier shift derivatives
        self.proj_t = self._projector(self.crops(np.stack(gen.tilt_derivatives())).transpose(0, 1))  # the truth's tilts

    def crops(self, img) -> torch.Tensor:
        """``[..., H, W]`` -> ``[..., M, p, p]``: the subapertures' cells."""
        p = self.p
        return torch.as_tensor(np.stack([img[..., i * p:(i + 1) * p, j * p:(j + 1) * p] for i, j in zip(*self.rc)], -3), dtype=F64)

    def _projector(self, d) -> torch.Tensor:
        """``[M, 2, pp]``: the least-squares shift per unit image change on the derivatives ``d [M, 2, p, p]``."""
        d = d.reshape(self.M, 2, -1)
        return torch.linalg.pinv(d @ d.transpose(1, 2)) @ d

    def command(self, k, u) -> np.ndarray:
        """``[len(u), N]``: pattern ``k`` at the levels ``u`` (times the actuators' gains)."""
        return np.asarray(u, dtype=float)[:, None] * (self.pats[k] * self.gain)[None]

    def scale(self, k, s) -> float:
        """One scale ``eps`` of ``s [M, 2]`` against the truth of pattern ``k``."""
        t = torch.as_tensor((self.S @ (self.pats[k] * self.gain)).reshape(2, self.M).T)
        return float((s * t).sum() / (t * t).sum() - 1)

    def ladder(self, k) -> torch.Tensor:
        return self.crops(self.gen.intensity(self.command(k, self.levels[k]))).transpose(0, 1)  # [M, K, p, p]


def slope(b: Bench, L, lv, *, degree=lf.SLOPE_DEGREE, iters=lf.SHIFT_ITER) -> torch.Tensor:
    """``static_slope`` of ``L [M, K, p, p]`` at ``lv [K]`` with another polynomial degree or step count."""
    keep = lf.SLOPE_DEGREE, lf.SHIFT_ITER
    lf.SLOPE_DEGREE, lf.SHIFT_ITER = degree, iters
    try:
        return lf.static_slope(L, b.still, torch.as_tensor(lv, dtype=F64).expand(b.M, -1))[0]
    finally:
        lf.SLOPE_DEGREE, lf.SHIFT_ITER = keep


def spline_slope(b: Bench, L, lv) -> torch.Tensor:
    """The ladder spline's ``dL/du`` at 0 on the still's Fourier shift derivatives."""
    return (b.proj_f @ torch.as_tensor(CubicSpline(lv, L.numpy(), axis=1)(0.0, 1)).reshape(b.M, -1, 1))[..., 0]


def pattern_rows(b: Bench, n: int) -> dict:
    """Per pattern ``eps`` of every estimate of ``s`` (module docstring)."""
    rows = {}
    for k in range(n):
        lv, L = b.levels[k], b.ladder(k)
        poke = b.crops(b.gen.intensity(b.command(k, [POKE, -POKE])))
        dI = ((poke[0] - poke[1]) / (2 * POKE)).reshape(b.M, -1, 1)
        for key, s in (("static_slope (the run's cubic)", slope(b, L, lv)), ("static_slope, 6 fixed steps", slope(b, L, lv, iters=6)),
                       ("static_slope with a quintic", slope(b, L, lv, degree=5)), ("spline dL/du at 0 (former)", spline_slope(b, L, lv)),
                       (f"+-{POKE} poke, the still's Fourier derivs", (b.proj_f @ dI)[..., 0]),
                       (f"+-{POKE} poke, the truth's tilt derivs", (b.proj_t @ dI)[..., 0])):
            rows.setdefault(key, []).append(b.scale(k, s))
    return {key: np.asarray(v) * 100 for key, v in rows.items()}


def truth_shift(b: Bench, img, x0) -> np.ndarray:
    """``[M, 2]``: each spot's least-squares shift in the truth's convention (the generator's still
    under a whole-pupil tilt) to ``img [M, p, p]``, :data:`TILT_ITER` Gauss-Newton steps from ``x0 [M, 2]``."""
    out = np.array(x0, dtype=float)
    for _, (m, (i, j)) in itertools.product(range(TILT_ITER), enumerate(zip(*b.rc))):
        cell = (slice(i * b.p, (i + 1) * b.p), slice(j * b.p, (j + 1) * b.p))
        x, y, h = out[m, 0], out[m, 1], TILT_STEP
        J = np.stack([((b.gen.tilted(x + h, y) - b.gen.tilted(x - h, y)) / (2 * h))[cell].ravel(),
                      ((b.gen.tilted(x, y + h) - b.gen.tilted(x, y - h)) / (2 * h))[cell].ravel()], 1)
        out[m] += np.linalg.lstsq(J, (img[m].numpy() - b.gen.tilted(x, y)[cell]).ravel(), rcond=None)[0]
    return out


def secant_lines(b: Bench, patterns) -> list[str]:
    lines = []
    for k in patterns:
        U = np.abs(b.levels[k]).max()
        for f in (1 / 6, 1 / 2):
            u = f * U
            L = b.crops(b.gen.intensity(b.command(k, [u, -u]))).transpose(0, 1)  # [M, 2, p, p]
            s_f = slope(b, L, [u, -u], degree=1)
            s_t = (truth_shift(b, L[:, 0], u * s_f.numpy()) - truth_shift(b, L[:, 1], -u * s_f.numpy())) / (2 * u)
            motion = float(np.hypot(*(b.S @ (b.pats[k] * b.gain)).reshape(2, b.M)).max() * u)
            lines.append(f"pattern {k}, +-{f:.3g} of the reach ({motion:.2f} px): truth's convention {b.scale(k, torch.as_tensor(s_t)) * 100:+.3f} %, "
                         f"the still's Fourier shift {b.scale(k, s_f) * 100:+.3f} %")
    return lines


def tilt_lines(b: Bench) -> list[str]:
    out = []
    for t in (0.01, 0.25, 0.5, 1.0, 2.0, 4.0):
        L = b.crops(np.stack([b.gen.tilted(t, 0), b.gen.tilted(-t, 0)])).transpose(0, 1)
        s = slope(b, L, [t, -t], degree=1)[:, 0] - 1
        out.append(f"{t:g} px: {float(s.mean()) * 100:+.3f} % (sd {float(s.std()) * 100:.3f} % over the spots)")
    return out


def noise_line(b: Bench, k: int, draws: int) -> str:
    cam, n = b.cfg.camera, int(b.cfg.dm_plan.ladder_frames)
    peak = float(cam.peak_fraction) * (2 ** int(cam.bit_depth) - 1) * float(cam.gain)  # e- at the still's brightest peak
    lv, L = b.levels[k], b.ladder(k)
    sd = ((peak * L.clamp_min(0) + float(cam.read_noise) ** 2) / n).sqrt() / peak  # the mean of n frames, still peak 1
    g = torch.Generator().manual_seed(0)
    ref = {"cubic": slope(b, L, lv), "spline": spline_slope(b, L, lv)}
    err = {key: [] for key in ref}
    for _ in range(draws):
        Ln = L + sd * torch.randn(L.shape, generator=g, dtype=F64)
        for key, fn in (("cubic", lambda: slope(b, Ln, lv)), ("spline", lambda: spline_slope(b, Ln, lv))):
            err[key].append(fn() - ref[key])
    big = ref["cubic"].norm(dim=1) > 0.3 * ref["cubic"].norm(dim=1).max()
    rel = {key: float((torch.stack(v).norm(dim=-1) / ref["cubic"].norm(dim=-1))[:, big].square().mean().div(2).sqrt()) * 100
           for key, v in err.items()}
    return (f"pattern {k}, {n} frames per level, still peak {peak:.0f} e-, {draws} draws: per spot and axis {rel['cubic']:.3f} % "
            f"(cubic), {rel['spline']:.3f} % (spline dL/du at 0: x{rel['spline'] / rel['cubic']:.1f}), of |s| over the spots above 0.3 of the largest")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patterns", type=int, default=16, help="the first N Hadamard patterns")
    ap.add_argument("--secant-patterns", default="9,33", help="patterns whose shift curve is fitted in the truth's convention ('' none)")
    ap.add_argument("--noise-pattern", type=int, default=9, help="-1: no noise draws")
    ap.add_argument("--noise-draws", type=int, default=8)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    b = Bench()
    rows = pattern_rows(b, args.patterns)
    print(f"s against shift_truth x pattern x gain, one scale per pattern (noiseless HCIPy ladders, {args.patterns} Hadamard patterns, "
          f"{b.levels.shape[1]} levels up to +-{np.abs(b.levels[:args.patterns]).max(1).min():.3g}..{np.abs(b.levels[:args.patterns]).max():.3g}):")
    for key, v in rows.items():
        print(f"  {key:44s} eps mean {v.mean():+.3f} %, sd {v.std():.3f} % over patterns")
    keys = list(rows)
    run, fourier, tilt = rows[keys[0]], rows[keys[4]], rows[keys[5]]
    print(f"  the run's eps {run.mean():+.3f} % = the truth's own +-0.05 poke {tilt.mean():+.3f} (sd {tilt.std():.3f}) + the still's "
          f"Fourier derivatives for the truth's tilts at {POKE} {(fourier - tilt).mean():+.3f} (sd {(fourier - tilt).std():.3f}) + the cubic "
          f"over the ladder for the slope at 0 {(run - fourier).mean():+.3f} (sd {(run - fourier).std():.3f}) %")
    for line in secant_lines(b, [int(k) for k in args.secant_patterns.split(",") if k.strip()]):
        print(f"  shift curve, {line}")
    for line in tilt_lines(b):
        print(f"  a whole-pupil tilt read by the still's Fourier-shift fit, {line}")
    if args.noise_pattern >= 0:
        print(f"  noise of s, {noise_line(b, args.noise_pattern, args.noise_draws)}")


if __name__ == "__main__":
    main()
