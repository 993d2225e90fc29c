"""python-control interop: named FRDs and systems with labels, the delay as an exact FRD or a
Pade approximation, model.json read back, frf.mat for MATLAB."""
from __future__ import annotations

import dataclasses

import json

import numpy as np
import pytest

control = pytest.importorskip("control")
matplotlib = pytest.importorskip("matplotlib")
scipy_io = pytest.importorskip("scipy.io")

from torchblur.errors import InputTypeError, ParameterError
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import TransferFunctionFit, fit_transfer_function

TWO_PI = 2.0 * np.pi
OMEGA = TWO_PI * np.logspace(0, 3.3, 60)
WN, ZETA, GAIN, TAU = TWO_PI * 300.0, 0.05, 2.0, 50e-6


def _plant(omega, tau=TAU):
    s = 1j * np.asarray(omega)
    return GAIN * WN**2 / (s**2 + 2 * ZETA * WN * s + WN**2) * np.exp(-s * tau)


def _loop(omega):
    """An open loop with an integrator: L(s) = 400 / (s (s / 2000 + 1)), gain crossover ~ 390 rad/s."""
    s = 1j * np.asarray(omega)
    return 400.0 / (s * (s / 2000.0 + 1.0))


@pytest.fixture(scope="module")
def siso_fit():
    frf = FrequencyResponse(OMEGA, _plant(OMEGA), input_labels=["u"], output_labels=["x"])
    return frf, fit_transfer_function(frf, n_poles=2, n_zeros=0)


@pytest.fixture(scope="module")
def mimo_fit():
    h = np.zeros((2, 2, OMEGA.size), complex)
    h[0, 0] = _plant(OMEGA)
    h[1, 1] = 0.5 * _plant(OMEGA, tau=20e-6)
    h[0, 1] = 0.1 * _plant(OMEGA, tau=0.0)
    h[1, 0] = 0.2 * _plant(OMEGA, tau=80e-6)
    frf = FrequencyResponse(OMEGA, h, input_labels=["ux", "uy"], output_labels=["px", "py"])
    return frf, fit_transfer_function(frf, n_poles=2, n_zeros=0)


# ------------------------------------------------------------- FrequencyResponse.to_control
def test_frd_is_named_and_labelled():
    frf = FrequencyResponse(OMEGA, _plant(OMEGA), input_labels=["u"], output_labels=["x"])
    sys_ = frf.to_control()
    assert sys_.name == "frf"
    assert list(sys_.input_labels) == ["u"] and list(sys_.output_labels) == ["x"]
    assert frf.to_control(name="stage").name == "stage"
    with pytest.raises(InputTypeError, match="name"):
        frf.to_control(name=3)


def test_a_spots_run_response_converts_in_order():
    """A many-spot run's labels ("s0.x": python-control refuses dots) become "s0_x" in the
    control object only, each name at its label's place; the torchblur labels are unchanged."""
    from torchblur.image.spots import spot_labels
    from torchblur.sysid.frequency_response import control_names

    labels = spot_labels(2)  # s0.x, s0.y, s1.x, s1.y
    h = np.stack([k * _plant(OMEGA) for k in (1.0, 2.0, 3.0, 4.0)])[:, None, :]  # output k: k H
    frf = FrequencyResponse(OMEGA, h, input_labels=["u.1"], output_labels=labels)
    sys_ = frf.to_control(name="spots.run")
    assert list(sys_.output_labels) == ["s0_x", "s0_y", "s1_x", "s1_y"] and list(sys_.input_labels) == ["u_1"]
    assert sys_.name == "spots_run" and list(frf.output_labels) == labels
    for k in range(4):
        np.testing.assert_allclose(np.asarray(sys_.frdata if hasattr(sys_, "frdata") else sys_.fresp)[k, 0], h[k, 0])
    back = FrequencyResponse.from_control(sys_)
    np.testing.assert_array_equal(back.response, frf.response)
    # a mapped name never merges with a label that is already a name: "s0.x" and "s0_x" stay two signals
    assert control_names(["s0.x", "s0_x", "s0.x_2"]) == ["s0_x_2", "s0_x", "s0_x_2_2"]
    two = FrequencyResponse(OMEGA, h[:2], output_labels=["s0.x", "s0_x"]).to_control()
    assert two.noutputs == 2 and list(two.output_labels) == ["s0_x_2", "s0_x"]
    fit = fit_transfer_function(FrequencyResponse(OMEGA, _plant(OMEGA), input_labels=["u"], output_labels=["s0.x"]), n_poles=2,
                                n_zeros=0)
    assert list(fit.to_control().output_labels) == ["s0_x"]


