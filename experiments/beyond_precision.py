"""Beyond the paper: precision limits of the acquisition design and the cost of a PSF error.

1. Cramer-Rao bound of theta = (M, phi) under Gaussian pixel noise of std s:
   ``F = J^T J / s^2``, ``J = dY/dtheta`` over every pixel (forward-mode AD through
   ``render_blur``: ``torch.func.jvp``), ``CRLB = sqrt(diag F^-1)``. A heatmap over the exposure
   fraction p / 2 pi and the trigger phase ``w tcam`` of one exposure, at one true phase, and
   the dual-exposure alternative (30% / 80%). The image depends on the trigger phase and the
   motion's phase only through their sum, so "the best trigger" means "the best trigger for
   the expected phase"; over an unknown phase the single exposure's bound is infinite where
   the two alias branches cross (and at whole periods), the dual design's stays finite.
   A Monte-Carlo check: the batched fitter's scatter against the bound.
2. Bandwidth versus noise and trigger jitter: the frequency at which the phase std (bound
   plus jitter, ``w * jitter``) reaches 1 degree.
3. The cost of a PSF error: noise-free images fitted with a PSF whose sigma is wrong by x%;
   the bias of M and phi against x (and against the bound).

Light: the laser power is set so that a still spot over the longest exposure of a design
peaks at 1 (as ``torchblur identify`` does); the noise is ``noise_frac`` of that peak.

    python experiments/beyond_precision.py --out runs/beyond [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch.func import jvp

from common import parse, plt, save_figure, write_metrics

import torchblur as tb
from torchblur.fit.sinusoid import fit_sinusoid

F64 = torch.float64


class Setup:
    def __init__(self, cfg):
        self.H, self.W = int(cfg.height), int(cfg.width)
        self.f = float(cfg.freq_hz)
        self.omega = 2 * math.pi * self.f
        self.T = 1 / self.f
        self.M = float(cfg.amplitude_px)
        self.sigma_psf = float(cfg.psf_sigma_px)
        self.rest = torch.tensor([(self.W - 1) / 2, (self.H - 1) / 2], dtype=F64)
        self.noise = float(cfg.noise_frac)

    def psf(self, longest_fraction, sigma_scale=1.0):
        """PSF with the power of a design whose longest exposure is ``longest_fraction`` ``[...]``."""
        amp = 1.0 / (torch.as_tensor(longest_fraction, dtype=F64) * self.T)
        sig = torch.as_tensor(sigma_scale, dtype=F64) * self.sigma_psf
        return tb.GaussianPSF.isotropic(self.rest, sig, amplitude=amp)

    def window(self, fraction, trigger):
        fraction, trigger = torch.broadcast_tensors(torch.as_tensor(fraction, dtype=F64), torch.as_tensor(trigger, dtype=F64))
        return tb.ExposureWindow(torch.remainder(trigger, 2 * math.pi) / self.omega, fraction * self.T)

    def render(self, M, phi, psf, window):
        z = torch.zeros_like(M)
        traj = tb.Sinusoid(torch.stack([M, z], -1), torch.stack([phi, phi], -1), torch.tensor(self.omega, dtype=F64))
        return tb.render_blur(traj, psf, window, height=self.H, width=self.W)


def fisher(setup: Setup, M, phi, fraction, trigger, longest, chunk=256):
    """Fisher information of (M, phi) ``[G, 2, 2]`` for single images: flat ``[G]`` designs."""
    G = fraction.numel()
    out = torch.empty(G, 2, 2, dtype=F64)
    for i in range(0, G, chunk):
        sl = slice(i, i + chunk)
        psf = setup.psf(longest[sl])
        win = setup.window(fraction[sl], trigger[sl])
        m, p = M[sl], phi[sl]

        def f(m_, p_):
            return setup.render(m_, p_, psf, win)

        _, dM = jvp(f, (m, p), (torch.ones_like(m), torch.zeros_like(p)))
        _, dP = jvp(f, (m, p), (torch.zeros_like(m), torch.ones_like(p)))
        J = torch.stack([dM.flatten(-2), dP.flatten(-2)], -1)  # [g, R, 2]
        out[sl] = J.transpose(-1, -2) @ J / setup.noise**2
    return out


def crlb(F):
    """``sqrt(diag(F^-1))`` ``[..., 2]`` (inf where F is singular)."""
    det = F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] ** 2
    scale = (F[..., 0, 0] * F[..., 1, 1]).clamp_min(1e-300)
    sing = det <= 1e-12 * scale
    var = torch.stack([F[..., 1, 1], F[..., 0, 0]], -1) / det[..., None]
    var = torch.where(sing[..., None], torch.full_like(var, float("inf")), var)
    return var.sqrt()


def finite_or_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "beyond_precision.yaml")
    torch.set_num_threads(int(cfg.threads))
    s = Setup(cfg)
    phi0 = float(cfg.true_phase_rad)
    g = cfg.grid
    fr = torch.linspace(float(g.fraction_min), float(g.fraction_max), int(g.n_fraction), dtype=F64)
    tb_grid = torch.arange(int(g.n_trigger), dtype=F64) * (2 * math.pi / int(g.n_trigger))
    FR, TR = torch.meshgrid(fr, tb_grid, indexing="ij")  # [Nf, Nb]
    n = FR.numel()
    Mv = torch.full((n,), s.M, dtype=F64)
    Pv = torch.full((n,), phi0, dtype=F64)

    # 1. Single exposure over (fraction, trigger) at phi0.
    F1 = fisher(s, Mv, Pv, FR.reshape(-1), TR.reshape(-1), FR.reshape(-1)).reshape(FR.shape + (2, 2))
    b1 = crlb(F1)  # [Nf, Nb, 2]
    ph_deg = torch.rad2deg(b1[..., 1])
    M_px = b1[..., 0]
    finite = torch.isfinite(ph_deg)
    best = int(torch.where(finite, ph_deg, torch.full_like(ph_deg, float("inf"))).argmin())
    ib, jb = divmod(best, ph_deg.shape[1])
    # The paper's design (half a period, w tcam = pi/2) at phi0.
    Fp = fisher(s, Mv[:1], Pv[:1], torch.tensor([0.5], dtype=F64), torch.tensor([math.pi / 2], dtype=F64), torch.tensor([0.5], dtype=F64))
    bp = crlb(Fp)[0]
    # Over an unknown phase (only b + phi matters, so the trigger axis scans it): per fraction.
    med_ph = ph_deg.median(1).values
    worst_ph = ph_deg.amax(1)
    ok_frac = torch.isfinite(med_ph)
    best_unknown = int(torch.where(ok_frac, med_ph, torch.full_like(med_ph, float("inf"))).argmin())

    # Dual exposure (shared start), over the trigger (= over an unknown phase).
    dual = [float(v) for v in cfg.dual_exposures]
    Nb = tb_grid.numel()
    Fd = sum(fisher(s, Mv[:Nb], Pv[:Nb], torch.full((Nb,), fe, dtype=F64), tb_grid, torch.full((Nb,), max(dual), dtype=F64))
             for fe in dual)
    bd = crlb(Fd)  # [Nb, 2]
    dual_ph = torch.rad2deg(bd[:, 1])
    # The dual family (f, f + 1/2): window centres a quarter period apart; worst case over the phase.
    fam = fr[fr + 0.5 <= float(g.fraction_max) - 1e-9]
    Ff = len(fam)
    fam_F = torch.zeros(Ff * Nb, 2, 2, dtype=F64)
    FA, TA = torch.meshgrid(fam, tb_grid, indexing="ij")
    for off in (0.0, 0.5):
        fam_F += fisher(s, Mv[:Ff * Nb], Pv[:Ff * Nb], FA.reshape(-1) + off, TA.reshape(-1), FA.reshape(-1) + 0.5)
    fam_ph = torch.rad2deg(crlb(fam_F)[:, 1]).reshape(Ff, Nb)
    fam_worst, fam_med = fam_ph.amax(1), fam_ph.median(1).values
    fam_best = int(fam_worst.argmin())
    # The single exposure at its best unknown-phase fraction with two images (same frame count).
    single2_med = float(med_ph[best_unknown]) / math.sqrt(2)

    # Monte-Carlo: the fitter at the dual design against the bound (w tcam = pi/2).
    gen = torch.Generator().manual_seed(int(cfg.seed))
    nmc = int(cfg.monte_carlo.n)
    win_d = s.window(torch.tensor(dual, dtype=F64), math.pi / 2)  # [E]
    psf_d = s.psf(max(dual))
    clean = s.render(torch.tensor([s.M], dtype=F64), torch.tensor([phi0], dtype=F64),
                     tb.GaussianPSF(psf_d.center, psf_d.cov, psf_d.amplitude), win_d)  # [E, H, W]
    noisy = clean + s.noise * torch.randn((nmc,) + clean.shape, generator=gen, dtype=F64)
    fit = fit_sinusoid(noisy, psf_d, win_d, s.omega, noise_std=s.noise)
    Fmc = sum(fisher(s, Mv[:1], Pv[:1], torch.tensor([fe], dtype=F64), torch.tensor([math.pi / 2], dtype=F64),
                     torch.tensor([max(dual)], dtype=F64)) for fe in dual)
    bmc = crlb(Fmc)[0]
    mc_ph_std = float(tb.wrap_phase(fit.phase - phi0).std())
    mc_M_std = float(fit.amplitude.std())

    # 2. Bandwidth vs noise and jitter (dual design, worst case over the phase).
    bw = cfg.bandwidth
    R, tol = int(bw.images), math.radians(float(bw.tolerance_deg))
    crlb_worst_1 = float(bd[:, 1].max())  # rad, at noise_frac
    noises = np.asarray(list(bw.noise_frac), dtype=float)
    jitters = np.asarray(list(bw.jitter_s), dtype=float)
    band = np.zeros((len(noises), len(jitters)))
    for i, nf in enumerate(noises):
        c2 = (crlb_worst_1 * nf / s.noise) ** 2  # per image pair
        # phase variance per point: (c2 + (w j)^2 / 2) / R  (two frames average the jitter)
        room = 2 * (R * tol**2 - c2)
        band[i] = np.where(room > 0, np.sqrt(np.maximum(room, 0)) / (2 * math.pi * jitters), 0.0)

    # 3. PSF error: noise-free dual-exposure images fitted with a wrong sigma.
    pe = cfg.psf_error
    pct = torch.tensor([float(v) for v in pe.pct], dtype=F64)
    npp = int(pe.n_phase)
    phases = -math.pi + (torch.arange(npp, dtype=F64) + 0.5) * (2 * math.pi / npp)
    ex = [float(v) for v in pe.exposures]
    win_e = s.window(torch.tensor(ex, dtype=F64), math.pi / 2)  # [E]
    psf_t = s.psf(max(ex))
    imgs = s.render(torch.full((npp,), s.M, dtype=F64)[:, None], phases[:, None],
                    tb.GaussianPSF(psf_t.center, psf_t.cov, psf_t.amplitude), win_e)  # [P, E, H, W]
    X = pct.numel()
    data = imgs[None].expand(X, npp, *imgs.shape[1:])
    psf_w = s.psf(torch.tensor(max(ex), dtype=F64), (1 + pct / 100)[:, None].expand(X, npp))
    fpe = fit_sinusoid(data, psf_w, win_e, s.omega, noise_std=s.noise)
    bias_M = fpe.amplitude - s.M  # [X, P]
    bias_ph = tb.wrap_phase(fpe.phase - phases)
    Fpe = sum(fisher(s, torch.full((npp,), s.M, dtype=F64), phases, torch.full((npp,), fe, dtype=F64),
                     torch.full((npp,), math.pi / 2, dtype=F64), torch.full((npp,), max(ex), dtype=F64)) for fe in ex)
    bpe = crlb(Fpe)  # [P, 2]
    maxM = bias_M.abs().amax(1)
    maxP = torch.rad2deg(bias_ph.abs().amax(1))
    neg, pos = pct < 0, pct > 0
    grows = bool((maxM[pos].diff() >= -1e-9).all() and (maxM[neg].flip(0).diff() >= -1e-9).all())

    metrics = {
        "single_exposure": {
            "true_phase_deg": math.degrees(phi0),
            "best_design_at_true_phase": {"exposure_fraction": float(FR[ib, jb]), "trigger_phase_rad": float(TR[ib, jb]),
                                          "crlb_phase_deg": float(ph_deg[ib, jb]), "crlb_M_px": float(M_px[ib, jb])},
            "paper_design_at_true_phase": {"exposure_fraction": 0.5, "trigger_phase_rad": math.pi / 2,
                                           "crlb_phase_deg": finite_or_none(math.degrees(bp[1])), "crlb_M_px": finite_or_none(bp[0])},
            "unknown_phase_best_fraction": float(fr[best_unknown]),
            "unknown_phase_best_median_crlb_phase_deg": float(med_ph[best_unknown]),
            "unknown_phase_worst_crlb_phase_deg_finite": bool(torch.isfinite(worst_ph).any() and float(worst_ph.min()) < 1e3),
            "fraction": fr.tolist(),
            "median_crlb_phase_deg_per_fraction": [finite_or_none(v) for v in med_ph],
            "worst_crlb_phase_deg_per_fraction": [finite_or_none(v) for v in worst_ph],
            "n_singular_designs": int((~finite).sum()),
            "n_near_singular_designs": int((~(ph_deg <= 10 * ph_deg[finite].median())).sum()),
            "two_images_best_fraction_median_crlb_phase_deg": single2_med,
        },
        "dual_exposure": {
            "exposures": dual,
            "crlb_phase_deg_worst": float(dual_ph.max()), "crlb_phase_deg_median": float(dual_ph.median()),
            "crlb_M_px_worst": float(bd[:, 0].max()), "crlb_M_px_median": float(bd[:, 0].median()),
            "finite": bool(torch.isfinite(bd).all()),
            "family_first_fraction": fam.tolist(),
            "family_worst_crlb_phase_deg": fam_worst.tolist(),
            "family_median_crlb_phase_deg": fam_med.tolist(),
            "family_best": [float(fam[fam_best]), float(fam[fam_best]) + 0.5],
            "family_best_worst_crlb_phase_deg": float(fam_worst[fam_best]),
        },
        "monte_carlo_dual": {"n": nmc, "crlb_phase_deg": math.degrees(float(bmc[1])), "fit_phase_std_deg": math.degrees(mc_ph_std),
                             "crlb_M_px": float(bmc[0]), "fit_M_std_px": mc_M_std,
                             "efficiency_phase": float(bmc[1]) ** 2 / mc_ph_std**2, "efficiency_M": float(bmc[0]) ** 2 / mc_M_std**2,
                             "fitter_reported_phase_std_deg": math.degrees(float(fit.phase_std.mean()))},
        "bandwidth": {"images_per_point": R, "tolerance_deg": float(bw.tolerance_deg), "noise_frac": noises.tolist(),
                      "jitter_s": jitters.tolist(), "bandwidth_hz": band.tolist(),
                      "note": "phase std per point = sqrt((CRLB_pair^2 + (w jitter)^2 / 2) / images), worst case over the phase"},
        "psf_error": {"sigma_error_pct": pct.tolist(), "max_abs_bias_M_px": maxM.tolist(),
                      "max_abs_bias_M_pct": (100 * maxM / s.M).tolist(), "max_abs_bias_phase_deg": maxP.tolist(),
                      "bias_M_over_crlb": (maxM / bpe[:, 0].max()).tolist(),
                      "bias_phase_over_crlb": (torch.deg2rad(maxP) / bpe[:, 1].max()).tolist(),
                      "bias_grows_with_error": grows, "converged_frac": float(fpe.converged.double().mean())},
    }
    metrics["summary"] = {
        "single_best_at_true_phase_crlb_phase_deg": metrics["single_exposure"]["best_design_at_true_phase"]["crlb_phase_deg"],
        "single_best_design": [metrics["single_exposure"]["best_design_at_true_phase"]["exposure_fraction"],
                               metrics["single_exposure"]["best_design_at_true_phase"]["trigger_phase_rad"]],
        "paper_design_crlb_phase_deg": metrics["single_exposure"]["paper_design_at_true_phase"]["crlb_phase_deg"],
        "dual_crlb_phase_deg_worst": metrics["dual_exposure"]["crlb_phase_deg_worst"],
        "dual_finite": metrics["dual_exposure"]["finite"],
        "dual_family_best": metrics["dual_exposure"]["family_best"],
        "dual_family_best_worst_crlb_phase_deg": metrics["dual_exposure"]["family_best_worst_crlb_phase_deg"],
        "mc_efficiency_phase": metrics["monte_carlo_dual"]["efficiency_phase"],
        "psf_10pct_bias_M_pct": None, "psf_10pct_bias_phase_deg": None,
    }
    for k, v in enumerate(pct.tolist()):
        if abs(v - 10.0) < 1e-9:
            metrics["summary"]["psf_10pct_bias_M_pct"] = float(100 * maxM[k] / s.M)
            metrics["summary"]["psf_10pct_bias_phase_deg"] = float(maxP[k])
    print(f"single exposure at phi = {math.degrees(phi0):.0f} deg: best (fraction {float(FR[ib, jb]):.2f}, w tcam {float(TR[ib, jb]):.2f}) "
          f"CRLB {float(ph_deg[ib, jb]):.3f} deg; paper design {math.degrees(bp[1]):.3f} deg; unknown phase: best fraction "
          f"{float(fr[best_unknown]):.2f} (median {float(med_ph[best_unknown]):.3f} deg, worst infinite)")
    print(f"dual {dual}: CRLB phase worst {float(dual_ph.max()):.3f} deg, median {float(dual_ph.median()):.3f} deg; "
          f"Monte Carlo phase std {math.degrees(mc_ph_std):.3f} vs bound {math.degrees(float(bmc[1])):.3f} deg; "
          f"best of the (f, f + 0.5) family: f = {float(fam[fam_best]):.2f}, worst {float(fam_worst[fam_best]):.3f} deg")
    print("PSF sigma error -> max |bias M| (%), |bias phi| (deg): " + ", ".join(
        f"{p:+.0f}%: {100 * float(m) / s.M:.2f}/{float(q):.3f}" for p, m, q in zip(pct.tolist(), maxM, maxP)))

    P = plt()
    from matplotlib.colors import LogNorm

    fig, axes = P.subplots(1, 3, figsize=(15.5, 4.4))
    ax = axes[0]
    shown = ph_deg.clamp(max=100.0).numpy()
    lo = max(float(ph_deg[finite].min()), 1e-4)
    im = ax.pcolormesh(TR[0].numpy(), fr.numpy(), shown, norm=LogNorm(vmin=lo, vmax=100 * lo), shading="nearest", cmap="viridis")
    fig.colorbar(im, ax=ax, label="phase CRLB (deg)")
    # where the branches cross: b + pi fraction + phi0 = pi/2 (mod pi)
    ff = np.linspace(float(fr[0]), float(fr[-1]), 200)
    for k in range(-2, 4):
        bc = math.pi / 2 + k * math.pi - phi0 - math.pi * ff
        m = (bc >= 0) & (bc <= 2 * math.pi)
        ax.plot(bc[m], ff[m], "w--", lw=0.8, label="branches cross" if k == 0 else None)
    ax.plot([float(TR[ib, jb])], [float(FR[ib, jb])], "r*", ms=12, label="best")
    ax.plot([math.pi / 2], [0.5], "wo", mfc="none", ms=9, label="paper (0.5, pi/2)")
    ax.set_xlabel("trigger phase w tcam (rad)")
    ax.set_ylabel("exposure (fraction of the period)")
    ax.set_title(f"one exposure, phi = {math.degrees(phi0):.0f} deg, M = {s.M:g} px, noise {100 * s.noise:g}%", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax = axes[1]
    ax.semilogy(fr.numpy(), med_ph.numpy(), "o-", ms=3, label="one exposure: median over the phase")
    ax.axhline(float(dual_ph.median()), color="C1", label=f"dual {dual}: median")
    ax.axhline(float(dual_ph.max()), color="C1", ls="--", label="dual: worst over the phase")
    ax.axhline(single2_med, color="C2", ls=":", label=f"one exposure x2 images at {float(fr[best_unknown]):.2f}: median")
    ax.semilogy(fam.numpy(), fam_worst.numpy(), "s-", ms=3, color="C3", label="dual (f, f + 0.5): worst over the phase")
    ax.set_xlabel("exposure f (fraction of the period)")
    ax.set_ylabel("phase CRLB (deg)")
    ax.set_ylim(top=100.0)
    ax.set_title("unknown phase: one exposure is unbounded at the crossing, dual is not", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[2]
    psi = np.degrees(tb_grid.numpy())
    i05 = int(torch.argmin((fr - 0.5).abs()))
    ax.semilogy(psi, ph_deg[i05].numpy(), label=f"one exposure {float(fr[i05]):.2f} (at phi = {math.degrees(phi0):.0f} deg)")
    ax.semilogy(psi, dual_ph.numpy(), label=f"dual {dual}")
    ax.set_xlabel("trigger phase w tcam (deg)  [only w tcam + phi matters]")
    ax.set_ylabel("phase CRLB (deg)")
    ax.set_ylim(top=max(10.0, 3 * float(dual_ph.max())))
    ax.set_title("the dual design's bound stays finite for every phase", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, "beyond_precision.png")

    fig, axes = P.subplots(1, 2, figsize=(11, 4.0))
    ax = axes[0]
    ax.plot(pct.numpy(), (100 * bias_M / s.M).numpy(), color="0.7", lw=0.8)
    ax.plot(pct.numpy(), (100 * bias_M / s.M).mean(1).numpy(), "o-", color="C0", label="bias of M (%), mean over phases")
    ax.axhspan(-100 * float(bpe[:, 0].max()) / s.M, 100 * float(bpe[:, 0].max()) / s.M, color="C0", alpha=0.15, label="CRLB of M (1 sigma)")
    ax.set_xlabel("PSF sigma error (%)")
    ax.set_ylabel("bias of M (%)")
    ax.legend(fontsize=7)
    ax.set_title(f"dual {ex}, noise-free images, fitted with a wrong PSF", fontsize=9)
    ax = axes[1]
    ax.plot(pct.numpy(), torch.rad2deg(bias_ph).numpy(), color="0.7", lw=0.8)
    ax.plot(pct.numpy(), maxP.numpy(), "o-", color="C3", label="max |bias of phi| over phases (deg)")
    ax.axhline(math.degrees(float(bpe[:, 1].max())), color="C3", ls="--", label="CRLB of phi (worst phase)")
    ax.set_xlabel("PSF sigma error (%)")
    ax.set_ylabel("bias of phi (deg)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, "beyond_psf_error.png")

    fig, ax = P.subplots(figsize=(7.0, 4.4))
    shown = np.where(band > 0, band, np.nan)
    im = ax.imshow(shown, origin="lower", aspect="auto", norm=LogNorm(), cmap="magma")
    fig.colorbar(im, ax=ax, label=f"bandwidth (Hz) for phase std <= {float(bw.tolerance_deg):g} deg")
    mid = np.nanmedian(shown) if np.isfinite(shown).any() else 0.0
    for i in range(len(noises)):
        for j in range(len(jitters)):
            ax.text(j, i, f"{band[i, j] / 1e3:.3g}k" if band[i, j] > 0 else "none",
                    ha="center", va="center", fontsize=7, color="w" if 0 < band[i, j] <= mid else "k")
    ax.set_xticks(range(len(jitters)), [f"{v * 1e6:g}" for v in jitters])
    ax.set_yticks(range(len(noises)), [f"{100 * v:g}" for v in noises])
    ax.set_xlabel("trigger jitter (us, rms)")
    ax.set_ylabel("pixel noise (% of peak)")
    ax.set_title(f"dual exposure, M = {s.M:g} px, {R} images per point (none: noise alone exceeds it)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, out, "beyond_bandwidth.png")
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"wrote {out}/beyond_precision.png, beyond_psf_error.png, beyond_bandwidth.png, metrics.json in {time.time() - started:.1f} s")


if __name__ == "__main__":
    main()
