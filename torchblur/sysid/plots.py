"""Figures (matplotlib): computing and plotting are separate, as in python-control.

Hz, dB-free absolute magnitude and degrees appear only here.
"""
from __future__ import annotations

import numpy as np

__all__ = ["bode_figure", "residual_figure"]


def _plt():
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "ps", "cairo"):
        try:
            matplotlib.use("Agg")
        except Exception:  # pragma: no cover - interactive backends already running
            pass
    import matplotlib.pyplot as plt

    return plt


def bode_figure(frf, *, model=None, truth=None, title: str | None = None, stamp: str | None = None):
    """Bode plot of a measured :class:`~torchblur.sysid.frequency_response.FrequencyResponse`
    with 1-sigma error bars (SISO, or one column per input for MIMO; more than 4 outputs,
    e.g. the spots of a wavefront sensor, are overlaid in one panel per input), the fitted model
    (``model.frequency_response(omega)``) and the truth (callable ``omega -> complex`` or an
    array ``[O, I, F]``/``[F]``) when known. Returns the figure."""
    plt = _plt()
    O, I = frf.n_outputs, frf.n_inputs
    if O > 4:
        return _bode_overlay(frf, truth=truth, title=title, stamp=stamp)
    fig, axes = plt.subplots(2 * O, I, figsize=(7 * I, 3.2 * 2 * O), squeeze=False, sharex=True)
    f = frf.freq_hz
    fine_f = np.geomspace(f.min(), f.max(), 400)
    fine_w = 2 * np.pi * fine_f
    mod = None
    if model is not None:
        mod = np.asarray(model.frequency_response(fine_w))
        if mod.ndim == 1:
            mod = mod[None, None]
    tru = None
    if truth is not None:
        tru = np.asarray(truth(fine_w) if callable(truth) else truth)
        if tru.ndim == 1:
            tru = tru[None, None]
    for o in range(O):
        for i in range(I):
            am, ap = axes[2 * o, i], axes[2 * o + 1, i]
            mag, ph = frf.magnitude[o, i], np.degrees(frf.unwrapped_phase()[o, i])
            ms, ps = frf.magnitude_std[o, i], np.degrees(frf.phase_std[o, i])
            if tru is not None:
                tf_ = fine_f if tru.shape[-1] == fine_f.size else f
                am.loglog(tf_, np.abs(tru[o, i]), color="0.6", lw=3, label="truth")
                tp = np.degrees(np.unwrap(np.angle(tru[o, i])))
                k = np.argmin(np.abs(tf_ - f[np.isfinite(ph)][0])) if np.isfinite(ph).any() else 0
                if np.isfinite(ph).any():
                    tp = tp + 360 * np.round((ph[np.isfinite(ph)][0] - tp[k]) / 360)
                ap.semilogx(tf_, tp, color="0.6", lw=3, label="truth")
            if mod is not None:
                am.loglog(fine_f, np.abs(mod[o, i]), "C1-", lw=1.2, label="model")
                mp = np.degrees(np.unwrap(np.angle(mod[o, i])))
                if np.isfinite(ph).any():
                    k = np.argmin(np.abs(fine_f - f[np.isfinite(ph)][0]))
                    mp = mp + 360 * np.round((ph[np.isfinite(ph)][0] - mp[k]) / 360)
                ap.semilogx(fine_f, mp, "C1-", lw=1.2, label="model")
            am.errorbar(f, mag, yerr=ms, fmt="o", ms=3.5, color="C0", capsize=2, label="measured (1 sigma)")
            ap.errorbar(f, ph, yerr=ps, fmt="o", ms=3.5, color="C0", capsize=2, label="measured (1 sigma)")
            am.set_ylabel("magnitude (out/in)")
            ap.set_ylabel("phase (deg)")
            ap.set_xlabel("frequency (Hz)")
            if O > 1 or I > 1:
                am.set_title(f"{frf.output_labels[o]} from {frf.input_labels[i]}")
            am.grid(True, which="both", alpha=0.3)
            ap.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title or "Frequency response identified from camera motion blur")
    if stamp:
        fig.text(0.99, 0.005, stamp, ha="right", va="bottom", fontsize=7, color="0.4")
    fig.tight_layout()
    return fig


