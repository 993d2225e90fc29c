"""Fig. 7 of Tani, Mishra, Wen (CDC 2012): two exposures remove the alias.

Two images of the same motion, exposed for 30% and 80% of the period from a shared start
(``torchblur.design.windows.dual_exposure_windows``, w tcam = pi/2), perfect predictor. Each single
exposure's cost has two minima, the true phase and its alias ``pi - 2c - phi``; the aliases
differ because the window centres c differ (by a quarter period here, the best case,
``alias_separation = 1``). The joint cost, the sum of both l2 costs (maximum likelihood under
equal pixel noise), keeps only the true minimum. The paper's eq. 8 (each term normalised by
its image's norm) is shown too.

Panels: (a) the relative cost versus phase (amplitude known) for each exposure and jointly;
(b) the joint cost over amplitude and phase, rendered in batches of grid points.

    python experiments/fig7_dual_exposure.py --out runs/fig7 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, periodic_minima, plt, save_figure, wrapped_distance, write_metrics, x_sinusoid

import torchblur as tb
from torchblur.design.windows import alias_separation, dual_exposure_windows
from torchblur.fit.landscape import cost_landscape

F64 = torch.float64


def grid_minima(cost: np.ndarray) -> list[tuple[int, int]]:
    """Local minima ``(i, j)`` of ``cost[amplitude i, phase j]`` over the 8 neighbours (phase
    periodic), deepest first."""
    padded = np.pad(cost, ((1, 1), (0, 0)), constant_values=np.inf)
    is_min = np.ones(cost.shape, dtype=bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                nb = np.roll(padded, (-di, -dj), axis=(0, 1))[1:-1]
                is_min &= (cost < nb) if (di < 0 or (di == 0 and dj < 0)) else (cost <= nb)
    return sorted(map(tuple, np.argwhere(is_min)), key=lambda ij: cost[ij])


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig7_dual_exposure.yaml")
    f = float(cfg.freq_hz)
    omega = 2 * math.pi * f
    H, W = int(cfg.height), int(cfg.width)
    M, phi0 = float(cfg.amplitude_px), float(cfg.true_phase_rad)
    fractions = tuple(float(v) for v in cfg.exposure_fractions)
    om = torch.tensor(omega, dtype=F64)
    window = dual_exposure_windows(om, fractions=fractions, trigger_phase=float(cfg.trigger_phase_rad))  # [E]
    E = window.shape[-1]
    separation = float(alias_separation(om, window))

    rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64)
    psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=F64))
    renderer = tb.BlurRenderer(height=H, width=W)


    data = renderer(x_sinusoid(M, phi0, om), psf, window).flatten(-2)   # [E, H*W]
    energy = data.square().sum(-1)                                 # [E] = ||Y_e||^2
    aliases = tb.alias_phase(torch.tensor(phi0, dtype=F64), om, window)  # [E]

    # 1-D: amplitude known, phase scanned; the loss of each exposure [P, E].
    P = int(cfg.n_phase)
    grid = torch.linspace(-math.pi, math.pi, P + 1, dtype=F64)[:-1]
    images = data.reshape(E, H, W)
    c = cost_landscape(images, psf, window, om, torch.tensor([M], dtype=F64), grid, chunk=int(cfg.batch))["l2"][0]  # [P, E]
    single = (c / energy).T.numpy()                                         # [E, P] relative
    joint = (c.sum(-1) / energy.sum()).numpy()                              # [P] maximum likelihood
    eq8 = (c.sqrt() / energy.sqrt()).sum(-1).numpy() / E                    # [P] the paper's eq. 8
    g = grid.numpy()

    single_minima = [periodic_minima(g, single[e])[:2] for e in range(E)]
    joint_minima = periodic_minima(g, joint)
    eq8_minima = periodic_minima(g, eq8)

    def at(curve, x):
        return float(np.interp(float(tb.wrap_phase(torch.tensor(x))), g, curve, period=2 * math.pi))

    # 2-D: the joint cost over (amplitude, phase), batched over grid points.
    NA, NP = int(cfg.n_amplitude), int(cfg.n_phase_2d)
    amps = torch.linspace(float(cfg.amplitude_range_px[0]), float(cfg.amplitude_range_px[1]), NA, dtype=F64)
    ph2 = torch.linspace(-math.pi, math.pi, NP + 1, dtype=F64)[:-1]
    land = (cost_landscape(images, psf, window, om, amps, ph2, chunk=int(cfg.batch))["l2"].sum(-1) / energy.sum()).numpy()
    mins2d = grid_minima(land)
    a_np, p2 = amps.numpy(), ph2.numpy()

    Pl = plt()
    fig, (ax, axl) = Pl.subplots(1, 2, figsize=(12.5, 4.7), gridspec_kw={"width_ratios": [1.25, 1]})
    deg = np.degrees(g)
    for e in range(E):
        ax.plot(deg, single[e], color=f"C{e}", lw=1.3, label=f"single exposure Te = {fractions[e]:.0%} of the period")
        ax.plot(math.degrees(float(aliases[e])), 0, "v", ms=9, color=f"C{e}", mec="k", mew=0.5)
    ax.plot(deg, joint, "k-", lw=2.2, label="joint (sum of l2 costs, max. likelihood)")
    ax.plot(deg, eq8, "--", color="0.5", lw=1.3, label="joint, paper eq. 8 (norms / ||Y_e||, mean)")
    ax.axvline(math.degrees(phi0), color="r", ls=":", lw=1.2, label=f"true phase {math.degrees(phi0):.0f} deg")
    ax.plot([], [], "v", color="0.6", mec="k", mew=0.5, label="aliases of the single exposures (formula)")
    ax.set_xlim(-180, 180)
    ax.set_xticks(np.arange(-180, 181, 45))
    ax.set_ylim(-0.04 * single.max(), 1.35 * single.max())
    ax.set_xlabel("model phase [deg]")
    ax.set_ylabel(r"relative cost $\|C - Y\|^2 / \|Y\|^2$")
    ax.set_title("(a) cost vs phase (amplitude known): the alias is no longer a minimum of the joint cost", fontsize=10)
    ax.legend(fontsize=7.5, loc="upper right", ncol=2, framealpha=0.9)
    ax.grid(alpha=0.3)
    dp = float(p2[1] - p2[0])
    da = float(a_np[1] - a_np[0])
    deg_c = np.append(np.degrees(p2), math.degrees(p2[0]) + 360.0)  # close the periodic phase axis
    closed = np.concatenate([land, land[:, :1]], 1)
    levels = np.arange(0.0, float(land.max()) + 0.1, 0.1)
    im = axl.contourf(deg_c, a_np, closed, levels=levels, cmap="viridis")
    axl.contour(deg_c, a_np, closed, levels=levels[1:9], colors="w", linewidths=0.4, alpha=0.5)
    axl.set_xlim(-180, 180)
    axl.plot(math.degrees(phi0), M, "*", ms=14, mfc="r", mec="w", label="truth")
    for e in range(E):
        axl.plot(math.degrees(float(aliases[e])), M, "X", ms=10, mfc=f"C{e}", mec="k",
                 label=f"alias of the {fractions[e]:.0%} exposure")
    i, j = mins2d[0]
    axl.plot(math.degrees(p2[j]), a_np[i], "o", ms=16, mfc="none", mec="w", mew=1.2)
    axl.plot([], [], "o", ms=10, mfc="none", mec="k", label="global minimum found")
    axl.set_xticks(np.arange(-180, 181, 60))
    axl.set_xlabel("model phase [deg]")
    axl.set_ylabel("model amplitude M' [px]")
    axl.set_title("(b) joint cost over amplitude and phase", fontsize=10)
    axl.legend(fontsize=7.5, loc="upper right", framealpha=0.85)
    fig.colorbar(im, ax=axl, shrink=0.85, pad=0.02, label="joint relative cost", ticks=np.arange(0.0, levels[-1] + 1e-9, 0.5))
    fig.suptitle(f"Fig. 7: dual exposure ({fractions[0]:.0%} and {fractions[1]:.0%} of the period, shared start "
                 f"w*tcam = {math.degrees(float(cfg.trigger_phase_rad)):.0f} deg), M = {M:g} px, perfect predictor",
                 fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig7_dual_exposure.png")

    jmin = joint_minima[0]
    joint_max = float(joint.max())
    metrics = {
        "true_phase_rad": phi0,
        "alias_separation": separation,
        "single_aliases_formula_rad": [float(a) for a in aliases],
        "single_minima_rad": [[m[0] for m in mins] for mins in single_minima],
        "joint_minima": [{"phase_rad": m[0], "phase_deg": math.degrees(m[0]), "cost_relative": m[1],
                          "cost_over_max": m[1] / joint_max} for m in joint_minima],
        "joint_n_local_minima": len(joint_minima),
        "joint_argmin_rad": jmin[0],
        "joint_argmin_error_rad": wrapped_distance(jmin[0], phi0),
        "joint_cost_at_truth": at(joint, phi0),
        "joint_cost_at_aliases": [at(joint, float(a)) for a in aliases],
        "joint_cost_at_aliases_over_max": [at(joint, float(a)) / joint_max for a in aliases],
        "joint_cost_max": joint_max,
        "eq8_minima": [{"phase_rad": m[0], "phase_deg": math.degrees(m[0]), "cost_over_max": m[1] / float(eq8.max())}
                       for m in eq8_minima],
        "eq8_argmin_rad": eq8_minima[0][0],
        "landscape": {
            "n_local_minima": len(mins2d),
            "minima": [{"amplitude_px": float(a_np[i]), "phase_rad": float(p2[j]), "cost_relative": float(land[i, j])}
                       for i, j in mins2d[:4]],
            "amplitude_step_px": da, "phase_step_rad": dp,
        },
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"fig7: joint minima {[(round(math.degrees(m[0]), 2), round(m[1] / joint_max, 4)) for m in joint_minima]} "
          f"(deg, cost/max); joint cost at the aliases / max {[round(v, 3) for v in metrics['joint_cost_at_aliases_over_max']]}; "
          f"2-D minima {metrics['landscape']['minima']}")


if __name__ == "__main__":
    main()