def test_bode_plot_accepts_the_frd_and_keeps_the_backend():
    import matplotlib.pyplot as plt

    frf = FrequencyResponse(OMEGA, _plant(OMEGA), input_labels=["u"], output_labels=["x"])
    backend = matplotlib.get_backend()
    out = control.bode_plot(frf.to_control(name="measured"))
    assert matplotlib.get_backend() == backend
    fig = out.figure if hasattr(out, "figure") else plt.gcf()
    assert len(fig.axes) >= 2  # magnitude and phase
    plt.close("all")


def test_stability_margins_of_the_frd_match_the_transfer_function():
    w = np.geomspace(10.0, 1e5, 2000)
    frf = FrequencyResponse(w, _loop(w))
    _, pm, _, _, wgc, _ = control.stability_margins(frf.to_control())
    tf = control.tf([400.0], [1 / 2000.0, 1.0, 0.0])
    _, pm_tf, _, _, wgc_tf, _ = control.stability_margins(tf)
    assert wgc == pytest.approx(wgc_tf, rel=1e-3)
    assert pm == pytest.approx(pm_tf, abs=0.05)  # degrees


def test_feedback_of_the_frd_is_the_closed_loop():
    w = np.geomspace(10.0, 1e5, 200)
    frf = FrequencyResponse(w, _loop(w), input_labels=["r"], output_labels=["y"])
    closed = FrequencyResponse.from_control(control.feedback(frf.to_control(), 1))
    want = _loop(w) / (1.0 + _loop(w))
    np.testing.assert_allclose(closed.response[0, 0], want, rtol=1e-12)


# -------------------------------------------------------------- TransferFunctionFit.to_control
def test_tf_default_is_the_rational_part_with_labels(siso_fit):
    _, fit = siso_fit
    sys_ = fit.to_control()
    assert isinstance(sys_, control.TransferFunction)
    assert sys_.name == "model"
    assert list(sys_.input_labels) == ["u"] and list(sys_.output_labels) == ["x"]
    w = OMEGA[::7]
    np.testing.assert_allclose(np.asarray(sys_(1j * w)) * np.exp(-1j * w * fit.delay_s), fit.frequency_response(w), rtol=1e-9)


def test_tf_frd_delay_is_exact(siso_fit, mimo_fit):
    for frf, fit in (siso_fit, mimo_fit):
        w = TWO_PI * np.logspace(-1, 4, 51)  # off the fitted grid too
        sys_ = fit.to_control(delay="frd", omega=w, name="fit")
        assert isinstance(sys_, control.FrequencyResponseData) and sys_.name == "fit"
        assert list(sys_.input_labels) == list(frf.input_labels)
        assert list(sys_.output_labels) == list(frf.output_labels)
        back = FrequencyResponse.from_control(sys_)
        want = fit.frequency_response(w)
        np.testing.assert_array_equal(back.response, want.reshape(back.response.shape))


def test_tf_pade_delay_converges_with_order(siso_fit):
    _, fit = siso_fit
    w = OMEGA
    want = fit.frequency_response(w)
    errors = []
    for order in (1, 3, 6):
        sys_ = fit.to_control(delay="pade", pade_order=order)
        assert isinstance(sys_, control.TransferFunction)
        assert len(sys_.poles()) == 2 + order
        errors.append(np.max(np.abs(np.asarray(sys_(1j * w)) - want) / np.abs(want)))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-6  # omega tau <= 0.63 over this band
    # the exact Pade factor of python-control, multiplied in
    pn, pd = control.pade(fit.delay_s, 3)
    ref = fit.to_control() * control.tf(pn, pd)
    np.testing.assert_allclose(np.asarray(fit.to_control(delay="pade", pade_order=3)(1j * w)), np.asarray(ref(1j * w)), rtol=1e-9)


def test_tf_pade_mimo_uses_each_channels_delay(mimo_fit):
    frf, fit = mimo_fit
    sys_ = fit.to_control(delay="pade", pade_order=6)
    assert (sys_.noutputs, sys_.ninputs) == (2, 2)
    assert list(sys_.input_labels) == ["ux", "uy"] and list(sys_.output_labels) == ["px", "py"]
    w = OMEGA[:40]
    got = np.asarray(sys_(1j * w))
    np.testing.assert_allclose(got, fit.frequency_response(w), rtol=1e-6, atol=1e-9)


