"""Figures (matplotlib): computing and plotting are separate, as in python-control.

Hz, degrees and percentages appear only here; magnitudes stay absolute, in the response's
units (:func:`response_units`).

The backend is never touched: without ``axes=`` each function builds a
``matplotlib.figure.Figure`` that pyplot does not know about (no backend switch, no figure
left open; save it with ``fig.savefig(...)``; in Jupyter, ``display(fig)`` or leave ``fig``
last in a cell). With ``axes=`` it draws into the caller's axes (from ``plt.subplots`` or
``fig.subplots``) and returns their figure.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from torchblur.errors import InputTypeError, ShapeError

__all__ = ["bode_figure", "residual_figure", "response_units"]

_OVERLAY_ABOVE = 4  # more outputs than this (the spots of a wavefront sensor): one overlaid panel per input
_TRUTH_STYLE = dict(color="0.3", ls="--", lw=2.0, alpha=0.9, zorder=2)
_MODEL_STYLE = dict(color="C1", ls="-", lw=1.4, zorder=3)
_MEAS_STYLE = dict(fmt="o", ms=4, color="C0", ecolor="C0", elinewidth=1.2, capsize=2.5, zorder=4)
_BAND_STYLE = dict(color="C0", alpha=0.18, lw=0, step="mid")


def response_units(frf, units: tuple[str, str] | None = None) -> tuple[str, str]:
    """``(output_unit, input_unit)`` of a response: ``units`` if given, else the response's
    ``meta["output_unit"]`` and ``meta["input_unit"]``, else ``("px", "input unit")`` (a
    torchblur response measures image motion in pixels per unit of the command)."""
    if units is not None:
        if len(units) != 2 or not all(isinstance(u, str) for u in units):
            raise InputTypeError(f"units: expected (output_unit, input_unit) strings, got {units!r}")
        return units[0], units[1]
    meta = frf.meta
    return str(meta.get("output_unit", "px")), str(meta.get("input_unit", "input unit"))


def _new_figure(figsize):
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, layout="constrained")


def _axes_grid(axes, rows: int, cols: int, what: str):
    """The caller's axes as an object array [rows, cols] (ShapeError naming ``axes``)."""
    a = np.asarray(axes, dtype=object)
    if a.size != rows * cols:
        raise ShapeError(f"axes: expected {rows} x {cols} Axes ({what}), got {a.size}")
    return a.reshape(rows, cols)


def _stamp(fig, stamp):
    if stamp:
        fig.text(0.995, 0.002, stamp, ha="right", va="bottom", fontsize=6.5, color="0.4")


def _align_phase(curve_deg: np.ndarray, f_curve: np.ndarray, f_meas: np.ndarray, ph_meas_deg: np.ndarray) -> np.ndarray:
    """Shift an unwrapped phase curve by a multiple of 360 deg to meet the measured phase at
    the first valid measured point."""
    ok = np.isfinite(ph_meas_deg)
    if not ok.any():
        return curve_deg
    k = int(np.argmin(np.abs(f_curve - f_meas[ok][0])))
    return curve_deg + 360.0 * np.round((ph_meas_deg[ok][0] - curve_deg[k]) / 360.0)


