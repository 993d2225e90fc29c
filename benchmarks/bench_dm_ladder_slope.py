"""The ladder's static shift ``s`` on noiseless HCIPy lenslet spots against the fitted-shift truth (issue 23).

``torchblur.dm.ladder_fit.static_slope`` turns every pattern's held images into ``s`` (px per unit
command): the slope at 0 of a cubic through the still's least-squares shift to each level. A run's
pattern responses are ``s G``, so an error of ``s`` common to a pattern's spots is a gain error of
that pattern, which the Hadamard demultiplexing hands to every actuator. Here, per Hadamard pattern
of ``configs/identify_dm.yaml``'s quick plan (64 patterns, 13 levels spanning +-1.3 x the command
the sweep expects, tests/hcipy_sh.py's optics and seed 23's gains, noiseless), the one scale ``eps``
of ``s`` against ``shift_truth x pattern x gain`` (least squares over the pattern's 80 spots):

- ``static_slope`` as the run computes it (Gauss-Newton to convergence), and with the former 6
  fixed steps;
- ``still-shift convention``: the least-squares shift of the still's Fourier shift derivatives
  (the renderer's, on the crop) under a small poke of the pattern (+-0.01 of a unit): what ``s``
  would be without the shift's nonlinearity over the ladder's reach; it differs from the truth's
  whole-pupil tilt derivatives by the lenslets' interference.

    python benchmarks/bench_dm_ladder_slope.py [--patterns 16]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import hcipy_sh as hs  # noqa: E402

import torchblur.dm.ladder_fit as lf  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.config.budget import dm_geometry, dm_plan  # noqa: E402
from torchblur.identify.dm_ladder import ladder_levels  # noqa: E402

F64 = torch.float64


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patterns", type=int, default=16, help="the first N Hadamard patterns")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config("configs/identify_dm.yaml", ["sweep.n=4", "dm_plan.budget_frames=512"])
    pats = np.asarray(dm_plan(cfg)[0].patterns)[:args.patterns]
    gen = hs.HcipySH()
    gain = hs.draw_dynamics(gen.n_actuators, 23).gain
    levels = ladder_levels(cfg, pats, dm_geometry(cfg), 5.0)
    S, M, p = gen.shift_truth(), gen.valid.size, gen.optics.pitch_px
    r, c = np.divmod(gen.valid, gen.optics.n_lenslets)

    def crops(img):  # [..., H, W] -> [..., M, p, p]: the subapertures' cells
        return torch.as_tensor(np.stack([img[..., i * p:(i + 1) * p, j * p:(j + 1) * p] for i, j in zip(r, c)], -3), dtype=F64)
    still = crops(gen.still())
    dsh = lf.shift_derivatives(still).reshape(M, 2, p * p)
    proj = torch.linalg.pinv(dsh @ dsh.transpose(1, 2)) @ dsh  # [M, 2, pp]: the least-squares shift per unit image change
    eps = {"static_slope (converged)": [], "static_slope, 6 fixed steps": [], "still-shift convention (+-0.01 poke)": []}
    iters = lf.SHIFT_ITER
    for k, pat in enumerate(pats):
        truth = torch.as_tensor((S @ (pat * gain)).reshape(2, M).T)

        def scale(s):
            return float((s * truth).sum() / (truth * truth).sum() - 1)
        L = crops(gen.intensity(levels[k][:, None] * (pat * gain)[None])).transpose(0, 1)  # [M, K, p, p]
        lv = torch.as_tensor(levels[k], dtype=F64).expand(M, -1)
        for key, n in (("static_slope (converged)", iters), ("static_slope, 6 fixed steps", 6)):
            lf.SHIFT_ITER = n
            eps[key].append(scale(lf.static_slope(L, still, lv)[0]))
        lf.SHIFT_ITER = iters
        poke = crops(gen.intensity(np.stack([0.01 * pat * gain, -0.01 * pat * gain])))
        eps["still-shift convention (+-0.01 poke)"].append(scale((proj @ ((poke[0] - poke[1]) / 0.02).reshape(M, -1, 1))[..., 0]))
    print(f"s against shift_truth x pattern x gain, one scale per pattern (noiseless HCIPy ladders, {len(pats)} Hadamard patterns, "
          f"{levels.shape[1]} levels up to +-{np.abs(levels).max(1).min():.3g}..{np.abs(levels).max():.3g}):")
    for key, v in eps.items():
        v = np.asarray(v) * 100
        print(f"  {key:38s} eps mean {v.mean():+.3f} %, sd {v.std():.3f} % over patterns")


if __name__ == "__main__":
    main()