def _bode_overlay(frf, *, truth=None, title=None, stamp=None):
    """Many outputs (the spots of a wavefront sensor): one magnitude and one phase panel per
    input, every output a line (its label in the legend); the truth dashed when known."""
    plt = _plt()
    O, I = frf.n_outputs, frf.n_inputs
    fig, axes = plt.subplots(2, I, figsize=(8 * I, 9), squeeze=False, sharex=True)
    f = frf.freq_hz
    fine_f = np.geomspace(f.min(), f.max(), 400)
    tru = None
    if truth is not None:
        tru = np.asarray(truth(2 * np.pi * fine_f) if callable(truth) else truth)
    cmap = plt.get_cmap("tab20")
    uph = np.degrees(frf.unwrapped_phase())
    for i in range(I):
        am, ap = axes[0, i], axes[1, i]
        for o in range(O):
            col = cmap(o % 20)
            am.errorbar(f, frf.magnitude[o, i], yerr=frf.magnitude_std[o, i], fmt="o-", ms=2.5, lw=0.8, color=col, capsize=1.5,
                        label=frf.output_labels[o])
            ap.errorbar(f, uph[o, i], yerr=np.degrees(frf.phase_std[o, i]), fmt="o-", ms=2.5, lw=0.8, color=col, capsize=1.5)
            if tru is not None:
                tf_ = fine_f if tru.shape[-1] == fine_f.size else f
                am.loglog(tf_, np.abs(tru[o, i]), "--", color=col, lw=0.8, alpha=0.7)
        am.set_xscale("log")
        am.set_yscale("log")
        ap.set_xscale("log")
        am.set_title(f"every output from input {frf.input_labels[i]}" + (" (dashed: truth)" if tru is not None else ""))
        am.set_ylabel("magnitude (out/in)")
        ap.set_ylabel("phase (deg)")
        ap.set_xlabel("frequency (Hz)")
        am.grid(True, which="both", alpha=0.3)
        ap.grid(True, which="both", alpha=0.3)
        am.legend(fontsize=6, ncol=max(1, O // 9), loc="lower left")
    fig.suptitle(title or f"Frequency response of {O} outputs identified from camera motion blur")
    if stamp:
        fig.text(0.99, 0.005, stamp, ha="right", va="bottom", fontsize=7, color="0.4")
    fig.tight_layout()
    return fig


def residual_figure(images, models, labels, *, stamp: str | None = None):
    """Data, model and residual of a few fits: ``images``, ``models`` ``[K, H, W]``."""
    plt = _plt()
    images = np.asarray(images)
    models = np.asarray(models)
    K = images.shape[0]
    fig, axes = plt.subplots(K, 3, figsize=(9, 2.8 * K), squeeze=False)
    for k in range(K):
        vmax = float(max(images[k].max(), models[k].max()))
        res = images[k] - models[k]
        r = float(np.abs(res).max()) or 1.0
        for a, im, t, kw in ((axes[k, 0], images[k], "data", dict(vmin=0, vmax=vmax, cmap="inferno")),
                             (axes[k, 1], models[k], "model", dict(vmin=0, vmax=vmax, cmap="inferno")),
                             (axes[k, 2], res, "residual", dict(vmin=-r, vmax=r, cmap="RdBu_r"))):
            h = a.imshow(im, **kw)
            a.set_title(f"{t}: {labels[k]}" if t == "data" else t, fontsize=8)
            a.set_axis_off()
            fig.colorbar(h, ax=a, fraction=0.046)
    if stamp:
        fig.text(0.99, 0.005, stamp, ha="right", va="bottom", fontsize=7, color="0.4")
    fig.tight_layout()
    return fig
