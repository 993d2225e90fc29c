"""DM estimation (issue 17): demultiplexing, per-actuator dynamics, the batched spot fitter.
Synthetic cases only (small random G, analytic H_j, noise of known covariance)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from torchblur.dm.demux import demultiplex
from torchblur.errors import ParameterError, ShapeError


def _random_cov(rng, shape, scale=1e-2):
    """Random SPD 2x2 covariances ``shape + (2, 2)``."""
    a = rng.normal(size=shape + (2, 2)) * scale
    return a @ np.swapaxes(a, -1, -2) + np.eye(2) * scale**2 * 0.1


def _noise(rng, cov):
    L = np.linalg.cholesky(cov)
    z = np.einsum("...ab,...b->...a", L, rng.normal(size=cov.shape[:-1]))
    return z[..., 0] + 1j * z[..., 1]


def _measure(rng, D, patterns, cov_scale=1e-2):
    """Pattern responses ``Y [P, S, F]`` of ``D [S, N, F]`` with noise of random known covariance."""
    Y0 = np.einsum("pj,sjf->psf", patterns, D)
    cov = _random_cov(rng, Y0.shape, cov_scale)
    return Y0 + _noise(rng, cov), cov


def _hadamard(N):
    n = 1 << (N - 1).bit_length()
    return scipy.linalg.hadamard(n)[:, :N].astype(float)


def test_hadamard_equals_one_at_a_time_noise_free():
    rng = np.random.default_rng(0)
    S, N, F = 8, 9, 3
    D = rng.normal(size=(S, N, F)) + 1j * rng.normal(size=(S, N, F))
    cov_1 = _random_cov(rng, (N, S, F))
    D1, C1 = demultiplex(np.einsum("pj,sjf->psf", np.eye(N), D), cov_1, np.eye(N))
    H = _hadamard(N)
    cov_h = np.broadcast_to(np.eye(2) * 1e-4, (H.shape[0], S, F, 2, 2))
    Dh, Ch = demultiplex(np.einsum("pj,sjf->psf", H, D), cov_h, H)
    np.testing.assert_allclose(D1, D, atol=1e-12)
    np.testing.assert_allclose(Dh, D1, atol=1e-12)
    # one at a time: the covariance is the measured one; Hadamard: 1/P of it
    np.testing.assert_allclose(C1, np.moveaxis(cov_1, 0, 1), rtol=1e-10)
    np.testing.assert_allclose(Ch, np.broadcast_to(np.eye(2) * 1e-4 / H.shape[0], Ch.shape), rtol=1e-10)


def test_demux_covariance_holds_monte_carlo():
    rng = np.random.default_rng(1)
    N, F, T = 5, 2, 400  # T trials stacked as slope rows
    H = _hadamard(N)[:7]  # 7 of 8 rows: rank 5, unequal per-pattern covariances
    D = rng.normal(size=(1, N, F)) + 1j * rng.normal(size=(1, N, F))
    Dt = np.broadcast_to(D, (T, N, F))
    cov = np.broadcast_to(_random_cov(rng, (H.shape[0], 1, F)), (H.shape[0], T, F, 2, 2))
    Y = np.einsum("pj,sjf->psf", H, Dt) + _noise(rng, np.array(cov))
    De, Ce = demultiplex(Y, cov, H)
    err = De - Dt
    e = np.stack([err.real, err.imag], -1)
    L = np.linalg.cholesky(Ce)
    z = np.linalg.solve(L, e[..., None])[..., 0]
    assert 0.9 < float(np.mean(z**2)) < 1.1
    assert abs(float(np.mean(z))) < 0.05


def _sparse_patterns(support):
    """Greedy 0/1 patterns: actuators in one pattern share no slope row."""
    N = support.shape[1]
    conflict = (support.T.astype(int) @ support.astype(int)) > 0
    colour = -np.ones(N, dtype=int)
    for j in range(N):
        used = {colour[k] for k in range(N) if conflict[j, k] and colour[k] >= 0}
        colour[j] = next(c for c in range(N) if c not in used)
    return (colour[None, :] == np.arange(colour.max() + 1)[:, None]).astype(float)


def test_sparse_support_recovers_and_zeroes_off_support():
    rng = np.random.default_rng(2)
    N, S, F = 9, 12, 2
    xy = np.stack(np.meshgrid(np.arange(3), np.arange(3)), -1).reshape(-1, 2)
    sxy = rng.uniform(0, 2, size=(S, 2))
    support = np.linalg.norm(sxy[:, None] - xy[None], axis=-1) < 1.1
    support[~support.any(1), 0] = True
    D = (rng.normal(size=(S, N, F)) + 1j * rng.normal(size=(S, N, F))) * support[..., None]
    pats = _sparse_patterns(support)
    assert pats.shape[0] < N
    Y, cov = _measure(rng, D, pats, 1e-6)
    De, Ce = demultiplex(Y, cov, pats, support)
    np.testing.assert_allclose(De, D, atol=1e-4)
    assert np.all(De[~support] == 0) and np.all(Ce[~support] == 0)
    with pytest.raises(ParameterError, match="support"):
        demultiplex(Y, cov, pats, np.ones((S, N), dtype=bool))


def test_demux_failed_pattern_left_out_and_shapes_checked():
    rng = np.random.default_rng(3)
    N, S, F = 4, 3, 2
    H = _hadamard(N)
    D = rng.normal(size=(S, N, F)) + 0j
    Y, cov = _measure(rng, D, np.vstack([H, H]), 1e-8)
    Y[0, 1, 0] = np.nan  # a failed fit: that row still has 7 patterns
    De, _ = demultiplex(Y, cov, np.vstack([H, H]))
    np.testing.assert_allclose(De, D, atol=1e-6)
    Y2, cov2 = _measure(rng, D, H, 1e-8)
    Y2[0, 1, 0] = np.nan  # now row 1 at f=0 is underdetermined: NaN, the others fitted
    De2, _ = demultiplex(Y2, cov2, H)
    assert np.all(np.isnan(De2[1, :, 0])) and np.all(np.isfinite(De2[0]))
    with pytest.raises(ShapeError, match="Y_cov"):
        demultiplex(Y2, cov2[:, :, :1], H)
    with pytest.raises(ShapeError, match="patterns"):
        demultiplex(Y2, cov2, H[:3])


# ---- per-actuator dynamics ---------------------------------------------------------------

from torchblur.dm.actuator_fit import fit_actuators, second_order  # noqa: E402

_TRUE = dict(dc_gain=np.array([1.0, 0.97, 1.04, 0.0, 0.3, 1.0]), mode_hz=np.array([900.0, 1100.0, 1300.0, 1000.0, 1000.0, 750.0]),
             damping=np.array([0.08, 0.15, 0.05, 0.1, 0.1, 0.3]), delay_s=np.array([3e-5, 5e-5, 1e-5, 3e-5, 3e-5, 2e-5]))


def _actuator_case(rng, sigma=0.02, S=24, F=24):
    """G [S, N] random, D = G H_j with noise of a random known covariance (std ~ sigma px)."""
    N = _TRUE["dc_gain"].size
    f = np.geomspace(10.0, 2000.0, F)
    G = rng.normal(size=(S, N))
    H = second_order(f, **_TRUE)  # [N, F]
    cov = _random_cov(rng, (S, N, F), sigma)
    return f, G, G[:, :, None] * H[None], cov


def test_actuator_fit_recovers_within_std_monte_carlo():
    rng = np.random.default_rng(10)
    f, G, D, cov = _actuator_case(rng)
    z = {k: [] for k in _TRUE}
    for _ in range(60):
        t = fit_actuators(f, D + _noise(rng, cov), cov, G)
        assert t.status == ("ok", "ok", "ok", "dead", "weak", "ok")
        live = np.array([0, 1, 2, 4, 5])
        for k in _TRUE:
            z[k].append((getattr(t, k)[live] - _TRUE[k][live]) / getattr(t, k + "_std")[live])
    for k in _TRUE:
        rms = float(np.sqrt(np.mean(np.square(z[k]))))
        assert 0.7 < rms < 1.4, (k, rms)


def test_dead_and_weak_actuators_and_static_column():
    rng = np.random.default_rng(11)
    f, G, D, cov = _actuator_case(rng, sigma=0.005)
    t = fit_actuators(f, D + _noise(rng, cov), cov, G, actuator_xy=np.zeros((6, 2)))
    assert t.status[3] == "dead" and np.isnan(t.mode_hz[3]) and abs(t.dc_gain[3]) < 3 * t.dc_gain_std[3]
    assert t.status[4] == "weak"
    D0 = G * _TRUE["dc_gain"]
    err = (t.static_column - D0) / t.static_column_std
    assert 0.7 < float(np.sqrt(np.mean(err[:, [0, 1, 2, 5]] ** 2))) < 1.4
    assert np.sqrt(np.mean((t.static_column - D0) ** 2)) < 0.01 * np.abs(D0).max()
    np.testing.assert_allclose(t.mode_hz[[0, 1, 2, 5]], _TRUE["mode_hz"][[0, 1, 2, 5]], rtol=5e-3)


def test_wrong_model_is_flagged_poor_fit():
    rng = np.random.default_rng(12)
    f, G, D, cov = _actuator_case(rng, sigma=0.002)
    D = D.copy()
    D[:, 0] *= (1 + 0.5 * (f / 2000.0) ** 2)[None]  # not a second-order response
    t = fit_actuators(f, D + _noise(rng, cov), cov, G)
    assert t.poor_fit[0] and t.reduced_chi2[0] > 3
    assert not t.poor_fit[1]
