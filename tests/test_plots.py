"""sysid.plots: figures that leave the backend alone, draw into the caller's axes, carry units,
an error panel with the 1-sigma band, truth and model told apart, residual images in pixels."""
from __future__ import annotations

import io

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
from matplotlib.figure import Figure  # noqa: E402

from torchblur.errors import InputTypeError, ShapeError  # noqa: E402
from torchblur.sysid.frequency_response import FrequencyResponse  # noqa: E402
from torchblur.sysid.plots import bode_figure, residual_figure, response_units  # noqa: E402
from torchblur.sysid.tf_fit import fit_transfer_function  # noqa: E402

TWO_PI = 2 * np.pi
OMEGA = TWO_PI * np.geomspace(1.0, 1000.0, 25)


def _plant(w):
    wn, zeta = TWO_PI * 400.0, 0.12
    s = 1j * np.asarray(w)
    return 20.0 * wn**2 / (s**2 + 2 * zeta * wn * s + wn**2) * np.exp(-s * 30e-6)


def _measured(n_out=1, n_in=1, rel=0.002, meta=None):
    rng = np.random.default_rng(1)
    h = np.broadcast_to(_plant(OMEGA), (n_out, n_in, OMEGA.size)).copy()
    h = h * (1 + rel * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape)))
    cov = np.zeros(h.shape + (2, 2))
    cov[..., 0, 0] = (rel * np.abs(h)) ** 2
    cov[..., 1, 1] = rel**2
    kw = {} if n_out == n_in == 1 else dict(input_labels=[f"u{i}" for i in range(n_in)],
                                             output_labels=[f"s{o}" for o in range(n_out)])
    if n_out == n_in == 1:
        h, cov = h[0, 0], cov[0, 0]
    return FrequencyResponse(OMEGA, h, cov=cov, meta=meta, **kw)


@pytest.fixture(scope="module")
def siso():
    frf = _measured()
    return frf, fit_transfer_function(frf, n_poles=2, n_zeros=0)


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=40)
    return buf.getvalue()


def test_figures_leave_the_backend_and_pyplot_alone(siso):
    import matplotlib.pyplot as plt

    frf, model = siso
    backend, open_before = matplotlib.get_backend(), plt.get_fignums()
    figs = [bode_figure(frf, model=model, truth=_plant), bode_figure(_measured(6, 2)),
            residual_figure(np.ones((2, 8, 9)), np.zeros((2, 8, 9)), ["a", "b"])]
    assert matplotlib.get_backend() == backend
    assert plt.get_fignums() == open_before  # nothing registered with pyplot
    for fig in figs:
        assert isinstance(fig, Figure)
        assert _png(fig).startswith(b"\x89PNG")


def test_bode_draws_into_the_callers_axes(siso):
    frf, model = siso
    fig = Figure()
    axes = fig.subplots(4, 1)
    assert bode_figure(frf, model=model, axes=axes) is fig
    assert len(fig.axes) == 4 and all(ax.has_data() for ax in axes)
    fig2 = Figure()
    assert bode_figure(frf, axes=fig2.subplots(2, 1)) is fig2  # no model, no truth: magnitude and phase
    with pytest.raises(ShapeError, match="axes"):
        bode_figure(frf, model=model, axes=Figure().subplots(2, 1))


def test_units_on_every_axis(siso):
    frf, model = siso
    fig = bode_figure(frf, model=model, truth=_plant)
    mag, mag_err, ph, ph_err = fig.axes[:4]
    assert mag.get_ylabel() == "|H| (px per input unit)"
    assert "%" in mag_err.get_ylabel() and "deg" in ph.get_ylabel() and "deg" in ph_err.get_ylabel()
    assert ph_err.get_xlabel() == "frequency (Hz)"
    frf_v = _measured(meta={"output_unit": "um", "input_unit": "V"})
    assert bode_figure(frf_v).axes[0].get_ylabel() == "|H| (um per V)"
    assert bode_figure(frf_v, units=("px", "A")).axes[0].get_ylabel() == "|H| (px per A)"
    assert response_units(frf_v) == ("um", "V")
    with pytest.raises(InputTypeError, match="units"):
        response_units(frf_v, ("px",))


def test_error_panel_is_measured_minus_model_with_the_sigma_band(siso):
    frf, model = siso
    fig = bode_figure(frf, model=model)
    mag_err, ph_err = fig.axes[1], fig.axes[3]
    ref = model.frequency_response(frf.omega)
    want_mag = 100 * (frf.magnitude[0, 0] - np.abs(ref)) / np.abs(ref)
    want_ph = np.degrees(np.angle(frf.response[0, 0] / ref))
    (pts,) = [ln for ln in mag_err.get_lines() if ln.get_label() == "measured − model"]
    np.testing.assert_allclose(pts.get_xdata(), frf.freq_hz)
    np.testing.assert_allclose(pts.get_ydata(), want_mag, rtol=1e-12)
    (pts,) = [ln for ln in ph_err.get_lines() if ln.get_label() == "measured − model"]
    np.testing.assert_allclose(pts.get_ydata(), want_ph, rtol=1e-12)
    # the band spans +-1 sigma (0.2 % here) and the panel is scaled to it: the bars are readable
    (band,) = mag_err.collections
    ys = np.concatenate([p.vertices[:, 1] for p in band.get_paths()])
    sigma = 100 * frf.magnitude_std[0, 0] / np.abs(ref)
    assert ys.max() == pytest.approx(sigma.max(), rel=1e-9) and ys.min() == pytest.approx(-sigma.max(), rel=1e-9)
    lo, hi = mag_err.get_ylim()
    assert hi < 10 * max(sigma.max(), np.abs(want_mag).max())  # sub-percent scale, not the magnitude's


