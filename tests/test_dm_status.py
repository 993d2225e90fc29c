"""Dead and weak decided so that crosstalk cannot make a dead actuator weak (issue 23): the rule
of torchblur.dm.actuator_fit.actuator_status against the model's own errors."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from torchblur.dm.actuator_fit import (DEAD_FRACTION, WEAK_FRACTION, actuator_status, fit_actuators, second_order,
                                       with_dc_gain_variance)
from torchblur.dm.registration import with_registration_stds
from torchblur.dm.slope_gains import SlopeGains, with_slope_gain_stds
from torchblur.errors import ShapeError

TRUE = dict(dc_gain=np.array([1.0, 0.97, 1.04, 0.0, 0.35, 1.0]), mode_hz=np.array([900.0, 1100.0, 1300.0, 1000.0, 1000.0, 750.0]),
            damping=np.array([0.08, 0.15, 0.05, 0.1, 0.1, 0.3]), delay_s=np.array([3e-5, 5e-5, 1e-5, 3e-5, 3e-5, 2e-5]))


def _case(seed, crosstalk, sigma=0.002, S=24, F=20):
    """D = G H_j plus noise; the dead actuator 3's column holds ``crosstalk`` of actuator 0's
    response, distorted (not a second-order shape) and spread on other slopes: what a spot model's
    error leaves in a dead column through the demultiplexing."""
    rng = np.random.default_rng(seed)
    f = np.geomspace(10.0, 2000.0, F)
    G = rng.normal(size=(S, 6))
    D = G[:, :, None] * second_order(f, **TRUE)[None]
    leak = crosstalk * (0.5 * G[:, 3] + rng.normal(size=S))[:, None] * second_order(f, 1.0, 900.0, 0.08, 3e-5) * (1 + (f / 1000.0) ** 2)
    D[:, 3] = leak
    cov = np.broadcast_to(np.eye(2) * sigma**2, D.shape + (2, 2)).copy()
    noise = sigma * (rng.normal(size=D.shape) + 1j * rng.normal(size=D.shape))
    return f, G, D + noise, cov


def test_crosstalk_in_a_dead_column_is_dead_not_weak():
    for seed in range(2):
        f, G, D, cov = _case(seed, crosstalk=0.04)
        t = fit_actuators(f, D, cov, G)
        # the crosstalk is far above the noise: the column is no zero, its gain many stds from 0
        assert abs(t.dc_gain[3]) > 3 * t.dc_gain_std[3]
        assert t.status == ("ok", "ok", "ok", "dead", "weak", "ok"), (seed, t.status, t.dc_gain, t.dc_gain_std)


def test_status_rule_bounds_and_significance():
    g = np.array([1.0, 1.0, 1.1, 0.05, 0.3, 0.45, 1.0, 1.0])  # the median of the responding gains: 1.0
    no, s = np.zeros(8, dtype=bool), np.full(8, 0.01)
    assert actuator_status(g, s, no) == ("ok", "ok", "ok", "dead", "weak", "weak", "ok", "ok")
    s2 = s.copy()
    s2[4] = 0.1  # 0.3 +- 0.1: not significantly above DEAD_FRACTION (0.1): cannot be told from a dead one
    assert actuator_status(g, s2, no)[4] == "dead"
    s2[5] = 0.05  # 0.45 +- 0.05: not significantly below WEAK_FRACTION (0.5): ok
    assert actuator_status(g, s2, no)[5] == "ok"
    assert actuator_status(g, s, np.array([0, 0, 0, 0, 0, 1, 0, 0], dtype=bool))[5] == "dead"
    g2 = g.copy()
    g2[3] = np.nan
    assert actuator_status(g2, s, no)[3] == "dead"
    assert 0 < DEAD_FRACTION < WEAK_FRACTION < 1


def test_grown_stds_decide_the_statuses_they_are_reported_with():
    """The registration's share and the slope rows' gains grow dc_gain_std after the fit: the
    statuses follow the grown std (an ok actuator whose gain is no longer significantly above 0.1
    of ref is dead, a weak one no longer significantly below 0.5 is ok), against the same ref."""
    f, G, D, cov = _case(0, crosstalk=0.04)
    t = fit_actuators(f, D, cov, G)
    assert t.status == ("ok", "ok", "ok", "dead", "weak", "ok")
    assert 0.9 < t.status_reference < 1.1  # the median of the responding actuators' gains (fitted before 3 was found dead)
    # actuator 1 (0.97) +- ~0.39: not 3 stds above 0.1 -> dead; 4 (0.35) +- ~0.07: not 3 stds below 0.5 -> ok
    share = np.array([0.0, 0.4, 0.0, 5.0, 0.2, 0.0])
    gains = SlopeGains(gain=np.ones(24), gain_std=np.ones(24), lit=np.ones(24, bool), tau={}, q_over_dof={}, n_rows={},
                       dc_gain_share=share)
    var = (t.dc_gain * share) ** 2
    reg = SimpleNamespace(ok=True, gain_var_registration=var)  # what with_registration_stds reads of a RegistrationFit
    for grown in (with_slope_gain_stds(t, gains), with_registration_stds(t, reg), with_dc_gain_variance(t, var)):
        np.testing.assert_allclose(grown.dc_gain_std, np.sqrt(t.dc_gain_std**2 + var), rtol=1e-12)
        assert grown.status == ("ok", "dead", "ok", "dead", "ok", "ok"), grown.status
        assert grown.status == actuator_status(grown.dc_gain, grown.dc_gain_std, [s == "dead" for s in t.status], ref=t.status_reference)
    assert with_dc_gain_variance(t, np.zeros(6)).status == t.status
    assert with_dc_gain_variance(replace(t, status_reference=float("nan")), np.zeros(6)).status == t.status  # none kept: the live median
    assert with_registration_stds(t, SimpleNamespace(ok=False, gain_var_registration=var)) is t
    # the reference is the fit's (the dead actuator's gain as measured against the median shape does not move it)
    assert with_dc_gain_variance(replace(t, dc_gain=t.dc_gain * [1, 1, 1, 50, 1, 1]), var).status[0] == "ok"
    with pytest.raises(ShapeError, match="var"):
        with_dc_gain_variance(t, np.zeros(5))
