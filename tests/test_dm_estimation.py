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


@pytest.mark.parametrize("method", ["wls", "ols"])
def test_demux_covariance_holds_monte_carlo(method):
    rng = np.random.default_rng(1)
    N, F, T = 5, 2, 400  # T trials stacked as slope rows
    H = _hadamard(N)[:7]  # 7 of 8 rows: rank 5, unequal per-pattern covariances
    D = rng.normal(size=(1, N, F)) + 1j * rng.normal(size=(1, N, F))
    Dt = np.broadcast_to(D, (T, N, F))
    cov = np.broadcast_to(_random_cov(rng, (H.shape[0], 1, F)), (H.shape[0], T, F, 2, 2))
    Y = np.einsum("pj,sjf->psf", H, Dt) + _noise(rng, np.array(cov))
    De, Ce = demultiplex(Y, cov, H, method=method)
    err = De - Dt
    e = np.stack([err.real, err.imag], -1)
    L = np.linalg.cholesky(Ce)
    z = np.linalg.solve(L, e[..., None])[..., 0]
    assert 0.9 < float(np.mean(z**2)) < 1.1
    assert abs(float(np.mean(z))) < 0.05


def test_ols_equals_wls_for_equal_covariances_and_falls_back_on_a_failed_fit():
    rng = np.random.default_rng(4)
    N, S, F = 6, 5, 3
    H = _hadamard(N)
    D = rng.normal(size=(S, N, F)) + 1j * rng.normal(size=(S, N, F))
    cov = np.broadcast_to(_random_cov(rng, (1, S, F)), (H.shape[0], S, F, 2, 2))
    Y = np.einsum("pj,sjf->psf", H, D) + _noise(rng, np.array(cov))
    Dw, Cw = demultiplex(Y, cov, H, method="wls")
    Do, Co = demultiplex(Y, cov, H, method="ols")
    np.testing.assert_allclose(Do, Dw, atol=1e-12)
    np.testing.assert_allclose(Co, Cw, rtol=1e-9, atol=1e-15)
    Y[3, 2, 1] = np.nan  # row 2 has a failed fit: weighted least squares over the patterns left
    Do2, _ = demultiplex(Y, cov, H, method="ols")
    Dw2, _ = demultiplex(Y, cov, H, method="wls")
    np.testing.assert_allclose(Do2[2], Dw2[2], atol=1e-12)
    np.testing.assert_allclose(Do2[[0, 1, 3, 4]], Do[[0, 1, 3, 4]], atol=1e-12)
    with pytest.raises(ParameterError, match="method"):
        demultiplex(Y, cov, H, method="svd")


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


def test_demux_lost_fit_of_an_unshared_pattern_costs_only_its_actuator():
    """A plan where each actuator has one pattern of its own (one at a time; a sparse plan's colouring):
    a failed spot fit in that pattern leaves only that actuator's entry of the row undetermined (NaN);
    the row's other actuators are determined by their own patterns and come out as without the loss
    (it used to make the whole row NaN: on the sparse plan of the HCIPy quick run, 1.5 % of the
    responses lost became 16 % of D)."""
    rng = np.random.default_rng(5)
    N, S, F = 5, 4, 2
    D = rng.normal(size=(S, N, F)) + 1j * rng.normal(size=(S, N, F))
    eye = np.eye(N)
    Y, cov = _measure(rng, D, eye, 1e-3)
    full, full_cov = demultiplex(Y, cov, eye)
    Y[2, 1, 0] = np.nan  # actuator 2's only pattern, slope 1, frequency 0
    De, De_cov = demultiplex(Y, cov, eye)
    lost = np.zeros(De.shape, dtype=bool)
    lost[1, 2, 0] = True
    assert np.all(np.isnan(De[lost])) and np.all(np.isnan(De_cov[lost]))
    np.testing.assert_allclose(De[~lost], full[~lost], rtol=1e-12)
    np.testing.assert_allclose(De_cov[~lost], full_cov[~lost], rtol=1e-12)
    # a sparse plan: two patterns, each slope seeing one actuator of each, its support declared
    pat = np.array([[1.0, 0, 1, 0], [0, 1, 0, 1]])
    sup = np.array([[1, 1, 0, 0], [0, 0, 1, 1], [1, 1, 0, 0]], dtype=bool)
    D2 = np.where(sup[:, :, None], rng.normal(size=(3, 4, F)) + 0j, 0)
    Y2, cov2 = _measure(rng, D2, pat, 1e-3)
    Y2[1, 0, 1] = np.nan  # slope 0's pattern of actuator 1, frequency 1
    De2, _ = demultiplex(Y2, cov2, pat, sup)
    assert np.isnan(De2[0, 1, 1]) and np.isfinite(De2[0, 0, 1]) and np.isfinite(De2[1:]).all() and np.isfinite(De2[:, :, 0]).all()



