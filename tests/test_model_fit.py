"""Tests of torchblur.sysid.tf_fit: transfer-function fits of known plants (noise-free and noisy)."""
from __future__ import annotations

import json

import numpy as np
import pytest

control = pytest.importorskip("control")

from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import TransferFunctionFit, fit_transfer_function

TWO_PI = 2.0 * np.pi


def _pair(f_hz, zeta):
    wn = TWO_PI * f_hz
    p = wn * complex(-zeta, np.sqrt(1.0 - zeta * zeta))
    return [p, p.conjugate()]


def _zpk(omega, zeros, poles, dc_gain, delay_s=0.0):
    """K prod(s - z) / prod(s - p) exp(-s tau), K chosen for the given H(0)."""
    zeros, poles = np.asarray(zeros, complex), np.asarray(poles, complex)
    k = dc_gain * np.prod(-poles).real / np.prod(-zeros).real
    s = 1j * np.asarray(omega)[:, None]
    return k * np.prod(s - zeros, axis=1) / np.prod(s - poles, axis=1) * np.exp(-s[:, 0] * delay_s)


def _max_rel_root_error(found, true):
    """Match each true root to the nearest found one; max relative distance."""
    found = list(np.asarray(found, complex))
    assert len(found) == len(true)
    worst = 0.0
    for r in true:
        k = int(np.argmin([abs(f - r) for f in found]))
        worst = max(worst, abs(found.pop(k) - r) / abs(r))
    return worst


# second-order resonant plant of case (a)
WN, ZETA, GAIN, TAU = TWO_PI * 300.0, 0.05, 2.0, 50e-6
OMEGA_A = TWO_PI * np.logspace(0, 3, 40)


def _plant_a(omega):
    s = 1j * omega
    return GAIN * WN**2 / (s**2 + 2 * ZETA * WN * s + WN**2) * np.exp(-s * TAU)


# fourth-order plant of case (b): resonance 400 Hz, anti-resonance 250 Hz, real poles 800 Hz, 1.5 kHz
POLES_B = np.array(_pair(400.0, 0.03) + [-TWO_PI * 800.0, -TWO_PI * 1500.0])
ZEROS_B = np.array(_pair(250.0, 0.05))
OMEGA_B = TWO_PI * np.logspace(0, np.log10(2000.0), 60)


# ---------------------------------------------------------------------------- (a)
def test_second_order_with_delay_noise_free_order_selected():
    frf = FrequencyResponse(OMEGA_A, _plant_a(OMEGA_A))
    fit = fit_transfer_function(frf)  # orders and delay estimated, uniform weights (no cov)
    assert fit.weighting == "uniform" and fit.delay_estimated
    assert (fit.n_poles, fit.n_zeros) == (2, 0)
    (mode,) = fit.modal_parameters()
    assert mode["omega_n"] == pytest.approx(WN, rel=1e-6)
    assert mode["freq_hz"] == pytest.approx(300.0, rel=1e-6)
    assert mode["zeta"] == pytest.approx(ZETA, rel=1e-6)
    assert abs(fit.delay_s - TAU) < 1e-9
    assert fit.dc_gain == pytest.approx(GAIN, rel=1e-6)
    assert fit.den[0] == 1.0 and len(fit.den) == 3 and len(fit.num) == 1
    assert fit.rms_relative_error < 1e-9
    assert fit.dof == 2 * 40 - 4


# ---------------------------------------------------------------------------- (b)
def test_fourth_order_resonance_antiresonance_noise_free():
    frf = FrequencyResponse(OMEGA_B, _zpk(OMEGA_B, ZEROS_B, POLES_B, 3.0))
    fit = fit_transfer_function(frf, n_poles=4, n_zeros=2, delay_s=0.0)
    assert _max_rel_root_error(fit.poles, POLES_B) < 1e-5
    assert _max_rel_root_error(fit.zeros, ZEROS_B) < 1e-5
    assert fit.delay_s == 0.0 and not fit.delay_estimated
    (res,) = fit.modal_parameters()
    (anti,) = fit.modal_parameters("zeros")
    assert res["freq_hz"] == pytest.approx(400.0, rel=1e-5) and res["zeta"] == pytest.approx(0.03, rel=1e-5)
    assert anti["freq_hz"] == pytest.approx(250.0, rel=1e-5) and anti["zeta"] == pytest.approx(0.05, rel=1e-5)
    # order selection finds the true (4, 2)
    sel = fit_transfer_function(frf, delay_s=0.0)
    assert (sel.n_poles, sel.n_zeros) == (4, 2)
    assert _max_rel_root_error(sel.poles, POLES_B) < 1e-5


