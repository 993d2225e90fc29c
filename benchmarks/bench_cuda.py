"""The renderer, the sinusoid fitter (Gaussian and measured-kernel PSF) and the DM spot fitter on
CUDA, against the same calls on the CPU in the same process: agreement and speed.

Every section computes the same problems on ``cpu`` and on ``--device`` and prints

- agreement: the largest difference between the two devices, relative to the image peak
  (renders) or in units of the fit's own std (fits), and how many items' statuses differ;
- speed: the time on each device (CUDA synchronised, the fastest of ``--repeats``) and the
  ratio CPU / device, with a bare ``torch.bmm`` of the same shape timed on each device as the
  baseline of that device (ratios, not absolute times, are what compare across machines).

Sections: ``render`` (``BlurRenderer`` forward and forward+backward, round and tilted Gaussian
PSF, float32 and float64, 160 and 4096 frames of 64 x 64; the backward of a fixed random weighting
of the image), ``gradcheck`` (the gradients on the device against central differences there),
``kernel`` (``render_blur`` with a ``KernelPSF``),
``fit`` (``fit_sinusoid``, the problems of ``bench_fit.py``, float64: 300 on both devices, then
3000 on the device alone), ``fit_kernel`` (the same problems fitted through a measured kernel
of the same spot: 40 on both, 1000 on the device), ``ladder`` (the ladder spot fit of
``bench_dm.py``'s problems, 4 patterns x 80 spots on both) and ``dm`` (``bench_dm.py --device``). Without CUDA, ``--device cpu`` runs the same code on both
sides (a check of the script itself).

    python benchmarks/bench_cuda.py [--device cuda] [--sections render gradcheck kernel fit fit_kernel ladder dm] [--repeats 3]
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
import traceback

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import torchblur as tb  # noqa: E402
from bench_fit import make_problems  # noqa: E402
from torchblur.fit.sinusoid import fit_sinusoid  # noqa: E402


def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def best_time(fn, dev: torch.device, repeats: int) -> tuple[float, object]:
    out = fn()
    sync(dev)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        sync(dev)
        best = min(best, time.perf_counter() - t0)
    return best, out


def to(x, dev):
    """Tensors, and the PSF/window/trajectory objects of torchblur (their ``.to``), on ``dev``."""
    if isinstance(x, torch.Tensor):
        return x.to(dev)
    if hasattr(x, "to"):
        return x.to(device=dev)
    return x


def bmm_baseline(dev: torch.device, repeats: int) -> float:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(160, 64, 256, generator=g).to(dev)
    b = torch.randn(160, 256, 64, generator=g).to(dev)
    return best_time(lambda: torch.bmm(a, b), dev, repeats)[0]


def render_problem(B: int, dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    f = 100.0
    omega = torch.full((B,), 2 * math.pi * f, dtype=dtype)
    amp = 4 + 8 * torch.rand(B, generator=g, dtype=dtype)
    ang = 2 * math.pi * torch.rand(B, generator=g, dtype=dtype)
    A = torch.stack([amp * torch.cos(ang), amp * torch.sin(ang)], -1)
    phase = 2 * math.pi * torch.rand(B, 2, generator=g, dtype=dtype)
    center = torch.full((B, 2), 31.5, dtype=dtype) + torch.rand(B, 2, generator=g, dtype=dtype)
    start = torch.rand(B, generator=g, dtype=dtype) / f
    return A, phase, omega, center, start, torch.full((B,), 0.5 / f, dtype=dtype)


def section_render(dev, repeats: int) -> None:
    cpu = torch.device("cpu")
    base = {d.type: bmm_baseline(d, repeats) for d in (cpu, dev)}
    print(f"[render] baseline bmm [160,64,256]x[160,256,64] float32: cpu {base['cpu'] * 1e3:.3f} ms, "
          f"{dev.type} {base[dev.type] * 1e3:.3f} ms")
    renderer = tb.BlurRenderer(64, 64)
    for B, tilted, dtype in ((160, False, torch.float32), (160, False, torch.float64), (4096, False, torch.float32),
                             (4096, False, torch.float64), (160, True, torch.float32), (4096, True, torch.float64)):
        raw = render_problem(B, dtype)
        res = {}
        for d in (cpu, dev):
            A, phase, omega, center, start, dur = (v.to(d) for v in raw)
            A, phase, center = (v.clone().requires_grad_() for v in (A, phase, center))
            traj = tb.Sinusoid(A, phase, omega)
            full = lambda v: torch.full((B,), v, dtype=dtype, device=d)  # noqa: E731
            psf = (tb.GaussianPSF.from_axes(center, full(2.4), full(1.6), full(0.6)) if tilted
                   else tb.GaussianPSF.isotropic(center, full(2.0)))
            win = tb.ExposureWindow(start, dur)

            def fwd():
                with torch.no_grad():
                    return renderer(traj, psf, win)

            weight = torch.randn((B, 64, 64), generator=torch.Generator().manual_seed(2), dtype=dtype).to(d)

            def fwd_bwd():
                # a fixed random weighting of the image: every gradient O(1) (a sum of squares is
                # nearly invariant to the motion, its gradients near rounding level)
                img = renderer(traj, psf, win)
                return torch.autograd.grad((img * weight).sum(), (A, phase, center))

            tf, img = best_time(fwd, d, repeats)
            tfb, grads = best_time(fwd_bwd, d, repeats)
            res[d.type] = (tf, tfb, img.detach().cpu(), [gg.detach().cpu() for gg in grads])
        (tfc, tfbc, ic, gc), (tfd, tfbd, idv, gd) = res["cpu"], res[dev.type]
        rel = float((ic - idv).abs().max() / ic.abs().max())
        grel = max(float((a - b).abs().max() / a.abs().max()) for a, b in zip(gc, gd))
        print(f"[render] B={B:5d} {'tilted' if tilted else 'round '} {str(dtype)[6:]:8s} forward: cpu {tfc * 1e3:8.2f} ms ({tfc / base['cpu']:6.2f}x bmm), "
              f"{dev.type} {tfd * 1e3:7.3f} ms ({tfd / base[dev.type]:6.2f}x bmm), cpu/{dev.type} {tfc / tfd:7.1f}; "
              f"fwd+bwd: cpu {tfbc * 1e3:8.2f} ms, {dev.type} {tfbd * 1e3:7.3f} ms, cpu/{dev.type} {tfbc / tfbd:7.1f}; "
              f"max |image diff|/peak {rel:.1e}, max |grad diff|/max|grad| {grel:.1e} (loss: a random weighting of the image)")


def section_gradcheck(dev) -> None:
    """The renderer's gradients on ``dev`` against central differences on ``dev`` (float64, 160
    frames, round and tilted PSF): the relative error of the directional derivative along a random
    direction, per parameter."""
    B, dtype = 160, torch.float64
    A, phase, omega, center, start, dur = (v.to(dev) for v in render_problem(B, dtype))
    weight = torch.randn((B, 64, 64), generator=torch.Generator().manual_seed(2), dtype=dtype).to(dev)
    renderer = tb.BlurRenderer(64, 64)
    full = lambda v: torch.full((B,), v, dtype=dtype, device=dev)  # noqa: E731
    gen = torch.Generator().manual_seed(1)
    for tilted in (False, True):
        def loss(A, phase, center):
            psf = (tb.GaussianPSF.from_axes(center, full(2.4), full(1.6), full(0.6)) if tilted
                   else tb.GaussianPSF.isotropic(center, full(2.0)))
            return (renderer(tb.Sinusoid(A, phase, omega), psf, tb.ExposureWindow(start, dur)) * weight).sum()

        xs = [v.clone().requires_grad_() for v in (A, phase, center)]
        grads = torch.autograd.grad(loss(*xs), xs)
        errs = []
        for i in range(3):
            v = torch.randn(xs[i].shape, generator=gen, dtype=dtype).to(dev)
            p = [x.detach().clone() for x in xs]
            m = [x.detach().clone() for x in xs]
            p[i] += 1e-6 * v
            m[i] -= 1e-6 * v
            with torch.no_grad():
                fd = float((loss(*p) - loss(*m)) / 2e-6)
            errs.append(abs(fd - float((grads[i] * v).sum())) / abs(fd))
        print(f"[gradcheck] {dev.type} float64 {'tilted' if tilted else 'round '}: directional derivative vs central "
              f"difference, relative error: amplitude {errs[0]:.1e}, phase {errs[1]:.1e}, centre {errs[2]:.1e}")


def section_kernel(dev, repeats: int) -> None:
    cpu = torch.device("cpu")
    for B, dtype in ((160, torch.float32), (160, torch.float64), (2048, torch.float32)):
        raw = render_problem(B, dtype, seed=1)
        yy, xx = torch.meshgrid(torch.arange(64, dtype=dtype), torch.arange(64, dtype=dtype), indexing="ij")
        res = {}
        for d in (cpu, dev):
            A, phase, omega, center, start, dur = (v.to(d) for v in raw)
            r2 = (xx.to(d) - center[:, 0, None, None]) ** 2 + (yy.to(d) - center[:, 1, None, None]) ** 2
            kern = tb.KernelPSF(torch.exp(-r2 / (2 * 1.5**2)) * 1e3)
            win = tb.ExposureWindow(start, dur)
            t, img = best_time(lambda: tb.render_blur(tb.Sinusoid(A, phase, omega), kern, win, height=64, width=64), d, repeats)
            res[d.type] = (t, img.cpu())
        (tc, ic), (td, idv) = res["cpu"], res[dev.type]
        rel = float((ic - idv).abs().max() / ic.abs().max())
        print(f"[kernel] B={B:5d} {str(dtype)[6:]:8s} render_blur(KernelPSF): cpu {tc * 1e3:8.2f} ms, {dev.type} {td * 1e3:7.3f} ms, "
              f"cpu/{dev.type} {tc / td:7.1f}; max |image diff|/peak {rel:.1e}")


def _fit_on(d, dev, psf_kind: str):
    images, win, om, sigma = (to(d[k], dev) for k in ("images", "win", "om", "sigma"))
    if psf_kind == "gaussian":
        psf = to(d["psf"], dev)
    else:
        psf = to(d["kernel"], dev)
    return fit_sinusoid(images, psf, win, om, noise_std=sigma)


def _kernel_of(d) -> None:
    """The problems' own tilted Gaussian sampled on the frame: a measured kernel of the same spot."""
    yy, xx = torch.meshgrid(torch.arange(48, dtype=torch.float64), torch.arange(64, dtype=torch.float64), indexing="ij")
    P, c = d["psf"].precision(), d["psf"].center
    dx, dy = xx - c[:, 0, None, None], yy - c[:, 1, None, None]
    q = P[0][:, None, None] * dx * dx + 2 * P[1][:, None, None] * dx * dy + P[2][:, None, None] * dy * dy
    d["kernel"] = tb.KernelPSF(torch.exp(-0.5 * q))


