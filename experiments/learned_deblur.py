"""Learned deblurring: a small CNN maps blurred spot images to the motion (M, phi), trained
self-supervised with ``BlurConsistencyLoss`` only.

No labels: the network predicts (M, cos phi, sin phi); the loss renders the predicted motion
with the very same renderer, PSF and exposure windows that made the data and compares it with
the input images (a chi-square under the known Gaussian noise). Two variants:

- single exposure (30% of the period, 1 channel): both branches of the alias render the same
  image, so the network learns one of them per image, whichever its initialisation favours;
  measured against the nearest branch its error is small, against the truth large;
- dual exposure (30% and 80%, 2 channels): the alias is no longer consistent with the data;
  the network learns the true phase.

The test errors are reported next to the batched fitter's (``fit_sinusoid``, Levenberg-
Marquardt from the closed-form moments) on the same test images.

    python experiments/learned_deblur.py --out runs/learned [--quick] [key=value ...]
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import nn

from common import parse, plt, save_figure, write_metrics

import torchblur as tb
from torchblur.fit.consistency import BlurConsistencyLoss
from torchblur.fit.sinusoid import fit_sinusoid

F32, F64 = torch.float32, torch.float64


class Design:
    """The measurement: frame, PSF, windows ``[E]`` at one frequency, in a given dtype."""

    def __init__(self, cfg, fractions, dtype):
        self.H = self.W = int(cfg.frame_px)
        f = float(cfg.freq_hz)
        self.omega = 2 * math.pi * f
        self.E = len(fractions)
        b = float(cfg.trigger_phase_rad)
        period = 1 / f
        # PSF amplitude: a still spot over the longest exposure peaks at 1.
        amp = 1.0 / (max(fractions) * period)
        rest = torch.tensor([(self.W - 1) / 2, (self.H - 1) / 2], dtype=dtype)
        self.psf = tb.GaussianPSF.isotropic(rest, torch.tensor(float(cfg.psf_sigma_px), dtype=dtype), amplitude=torch.tensor(amp, dtype=dtype))
        self.window = tb.ExposureWindow(torch.full((self.E,), b / self.omega, dtype=dtype),
                                        torch.tensor([float(v) for v in fractions], dtype=dtype) * period)  # [E]
        self.renderer = tb.BlurRenderer(height=self.H, width=self.W)
        self.dtype = dtype

    def params(self, M, phi):
        """Sinusoid parameters of a motion along x: amplitude (M, 0), phase (phi, phi)."""
        return {"amplitude": torch.stack([M, torch.zeros_like(M)], -1), "phase": torch.stack([phi, phi], -1)}

    def render(self, M, phi):
        p = self.params(M.to(self.dtype), phi.to(self.dtype))
        traj = tb.Sinusoid(p["amplitude"][:, None], p["phase"][:, None], torch.tensor(self.omega, dtype=self.dtype))
        return self.renderer(traj, self.psf, self.window)  # [N, E, H, W]

    def alias(self, phi):
        """The single-exposure alias of ``phi`` for the first window."""
        return tb.alias_phase(phi.to(F64), self.omega, self.window.to(F64)[0])


def simulate(design: Design, n: int, m_range, noise_frac, gen, *, sigma=None, chunk=1024):
    """``n`` noisy images ``[n, E, H, W]`` (float64), their noise std ``[E, 1, 1]`` and the truth.
    ``sigma``: the noise std per exposure; default ``noise_frac`` times the median peak."""
    M = m_range[0] + (m_range[1] - m_range[0]) * torch.rand(n, generator=gen, dtype=F64)
    phi = (2 * torch.rand(n, generator=gen, dtype=F64) - 1) * math.pi
    clean = torch.cat([design.render(M[i:i + chunk], phi[i:i + chunk]) for i in range(0, n, chunk)])
    if sigma is None:
        sigma = noise_frac * clean.amax((-1, -2)).median(0).values[:, None, None]  # [E, 1, 1]
    noisy = clean + sigma * torch.randn(clean.shape, generator=gen, dtype=F64)
    return noisy, sigma, M, phi


class SpotNet(nn.Module):
    """A few conv layers (with coordinate channels) and an MLP head.

    ``forward(images [B, E, H, W]) -> (M [B], phi [B])``, M in ``(m_lo, m_hi)`` px, phi in
    (-pi, pi] from a predicted (cos phi, sin phi).
    """

    def __init__(self, channels: int, frame: int, width: int, hidden: int, m_lo: float, m_hi: float, scale: torch.Tensor):
        super().__init__()
        self.register_buffer("scale", scale.reshape(1, channels, 1, 1).to(F32))
        yy, xx = torch.meshgrid(torch.linspace(-1, 1, frame), torch.linspace(-1, 1, frame), indexing="ij")
        self.register_buffer("coords", torch.stack([xx, yy])[None])
        self.m_lo, self.m_hi = m_lo, m_hi
        self.features = nn.Sequential(
            nn.Conv2d(channels + 2, width, 5, stride=2, padding=2), nn.ReLU(),          # H/2
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1), nn.ReLU(),             # H/4
            nn.Conv2d(2 * width, 2 * width, 3, stride=2, padding=1), nn.ReLU(),         # H/8
        )
        n_feat = 2 * width * (frame // 8) ** 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(n_feat, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, images):
        x = images / self.scale
        x = torch.cat([x, self.coords.expand(x.shape[0], -1, -1, -1)], 1)
        o = self.head(self.features(x))
        M = self.m_lo + (self.m_hi - self.m_lo) * torch.sigmoid(o[:, 0])
        phi = torch.atan2(o[:, 2], o[:, 1])
        return M, phi


def train(name, design, cfg, images, sigma, gen, evaluate=None, bar_position=0):
    """Self-supervised training with the consistency loss only. Returns the model, the loss
    history (chi-square per pixel, one value per step) and ``[(step, evaluate(model))]`` every
    ``train.eval_every`` steps (the labels are used only there, for the curve, never to train)."""
    from tqdm.auto import tqdm

    t = cfg.train
    m_lo, m_hi = 0.25, 1.5 * float(cfg.amplitude_px[1])
    peak = sigma.reshape(-1) / float(cfg.noise_frac)
    model = SpotNet(design.E, design.H, int(t.width), int(t.hidden), m_lo, m_hi, peak)
    crit = BlurConsistencyLoss(design.renderer, design.psf, design.window, omega=design.omega,
                               noise_std=sigma.to(F32), reduction="mean")
    n_pix = design.E * design.H * design.W
    opt = torch.optim.Adam(model.parameters(), lr=float(t.lr))
    steps, B = int(t.steps), int(t.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=float(t.lr), total_steps=steps, pct_start=0.1)
    data = images.to(F32)
    history, evals = [], []
    every = int(t.eval_every)
    bar = tqdm(range(steps), desc=f"train {name}", unit="step", position=bar_position, leave=True, mininterval=1.0)
    for step in bar:
        idx = torch.randint(0, data.shape[0], (B,), generator=gen)
        batch = data[idx]
        M, phi = model(batch)
        loss = crit(design.params(M, phi), batch) / n_pix
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        history.append(loss.item())
        if len(history) % 25 == 0:
            bar.set_postfix(chi2_per_px=f"{np.mean(history[-25:]):.3f}")
        if evaluate is not None and ((step + 1) % every == 0 or step + 1 == steps):
            model.eval()
            with torch.no_grad():
                evals.append((step + 1, evaluate(model)))
            model.train()
    bar.close()
    return model, np.asarray(history), evals


def wrapped(x):
    return tb.wrap_phase(torch.as_tensor(x, dtype=F64)).abs()


def rms(x):
    return float(torch.sqrt(torch.mean(torch.as_tensor(x, dtype=F64) ** 2)))


def phase_report(pred_phi, pred_M, phi, M, alias, tol):
    """Errors against the truth and against the nearest branch; fractions near each branch.
    ``alias`` None (dual exposure): the truth only."""
    e_true = wrapped(pred_phi - phi)
    out = {"M_rmse_px": rms(pred_M - M), "phase_rmse_vs_truth_deg": math.degrees(rms(e_true)),
           "phase_median_abs_err_vs_truth_deg": math.degrees(float(e_true.median())),
           "frac_near_truth": float((e_true < tol).double().mean())}
    if alias is not None:
        e_alias = wrapped(pred_phi - alias)
        e_near = torch.minimum(e_true, e_alias)
        apart = wrapped(phi - alias) > 2 * tol  # the two branches are distinguishable here
        out.update({
            "phase_rmse_vs_nearest_branch_deg": math.degrees(rms(e_near)),
            "frac_near_either_branch": float((e_near < tol).double().mean()),
            "frac_near_truth_where_apart": float((e_true[apart] < tol).double().mean()),
            "frac_near_alias_where_apart": float((e_alias[apart] < tol).double().mean()),
            "n_apart": int(apart.sum()),
        })
    return out


def main():
    started = time.time()
    args, cfg, out = parse(__doc__.splitlines()[0], "learned_deblur.yaml")
    torch.set_num_threads(int(cfg.threads))
    torch.set_flush_denormal(True)  # float32 Gaussian tails underflow: denormal arithmetic is slow on CPU
    torch.manual_seed(int(cfg.seed))
    tol = math.radians(float(cfg.branch_tol_deg))
    m_range = (float(cfg.amplitude_px[0]), float(cfg.amplitude_px[1]))
    variants = {"single": list(cfg.single_exposures), "dual": list(cfg.dual_exposures)}
    variants = {k: v for k, v in variants.items() if k in list(cfg.variants)}
    metrics, histories, preds = {"variants": {}}, {}, {}

    for k, (name, fractions) in enumerate(variants.items()):
        gen = torch.Generator().manual_seed(int(cfg.seed) + 1000 * k)
        d64, d32 = Design(cfg, fractions, F64), Design(cfg, fractions, F32)
        train_img, sigma, _, _ = simulate(d64, int(cfg.train.n_train), m_range, float(cfg.noise_frac), gen)  # labels unused
        test_img, _, M, phi = simulate(d64, int(cfg.train.n_test), m_range, float(cfg.noise_frac), gen, sigma=sigma)
        alias = d64.alias(phi) if d64.E == 1 else None
        test32 = test_img.to(F32)

        def evaluate(model):
            pM_, pphi_ = (v.to(F64) for v in model(test32))
            e = wrapped(pphi_ - phi)
            if alias is not None:
                e = torch.minimum(e, wrapped(pphi_ - alias))
            return math.degrees(rms(e)), rms(pM_ - M)

        t0 = time.time()
        model, hist, evals = train(name, d32, cfg, train_img, sigma, gen, evaluate=evaluate, bar_position=0)
        train_s = time.time() - t0
        torch.save(model.state_dict(), out / f"model_{name}.pt")
        model.eval()
        with torch.no_grad():
            pM, pphi = model(test_img.to(F32))
        pM, pphi = pM.to(F64), pphi.to(F64)

        t0 = time.time()
        fit = fit_sinusoid(test_img, d64.psf, d64.window, d64.omega, noise_std=sigma.expand(test_img.shape))
        fit_s = time.time() - t0
        learned = phase_report(pphi, pM, phi, M, alias, tol)
        fitted = phase_report(fit.phase, fit.amplitude, phi, M, alias, tol)
        # The fitter's own precision (Cramer-Rao, at its solutions): the floor for both.
        # (median: at the single exposure's branch crossing the bound is infinite)
        crlb_phase = math.degrees(float(fit.phase_std.median()))
        crlb_M = float(fit.amplitude_std.median())
        with torch.no_grad():
            final_chi2 = float(BlurConsistencyLoss(d64.renderer, d64.psf, d64.window, omega=d64.omega, noise_std=sigma,
                                                   reduction="mean")(d64.params(pM, pphi), test_img)) / (d64.E * d64.H * d64.W)
        m = {"exposures": [float(v) for v in fractions], "train_s": round(train_s, 2), "fit_s": round(fit_s, 3),
             "learned": learned, "fitter": fitted, "fitter_converged_frac": float(fit.converged.double().mean()),
             "crlb_median_phase_deg": crlb_phase, "crlb_median_M_px": crlb_M, "test_chi2_per_px_learned": final_chi2,
             "final_train_chi2_per_px": float(np.mean(hist[-max(1, len(hist) // 20):])),
             "noise_std_per_exposure": [float(v) for v in sigma.reshape(-1)]}
        if alias is None:
            m["phase_rmse_ratio_learned_over_fitter"] = learned["phase_rmse_vs_truth_deg"] / fitted["phase_rmse_vs_truth_deg"]
            m["M_rmse_ratio_learned_over_fitter"] = learned["M_rmse_px"] / fitted["M_rmse_px"]
        else:
            m["phase_rmse_ratio_learned_over_fitter_nearest_branch"] = (
                learned["phase_rmse_vs_nearest_branch_deg"] / fitted["phase_rmse_vs_nearest_branch_deg"])
            m["M_rmse_ratio_learned_over_fitter"] = learned["M_rmse_px"] / fitted["M_rmse_px"]
        metrics["variants"][name] = m
        histories[name] = (hist, evals)
        m["eval_curve"] = {"step": [e[0] for e in evals], "phase_rmse_deg": [e[1][0] for e in evals], "M_rmse_px": [e[1][1] for e in evals]}
        preds[name] = dict(phi=phi, M=M, pphi=pphi, pM=pM, fphi=fit.phase, alias=alias)
        print(f"{name}: learned phase RMSE vs truth {learned['phase_rmse_vs_truth_deg']:.2f} deg, M RMSE {learned['M_rmse_px']:.3f} px; "
              f"fitter {fitted['phase_rmse_vs_truth_deg']:.2f} deg, {fitted['M_rmse_px']:.3f} px"
              + (f"; vs nearest branch: learned {learned['phase_rmse_vs_nearest_branch_deg']:.2f} deg, "
                 f"fitter {fitted['phase_rmse_vs_nearest_branch_deg']:.2f} deg; near truth {learned['frac_near_truth_where_apart']:.2f}, "
                 f"near alias {learned['frac_near_alias_where_apart']:.2f}" if alias is not None else ""))

    if set(variants) != {"single", "dual"}:  # a partial run (tuning): no comparison, no figures
        write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
        return
    s, d = metrics["variants"]["single"], metrics["variants"]["dual"]
    metrics["summary"] = {
        "single_phase_rmse_vs_truth_deg": s["learned"]["phase_rmse_vs_truth_deg"],
        "single_phase_rmse_vs_nearest_branch_deg": s["learned"]["phase_rmse_vs_nearest_branch_deg"],
        "single_frac_near_either_branch": s["learned"]["frac_near_either_branch"],
        "single_frac_near_truth_where_apart": s["learned"]["frac_near_truth_where_apart"],
        "single_frac_near_alias_where_apart": s["learned"]["frac_near_alias_where_apart"],
        "dual_phase_rmse_vs_truth_deg": d["learned"]["phase_rmse_vs_truth_deg"],
        "dual_M_rmse_px": d["learned"]["M_rmse_px"],
        "dual_fitter_phase_rmse_deg": d["fitter"]["phase_rmse_vs_truth_deg"],
        "dual_fitter_M_rmse_px": d["fitter"]["M_rmse_px"],
        "dual_phase_ratio_learned_over_fitter": d["phase_rmse_ratio_learned_over_fitter"],
        "dual_M_ratio_learned_over_fitter": d["M_rmse_ratio_learned_over_fitter"],
    }

    P = plt()
    fig, (ax, ax2) = P.subplots(1, 2, figsize=(12, 3.9))
    for name, (hist, _) in histories.items():
        ax.plot(np.arange(1, len(hist) + 1), hist, lw=0.6, alpha=0.35)
        w = max(1, len(hist) // 50)
        smooth = np.convolve(hist, np.ones(w) / w, mode="valid")
        ax.plot(np.arange(w, len(hist) + 1), smooth, lw=1.6, label=f"{name} exposure ({len(variants[name])} ch)",
                color=ax.lines[-1].get_color())
    ax.axhline(1.0, color="k", ls=":", lw=1, label="noise floor (chi2/px = 1)")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("consistency loss (chi2 per pixel)")
    ax.set_title("Self-supervised training: BlurConsistencyLoss only")
    ax.legend()
    for k, (name, (_, evals)) in enumerate(histories.items()):
        st = [e[0] for e in evals]
        ax2.semilogy(st, [e[1][0] for e in evals], "o-", ms=3, color=f"C{k}",
                     label=f"{name}: phase RMSE (deg)" + (" vs nearest branch" if name == "single" else ""))
        ax2.axhline(metrics["variants"][name]["fitter"]["phase_rmse_vs_nearest_branch_deg" if name == "single" else "phase_rmse_vs_truth_deg"],
                    color=f"C{k}", ls="--", lw=1, label=f"{name}: fitter")
    ax2.set_xlabel("step")
    ax2.set_ylabel("test phase error (deg)")
    ax2.set_title("Test error during training (labels used only here)")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, "loss_curve.png")

    fig, axes = P.subplots(1, 3, figsize=(13.5, 4.3))
    grid = torch.linspace(-math.pi, math.pi, 721, dtype=F64)
    for ax, name in zip(axes[:2], ("single", "dual")):
        p = preds[name]
        deg = np.degrees
        grid_deg = deg(grid.numpy())
        ax.plot(grid_deg, grid_deg, color="C2", lw=0.8, label="truth branch", zorder=4)
        if p["alias"] is not None:
            al = Design(cfg, variants[name], F64).alias(grid)
            al_plot = deg(al.numpy()).copy()
            al_plot[1:][np.abs(np.diff(al_plot)) > 180] = np.nan
            ax.plot(grid_deg, al_plot, color="C3", lw=0.8, label="alias branch", zorder=4)
        ax.scatter(deg(p["phi"].numpy()), deg(p["fphi"].numpy()), s=6, color="0.6", label="fitter", zorder=2)
        ax.scatter(deg(p["phi"].numpy()), deg(p["pphi"].numpy()), s=7, color="C0", label="CNN (self-supervised)", zorder=3)
        r = metrics["variants"][name]["learned"]
        title = f"{name} exposure {variants[name]} of the period"
        if p["alias"] is not None:
            title += f"\nnear truth {r['frac_near_truth_where_apart']:.0%}, near alias {r['frac_near_alias_where_apart']:.0%}"
        else:
            title += f"\nphase RMSE {r['phase_rmse_vs_truth_deg']:.2f} deg (fitter {metrics['variants'][name]['fitter']['phase_rmse_vs_truth_deg']:.2f})"
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("true phase (deg)")
        ax.set_ylabel("predicted phase (deg)")
        ax.set_xlim(-180, 180)
        ax.set_ylim(-180, 180)
        ax.legend(fontsize=7, loc="upper left")
    ax = axes[2]
    for name, c in (("single", "C1"), ("dual", "C0")):
        p = preds[name]
        ax.scatter(p["M"], p["pM"], s=6, color=c, label=f"CNN, {name}")
    lo, hi = m_range
    ax.plot([lo, hi], [lo, hi], "k", lw=1)
    ax.set_xlabel("true M (px)")
    ax.set_ylabel("predicted M (px)")
    ax.set_title(f"amplitude: RMSE single {s['learned']['M_rmse_px']:.3f}, dual {d['learned']['M_rmse_px']:.3f} px\n"
                 f"(fitter dual {d['fitter']['M_rmse_px']:.3f} px)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, "learned_deblur.png")
    write_metrics(out, metrics, started=started, cfg=cfg, quick=args.quick)
    print(f"wrote {out}/learned_deblur.png, loss_curve.png, metrics.json in {time.time() - started:.1f} s")


if __name__ == "__main__":
    main()
