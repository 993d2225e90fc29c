"""Fig. 6 of Tani, Mishra, Wen (CDC 2012): the cost landscape over amplitude and phase.

One exposure (p = half a period, w tcam = pi/2), perfect predictor: the cost
``||C(M' sin(w t + phi')) - Y|| / ||Y||`` over a grid of (M', phi'), rendered in batches of
grid points (one ``BlurRenderer`` call per batch). It has two minima at the same amplitude:
the true phase and its alias (Proposition 3); the amplitude has no alias. Shown for the
2-norm (Frobenius) and for the paper's inf-norm.

Panels: (a), (b) the landscapes with the true point and the alias of the formula marked;
(c) the lowest cost over M' at each phase (two minima); (d) the lowest cost over phi' at
each amplitude (one minimum, at M).

    python experiments/fig6_landscape.py --out runs/fig6 [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common import parse, plt, save_figure, write_metrics, x_sinusoid

import torchblur as tb
from torchblur.fit.landscape import cost_landscape
from torchblur.losses import image_loss

F64 = torch.float64
LABEL = {"l1": "1-norm", "l2": "2-norm (Frobenius)", "linf": "inf-norm"}


def grid_minima(cost: np.ndarray) -> list[tuple[int, int]]:
    """Local minima ``(i, j)`` of ``cost[amplitude i, phase j]``: no lower neighbour among the
    8 (phase periodic, amplitude not), deepest first. Ties are broken towards lower indices."""
    padded = np.pad(cost, ((1, 1), (0, 0)), constant_values=np.inf)
    is_min = np.ones(cost.shape, dtype=bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            nb = np.roll(padded, (-di, -dj), axis=(0, 1))[1:-1]
            earlier = di < 0 or (di == 0 and dj < 0)
            is_min &= (cost < nb) if earlier else (cost <= nb)
    idx = np.argwhere(is_min)
    return sorted(map(tuple, idx), key=lambda ij: cost[ij])


def refine(values: np.ndarray, i: int, step: float, periodic: bool) -> float:
    """Sub-grid offset (in units of ``step``) of a minimum at ``i`` by a parabola through
    its neighbours."""
    n = values.size
    if not periodic and (i == 0 or i == n - 1):
        return 0.0
    cm, c0, cp = values[(i - 1) % n], values[i], values[(i + 1) % n]
    den = cm - 2 * c0 + cp
    return float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5)) * step if den > 0 else 0.0


def profile_minima(values: np.ndarray, periodic: bool) -> list[int]:
    """Indices of local minima of a 1-D profile."""
    if periodic:
        left, right = np.roll(values, 1), np.roll(values, -1)
    else:
        left = np.concatenate([[np.inf], values[:-1]])
        right = np.concatenate([values[1:], [np.inf]])
    return [int(i) for i in np.nonzero((values < left) & (values <= right))[0]]


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "fig6_landscape.yaml")
    f = float(cfg.freq_hz)
    omega = 2 * math.pi * f
    H, W = int(cfg.height), int(cfg.width)
    M, phi0 = float(cfg.amplitude_px), float(cfg.true_phase_rad)
    b, p = float(cfg.trigger_phase_rad), 2 * math.pi * float(cfg.exposure_fraction)
    NA, NP = int(cfg.n_amplitude), int(cfg.n_phase)
    norms = list(cfg.norms)

    rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64)
    psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=F64))
    window = tb.ExposureWindow(torch.tensor(b / omega, dtype=F64), torch.tensor(p / omega, dtype=F64))
    renderer = tb.BlurRenderer(height=H, width=W)
    om = torch.tensor(omega, dtype=F64)


    data = renderer(x_sinusoid(M, phi0, om), psf, window).flatten()  # [H*W]
    amps = torch.linspace(float(cfg.amplitude_range_px[0]), float(cfg.amplitude_range_px[1]), NA, dtype=F64)
    phases = torch.linspace(-math.pi, math.pi, NP + 1, dtype=F64)[:-1]
    land = cost_landscape(data.reshape(1, H, W), psf, window[None], om, amps, phases, losses=norms,
                          chunk=int(cfg.batch))  # {norm: [NA, NP, 1]}
    costs = {nm: (land[nm][..., 0].sqrt() if nm == "l2" else land[nm][..., 0]).reshape(-1) for nm in norms}
    ref = {nm: float(image_loss(torch.zeros_like(data)[None], data[None], loss=nm)[0]) for nm in norms}
    rel = {nm: (costs[nm] / (math.sqrt(ref[nm]) if nm == "l2" else ref[nm])).reshape(NA, NP).numpy() for nm in norms}
    alias = float(tb.alias_phase(torch.tensor(phi0, dtype=F64), om, window))

    a_np, p_np = amps.numpy(), phases.numpy()
    da, dp = float(a_np[1] - a_np[0]), float(p_np[1] - p_np[0])
    results = {}
    for nm in norms:
        c = rel[nm]
        found = []
        for i, j in grid_minima(c)[:2]:
            found.append({
                "amplitude_px": float(a_np[i] + refine(c[:, j], i, da, periodic=False)),
                "phase_rad": float(tb.wrap_phase(torch.tensor(p_np[j] + refine(c[i], j, dp, periodic=True)))),
                "cost_relative": float(c[i, j]),
            })
        for m in found:
            m["phase_deg"] = math.degrees(m["phase_rad"])
            d_true = abs(float(tb.wrap_phase(torch.tensor(m["phase_rad"] - phi0))))
            d_alias = abs(float(tb.wrap_phase(torch.tensor(m["phase_rad"] - alias))))
            m["branch"] = "true" if d_true <= d_alias else "alias"
            m["phase_error_rad"] = min(d_true, d_alias)
            m["amplitude_error_px"] = m["amplitude_px"] - M
        amp_profile = c.min(1)     # [NA]: best phase at each amplitude
        phase_profile = c.min(0)   # [NP]: best amplitude at each phase
        results[nm] = {
            "minima": found,
            "n_local_minima": len(grid_minima(c)),
            "amplitude_profile_minima_px": [float(a_np[i]) for i in profile_minima(amp_profile, periodic=False)],
            "phase_profile_minima_rad": [float(p_np[j]) for j in profile_minima(phase_profile, periodic=True)
                                         if phase_profile[j] < 0.5 * phase_profile.max()],
            "_profiles": (amp_profile, phase_profile),
        }

    Pl = plt()
    fig = Pl.figure(figsize=(13, 4.9))
    gs = fig.add_gridspec(2, 3, width_ratios=[1, 1, 0.85])
    deg = np.degrees(p_np)
    deg_c = np.append(deg, deg[0] + 360.0)  # close the periodic phase axis for the contour plots
    for k, nm in enumerate(norms[:2]):
        ax = fig.add_subplot(gs[:, k])
        levels = np.arange(0.0, float(rel[nm].max()) + 0.1, 0.1)
        closed = np.concatenate([rel[nm], rel[nm][:, :1]], 1)
        im = ax.contourf(deg_c, a_np, closed, levels=levels, cmap="viridis")
        ax.contour(deg_c, a_np, closed, levels=levels[1:9], colors="w", linewidths=0.4, alpha=0.5)
        ax.set_xlim(-180, 180)
        ax.plot(math.degrees(phi0), M, "*", ms=14, mfc="r", mec="w", label=f"truth ({M:g} px, {math.degrees(phi0):.0f} deg)")
        ax.plot(math.degrees(alias), M, "X", ms=11, mfc="orange", mec="k", label=f"alias formula ({math.degrees(alias):.0f} deg)")
        for m in results[nm]["minima"]:
            ax.plot(m["phase_deg"], m["amplitude_px"], "o", ms=16, mfc="none", mec="w", mew=1.2)
        ax.plot([], [], "o", ms=10, mfc="none", mec="k", label="grid minima found")
        ax.set_xlabel("model phase [deg]")
        ax.set_ylabel("model amplitude M' [px]")
        ax.set_xticks(np.arange(-180, 181, 60))
        ax.set_title(f"({'ab'[k]}) {LABEL.get(nm, nm)}: cost / ||Y||", fontsize=10)
        ax.legend(fontsize=7.5, loc="upper right", framealpha=0.85)
        fig.colorbar(im, ax=ax, shrink=0.85, pad=0.02, ticks=np.arange(0.0, levels[-1] + 1e-9, 0.5))
    axc, axd = fig.add_subplot(gs[0, 2]), fig.add_subplot(gs[1, 2])
    for k, nm in enumerate(norms):
        amp_profile, phase_profile = results[nm]["_profiles"]
        axc.plot(deg, phase_profile, color=f"C{k}", label=LABEL.get(nm, nm))
        axd.plot(a_np, amp_profile, color=f"C{k}", label=LABEL.get(nm, nm))
    for x in (math.degrees(phi0), math.degrees(alias)):
        axc.axvline(x, color="0.4", ls=":", lw=1)
    axd.axvline(M, color="0.4", ls=":", lw=1)
    axc.set_xlabel("model phase [deg]")
    axc.set_ylabel("min over M'")
    axc.set_xticks(np.arange(-180, 181, 60))
    axc.set_title("(c) best amplitude at each phase: two minima", fontsize=10)
    axd.set_xlabel("model amplitude M' [px]")
    axd.set_ylabel("min over phase")
    axd.set_title("(d) best phase at each amplitude: one minimum", fontsize=10)
    for a in (axc, axd):
        a.grid(alpha=0.3)
        a.legend(fontsize=7.5)
    fig.suptitle(f"Fig. 6: cost over amplitude and phase, one exposure (p = {math.degrees(p):.0f} deg, "
                 f"w*tcam = {math.degrees(b):.0f} deg): the phase has an alias, the amplitude none", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, "fig6_landscape.png")

    for nm in norms:
        results[nm].pop("_profiles")
    metrics = {
        "true_amplitude_px": M,
        "true_phase_rad": phi0,
        "alias_formula_rad": alias,
        "grid": {"n_amplitude": NA, "n_phase": NP, "amplitude_step_px": da, "phase_step_rad": dp, "points": NA * NP},
        **results,
    }
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    for nm in norms:
        print(f"fig6 {nm}: minima " + ", ".join(f"({m['amplitude_px']:.2f} px, {m['phase_deg']:.1f} deg, {m['branch']})"
                                                for m in results[nm]["minima"])
              + f"; amplitude profile minima {results[nm]['amplitude_profile_minima_px']}")


if __name__ == "__main__":
    main()