def section_fit(dev, repeats: int, psf_kind: str, n_cmp: int, n_big: int) -> None:
    """``n_cmp`` problems on both devices (agreement, speed); ``n_big`` on ``dev`` alone (throughput
    at a size the CPU side would take minutes for; the rms of the amplitude's error/std)."""
    cpu = torch.device("cpu")
    d = make_problems(n_big, torch.float64, seed=0)
    small = {k: v[:n_cmp] for k, v in d.items()}
    if psf_kind == "kernel":
        _kernel_of(d)
        _kernel_of(small)
    tc, fc = best_time(lambda: _fit_on(small, cpu, psf_kind), cpu, max(1, repeats - 1))
    td, fd = best_time(lambda: _fit_on(small, dev, psf_kind), dev, max(1, repeats - 1))
    std = fc.amplitude_std.cpu().clamp_min(1e-300)
    dM = float(((fc.amplitude.cpu() - fd.amplitude.cpu()).abs() / std).max())
    dP = float((tb.wrap_phase(fc.phase.cpu() - fd.phase.cpu()).abs() / fc.phase_std.cpu().clamp_min(1e-300)).max())
    nstat = int((fc.status.cpu() != fd.status.cpu()).sum())
    print(f"[fit:{psf_kind}] n={n_cmp:5d} float64: cpu {tc:7.3f} s ({tc / n_cmp * 1e3:7.3f} ms/problem), {dev.type} {td:7.3f} s "
          f"({td / n_cmp * 1e3:7.3f} ms/problem), cpu/{dev.type} {tc / td:6.1f}; max |dM|/std {dM:.1e}, "
          f"max |dphi|/std {dP:.1e}, statuses differing {nstat}", flush=True)
    tb_, fb = best_time(lambda: _fit_on(d, dev, psf_kind), dev, 1)
    eM = fb.amplitude.cpu().double() - d["M"]
    zM = float((eM / fb.amplitude_std.cpu().double()).square().mean().sqrt())
    print(f"[fit:{psf_kind}] n={n_big:5d} float64 on {dev.type}: {tb_:7.3f} s ({tb_ / n_big * 1e3:7.3f} ms/problem, "
          f"{tb_ / n_big / (td / n_cmp):.2f}x the per-problem time at n={n_cmp}); rms(M error/std) {zM:.2f}; "
          f"status 0: {int((fb.status == 0).sum())} of {n_big}", flush=True)


