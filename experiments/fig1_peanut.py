"""Fig. 1/3 of Tani, Mishra, Wen (CDC 2012): a time-domain motion and the image it blurs into.

A sine command ``u = A sin(w t)`` drives a second-order mirror; its steady-state output
``y = M sin(w t + phi)`` moves the laser spot along x. The camera integrates the spot over
half a period (p = w Te = pi) starting at ``w tcam = pi/2``: the spot dwells at the turning
points, so the streak has bright ends, the "peanut" of the paper's Fig. 3.

Panels: (a) command and output over a few periods with the exposure window shaded;
(b) the rendered (noise-free) image; (c) one frame of the simulated rig (same motion, with
shot and read noise); (d) the profile along the motion (column sums) with the spot's
positions at the window's ends.

    python experiments/fig1_peanut.py --out runs/fig1 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, plt, save_figure, write_metrics

import torchblur as tb
from torchblur.render.camera import CameraModel
from torchblur.systems.lti import Plant
from torchblur.rig.simulated import SimulatedRig

F64 = torch.float64


def local_maxima(profile: np.ndarray) -> np.ndarray:
    """Indices of strict interior local maxima of a 1-D profile."""
    p = profile
    return np.nonzero((p[1:-1] > p[:-2]) & (p[1:-1] >= p[2:]))[0] + 1


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig1_peanut.yaml")
    f = float(cfg.freq_hz)
    omega = 2 * math.pi * f
    H, W = int(cfg.height), int(cfg.width)
    wn = 2 * math.pi * float(cfg.plant.natural_freq_hz)
    plant = Plant(num=(wn * wn,), den=(1.0, 2 * float(cfg.plant.damping) * wn, wn * wn), delay_s=float(cfg.plant.delay_s))
    A = float(cfg.command_amplitude)
    h = complex(plant.frequency_response(omega))
    M, phi = A * abs(h), math.atan2(h.imag, h.real)

    p = 2 * math.pi * float(cfg.exposure_fraction)   # w Te
    b = float(cfg.trigger_phase_rad)                 # w tcam
    window = tb.ExposureWindow(torch.tensor(b / omega, dtype=F64), torch.tensor(p / omega, dtype=F64))
    rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64)
    cam = cfg.camera
    psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=F64), amplitude=float(cam.peak_e_per_s))
    traj = tb.Sinusoid(torch.tensor([M, 0.0], dtype=F64), torch.tensor([phi, 0.0], dtype=F64), torch.tensor(omega, dtype=F64))
    settings = tb.RenderSettings(pixel_integration=True)
    image = tb.render_blur(traj, psf, window, height=H, width=W, settings=settings)  # [H, W] electrons

    # The same motion through the simulated rig (exact LTI response, camera noise).
    camera = CameraModel(read_noise_e=float(cam.read_noise_e), full_well_e=float(cam.full_well_e),
                         gain_e_per_adu=float(cam.gain_e_per_adu), dark_level_adu=float(cam.dark_level_adu),
                         bit_depth=int(cam.bit_depth))
    rig = SimulatedRig(plant=plant, camera=camera, frame_shape=(H, W), psf_sigma_px=float(cfg.psf_sigma_px),
                       latency_s=0.0, jitter_s=0.0, peak_e_per_s=float(cam.peak_e_per_s), seed=int(cfg.seed))
    cap = rig.sine(f, A, [p / omega], b / omega, n_repeats=1)
    frame = camera.to_electrons(cap.frames[0, 0])

    # Time domain: a few periods of steady state, t = 0 at an upward zero crossing of u.
    t = np.linspace(0.0, float(cfg.periods_shown) / f, 1200)
    u = A * np.sin(omega * t)
    y = M * np.sin(omega * t + phi)
    tw = np.linspace(b / omega, (b + p) / omega, 400)
    yw = M * np.sin(omega * tw + phi)

    # The peanut: profile along the motion (x); bright ends where the spot dwells.
    prof = image.sum(0).numpy()
    x = np.arange(W) - float(rest[0])
    peaks = local_maxima(prof)
    top2 = np.sort(peaks[np.argsort(prof[peaks])[-2:]]) if peaks.size >= 2 else peaks
    centre_val = float(np.interp(0.5 * (yw.max() + yw.min()), x, prof))
    ends_ratio = float(prof[top2].min() / centre_val) if top2.size == 2 else float("nan")
    total = float(image.sum())
    total_expected = float(cam.peak_e_per_s) * 2 * math.pi * float(cfg.psf_sigma_px) ** 2 * p / omega

    P = plt()
    fig, axes = P.subplots(2, 2, figsize=(11, 7.2))
    ax = axes[0, 0]
    ms = 1e3
    ax.axvspan(b / omega * ms, (b + p) / omega * ms, color="C2", alpha=0.18, label="exposure window")
    ax.plot(t * ms, u, "C0--", lw=1.2, label=r"command $u = A\,\sin(\omega t)$")
    ax.plot(t * ms, y, "C3-", lw=1.6, label=r"output $y = M\,\sin(\omega t + \phi)$")
    ax.plot(tw * ms, yw, "C3-", lw=4, alpha=0.5)
    ax.axhline(0, color="0.6", lw=0.6)
    ax.set_xlabel("time since an upward zero crossing of u [ms]")
    ax.set_ylabel("u [command units], y = x - x0 [px]")
    ax.set_title(f"(a) {f:g} Hz: M = {M:.2f} px, phase = {math.degrees(phi):.1f} deg;\n"
                 f"exposure p = {math.degrees(p):.0f} deg from w*tcam = {math.degrees(b):.0f} deg", fontsize=10)
    ax.set_ylim(-1.25 * max(A, M), 1.9 * max(A, M))
    ax.legend(fontsize=8, loc="upper right", ncol=2, framealpha=0.9)
    ext = [-0.5 - float(rest[0]), W - 0.5 - float(rest[0]), H - 0.5 - float(rest[1]), -0.5 - float(rest[1])]
    for ax, img, title in ((axes[0, 1], image, "(b) rendered image (noise-free)"),
                           (axes[1, 0], frame, "(c) simulated camera frame (rig: shot + read noise)")):
        im = ax.imshow(img.numpy(), cmap="inferno", extent=ext, interpolation="nearest")
        ax.set_xlabel("x - x0 [px]")
        ax.set_ylabel("y - y0 [px]")
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, ax=ax, shrink=0.8, label="electrons")
    ax = axes[1, 1]
    ax.plot(x, prof / prof.max(), "k-", lw=1.5, label="column sum of (b)")
    for i in top2:
        ax.plot(x[i], prof[i] / prof.max(), "o", color="C3")
    ax.axvline(M * math.sin(b + phi), color="C0", ls=":", label="spot at exposure start")
    ax.axvline(M * math.sin(b + p + phi), color="C1", ls=":", label="spot at exposure end")
    ax.axvspan(yw.min(), yw.max(), color="C2", alpha=0.12, label="range swept")
    ax.set_xlabel("x - x0 [px]")
    ax.set_ylabel("intensity (normalised)")
    ax.set_title(f"(d) profile along the motion: ends {ends_ratio:.1f}x brighter than the middle", fontsize=10)
    ax.set_ylim(0, 1.45)
    ax.legend(fontsize=8, loc="upper center", ncol=2)
    fig.suptitle("Fig. 1/3: a sine exposed for half a period blurs into a peanut", fontsize=12)
    fig.tight_layout()
    save_figure(fig, out, "fig1_peanut.png")

    metrics = {
        "amplitude_px": M,
        "phase_rad": phi,
        "phase_deg": math.degrees(phi),
        "exposure_phase_rad": p,
        "trigger_phase_rad": b,
        "motion_range_px": [float(yw.min()), float(yw.max())],
        "profile_peaks_px": [float(x[i]) for i in top2],
        "n_profile_peaks": int(peaks.size),
        "ends_to_middle_ratio": ends_ratio,
        "total_light_e": total,
        "total_light_expected_e": total_expected,
        "rig_frame_peak_e": float(frame.max()),
        "rig_vs_render_rel_rms": float((frame - image).square().mean().sqrt() / image.max()),
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"fig1: M = {M:.3f} px, phase = {math.degrees(phi):.2f} deg, profile peaks at {metrics['profile_peaks_px']} px, "
          f"ends/middle = {ends_ratio:.2f}  -> {out}")


if __name__ == "__main__":
    main()
