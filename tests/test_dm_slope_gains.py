"""The slope rows' own gains (torchblur.dm.slope_gains): measured from D0, and the DC gains' stds that hold with them."""
import numpy as np
import pytest

from torchblur.dm.actuator_fit import fit_actuators
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.registration import fully_lit, register_and_refit
from torchblur.dm.shack_hartmann import ShackHartmann
from torchblur.dm.slope_gains import random_effects_scatter, slope_gains, slope_gains_line, with_slope_gain_stds
from torchblur.errors import ShapeError


def test_random_effects_scatter_recovers_the_spread_beyond_the_noise():
    rng = np.random.default_rng(0)
    k = 4000
    std = rng.uniform(0.5e-3, 2e-3, k)
    for tau in (0.0, 1e-3):
        g = 1 + tau * rng.standard_normal(k) + std * rng.standard_normal(k)
        mean, t, qd = random_effects_scatter(g, std)
        assert abs(mean - 1) < 1e-4
        if tau:
            assert abs(t / tau - 1) < 0.1, t  # ~0.03 sampling error at k = 4000
        else:
            assert t < 2e-4 and abs(qd - 1) < 0.1, (t, qd)
    assert np.isnan(random_effects_scatter([1.0], [1e-3])[1])


def _run(seed, row_sd, f=np.geomspace(50.0, 2000.0, 10)):
    """A 12-actuator mirror on 21 subapertures, every slope row scaled by its own gain at every frequency
    (``row_sd``), D(jw) with 1e-3 noise; the run's stage 4 (actuators, registration, refit, row gains)."""
    mirror = DeformableMirror.build(4, coupling=0.15, mode_hz=800.0, mode_spread=0.05, gain_spread=0.05, dead=[3], seed=1)
    wfs = ShackHartmann(n_across=5, pupil_diameter=4.0, oversample=8)
    rng = np.random.default_rng(seed)
    G = wfs.geometry_matrix(mirror)
    row = 1 + row_sd * rng.standard_normal(G.shape[0])
    D_true = (row[:, None] * G)[:, :, None] * mirror.response(f)[None]
    s = 1e-3 * np.abs(G).max()
    D = D_true + s * (rng.standard_normal(D_true.shape) + 1j * rng.standard_normal(D_true.shape))
    cov = np.broadcast_to(s * s * np.eye(2), D.shape + (2, 2)).copy()
    table = fit_actuators(f, D, cov, G, actuator_xy=mirror.actuator_xy)
    table, fit, _ = register_and_refit(f, D, cov, table, wfs, mirror.actuator_xy, 0.15)
    gains = slope_gains(table.static_column, table.static_column_std, fit.G, table.dc_gain, np.tile(fully_lit(wfs), 2))
    return mirror, table, with_slope_gain_stds(table, gains), gains


def test_dc_gain_stds_hold_with_the_slopes_own_gains():
    """Rows scaled by 0.5 % each (the size measured on HCIPy's lenslet frames): the DC gains' errors are many of
    their stds from the frequencies alone, and about one with the rows' scatter measured from D0 and added."""
    z0, z1, taus = [], [], []
    for seed in range(8):
        mirror, before, after, gains = _run(seed, 5e-3)
        live = ~mirror.dead
        z0.append((before.dc_gain - mirror.gain)[live] / before.dc_gain_std[live])
        z1.append((after.dc_gain - mirror.gain)[live] / after.dc_gain_std[live])
        taus.append(gains.tau["lit"])
        np.testing.assert_array_equal(after.mode_hz, before.mode_hz)  # a gain common to every frequency moves no mode
        assert after.status == before.status
    rms0, rms1 = np.sqrt(np.mean(np.square(z0))), np.sqrt(np.mean(np.square(z1)))
    assert rms0 > 2.0, rms0
    assert 0.7 < rms1 < 1.3, rms1
    assert 1e-3 < np.median(taus) < 8e-3, taus  # part of the rows' scatter is absorbed by the actuators' own gains


def test_no_row_gains_leaves_the_stds():
    mirror, before, after, gains = _run(11, 0.0)
    assert gains.q_over_dof["lit"] < 1.5 and gains.tau["lit"] < 2e-4
    live = ~mirror.dead
    assert np.all(after.dc_gain_std[live] / before.dc_gain_std[live] < 1.1)
    assert "dm slope gains" in slope_gains_line(gains)


def test_bad_shapes_are_refused():
    with pytest.raises(ShapeError, match="D0, D0_std, G"):
        slope_gains(np.ones((4, 3)), np.ones((4, 3)), np.ones((4, 2)), np.ones(3), np.ones(4, bool))
