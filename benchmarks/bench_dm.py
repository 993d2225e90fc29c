"""DM spot-fit throughput and peak memory, as ratios to the single-spot fitter, and the plan
comparison (issue 17).

1. Throughput: for mirrors of about 50, 241 and 820 actuators (8/10, 18/20, 32/34 actuators /
   subapertures across), the spot problems of ``--points`` sweep points (every valid
   subaperture's spot: a 16x16 px crop, sigma 1.2 px, 2 exposures x 2 repeats, a random 2-D
   sinusoid of 0.5-3 px at 10 Hz-2 kHz, camera noise: shot + 3 e- read) are fitted by
   :func:`torchblur.dm.spot_fit.fit_spot_problems` (batched, chunks from the free memory) and,
   on the first ``--single`` problems, by ``fit_sinusoid`` one problem per call (the
   single-spot fitter). Each fit runs in its own process so the peak memory is its own: the
   rise of the peak RSS over the loaded crops (CPU) or ``torch.cuda.max_memory_allocated``
   (CUDA). Printed: problems/s and peak MB of both, and their ratios.
   With kernels (issue 23): the same problems by ``fit_spot_problems`` with every spot's measured
   kernel (a :class:`~torchblur.render.psf.KernelPSF` ``[M, h, w]``: here the spot's exact image,
   so the figures are the kernel path's cost, not a PSF error), problems/s and the ratio to the
   Gaussian batched run; and whether that keeps up with a 30 Hz camera on
   ``configs/identify_dm.yaml`` (64 patterns x 80 spots per frequency, 64 x 4 frames = 8.5 s of
   acquisition per frequency at 30 Hz, 16 frequencies).
2. Plans (when d1's ``torchblur.dm.plans`` is present): for the ``configs/identify_dm.yaml``
   mirror (8 across, 10x10 sensor), the frames one-at-a-time needs to reach the worst D std
   the chosen plan reaches with its frames, from the demultiplexing covariance
   (:func:`torchblur.dm.demux.demultiplex`, every response of std ``sigma_1 / a``, ``a`` the
   plan's amplitude for a ``target_px`` motion), beside ``plan_cost``'s ratio.

3. The ladder spot fit (``dm_plan.spot_model=ladder``, issue 23): problems/s for the same three
   mirrors (``--ladder-points`` patterns x every subaperture's spot on its own ladder,
   :func:`ladder_problems`), each in its own process; with ``--ladder-baseline REV`` the same
   problems by the ladder fit of git revision ``REV`` in the same process (speed-up, largest
   difference in stds); and the 30 Hz test on ``configs/identify_dm.yaml`` with the ladder.

    python benchmarks/bench_dm.py [--device cuda] [--cases 8/10 18/20 32/34] [--points 2] [--single 24] [--threads N]
        [--ladder-points 2] [--ladder-baseline 1d13187] [--no-plans]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.config.budget import dm_ladder_plan
from torchblur.design.windows import dual_exposure_windows
from torchblur.dm.plans import driven_spots
from torchblur.identify.dm_plan import AMPLITUDE_LAG
from torchblur.identify.keep_up import sweep_schedule
from torchblur.render.alias import wrap_phase
from torchblur.render.blur import render_blur
from torchblur.render.camera import camera_noise_std
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

CROP, SIGMA, PEAK_E, READ_E, FRACS, R = 16, 1.2, 2000.0, 3.0, (0.3, 0.8), 2


def grid_count(n: int, radius: float) -> int:
    """Cells of an n x n grid (pitch 1, centred) whose centre lies within ``radius``."""
    c = np.arange(n) - (n - 1) / 2
    x, y = np.meshgrid(c, c)
    return int(np.sum(np.hypot(x, y) <= radius + 1e-9))


def case_sizes(spec: str) -> tuple[int, int]:
    """``"8/10"`` -> (actuators inside the pupil, valid subapertures): d1's mirror and sensor
    where present, else the actuator rule ``|r| <= n/2 + 0.1`` pitches and subapertures whose
    centre is within the pupil less a quarter cell."""
    n_dm, n_wfs = (int(v) for v in spec.split("/"))
    try:
        from torchblur.dm.mirror import actuator_grid
        from torchblur.dm.shack_hartmann import ShackHartmann
    except ImportError:
        return grid_count(n_dm, n_dm / 2 + 0.1), grid_count(n_wfs, n_wfs / 2 - 0.25)
    return len(actuator_grid(n_dm)), ShackHartmann(n_across=n_wfs, pupil_diameter=float(n_dm)).n_valid


def render_problems(n: int, seed: int = 0) -> dict:
    """``n`` spot problems: crops ``[1, n, 1, E*R, h, w]`` (one spot per point: the fitter's
    batch is flat), the PSF, windows, omega and noise std."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    freq = torch.exp(torch.empty(n, dtype=f64).uniform_(math.log(10.0), math.log(2000.0), generator=g))
    omega = 2 * math.pi * freq
    win = dual_exposure_windows(omega, fractions=FRACS)  # [n, E]
    win = ExposureWindow(win.start.repeat_interleave(R, -1), win.duration.repeat_interleave(R, -1))  # [n, E*R]
    centre = (CROP - 1) / 2 + torch.rand(n, 2, generator=g, dtype=f64) - 0.5
    amp_e = PEAK_E * 2 * math.pi * SIGMA**2 / win.duration.max(-1).values  # a still spot over the longest exposure peaks at PEAK_E
    psf = GaussianPSF(centre, torch.eye(2, dtype=f64) * SIGMA**2, amp_e)
    mag = 0.5 + 2.5 * torch.rand(n, 2, generator=g, dtype=f64)
    ph = (torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 2 * math.pi
    clean = torch.cat([render_blur(Sinusoid(mag[i:i + 256, None], ph[i:i + 256, None], omega[i:i + 256, None]),
                                   GaussianPSF(centre[i:i + 256, None], psf.cov[i:i + 256, None], amp_e[i:i + 256, None]),
                                   ExposureWindow(win.start[i:i + 256], win.duration[i:i + 256]), height=CROP, width=CROP)
                       for i in range(0, n, 256)])  # [n, E*R, h, w]
    noise = camera_noise_std(clean, READ_E)
    noisy = clean + noise * torch.randn(clean.shape, generator=g, dtype=f64)
    return dict(crops=noisy[None, :, None], noise=noise[None, :, None], center=centre, cov=psf.cov, amp=amp_e,
                start=win.start[None], duration=win.duration[None], omega=omega, mag=mag)


def spot_images(psf: GaussianPSF) -> torch.Tensor:
    """``[..., CROP, CROP]``: the point-sampled image of every spot of ``psf`` (batch ``[...]``)."""
    g = torch.arange(CROP, dtype=psf.cov.dtype, device=psf.cov.device)
    e = (...,) + (None, None)
    A, B, C = (v[e] for v in psf.precision())
    dx, dy = g[None, :] - psf.center[..., 0][e], g[:, None] - psf.center[..., 1][e]
    return psf.amplitude[e] * torch.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy))