def test_demux_lost_fits_that_leave_a_combination_cost_only_its_actuators():
    """Lost fits that leave some actuators determined only in combination (the data left span ``x0 - x1``,
    not ``x0`` and ``x1``) make those actuators NaN and leave the row's others with their generalised
    least-squares value and variance (it used to make the whole row NaN). Two lost patterns of the
    64-pattern Hadamard plan of 52 actuators do this for 96 of the 2016 pairs (patterns 4 and 52 on
    HCIPy's misregistered whole grid: 2 rows x 52 entries lost became 2 x 32)."""
    rng = np.random.default_rng(11)
    pat = np.array([[1.0, 1, 0], [1, -1, 0], [0, 0, 1], [0, 0, 1]])
    D = rng.normal(size=(2, 3, 1)) + 1j * rng.normal(size=(2, 3, 1))
    Y, cov = _measure(rng, D, pat, 1e-2)
    Y[0, 0, 0] = np.nan  # slope 0 keeps only x0 - x1 and x2 twice
    De, De_cov = demultiplex(Y, cov, pat)
    assert np.isnan(De[0, :2, 0]).all() and np.isnan(De_cov[0, :2, 0]).all() and np.isfinite(De[1]).all()
    W = np.linalg.inv(cov[2:, 0, 0])  # actuator 2: the weighted mean of patterns 2 and 3
    want_cov = np.linalg.inv(W.sum(0))
    y = np.stack([Y[2:, 0, 0].real, Y[2:, 0, 0].imag], -1)
    want = want_cov @ np.einsum("pab,pb->a", W, y)
    np.testing.assert_allclose([De[0, 2, 0].real, De[0, 2, 0].imag], want, rtol=1e-10)
    np.testing.assert_allclose(De_cov[0, 2, 0], want_cov, rtol=1e-10)
    # the Hadamard plan: the pair the HCIPy run lost; the determined entries unbiased with the stds they report
    H = _hadamard(52)
    lost = [4, 52]
    pairs = [(a, b) for a in range(64) for b in range(a + 1, 64) if np.linalg.matrix_rank(np.delete(H, [a, b], 0)) < 52]
    assert len(pairs) == 96 and tuple(lost) in pairs
    N, draws = 52, 300
    D = rng.normal(size=(1, N, 1)) + 1j * rng.normal(size=(1, N, 1))
    cov = _random_cov(rng, (64, 1, 1), 1e-2)
    Y0 = np.einsum("pj,sjf->psf", H, D)
    Y0[lost] = np.nan
    z = []
    for _ in range(draws):
        De, De_cov = demultiplex(Y0 + _noise(rng, cov), cov, H)
        keep = np.isfinite(De[0, :, 0])
        e = np.stack([De[0, keep, 0].real - D[0, keep, 0].real, De[0, keep, 0].imag - D[0, keep, 0].imag], -1)
        z.append(np.einsum("ja,jab,jb->j", e, np.linalg.inv(De_cov[0, keep, 0]), e) / 2)
    assert keep.sum() == 20 and np.isnan(De_cov[0, ~keep, 0]).all()
    z = np.concatenate(z)  # each entry's Mahalanobis distance / 2: mean 1 where the stds hold
    assert abs(z.mean() - 1) < 0.05, z.mean()
    Dn, _ = demultiplex(Y0, cov, H)  # noise-free: the determined entries exact
    np.testing.assert_allclose(Dn[0, keep, 0], D[0, keep, 0], rtol=1e-9)

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


def test_sparse_support_zeros_stay_zero_in_the_static_column():
    rng = np.random.default_rng(13)
    f, G, D, cov = _actuator_case(rng, sigma=0.005)
    off = rng.random(G.shape) < 0.3
    off[:, 3] = False
    G = np.where(off, 0.0, G)
    D = np.where(off[..., None], 0.0, D + _noise(rng, cov))
    cov = np.where(off[..., None, None, None], 0.0, cov)
    t = fit_actuators(f, D, cov, G)
    assert np.all(t.static_column[off] == 0) and np.all(t.static_column_std[off] == 0)
    assert np.all(np.isfinite(t.static_column)) and t.status == ("ok", "ok", "ok", "dead", "weak", "ok")


