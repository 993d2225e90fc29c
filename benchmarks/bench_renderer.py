"""Renderer speed against the cost floor of a naive 256-sample splat (issue 2).

Renders B=160 frames of 64x64: a 2 px spot moving 4-12 px over half a period, with the
nodes the renderer chooses, and prints the time as a ratio to a bare torch.bmm of
[160, 64, 256] x [160, 256, 64], measured in the same run. Also a tilted PSF and float64.

    python benchmarks/bench_renderer.py [--threads N] [--repeats R]
"""
from __future__ import annotations

import argparse
import math
import time

import torch

import torchblur as tb
from torchblur.render.blur import RenderSettings, choose_node_count


def best_time(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def problem(B: int, tilted: bool, dtype, gen):
    f = 100.0
    omega = torch.full((B,), 2 * math.pi * f, dtype=dtype)
    amp = 4 + 8 * torch.rand(B, generator=gen, dtype=dtype)
    ang = 2 * math.pi * torch.rand(B, generator=gen, dtype=dtype)
    A = torch.stack([amp * torch.cos(ang), amp * torch.sin(ang)], -1)
    phase = (2 * math.pi * torch.rand(B, 2, generator=gen, dtype=dtype)).requires_grad_()
    A = A.requires_grad_()
    center = (torch.full((B, 2), 31.5, dtype=dtype) + torch.rand(B, 2, generator=gen, dtype=dtype)).requires_grad_()
    if tilted:
        psf = tb.GaussianPSF.from_axes(center, torch.full((B,), 2.4, dtype=dtype), torch.full((B,), 1.6, dtype=dtype),
                                       torch.full((B,), 0.6, dtype=dtype))
    else:
        psf = tb.GaussianPSF.isotropic(center, torch.full((B,), 2.0, dtype=dtype))
    start = torch.rand(B, generator=gen, dtype=dtype) / f
    win = tb.ExposureWindow(start, torch.full((B,), 0.5 / f, dtype=dtype))
    return tb.Sinusoid(A, phase, omega), psf, win, (A, phase, center)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    B, H, W = 160, 64, 64
    a = torch.randn(B, 64, 256, generator=gen)
    b = torch.randn(B, 256, 64, generator=gen)
    t_bmm = best_time(lambda: torch.bmm(a, b), args.repeats)
    print(f"threads={args.threads}  baseline torch.bmm [160,64,256]x[160,256,64] float32: {t_bmm * 1e3:.2f} ms")
    renderer = tb.BlurRenderer(H, W)
    for tilted in (False, True):
        for dtype in (torch.float32, torch.float64):
            traj, psf, win, params = problem(B, tilted, dtype, gen)
            S = choose_node_count(traj.path_length(win), psf.sigma_min(), RenderSettings())

            def fwd():
                with torch.no_grad():
                    renderer(traj, psf, win)

            def fwd_bwd():
                img = renderer(traj, psf, win)
                torch.autograd.grad(img.square().sum(), params)

            tf = best_time(fwd, args.repeats)
            tfb = best_time(fwd_bwd, args.repeats)
            kind = "tilted " if tilted else "round  "
            print(f"{kind} {str(dtype)[6:]:8s} S={S:4d}  forward {tf * 1e3:7.2f} ms = {tf / t_bmm:5.2f}x bmm   "
                  f"forward+backward {tfb * 1e3:7.2f} ms = {tfb / t_bmm:5.2f}x bmm")


if __name__ == "__main__":
    main()