def _plain_log_ticks(ax) -> None:
    """Label a log magnitude axis 1, 2, 5, 10, 20, ... (not 2x10^1)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _as_oif(h, frf) -> np.ndarray:
    """A response [F] or [O, I, F] as [O, I, F] (one [F] curve serves every channel)."""
    h = np.asarray(h)
    if h.ndim == 1:
        return np.broadcast_to(h, (frf.n_outputs, frf.n_inputs, h.size))
    if h.ndim != 3 or h.shape[:2] != (frf.n_outputs, frf.n_inputs):
        raise ShapeError(f"truth, model: expected a response [F] or [O, I, F] = [{frf.n_outputs}, {frf.n_inputs}, F], got {h.shape}")
    return h


def _curves(frf, model, truth, fine_w):
    """Model and truth on the fine grid and the reference (model, else truth) at the measured
    frequencies, each complex [O, I, *] or None; the truth's own grid and the reference's name."""
    mod = None if model is None else _as_oif(model.frequency_response(fine_w), frf)
    tru, tru_f = None, None
    f = frf.freq_hz
    if truth is not None:
        tru = _as_oif(truth(fine_w) if callable(truth) else truth, frf)
        tru_f = fine_w / (2 * np.pi) if tru.shape[-1] == fine_w.size else f
    ref, ref_name = None, None
    if model is not None:
        ref, ref_name = _as_oif(model.frequency_response(frf.omega), frf), "model"
    elif truth is not None and (callable(truth) or tru.shape[-1] == f.size):
        ref, ref_name = _as_oif(truth(frf.omega) if callable(truth) else truth, frf), "truth"
    return mod, tru, tru_f, ref, ref_name


def _error_panels(a_mag, a_ph, frf, o, i, ref, ref_name):
    """Measured minus reference: magnitude in % of |reference|, phase in deg, each with the
    measurement's 1-sigma band around zero (so 0.2 % bars are readable)."""
    f = frf.freq_hz
    r = ref[o, i]
    with np.errstate(invalid="ignore", divide="ignore"):
        mag_err = 100.0 * (frf.magnitude[o, i] - np.abs(r)) / np.abs(r)
        mag_sig = 100.0 * frf.magnitude_std[o, i] / np.abs(r)
    ph_err = np.degrees(np.angle(frf.response[o, i] / r))
    ph_sig = np.degrees(frf.phase_std[o, i])
    for ax, err, sig, unit in ((a_mag, mag_err, mag_sig, "%"), (a_ph, ph_err, ph_sig, "deg")):
        ax.axhline(0.0, color="0.5", lw=0.8, zorder=1)
        if np.isfinite(sig).any():
            ax.fill_between(f, -sig, sig, label="±1σ of the measurement", **_BAND_STYLE)
        ax.plot(f, err, "o", ms=3.5, color="C0", zorder=4, label=f"measured − {ref_name}")
        ax.set_xscale("log")
        vals = np.abs(np.concatenate([err, sig]))
        vals = vals[np.isfinite(vals)]
        lim = float(vals.max()) if vals.size else 0.0
        ax.set_ylim(-1.15 * (lim or 1.0), 1.15 * (lim or 1.0))
        ax.grid(True, which="both", alpha=0.3)
    a_mag.set_ylabel(f"|H| error\n(% of {ref_name})")
    a_ph.set_ylabel("phase error\n(deg)")


def _bode_channel(axs, frf, o, i, fine_f, curves, mag_label):
    """One output/input channel into ``axs`` = [magnitude, (magnitude error), phase, (phase error)]."""
    mod, tru, tru_f, ref, ref_name = curves
    f = frf.freq_hz
    a_mag, a_ph = (axs[0], axs[2]) if ref is not None else (axs[0], axs[1])
    ph = np.degrees(frf.unwrapped_phase()[o, i])
    if tru is not None:
        a_mag.loglog(tru_f, np.abs(tru[o, i]), label="truth (simulation)", **_TRUTH_STYLE)
        tp = _align_phase(np.degrees(np.unwrap(np.angle(tru[o, i]))), tru_f, f, ph)
        a_ph.semilogx(tru_f, tp, label="truth (simulation)", **_TRUTH_STYLE)
    if mod is not None:
        a_mag.loglog(fine_f, np.abs(mod[o, i]), label="model (fit)", **_MODEL_STYLE)
        mp = _align_phase(np.degrees(np.unwrap(np.angle(mod[o, i]))), fine_f, f, ph)
        a_ph.semilogx(fine_f, mp, label="model (fit)", **_MODEL_STYLE)
    a_mag.errorbar(f, frf.magnitude[o, i], yerr=frf.magnitude_std[o, i], label="measured ±1σ", **_MEAS_STYLE)
    a_ph.errorbar(f, ph, yerr=np.degrees(frf.phase_std[o, i]), label="measured ±1σ", **_MEAS_STYLE)
    a_mag.set_xscale("log")
    a_mag.set_yscale("log")
    _plain_log_ticks(a_mag)
    a_ph.set_xscale("log")
    a_mag.set_ylabel(f"|H| ({mag_label})")
    a_ph.set_ylabel("phase (deg)")
    for ax in (a_mag, a_ph):
        ax.grid(True, which="both", alpha=0.3)
    if ref is not None:
        _error_panels(axs[1], axs[3], frf, o, i, ref, ref_name)
    if frf.n_outputs > 1 or frf.n_inputs > 1:
        a_mag.set_title(f"output {frf.output_labels[o]} from input {frf.input_labels[i]}", fontsize=9)


