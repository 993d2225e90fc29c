"""The ladder's static-shift noise, common to every frequency of a spot (torchblur.dm.common_noise,
torchblur.dm.ladder_fit.slope_covariance): its covariance against Monte Carlo, and the static columns'
and DC gains' stds that hold with it."""
import numpy as np
import pytest
import scipy.linalg
import torch

from torchblur.dm.actuator_fit import fit_actuators
from torchblur.dm.common_noise import common_noise_line, static_column_variance, with_common_variance
from torchblur.dm.demux import demultiplex
from torchblur.dm.ladder_fit import PatternLadder, slope_covariance, static_slope
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.shack_hartmann import ShackHartmann
from torchblur.errors import ShapeError

F64 = torch.float64


def test_slope_covariance_is_the_scatter_of_static_slope_over_noisy_ladders():
    """A spot that moves (1.1, -0.6) px per unit and widens as it does, 5 levels, each pixel with its
    Poisson variance of a mean of 8 frames: the first-order covariance against the scatter of ``s`` over
    600 noisy ladders (Monte Carlo error of a variance ~6 %)."""
    H, rate = 15, 4000.0
    y, x = torch.arange(H, dtype=F64)[:, None], torch.arange(H, dtype=F64)[None, :]

    def spot(u):
        sx = 1.4 + 0.1 * u
        return rate * torch.exp(-((x - 7.2 - 1.1 * u) ** 2 / (2 * sx**2) + (y - 7.4 + 0.6 * u) ** 2 / (2 * 1.4**2)))

    levels = torch.linspace(-1.2, 1.2, 5, dtype=F64)
    imgs = torch.stack([spot(float(u)) for u in levels])  # [K, h, w]
    var = (imgs + 25.0) / 8
    still = spot(0.0)
    lad = PatternLadder(levels=levels[None], images=imgs[None, :, None], variance=var[None, :, None], still=still[None])
    C = slope_covariance(lad)[0, 0].numpy()
    gen = torch.Generator().manual_seed(3)
    n = 600
    noisy = imgs[None] + var.sqrt()[None] * torch.randn((n,) + tuple(imgs.shape), generator=gen, dtype=F64)
    s = static_slope(noisy, still.expand(n, H, H), levels.expand(n, -1))[0].numpy()
    emp = np.cov(s.T)
    assert np.all(np.abs(np.diag(emp) / np.diag(C) - 1) < 0.15), (np.diag(emp), np.diag(C))
    assert abs(emp[0, 1] - C[0, 1]) < 0.15 * np.sqrt(C[0, 0] * C[1, 1])
    assert np.abs(s.mean(0) - np.array([1.1, -0.6])).max() < 0.02  # the slope itself (the spot widens: not exact)


def test_static_column_variance_is_the_demultiplexed_common_error():
    """A Hadamard plan of 12 actuators over 16 patterns, every (pattern, spot)'s ``s`` off by its own
    noise: the variance of the static columns' error (``delta_s G_0`` of every pattern demultiplexed)
    over 4000 draws against :func:`static_column_variance`."""
    rng = np.random.default_rng(1)
    mirror = DeformableMirror.build(4, coupling=0.15, gain_spread=0.05, seed=1)
    wfs = ShackHartmann(n_across=5, pupil_diameter=4.0, oversample=8)
    G = wfs.geometry_matrix(mirror)
    S, N = G.shape
    M = S // 2
    A = scipy.linalg.hadamard(16)[:, 1:N + 1].astype(float)
    D0 = G * mirror.gain
    Y0 = A @ D0.T  # [P, 2M]
    s = np.stack([Y0[:, :M], Y0[:, M:]], -1)  # the command at DC is 1 (s = the static response per unit)
    L = rng.uniform(0.5, 2.0, (16, M, 2, 2)) * 1e-3 * np.abs(s).max()
    Cs = L @ np.swapaxes(L, -1, -2)
    var = static_column_variance(s, Cs, A, None, D0)
    ds = np.einsum("pmab,npmb->npma", np.linalg.cholesky(Cs), rng.standard_normal((4000, 16, M, 2)))
    dY = np.concatenate([ds[..., 0], ds[..., 1]], -1)  # [n, P, 2M]: delta_s times G_0 = 1
    dD = np.linalg.pinv(A) @ dY  # [n, N, 2M]: every row's ordinary least squares (the support is every actuator)
    emp = dD.var(0).T
    assert np.allclose(emp / var, 1.0, atol=0.12), (emp / var).min()
    # a sparse support: 0 off it, and one pattern's variance where an actuator has a pattern of its own
    sup = np.abs(G) > 0.05 * np.abs(G).max()
    eye = np.eye(N)
    Ds = np.where(sup, D0, 0.0)
    v1 = static_column_variance(np.stack([Ds[:M].T, Ds[M:].T], -1), Cs[:N], eye, sup, Ds)
    assert np.all(v1[~sup] == 0)
    want = np.concatenate([Cs[:N, :, 0, 0], Cs[:N, :, 1, 1]], 1).T
    np.testing.assert_allclose(v1[sup], want[sup], rtol=1e-9)


