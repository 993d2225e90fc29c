"""Figures (matplotlib): computing and plotting are separate, as in python-control.

Hz, degrees and percentages appear only here; magnitudes stay absolute, in the response's
units (:func:`response_units`). The backend is never touched: without ``axes=`` each function
builds a ``matplotlib.figure.Figure`` that pyplot does not know about (save it with
``fig.savefig(...)``); with ``axes=`` it draws into the caller's axes and returns their figure.
What the figures show (the measured phase on the model's branch, flagged points ringed and
never setting the limits, the camera's frame rate, residuals in units of the noise model's
sigma): README.md, "Reading the figures", and docs/reliability.md.
"""
from __future__ import annotations

import textwrap
from typing import Sequence

import numpy as np

from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.sysid.flags import POINT_FLAGS
from torchblur.sysid.frequency_response import unwrap_along_frequency

__all__ = ["bode_figure", "residual_figure", "response_units", "flag_style", "FLAG_STYLES"]

_OVERLAY_ABOVE = 4  # more outputs than this (the spots of a wavefront sensor): one overlaid panel per input
_TRUTH_STYLE = dict(color="0.3", ls="--", lw=2.0, alpha=0.9, zorder=2)
_MODEL_STYLE = dict(color="C1", ls="-", lw=1.4, zorder=3)
_MEAS_STYLE = dict(fmt="o", ms=4, color="C0", ecolor="C0", elinewidth=1.2, capsize=2.5, zorder=4)
_FLAGGED_BAR_STYLE = dict(fmt="none", ecolor="C0", elinewidth=1.0, capsize=2.0, alpha=0.35, zorder=4)
_BAND_STYLE = dict(color="C0", alpha=0.18, lw=0, step="mid")
_CAMERA_STYLE = {"frame rate": dict(color="0.15", ls="-.", lw=1.0, zorder=1), "Nyquist": dict(color="0.15", ls=":", lw=1.2, zorder=1)}
_EDGE = 0.03  # axes fraction where an off-scale (or valueless) flagged point is drawn

#: How each per-point flag (:data:`torchblur.sysid.flags.POINT_FLAGS`) is drawn over its point:
#: a hollow marker of its own shape and colour (a point with several flags gets one ring each,
#: larger ones outside) and the legend's words. A flag not listed gets a style of its own from
#: :func:`flag_style` (a spare marker, its name as the words).
FLAG_STYLES = {
    "poor_fit": dict(marker="s", color="C3", text="poor_fit: the model does not explain the images"),
    "timing": dict(marker="D", color="C4", text="timing: jitter/latency beyond the tolerance"),
    "limited": dict(marker="v", color="C2", text="limited: the drive limit cut the motion"),
    "no_motion": dict(marker="o", color="0.45", text="no_motion: not a measurement"),
    "failed": dict(marker="X", color="k", text="failed: no value (drawn at the bottom)"),
    "alias": dict(marker="P", color="C6", text="alias: one exposure, phase branch undecided"),
}
_SPARE_MARKERS = ("P", "*", "h", "p", "<", ">", "d", "H", "8")  # not ^ or v: the off-scale arrows
_SPARE_COLORS = ("C8", "C6", "C9", "C5", "C7")


def flag_style(name: str) -> dict:
    """``{"marker", "color", "text"}`` of the flag ``name``: :data:`FLAG_STYLES`, else a
    default that no listed flag uses (picked from the flag's bit, so it is stable)."""
    if name in FLAG_STYLES:
        return dict(FLAG_STYLES[name])
    bits = {v: k for k, v in POINT_FLAGS.items()}
    k = bits[name].bit_length() if name in bits else (int(name[3:]) + 1 if name[3:].isdigit() else len(name))
    return dict(marker=_SPARE_MARKERS[k % len(_SPARE_MARKERS)], color=_SPARE_COLORS[k % len(_SPARE_COLORS)], text=name)


def _flag_names_of(mask: int) -> list[str]:
    """Names of the bits set in ``mask`` (unknown bits as ``bit<N>``), lowest bit first."""
    return [POINT_FLAGS.get(1 << b, f"bit{b}") for b in range(63) if (int(mask) >> b) & 1]


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


def _wrap(stamp, width_in: float, size: float = 6.5) -> str:
    """``stamp`` wrapped to lines that fit ``width_in`` inches at ``size`` pt."""
    chars = max(20, int(width_in * 72 / (0.6 * size)))
    return "\n".join(textwrap.wrap(str(stamp), chars, break_long_words=True, break_on_hyphens=False))


