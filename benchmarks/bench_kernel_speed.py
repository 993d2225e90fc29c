"""What a measured kernel costs on each route (issue 29): the same fits with a GaussianPSF and with
its still image as a KernelPSF, on frames of that Gaussian (where the Gaussian is right and
``fit.psf=auto`` keeps it), timed in one process (each fit run ``--repeats`` times alternately,
the best time kept), with the largest difference of the two fits' estimates in their stds.

Routes and sizes (noise: Poisson-like ``sqrt(25 + image)``, seeded):
- sine: ``fit_sinusoid`` of 16 points, two exposures (0.3, 0.8 period) of 40x56 px, M 3-6 px.
- multisine: ``fit_multisine`` of 4 sets of 3 tones, 8 frames of 40x56 px.
- direct: ``fit_direct`` of a 12-point sweep (2 exposures, 40x56 px) of a 2-pole plant, started at the truth.
- coded: ``fit_sinusoid_coded`` of 8 single coded images of 24x48 px.
- spots: ``fit_sinusoid`` ``axes="xy"`` of 4 points x 9 spots, 8 frames of 32x32 px crops.

    python benchmarks/bench_kernel_speed.py [--threads 1] [--repeats 2]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from torchblur.fit.coded import fit_sinusoid_coded
from torchblur.render.coded import render_coded
from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.render.blur import render_blur
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow
from torchblur.sysid.direct import fit_direct
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function

F64 = torch.float64


def gaussian_and_kernel(center, H, W, sigma=(1.7, 1.4), rho=0.2, rate=4000 / 5e-3):
    """A tilted Gaussian spot of batch ``center.shape[:-1]`` and its still images ``[..., H, W]``
    (point-sampled, per second) as a KernelPSF of the same batch."""
    center = torch.as_tensor(center, dtype=F64)
    batch = center.shape[:-1]
    sx, sy = sigma
    cov = torch.tensor([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]], dtype=F64).expand(batch + (2, 2))
    g = GaussianPSF(center, cov, torch.full(batch, rate, dtype=F64))
    y, x = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    flat = [GaussianPSF(c, cv, a).evaluate(x, y) for c, cv, a in zip(g.center.reshape(-1, 2), g.cov.reshape(-1, 2, 2), g.amplitude.reshape(-1))]
    return g, KernelPSF(torch.stack(flat).reshape(batch + (H, W)))


def noisy(img, seed):
    s = torch.sqrt(25 + img.clamp_min(0))
    return img + s * torch.randn(img.shape, generator=torch.Generator().manual_seed(seed), dtype=F64), s


def timed(fn, repeats):
    best, out = math.inf, None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def sine_route(rng):
    n, H, W = 16, 40, 56
    g, k = gaussian_and_kernel(torch.tensor([[27.5 + rng.random() - 0.5, 19.5 + rng.random() - 0.5] for _ in range(n)]), H, W)
    om = torch.tensor(2 * math.pi * (20 + 780 * rng.random(n)))
    T = 2 * math.pi / om
    start = (T * rng.random())[:, None].expand(n, 2)
    win = ExposureWindow(start, torch.stack([0.3 * T, 0.8 * T], -1))
    M, ph = torch.tensor(3 + 3 * rng.random(n)), torch.tensor((2 * rng.random(n) - 1) * math.pi)
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1)[:, None], torch.stack([ph, ph], -1)[:, None], om[:, None])
    img, s = noisy(render_blur(traj, GaussianPSF(g.center[:, None], g.cov[:, None], g.amplitude[:, None]), win, height=H, width=W), 1)

    def fit(p):
        return lambda: fit_sinusoid(img, p, win, om, axes="x", noise_std=s)
    return fit(g), fit(k), lambda f: (f.amplitude, f.phase, f.amplitude_std, f.phase_std)


def multisine_route(rng):
    B, E, H, W = 4, 8, 40, 56
    g, k = gaussian_and_kernel(torch.tensor([[27.5, 19.5]] * B), H, W)
    f0 = 20 + 80 * rng.random(B)
    om = torch.tensor(2 * math.pi * f0[:, None] * np.array([3.0, 4.0, 5.0]))
    T0 = torch.tensor(1 / f0)[:, None]
    win = ExposureWindow(T0 * torch.tensor(rng.random((B, E))), T0 * torch.tensor(0.1 + 0.5 * rng.random((B, E))))
    theta = torch.tensor(np.concatenate([3 + 2 * rng.random((B, 3)), (2 * rng.random((B, 3)) - 1) * math.pi, np.ones((B, 1))], 1))
    img, s = noisy(render_multisine(theta, om, g, win, height=H, width=W), 2)

    def fit(p):
        return lambda: fit_multisine(img, p, win, om, noise_std=s, amplitude_guess=theta[:, :3])
    return fit(g), fit(k), lambda f: (f.amplitude, f.phase, f.amplitude_std, f.phase_std)


def direct_route(rng):
    F, H, W = 12, 40, 56
    wn, zeta, gain = 2 * math.pi * 250.0, 0.1, 8.0
    om = torch.tensor(wn * np.geomspace(0.3, 2.5, F))
    s_ = 1j * om.numpy()
    Hs = gain * wn**2 / (s_**2 + 2 * zeta * wn * s_ + wn**2)
    A = torch.tensor(4.0 / np.abs(Hs))
    M, ph = torch.tensor(np.abs(Hs)) * A, torch.tensor(np.angle(Hs))
    T = 2 * math.pi / om
    win = ExposureWindow((0.1 * T)[:, None].expand(F, 2), torch.stack([0.3 * T, 0.8 * T], -1))
    g, k = gaussian_and_kernel(torch.tensor([[27.5, 19.5]] * F), H, W)
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1)[:, None], torch.stack([ph, ph], -1)[:, None], om[:, None])
    img, s = noisy(render_blur(traj, GaussianPSF(g.center[:, None], g.cov[:, None], g.amplitude[:, None]), win, height=H, width=W), 3)
    frf = FrequencyResponse(om.numpy(), Hs * (1 + 0.01j), input_labels=["x"], output_labels=["x"])
    start = fit_transfer_function(frf, n_poles=2, n_zeros=0, weights="uniform")

    def fit(p):
        return lambda: fit_direct(img, p, win, om, A, start, form="modal", axis="x", noise_std=s)
    return fit(g), fit(k), lambda d: (torch.as_tensor(d.params), torch.as_tensor(d.std))


def coded_route(rng):
    B, H, W = 8, 24, 48
    om = 2 * math.pi * 200.0
    T = 1 / 200.0
    g, k = gaussian_and_kernel(torch.tensor([[23.5, 11.5]] * B), H, W)
    code = torch.tensor([[0.0, 0.2], [0.45, 0.55], [0.8, 0.9]], dtype=F64)
    win = ExposureWindow(torch.full((B,), 0.25 * T, dtype=F64), torch.full((B,), 0.5 * T, dtype=F64))
    M, ph = torch.tensor(4 + 2 * rng.random(B)), torch.tensor((2 * rng.random(B) - 1) * math.pi)
    traj = Sinusoid(torch.stack([M, torch.zeros_like(M)], -1), torch.stack([ph, ph], -1), torch.full((B, 2), om, dtype=F64))
    img, s = noisy(render_coded(traj, g, win, code, height=H, width=W), 4)

    def fit(p):
        return lambda: fit_sinusoid_coded(img, p, win, code, om, noise_std=s, n_phases=6)
    return fit(g), fit(k), lambda f: (f.amplitude, f.phase, f.amplitude_std, f.phase_std)


def spots_route(rng):
    n, K, E, h = 4, 9, 8, 32
    g, k = gaussian_and_kernel(torch.tensor([[15.5 + rng.random() - 0.5, 15.5 + rng.random() - 0.5] for _ in range(K)])
                               .expand(n, K, 2).contiguous(), h, h)
    om = torch.tensor(2 * math.pi * (20 + 780 * rng.random(n)))[:, None]
    T = 2 * math.pi / om
    win = ExposureWindow((0.1 * T)[..., None].expand(n, 1, E),
                         torch.cat([0.3 * T, 0.8 * T], -1).repeat_interleave(4, -1)[:, None])
    amp = torch.tensor(3 + 3 * rng.random((n, 2)))[:, None].expand(n, K, 2)
    ph = torch.tensor((2 * rng.random((n, 2)) - 1) * math.pi)[:, None].expand(n, K, 2)
    traj = Sinusoid(amp[..., None, :], ph[..., None, :], om[..., None])
    img, s = noisy(render_blur(traj, GaussianPSF(g.center[..., None, :], g.cov[..., None, :, :], g.amplitude[..., None]), win,
                               height=h, width=h), 5)

    def fit(p):
        return lambda: fit_sinusoid(img, p, win, om, axes="xy", noise_std=s)
    return fit(g), fit(k), lambda f: (f.amplitude, f.phase, f.amplitude_std, f.phase_std)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch threads {args.threads}; best of {args.repeats} alternating runs")
    print(f"  {'route':<10} {'Gaussian s':>10} {'kernel s':>9} {'ratio':>6}  {'max |diff| / std':>16}")
    for name, route in (("sine", sine_route), ("multisine", multisine_route), ("direct", direct_route), ("coded", coded_route),
                        ("spots", spots_route)):
        fg, fk, vals = route(np.random.default_rng(0))
        tg = tk = math.inf
        for _ in range(args.repeats):
            t, og = timed(fg, 1)
            tg = min(tg, t)
            t, ok = timed(fk, 1)
            tk = min(tk, t)
        vg, vk = vals(og), vals(ok)
        n_est = len(vg) // 2
        diff = max(float(((a - b).abs() / sd).max()) for a, b, sd in zip(vg[:n_est], vk[:n_est], vg[n_est:]))
        print(f"  {name:<10} {tg:10.2f} {tk:9.2f} {tk / tg:6.2f}  {diff:16.2e}", flush=True)


if __name__ == "__main__":
    main()
