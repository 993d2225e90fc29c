"""Why the DM spot fit misses on HCIPy lenslet spots (issue 23): its reduced chi2, the D(jw) error
against the fitted-shift truth and the delay, traced on noiseless frames.

Frames from tests/hcipy_sh.py (HCIPy's pupil, DM, square lenslets with diffraction and crosstalk,
the motion integrated over each exposure), without noise, so every misfit is the model's. Each
spot's 16 x 16 crop (the sensor's layout, as the DM calibration crops) is fitted as the run fits it
(:func:`torchblur.dm.spot_fit.fit_spot_problems`, each spot's measured kernel: here its exact
noiseless still crop), weighted by the camera noise of the expected signal (read noise 5 e-, a
still-spot peak of ``PEAK_E`` electrons over the longer exposure, as the quick benchmark's run), so
a noiseless reduced chi2 is the misfit's share of the noisy fit's reduced chi2. Printed:

1. A pure motion: a whole-pupil tilt moving every spot on the same sinusoid (3 px). The kernel's
   Fourier shift is exact here but for the light that enters the 16 px crop from outside it
   (``margin 4``: the data and the kernel cropped 4 px wider, the fit on the central 16 x 16).
2. Hadamard patterns of configs/identify_dm.yaml's plan (3 px largest motion, as the run): the
   noiseless reduced chi2, ``D`` error against ``shift_truth x pattern x H(jw)`` (rms over max,
   and in units of the fit's own stds), and its mean relative part along the truth (``gain``) and
   across it (``phase``, rad), at the full motion, half of it and a tenth; at a tenth fitted as
   ``shift_truth`` defines the shift (uniform weights, no crop edge: ``margin 4``), which tells
   the truth's convention from the fit's error; then with every other lenslet dark (no neighbour:
   no crosstalk; ``shift_truth`` is still the lit array's) to tell the spot's own change of shape
   from its neighbours' light.
3. What a constant phase lead of that size does to the actuator fit
   (:func:`torchblur.dm.actuator_fit.fit_actuators` of ``shift_truth x H(jw)`` rotated by it):
   the delay and damping errors of the quick plan (4 frequencies) and the full one (16).

    python benchmarks/bench_dm_spot_causes.py [--patterns 4]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import hcipy_sh as hs  # noqa: E402

from torchblur.dm.actuator_fit import fit_actuators  # noqa: E402
from torchblur.config.budget import dm_plan  # noqa: E402
from torchblur.dm.spot_fit import crop_problems, fit_spot_problems, pattern_responses  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.render.camera import camera_noise_std  # noqa: E402
from torchblur.render.psf import KernelPSF  # noqa: E402
from torchblur.render.window import ExposureWindow  # noqa: E402

PEAK_E = 1650.0  #: the still spot's peak electrons over the longer exposure (the quick run's power)
READ_NOISE_E = 5.0
LATENCY_S = 12e-6
TARGET_PX = 3.0  #: configs/identify_dm.yaml's excitation.target_px
EXPOSURES = (0.3, 0.8)  #: of the period (the config's sweep.exposures)
MARGIN = 4


def windows(f: float, n: int) -> ExposureWindow:
    """``[n, 1, 2]`` windows as the run takes them: triggered a quarter period after the command's
    upward zero crossing (sweep.trigger_phase_rad), the camera's latency later."""
    T = 1 / f
    start = torch.full((n, 1, 2), T / 4 + LATENCY_S, dtype=torch.float64)
    return ExposureWindow(start, torch.tensor([e * T for e in EXPOSURES], dtype=torch.float64).expand(n, 1, 2))


def fit(frames, still, offset, size, window, f, margin: int = 0, uniform: bool = False):
    """Fit the spots of noiseless frames ``[n, 2, H, W]`` (e-) with their still crops as kernels; the
    crops ``margin`` px wider on every side, the fit on the central ``size``; weighted by the camera
    noise, or ``uniform`` (as ``shift_truth``'s least squares). Returns SpotFits [n, 1, M]."""
    off = offset - margin
    sz = (size[0] + 2 * margin, size[1] + 2 * margin)
    crops, inside = crop_problems(frames[:, None], off, sz)
    centre = torch.zeros(sz, dtype=torch.bool)
    centre[margin:margin + size[0], margin:margin + size[1]] = True
    kern = crop_problems(still[None, None, None], off, sz)[0][0, 0, :, 0]
    return fit_spot_problems(crops, KernelPSF(kern), window, torch.tensor([2 * math.pi * f], dtype=torch.float64),
                             noise_std=torch.full_like(crops, 30.0) if uniform else camera_noise_std(crops, READ_NOISE_E),
                             mask=(inside & centre)[:, None])