def section_ladder(dev, n_spots: int, n_patterns: int) -> None:
    """The ladder spot fit (``dm_plan.spot_model=ladder``, bench_dm.py's :func:`ladder_problems`) of the
    same problems on the CPU and on ``dev``: the largest amplitude and phase difference in the CPU
    fit's stds, statuses that differ, and the time on each (the slopes included)."""
    from bench_dm import _fit_ladder, ladder_problems

    import torchblur.dm.ladder_fit as lf
    d = ladder_problems(n_spots, n_patterns, seed=2)
    out = {}
    for x in (torch.device("cpu"), dev):
        dd = {k: v.to(x) if isinstance(v, torch.Tensor) else v for k, v in d.items()}
        _fit_ladder(dd, lf, slice(0, 1))  # warm-up (one pattern)
        sync(x)
        t0 = time.perf_counter()
        fits = _fit_ladder(dd, lf)[0]
        sync(x)
        out[x.type] = (time.perf_counter() - t0, fits)
    (tc, fc), (td, fd) = out["cpu"], out[dev.type]
    ok = (fc.status == 0) & (fd.status.cpu() == 0)
    sd = torch.diagonal(fc.covariance, dim1=-2, dim2=-1).sqrt()
    dM = float(((fc.amplitude - fd.amplitude.cpu()).abs() / sd[..., ::2])[ok].max())
    dP = float((tb.wrap_phase(fc.phase - fd.phase.cpu()).abs() / sd[..., 1::2])[ok].max())
    n = fc.status.numel()
    print(f"[ladder] {n} problems ({n_patterns} patterns x {n_spots} spots) float64: cpu {tc:.2f} s ({n / tc:.1f}/s), {dev.type} {td:.2f} s "
          f"({n / td:.1f}/s), cpu/{dev.type} {tc / td:.1f}; max |dM|/std {dM:.1e}, max |dphi|/std {dP:.1e}, statuses differing "
          f"{int((fc.status != fd.status.cpu()).sum())}, ok {int(ok.sum())} of {n}", flush=True)