def _stamp(fig, stamp):
    """``stamp`` at the bottom right, wrapped to the figure's width, in a strip the constrained
    layout leaves free (so it never overlaps an axis label)."""
    if not stamp:
        return
    from matplotlib.layout_engine import ConstrainedLayoutEngine

    size = 6.5
    text = _wrap(stamp, fig.get_figwidth(), size)
    engine = fig.get_layout_engine()
    if isinstance(engine, ConstrainedLayoutEngine):
        strip = (text.count("\n") + 1) * 1.3 * size / 72 / fig.get_figheight()
        engine.set(rect=(0.0, strip, 1.0, 1.0 - strip))
    fig.text(0.995, 0.002, text, ha="right", va="bottom", fontsize=size, color="0.4")


def _log_ticks(ax, lo: float, hi: float) -> None:
    """Label a log magnitude axis 1, 2, 5, 10, ... (not 2x10^1), as few as fit its height
    without overlapping: 1-2-5 over a few decades, then every decade, then every n-th."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fits = max(3, int(ax.get_position().height * ax.figure.get_figheight() * 72 / 16))  # a label per ~16 pt
    decades = max(np.log10(hi / lo), 1e-9)
    subs = (1.0, 2.0, 5.0) if 3 * decades <= fits else (1.0,)
    ax.yaxis.set_major_locator(LogLocator(subs=subs, numticks=fits + 1))
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


def _unwrap_deg(h: np.ndarray) -> np.ndarray:
    """Unwrapped phase in deg along the last axis, NaN points bridged."""
    return np.degrees(unwrap_along_frequency(np.angle(np.where(np.isfinite(h), h, np.nan))))


def _curves(frf, model, truth):
    """The model and the truth as drawn, and the reference the data are measured against.

    The fine grid is 400 log-spaced frequencies over the measured range joined with the
    measured ones, so the reference's unwrapped phase at a measured point is the drawn
    curve's own branch. Returns a dict: ``grid_f`` [G] Hz; ``model``, ``model_ph`` (complex
    and deg [O, I, G] or None); ``truth``, ``truth_ph``, ``truth_f`` (on the grid, or at the
    measured points when an array is given there; the truth's phase on the model's branch);
    ``ref`` [O, I, F] complex and ``ref_ph`` [O, I, F] deg (model, else truth, else None) and
    ``ref_name``."""
    f = frf.freq_hz
    fine = np.geomspace(f.min(), f.max(), 400)
    grid = np.union1d(fine, f)
    at = np.searchsorted(grid, f)
    c = dict(grid_f=grid, model=None, model_ph=None, truth=None, truth_ph=None, truth_f=None, ref=None, ref_ph=None, ref_name=None)
    if model is not None:
        c["model"] = _as_oif(model.frequency_response(2 * np.pi * grid), frf)
        c["model_ph"] = _unwrap_deg(c["model"])
        c["ref"], c["ref_ph"], c["ref_name"] = c["model"][..., at], c["model_ph"][..., at], "model"
    if truth is not None:
        if callable(truth):
            tru, tf_, k = _as_oif(truth(2 * np.pi * grid), frf), grid, at
        else:
            tru = _as_oif(truth, frf)
            if tru.shape[-1] not in (fine.size, f.size):
                raise ShapeError(f"truth: expected the response at the {f.size} measured or at 400 log-spaced frequencies, got "
                                 f"{tru.shape[-1]}")
            tf_, k = (fine, None) if tru.shape[-1] == fine.size else (f, np.arange(f.size))
        c["truth"], c["truth_f"], c["truth_ph"] = tru, tf_, _unwrap_deg(tru)
        if c["ref"] is None and k is not None:
            c["ref"], c["ref_ph"], c["ref_name"] = tru[..., k], c["truth_ph"][..., k], "truth"
        elif c["model_ph"] is not None:  # the truth on the model's branch at the first measured point
            k0 = int(np.argmin(np.abs(tf_ - f[0])))
            shift = 360.0 * np.round((c["model_ph"][..., at[0]] - c["truth_ph"][..., k0]) / 360.0)
            c["truth_ph"] = c["truth_ph"] + np.nan_to_num(shift)[..., None]
    return c


def _data_phase_deg(frf, o: int, i: int, c) -> np.ndarray:
    """The measured phase in deg on the reference's branch: the reference's unwrapped phase
    plus the wrapped difference (so data minus curve is the error panel's value), else the
    response's own unwrapping."""
    if c["ref"] is None:
        return np.degrees(frf.unwrapped_phase()[o, i])
    with np.errstate(invalid="ignore", divide="ignore"):
        return c["ref_ph"][o, i] + np.degrees(np.angle(frf.response[o, i] / c["ref"][o, i]))


def _limits(values, log: bool, pad: float = 0.06):
    """``(lo, hi)`` spanning the finite ``values`` (positive ones on a log axis) with a margin,
    or None when there are none."""
    v = np.concatenate([np.ravel(np.asarray(x, dtype=float)) for x in values if x is not None] or [np.zeros(0)])
    v = v[np.isfinite(v) & ((v > 0) if log else True)]
    if not v.size:
        return None
    lo, hi = float(v.min()), float(v.max())
    if log:
        r = max((hi / lo) ** pad, 1.25)
        return lo / r, hi * r
    d = max((hi - lo) * pad, 1e-9 * max(abs(hi), abs(lo)), 1e-12)
    return lo - d, hi + d


def _draw_points(ax, x, y, yerr, flags, label: str):
    """The measured points: the unflagged ones with error bars (``label``), the flagged ones'
    bars faint (their marks come from :func:`_flag_marks`). Returns the unflagged mask."""
    good = np.isfinite(y) & (flags == 0)
    bad = np.isfinite(y) & (flags != 0)
    yerr = np.asarray(yerr, dtype=float)
    yerr = np.where(np.isfinite(yerr), yerr, 0.0)
    pick = (lambda m: yerr[..., m]) if yerr.ndim else (lambda m: yerr)
    ax.errorbar(x[good], y[good], yerr=pick(good), label=label, **_MEAS_STYLE)
    if bad.any():
        ax.errorbar(x[bad], y[bad], yerr=pick(bad), **_FLAGGED_BAR_STYLE)
    return good


def _axes_fraction(ax, y, log: bool) -> np.ndarray:
    lo, hi = ax.get_ylim()
    with np.errstate(invalid="ignore", divide="ignore"):
        if log:
            return (np.log10(y) - np.log10(lo)) / (np.log10(hi) - np.log10(lo))
        return (y - lo) / (hi - lo)


def _flag_marks(ax, x, y, flags, log: bool, rings_in_legend: bool = True) -> None:
    """Every flagged point's rings, one per flag (:func:`flag_style`), after the limits are
    set: a point off the axes (or without a value) is drawn at its edge, with an arrow when
    it is off scale. Nothing here moves the limits (axes-fraction coordinates)."""
    idx = np.nonzero(flags != 0)[0]
    if not idx.size:
        return
    from matplotlib.transforms import blended_transform_factory

    tr = blended_transform_factory(ax.transData, ax.transAxes)
    frac = _axes_fraction(ax, np.asarray(y, dtype=float), log)
    yf = np.where(np.isfinite(frac), np.clip(frac, _EDGE, 1 - _EDGE), _EDGE)
    rings: dict[str, list] = {}
    for k in idx:
        for r, name in enumerate(_flag_names_of(flags[k])):
            rings.setdefault(name, []).append((k, r))
    for name, items in rings.items():
        st = flag_style(name)
        ks, rs = np.array([k for k, _ in items]), np.array([r for _, r in items])
        ax.scatter(x[ks], yf[ks], s=(6.5 + 4.0 * rs) ** 2, marker=st["marker"], facecolors="none", edgecolors=st["color"],
                   linewidths=1.4, transform=tr, clip_on=False, zorder=6, label=st["text"] if rings_in_legend else "_nolegend_")
    for side, sel, mk in ((1 - _EDGE, frac > 1, "^"), (_EDGE, frac < 0, "v")):
        sel = sel & np.isfinite(frac) & (flags != 0)
        if sel.any():
            ax.scatter(x[sel], np.full(int(sel.sum()), side), s=30, marker=mk, color="0.2", transform=tr, clip_on=False, zorder=7,
                       label="off scale: drawn at the edge (value in frf.csv)")


def _camera_marks(axs, frame_rate_hz, xscale: float, xlim) -> str:
    """The camera's frame rate and its Nyquist frequency as vertical lines on ``axs`` (labels
    on the first); returns a note for the x label when they lie outside ``xlim``."""
    if not frame_rate_hz:
        return ""
    out = []
    for name, fr in (("frame rate", float(frame_rate_hz)), ("Nyquist", 0.5 * float(frame_rate_hz))):
        xv = fr * xscale
        if xlim[0] <= xv <= xlim[1]:
            for n, ax in enumerate(axs):
                ax.axvline(xv, label=f"camera {name} {fr:.4g} Hz" if n == 0 else "_nolegend_", **_CAMERA_STYLE[name])
        else:
            out.append(f"{name} {fr:.4g} Hz")
    if not out:
        return ""
    side = "below" if float(frame_rate_hz) * xscale < xlim[0] else "above"
    return f"; camera {', '.join(out)}: {side} this range"


def _mag_values(frf, o, i, dB: bool):
    """Magnitude and its error bar as drawn: absolute, or dB (asymmetric bars ``[2, F]``)."""
    m, s = frf.magnitude[o, i], frf.magnitude_std[o, i]
    if not dB:
        return m, s
    with np.errstate(divide="ignore", invalid="ignore"):
        y = 20 * np.log10(m)
        lo = y - 20 * np.log10(np.maximum(m - s, m * 1e-3))
        hi = 20 * np.log10(m + s) - y
    return y, np.stack([lo, hi])


def _curve_mag(h, dB: bool):
    a = np.abs(h)
    if not dB:
        return a
    with np.errstate(divide="ignore"):
        return 20 * np.log10(a)


def _error_panels(a_mag, a_ph, frf, o, i, c, x):
    """Measured minus reference: magnitude in % of |reference|, phase in deg, each with the
    measurement's 1-sigma band around zero (so 0.2 % bars are readable); the limits from the
    unflagged points only, the flagged ones marked."""
    r, flags = c["ref"][o, i], frf.flags[o, i]
    with np.errstate(invalid="ignore", divide="ignore"):
        mag_err = 100.0 * (frf.magnitude[o, i] - np.abs(r)) / np.abs(r)
        mag_sig = 100.0 * frf.magnitude_std[o, i] / np.abs(r)
        ph_err = np.degrees(np.angle(frf.response[o, i] / r))
    ph_sig = np.degrees(frf.phase_std[o, i])
    name = c["ref_name"]
    for ax, err, sig in ((a_mag, mag_err, mag_sig), (a_ph, ph_err, ph_sig)):
        ax.axhline(0.0, color="0.5", lw=0.8, zorder=1)
        if np.isfinite(sig).any():
            ax.fill_between(x, -sig, sig, label="±1σ of the measurement", **_BAND_STYLE)
        good = np.isfinite(err) & (flags == 0)
        ax.plot(x[good], err[good], "o", ms=3.5, color="C0", zorder=4, label=f"measured − {name}")
        if (flags != 0).any():
            ax.plot(x[flags != 0], err[flags != 0], "o", ms=3.0, color="C0", alpha=0.35, zorder=4)
        pick = good if good.any() else np.isfinite(err)
        vals = np.abs(np.concatenate([err[pick], sig[pick]]))
        vals = vals[np.isfinite(vals)]
        lim = float(vals.max()) if vals.size else 0.0
        ax.set_ylim(-1.15 * (lim or 1.0), 1.15 * (lim or 1.0))
        _flag_marks(ax, x, err, flags, log=False, rings_in_legend=False)
        ax.grid(True, which="both", alpha=0.3)
    a_mag.set_ylabel(f"|H| error\n(% of {name})")
    a_ph.set_ylabel("phase error\n(deg)")


def _bode_channel(axs, frf, o, i, c, opt):
    """One output/input channel into ``axs`` = [magnitude, (magnitude error), phase, (phase error)]."""
    xs = opt["xs"]
    x, flags = frf.freq_hz * xs, frf.flags[o, i]
    a_mag, a_ph = (axs[0], axs[2]) if c["ref"] is not None else (axs[0], axs[1])
    mag_c, ph_c = [], []
    for key, f_key, label, style in (("truth", "truth_f", "truth (simulation)", _TRUTH_STYLE),
                                     ("model", "grid_f", "model (fit)", _MODEL_STYLE)):
        if c[key] is not None:
            cx = c[f_key] * xs
            mag_c.append(_curve_mag(c[key][o, i], opt["dB"]))
            ph_c.append(c[key + "_ph"][o, i])
            a_mag.plot(cx, mag_c[-1], label=label, **style)
            a_ph.plot(cx, ph_c[-1], label=label, **style)
    my, merr = _mag_values(frf, o, i, opt["dB"])
    ph, ph_s = _data_phase_deg(frf, o, i, c), np.degrees(frf.phase_std[o, i])
    good = _draw_points(a_mag, x, my, merr, flags, "measured ±1σ")
    _draw_points(a_ph, x, ph, ph_s, flags, "measured ±1σ")
    pick = good if good.any() else np.isfinite(my)
    _bode_axes(a_mag, a_ph, [my[pick], *mag_c], [ph[pick] - ph_s[pick], ph[pick] + ph_s[pick], *ph_c], opt)
    _flag_marks(a_mag, x, my, flags, log=not opt["dB"])
    _flag_marks(a_ph, x, ph, flags, log=False)
    if c["ref"] is not None:
        _error_panels(axs[1], axs[3], frf, o, i, c, x)
    if frf.n_outputs > 1 or frf.n_inputs > 1:
        a_mag.set_title(f"output {frf.output_labels[o]} from input {frf.input_labels[i]}", fontsize=9)


def _bode_axes(a_mag, a_ph, mag_vals, ph_vals, opt) -> None:
    """Log frequency axes; y limits spanning ``mag_vals`` and ``ph_vals`` (lists of arrays: the
    unflagged points and the curves), grids, the magnitude's ticks and both y labels."""
    for ax, vals, log in ((a_mag, mag_vals, not opt["dB"]), (a_ph, ph_vals, False)):
        ax.set_xscale("log")
        if log:
            ax.set_yscale("log")
        lim = _limits(vals, log)
        if lim is not None:
            ax.set_ylim(*lim)
        ax.grid(True, which="both", alpha=0.3)
    if not opt["dB"] and a_mag.get_ylim()[0] > 0:
        _log_ticks(a_mag, *a_mag.get_ylim())
    a_mag.set_ylabel(f"|H| ({'dB re 1 ' if opt['dB'] else ''}{opt['mag_label']})")
    a_ph.set_ylabel("phase (deg)")


def _legend(ax, axes, **kw) -> None:
    """One legend on ``ax`` with every label drawn on ``axes`` (each once, first seen first)."""
    seen = {}
    for a in axes:
        for h, lab in zip(*a.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    if seen:
        ax.legend(list(seen.values()), list(seen.keys()), **kw)


def bode_figure(
    frf,
    *,
    model=None,
    truth=None,
    title: str | None = None,
    stamp: str | None = None,
    axes=None,
    units: tuple[str, str] | None = None,
    frame_rate_hz: float | None = None,
    Hz: bool = True,
    dB: bool = False,
):
    """Bode plot of a measured :class:`~torchblur.sysid.frequency_response.FrequencyResponse`.

    Per channel (one column per input, a block of rows per output): the magnitude (log-log,
    in the response's units, :func:`response_units`) and the phase (deg, unwrapped) with
    1-sigma error bars; the fitted model (``model.frequency_response(omega)``, a solid line)
    and the truth when known (a callable ``omega -> complex`` or an array ``[O, I, F]``/``[F]``
    at the measured or at 400 log-spaced frequencies; a dashed grey line). With a model (or
    else a truth) each block adds two error panels under magnitude and phase: measured minus
    model, in % of the model's magnitude and in deg, with the measurement's 1-sigma band
    around zero, where sub-percent error bars are readable. Phase branch, flags, limits and
    the camera's frame rate: README.md, "Reading the figures". More than 4 outputs (the spots of a
    wavefront sensor) are overlaid, one magnitude and one phase panel per input, the truth
    dashed (``model`` is not drawn there).

    Args:
        frf: the measured response ([O, I, F]).
        model: anything with ``frequency_response(omega) -> complex [F] or [O, I, F]``
            (:class:`~torchblur.sysid.tf_fit.TransferFunctionFit`, a direct fit, a plant).
        truth: the true response, see above.
        title: the figure's title (default: says what is shown).
        stamp: small text at the bottom right (version, seed, ...), wrapped, in its own strip.
        axes: draw into these Axes instead of a new figure: a grid of ``rows x I`` where
            ``rows = 4 O`` with a reference (model or truth at the measured points), else
            ``2 O``; overlaid (O > 4): ``2 x I``.
        units: ``(output_unit, input_unit)``, overriding :func:`response_units`.
        frame_rate_hz: the camera's frame rate (Hz); None: ``frf.meta["frame_rate_hz"]``
            if present, else nothing is marked.
        Hz: frequency axis in Hz (default), else rad/s (python-control's ``Hz`` option).
        dB: magnitude in dB (``20 log10 |H|``) on a linear axis (python-control's ``dB``).

    Returns:
        The ``matplotlib.figure.Figure`` drawn on.
    """
    O, I = frf.n_outputs, frf.n_inputs
    xs = 1.0 if Hz else 2 * np.pi
    opt = dict(mag_label="{} per {}".format(*response_units(frf, units)), Hz=bool(Hz), dB=bool(dB), xs=xs,
               xlim=(frf.freq_hz.min() * xs / 1.15, frf.freq_hz.max() * xs * 1.15),
               frame_rate_hz=frame_rate_hz if frame_rate_hz is not None else frf.meta.get("frame_rate_hz"))
    if O > _OVERLAY_ABOVE:
        return _bode_overlay(frf, truth=truth, title=title, stamp=stamp, axes=axes, opt=opt)
    c = _curves(frf, model, truth)
    per = 4 if c["ref"] is not None else 2
    if axes is None:
        fig = _new_figure((6.4 * I, (8.6 if per == 4 else 5.6) * O))
        ratios = [3, 1.3, 3, 1.3] * O if per == 4 else [3, 2] * O
        grid = fig.subplots(per * O, I, squeeze=False, sharex=True, gridspec_kw={"height_ratios": ratios})
    else:
        grid = _axes_grid(axes, per * O, I, f"{per} rows per output, one column per input")
        fig = grid[0, 0].figure
    for o in range(O):
        for i in range(I):
            grid[per * o, i].set_xlim(*opt["xlim"])
            _bode_channel(grid[per * o:per * (o + 1), i], frf, o, i, c, opt)
    for i in range(I):
        note = _camera_marks(list(grid[:, i]), opt["frame_rate_hz"], xs, opt["xlim"])
        grid[-1, i].set_xlabel(f"frequency ({'Hz' if opt['Hz'] else 'rad/s'}){note}")
    if axes is None:  # the upper panels' x tick labels are hidden (shared axis): the layout need not measure them
        for ax in grid[:-1].ravel():
            ax.xaxis.set_in_layout(False)
    mains = [grid[per * o + r, i] for o in range(O) for i in range(I) for r in ((0, 2) if per == 4 else (0, 1))]
    _legend(grid[0, 0], mains, fontsize=7, loc="best")
    if per == 4:
        _legend(grid[1, 0], [grid[1, 0]], fontsize=7, loc="best")
    if axes is None or title:
        fig.suptitle(title or "Frequency response identified from camera motion blur")
    _stamp(fig, stamp)
    return fig


def _bode_overlay(frf, *, truth, title, stamp, axes, opt):
    """Many outputs: one magnitude and one phase panel per input, every output a line (its
    label in the legend); the truth dashed when known; flagged points ringed and out of the
    limits as in :func:`bode_figure`."""
    from matplotlib import colormaps

    O, I = frf.n_outputs, frf.n_inputs
    if axes is None:
        fig = _new_figure((8 * I, 9))
        grid = fig.subplots(2, I, squeeze=False, sharex=True)
    else:
        grid = _axes_grid(axes, 2, I, "magnitude and phase rows, one column per input")
        fig = grid[0, 0].figure
    xs, xlim, f = opt["xs"], opt["xlim"], frf.freq_hz
    x, fine_f = f * xs, np.geomspace(f.min(), f.max(), 400)
    tru = None if truth is None else _as_oif(truth(2 * np.pi * fine_f) if callable(truth) else truth, frf)
    cmap = colormaps["tab20"]
    uph = np.degrees(frf.unwrapped_phase())
    for i in range(I):
        am, ap = grid[0, i], grid[1, i]
        mags, phs = [], []
        for o in range(O):
            col, good = cmap(o % 20), (frf.flags[o, i] == 0) & np.isfinite(frf.magnitude[o, i])
            my, merr = _mag_values(frf, o, i, opt["dB"])
            for ax, y, err, lab in ((am, my, merr, frf.output_labels[o]), (ap, uph[o, i], np.degrees(frf.phase_std[o, i]), None)):
                ax.errorbar(x, np.where(good, y, np.nan), yerr=err, fmt="o-", ms=2.5, lw=0.8, color=col, capsize=1.5, label=lab)
                bad = ~good & np.isfinite(y)
                if bad.any():  # flagged: faint bars, no line through them (their rings come below)
                    ax.errorbar(x[bad], y[bad], yerr=np.asarray(err)[..., bad], fmt="none", ecolor=col, alpha=0.35, capsize=1.5)
            mags.append(my[good])
            phs.append(uph[o, i][good])
            if tru is not None:
                mags.append(_curve_mag(tru[o, i], opt["dB"]))
                am.plot((fine_f if tru.shape[-1] == fine_f.size else f) * xs, mags[-1], "--", color=col, lw=0.8, alpha=0.7)
        am.set_xlim(*xlim)
        _bode_axes(am, ap, mags, phs, opt)
        for o in range(O):
            _flag_marks(am, x, _mag_values(frf, o, i, opt["dB"])[0], frf.flags[o, i], log=not opt["dB"])
            _flag_marks(ap, x, uph[o, i], frf.flags[o, i], log=False)
        note = _camera_marks([am, ap], opt["frame_rate_hz"], xs, xlim)
        am.set_title(f"every output from input {frf.input_labels[i]}" + (" (dashed: truth)" if tru is not None else ""))
        ap.set_xlabel(f"frequency ({'Hz' if opt['Hz'] else 'rad/s'}){note}")
        _legend(am, [am, ap], fontsize=6, ncol=max(1, O // 9), loc="lower left")
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
    sigma=None,
):
    """Data, fitted model and residual of a few fits, one row each.

    The residual is ``(data - model) / sigma`` when ``sigma`` is given (the noise model's std
    of each pixel's expected value, the fitted model: what the fit weighed it by), so a fit
    that the noise explains shows a residual of rms about 1 whatever the light; else
    ``data - model`` in ``unit``. Its colour scale is symmetric, at least +-3 sigma.

    Args:
        images, models: ``[K, H, W]``; ``images[k, i, j]`` = the recorded value of pixel
            row i, column j of panel k in ``unit`` (identify's images: electrons, dark
            subtracted).
        labels: K strings naming the point of each panel (e.g. ``"412 Hz, input x"``).
        stamp: small text at the bottom right.
        axes: draw into these Axes (``K x 3``) instead of a new figure.
        unit: the images' unit, e.g. ``"e-"`` or ``"ADU"`` (the colour bars' label).
        exposures: K strings, which exposure each panel shows (e.g. ``"exposure 1 of 2,
            1.25 ms long (1.25-2.5 ms), image 1 of 2"``); in the row's title.
        reason: why these fits are shown (e.g. ``"the 3 fits with the largest cost per
            pixel"``); in the figure's title.
        origins: ``[K, 2]`` (x, y) px of each image's pixel (0, 0) in the camera frame (for
            crops); default 0: the axes are the camera's pixel coordinates (pixel centres at
            integers, x = column, y = row, y down).
        sigma: ``[K, H, W]`` (or broadcastable to it; > 0) the noise std of each pixel of
            ``models``, in ``unit`` (e.g. ``CameraNoise.std(models)``).

    Returns:
        The ``matplotlib.figure.Figure`` drawn on.
    """
    images = np.asarray(images, dtype=np.float64)
    models = np.asarray(models, dtype=np.float64)
    if images.ndim != 3 or models.shape != images.shape:
        raise ShapeError(f"images, models: expected two arrays [K, H, W] of one shape, got {images.shape} and {models.shape}")
    K, H, W = images.shape
    res, res_unit = images - models, unit
    if sigma is not None:
        res, res_unit = res / _check_sigma(sigma, images.shape), "σ"
    labels = _per_panel(labels, K, "labels")
    exposures = _per_panel(exposures, K, "exposures")
    org = np.zeros((K, 2)) if origins is None else np.asarray(origins, dtype=np.float64).reshape(K, 2)
    if axes is None:
        fig, grid, cax = _residual_layout(K, H / W, _wrap(stamp, 11.7).count("\n") + 1 if stamp else 0)
    else:
        grid = _axes_grid(axes, K, 3, "data, model, residual per panel")
        fig, cax = grid[0, 0].figure, [None] * K
    for k in range(K):
        where = labels[k] + (f"\n{exposures[k]}" if exposures[k] else "")
        _residual_row(fig, grid[k], images[k], models[k], res[k], org[k], where, (unit, res_unit), cax=cax[k])
    if axes is None or reason:
        at = dict(y=1 - 0.1 / fig.get_figheight(), va="top") if axes is None else {}
        fig.suptitle("Recorded frame, fitted model and residual" + (f": {reason}" if reason else "")
                     + ("\nresidual in units of σ, the camera noise model's std of the fitted model" if sigma is not None else ""),
                     fontsize=10, **at)
    _stamp(fig, stamp)
    return fig


def _check_sigma(sigma, shape) -> np.ndarray:
    """``sigma`` broadcast to ``shape``; ShapeError / ParameterError naming ``sigma``."""
    sig = np.asarray(sigma, dtype=np.float64)
    try:
        sig = np.broadcast_to(sig, shape)
    except ValueError:
        raise ShapeError(f"sigma: expected an array broadcastable to the images' {shape}, got {sig.shape}") from None
    if not np.all(sig > 0):
        raise ParameterError("sigma: expected positive noise stds, got a value <= 0 or NaN")
    return sig


_RES_IN = dict(left=0.65, panel=3.0, gap=0.12, cb_pad=0.08, cb=0.15, cb_text=0.75, title=0.42, xlabel=0.45, top=0.75, line=0.12)


def _residual_layout(K: int, aspect: float, stamp_lines: int):
    """A figure of K rows [data, model, bar, residual, bar] placed in inches (no layout
    engine: it costs more than the drawing), panels of the images' ``aspect`` (H / W).
    Returns ``(fig, axes [K, 3], colour-bar axes [K] of pairs)``."""
    from matplotlib.figure import Figure

    d = _RES_IN
    ph = float(np.clip(d["panel"] * aspect, 0.8, 4.5))
    row = d["title"] + ph + d["xlabel"]
    bottom = 0.1 + d["line"] * stamp_lines
    fw = d["left"] + 3 * d["panel"] + d["gap"] + 2 * (d["cb_pad"] + d["cb"] + d["cb_text"])
    fh = d["top"] + K * row + bottom
    fig = Figure(figsize=(fw, fh))
    xs = [d["left"], d["left"] + d["panel"] + d["gap"]]
    xs.append(xs[1] + d["panel"] + d["cb_pad"] + d["cb"] + d["cb_text"])
    cbx = [xs[1] + d["panel"] + d["cb_pad"], xs[2] + d["panel"] + d["cb_pad"]]
    grid, cax = np.empty((K, 3), dtype=object), []
    for k in range(K):
        y = (fh - d["top"] - k * row - d["title"] - ph) / fh
        for c in range(3):
            grid[k, c] = fig.add_axes((xs[c] / fw, y, d["panel"] / fw, ph / fh), sharex=None if c == 0 else grid[k, 0],
                                      sharey=None if c == 0 else grid[k, 0])
        cax.append([fig.add_axes((x / fw, y, d["cb"] / fw, ph / fh), label="<colorbar>") for x in cbx])
    return fig, grid, cax


def _residual_row(fig, axs, img, mod, res, org, where: str, units: tuple[str, str], cax=None) -> None:
    """One row: data and model on one colour scale (one colour bar, ``units[0]``), the
    residual on a symmetric one (``units[1]``); with ``cax`` (the layout's two colour-bar
    axes) the three panels share their axes (one set of y tick labels)."""
    share = cax is not None
    unit, res_unit = units
    H, W = img.shape
    x0, y0 = org
    extent = (x0 - 0.5, x0 + W - 0.5, y0 + H - 0.5, y0 - 0.5)
    lo, vmax = min(0.0, float(np.nanmin(img))), float(np.nanmax([img.max(), mod.max()]))
    r = float(np.nanmax(np.abs(res))) if np.isfinite(res).any() else 1.0
    r = max(r, 3.0) if res_unit == "σ" else (r or 1.0)
    rms = float(np.sqrt(np.nanmean(res**2)))
    title = f"residual (data − model)/σ: rms {rms:.3g}" if res_unit == "σ" else f"residual data − model (rms {rms:.3g} {unit})"
    hs = []
    for ax, im, t, kw in ((axs[0], img, f"data: {where}", dict(vmin=lo, vmax=vmax, cmap="inferno")),
                          (axs[1], mod, "fitted model", dict(vmin=lo, vmax=vmax, cmap="inferno")),
                          (axs[2], res, title, dict(vmin=-r, vmax=r, cmap="RdBu_r"))):
        hs.append(ax.imshow(im, extent=extent, origin="upper", interpolation="nearest", **kw))
        ax.set_title(t, fontsize=8)
        ax.set_xlabel("x (px)", fontsize=8)
        ax.tick_params(labelsize=7)
        if share and ax is not axs[0]:
            ax.tick_params(labelleft=False)
    for ax in axs[:1] if share else axs:
        ax.set_ylabel("y (px)", fontsize=8)
    for n, (h, on, lab) in enumerate(((hs[0], [axs[0], axs[1]], unit), (hs[2], axs[2], res_unit))):
        cb = fig.colorbar(h, cax=cax[n]) if share else fig.colorbar(h, ax=on, fraction=0.046, pad=0.02)
        cb.set_label(lab, fontsize=8)
        cb.ax.tick_params(labelsize=7)