LADDER_LEVELS, LADDER_REACH, LADDER_FRAMES, LADDER_FREQ_HZ = 13, 1.3, 32, 300.0  #: dm_plan's defaults; the sweep point


def _gauss_spots(centre, sigma, rate):
    """``[..., CROP, CROP]`` e-/s: point-sampled round Gaussians at ``centre [..., 2]`` (x, y px), width ``sigma [...]``."""
    g = torch.arange(CROP, dtype=centre.dtype)
    r2 = (g[None, :] - centre[..., 0, None, None]) ** 2 + (g[:, None] - centre[..., 1, None, None]) ** 2
    return rate * torch.exp(-r2 / (2 * sigma[..., None, None] ** 2))


def ladder_problems(n_spots: int, n_patterns: int, seed: int = 0) -> dict:
    """The ladder fit's problems of ``n_patterns`` patterns x ``n_spots`` spots at one sweep point
    (:data:`LADDER_FREQ_HZ`, exposures 0.3 and 0.8 of the period x 2 repeats, a still peak of
    ``PEAK_E`` e- over the longer one, shot + 3 e- read noise): each spot a Gaussian (sigma
    1.2 px) that moves by ``s u`` (``s`` 0.9-3 px per unit command, any direction) and widens by
    15 % per unit ``u`` (a lenslet spot changes shape as it moves), plus a free motion of 0-1 px
    across ``s`` (the actuators' own dynamics near a resonance); the command ``u = Re(G e^{iwt})``,
    ``|G|`` 0.6-1; the ladder: ``LADDER_LEVELS`` levels over +-``LADDER_REACH``, the mean of
    ``LADDER_FRAMES`` frames each, its variance; the still the mean of 256 frames. Returns the
    tensors and the truth ``z [P, 1, M, 2]`` (px phasors ``s G + n N``)."""
    g = torch.Generator().manual_seed(seed)
    f64, P, M = torch.float64, n_patterns, n_spots

    def rand(*shape, lo=0.0, hi=1.0):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=f64)
    om = 2 * math.pi * LADDER_FREQ_HZ
    win = dual_exposure_windows(torch.tensor([om], dtype=f64), fractions=FRACS)  # [1, E]
    start, dur = win.start.repeat_interleave(R, -1).expand(P, 1, -1), win.duration.repeat_interleave(R, -1).expand(P, 1, -1)
    te = float(dur.max())
    rate = PEAK_E / te
    centre = CROP / 2 - 0.5 + rand(M, 2, lo=-0.5, hi=0.5)
    ang = rand(P, M, lo=0, hi=2 * math.pi)
    s = rand(P, M, lo=0.9, hi=3.0)[..., None] * torch.stack([torch.cos(ang), torch.sin(ang)], -1)  # [P, M, 2] px per unit u
    n = torch.stack([-torch.sin(ang), torch.cos(ang)], -1)
    G = rand(P, M, lo=0.6, hi=1.0) * torch.exp(1j * rand(P, M, lo=0, hi=2 * math.pi))  # u = |G| sin(wt + arg G)
    N = rand(P, M) * torch.exp(1j * rand(P, M, lo=0, hi=2 * math.pi))  # the free motion along n (px)
    levels = torch.linspace(-LADDER_REACH, LADDER_REACH, LADDER_LEVELS, dtype=f64)

    def image(u, d):  # [P, M, ...] e-/s at the command u and free motion d (broadcast)
        c = centre[None, :, None] + s[..., None, :] * u[..., None] + n[..., None, :] * d[..., None]
        return _gauss_spots(c, SIGMA * (1 + 0.15 * u), rate)

    def noisy(e, frames):  # the mean of `frames` frames of e electrons each, and its variance
        var = (e.clamp_min(0) + READ_E ** 2) / frames
        return e + var.sqrt() * torch.randn(e.shape, generator=g, dtype=f64), var
    lad, lvar = noisy(image(levels.expand(P, M, -1), torch.zeros(P, M, LADDER_LEVELS, dtype=f64)) * te, LADDER_FRAMES)
    still = noisy(_gauss_spots(centre, torch.full((M,), SIGMA, dtype=f64), rate) * te, 256)[0] / te
    x, w = np.polynomial.legendre.leggauss(48)
    crops = []
    for e in range(start.shape[-1]):  # each exposure by 48 Gauss-Legendre nodes
        t = float(start[0, 0, e]) + float(dur[0, 0, e]) * torch.as_tensor((x + 1) / 2)
        ph = om * t
        u = G.abs()[..., None] * torch.sin(ph + G.angle()[..., None])
        d = N.abs()[..., None] * torch.sin(ph + N.angle()[..., None])
        crops.append((image(u, d) * torch.as_tensor(w / 2 * float(dur[0, 0, e]))[:, None, None]).sum(2))
    clean = torch.stack(crops, 2)[:, None]  # [P, 1, M, E*R, h, w] e-
    noise = camera_noise_std(clean, READ_E)
    data = clean + noise * torch.randn(clean.shape, generator=g, dtype=f64)
    return dict(crops=data, noise=noise, levels=levels.expand(P, -1).clone(), images=(lad / te).transpose(1, 2).contiguous(),
                variance=(lvar / te ** 2).transpose(1, 2).contiguous(), still=still, start=start, duration=dur,
                omega=torch.tensor([om], dtype=f64), amplitude=torch.ones(P, 1, dtype=f64),
                z=(s * G[..., None] + n * N[..., None])[:, None])


