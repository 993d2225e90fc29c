"""Fig. 5 of Tani, Mishra, Wen (CDC 2012): the cost versus phase for different norms.

One exposure (p = half a period, w tcam = pi/2), the amplitude known, the phase scanned
over a full turn: ``||C(M sin(w t + phi)) - Y||`` with the 1-norm, the 2-norm (Frobenius)
and the inf-norm of the pixel residual (``torchblur.losses.image_loss``; the l2 loss is the
squared norm, its square root is plotted). Noise-free (perfect predictor) and noisy
(``CameraModel``: shot and read noise, 12-bit ADC, four frames averaged, as the paper). Each
curve is normalised to [0, 1] for display. Both minima (the true phase and its alias) are
minima of every norm; the norms differ in how sharp the minimum is and in how much the noise
moves it.

Panels: top, the full turn (noise-free | noisy); bottom, the detail near the true phase.

    python experiments/fig5_norms.py --out runs/fig5 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, periodic_minima, plt, save_figure, wrapped, write_metrics, x_sinusoid

import torchblur as tb
from torchblur.render.camera import CameraModel
from torchblur.losses import image_loss

F64 = torch.float64
LABEL = {"l1": "1-norm", "l2": "2-norm (Frobenius)", "linf": "inf-norm"}


def sharpness(phase: np.ndarray, cost: np.ndarray, at: float, halfwidth: float) -> tuple[float, float]:
    """Curvature (second derivative, 1/rad^2) of a quadratic least-squares fit of ``cost``
    over ``|phase - at| <= halfwidth``, and the mean rise of ``cost`` at +-halfwidth."""
    d = wrapped(phase - at)
    sel = np.abs(d) <= halfwidth + 1e-12
    coef = np.polyfit(d[sel], cost[sel], 2)
    c0 = np.interp(0.0, np.sort(d[sel]), cost[sel][np.argsort(d[sel])])
    lo = np.interp(-halfwidth, np.sort(d[sel]), cost[sel][np.argsort(d[sel])])
    hi = np.interp(halfwidth, np.sort(d[sel]), cost[sel][np.argsort(d[sel])])
    return float(2 * coef[0]), float(0.5 * (lo + hi) - c0)


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig5_norms.yaml")
    f = float(cfg.freq_hz)
    omega = 2 * math.pi * f
    H, W = int(cfg.height), int(cfg.width)
    M, phi0 = float(cfg.amplitude_px), float(cfg.true_phase_rad)
    b, p = float(cfg.trigger_phase_rad), 2 * math.pi * float(cfg.exposure_fraction)
    P = int(cfg.n_phase)
    norms = list(cfg.norms)

    rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64)
    psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=F64), amplitude=float(cfg.peak_e_per_s))
    window = tb.ExposureWindow(torch.tensor(b / omega, dtype=F64), torch.tensor(p / omega, dtype=F64))
    renderer = tb.BlurRenderer(height=H, width=W)
    om = torch.tensor(omega, dtype=F64)


    clean = renderer(x_sinusoid(M, phi0, om), psf, window)  # [H, W] electrons
    c = cfg.camera
    camera = CameraModel(dark_level_adu=float(c.dark_level_adu), read_noise_e=float(c.read_noise_e),
                         gain_e_per_adu=float(c.gain_e_per_adu), full_well_e=float(c.full_well_e), bit_depth=int(c.bit_depth))
    gen = torch.Generator().manual_seed(int(cfg.seed))
    n_avg = int(cfg.frames_averaged)
    frames = camera.expose(clean.expand(n_avg, H, W).contiguous(), generator=gen)
    noisy = camera.to_electrons(frames).mean(0)  # [H, W] electrons, dark level removed
    alias = float(tb.alias_phase(torch.tensor(phi0, dtype=F64), om, window))

    grid = torch.linspace(-math.pi, math.pi, P + 1, dtype=F64)[:-1]
    model = renderer(x_sinusoid(M, grid, om), psf, window).flatten(-2)  # [P, H*W]
    g = grid.numpy()

    def cost_curve(data, nm):
        cost = image_loss(model, data.flatten()[None], loss=nm)  # [P]
        return (cost.sqrt() if nm == "l2" else cost).numpy()

    def true_branch_min(cost):
        return min(periodic_minima(g, cost)[:2], key=lambda m: abs(wrapped(m[0] - phi0)))

    # Noise sensitivity: the true-branch argmin over independent noise realisations.
    R = int(cfg.noise_realisations)
    more = camera.to_electrons(camera.expose(clean.expand(R, n_avg, H, W).contiguous(), generator=gen)).mean(1)
    spread = {nm: np.array([true_branch_min(cost_curve(more[r], nm))[0] for r in range(R)]) for nm in norms}
    hw = float(cfg.curvature_halfwidth_rad)
    curves, metrics_cases = {}, {}
    for case, data in (("noise_free", clean), ("noisy", noisy)):
        curves[case] = {}
        metrics_cases[case] = {}
        for nm in norms:
            cost = cost_curve(data, nm)
            norm = (cost - cost.min()) / (cost.max() - cost.min())
            curves[case][nm] = norm
            mins = periodic_minima(g, norm)[:2]
            true_m = true_branch_min(norm)
            alias_m = min(mins, key=lambda m: abs(wrapped(m[0] - alias)))
            curv, rise = sharpness(g, norm, true_m[0], hw)
            metrics_cases[case][nm] = {
                "argmin_rad": true_m[0],
                "argmin_deg": math.degrees(true_m[0]),
                "error_rad": float(wrapped(true_m[0] - phi0)),
                "alias_argmin_rad": alias_m[0],
                "alias_error_rad": float(wrapped(alias_m[0] - alias)),
                "curvature_per_rad2": curv,
                "rise_at_halfwidth": rise,
                "min_value_normalised": true_m[1],
                "cost_min": float(cost.min()),
                "cost_max": float(cost.max()),
            }
            if case == "noisy":
                err = wrapped(spread[nm] - phi0)
                metrics_cases[case][nm].update({"argmin_std_rad": float(err.std()), "argmin_bias_rad": float(err.mean()),
                                                "argmin_std_deg": math.degrees(float(err.std())), "realisations": R})

    Pl = plt()
    fig, axes = Pl.subplots(2, 2, figsize=(9.4, 5.9))
    deg = np.degrees(g)
    dsel = np.abs(wrapped(g - phi0)) <= float(cfg.detail_halfwidth_rad)
    styles = {"l1": ("C0", "-"), "l2": ("C3", "-"), "linf": ("C2", "-")}
    for col, (case, title) in enumerate((("noise_free", "noise-free (perfect predictor)"),
                                         ("noisy", f"noisy (shot + read noise, {n_avg} frames averaged, one draw)"))):
        for row in range(2):
            ax = axes[row, col]
            for nm in norms:
                colr, ls = styles.get(nm, ("k", "-"))
                m = metrics_cases[case][nm]
                lab = f"{LABEL.get(nm, nm)}: min {m['argmin_deg']:.1f} deg, curv. {m['curvature_per_rad2']:.1f}/rad^2"
                if case == "noisy":
                    lab += f", std {m['argmin_std_deg']:.2f} deg"
                sel = dsel if row else slice(None)
                ax.plot(deg[sel], curves[case][nm][sel], color=colr, ls=ls, lw=1.4, label=lab if row else LABEL.get(nm, nm))
            ax.axvline(math.degrees(phi0), color="k", ls="--", lw=1, label=f"true phase {math.degrees(phi0):.0f} deg")
            if not row:
                ax.axvline(math.degrees(alias), color="0.5", ls=":", lw=1.2, label=f"alias {math.degrees(alias):.0f} deg")
                ax.set_xlim(-180, 180)
                ax.set_xticks(np.arange(-180, 181, 45))
                ax.set_title(f"({'ab'[col]}) {title}", fontsize=10)
            else:
                ax.set_title(f"({'cd'[col]}) detail near the true phase, {title.split(' (')[0]}", fontsize=10)
                ax.set_ylim(-0.02, 0.6)
            ax.set_xlabel("model phase [deg]")
            ax.set_ylabel("normalised cost")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7.5, loc="upper left" if not row else "upper center", framealpha=0.9)
    fig.suptitle(f"Fig. 5: cost vs phase for three norms (M = {M:g} px, p = {math.degrees(p):.0f} deg, "
                 f"w*tcam = {math.degrees(b):.0f} deg), each normalised to [0, 1]"
                 f"\nstd: spread of the true-branch minimum over {R} noise draws", fontsize=10.5)
    fig.tight_layout()
    save_figure(fig, out, "fig5_norms.png")

    metrics = {
        "true_phase_rad": phi0,
        "alias_phase_rad": alias,
        "peak_electrons": float(clean.max()),
        "noise_rms_electrons": float((noisy - clean).square().mean().sqrt()),
        **metrics_cases,
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    for case in metrics_cases:
        print(f"fig5 {case}: " + ", ".join(f"{nm} argmin {v['argmin_deg']:.2f} deg curvature {v['curvature_per_rad2']:.1f}"
                                           for nm, v in metrics_cases[case].items()))


if __name__ == "__main__":
    main()