# ---------------------------------------------------------------------------- (c)
@pytest.fixture
def noisy_a():
    """Case (a) at 100 points with 1% complex Gaussian noise and its exact covariance."""
    rng = np.random.default_rng(20240611)
    omega = TWO_PI * np.logspace(0, 3, 100)
    h_true = _plant_a(omega)
    sigma = 0.01 * np.abs(h_true)  # E|dH|^2 = sigma^2, circular
    noise = sigma * (rng.standard_normal(omega.size) + 1j * rng.standard_normal(omega.size)) / np.sqrt(2)
    h = h_true + noise
    cov = np.zeros((omega.size, 2, 2))
    cov[:, 0, 0] = sigma**2 / 2  # radial part: var of |H|
    cov[:, 1, 1] = sigma**2 / 2 / np.abs(h) ** 2  # tangential part: var of the phase
    return FrequencyResponse(omega, h, cov=cov), h_true, sigma


def test_noisy_fit_is_statistically_consistent(noisy_a):
    frf, h_true, sigma = noisy_a
    fit = fit_transfer_function(frf, n_poles=2, n_zeros=0)
    assert fit.weighting == "uncertainty"
    assert fit.dof == 2 * 100 - 4
    # chi2 ~ chi-square(dof): reduced chi2 within 4 standard deviations of 1
    assert abs(fit.reduced_chi2 - 1.0) < 4.0 * np.sqrt(2.0 / fit.dof)
    h_fit = fit.frequency_response(frf.omega)
    assert np.all(np.abs(h_fit - h_true) < 3.0 * sigma)
    (mode,) = fit.modal_parameters()
    assert mode["omega_n"] == pytest.approx(WN, rel=5e-3)
    assert mode["zeta"] == pytest.approx(ZETA, rel=5e-2)
    assert abs(fit.delay_s - TAU) < 5e-6
    assert fit.rms_relative_error == pytest.approx(0.01, rel=0.3)


def test_noisy_order_selection_picks_true_order(noisy_a):
    frf, _, _ = noisy_a
    fit = fit_transfer_function(frf, max_order=4)
    assert (fit.n_poles, fit.n_zeros) == (2, 0)


def test_magnitude_only_points_enter_by_their_magnitude(noisy_a):
    """Points marked ``magnitude_only`` (a single exposure's undecided phase branch) count one
    observation each, their magnitude: the fit does not depend on the phase they carry, and
    still finds the resonance they cover."""
    frf, h_true, sigma = noisy_a
    mo = frf.freq_hz > 200.0  # the resonance (300 Hz) and everything above it: magnitude only
    fits = []
    for turn in (2.0, -1.0):  # two wrong phases at those points
        h = np.where(mo, frf.response[0, 0] * np.exp(1j * turn), frf.response[0, 0])
        fits.append(fit_transfer_function(frf.replace(response=h), n_poles=2, n_zeros=0, magnitude_only=mo))
    a, b = fits
    assert a.dof == 2 * 100 - int(mo.sum()) - 4
    np.testing.assert_allclose(a.params, b.params, rtol=1e-6)
    assert abs(a.reduced_chi2 - 1.0) < 4.0 * np.sqrt(2.0 / a.dof)
    (mode,) = a.modal_parameters()
    assert abs(mode["omega_n"] - WN) < 4 * mode["omega_n_std"] and abs(mode["zeta"] - ZETA) < 4 * mode["zeta_std"]
    # the model's phase at the magnitude-only points is the true one within its stds
    err = np.angle(a.frequency_response(frf.omega[mo]) / h_true[mo])
    assert np.all(np.abs(err) < 4 * a.phase_std(frf.omega[mo]))