def bode_figure(
    frf,
    *,
    model=None,
    truth=None,
    title: str | None = None,
    stamp: str | None = None,
    axes=None,
    units: tuple[str, str] | None = None,
):
    """Bode plot of a measured :class:`~torchblur.sysid.frequency_response.FrequencyResponse`.

    Per channel (one column per input, a block of rows per output): the magnitude (log-log,
    in the response's units, :func:`response_units`) and the phase (deg, unwrapped) with
    1-sigma error bars; the fitted model (``model.frequency_response(omega)``, a solid line)
    and the truth when known (a callable ``omega -> complex`` or an array ``[O, I, F]``/``[F]``
    at the measured or at 400 log-spaced frequencies; a dashed grey line). With a model (or
    else a truth) each block adds two error panels under magnitude and phase: measured minus
    model, in % of the model's magnitude and in deg, with the measurement's 1-sigma band
    around zero, where sub-percent error bars are readable.

    More than 4 outputs (the spots of a wavefront sensor) are overlaid, one magnitude and
    one phase panel per input, the truth dashed (``model`` is not drawn there).

    Args:
        frf: the measured response ([O, I, F]).
        model: anything with ``frequency_response(omega) -> complex [F] or [O, I, F]``
            (:class:`~torchblur.sysid.tf_fit.TransferFunctionFit`, a direct fit, a plant).
        truth: the true response, see above.
        title: the figure's title (default: says what is shown).
        stamp: small text at the bottom right (version, seed, ...).
        axes: draw into these Axes instead of a new figure: a grid of ``rows x I`` where
            ``rows = 4 O`` with a reference (model or truth at the measured points), else
            ``2 O``; overlaid (O > 4): ``2 x I``.
        units: ``(output_unit, input_unit)``, overriding :func:`response_units`.

    Returns:
        The ``matplotlib.figure.Figure`` drawn on.
    """
    O, I = frf.n_outputs, frf.n_inputs
    mag_label = "{} per {}".format(*response_units(frf, units))
    if O > _OVERLAY_ABOVE:
        return _bode_overlay(frf, truth=truth, title=title, stamp=stamp, axes=axes, mag_label=mag_label)
    f = frf.freq_hz
    fine_f = np.geomspace(f.min(), f.max(), 400)
    curves = _curves(frf, model, truth, 2 * np.pi * fine_f)
    per = 4 if curves[3] is not None else 2
    if axes is None:
        fig = _new_figure((6.4 * I, (8.6 if per == 4 else 5.6) * O))
        ratios = [3, 1.3, 3, 1.3] * O if per == 4 else [3, 2] * O
        grid = fig.subplots(per * O, I, squeeze=False, sharex=True, gridspec_kw={"height_ratios": ratios})
    else:
        grid = _axes_grid(axes, per * O, I, f"{per} rows per output, one column per input")
        fig = grid[0, 0].figure
    for o in range(O):
        for i in range(I):
            _bode_channel(grid[per * o:per * (o + 1), i], frf, o, i, fine_f, curves, mag_label)
    for i in range(I):
        grid[-1, i].set_xlabel("frequency (Hz)")
    grid[0, 0].legend(fontsize=7.5, loc="best")
    if per == 4:
        grid[1, 0].legend(fontsize=7, loc="best")
    if axes is None or title:
        fig.suptitle(title or "Frequency response identified from camera motion blur")
    _stamp(fig, stamp)
    return fig