def section_dm(dev) -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    cmd = [sys.executable, os.path.join(here, "bench_dm.py"), "--device", str(dev), "--cases", "8/10", "18/20", "32/34"]
    print("[dm] " + " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sections", nargs="+", default=["render", "gradcheck", "kernel", "fit", "fit_kernel", "ladder", "dm"])
    ap.add_argument("--ladder-size", type=int, nargs=2, default=[80, 4], metavar=("SPOTS", "PATTERNS"),
                    help="the ladder section's problems: spots x patterns (on both devices)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fit-sizes", type=int, nargs=2, default=[300, 3000], metavar=("N_BOTH", "N_DEVICE"),
                    help="Gaussian fits: problems on both devices, then on the device alone")
    ap.add_argument("--kernel-fit-sizes", type=int, nargs=2, default=[40, 1000], metavar=("N_BOTH", "N_DEVICE"),
                    help="kernel-PSF fits: problems on both devices, then on the device alone")
    args = ap.parse_args()
    dev = torch.device(args.device)
    if dev.type == "cuda":
        print(f"device: {torch.cuda.get_device_name(dev)}, torch {torch.__version__}, cpu threads {torch.get_num_threads()}")
    for s in args.sections:
        t0 = time.perf_counter()
        try:
            if s == "render":
                section_render(dev, args.repeats)
            elif s == "gradcheck":
                section_gradcheck(dev)
            elif s == "kernel":
                section_kernel(dev, args.repeats)
            elif s == "fit":
                section_fit(dev, args.repeats, "gaussian", *args.fit_sizes)
            elif s == "fit_kernel":
                section_fit(dev, args.repeats, "kernel", *args.kernel_fit_sizes)
            elif s == "ladder":
                section_ladder(dev, *args.ladder_size)
            elif s == "dm":
                section_dm(dev)
            else:
                raise SystemExit(f"--sections: unknown section {s!r}")
        except Exception:  # a failing section is reported and the others still run
            print(f"[{s}] FAILED:\n{traceback.format_exc()}")
        print(f"[{s}] section wall {time.perf_counter() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main()
