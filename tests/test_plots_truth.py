"""Figures that tell the truth (issue 25): every flag kind drawn and named, flagged points never
driving the axes, the measured phase on the model's branch, the camera's frame rate and Nyquist
frequency marked, Hz / rad/s and dB, tick labels and footer that do not overlap, residuals in
units of sigma, DM maps with every status, units and y down; no backend switched. Checked on the
Figure objects (artists, labels, limits), not pixels."""
from __future__ import annotations

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")

from torchblur.errors import ParameterError, ShapeError  # noqa: E402
from torchblur.sysid.flags import ALIAS, FAILED, LIMITED, NO_MOTION, POINT_FLAGS, POOR_FIT, TIMING  # noqa: E402
from torchblur.sysid.frequency_response import FrequencyResponse  # noqa: E402
from torchblur.sysid.plots import FLAG_STYLES, bode_figure, flag_style, residual_figure  # noqa: E402

TWO_PI = 2 * np.pi
F_HZ = np.geomspace(1.0, 2e5, 14)  # the fast sweep's span: 5 decades and more of magnitude
UNKNOWN = 1 << 9  # a flag this module has no style for (a new one, or a newer file's)


class Plant:
    """A 400 Hz resonance with a 30 us delay (the phase reaches about -2300 deg at 200 kHz)."""

    def frequency_response(self, w):
        wn, s = TWO_PI * 400.0, 1j * np.asarray(w)
        return 20.0 * wn**2 / (s**2 + 0.24 * wn * s + wn**2) * np.exp(-s * 30e-6)


def _flagged(outlier=1e3):
    """The plant measured at 0.3 % with one point of each flag kind (and a three-flag point);
    the no_motion point ``outlier`` times too large, the failed one NaN."""
    rng = np.random.default_rng(3)
    h = Plant().frequency_response(TWO_PI * F_HZ)
    h = h * (1 + 0.003 * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape)))
    flags = np.zeros(F_HZ.size, dtype=np.int64)
    flags[[3, 5, 7, 9, 11, 13]] = [POOR_FIT, TIMING, LIMITED, NO_MOTION, UNKNOWN, TIMING | LIMITED | NO_MOTION]
    flags[12] = FAILED
    flags[1] = ALIAS
    h[9] *= outlier
    h[12] = np.nan
    cov = np.zeros(h.shape + (2, 2))
    cov[..., 0, 0], cov[..., 1, 1] = (0.003 * np.abs(h)) ** 2, 0.003**2
    return FrequencyResponse(TWO_PI * F_HZ, h, cov=cov, flags=flags)


def _texts(ax):
    return [t.get_text() for t in ax.get_legend().get_texts()]


def _rings(ax, name):
    st = flag_style(name)
    return [c for c in ax.collections if c.get_label() == st["text"]]


def test_each_flag_kind_drawn_distinctly_and_named():
    frf = _flagged()
    fig = bode_figure(frf, model=Plant(), frame_rate_hz=30.0)
    mag = fig.axes[0]
    names = list(POINT_FLAGS.values()) + ["bit9"]
    legend = _texts(mag)
    for name in names:
        assert flag_style(name)["text"] in legend, name
    styles = {(flag_style(n)["marker"], flag_style(n)["color"]) for n in names}
    assert len(styles) == len(names)  # each kind its own marker and colour, the unknown one too
    assert flag_style("bit9")["text"] == "bit9" and set(FLAG_STYLES) <= set(POINT_FLAGS.values())
    # every ring sits on its point: poor_fit at f[3], timing at f[5] and f[13], ...
    for name, bit in [*((n, b) for b, n in POINT_FLAGS.items()), ("bit9", UNKNOWN)]:
        (coll,) = _rings(mag, name)
        np.testing.assert_allclose(np.sort(coll.get_offsets()[:, 0]), F_HZ[(frf.flags[0, 0] & bit) != 0])
    # the three-flag point: three rings of growing size
    sizes = [c.get_sizes()[-1] for n in ("timing", "limited", "no_motion") for c in _rings(mag, n)]
    assert sizes == sorted(sizes) and len(set(sizes)) == 3
    # an unflagged point is not ringed; the measured ones carry the plain label
    assert "measured ±1σ" in legend


def test_flagged_points_never_drive_the_limits():
    near, far = (bode_figure(_flagged(outlier), model=Plant()) for outlier in (1.0, 1e6))
    for a, b in zip(near.axes, far.axes):  # magnitude, its error, phase, its error
        assert a.get_ylim() == pytest.approx(b.get_ylim(), rel=1e-12)
    mag, mag_err = far.axes[0], far.axes[1]
    assert mag.get_ylim()[1] < 0.01 * _flagged(1e6).magnitude[0, 0, 9]  # the no_motion point (x 1e6) lies far above the axis
    lo, hi = mag_err.get_ylim()
    assert hi < 5  # % : the good points' scale (0.3 %), not the outlier's 1e6 %
    # the off-scale point is still drawn, at the edge, and the legend says so
    assert "off scale: drawn at the edge (value in frf.csv)" in _texts(mag)