def _ladder_module(rev: str | None):
    """``torchblur.dm.ladder_fit``, or its source at git revision ``rev`` (the baseline) as a module."""
    import importlib.util

    import torchblur.dm.ladder_fit as lf
    if not rev:
        return lf
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    src = subprocess.run(["git", "-C", root, "show", f"{rev}:torchblur/dm/ladder_fit.py"], capture_output=True, text=True, check=True).stdout
    spec = importlib.util.spec_from_loader(f"ladder_fit_{rev}", loader=None)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    exec(compile(src, f"{rev}:torchblur/dm/ladder_fit.py", "exec"), mod.__dict__)
    return mod


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _fit_ladder(d: dict, mod, sl=slice(None)):
    """``(fits, seconds of with_slopes)``: :func:`~torchblur.dm.ladder_fit.fit_ladder_problems` of the patterns ``sl``
    (the slopes computed once first where ``mod`` has ``with_slopes``, timed apart)."""
    lad = mod.PatternLadder(d["levels"][sl], d["images"][sl], d["variance"][sl], d["still"])
    t0 = time.perf_counter()
    lad = mod.with_slopes(lad) if hasattr(mod, "with_slopes") else lad
    _sync(lad.levels.device)
    t_slopes = time.perf_counter() - t0
    fits = mod.fit_ladder_problems(d["crops"][sl], lad, ExposureWindow(d["start"][sl], d["duration"][sl]), d["omega"], d["amplitude"][sl],
                                   power=1.0, noise_std=d["noise"][sl])
    return fits, t_slopes


