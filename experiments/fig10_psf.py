"""Fig. 10 of Tani, Mishra, Wen (CDC 2012): PSF identification.

The paper's steps 1-2 on the simulated rig: dark frames give the dark level
(``torchblur.image.preprocess.dark_frame``); still frames of a tilted elliptical spot, dark
subtracted and averaged, are fitted with a 2-D Gaussian of full covariance
(``torchblur.image.preprocess.fit_gaussian_psf``, pixel-area integration like the rig's camera),
weighted by the measured per-pixel noise of the average. The residual is at the noise level.

Panels: (a) the averaged still spot; (b) the fitted Gaussian with the 1- and 2-sigma
ellipses of the fit and of the truth; (c) the residual in units of its noise; (d) cuts
through the spot along x and y, measured and fitted.

    python experiments/fig10_psf.py --out runs/fig10 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, plt, save_figure, write_metrics

from torchblur.render.camera import CameraModel
from torchblur.systems.lti import Plant
from torchblur.image.preprocess import dark_frame, fit_gaussian_psf, subtract_dark
from torchblur.rig.simulated import SimulatedRig

F64 = torch.float64


def ellipse(center, cov, k: float, n: int = 200) -> np.ndarray:
    """Points ``[n, 2]`` (x, y) of the k-sigma ellipse of a covariance."""
    vals, vecs = np.linalg.eigh(np.asarray(cov))
    t = np.linspace(0, 2 * math.pi, n)
    circle = np.stack([np.cos(t), np.sin(t)], -1) * (k * np.sqrt(vals))
    return np.asarray(center) + circle @ vecs.T


def axes_of(cov) -> tuple[float, float, float]:
    """(sigma_major px, sigma_minor px, angle of the major axis from +x toward +y, rad)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov))
    ang = math.atan2(vecs[1, 1], vecs[0, 1])
    ang = (ang + math.pi / 2) % math.pi - math.pi / 2
    return float(math.sqrt(vals[1])), float(math.sqrt(vals[0])), ang


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig10_psf.yaml")
    H, W = (int(v) for v in cfg.frame_shape)
    c = cfg.camera
    camera = CameraModel(dark_level_adu=float(c.dark_level_adu), read_noise_e=float(c.read_noise_e),
                         gain_e_per_adu=float(c.gain_e_per_adu), full_well_e=float(c.full_well_e), bit_depth=int(c.bit_depth))
    cov_true = torch.tensor([[float(v) for v in row] for row in cfg.psf_cov], dtype=F64)
    rest = [float(v) for v in cfg.rest_px]
    rig = SimulatedRig(plant=Plant(num=(1.0,), den=(1.0,)), camera=camera, frame_shape=(H, W), psf_cov=cov_true,
                       rest_px=rest, peak_e_per_s=float(cfg.peak_e_per_s), seed=int(cfg.seed))
    te = float(cfg.exposure_s)
    n = int(cfg.n_frames)
    dark = dark_frame(rig.dark(int(cfg.n_dark), te).frames)
    frames = subtract_dark(rig.still(n, te).frames, dark)  # [n, H, W] ADU above dark
    image = frames.mean(0)
    noise = (frames.var(0) / n + dark.read_noise**2 / dark.n_frames).sqrt()  # std of the averaged pixel
    fit = fit_gaussian_psf(image, exposure_s=te, noise_std=noise, pixel_integration=True)
    cov_fit = fit.psf.cov
    resid = image - fit.model
    chi2_dof = float((resid / noise).square().sum() / (H * W - 7))
    rel_err = float((cov_fit - cov_true).norm() / cov_true.norm())
    entry_err = ((cov_fit - cov_true).abs() / cov_true.abs().max()).max()
    z = ((cov_fit - cov_true) / fit.cov_std)
    amp_true = float(cfg.peak_e_per_s) / camera.gain_e_per_adu
    ax_true, ax_fit = axes_of(cov_true.numpy()), axes_of(cov_fit.numpy())

    Pl = plt()
    fig, axs = Pl.subplots(1, 4, figsize=(16, 4.1), gridspec_kw={"width_ratios": [1, 1, 1, 1.15]})
    ext = [-0.5, W - 0.5, H - 0.5, -0.5]
    vmax = float(image.max())
    im = axs[0].imshow(image.numpy(), cmap="inferno", extent=ext, vmin=0, vmax=vmax, interpolation="nearest")
    axs[0].set_title(f"(a) measured: mean of {n} still frames\n(dark subtracted, cropped)", fontsize=10)
    fig.colorbar(im, ax=axs[0], shrink=0.8, label="ADU")
    im = axs[1].imshow(fit.model.numpy(), cmap="inferno", extent=ext, vmin=0, vmax=vmax, interpolation="nearest")
    cf = fit.psf.center.numpy()
    for k, ls in ((1, "-"), (2, "--")):
        e_fit, e_true = ellipse(cf, cov_fit.numpy(), k), ellipse(rest, cov_true.numpy(), k)
        axs[1].plot(e_true[:, 0], e_true[:, 1], color="c", ls=ls, lw=2.2, alpha=0.8, label=f"truth {k} sigma")
        axs[1].plot(e_fit[:, 0], e_fit[:, 1], color="w", ls=ls, lw=1.0, label=f"fit {k} sigma")
    axs[1].legend(fontsize=7, loc="lower right", framealpha=0.6)
    axs[1].set_title("(b) fitted 2-D Gaussian (full covariance)\n"
                     f"sigma {ax_fit[0]:.3f} x {ax_fit[1]:.3f} px at {math.degrees(ax_fit[2]):.1f} deg", fontsize=10)
    fig.colorbar(im, ax=axs[1], shrink=0.8, label="ADU")
    r = (resid / noise).numpy()
    lim = max(4.0, float(np.abs(r).max()))
    im = axs[2].imshow(r, cmap="RdBu_r", extent=ext, vmin=-lim, vmax=lim, interpolation="nearest")
    axs[2].set_title(f"(c) residual / noise: chi2/dof = {chi2_dof:.2f}\n"
                     f"rms {float(fit.residual_rms):.2f} ADU = {float(fit.relative_residual):.1e} of the peak", fontsize=10)
    fig.colorbar(im, ax=axs[2], shrink=0.8, label="residual [noise std]")
    row, col = int(round(float(cf[1]))), int(round(float(cf[0])))
    half = int(cfg.crop_halfwidth_px)
    for a in axs[:3]:
        a.set_xlim(col - half - 0.5, col + half + 0.5)
        a.set_ylim(row + half + 0.5, row - half - 0.5)
        a.set_xlabel("x [px]")
        a.set_ylabel("y [px]")
    x = np.arange(W)
    y = np.arange(H)
    axs[3].errorbar(x, image[row].numpy(), yerr=noise[row].numpy(), fmt="o", ms=3, color="C0", label=f"measured, row y = {row}")
    axs[3].plot(x, fit.model[row].numpy(), "-", color="C0", lw=1.2, label="fit, row")
    axs[3].errorbar(y, image[:, col].numpy(), yerr=noise[:, col].numpy(), fmt="s", ms=3, color="C3",
                    label=f"measured, column x = {col}")
    axs[3].plot(y, fit.model[:, col].numpy(), "-", color="C3", lw=1.2, label="fit, column")
    axs[3].set_xlim(min(row, col) - half - 0.5, max(row, col) + half + 0.5)
    axs[3].set_xlabel("x (row cut) or y (column cut) [px]")
    axs[3].set_ylabel("intensity above dark [ADU]")
    axs[3].set_title("(d) cuts through the spot", fontsize=10)
    axs[3].legend(fontsize=7.5, loc="upper left")
    axs[3].grid(alpha=0.3)
    fig.suptitle(f"Fig. 10: PSF identification on the simulated rig: true cov "
                 f"[[{cov_true[0, 0]:.2f}, {cov_true[0, 1]:.2f}], [{cov_true[1, 0]:.2f}, {cov_true[1, 1]:.2f}]], fitted "
                 f"[[{cov_fit[0, 0]:.3f}, {cov_fit[0, 1]:.3f}], [{cov_fit[1, 0]:.3f}, {cov_fit[1, 1]:.3f}]] px^2", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig10_psf.png")

    metrics = {
        "cov_true_px2": cov_true.tolist(),
        "cov_fit_px2": cov_fit.tolist(),
        "cov_std_px2": fit.cov_std.tolist(),
        "cov_z_scores": z.tolist(),
        "cov_rel_error_frobenius": rel_err,
        "cov_max_entry_error_rel": float(entry_err),
        "sigma_axes_true_px": list(ax_true[:2]),
        "sigma_axes_fit_px": list(ax_fit[:2]),
        "angle_true_rad": ax_true[2],
        "angle_fit_rad": ax_fit[2],
        "center_true_px": rest,
        "center_fit_px": fit.psf.center.tolist(),
        "amplitude_true_adu_per_s": amp_true,
        "amplitude_fit_adu_per_s": float(fit.psf.amplitude),
        "amplitude_rel_error": float(fit.psf.amplitude) / amp_true - 1,
        "background_adu": float(fit.background),
        "relative_residual": float(fit.relative_residual),
        "residual_rms_adu": float(fit.residual_rms),
        "chi2_per_dof": chi2_dof,
        "converged": bool(fit.converged),
        "dark_read_noise_adu": float(dark.read_noise),
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"fig10: cov fit {np.round(cov_fit.numpy(), 4).tolist()} vs truth {cov_true.tolist()} "
          f"(rel. error {rel_err:.2e}), relative residual {metrics['relative_residual']:.2e}, chi2/dof {chi2_dof:.2f}")


if __name__ == "__main__":
    main()