def _ladder_run(seed, rel_sd, f=np.geomspace(50.0, 2000.0, 12)):
    """12 live actuators one at a time over 21 subapertures; every (actuator, spot)'s ``s`` off by ``rel_sd`` of
    the spot's largest static shift (common to every frequency), D(jw) noise 1e-3 of the largest element;
    each frequency's covariance holding the ``s`` error once, as the spot fits' do."""
    mirror = DeformableMirror.build(4, coupling=0.15, mode_hz=800.0, mode_spread=0.05, gain_spread=0.05, dead=[], seed=1)
    wfs = ShackHartmann(n_across=5, pupil_diameter=4.0, oversample=8)
    rng = np.random.default_rng(seed)
    G = wfs.geometry_matrix(mirror)
    S, N = G.shape
    M = S // 2
    D0 = G * mirror.gain
    H = mirror.response(f) / mirror.gain[:, None]  # [N, F]: the command phasor, 1 at DC
    s = np.stack([D0[:M].T, D0[M:].T], -1)  # [P = N, M, 2]
    sd = rel_sd * np.abs(D0).max()
    Cs = np.broadcast_to(sd**2 * np.eye(2), (N, M, 2, 2)).copy()
    ds = sd * rng.standard_normal((N, M, 2))
    d = 1e-3 * np.abs(D0).max()
    Y = (np.concatenate([s[..., 0] + ds[..., 0], s[..., 1] + ds[..., 1]], 1)[:, :, None] * H[:, None, :]
         + d * (rng.standard_normal((N, S, len(f))) + 1j * rng.standard_normal((N, S, len(f)))))
    h = np.stack([H.real, H.imag], -1)  # [N, F, 2]: delta_s H in (Re, Im)
    Y_cov = np.broadcast_to((d**2 * np.eye(2) + sd**2 * h[..., :, None] * h[..., None, :])[:, None], Y.shape + (2, 2)).copy()
    D, D_cov = demultiplex(Y, Y_cov, np.eye(N))
    table = fit_actuators(f, D, D_cov, G, actuator_xy=mirror.actuator_xy)
    var = static_column_variance(s + ds, Cs, np.eye(N), None, table.static_column)
    return mirror, D0, table, with_common_variance(table, var, G), var


def test_static_columns_and_dc_gains_hold_with_the_common_error():
    """``s`` off by 1e-3 of the largest shift, common to 12 frequencies: without its common share the static
    columns' and DC gains' errors are well beyond their stds; with it, about one (modes untouched)."""
    zc0, zc1, zg0, zg1 = [], [], [], []
    for seed in range(6):
        mirror, D0, before, after, var = _ladder_run(seed, 1e-3)
        live = np.ones(len(mirror.gain), bool)
        big = np.abs(D0) > 0.2 * np.abs(D0).max()
        zc0.append(((before.static_column - D0) / before.static_column_std)[big])
        zc1.append(((after.static_column - D0) / after.static_column_std)[big])
        zg0.append((before.dc_gain - mirror.gain)[live] / before.dc_gain_std[live])
        zg1.append((after.dc_gain - mirror.gain)[live] / after.dc_gain_std[live])
        np.testing.assert_array_equal(after.mode_hz, before.mode_hz)
    rms = [float(np.sqrt(np.mean(np.square(np.concatenate(z))))) for z in (zc0, zc1, zg0, zg1)]
    assert rms[0] > 1.6 and rms[2] > 1.6, rms
    assert 0.8 < rms[1] < 1.2 and 0.75 < rms[3] < 1.3, rms
    assert "grows the static columns' stds" in common_noise_line(var, after)


def test_bad_shapes_are_refused():
    with pytest.raises(ShapeError, match="slope"):
        static_column_variance(np.ones((3, 2, 2)), np.ones((3, 2, 2)), np.eye(3), None, np.ones((4, 3)))