def _bode_overlay(frf, *, truth, title, stamp, axes, mag_label):
    """Many outputs: one magnitude and one phase panel per input, every output a line (its
    label in the legend); the truth dashed when known."""
    from matplotlib import colormaps

    O, I = frf.n_outputs, frf.n_inputs
    if axes is None:
        fig = _new_figure((8 * I, 9))
        grid = fig.subplots(2, I, squeeze=False, sharex=True)
    else:
        grid = _axes_grid(axes, 2, I, "magnitude and phase rows, one column per input")
        fig = grid[0, 0].figure
    f = frf.freq_hz
    fine_f = np.geomspace(f.min(), f.max(), 400)
    tru = None if truth is None else _as_oif(truth(2 * np.pi * fine_f) if callable(truth) else truth, frf)
    cmap = colormaps["tab20"]
    uph = np.degrees(frf.unwrapped_phase())
    for i in range(I):
        am, ap = grid[0, i], grid[1, i]
        for o in range(O):
            col = cmap(o % 20)
            am.errorbar(f, frf.magnitude[o, i], yerr=frf.magnitude_std[o, i], fmt="o-", ms=2.5, lw=0.8, color=col,
                        capsize=1.5, label=frf.output_labels[o])
            ap.errorbar(f, uph[o, i], yerr=np.degrees(frf.phase_std[o, i]), fmt="o-", ms=2.5, lw=0.8, color=col, capsize=1.5)
            if tru is not None:
                tf_ = fine_f if tru.shape[-1] == fine_f.size else f
                am.plot(tf_, np.abs(tru[o, i]), "--", color=col, lw=0.8, alpha=0.7)
        am.set_xscale("log")
        am.set_yscale("log")
        ap.set_xscale("log")
        am.set_title(f"every output from input {frf.input_labels[i]}" + (" (dashed: truth)" if tru is not None else ""))
        am.set_ylabel(f"|H| ({mag_label})")
        ap.set_ylabel("phase (deg)")
        ap.set_xlabel("frequency (Hz)")
        am.grid(True, which="both", alpha=0.3)
        ap.grid(True, which="both", alpha=0.3)
        am.legend(fontsize=6, ncol=max(1, O // 9), loc="lower left")
    if axes is None or title:
        fig.suptitle(title or f"Frequency response of {O} outputs identified from camera motion blur")
    _stamp(fig, stamp)
    return fig


def _per_panel(values, K: int, name: str):
    if values is None:
        return [None] * K
    if isinstance(values, str) or len(values) != K:
        raise ShapeError(f"{name}: expected {K} entries (one per panel), got {values!r}")
    return list(values)


def residual_figure(
    images,
    models,
    labels: Sequence[str],
    *,
    stamp: str | None = None,
    axes=None,
    unit: str = "e-",
    exposures: Sequence[str] | None = None,
    reason: str | None = None,
    origins=None,
):
    """Data, fitted model and residual (data - model) of a few fits, one row each.

    Args:
        images, models: ``[K, H, W]``; ``images[k, i, j]`` = the recorded value of pixel
            row i, column j of panel k in ``unit`` (identify's images: electrons, dark
            subtracted).
        labels: K strings naming the point of each panel (e.g. ``"412 Hz, input x"``).
        stamp: small text at the bottom right.
        axes: draw into these Axes (``K x 3``) instead of a new figure.
        unit: the images' unit, e.g. ``"e-"`` or ``"ADU"`` (the colour bars' label).
        exposures: K strings, which exposure each panel shows (e.g. ``"exposure 0 of 8,
            1.25-3.75 ms"``); in the row's title.
        reason: why these fits are shown (e.g. ``"the 3 fits with the largest cost per
            pixel"``); in the figure's title.
        origins: ``[K, 2]`` (x, y) px of each image's pixel (0, 0) in the camera frame (for
            crops); default 0: the axes are the camera's pixel coordinates (pixel centres at
            integers, x = column, y = row, y down).

    Returns:
        The ``matplotlib.figure.Figure`` drawn on.
    """
    images = np.asarray(images, dtype=np.float64)
    models = np.asarray(models, dtype=np.float64)
    if images.ndim != 3 or models.shape != images.shape:
        raise ShapeError(f"images, models: expected two arrays [K, H, W] of one shape, got {images.shape} and {models.shape}")
    K, H, W = images.shape
    labels = _per_panel(labels, K, "labels")
    exposures = _per_panel(exposures, K, "exposures")
    org = np.zeros((K, 2)) if origins is None else np.asarray(origins, dtype=np.float64).reshape(K, 2)
    if axes is None:
        fig = _new_figure((11.5, 3.1 * K + 0.6))
        grid = fig.subplots(K, 3, squeeze=False)
    else:
        grid = _axes_grid(axes, K, 3, "data, model, residual per panel")
        fig = grid[0, 0].figure
    for k in range(K):
        x0, y0 = org[k]
        extent = (x0 - 0.5, x0 + W - 0.5, y0 + H - 0.5, y0 - 0.5)
        vmax = float(np.nanmax([images[k].max(), models[k].max()]))
        res = images[k] - models[k]
        r = float(np.nanmax(np.abs(res))) or 1.0
        rms = float(np.sqrt(np.nanmean(res**2)))
        where = labels[k] + (f"; {exposures[k]}" if exposures[k] else "")
        for ax, im, t, kw in ((grid[k, 0], images[k], f"data: {where}", dict(vmin=min(0.0, images[k].min()), vmax=vmax, cmap="inferno")),
                              (grid[k, 1], models[k], "fitted model", dict(vmin=min(0.0, images[k].min()), vmax=vmax, cmap="inferno")),
                              (grid[k, 2], res, f"residual data − model (rms {rms:.3g} {unit})", dict(vmin=-r, vmax=r, cmap="RdBu_r"))):
            h = ax.imshow(im, extent=extent, origin="upper", interpolation="nearest", **kw)
            ax.set_title(t, fontsize=8)
            ax.set_xlabel("x (px)", fontsize=8)
            ax.set_ylabel("y (px)", fontsize=8)
            ax.tick_params(labelsize=7)
            cb = fig.colorbar(h, ax=ax, fraction=0.046, pad=0.02)
            cb.set_label(unit, fontsize=8)
            cb.ax.tick_params(labelsize=7)
    if axes is None or reason:
        fig.suptitle("Recorded frame, fitted model and residual" + (f": {reason}" if reason else ""), fontsize=10)
    _stamp(fig, stamp)
    return fig