def ladder_child(path: str, baseline: str | None, device: str = "cpu") -> dict:
    """The ladder fit of the problems at ``path`` in this process, every tensor on ``device``: problems/s
    of the fit, the slopes' seconds, rms(error/std) of the amplitudes against the truth; with ``baseline`` (a
    git revision) also that revision's fit of the same problems, its time and the largest difference in stds."""
    dev = torch.device(device)
    d = {k: v.to(dev) if isinstance(v, torch.Tensor) else v for k, v in torch.load(path).items()}
    new = _ladder_module(None)
    _fit_ladder(d, new, slice(0, 1))  # warm up (first-call allocations, the derivative matrix), not timed
    _sync(dev)
    t0 = time.perf_counter()
    fits, t_slopes = _fit_ladder(d, new)
    _sync(dev)
    dt = time.perf_counter() - t0 - t_slopes
    n = fits.status.numel()
    ok = fits.status == 0
    sd = torch.diagonal(fits.covariance, dim1=-2, dim2=-1)[..., ::2].sqrt()
    z = ((fits.amplitude - d["z"].abs()) / sd)[ok]
    out = {"problems": n, "per_s": n / dt, "slopes_s": t_slopes, "ok": int(ok.sum()), "rms_z": float(z.square().mean().sqrt()),
           "load": os.getloadavg()[0]}
    if baseline:
        old = _ladder_module(baseline)
        _fit_ladder(d, old, slice(0, 1))
        _sync(dev)
        t0 = time.perf_counter()
        ref = _fit_ladder(d, old)[0]
        _sync(dev)
        out["baseline_s"] = time.perf_counter() - t0
        sd0 = torch.diagonal(ref.covariance, dim1=-2, dim2=-1).sqrt()
        both = ok & (ref.status == 0)
        dz = torch.cat([((fits.amplitude - ref.amplitude) / sd0[..., ::2])[both], (wrap_phase(fits.phase - ref.phase) / sd0[..., 1::2])[both]])
        out.update(baseline_per_s=n / out["baseline_s"], max_diff_std=float(dz.abs().max()), same_status=bool(torch.equal(fits.status, ref.status)),
                   max_cov_rel=float(((fits.covariance - ref.covariance).abs() / (sd0[..., :, None] * sd0[..., None, :]))[both].max()))
    return out


def _peak(device) -> float:
    if device.type == "cuda":
        return float(torch.cuda.max_memory_allocated(device))
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024.0