def test_wrong_model_is_flagged_poor_fit():
    rng = np.random.default_rng(12)
    f, G, D, cov = _actuator_case(rng, sigma=0.002)
    D = D.copy()
    D[:, 0] *= (1 + 0.5 * (f / 2000.0) ** 2)[None]  # not a second-order response
    t = fit_actuators(f, D + _noise(rng, cov), cov, G)
    assert t.poor_fit[0] and t.reduced_chi2[0] > 3
    assert not t.poor_fit[1]


def test_poor_fit_level_holds_the_run_s_false_alarm_rate_whatever_its_size():
    """A run of n actuators whose models all hold flags one poor fit with chance POOR_FIT_P (Sidak), not
    n times it: 1e-3 at 1, 52 and 800 actuators, from independent chi2 survivals."""
    from torchblur.dm.actuator_fit import POOR_FIT_P, poor_fit_p

    for n in (1, 52, 800):
        assert abs(1 - (1 - poor_fit_p(n)) ** n - POOR_FIT_P) < 1e-12
    rng = np.random.default_rng(4)
    runs = rng.random((200_000, 52))  # uniform survivals of 52 models that hold
    rate = (runs < poor_fit_p(52)).any(1).mean()
    assert abs(rate - POOR_FIT_P) < 4 * np.sqrt(POOR_FIT_P / runs.shape[0]), rate
    assert (runs < POOR_FIT_P).any(1).mean() > 0.04  # the former per-actuator level: about 5 % of such runs


# ---- batched spot fits --------------------------------------------------------------------

import math  # noqa: E402

import torch  # noqa: E402

from torchblur.design.windows import dual_exposure_windows  # noqa: E402
from torchblur.dm.spot_fit import CHUNK_BYTES, chunk_size, crop_problems, fit_spot_problems, pattern_responses  # noqa: E402
from torchblur.render.blur import render_blur  # noqa: E402
from torchblur.render.psf import GaussianPSF  # noqa: E402
from torchblur.render.trajectory import Sinusoid  # noqa: E402
from torchblur.render.window import ExposureWindow  # noqa: E402

_F64 = torch.float64


def _sensor_case(seed=0, P=2, F=2, cell=16, n_side=2, read_noise=3.0, dark_spot=None, Y=None, freqs=(40.0, 90.0)):
    """Whole frames [P, F, E, H, W] of an n_side x n_side grid of spots (one per cell), each
    moving on the sinusoid of a known response Y (command amplitude 1, phase 0): random, or
    ``Y [P, 2M, F]`` given."""
    g = torch.Generator().manual_seed(seed)
    M, H = n_side * n_side, n_side * cell
    corner = torch.stack(torch.meshgrid(torch.arange(n_side), torch.arange(n_side), indexing="xy"), -1).reshape(M, 2) * cell
    centre = corner.to(_F64) + (cell - 1) / 2 + torch.rand(M, 2, generator=g, dtype=_F64) - 0.5
    amp = torch.full((M,), 4e5, dtype=_F64)
    if dark_spot is not None:
        amp[dark_spot] = 0.0
    psf = GaussianPSF(centre, torch.eye(2, dtype=_F64) * 2.0, amp)
    freqs = torch.tensor(list(freqs)[:F], dtype=_F64)
    omega = 2 * math.pi * freqs
    win = dual_exposure_windows(omega)  # [F, E]
    mag = 0.5 + 1.5 * torch.rand(P, F, M, 2, generator=g, dtype=_F64)
    ph = (torch.rand(P, F, M, 2, generator=g, dtype=_F64) - 0.5) * 2 * math.pi
    if Y is not None:  # [P, (axis, m), F] -> [P, F, M, 2]
        Yt = torch.as_tensor(np.moveaxis(np.asarray(Y).reshape(P, 2, M, F), (1, 3), (3, 1)))
        mag, ph = Yt.abs().to(_F64), Yt.angle().to(_F64)
    traj = Sinusoid(mag[:, :, :, None], ph[:, :, :, None], omega[None, :, None, None, None].expand(P, F, M, 1, 2))
    w_b = ExposureWindow(win.start[None, :, None], win.duration[None, :, None])  # [1, F, 1, E]
    psf_e = GaussianPSF(centre[:, None], torch.eye(2, dtype=_F64) * 2.0, amp[:, None])  # batch [M, 1]: the E exposures share it
    clean = render_blur(traj, psf_e, w_b, height=H, width=H).sum(2)  # [P, F, E, H, W]
    frames = clean + read_noise * torch.randn(clean.shape, generator=g, dtype=_F64)
    Ytrue = (mag * torch.exp(1j * ph)).permute(0, 3, 2, 1).reshape(P, 2 * M, F).numpy()
    psf_crop = GaussianPSF(centre - corner.to(_F64), psf.cov, amp)
    return frames, corner.long(), (cell, cell), psf_crop, win, omega, Ytrue, read_noise