def tilt_frames(gen, f, window, power):
    """Frames ``[3, 2, H, W]`` of whole-pupil tilts: every spot moves ``(ax sin(wt + px), ay sin(wt + py))``."""
    cases = [(TARGET_PX, 0.0, 0.3, 0.7), (0.7 * TARGET_PX, 0.7 * TARGET_PX, 1.1, 2.0), (0.0, TARGET_PX, 0.0, 0.5)]
    k = 2 * np.pi / hs._WAVELENGTH
    X, Y = np.asarray(gen.grid.x), np.asarray(gen.grid.y)
    om = 2 * math.pi * f
    out = np.zeros((len(cases), 2) + gen.shape)
    x, w = np.polynomial.legendre.leggauss(64)
    for c, (ax, ay, px, py) in enumerate(cases):
        for e, (t0, te) in enumerate(zip(window.start[0, 0].numpy(), window.duration[0, 0].numpy())):
            for xi, wi in zip(x, w):
                t = t0 + (xi + 1) * te / 2
                tilt = np.exp(1j * k * (ax * math.sin(om * t + px) * X + ay * math.sin(om * t + py) * Y) * hs._PIXEL / gen.focal)
                out[c, e] += wi * te / 2 * gen._image_of(gen._pupil_lens * tilt.astype(np.complex64))
    truth = torch.tensor([[[c[0], c[1]]] for c in cases], dtype=torch.float64), torch.tensor([[[c[2], c[3]]] for c in cases])
    return torch.as_tensor(out * power), truth


def pure_motion(gen, still, offset, size, f, power):
    window = windows(f, 3)
    frames, (amp, ph) = tilt_frames(gen, f, window, power)
    for margin in (0, MARGIN):
        fits = fit(frames, still, offset, size, window, f, margin)
        a = fits.amplitude[:, 0]  # [3, M, 2]
        moving = amp[:, 0, None, :].expand_as(a) > 0
        rel = (a / amp[:, 0, None, :] - 1)[moving]
        dph = (torch.remainder(fits.phase[:, 0] - ph[:, 0, None, :] + math.pi, 2 * math.pi) - math.pi)[moving]
        print(f"  pure motion {TARGET_PX:g} px, crop 16{f' + margin {margin}' if margin else ''}: noiseless reduced chi2 median "
              f"{float(fits.reduced_chi2.median()):.4f}; amplitude error rms {float(rel.square().mean().sqrt()) * 100:.3f} %, "
              f"phase error rms {float(dph.square().mean().sqrt()):.5f} rad")


def dm_frames(gen, dyn, S, pats, f, window, power, scale):
    """Noiseless frames ``[P, 2, H, W]`` of the patterns (largest spot motion ``scale * TARGET_PX``)
    and the linearised truth ``Y [P, 2M]`` per unit amplitude, with the amplitudes ``[P]``."""
    H = dyn.response(f)
    om = 2 * math.pi * f
    Yt = (S @ (H[:, None] * pats.T)).T  # [P, 2M]
    M = S.shape[0] // 2
    amps = scale * TARGET_PX / np.hypot(np.abs(Yt[:, :M]), np.abs(Yt[:, M:])).max(1)
    st, du = window.start[0, 0].numpy(), window.duration[0, 0].numpy()
    out = []
    for p in range(len(pats)):
        h = H * amps[p] * pats[p]
        nodes = [gen.node_count(scale * TARGET_PX, om, float(d)) for d in du]
        out.append(gen.blurred(np.abs(h), np.angle(h), om, st, du, nodes))
    return torch.as_tensor(np.stack(out) * power), Yt, amps


def dm_case(gen, dyn, S, pats, still, offset, size, f, power, scale, label, rows=None, margin=0, uniform=False):
    window = windows(f, len(pats))
    frames, Yt, amps = dm_frames(gen, dyn, S, pats, f, window, power, scale)
    sel = np.arange(offset.shape[0]) if rows is None else rows
    fits = fit(frames, still, offset[sel], size, window, f, margin, uniform)
    Y, Yc = pattern_responses(fits, amps[:, None])
    M = S.shape[0] // 2
    cols = np.concatenate([sel, M + sel])
    Y, Yc, Yt = Y[..., 0], Yc[:, :, 0], Yt[:, cols]
    err = Y - Yt
    std = np.sqrt(np.trace(Yc, axis1=-2, axis2=-1) / 2)
    big = np.abs(Yt) > 0.3 * np.abs(Yt).max(1, keepdims=True)
    r = err[big] / Yt[big]
    print(f"  {label}, {f:.4g} Hz, motion {scale * TARGET_PX:g} px: noiseless reduced chi2 median {float(fits.reduced_chi2.median()):.4f} "
          f"(mean {float(fits.reduced_chi2.mean()):.4f}); D error rms/max {np.sqrt(np.mean(np.abs(err) ** 2)) / np.abs(Yt).max() * 100:.2f} %, "
          f"rms(|error|/std) {np.sqrt(np.mean((np.abs(err) / std) ** 2)):.2f}; slopes > 0.3 max: gain {np.mean(r.real) * 100:+.2f} %, "
          f"phase {np.mean(r.imag):+.4f} rad")
    if scale == 1.0 and rows is None and f == 342.0:
        _worst(Y, Yt, amps, fits.reduced_chi2[:, 0].numpy(), M)
    return float(np.mean(r.imag))