def _fit_batched(d: dict, method: str, sl=slice(None)):
    """``fit_spot_problems`` of the problems ``sl`` with the Gaussian (``batched``) or every spot's kernel."""
    from torchblur.dm.spot_fit import fit_spot_problems

    psf = GaussianPSF(d["center"][sl, None], d["cov"][sl, None], d["amp"][sl, None])  # [F=n, M=1]
    if method == "kernel":  # every spot its exact image as a measured kernel [F=n, M=1, h, w]
        psf = KernelPSF(spot_images(psf))
    return fit_spot_problems(d["crops"][:, sl], psf, ExposureWindow(d["start"][:, sl], d["duration"][:, sl]), d["omega"][sl],
                             noise_std=d["noise"][:, sl])


def child(path: str, method: str, device: str, n_single: int) -> dict:
    """One measurement in this process: fit the problems saved at ``path``."""
    from torchblur.fit.sinusoid import fit_sinusoid

    dev = torch.device(device)
    d = {k: v.to(dev) if isinstance(v, torch.Tensor) else v for k, v in torch.load(path).items()}
    _sync(dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    if method in ("batched", "kernel"):  # warm up (first-call imports and allocations) on two problems, not timed
        _fit_batched(d, method, slice(0, 2))
    base = _peak(dev)
    t0 = time.perf_counter()
    if method in ("batched", "kernel"):
        fits = _fit_batched(d, method)
        n, amp_std = d["crops"].shape[1], fits.covariance[0, :, 0, 0, 0].sqrt()
        ok = int((fits.status == 0).sum())
        err = (fits.amplitude[0, :, 0] - d["mag"]).abs().max().item()
        chunks = fits.n_chunks
    else:
        n = min(n_single, d["crops"].shape[1])
        stds, ok, err = [], 0, 0.0
        for i in range(n):
            f = fit_sinusoid(d["crops"][0, i, 0], GaussianPSF(d["center"][i], d["cov"][i], d["amp"][i]),
                             ExposureWindow(d["start"][0, i], d["duration"][0, i]), d["omega"][i], axes="xy",
                             noise_std=d["noise"][0, i, 0])
            ok += int(f.status == 0)
            err = max(err, (f.amplitude - d["mag"][i]).abs().max().item())
            stds.append(f.amplitude_std[0])
        amp_std, chunks = torch.stack(stds), n
    _sync(dev)
    dt = time.perf_counter() - t0
    peak = _peak(dev)
    return {"problems": n, "seconds": dt, "per_s": n / dt, "peak_mb": max(0.0, peak - base) / 2**20, "process_mb": peak / 2**20, "ok": ok,
            "max_err_px": err, "sigma1_px": float(amp_std.median()), "chunks": chunks}


def run_child(path, method, device, n_single, baseline=None) -> dict:
    cmd = [sys.executable, __file__, "--child", path, "--method", method, "--device", device, "--single", str(n_single)]
    cmd += ["--ladder-baseline", baseline] if baseline else []
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=dict(os.environ))
    return json.loads(out.stdout.strip().splitlines()[-1])