def test_truth_and_model_are_distinguishable(siso):
    frf, model = siso
    fig = bode_figure(frf, model=model, truth=_plant)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    truth, fit = lines["truth (simulation)"], lines["model (fit)"]
    assert truth.get_linestyle() != fit.get_linestyle()
    assert matplotlib.colors.to_rgba(truth.get_color()) != matplotlib.colors.to_rgba(fit.get_color())
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend == ["truth (simulation)", "model (fit)", "measured ±1σ"]


def test_mimo_and_overlay_layouts():
    frf = _measured(2, 2)
    model = fit_transfer_function(frf, n_poles=2, n_zeros=0)
    fig = bode_figure(frf, model=model, title="two axes")
    assert len(fig.axes) == 16  # 4 rows per output x 2 outputs, one column per input
    assert fig.axes[0].get_title() == "output s0 from input u0"
    assert fig._suptitle.get_text() == "two axes"
    fig = bode_figure(frf, model=model, truth=_plant)  # one [F] truth serves every channel
    truth_lines = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_label() == "truth (simulation)"]
    assert len(truth_lines) == 8  # magnitude and phase of 4 channels
    with pytest.raises(ShapeError, match="truth"):
        bode_figure(frf, truth=np.ones((3, 2, OMEGA.size)))
    many = _measured(6, 2)
    fig = bode_figure(many, truth=np.broadcast_to(_plant(OMEGA), (6, 2, OMEGA.size)))
    assert len(fig.axes) == 4 and fig.axes[0].get_ylabel() == "|H| (px per input unit)"
    mine = Figure()
    assert bode_figure(many, axes=mine.subplots(2, 2)) is mine


def test_residual_figure_pixels_units_and_titles():
    rng = np.random.default_rng(0)
    data = rng.uniform(0, 100, (2, 10, 12))
    model = data + rng.normal(0, 1, data.shape)
    fig = residual_figure(data, model, ["412 Hz, input x", "1000 Hz, input x"], unit="ADU",
                          exposures=["exposure 0 of 8 (0.25-4.25 ms)", "exposure 3 of 8 (1.0-2.0 ms)"],
                          reason="the 2 fits with the largest cost per pixel", origins=[[100, 40], [0, 0]], stamp="v0")
    img_axes = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    cbars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(img_axes) == 6 and len(cbars) == 4  # data and model share one colour scale and bar per row
    assert all(ax.get_xlabel() == "x (px)" for ax in img_axes)
    assert [ax.get_ylabel() for ax in img_axes] == ["y (px)", "", ""] * 2  # a row's panels share their axes
    assert img_axes[1].get_shared_y_axes().joined(img_axes[0], img_axes[2])
    assert all(cb.get_ylabel() == "ADU" for cb in cbars)
    title = img_axes[0].get_title()
    assert "412 Hz" in title and "exposure 0 of 8" in title
    assert "residual" in img_axes[2].get_title() and "ADU" in img_axes[2].get_title()
    assert "largest cost per pixel" in fig._suptitle.get_text()
    # pixel centres at integers, offset by the crop's origin; y grows downwards
    assert img_axes[0].get_xlim() == (99.5, 111.5) and img_axes[0].get_ylim() == (49.5, 39.5)
    assert img_axes[3].get_xlim() == (-0.5, 11.5)
    # the caller's axes, and the CLI's positional call
    mine = Figure()
    assert residual_figure(data, model, ["a", "b"], axes=mine.subplots(2, 3)) is mine
    assert isinstance(residual_figure(data, model, ["a", "b"], stamp="s"), Figure)
    with pytest.raises(ShapeError, match="labels"):
        residual_figure(data, model, ["a"])
    with pytest.raises(ShapeError, match="images"):
        residual_figure(data, model[:, :5], ["a", "b"])


def test_degenerate_responses_still_draw():
    """NaN points, unknown covariance, an exact model (zero error) and a model with a zero: no crash."""
    h = _plant(OMEGA)
    h[3] = np.nan
    frf = FrequencyResponse(OMEGA, h)  # cov unknown
    exact = fit_transfer_function(FrequencyResponse(OMEGA, _plant(OMEGA)), n_poles=2, n_zeros=0)
    fig = bode_figure(frf, model=exact, truth=_plant)
    assert _png(fig).startswith(b"\x89PNG")

    class Notch:
        def frequency_response(self, w):
            return np.where(np.isclose(w, OMEGA[5]), 0.0, 1.0) + 0j

    assert _png(bode_figure(frf, model=Notch())).startswith(b"\x89PNG")
