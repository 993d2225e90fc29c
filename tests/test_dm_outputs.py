"""DM outputs (issue 17): OUT/dm/ files from a DMEstimate, read back by numpy, astropy and python-control."""
from __future__ import annotations

import csv
import json
import sys

import numpy as np
import pytest

from torchblur.dm.actuator_fit import fit_actuators, second_order
from torchblur.identify.dm_outputs import CSV_COLUMNS, DMEstimate, command_matrix, magnitude_phase_cov, write_dm_outputs
from torchblur.errors import ParameterError
from torchblur.identify.record import collect_log
from torchblur.sysid.frequency_response import FrequencyResponse


def _estimate(seed=0):
    """9 actuators (3x3), 4x4 subapertures (2M = 32), actuator 4 dead, noise of known covariance."""
    rng = np.random.default_rng(seed)
    N, S = 9, 32
    f = np.geomspace(10.0, 2000.0, 16)
    xy = np.stack(np.meshgrid(np.arange(3) - 1.0, np.arange(3) - 1.0), -1).reshape(-1, 2)
    G = rng.normal(size=(S, N))
    gain = np.ones(N)
    gain[4] = 0.0
    H = second_order(f, gain, rng.uniform(800, 1200, N), rng.uniform(0.05, 0.2, N), np.full(N, 3e-5))
    D = G[:, :, None] * H[None]
    cov = np.broadcast_to(np.eye(2) * 1e-5, D.shape + (2, 2)).copy()
    noise = rng.normal(size=D.shape + (2,)) * np.sqrt(1e-5)
    D = D + noise[..., 0] + 1j * noise[..., 1]
    table = fit_actuators(f, D, cov, G, actuator_xy=xy)
    return DMEstimate(freq_hz=f, D=D, D_cov=cov, table=table, meta={"plan": "hadamard", "seed": seed}), G


def test_write_outputs_read_back(tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt

    est, G = _estimate()
    backend, open_before = matplotlib.get_backend(), plt.get_fignums()
    paths = write_dm_outputs(tmp_path, est)
    assert matplotlib.get_backend() == backend and plt.get_fignums() == open_before  # actuator_maps.png: no backend switch
    d = tmp_path / "dm"
    for name in ("actuators.csv", "interaction_matrix.npy", "interaction_matrix.fits", "command_matrix.npy", "unseen_modes.npy",
                 "command_matrix.json", "frf.json", "actuator_maps.png"):
        assert (d / name).is_file() and paths[name] == d / name
    rows = list(csv.reader(open(d / "actuators.csv")))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 10
    assert rows[1 + 4][CSV_COLUMNS.index("status")] == "dead" and rows[1][CSV_COLUMNS.index("status")] == "ok"
    np.testing.assert_allclose(float(rows[1][CSV_COLUMNS.index("mode_hz")]), est.table.mode_hz[0], rtol=1e-8)
    D0 = np.load(d / "interaction_matrix.npy")
    assert D0.shape == (32, 9)
    from astropy.io import fits
    np.testing.assert_array_equal(fits.getdata(d / "interaction_matrix.fits"), D0)
    C = np.load(d / "command_matrix.npy")
    assert C.shape == (9, 32) and np.load(d / "unseen_modes.npy").shape[1] == 9
    info = json.loads((d / "command_matrix.json").read_text())
    assert info["n_kept"] == 8 and info["rcond"] == 0.05  # the dead actuator is the unseen mode


def test_frf_json_is_a_control_frd(tmp_path):
    import control

    est, _ = _estimate()
    write_dm_outputs(tmp_path, est)
    frf = FrequencyResponse.from_json(tmp_path / "dm" / "frf.json")
    assert (frf.n_outputs, frf.n_inputs) == (32, 9)
    assert frf.output_labels[0] == "s0_x" and frf.output_labels[16] == "s0_y" and frf.input_labels[3] == "a3"
    sys_frd = control.frd(frf.response, frf.omega)
    assert (sys_frd.noutputs, sys_frd.ninputs) == (32, 9)
    np.testing.assert_allclose(sys_frd.frdata, est.D, rtol=1e-12)
    named = frf.to_control()
    np.testing.assert_allclose(named.frdata, est.D, rtol=1e-12)
    live = np.isfinite(frf.cov).all((-1, -2))
    assert live.mean() > 0.99 and frf.meta["plan"] == "hadamard"


def test_outputs_without_astropy_log_and_skip(tmp_path, monkeypatch):
    est, _ = _estimate()
    monkeypatch.setitem(sys.modules, "astropy", None)
    monkeypatch.setitem(sys.modules, "astropy.io", None)
    with collect_log() as lines:  # the run's log lines
        paths = write_dm_outputs(tmp_path, est)
    assert "interaction_matrix.fits" not in paths and not (tmp_path / "dm" / "interaction_matrix.fits").exists()
    assert any("astropy" in s and "skipped" in s for s in lines)


def test_command_matrix_rule():
    rng = np.random.default_rng(3)
    D0 = rng.normal(size=(12, 6))
    D0[:, 2] = 0.0  # an actuator the sensor does not see
    C, unseen, info = command_matrix(D0, rcond=0.05)
    assert info["n_kept"] == 5 and unseen.shape == (1, 6)
    np.testing.assert_allclose(np.abs(unseen[0]), np.eye(6)[2], atol=1e-12)
    keep = np.eye(6) - unseen.T @ unseen
    np.testing.assert_allclose(C @ D0, keep, atol=1e-10)
    wide = rng.normal(size=(4, 6))  # N > 2M: a 2-D null space
    _, unseen_w, info_w = command_matrix(wide)
    assert info_w["n_kept"] == 4 and unseen_w.shape == (2, 6)
    np.testing.assert_allclose(wide @ unseen_w.T, 0, atol=1e-12)
    with pytest.raises(ParameterError, match="rcond"):
        command_matrix(D0, rcond=0.0)
    with pytest.raises(ParameterError, match="D0"):
        command_matrix(np.full((2, 2), np.nan))


def test_magnitude_phase_cov_formula():
    z = np.array([3 + 4j, 0j])
    cov = np.broadcast_to(np.diag([0.01, 0.04]), (2, 2, 2))
    out = magnitude_phase_cov(z, cov)
    # |z| = 5: var|z| = (9 * 0.01 + 16 * 0.04) / 25, var phase = (16 * 0.01 + 9 * 0.04) / 625, cov = 12 (0.04 - 0.01) / 125
    np.testing.assert_allclose(out[0], [[0.73 / 25, 0.36 / 125], [0.36 / 125, 0.52 / 625]], rtol=1e-12)
    assert np.all(np.isnan(out[1]))