def throughput(cases, points: int, n_single: int, device: str) -> float:
    print(f"spot-fit throughput and peak memory on {device} (16x16 px crops, 4 exposures, {points} points per case)")
    print(f"{'case':>6} {'act':>4} {'subap':>5} {'problems':>8} | {'batched /s':>10} {'single /s':>9} {'ratio':>6} | "
          f"{'batched MB':>10} {'single MB':>9} {'ratio':>8} {'per problem':>12} | {'process MB b/s':>14} {'ratio':>5} | "
          f"{'chunks':>6} {'max err px':>10}")
    sigma1 = math.nan
    with tempfile.TemporaryDirectory() as tmp:
        for spec in cases:
            n_act, n_sub = case_sizes(spec)
            path = os.path.join(tmp, f"case_{spec.replace('/', '_')}.pt")
            torch.save(render_problems(points * n_sub), path)
            b = run_child(path, "batched", device, n_single)
            s = run_child(path, "single", device, n_single)
            per_b = b["peak_mb"] / b["problems"]
            s_mb = max(s["peak_mb"], 1 / 1024)  # ru_maxrss counts KB: a rise under 1 KB reads 0
            m_ratio = f"{b['peak_mb'] / s_mb:>8.0f}" if s["peak_mb"] > 0 else f"{'>' + format(b['peak_mb'] * 1024, '.0f'):>8}"
            print(f"{spec:>6} {n_act:>4} {n_sub:>5} {b['problems']:>8} | {b['per_s']:>10.1f} {s['per_s']:>9.2f} "
                  f"{b['per_s'] / s['per_s']:>6.1f} | {b['peak_mb']:>10.1f} {s['peak_mb']:>9.3f} {m_ratio} "
                  f"{1024 * per_b:>6.1f} KB/pb | {b['process_mb']:>6.0f}/{s['process_mb']:<7.0f} {b['process_mb'] / s['process_mb']:>5.2f} | "
                  f"{b['chunks']:>6} {b['max_err_px']:>10.3g}")
            sigma1 = b["sigma1_px"] if spec == cases[0] else sigma1
    print("  ratio = batched problems/s over the single-spot fitter's (fit_sinusoid one problem per call, the same crops);"
          " MB = the fit's own peak (RSS rise in its own process after its imports, or CUDA max allocated);"
          " '>N': the single fitter's rise was under the 1 KB resolution; process MB: the whole process's peak"
          " (imports and data included), batched / single")
    return sigma1


#: configs/identify_dm.yaml per frequency: 64 Hadamard patterns x 80 spots, 64 x (2 exposures x 2 repeats) frames
SHIPPED = {"problems": 64 * 80, "frames": 64 * 4, "frequencies": 16, "frame_rate_hz": 30.0}


