"""Fig. 4 of Tani, Mishra, Wen (CDC 2012): peak intensity versus exposure time.

The simulated rig's camera looks at the still spot (mirror at rest) for a range of exposure
times; the peak pixel of the averaged frames grows linearly with the exposure until the
pixel's well is full, then stays flat. ``torchblur.image.preprocess.saturation_curve`` fits
``min(offset + slope t, plateau)``; the camera model's truth is overlaid. Saturated pixels
carry no information, which is why a fitter masks them (``SaturationCurve.mask``).

Panels: (a) peak versus exposure, the fit and the truth; (b) the row through the spot at a
few exposures: the top flattens once the spot saturates.

    python experiments/fig4_saturation.py --out runs/fig4 [--quick] [key=value ...]
"""
from __future__ import annotations

import time

import numpy as np
import torch

from common import parse, plt, save_figure, write_metrics

import torchblur as tb
from torchblur.render.camera import CameraModel
from torchblur.systems.lti import Plant
from torchblur.image.preprocess import saturation_curve
from torchblur.rig.simulated import SimulatedRig

F64 = torch.float64


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig4_saturation.yaml")
    H, W = (int(v) for v in cfg.frame_shape)
    c = cfg.camera
    camera = CameraModel(dark_level_adu=float(c.dark_level_adu), read_noise_e=float(c.read_noise_e),
                         gain_e_per_adu=float(c.gain_e_per_adu), full_well_e=float(c.full_well_e), bit_depth=int(c.bit_depth))
    rest = ((W - 1) // 2, (H - 1) // 2)  # a pixel centre
    rig = SimulatedRig(plant=Plant(num=(1.0,), den=(1.0,)), camera=camera, frame_shape=(H, W),
                       psf_sigma_px=float(cfg.psf_sigma_px), rest_px=rest, peak_e_per_s=float(cfg.peak_e_per_s),
                       seed=int(cfg.seed))
    exposures = np.linspace(float(cfg.exposure_min_s), float(cfg.exposure_max_s), int(cfg.n_exposures))
    extra = [float(t) for t in cfg.profile_exposures_s]
    n = int(cfg.frames_per_exposure)
    peaks = np.array([float(rig.still(n, float(te)).frames.mean(0).max()) for te in exposures])  # ADU
    rows = {te: rig.still(n, te).frames.mean(0)[rest[1]].numpy() for te in extra}  # row through the spot
    fit = saturation_curve(torch.tensor(peaks, dtype=F64), torch.tensor(exposures, dtype=F64), full_scale_adu=camera.max_adu)

    # The truth: the pixel-integrated still spot's peak rate through the camera's gain.
    still = tb.Sinusoid(torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64), torch.tensor(1.0, dtype=F64))
    rate = tb.render_blur(still, rig.psf, tb.ExposureWindow(0.0, 1.0), height=H, width=W,
                          settings=tb.RenderSettings(pixel_integration=True)).max()
    slope_true = float(rate) / camera.gain_e_per_adu
    plateau_true = camera.saturation_adu
    limit_true = (plateau_true - camera.dark_level_adu) / slope_true

    P = plt()
    fig, (ax, axr) = P.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.3, 1]})
    tt = np.linspace(0, exposures.max() * 1.02, 400)
    ms = 1e3
    ax.plot(tt * ms, np.minimum(camera.dark_level_adu + slope_true * tt, plateau_true), color="0.6", lw=4, alpha=0.6,
            label="camera model (truth)")
    ax.plot(exposures * ms, peaks, "o", color="C0", ms=5, label=f"peak of {n} averaged still frames (rig)")
    ax.plot(tt * ms, fit(torch.tensor(tt, dtype=F64)).numpy(), "C3-", lw=1.5,
            label=f"fitted saturation_curve: slope {float(fit.slope_adu_per_s):.4g} ADU/s")
    if fit.saturated_in_data:
        ax.axhline(float(fit.saturation_adu), color="C3", ls=":", lw=1)
        ax.axvline(float(fit.linear_limit_s) * ms, color="C3", ls="--", lw=1,
                   label=f"linear limit {float(fit.linear_limit_s) * ms:.2f} ms, plateau {float(fit.saturation_adu):.0f} ADU")
        ax.axvspan(float(fit.linear_limit_s) * ms, tt.max() * ms, color="C3", alpha=0.07)
    ax.set_xlabel("exposure time [ms]")
    ax.set_ylabel("peak intensity [ADU]")
    ax.set_xlim(0, tt.max() * ms)
    ax.set_ylim(0, plateau_true * 1.15)
    ax.set_title("(a) peak intensity of a still spot vs exposure: linear, then saturated", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    x = np.arange(W) - rest[0]
    for k, te in enumerate(extra):
        lin = "linear" if te <= float(fit.linear_limit_s) else "saturated"
        axr.plot(x, rows[te], "-o", ms=3, color=f"C{k}", label=f"Te = {te * ms:g} ms ({lin})")
    axr.axhline(plateau_true, color="0.4", ls=":", label=f"saturation {plateau_true:.0f} ADU")
    axr.set_xlabel("x - x0 [px] (row through the spot)")
    axr.set_ylabel("intensity [ADU]")
    axr.set_title("(b) the spot's profile: flat-topped once saturated", fontsize=10)
    axr.legend(fontsize=8, loc="upper right")
    axr.set_ylim(0, plateau_true * 1.3)
    axr.grid(alpha=0.3)
    fig.suptitle("Fig. 4: peak intensity vs exposure time (simulated rig, 12-bit camera, full well 20000 e)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig4_saturation.png")

    metrics = {
        "slope_adu_per_s": float(fit.slope_adu_per_s),
        "slope_true_adu_per_s": slope_true,
        "slope_rel_error": float(fit.slope_adu_per_s) / slope_true - 1,
        "offset_adu": float(fit.offset_adu),
        "dark_level_adu": camera.dark_level_adu,
        "plateau_adu": float(fit.saturation_adu),
        "camera_saturation_adu": plateau_true,
        "linear_limit_s": float(fit.linear_limit_s),
        "linear_limit_true_s": limit_true,
        "saturated_in_data": bool(fit.saturated_in_data),
        "residual_rms_adu": float(fit.residual_rms_adu),
        "exposures_s": exposures.tolist(),
        "peaks_adu": peaks.tolist(),
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"fig4: slope {metrics['slope_adu_per_s']:.5g} (truth {slope_true:.5g}) ADU/s, "
          f"plateau {metrics['plateau_adu']:.1f} (camera {plateau_true:.1f}) ADU, "
          f"linear limit {metrics['linear_limit_s'] * 1e3:.3f} ms (truth {limit_true * 1e3:.3f})  -> {out}")


if __name__ == "__main__":
    main()