def test_phase_std_holds_over_noise_draws():
    """The model's phase std (delta method over the parameters' covariance), inside the band and
    extrapolated past it, against the spread of the phase over 24 noise draws."""
    rng = np.random.default_rng(5)
    omega = OMEGA_A[::2]
    h_true = _plant_a(omega)
    sigma = 0.01 * np.abs(h_true)
    cov = np.zeros((omega.size, 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = sigma**2 / 2, 0.5e-4
    at = TWO_PI * np.array([10.0, 300.0, 1000.0, 2000.0])
    phases, stds = [], []
    for _ in range(24):
        noise = sigma * (rng.standard_normal(omega.size) + 1j * rng.standard_normal(omega.size)) / np.sqrt(2)
        fit = fit_transfer_function(FrequencyResponse(omega, h_true + noise, cov=cov), n_poles=2, n_zeros=0)
        phases.append(np.angle(fit.frequency_response(at) / _plant_a(at)))
        stds.append(fit.phase_std(at))
    ratio = np.std(phases, axis=0) / np.mean(stds, axis=0)
    assert np.all((ratio > 0.65) & (ratio < 1.4)), ratio  # 24 draws: the spread's own error is ~15 %
    assert np.isnan(TransferFunctionFit(**{**fit.__dict__, "covariance": np.full((5, 5), np.nan)}).phase_std(at)).all()


def test_nan_points_are_skipped(noisy_a):
    frf, _, _ = noisy_a
    h = np.array(frf.response[0, 0])
    h[[5, 50, 90]] = np.nan
    holed = FrequencyResponse(frf.omega, h, cov=frf.cov[0, 0])
    fit = fit_transfer_function(holed, n_poles=2, n_zeros=0)
    assert fit.dof == 2 * 97 - 4
    assert fit.modal_parameters()[0]["omega_n"] == pytest.approx(WN, rel=5e-3)


def test_array_weights_match_uncertainty_for_circular_noise(noisy_a):
    """For circular noise, weights 1 / (sigma / sqrt 2) are the same whitening as 'uncertainty'."""
    frf, _, sigma = noisy_a
    a = fit_transfer_function(frf, n_poles=2, n_zeros=0)
    b = fit_transfer_function(frf, n_poles=2, n_zeros=0, weights=np.sqrt(2.0) / sigma)
    assert b.weighting == "array"
    assert b.chi2 == pytest.approx(a.chi2, rel=1e-9)
    assert b.modal_parameters()[0]["omega_n"] == pytest.approx(a.modal_parameters()[0]["omega_n"], rel=1e-9)


# ---------------------------------------------------------------------------- (d)
def test_mimo_per_channel_fit():
    omega = TWO_PI * np.logspace(0, 3, 50)
    h = np.empty((2, 2, omega.size), dtype=complex)
    truth = {
        (0, 0): (_pair(300.0, 0.05), 2.0),
        (0, 1): (_pair(200.0, 0.1), -0.3),
        (1, 0): (_pair(350.0, 0.08), 0.2),
        (1, 1): (_pair(320.0, 0.04), 1.5),
    }
    for (o, i), (poles, k) in truth.items():
        h[o, i] = _zpk(omega, [], poles, k, delay_s=30e-6)
    frf = FrequencyResponse(omega, h, input_labels=["x", "y"], output_labels=["px", "py"])
    fit = fit_transfer_function(frf, n_poles=2, n_zeros=0, delay_s=30e-6)
    assert not fit.is_siso
    assert np.shape(fit.n_poles) == (2, 2) and len(fit.num) == 2 and len(fit.num[0]) == 2
    for (o, i), (poles, k) in truth.items():
        assert _max_rel_root_error(fit.poles[o][i], poles) < 1e-6
        assert fit.dc_gain[o][i] == pytest.approx(k, rel=1e-6)
        assert fit.delay_s[o][i] == 30e-6
    np.testing.assert_allclose(fit.frequency_response(omega), h, rtol=1e-8)
    sys = fit.to_control()
    assert isinstance(sys, control.TransferFunction)
    assert (sys.noutputs, sys.ninputs) == (2, 2)
    assert list(sys.input_labels) == ["x", "y"]
    np.testing.assert_allclose(
        sys(1j * omega[10]) * np.exp(-1j * omega[10] * 30e-6), h[:, :, 10], rtol=1e-8
    )
    modes = fit.modal_parameters()
    assert modes[0][1][0]["freq_hz"] == pytest.approx(200.0, rel=1e-6)


# ---------------------------------------------------------------------------- (e)
def test_to_control_times_delay_equals_frequency_response():
    frf = FrequencyResponse(OMEGA_B, _zpk(OMEGA_B, ZEROS_B, POLES_B, 3.0, delay_s=80e-6))
    fit = fit_transfer_function(frf, n_poles=4, n_zeros=2)
    assert abs(fit.delay_s - 80e-6) < 1e-9
    sys = fit.to_control()
    assert isinstance(sys, control.TransferFunction) and sys.isctime()
    w = TWO_PI * np.logspace(-1, 4, 77)  # also off the fitted grid
    h_ctrl = np.asarray(sys(1j * w)) * np.exp(-1j * w * fit.delay_s)
    np.testing.assert_allclose(fit.frequency_response(w), h_ctrl, rtol=1e-9)
    np.testing.assert_allclose(np.sort_complex(sys.poles()), np.sort_complex(fit.poles), rtol=1e-8)


# ---------------------------------------------------------------------------- misc
def test_to_dict_is_json_serialisable():
    frf = FrequencyResponse(OMEGA_A, _plant_a(OMEGA_A))
    fit = fit_transfer_function(frf, n_poles=2, n_zeros=0)
    doc = json.loads(json.dumps(fit.to_dict(), allow_nan=False))
    assert doc["schema"] == "torchblur.transfer_function_fit"
    assert doc["num"] == fit.num and doc["den"] == fit.den
    assert doc["delay_s"] == fit.delay_s and doc["n_poles"] == 2
    assert set(doc["poles"]) == {"real", "imag"} and len(doc["poles"]["real"]) == 2
    assert isinstance(fit, TransferFunctionFit)
    with pytest.raises(AttributeError):
        fit.delay_s = 0.0  # frozen


def test_stable_reflects_unstable_poles():
    """Data of an unstable resonance: stable=True returns its mirror image, stable=False the truth."""
    omega = TWO_PI * np.logspace(1, 3, 60)
    poles = [complex(+0.05, 1.0) * TWO_PI * 200.0, complex(+0.05, -1.0) * TWO_PI * 200.0]
    frf = FrequencyResponse(omega, _zpk(omega, [], poles, 1.0))
    free = fit_transfer_function(frf, n_poles=2, n_zeros=0, delay_s=0.0, stable=False)
    assert _max_rel_root_error(free.poles, poles) < 1e-8
    stab = fit_transfer_function(frf, n_poles=2, n_zeros=0, delay_s=0.0, stable=True)
    assert np.all(stab.poles.real <= 0)


def test_bad_arguments_raise():
    frf = FrequencyResponse(OMEGA_A, _plant_a(OMEGA_A))
    with pytest.raises(InputTypeError, match="^frf:"):
        fit_transfer_function(_plant_a(OMEGA_A))
    with pytest.raises(ParameterError, match="^n_zeros:"):
        fit_transfer_function(frf, n_poles=2, n_zeros=3)
    with pytest.raises(ParameterError, match="^n_poles:"):
        fit_transfer_function(frf, n_poles=-1)
    with pytest.raises(InputTypeError, match="^n_poles:"):
        fit_transfer_function(frf, n_poles=2.0)
    with pytest.raises(ParameterError, match="^delay_s:"):
        fit_transfer_function(frf, delay_s=-1e-3)
    with pytest.raises(ParameterError, match="^weights: must be one of"):
        fit_transfer_function(frf, weights="sigma")
    with pytest.raises(ShapeError, match="^weights:"):
        fit_transfer_function(frf, weights=np.ones(3))
    with pytest.raises(ParameterError, match="^weights:"):
        fit_transfer_function(frf, weights=-np.ones(40))
    with pytest.raises(ParameterError, match="^kind:"):
        fit_transfer_function(frf, n_poles=2, n_zeros=0).modal_parameters("modes")
    with pytest.raises(InputTypeError, match="^magnitude_only:"):
        fit_transfer_function(frf, magnitude_only=np.ones(40))
    with pytest.raises(ShapeError, match="^magnitude_only:"):
        fit_transfer_function(frf, magnitude_only=np.ones(3, dtype=bool))
    few = FrequencyResponse(OMEGA_A[:2], _plant_a(OMEGA_A[:2]))
    with pytest.raises(ParameterError, match="^n_poles:"):
        fit_transfer_function(few, n_poles=2, n_zeros=1)


def test_partially_known_cov_is_refused():
    cov = np.full((40, 2, 2), np.nan)
    cov[:10] = np.diag([1e-4, 1e-4])
    frf = FrequencyResponse(OMEGA_A, _plant_a(OMEGA_A), cov=cov)
    with pytest.raises(ParameterError, match="^weights:"):
        fit_transfer_function(frf, n_poles=2, n_zeros=0)
    fit = fit_transfer_function(frf, n_poles=2, n_zeros=0, weights="uniform")
    assert fit.weighting == "uniform"