def ladder_route() -> dict:
    """The shipped config's sweep with the ladder as ``dm_plan.kind=auto`` runs it: the sparse plan seen at
    ``SPARSE_MARGIN`` x the support threshold, its repeats from the frame budget, and only the (pattern,
    spot) problems it drives (:func:`~torchblur.dm.plans.driven_spots`): ``{problems, frames}`` per frequency."""
    cfg = load_config(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", "identify_dm.yaml"))
    plan, R = dm_ladder_plan(cfg)[:2]
    return {"problems": int(driven_spots(plan).sum()), "frames": plan.n_patterns * len(cfg.sweep.exposures) * R,
            "patterns": plan.n_patterns, "repeats": R}


def keep_up(rate: float, problems: int = SHIPPED["problems"], frames: int = SHIPPED["frames"]) -> tuple[float, float, float]:
    """The shipped config's fitting time per frequency (s) at ``rate`` problems/s (``problems`` and ``frames``
    per frequency: its Hadamard sweep's by default), its acquisition time per frequency (s) at 30 Hz, and
    the wait after the last frame (s): :func:`~torchblur.identify.keep_up.sweep_schedule`, the sweep's schedule
    (one fit worker, frequency k acquired once k - AMPLITUDE_LAG's fit is done)."""
    acq, F = frames / SHIPPED["frame_rate_hz"], SHIPPED["frequencies"]
    t_fit = problems / rate
    return t_fit, acq, sweep_schedule(np.full(F, t_fit), acq, AMPLITUDE_LAG)[0]


def kernel_throughput(cases, points: int, device: str) -> None:
    """The DM spot fitter with every spot's measured kernel against the Gaussian, in problems/s
    (each in its own process, on the same crops), and the 30 Hz test on the shipped config."""
    print(f"\nwith kernels (every spot a KernelPSF [M, 16, 16], its exact image), {points} points per case, on {device}, "
          f"{torch.get_num_threads()} thread(s)")
    print(f"{'case':>6} {'act':>4} {'subap':>5} {'problems':>8} | {'Gaussian /s':>11} {'kernel /s':>9} {'kernel/Gaussian':>15} | "
          f"{'max err px G/K':>15}")
    rates = {}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in cases:
            n_act, n_sub = case_sizes(spec)
            path = os.path.join(tmp, f"k_{spec.replace('/', '_')}.pt")
            torch.save(render_problems(points * n_sub, seed=1), path)
            b = run_child(path, "batched", device, 0)
            k = run_child(path, "kernel", device, 0)
            rates[spec] = (b["per_s"], k["per_s"])
            print(f"{spec:>6} {n_act:>4} {n_sub:>5} {b['problems']:>8} | {b['per_s']:>11.1f} {k['per_s']:>9.1f} {k['per_s'] / b['per_s']:>15.3f} | "
                  f"{b['max_err_px']:>7.3g}/{k['max_err_px']:<7.3g}")
    g_rate, k_rate = rates.get("8/10", next(iter(rates.values())))
    for name, rate in (("Gaussian", g_rate), ("kernel", k_rate)):
        t_fit, acq, wait = keep_up(rate)
        print(f"configs/identify_dm.yaml at {SHIPPED['frame_rate_hz']:g} Hz with every spot {name}: {t_fit:.1f} s of fitting per frequency "
              f"({SHIPPED['problems']} problems at {rate:.0f}/s) against {acq:.1f} s of acquisition: "
              f"{'keeps up' if t_fit <= acq else 'does NOT keep up'}; wait after the last frame about {wait:.0f} s")


def ladder_throughput(cases, points: int, baseline: str | None, device: str = "cpu") -> None:
    """The ladder spot fit (:func:`~torchblur.dm.ladder_fit.fit_ladder_problems`, each pattern's
    spots on their own ladders: :func:`ladder_problems`) in problems/s per case, each in its own
    process; with ``baseline`` the ratio to that git revision's fit of the same problems in the same
    process; and whether that keeps up with a 30 Hz camera on ``configs/identify_dm.yaml`` with
    ``dm_plan.spot_model=ladder``."""
    print(f"\nthe ladder spot fit (dm_plan.spot_model=ladder: {LADDER_LEVELS} levels x {LADDER_FRAMES} frames, Gaussian spots that "
          f"widen as they move plus 0-1 px of free motion), {points} patterns per case at {LADDER_FREQ_HZ:g} Hz, {device}, "
          f"{torch.get_num_threads()} thread(s)")
    print(f"{'case':>6} {'act':>4} {'subap':>5} {'problems':>8} | {'ladder /s':>9} {'slopes s':>8} {'ok':>5} {'rms z':>6} | "
          f"{'baseline /s':>11} {'speed-up':>8} {'max diff std':>12} {'status same':>11} | {'load':>5}")
    rates = {}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in cases:
            n_act, n_sub = case_sizes(spec)
            path = os.path.join(tmp, f"l_{spec.replace('/', '_')}.pt")
            torch.save(ladder_problems(n_sub, points, seed=2), path)
            r = run_child(path, "ladder", device, 0, baseline)
            rates[spec] = r
            base = (f"{r['baseline_per_s']:>11.1f} {r['per_s'] / r['baseline_per_s']:>8.2f} {r['max_diff_std']:>12.2g} {str(r['same_status']):>11}"
                    if baseline else f"{'-':>11} {'-':>8} {'-':>12} {'-':>11}")
            print(f"{spec:>6} {n_act:>4} {n_sub:>5} {r['problems']:>8} | {r['per_s']:>9.1f} {r['slopes_s']:>8.2f} {r['ok']:>5} {r['rms_z']:>6.2f} | "
                  f"{base} | {r['load']:>5.2f}")
    print("  slopes s: with_slopes (every (pattern, spot)'s static shift, once per run, before the sweep); rms z: the amplitudes' "
          "rms(error/std) against the truth; speed-up: problems/s over the baseline's (its fit computes the slopes itself); "
          "max diff std: the largest |amplitude or phase difference| / the baseline's std; load: the 1-minute load average")
    r = rates.get("8/10", next(iter(rates.values())))
    route = ladder_route()
    n = route["problems"]
    t_fit, acq, wait = keep_up(r["per_s"], n, route["frames"])
    print(f"configs/identify_dm.yaml at {SHIPPED['frame_rate_hz']:g} Hz with dm_plan.spot_model=ladder (auto's sparse plan: "
          f"{route['patterns']} patterns x {route['frames'] // route['patterns']} frames, the {n} (pattern, spot) problems it drives): "
          f"{t_fit:.1f} s of fitting per frequency at {r['per_s']:.0f}/s against {acq:.1f} s of acquisition: "
          f"{'keeps up' if t_fit <= acq else 'does NOT keep up'} (fit/acquisition {t_fit / acq:.2f}); wait after the last frame about "
          f"{wait:.0f} s; the slopes once before the sweep about {r['slopes_s'] / r['problems'] * n:.0f} s")


def plan_comparison(sigma1: float, target_px: float = 3.0, n_freq: int = 16, n_exp: int = 2, budget: int = 4096) -> None:
    try:
        from torchblur.dm.mirror import DeformableMirror
        from torchblur.dm.plans import choose_plan, one_at_a_time_plan, plan_cost, static_motion_px
        from torchblur.dm.shack_hartmann import ShackHartmann
    except ImportError as e:
        print(f"plans: skipped ({e}: d1's mirror model and plans are not in this tree)")
        return
    from torchblur.dm.demux import demultiplex

    mirror = DeformableMirror.build(8)
    G = ShackHartmann(n_across=10, pupil_diameter=8.0, pitch_px=16.0, sigma_px=1.2).geometry_matrix(mirror)
    plan, reps, _ = choose_plan("auto", G, budget_frames=budget, n_freq=n_freq, n_exposures=n_exp)
    one = one_at_a_time_plan(G)

    def worst_std(p, repeats):
        a = target_px / static_motion_px(p, G)
        var = sigma1**2 / (a**2 * repeats * n_exp)  # one response from E*R frames
        P = p.patterns.shape[0]
        cov = np.broadcast_to(np.eye(2) * var, (P, G.shape[0], 1, 2, 2))
        _, Dc = demultiplex(np.zeros((P, G.shape[0], 1), complex), cov, p.patterns, p.support)
        return float(np.sqrt(Dc[..., 0, 0][p.support[:, :, None]].max()))

    s_plan = worst_std(plan, reps)
    r_one = math.ceil((worst_std(one, 1) / s_plan) ** 2)
    f_plan, f_one = plan.n_frames(n_freq, n_exp, reps), one.n_frames(n_freq, n_exp, r_one)
    print(f"plans (8 across, 10x10 sensor, {n_freq} frequencies x {n_exp} exposures, sigma_1 = {sigma1:.3g} px, "
          f"target {target_px} px): chosen {plan.kind} P={plan.n_patterns} x {reps} repeats = {f_plan} frames, worst D std "
          f"{s_plan:.3g} px/unit; one-at-a-time needs {r_one} repeats = {f_one} frames for it; ratio {f_plan / f_one:.3f} "
          f"(plan_cost ratio {plan_cost(plan, G) / plan_cost(one, G):.3f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="+", default=["8/10", "18/20", "32/34"])
    ap.add_argument("--points", type=int, default=2, help="sweep points (pattern, frequency) per case")
    ap.add_argument("--single", type=int, default=24, help="problems fitted one by one")
    ap.add_argument("--kernel-points", type=int, default=1, help="sweep points per case of the kernel comparison (0: skip it)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads in every fit (0: torch's default)")
    ap.add_argument("--ladder-points", type=int, default=2, help="patterns per case of the ladder fit's throughput (0: skip it)")
    ap.add_argument("--ladder-baseline", default="", help="a git revision whose ladder fit is timed on the same problems (the ratio)")
    ap.add_argument("--no-plans", action="store_true", help="skip the plan comparison")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--method", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
        os.environ["BENCH_DM_THREADS"] = str(args.threads)
    elif os.environ.get("BENCH_DM_THREADS"):
        torch.set_num_threads(int(os.environ["BENCH_DM_THREADS"]))
    if args.child:
        out = ladder_child(args.child, args.ladder_baseline, args.device) if args.method == "ladder" else child(args.child, args.method, args.device, args.single)
        print(json.dumps(out))
        return
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device here")
    sigma1 = throughput(args.cases, args.points, args.single, args.device) if args.points > 0 else 0.3
    if args.kernel_points > 0:
        kernel_throughput(args.cases, args.kernel_points, args.device)
    if args.ladder_points > 0:
        ladder_throughput(args.cases, args.ladder_points, args.ladder_baseline or None, args.device)
    if not args.no_plans:
        plan_comparison(sigma1)


if __name__ == "__main__":
    main()
