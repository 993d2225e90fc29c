"""Tests of torchblur.sysid.frequency_response.FrequencyResponse (pure numpy / python-control)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

control = pytest.importorskip("control")

from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.sysid.frequency_response import FrequencyResponse


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def _plant(omega):
    wn, zeta = 2 * np.pi * 300.0, 0.05
    s = 1j * omega
    return 2.0 * wn**2 / (s**2 + 2 * zeta * wn * s + wn**2) * np.exp(-s * 50e-6)


def _random_cov(rng, shape):
    """Random symmetric positive-definite (magnitude, phase) covariances of the given batch shape."""
    sm = rng.uniform(1e-3, 1e-1, shape)
    sp = rng.uniform(1e-3, 1e-1, shape)
    rho = rng.uniform(-0.9, 0.9, shape)
    cov = np.empty(shape + (2, 2))
    cov[..., 0, 0] = sm * sm
    cov[..., 1, 1] = sp * sp
    cov[..., 0, 1] = cov[..., 1, 0] = rho * sm * sp
    return cov


@pytest.fixture
def siso(rng):
    omega = 2 * np.pi * np.logspace(0, 3, 25)
    h = _plant(omega)
    h[7] = np.nan  # a failed point
    return FrequencyResponse(omega, h, cov=_random_cov(rng, (25,)), meta={"seed": 3, "note": "test"})


@pytest.fixture
def mimo(rng):
    omega = 2 * np.pi * np.logspace(0, 3, 12)
    h = rng.standard_normal((2, 2, 12)) + 1j * rng.standard_normal((2, 2, 12))
    h[1, 0, 3] = np.nan
    return FrequencyResponse(
        omega, h, cov=_random_cov(rng, (2, 2, 12)), input_labels=["x", "y"], output_labels=["px", "py"]
    )


# ---------------------------------------------------------------------------- layout
def test_siso_is_stored_as_1x1(siso):
    assert siso.response.shape == (1, 1, 25)
    assert siso.cov.shape == (1, 1, 25, 2, 2)
    assert siso.is_siso and siso.n_outputs == 1 and siso.n_inputs == 1
    assert siso.input_labels == ("u0",) and siso.output_labels == ("y0",)
    assert siso.valid.shape == (1, 1, 25)
    assert not siso.valid[0, 0, 7] and siso.valid.sum() == 24
    np.testing.assert_allclose(siso.freq_hz, np.logspace(0, 3, 25), rtol=1e-15)


def test_properties_match_definitions(siso):
    h = siso.response
    np.testing.assert_array_equal(siso.magnitude, np.abs(h))
    ok = siso.valid
    np.testing.assert_allclose(np.exp(1j * siso.phase[ok]), h[ok] / np.abs(h[ok]), rtol=0, atol=1e-15)
    assert np.all(siso.phase[ok] > -np.pi) and np.all(siso.phase[ok] <= np.pi)
    c = siso.cov
    np.testing.assert_array_equal(siso.magnitude_std, np.sqrt(c[..., 0, 0]))
    np.testing.assert_array_equal(siso.phase_std, np.sqrt(c[..., 1, 1]))
    np.testing.assert_allclose(siso.correlation, c[..., 0, 1] / np.sqrt(c[..., 0, 0] * c[..., 1, 1]), rtol=1e-15)


def test_phase_of_negative_real_is_plus_pi():
    # np.angle(-1 - 0j) is -pi; the wrapped phase must be +pi
    frf = FrequencyResponse([1.0, 2.0], np.array([complex(-1.0, -0.0), 1j]))
    assert frf.phase[0, 0, 0] == np.pi


def test_unwrapped_phase_is_continuous_and_skips_nan():
    omega = 2 * np.pi * np.logspace(1, 3.5, 60)
    s = 1j * omega
    h = 1.0 / (s / 300.0 + 1.0) ** 3 * np.exp(-s * 2e-4)  # phase falls well past -pi
    h[20] = np.nan
    frf = FrequencyResponse(omega, h)
    ph = frf.unwrapped_phase()[0, 0]
    assert np.isnan(ph[20])
    ok = ~np.isnan(ph)
    true = -3 * np.arctan(omega / 300.0) - omega * 2e-4
    np.testing.assert_allclose(ph[ok], true[ok], atol=1e-12)
    assert np.max(np.abs(np.diff(ph[ok]))) < np.pi


def test_response_std_is_the_linearised_covariance(rng):
    """Monte Carlo check of the (mag, phase) -> (Re, Im) linearisation for small noise."""
    h0 = 0.8 * np.exp(1j * 2.2)
    cov = np.array([[4e-6, 0.6 * 2e-3 * 3e-3], [0.6 * 2e-3 * 3e-3, 9e-6]])
    frf = FrequencyResponse([1.0], np.array([h0]), cov=cov[None])
    sr, si, corr = (x[0, 0, 0] for x in frf.response_std())
    draws = rng.multivariate_normal([abs(h0), np.angle(h0)], cov, size=200_000)
    hs = draws[:, 0] * np.exp(1j * draws[:, 1])
    emp = np.cov(np.stack([hs.real, hs.imag]))
    assert sr == pytest.approx(np.sqrt(emp[0, 0]), rel=1e-2)
    assert si == pytest.approx(np.sqrt(emp[1, 1]), rel=1e-2)
    assert corr == pytest.approx(emp[0, 1] / np.sqrt(emp[0, 0] * emp[1, 1]), abs=1e-2)
    # the total is var_mag + mag^2 var_phase whatever the correlation
    assert sr**2 + si**2 == pytest.approx(cov[0, 0] + abs(h0) ** 2 * cov[1, 1], rel=1e-12)


def test_unknown_cov_is_nan():
    frf = FrequencyResponse([1.0, 2.0], [1.0, 2.0])
    assert np.all(np.isnan(frf.cov))
    assert np.all(np.isnan(frf.magnitude_std)) and np.all(np.isnan(frf.response_std()[0]))


def test_arrays_are_read_only(siso):
    with pytest.raises(ValueError):
        siso.response[0, 0, 0] = 1.0
    with pytest.raises(ValueError):
        siso.omega[0] = 1.0


# ---------------------------------------------------------------------------- JSON
def _assert_bit_identical(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    fin = np.isfinite(a)
    np.testing.assert_array_equal(fin, np.isfinite(b))
    assert a[fin].tobytes() == b[fin].tobytes()


def test_json_round_trip_is_bit_exact(siso, tmp_path):
    path = tmp_path / "frf.json"
    siso.to_json(path)
    doc = json.loads(path.read_text())
    assert doc["schema"] == "torchblur.sysid.frequency_response" and doc["schema_version"] == 2
    assert doc["units"]["omega"] == "rad/s" and doc["units"]["phase"] == doc["units"]["phase_std"] == "rad"
    back = FrequencyResponse.from_json(path)
    _assert_bit_identical(back.omega, siso.omega)
    _assert_bit_identical(back.response.real, siso.response.real)
    _assert_bit_identical(back.response.imag, siso.response.imag)
    _assert_bit_identical(back.cov, siso.cov)
    np.testing.assert_array_equal(back.valid, siso.valid)
    assert back.meta == {"seed": 3, "note": "test"}
    assert back.input_labels == siso.input_labels and back.output_labels == siso.output_labels


def test_json_is_strict_json(siso, tmp_path):
    path = tmp_path / "frf.json"
    siso.to_json(path)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard constant {c}"))


def test_json_round_trip_mimo(mimo, tmp_path):
    path = tmp_path / "frf.json"
    mimo.to_json(path)
    back = FrequencyResponse.from_json(path)
    _assert_bit_identical(back.response.real, mimo.response.real)
    _assert_bit_identical(back.response.imag, mimo.response.imag)
    _assert_bit_identical(back.cov, mimo.cov)
    assert back.input_labels == ("x", "y") and back.output_labels == ("px", "py")


def test_json_unknown_schema_version_raises(siso, tmp_path):
    path = tmp_path / "frf.json"
    doc = siso.to_dict()
    doc["schema_version"] = 3
    path.write_text(json.dumps(doc))
    with pytest.raises(ParameterError, match=r"schema_version.*newer torchblur.*supported versions: \[1, 2\]"):
        FrequencyResponse.from_json(path)


def test_json_version_1_reads_without_units_and_refuses_other_units(siso):
    doc = siso.to_dict()
    old = {**{k: v for k, v in doc.items() if k != "units"}, "schema_version": 1}  # a file written before units
    assert FrequencyResponse.from_dict(old).to_dict() == doc
    with pytest.raises(ParameterError, match=r"unknown keys \['units'\] for schema_version 1"):
        FrequencyResponse.from_dict({**doc, "schema_version": 1})
    with pytest.raises(ParameterError, match="^units"):
        FrequencyResponse.from_dict({**doc, "units": {**doc["units"], "phase": "deg"}})


def test_json_unknown_key_raises(siso):
    doc = siso.to_dict()
    doc["colour"] = "red"
    with pytest.raises(ParameterError, match="colour"):
        FrequencyResponse.from_dict(doc)


# ---------------------------------------------------------------------------- CSV
def _rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    fin = np.isfinite(b)
    np.testing.assert_array_equal(np.isfinite(a), fin)
    return np.max(np.abs(a[fin] - b[fin]) / np.abs(b[fin]))


def test_csv_round_trip_siso(siso, tmp_path):
    path = tmp_path / "frf.csv"
    siso.to_csv(path)
    lines = path.read_text().splitlines()
    assert lines[0] == "freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg"
    assert not any(line.startswith("#") for line in lines)
    assert len(lines) == 1 + 25
    back = FrequencyResponse.from_csv(path)
    assert _rel_err(back.omega, siso.omega) <= 1e-15
    assert _rel_err(back.magnitude, siso.magnitude) <= 1e-15
    assert _rel_err(back.phase, siso.phase) <= 1e-15
    ok = siso.valid
    assert np.max(np.abs(back.response[ok] - siso.response[ok]) / np.abs(siso.response[ok])) <= 1e-15
    assert _rel_err(back.magnitude_std, siso.magnitude_std) <= 1e-15
    assert _rel_err(back.phase_std, siso.phase_std) <= 1e-15
    np.testing.assert_array_equal(back.valid, siso.valid)
    # documented loss: the correlation comes back as 0
    np.testing.assert_array_equal(back.correlation, 0.0)


def test_csv_phase_is_wrapped_and_minus_pi_written_as_180(tmp_path):
    omega = np.array([1.0, 2.0, 3.0, 4.0])
    h = np.array([complex(-2.0, -0.0), np.exp(-1j * (np.pi - 1e-16)), np.exp(1j * 3.0), 1j])
    frf = FrequencyResponse(omega, h)
    frf.to_csv(tmp_path / "p.csv")
    with open(tmp_path / "p.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    deg = np.array([float(r["phase_deg"]) for r in rows])
    assert rows[0]["phase_deg"] == "180.0"
    assert np.all(deg > -180.0) and np.all(deg <= 180.0)
    assert deg[3] == 90.0
    assert rows[0]["magnitude_std"] == "nan"


def test_csv_round_trip_mimo_has_output_input_columns(mimo, tmp_path):
    path = tmp_path / "frf.csv"
    mimo.to_csv(path)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["output", "input", "freq_hz", "magnitude", "phase_deg", "magnitude_std", "phase_std_deg"]
    assert len(rows) == 1 + 2 * 2 * 12
    assert [r[:2] for r in rows[1::12]] == [["px", "x"], ["px", "y"], ["py", "x"], ["py", "y"]]
    back = FrequencyResponse.from_csv(path)
    assert back.input_labels == ("x", "y") and back.output_labels == ("px", "py")
    assert back.response.shape == (2, 2, 12)
    np.testing.assert_array_equal(back.valid, mimo.valid)
    ok = mimo.valid
    assert np.max(np.abs(back.response[ok] - mimo.response[ok]) / np.abs(mimo.response[ok])) <= 1e-15
    assert _rel_err(back.magnitude_std, mimo.magnitude_std) <= 1e-15
    assert _rel_err(back.phase_std, mimo.phase_std) <= 1e-15


def test_csv_bad_header_raises(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("# comment\nfreq_hz,magnitude\n1,2\n")
    with pytest.raises(ParameterError, match="header"):
        FrequencyResponse.from_csv(path)


# ---------------------------------------------------------------------------- python-control
def test_to_control_siso_evaluates_to_the_data(siso):
    sys = siso.to_control()
    assert isinstance(sys, control.FrequencyResponseData)
    assert sys.ninputs == 1 and sys.noutputs == 1
    ok = siso.valid[0, 0]
    np.testing.assert_array_equal(sys.eval(siso.omega[ok]), siso.response[0, 0, ok])


def test_to_control_mimo_layout(mimo):
    sys = mimo.to_control()
    assert (sys.noutputs, sys.ninputs) == (2, 2)
    assert list(sys.input_labels) == ["x", "y"] and list(sys.output_labels) == ["px", "py"]
    k = 5
    np.testing.assert_array_equal(sys(1j * mimo.omega[k]), mimo.response[:, :, k])
    back = FrequencyResponse.from_control(sys)
    np.testing.assert_array_equal(back.response, mimo.response)
    assert back.input_labels == ("x", "y")


def test_to_control_smooth_interpolates():
    omega = 2 * np.pi * np.logspace(0, 3, 200)
    frf = FrequencyResponse(omega, _plant(omega))
    sys = frf.to_control(smooth=True)
    w = np.sqrt(omega[100] * omega[101])
    assert abs(sys.eval(w) - _plant(np.array([w]))[0]) < 1e-3 * abs(_plant(np.array([w]))[0])


def test_to_control_smooth_refuses_nan(siso):
    with pytest.raises(ParameterError, match="smooth"):
        siso.to_control(smooth=True)


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "omega, exc, name",
    [
        ([1.0, 3.0, 2.0], ParameterError, "omega"),  # not increasing
        ([1.0, 2.0, 2.0], ParameterError, "omega"),  # repeated
        ([-1.0, 2.0, 3.0], ParameterError, "omega"),  # negative
        ([0.0, 2.0, 3.0], ParameterError, "omega"),  # zero
        ([1.0, np.nan, 3.0], ParameterError, "omega"),
        ([[1.0, 2.0, 3.0]], ShapeError, "omega"),
        ("abc", InputTypeError, "omega"),
    ],
)
def test_bad_omega_raises(omega, exc, name):
    with pytest.raises(exc, match=f"^{name}:"):
        FrequencyResponse(omega, np.ones(3))


def test_response_shape_mismatch_raises():
    with pytest.raises(ShapeError, match="^response:"):
        FrequencyResponse([1.0, 2.0, 3.0], np.ones(4))
    with pytest.raises(ShapeError, match="^response:"):
        FrequencyResponse([1.0, 2.0, 3.0], np.ones((2, 2, 4)))
    with pytest.raises(ShapeError, match="^response:"):
        FrequencyResponse([1.0, 2.0, 3.0], np.ones((2, 3)))


def test_response_inf_raises():
    with pytest.raises(ParameterError, match="^response:"):
        FrequencyResponse([1.0, 2.0], [1.0, np.inf])


def test_bad_cov_raises(rng):
    w = [1.0, 2.0, 3.0]
    with pytest.raises(ShapeError, match=r"^cov: expected shape \[F, 2, 2\]"):
        FrequencyResponse(w, np.ones(3), cov=np.zeros((3, 2)))
    with pytest.raises(ShapeError, match=r"^cov: expected shape \[O, I, F, 2, 2\]"):
        FrequencyResponse(w, np.ones((2, 2, 3)), cov=np.zeros((3, 2, 2)))
    bad = np.zeros((3, 2, 2))
    bad[0, 0, 1] = 1e-3
    with pytest.raises(ParameterError, match="^cov: expected symmetric"):
        FrequencyResponse(w, np.ones(3), cov=bad)
    neg = np.zeros((3, 2, 2))
    neg[1, 0, 0] = -1.0
    with pytest.raises(ParameterError, match="^cov: expected variances >= 0"):
        FrequencyResponse(w, np.ones(3), cov=neg)
    with pytest.raises(InputTypeError, match="^cov:"):
        FrequencyResponse(w, np.ones(3), cov=np.zeros((3, 2, 2), dtype=complex))


def test_bad_labels_and_meta_raise():
    w = [1.0, 2.0]
    with pytest.raises(ShapeError, match="^input_labels:"):
        FrequencyResponse(w, np.ones((1, 2, 2)), input_labels=["x"])
    with pytest.raises(ParameterError, match="^output_labels:"):
        FrequencyResponse(w, np.ones((2, 1, 2)), output_labels=["a", "a"])
    with pytest.raises(InputTypeError, match="^input_labels:"):
        FrequencyResponse(w, np.ones((1, 2, 2)), input_labels="xy")
    with pytest.raises(InputTypeError, match="^meta:"):
        FrequencyResponse(w, np.ones(2), meta={"x": object()})
    with pytest.raises(InputTypeError, match="^meta:"):
        FrequencyResponse(w, np.ones(2), meta={"x": float("nan")})


def test_errors_are_builtin_subclasses():
    with pytest.raises(ValueError):
        FrequencyResponse([2.0, 1.0], [1.0, 1.0])
    with pytest.raises(TypeError):
        FrequencyResponse([1.0, 2.0], ["a", "b"])


def test_repr_is_short(siso):
    r = repr(siso)
    assert r.startswith("FrequencyResponse(1x1, 25 points") and "1 invalid" in r and len(r) < 100


# ---------------------------------------------------------------------------- per-point flags
from torchblur.sysid.flags import FAILED, LIMITED, POOR_FIT, TIMING, flag_names, parse_flags  # noqa: E402


@pytest.fixture
def flagged(rng):
    """A 2x2 response with flags and reduced chi2 at some points (NaN chi2 at others)."""
    omega = 2 * np.pi * np.logspace(0, 3, 6)
    h = rng.standard_normal((2, 2, 6)) + 1j * rng.standard_normal((2, 2, 6))
    h[0, 1, 2] = np.nan
    flags = np.zeros((2, 2, 6), dtype=np.int64)
    flags[0, 0, 1] = POOR_FIT
    flags[1, 1, 5] = POOR_FIT | TIMING | LIMITED
    flags[0, 1, 2] = FAILED
    chi2 = rng.uniform(0.8, 3.0, (2, 2, 6))
    chi2[0, 1, 2] = np.nan
    return FrequencyResponse(omega, h, cov=_random_cov(rng, (2, 2, 6)), input_labels=["x", "y"], output_labels=["px", "py"],
                             flags=flags, reduced_chi2=chi2)


def test_flags_default_to_zero_and_chi2_to_nan(siso):
    assert siso.flags.shape == (1, 1, 25) and siso.flags.dtype == np.int64 and not siso.flags.any()
    assert np.isnan(siso.reduced_chi2).all() and not siso.has_adequacy
    with pytest.raises(ValueError):
        siso.flags[0, 0, 0] = 1  # read-only


def test_flag_names_round_trip():
    assert flag_names(0) == "" and parse_flags("") == 0
    assert flag_names(POOR_FIT | TIMING) == "poor_fit|timing"
    for mask in range(16):
        assert parse_flags(flag_names(mask)) == mask
    assert parse_flags(flag_names(64 | FAILED)) == 64 | FAILED  # an unknown bit survives as bit6
    with pytest.raises(ParameterError, match="unknown flag 'bogus'"):
        parse_flags("poor_fit|bogus")


@pytest.mark.parametrize("kw, exc", [
    ({"flags": np.zeros(5, dtype=int)}, ShapeError),
    ({"flags": np.zeros(3)}, InputTypeError),  # floats are not bit masks
    ({"flags": np.array([0, -1, 0])}, ParameterError),
    ({"reduced_chi2": np.array([1.0, -1.0, 1.0])}, ParameterError),
    ({"reduced_chi2": np.array([1.0, np.inf, 1.0])}, ParameterError),
    ({"reduced_chi2": np.zeros((1, 1, 2))}, ShapeError),
])
def test_bad_flags_and_chi2_are_refused(kw, exc):
    with pytest.raises(exc, match=next(iter(kw))):
        FrequencyResponse([1.0, 2.0, 3.0], [1.0, 1.0, 1.0], **kw)


def test_flags_round_trip_through_json(flagged, tmp_path):
    flagged.to_json(tmp_path / "frf.json")
    back = FrequencyResponse.from_json(tmp_path / "frf.json")
    np.testing.assert_array_equal(back.flags, flagged.flags)
    np.testing.assert_array_equal(back.reduced_chi2, flagged.reduced_chi2)  # NaN where unknown, bit-exact elsewhere


def test_flags_round_trip_through_csv(flagged, tmp_path):
    path = tmp_path / "frf.csv"
    flagged.to_csv(path, extra_columns={"seed": 3})
    rows = list(csv.reader(path.open()))
    assert rows[0] == ["output", "input", "freq_hz", "magnitude", "phase_deg", "magnitude_std", "phase_std_deg",
                       "reduced_chi2", "flags", "seed"]
    by_freq = {(r[0], r[1], float(r[2])): r[8] for r in rows[1:]}
    assert by_freq[("py", "y", float(flagged.freq_hz[5]))] == "poor_fit|timing|limited"
    assert by_freq[("px", "x", float(flagged.freq_hz[0]))] == ""
    back = FrequencyResponse.from_csv(path)
    np.testing.assert_array_equal(back.flags, flagged.flags)
    np.testing.assert_array_equal(back.reduced_chi2, flagged.reduced_chi2)


def test_flags_in_the_mat_file(flagged, tmp_path):
    import scipy.io

    flagged.to_mat(tmp_path / "frf.mat")
    mat = scipy.io.loadmat(tmp_path / "frf.mat")
    np.testing.assert_array_equal(mat["flags"], flagged.flags)
    np.testing.assert_array_equal(mat["reduced_chi2"], flagged.reduced_chi2)


def test_old_files_load_with_no_flags(siso, tmp_path):
    doc = siso.to_dict()
    assert "flags" not in doc and "reduced_chi2" not in doc  # a response without them writes the old schema
    back = FrequencyResponse.from_dict(doc)
    assert not back.flags.any() and np.isnan(back.reduced_chi2).all()
    siso.to_csv(tmp_path / "old.csv")
    back = FrequencyResponse.from_csv(tmp_path / "old.csv")
    assert not back.flags.any() and np.isnan(back.reduced_chi2).all()


def test_replace_and_select_outputs_keep_the_flags(flagged):
    meta = flagged.replace(meta={"a": 1})
    assert meta.meta == {"a": 1}
    np.testing.assert_array_equal(meta.flags, flagged.flags)
    np.testing.assert_array_equal(meta.reduced_chi2, flagged.reduced_chi2)
    one = flagged.select_outputs([False, True])
    assert one.output_labels == ("py",) and one.response.shape == (1, 2, 6)
    np.testing.assert_array_equal(one.flags, flagged.flags[1:])
    np.testing.assert_array_equal(one.reduced_chi2, flagged.reduced_chi2[1:])
    np.testing.assert_array_equal(one.cov, flagged.cov[1:])
    with pytest.raises(ParameterError, match="changes"):
        flagged.replace(colour="red")
    with pytest.raises(ShapeError, match="keep"):
        flagged.select_outputs([True])


@pytest.mark.parametrize("flags, exc", [
    ([[[1.0, 0, 0]]], InputTypeError),  # floats are not bit masks
    ([[[None, 0, 0]]], InputTypeError),
    ([[[2**70, 0, 0]]], InputTypeError),
    ([[[-2, 0, 0]]], ParameterError),
    ([[[1, 0]]], ShapeError),
])
def test_untrusted_flags_in_json_are_refused_with_the_path(tmp_path, flags, exc):
    doc = FrequencyResponse([1.0, 2.0, 3.0], [1.0, 1.0, 1.0]).to_dict()
    doc["flags"] = flags
    path = tmp_path / "frf.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(exc, match="frf.json.*flags"):
        FrequencyResponse.from_json(path)


def test_unknown_flag_names_in_csv_are_refused_with_the_path(tmp_path):
    path = tmp_path / "frf.csv"
    path.write_text("freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg,reduced_chi2,flags\n1,1,0,0.1,1,1.0,poor_fit|odd\n")
    with pytest.raises(ParameterError, match="frf.csv.*unknown flag 'odd'"):
        FrequencyResponse.from_csv(path)


def test_mat_round_trip_mimo(mimo, tmp_path):
    """frf.mat reads back: response, labels, meta, flags exactly; the covariance (rebuilt from
    the stds and the correlation) to round-off; its units say radians."""
    import scipy.io

    path = tmp_path / "frf.mat"
    mimo.to_mat(path)
    back = FrequencyResponse.from_mat(path)
    _assert_bit_identical(back.response.real, mimo.response.real)
    _assert_bit_identical(back.omega, mimo.omega)
    np.testing.assert_allclose(back.cov, mimo.cov, rtol=1e-12, atol=1e-15 * np.nanmax(np.abs(mimo.cov)))
    assert back.input_labels == mimo.input_labels and back.output_labels == mimo.output_labels and back.meta == mimo.meta
    np.testing.assert_array_equal(back.flags, mimo.flags)
    units = scipy.io.loadmat(path)["units"]
    assert str(units["phase_std"][0, 0][0]) == "rad" and str(units["omega"][0, 0][0]) == "rad/s"
    (tmp_path / "bad.mat").write_text("not a mat file")
    with pytest.raises(ParameterError, match="bad.mat"):
        FrequencyResponse.from_mat(tmp_path / "bad.mat")