def test_tf_to_control_bad_arguments(siso_fit):
    _, fit = siso_fit
    with pytest.raises(ParameterError, match="delay"):
        fit.to_control(delay="exact")
    with pytest.raises(ParameterError, match="omega"):
        fit.to_control(delay="frd")
    with pytest.raises(ParameterError, match="pade_order"):
        fit.to_control(delay="pade", pade_order=0)
    with pytest.raises(InputTypeError, match="pade_order"):
        fit.to_control(delay="pade", pade_order=2.5)
    with pytest.raises(InputTypeError, match="name"):
        fit.to_control(name=None)


def test_tf_systems_work_in_control(siso_fit):
    _, fit = siso_fit
    import matplotlib.pyplot as plt

    for sys_ in (fit.to_control(delay="pade", pade_order=4), fit.to_control(delay="frd", omega=OMEGA)):
        control.bode_plot(sys_)
        control.stability_margins(sys_)
        closed = control.feedback(0.2 * sys_, 1)
        assert (closed.noutputs, closed.ninputs) == (1, 1)
    plt.close("all")


# ------------------------------------------------------------------------ from_json
def _same_fit(a: TransferFunctionFit, b: TransferFunctionFit):
    assert json.dumps(a.to_dict(), allow_nan=False) == json.dumps(b.to_dict(), allow_nan=False)
    w = TWO_PI * np.logspace(0, 3, 17)
    np.testing.assert_array_equal(a.frequency_response(w), b.frequency_response(w))
    assert (a.input_labels, a.output_labels, a.weighting, a.delay_estimated) == (
        b.input_labels, b.output_labels, b.weighting, b.delay_estimated)


def test_from_json_round_trips(siso_fit, mimo_fit, tmp_path):
    for k, (_, fit) in enumerate((siso_fit, mimo_fit)):
        path = tmp_path / f"model{k}.json"
        fit.to_json(path)
        back = TransferFunctionFit.from_json(path)
        _same_fit(fit, back)
        assert back.n_poles == fit.n_poles and back.dof == fit.dof


def test_from_json_reads_the_cli_model_json(siso_fit, tmp_path):
    _, fit = siso_fit
    doc = {"torchblur_version": "0.1.0", "seed": 3}
    doc.update(fit.to_dict())
    path = tmp_path / "model.json"
    path.write_text(json.dumps(doc, indent=2))
    _same_fit(fit, TransferFunctionFit.from_json(path))
    path.write_text(json.dumps({"torchblur_version": "0.1.0", "seed": 3, "error": "the model fit failed"}))
    with pytest.raises(ParameterError, match="schema.*the model fit failed"):
        TransferFunctionFit.from_json(path)


def test_from_dict_reads_a_version_1_file(siso_fit):
    """A model.json written before ``units`` (schema_version 1, with the CLI's keys) still reads."""
    _, fit = siso_fit
    from torchblur.sysid.model_io import TF_UNCERTAINTY_KEYS as _UNCERTAINTY_KEYS  # version 1 had neither units nor the parameters' covariance

    old = {k: v for k, v in fit.to_dict().items() if k != "units" and k not in _UNCERTAINTY_KEYS}
    old.update(schema_version=1, torchblur_version="0.1.0", seed=0, left_out_points=[], poor_fit_points_kept=[])
    bare = dataclasses.replace(fit, **{k: TransferFunctionFit.__dataclass_fields__[k].default for k in _UNCERTAINTY_KEYS})
    _same_fit(bare, TransferFunctionFit.from_dict(old))


def test_from_dict_recovers_an_infinite_dc_gain():
    w = TWO_PI * np.logspace(0, 3, 40)
    frf = FrequencyResponse(w, 1000.0 / (1j * w * (1j * w / 3000.0 + 1.0)))
    fit = fit_transfer_function(frf, n_poles=2, n_zeros=0, delay_s=0.0, stable=False)
    fit = TransferFunctionFit(**{**fit.__dict__, "den": [1.0, 3000.0, 0.0], "num": [3e6], "dc_gain": float("inf")})
    doc = json.loads(json.dumps(fit.to_dict(), allow_nan=False))
    assert doc["dc_gain"] is None
    assert TransferFunctionFit.from_dict(doc).dc_gain == float("inf")