def test_measured_phase_sits_on_the_models_branch():
    frf = _flagged()
    fig = bode_figure(frf, model=Plant(), truth=Plant().frequency_response)
    ph = fig.axes[2]
    (model,) = [ln for ln in ph.get_lines() if ln.get_label() == "model (fit)"]
    (truth,) = [ln for ln in ph.get_lines() if ln.get_label() == "truth (simulation)"]
    (pts,) = [c for c in ph.containers if c.get_label() == "measured ±1σ"]
    x, y = pts.lines[0].get_xdata(), pts.lines[0].get_ydata()
    curve = np.interp(np.log(x), np.log(model.get_xdata()), model.get_ydata())
    assert model.get_ydata().min() < -2000  # unwrapped over the delay
    assert np.all(np.abs(y - curve) < 5)  # on the branch (0.3 % noise: under a degree), not 360 k away
    np.testing.assert_allclose(truth.get_ydata(), model.get_ydata(), atol=1e-9)  # the truth on the model's branch
    # and the error panel is exactly data minus curve
    (err,) = [ln for ln in fig.axes[3].get_lines() if ln.get_label() == "measured − model"]
    np.testing.assert_allclose(err.get_ydata(), y - curve, atol=1e-6)


def test_frame_rate_nyquist_and_units():
    frf = _flagged()
    fig = bode_figure(frf, model=Plant(), frame_rate_hz=30.0)
    marks = {ln.get_label(): ln.get_xdata()[0] for ln in fig.axes[0].get_lines() if ln.get_label().startswith("camera")}
    assert marks == {"camera frame rate 30 Hz": 30.0, "camera Nyquist 15 Hz": 15.0}
    assert all(any(ln.get_xdata()[0] == 15.0 for ln in ax.get_lines()) for ax in fig.axes[:4])  # on every panel
    # a sweep above both: named in the x label instead of stretching the axis
    above = FrequencyResponse(frf.omega[5:8], frf.response[0, 0, 5:8], meta={"frame_rate_hz": 30.0})
    fig2 = bode_figure(above, model=Plant())
    assert "frame rate 30 Hz, Nyquist 15 Hz: below this range" in fig2.axes[-1].get_xlabel()
    assert fig2.axes[0].get_xlim()[0] > 30.0
    # rad/s and dB, as python-control's bode_plot offers
    fig3 = bode_figure(frf, model=Plant(), Hz=False, dB=True, frame_rate_hz=30.0)
    mag = fig3.axes[0]
    (pts,) = [c for c in mag.containers if c.get_label() == "measured ±1σ"]
    good = frf.flags[0, 0] == 0
    np.testing.assert_allclose(pts.lines[0].get_xdata(), frf.omega[good])
    np.testing.assert_allclose(pts.lines[0].get_ydata(), 20 * np.log10(frf.magnitude[0, 0, good]))
    assert mag.get_yscale() == "linear" and "dB" in mag.get_ylabel() and "rad/s" in fig3.axes[-1].get_xlabel()
    assert any(ln.get_xdata()[0] == pytest.approx(TWO_PI * 30.0) for ln in mag.get_lines())


def _overlaps(boxes):
    return [(a, b) for k, a in enumerate(boxes) for b in boxes[k + 1:] if a.overlaps(b)]


def test_magnitude_tick_labels_and_footer_do_not_overlap():
    frf = _flagged()
    stamp = "torchblur 0.1.0, fit of the outside recording /a/very/long/path/" + "x" * 150 + "/frames"
    fig = bode_figure(frf, model=Plant(), stamp=stamp)
    fig.draw_without_rendering()  # the constrained layout placed; extents below use the figure's renderer
    mag = fig.axes[0]
    lo, hi = mag.get_ylim()
    labels = [t for t in mag.get_yticklabels() if t.get_text() and lo <= t.get_position()[1] <= hi]
    assert len(labels) >= 4
    assert not _overlaps([t.get_window_extent() for t in labels])
    footer = [t for t in fig.texts if "outside recording" in t.get_text()]
    assert len(footer) == 1 and "\n" in footer[0].get_text()  # wrapped to the figure's width
    box = footer[0].get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 + 1
    xlabel = fig.axes[-1].xaxis.label.get_window_extent()
    ticks = [t.get_window_extent() for t in fig.axes[-1].get_xticklabels() if t.get_text()]
    assert not _overlaps([box, xlabel]) and not any(box.overlaps(t) for t in ticks)


