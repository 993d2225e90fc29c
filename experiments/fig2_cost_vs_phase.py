"""Fig. 2 of Tani, Mishra, Wen (CDC 2012): cost versus phase for several exposure times.

Perfect predictor: the measured image is rendered at the true (M, phi); the model is
rendered at the true M over a grid of phases, one exposure at a time, and compared with the
l2 (Frobenius squared) cost. Each curve has two zeros: the true phase, the same for every
exposure, and its alias ``pi - 2c - phi`` (c: phase at the window centre), which moves with
the exposure (Proposition 3, ``torchblur.alias_phase``). The whole grid (exposures x phases)
is one batched render.

Panels: (a) the relative cost ``||C(phi) - Y||^2 / ||Y||^2`` over a full turn, the alias
predicted by the formula marked; (b) the detail near the true phase.

    python experiments/fig2_cost_vs_phase.py --out runs/fig2 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, periodic_minima, plt, save_figure, wrapped_distance, write_metrics, x_sinusoid

import torchblur as tb
from torchblur.losses import image_loss

F64 = torch.float64


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig2_cost_vs_phase.yaml")
    f = float(cfg.freq_hz)
    omega = 2 * math.pi * f
    H, W = int(cfg.height), int(cfg.width)
    M, phi0 = float(cfg.amplitude_px), float(cfg.true_phase_rad)
    b = float(cfg.trigger_phase_rad)
    fractions = [float(v) for v in cfg.exposure_fractions]
    E, P = len(fractions), int(cfg.n_phase)

    rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64)
    psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=F64))
    period = 1 / f
    window = tb.ExposureWindow(torch.full((E, 1), b / omega, dtype=F64),
                               torch.tensor(fractions, dtype=F64)[:, None] * period)  # [E, 1]
    renderer = tb.BlurRenderer(height=H, width=W)
    om = torch.tensor(omega, dtype=F64)


    data = renderer(x_sinusoid(M, phi0, om), psf, window)                    # [E, 1, H, W]
    grid = torch.linspace(-math.pi, math.pi, P + 1, dtype=F64)[:-1]     # [P]
    model = renderer(x_sinusoid(M, grid, om), psf, window)                    # [E, P, H, W]
    cost = image_loss(model.flatten(-2), data.flatten(-2), loss="l2")   # [E, P]
    rel = (cost / data.flatten(-2).square().sum(-1)).numpy()            # relative to ||Y||^2
    alias = tb.alias_phase(torch.tensor(phi0, dtype=F64), om, window[:, 0])  # [E]

    g = grid.numpy()
    per_exposure = []
    for e in range(E):
        mins = periodic_minima(g, rel[e])
        deep = [m for m in mins if m[1] < 1e-3][:2] or mins[:2]
        true_m = min(deep, key=lambda m: wrapped_distance(m[0], phi0))
        others = [m for m in deep if m is not true_m]
        alias_m = others[0] if others else true_m
        per_exposure.append({
            "exposure_fraction": fractions[e],
            "exposure_phase_rad": 2 * math.pi * fractions[e],
            "minima_rad": [m[0] for m in deep],
            "n_local_minima": len(mins),
            "true_argmin_rad": true_m[0],
            "true_argmin_deg": math.degrees(true_m[0]),
            "alias_argmin_rad": alias_m[0],
            "alias_argmin_deg": math.degrees(alias_m[0]),
            "alias_formula_rad": float(alias[e]),
            "alias_formula_deg": math.degrees(float(alias[e])),
            "alias_error_rad": wrapped_distance(alias_m[0], float(alias[e])),
            "true_error_rad": wrapped_distance(true_m[0], phi0),
            "cost_max_relative": float(rel[e].max()),
        })
    trues = np.array([m["true_argmin_rad"] for m in per_exposure])
    aliases = np.array([m["alias_argmin_rad"] for m in per_exposure])
    spread_true = float(max(wrapped_distance(a, c) for a in trues for c in trues))
    spread_alias = float(max(wrapped_distance(a, c) for a in aliases for c in aliases))

    P_ = plt()
    fig, (ax, axd) = P_.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.6, 1]})
    deg = np.degrees(g)
    for e in range(E):
        col = f"C{e}"
        lab = f"Te = {fractions[e]:.0%} of the period"
        ax.plot(deg, rel[e], color=col, lw=1.4, label=lab)
        ax.plot(math.degrees(float(alias[e])), 0, "v", color=col, ms=8, mec="k", mew=0.5)
        sel = np.abs(np.degrees(tb.wrap_phase(torch.tensor(g - phi0)).numpy())) <= math.degrees(float(cfg.detail_halfwidth_rad))
        axd.plot(deg[sel], rel[e][sel], color=col, lw=1.6, label=lab)
        axd.plot(math.degrees(per_exposure[e]["true_argmin_rad"]), per_exposure[e]["cost_max_relative"] * 0, "o", color=col, ms=5)
    for a in (ax, axd):
        a.axvline(math.degrees(phi0), color="k", ls="--", lw=1, label=f"true phase {math.degrees(phi0):.0f} deg")
        a.set_xlabel("model phase [deg]")
        a.set_ylabel(r"cost $\|C(\phi) - Y\|_2^2 / \|Y\|_2^2$")
        a.grid(alpha=0.3)
    ax.plot([], [], "v", color="0.5", mec="k", mew=0.5, label="alias (formula)")
    ax.set_xlim(-180, 180)
    ax.set_xticks(np.arange(-180, 181, 45))
    ax.set_title("(a) cost vs phase, one exposure each (w*tcam = 90 deg): two minima per curve", fontsize=10)
    ax.legend(fontsize=8, loc="upper right", ncol=2)
    top = float(rel.max())
    ax.set_ylim(-0.03 * top, 1.25 * top)
    axd.set_title("(b) detail near the true phase: its position does not move", fontsize=10)
    axd.set_ylim(bottom=-0.02 * float(max(rel[e][sel].max() for e in range(E))))
    fig.suptitle(f"Fig. 2: M = {M:g} px at {f:g} Hz, perfect predictor; the true minimum stays, the alias moves with Te",
                 fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig2_cost_vs_phase.png")

    metrics = {
        "true_phase_rad": phi0,
        "per_exposure": per_exposure,
        "true_argmins_rad": trues.tolist(),
        "alias_argmins_rad": aliases.tolist(),
        "alias_formula_rad": [float(a) for a in alias],
        "true_argmin_spread_rad": spread_true,
        "alias_argmin_spread_rad": spread_alias,
        "max_alias_error_rad": float(max(m["alias_error_rad"] for m in per_exposure)),
        "grid_step_rad": float(g[1] - g[0]),
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"fig2: true argmins {np.degrees(trues).round(2)} deg (spread {math.degrees(spread_true):.3f} deg), "
          f"alias argmins {np.degrees(aliases).round(2)} deg vs formula {np.degrees(alias.numpy()).round(2)}  -> {out}")


if __name__ == "__main__":
    main()