def test_from_dict_rejects_bad_documents(siso_fit, mimo_fit):
    _, fit = siso_fit
    doc = fit.to_dict()
    with pytest.raises(InputTypeError, match="doc"):
        TransferFunctionFit.from_dict([doc])
    with pytest.raises(ParameterError, match="schema"):
        TransferFunctionFit.from_dict({**doc, "schema": "torchblur.direct_model_fit"})
    with pytest.raises(ParameterError, match="schema_version: unsupported version 3 .written by a newer torchblur"):
        TransferFunctionFit.from_dict({**doc, "schema_version": 3})
    with pytest.raises(ParameterError, match="unknown keys"):
        TransferFunctionFit.from_dict({**doc, "extra": 1})
    with pytest.raises(ParameterError, match=r"unknown keys \[[^]]*'units'\] for schema_version 1"):  # 1 had no units
        TransferFunctionFit.from_dict({**doc, "schema_version": 1})
    with pytest.raises(ParameterError, match="units"):
        TransferFunctionFit.from_dict({**doc, "units": {**doc["units"], "delay_s": "ms"}})
    with pytest.raises(ParameterError, match="left_out_points"):
        TransferFunctionFit.from_dict({**doc, "left_out_points": 3})
    with pytest.raises(ParameterError, match="missing keys"):
        TransferFunctionFit.from_dict({k: v for k, v in doc.items() if k != "den"})
    with pytest.raises(ParameterError, match="n_poles"):
        TransferFunctionFit.from_dict({**doc, "n_poles": 2.5})
    mdoc = mimo_fit[1].to_dict()
    with pytest.raises(ParameterError, match=r"num.*\[O\]\[I\]"):
        TransferFunctionFit.from_dict({**mdoc, "num": mdoc["num"][0]})


# ----------------------------------------------------------------------------- to_mat
def test_to_mat_loads_back_in_scipy(tmp_path):
    h = np.stack([np.stack([_plant(OMEGA), 0.3 * _plant(OMEGA)]), np.stack([0.1 * _plant(OMEGA), _plant(OMEGA, 0.0)])])
    h[1, 0, 5] = np.nan  # a failed point
    rng = np.random.default_rng(0)
    cov = np.zeros(h.shape + (2, 2))
    cov[..., 0, 0] = rng.uniform(1e-4, 1e-3, h.shape) ** 2
    cov[..., 1, 1] = rng.uniform(1e-3, 1e-2, h.shape) ** 2
    cov[..., 0, 1] = cov[..., 1, 0] = 0.3 * np.sqrt(cov[..., 0, 0] * cov[..., 1, 1])
    frf = FrequencyResponse(OMEGA, h, cov=cov, input_labels=["x", "y"], output_labels=["spot0_x", "spot0_y"],
                            meta={"seed": 4, "output_unit": "px"})
    path = tmp_path / "frf.mat"
    frf.to_mat(path)
    m = scipy_io.loadmat(path)
    np.testing.assert_array_equal(m["freq_hz"], frf.freq_hz[None, :])
    np.testing.assert_array_equal(m["omega"], frf.omega[None, :])
    assert m["H"].shape == (2, 2, OMEGA.size) and np.iscomplexobj(m["H"])
    np.testing.assert_array_equal(m["H"], frf.response)
    np.testing.assert_array_equal(m["magnitude_std"], frf.magnitude_std)
    np.testing.assert_array_equal(m["phase_std"], frf.phase_std)
    np.testing.assert_allclose(m["correlation"][np.isfinite(h)], 0.3, rtol=1e-12)
    assert [str(c[0]) for c in m["input_labels"][0]] == ["x", "y"]
    assert [str(c[0]) for c in m["output_labels"][0]] == ["spot0_x", "spot0_y"]
    assert json.loads(str(m["meta"][0])) == {"seed": 4, "output_unit": "px"}


def test_to_mat_siso_keeps_three_axes(tmp_path):
    frf = FrequencyResponse(OMEGA, _plant(OMEGA))
    frf.to_mat(tmp_path / "siso.mat")
    m = scipy_io.loadmat(tmp_path / "siso.mat")
    assert m["H"].shape == (1, 1, OMEGA.size)
    assert np.all(np.isnan(m["magnitude_std"]))  # unknown covariance stays NaN