def test_residuals_in_units_of_sigma():
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:20, :24]
    model = np.stack([2000 * np.exp(-((xx - 12) ** 2 + (yy - 10) ** 2) / 8.0)] * 2)  # e-
    sigma = np.sqrt(25.0 + model)  # read noise 5 e- and shot noise: the camera noise model's std
    data = model + sigma * rng.standard_normal(model.shape)
    fig = residual_figure(data, model, ["412 Hz", "1 kHz"], sigma=sigma,
                          exposures=["exposure 1 of 2, 0.75 ms long (0.6-1.35 ms), image 2 of 2", None])
    res_ax = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"][2]
    (im,) = res_ax.get_images()
    np.testing.assert_allclose(im.get_array(), (data[0] - model[0]) / sigma[0], rtol=1e-12)
    assert 0.85 < float(np.sqrt(np.mean(im.get_array() ** 2))) < 1.15  # pure noise: rms 1 at the peak and in the dark
    assert "/σ" in res_ax.get_title() and im.get_clim()[1] >= 3.0 and im.get_clim()[0] == -im.get_clim()[1]
    cbars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert [cb.get_ylabel() for cb in cbars] == ["e-", "σ", "e-", "σ"]
    title = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"][0].get_title()
    assert "0.75 ms long" in title and "image 2 of 2" in title
    assert "units of σ" in fig._suptitle.get_text()
    with pytest.raises(ParameterError, match="sigma"):
        residual_figure(data, model, ["a", "b"], sigma=np.zeros_like(model))
    with pytest.raises(ShapeError, match="sigma"):
        residual_figure(data, model, ["a", "b"], sigma=np.ones((3, 20, 24)))


def _actuator_table():
    """A 3 x 3 mirror's table as the fit reports it: actuator 4 dead (gain ~0, NaN dynamics),
    2 weak, 6 poor_fit; row-major from the top left (y down)."""
    from torchblur.dm.actuator_fit import ActuatorTable

    rng = np.random.default_rng(5)
    N = 9
    xy = np.stack(np.meshgrid(np.arange(3) - 1.0, np.arange(3) - 1.0), -1).reshape(-1, 2)
    gain, mode, damp = rng.normal(1, 0.05, N), rng.uniform(800, 1200, N), rng.uniform(0.05, 0.2, N)
    gain[2], gain[4] = 0.3, 0.001
    mode[4] = damp[4] = np.nan
    status = ("ok", "ok", "weak", "ok", "dead", "ok", "ok", "ok", "ok")
    poor = np.zeros(N, dtype=bool)
    poor[6] = True
    f = np.geomspace(10.0, 2000.0, 4)
    return ActuatorTable(gain, gain * 0.01, mode, mode * 0.01, damp, damp * 0.05, np.full(N, 3e-5), np.full(N, 1e-6), status, poor,
                         np.ones(N), np.zeros((4, N)), np.zeros((4, N)), np.zeros((N, 4), complex), np.zeros((N, 4, 2, 2)), f,
                         actuator_xy=xy)


def test_dm_maps_mark_every_status_with_units_and_y_down():
    from torchblur.identify.dm_outputs import STATUS_STYLES, actuator_maps_figure

    t = _actuator_table()
    fig = actuator_maps_figure(t, failed=[8])
    maps = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert [ax.get_title() for ax in maps] == ["DC gain", "mode", "damping"]
    assert all(ax.yaxis_inverted() and "down" in ax.get_ylabel() for ax in maps)  # the guide's y down
    cbars = [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert cbars == ["DC gain (× nominal (1 = nominal actuator))", "mode (Hz)", "damping (ratio ζ)"]
    legend = [tx.get_text() for tx in fig.legends[0].get_texts()]
    assert legend == [STATUS_STYLES[k]["text"] for k in ("dead", "weak", "poor_fit", "failed")]
    for ax in maps:  # each status on every map, at its actuator; the dead one not coloured
        where = {c.get_label(): c.get_offsets() for c in ax.collections if c.get_label() in legend}
        for key, j in (("dead", 4), ("weak", 2), ("poor_fit", 6), ("failed", 8)):
            np.testing.assert_allclose(where[STATUS_STYLES[key]["text"]], t.actuator_xy[[j]])
        coloured = ax.collections[0].get_offsets()
        assert len(coloured) == 8 and not (np.asarray(coloured) == t.actuator_xy[4]).all(1).any()


def test_no_module_switches_the_backend():
    """No ``matplotlib.use(...)`` and no pyplot anywhere in the package: figures are
    ``matplotlib.figure.Figure`` objects, so a notebook's backend is untouched."""
    import re
    from pathlib import Path

    import torchblur

    pattern = re.compile(r"^\s*(?:matplotlib\.use\(|import matplotlib\.pyplot|from matplotlib import pyplot|from matplotlib\.pyplot import)",
                         re.M)
    offenders = [f"{p.name}: {m.group(0).strip()}" for p in Path(torchblur.__file__).parent.rglob("*.py")
                 for m in pattern.finditer(p.read_text())]
    assert offenders == []