def test_spot_fit_recovers_responses_and_chunking_is_round_off():
    frames, offset, size, psf, win, omega, Yt, rn = _sensor_case()
    crops, in_frame = crop_problems(frames, offset, size)
    assert crops.shape == (2, 2, 4, 2, 16, 16)
    one = fit_spot_problems(crops, psf, win[None], omega, noise_std=rn, mask=in_frame[:, None])
    many = fit_spot_problems(crops, psf, win[None], omega, noise_std=rn, mask=in_frame[:, None], chunk=3)
    assert one.n_chunks == 1 and many.n_chunks == 6
    torch.testing.assert_close(many.amplitude, one.amplitude, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(many.covariance, one.covariance, rtol=1e-7, atol=1e-12)
    Y, Yc = pattern_responses(one, 1.0)
    assert Y.shape == Yt.shape and Yc.shape == Yt.shape + (2, 2)
    e = np.stack([(Y - Yt).real, (Y - Yt).imag], -1)
    z2 = np.einsum("...a,...ab,...b->...", e, np.linalg.inv(Yc), e)  # chi2 with 2 dof each
    assert float(np.mean(z2)) < 4.0 and np.all(z2 < 30)


def test_dark_or_out_of_frame_spot_is_flagged_and_does_not_poison_the_batch():
    frames, offset, size, psf, win, omega, Yt, rn = _sensor_case(dark_spot=1)
    offset = offset.clone()
    offset[2] = torch.tensor([200, 200])  # spot 2's crop is wholly outside the frame
    crops, in_frame = crop_problems(frames, offset, size)
    fits = fit_spot_problems(crops, psf, win[None], omega, noise_std=rn, mask=in_frame[:, None], chunk=5)
    assert bool((fits.status[:, :, 1] != 0).all()) and bool((fits.status[:, :, 2] != 0).all())
    assert bool((fits.status[:, :, [0, 3]] == 0).all())
    alone = fit_spot_problems(crops[:, :, [0, 3]], GaussianPSF(psf.center[[0, 3]], psf.cov[[0, 3]], psf.amplitude[[0, 3]]), win[None], omega,
                              noise_std=rn, mask=in_frame[[0, 3], None])
    torch.testing.assert_close(fits.amplitude[:, :, [0, 3]], alone.amplitude, rtol=1e-9, atol=1e-9)
    Y, Yc = pattern_responses(fits, 1.0)
    M = 4
    assert np.all(np.isnan(Y[:, [1, 2, M + 1, M + 2]])) and np.all(np.isfinite(Y[:, [0, 3, M, M + 3]]))


def test_chunk_size_from_free_memory():
    assert chunk_size(4, 12, 12, free_bytes=10**9) == int(0.25 * 10**9 // (256 * 4 * 144))
    assert chunk_size(4, 12, 12, free_bytes=10**9, dtype=torch.float32) == int(0.25 * 10**9 // (128 * 4 * 144))
    assert chunk_size(4, 12, 12, free_bytes=1) == 1
    assert chunk_size(4, 12, 12) >= 1
    # beyond CHUNK_BYTES the chunks do not follow the free memory (a run and its re-fit group the problems alike)
    assert chunk_size(4, 12, 12, free_bytes=10**12) == chunk_size(4, 12, 12, free_bytes=10**13) == CHUNK_BYTES // (256 * 4 * 144)


def test_spot_fit_float32_follows_the_input_dtype():
    frames, offset, size, psf, win, omega, _, rn = _sensor_case(P=1, F=1)
    crops, in_frame = crop_problems(frames, offset, size)
    f64 = fit_spot_problems(crops, psf, win[None, :1], omega[:1], noise_std=rn, mask=in_frame[:, None])
    f32 = fit_spot_problems(crops.float(), psf, win[None, :1], omega[:1], noise_std=rn, mask=in_frame[:, None])
    assert f32.amplitude.dtype == torch.float32 and f64.amplitude.dtype == torch.float64
    torch.testing.assert_close(f32.amplitude.double(), f64.amplitude, rtol=0, atol=1e-3)


def test_fit_actuators_names_bad_arguments():
    f = np.geomspace(10.0, 2000.0, 5)
    D = np.zeros((4, 2, 5), complex)
    cov = np.broadcast_to(np.eye(2), (4, 2, 5, 2, 2))
    with pytest.raises(ShapeError, match="G_nominal"):
        fit_actuators(f, D, cov, np.ones((4, 3)))
    with pytest.raises(ShapeError, match="D_cov"):
        fit_actuators(f, D, cov[:, :1], np.ones((4, 2)))
    with pytest.raises(ParameterError, match="freq_hz"):
        fit_actuators(f[:2], D[..., :2], cov[:, :, :2], np.ones((4, 2)))


def test_frames_to_actuators_end_to_end():
    """Rendered sensor frames under Hadamard patterns -> spot fits -> demultiplexing -> actuator
    dynamics: D and every parameter within their stds of the truth."""
    rng = np.random.default_rng(20)
    N, M, f = 4, 4, np.array([60.0, 250.0, 420.0, 700.0])
    G = rng.uniform(-0.5, 0.5, size=(2 * M, N))
    truth = dict(dc_gain=np.array([1.0, 0.9, 1.1, 1.0]), mode_hz=np.array([400.0, 450.0, 500.0, 550.0]),
                 damping=np.array([0.2, 0.25, 0.3, 0.2]), delay_s=np.array([1e-4, 2e-4, 1e-4, 1.5e-4]))
    D = G[:, :, None] * second_order(f, **truth)[None]
    H = _hadamard(N)
    Y = np.einsum("pj,sjf->psf", H, D)
    frames, offset, size, psf, win, omega, _, rn = _sensor_case(seed=5, P=N, F=f.size, Y=Y, freqs=f)
    crops, in_frame = crop_problems(frames, offset, size)
    fits = fit_spot_problems(crops, psf, win[None], omega, noise_std=rn, mask=in_frame[:, None])
    assert bool((fits.status == 0).all())
    Ym, Yc = pattern_responses(fits, 1.0)
    De, Dc = demultiplex(Ym, Yc, H)
    e = np.stack([(De - D).real, (De - D).imag], -1)
    z2 = np.einsum("...a,...ab,...b->...", e, np.linalg.inv(Dc), e)
    assert float(np.mean(z2)) < 4.0  # chi2 of 2 dof: mean 2
    t = fit_actuators(f, De, Dc, G)
    assert t.status == ("ok",) * N
    for k, v in truth.items():
        assert np.all(np.abs(getattr(t, k) - v) < 4 * getattr(t, k + "_std")), (k, getattr(t, k), v)


def test_pattern_responses_phase_variance_and_command_phase():
    frames, offset, size, psf, win, omega, _, rn = _sensor_case(P=1, F=1)
    crops, in_frame = crop_problems(frames, offset, size)
    fits = fit_spot_problems(crops, psf, win[None, :1], omega[:1], noise_std=rn, mask=in_frame[:, None])
    Y0, C0 = pattern_responses(fits, 2.0)
    Y1, C1 = pattern_responses(fits, 2.0, command_phase=0.3, phase_var=1e-2)
    np.testing.assert_allclose(Y1, Y0 * np.exp(-0.3j), rtol=1e-12)
    # the extra phase variance adds |Y|^2 var along the tangent (-Im, Re) of the rotated response
    t = np.stack([-Y1.imag, Y1.real], -1)
    R = np.array([[np.cos(0.3), np.sin(0.3)], [-np.sin(0.3), np.cos(0.3)]])
    np.testing.assert_allclose(C1, R @ C0 @ R.T + 1e-2 * t[..., :, None] * t[..., None, :], rtol=1e-9, atol=1e-15)