def _worst(Y, Yt, amps, chi2, M, k: int = 3) -> None:
    """The spots with the largest error (px of motion, both axes): where the surface is curved
    under the lenslet but hardly tilted, a spot that barely moves changes shape, and the fit calls that motion."""
    e = np.abs(Y - Yt).reshape(len(amps), 2, M).max(1) * amps[:, None]  # [P, M] px
    for i in np.argsort(-e, axis=None)[:k]:
        p, m = np.unravel_index(i, e.shape)
        fmt = lambda z: f"{z.real * amps[p]:+.3f}{z.imag * amps[p]:+.3f}j"  # noqa: E731
        print(f"    worst: pattern {p + 1} spot {m}: fitted x {fmt(Y[p, m])}, y {fmt(Y[p, M + m])} px; truth x {fmt(Yt[p, m])}, "
              f"y {fmt(Yt[p, M + m])} px; reduced chi2 {chi2[p, m]:.3f}")


def phase_lead_effect(dyn, S, leads) -> None:
    for freqs in ([10.0, 58.48, 342.0, 2000.0], list(np.geomspace(10, 2000, 16))):
        H = dyn.response(np.asarray(freqs))
        live = ~dyn.dead
        for lead in leads:
            D = S[:, :, None] * H[None] * np.exp(1j * lead)
            C = np.zeros(D.shape + (2, 2))
            C[..., 0, 0] = C[..., 1, 1] = (0.008 * np.abs(S).max()) ** 2
            t = fit_actuators(np.asarray(freqs), D, C, S)
            dd = (t.delay_s[live] - dyn.delay_s[live]) * 1e6
            dz = t.damping[live] / dyn.damping[live] - 1
            print(f"  {len(freqs)} frequencies, phase lead {lead:+.4f} rad: delay error mean {np.nanmean(dd):+.2f} us (max |.| "
                  f"{np.nanmax(np.abs(dd)):.2f}), damping mean {np.nanmean(dz) * 100:+.1f} % (max |.| {np.nanmax(np.abs(dz)) * 100:.1f} %), "
                  f"mode max |.| {np.nanmax(np.abs(t.mode_hz[live] / dyn.mode_hz[live] - 1)) * 100:.3f} %")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patterns", type=int, default=4, help="Hadamard patterns per case (rows 1.. of the plan)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    cfg = load_config("configs/identify_dm.yaml", ["sweep.n=4", "dm_plan.budget_frames=512"])
    gen = hs.HcipySH()
    dyn = hs.draw_dynamics(gen.n_actuators, 23)
    S = gen.shift_truth()
    pats = dm_plan(cfg)[0].patterns[1:1 + args.patterns]
    n, pitch = gen.optics.n_lenslets, gen.optics.pitch_px
    r, c = np.divmod(gen.valid, n)
    offset = torch.as_tensor(np.stack([c * pitch, r * pitch], -1))  # the cells' corners (x0, y0): the layout's crops
    size = (pitch, pitch)
    print(f"torch threads 1; HCIPy dynamics seed 23; {len(pats)} Hadamard patterns; weights: camera noise of the expected signal, "
          f"still peak {PEAK_E:g} e- over the longer exposure, read noise {READ_NOISE_E:g} e-")
    f = 342.0
    power = PEAK_E / (EXPOSURES[1] / f)
    still = torch.as_tensor(gen.still() * power)
    pure_motion(gen, still, offset, size, f, power)
    leads = []
    for f in (342.0, 2000.0):
        power = PEAK_E / (EXPOSURES[1] / f)
        still = torch.as_tensor(gen.still() * power)
        for scale in ((1.0, 0.5, 0.1) if f == 342.0 else (1.0,)):
            lead = dm_case(gen, dyn, S, pats, still, offset, size, f, power, scale, "DM patterns")
            leads += [lead] if scale == 1.0 else []
    power = PEAK_E / (EXPOSURES[1] / 342.0)
    dm_case(gen, dyn, S, pats, torch.as_tensor(gen.still() * power), offset, size, 342.0, power, 0.1,
            f"DM patterns, uniform weights (shift_truth's), crop 16 + margin {MARGIN}", margin=MARGIN, uniform=True)
    power = PEAK_E / (EXPOSURES[1] / 342.0)
    iso = np.zeros((n, n))
    iso[::2, ::2] = 1
    gen._pupil_lens = (gen._pupil_lens * np.kron(iso, np.ones((pitch, pitch))).reshape(-1)).astype(np.complex64)
    rows = np.flatnonzero((r % 2 == 0) & (c % 2 == 0))
    dm_case(gen, dyn, S, pats, torch.as_tensor(gen.still() * power), offset, size, 342.0, power, 1.0,
            f"DM patterns, every other lenslet dark ({rows.size} spots, no neighbour)", rows)
    phase_lead_effect(dyn, S, [0.0, float(np.mean(leads))])
    print(f"  ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
