"""Batched sinusoid fitting (issue 3): exactness, alias, uncertainty, flags, bad input."""
import math
import warnings

import pytest
import torch

import torchblur as tb
from torchblur.design.windows import (DesignWarning, alias_separation, check_design, dual_exposure_windows, resolve_branches,
                              trigger_phase_for)
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.image.moments import image_moments, sinusoid_from_moments

F64 = torch.float64
H, W = 32, 40


def make(N=4, E=2, seed=0, axis=0, sigma_frac=0.0, tilted=True, fractions=(0.3, 0.8), lissajous=False):
    g = torch.Generator().manual_seed(seed)
    f = 20 + 780 * torch.rand(N, generator=g, dtype=F64)
    om = 2 * math.pi * f
    M = 3 + 4 * torch.rand(N, generator=g, dtype=F64)
    phi = (2 * torch.rand(N, generator=g, dtype=F64) - 1) * math.pi
    b = 2 * math.pi * torch.rand(N, generator=g, dtype=F64)
    win = dual_exposure_windows(om, fractions=fractions[:E], trigger_phase=b)
    cen = torch.tensor([19.5, 15.5], dtype=F64).expand(N, 2)
    if tilted:
        psf = tb.GaussianPSF.from_axes(cen, torch.full((N,), 2.2, dtype=F64), torch.full((N,), 1.5, dtype=F64), torch.full((N,), 0.5, dtype=F64))
    else:
        psf = tb.GaussianPSF.isotropic(cen, torch.full((N,), 1.8, dtype=F64))
    amp = torch.zeros(N, 2, dtype=F64)
    ph = torch.stack([phi, phi], -1)
    if lissajous:
        amp = torch.stack([M, 0.6 * M], -1)
        ph = torch.stack([phi, wrap(phi + 0.9)], -1)
    else:
        amp[:, axis] = M
    traj = tb.Sinusoid(amp[:, None], ph[:, None], om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=H, width=W)
    sigma = sigma_frac * clean.amax((-1, -2, -3))
    noisy = clean + sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64)
    return dict(images=noisy, clean=clean, psf=psf, win=win, om=om, M=M, phi=phi, amp=amp, ph=ph, sigma=sigma)


def wrap(x):
    return tb.wrap_phase(x)


def test_moments_give_the_alias_pair_exactly():
    d = make(N=3, E=1)
    _, cen, cov = image_moments(d["clean"])
    mu1 = cen[..., 0] - d["psf"].center[:, None, 0]
    vex = cov[..., 0, 0] - d["psf"].cov[:, None, 0, 0]
    M, phi = sinusoid_from_moments(mu1, vex, d["om"][:, None], d["win"].start, d["win"].duration)
    torch.testing.assert_close(M[:, 0], d["M"], rtol=1e-6, atol=0)
    err = wrap(phi[:, 0] - d["phi"][:, None]).abs().amin(-1)
    assert float(err.max()) < 1e-6
    alias = tb.alias_phase(d["phi"], d["om"], d["win"][:, 0])
    err2 = wrap(phi[:, 0] - alias[:, None]).abs().amin(-1)
    assert float(err2.max()) < 1e-6


@pytest.mark.parametrize("axis,axes", [(0, "x"), (1, "y")])
def test_noise_free_dual_exposure_is_exact(axis, axes):
    d = make(axis=axis)
    res = fit_sinusoid(d["clean"], d["psf"], d["win"], d["om"], axes=axes)
    assert res.converged.all()
    torch.testing.assert_close(res.amplitude, d["M"], rtol=1e-7, atol=1e-9)
    assert float(wrap(res.phase - d["phi"]).abs().max()) < 1e-7
    assert (res.alias_cost > 100 * res.cost + 1e-20).all()  # two exposures: the alias is not a minimum


def test_single_exposure_returns_both_branches():
    d = make(E=1, N=3)
    res = fit_sinusoid(d["clean"], d["psf"], d["win"], d["om"])
    branches = torch.stack([res.phase, res.alias_phase], -1)
    assert float(wrap(branches - d["phi"][:, None]).abs().amin(-1).max()) < 1e-6
    torch.testing.assert_close(res.alias_cost, res.cost, rtol=0, atol=1e-12 * float(d["clean"].square().sum()))


def test_lissajous_xy_fit():
    d = make(lissajous=True, N=3)
    res = fit_sinusoid(d["clean"], d["psf"], d["win"], d["om"], axes="xy")
    assert res.amplitude.shape == (3, 2) and res.converged.all()
    torch.testing.assert_close(res.amplitude, d["amp"], rtol=1e-6, atol=1e-8)
    assert float(wrap(res.phase - d["ph"]).abs().max()) < 1e-6


def test_uncertainty_is_honest():
    d = make(N=40, sigma_frac=0.02, seed=3)
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    zM = (res.amplitude - d["M"]) / res.amplitude_std
    zp = wrap(res.phase - d["phi"]) / res.phase_std
    assert res.converged.all()
    for z in (zM, zp):
        rms = float(z.square().mean().sqrt())
        assert 0.7 < rms < 1.35, rms
    # estimated noise (no noise_std given) gives the same std to within ~20%
    res2 = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"])
    torch.testing.assert_close(res2.phase_std, res.phase_std, rtol=0.2, atol=0)


def test_batch_equals_singles():
    d = make(N=3, sigma_frac=0.01, seed=5)
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    for k in range(3):
        one = fit_sinusoid(d["images"][k], d["psf"][k], d["win"][k], d["om"][k], noise_std=d["sigma"][k])
        torch.testing.assert_close(one.amplitude, res.amplitude[k], rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(one.phase, res.phase[k], rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(one.phase_std, res.phase_std[k], rtol=1e-4, atol=0)


def test_dark_and_out_of_frame_items_are_flagged_not_raised():
    d = make(N=4, sigma_frac=0.01, seed=2)
    images = d["images"].clone()
    sig = float(d["sigma"].mean())
    images[1] = sig * torch.randn(images[1].shape, generator=torch.Generator().manual_seed(0), dtype=F64)  # all dark
    psf = tb.GaussianPSF(d["psf"].center.clone(), d["psf"].cov)
    psf.center[2] = torch.tensor([300.0, 300.0], dtype=F64)  # rest position far outside the frame
    res = fit_sinusoid(images, psf, d["win"], d["om"], noise_std=d["sigma"])
    assert res.status.tolist()[1] == 1 and not res.converged[1] and torch.isnan(res.amplitude[1])
    assert res.status[2] in (1, 3) and not res.converged[2]
    for k in (0, 3):
        assert res.converged[k]
        assert abs(float(res.amplitude[k] - d["M"][k])) < 5 * float(res.amplitude_std[k])


def test_nuisance_scale_background_and_center():
    d = make(N=3, sigma_frac=0.0)
    images = 1.7 * d["clean"] + 0.3 * float(d["clean"].max())
    res = fit_sinusoid(images, d["psf"], d["win"], d["om"], fit_scale=True, fit_background=True, fit_center=True)
    assert res.converged.all()
    torch.testing.assert_close(res.scale, torch.full((3,), 1.7, dtype=F64), rtol=1e-6, atol=0)
    torch.testing.assert_close(res.amplitude, d["M"], rtol=1e-6, atol=0)
    torch.testing.assert_close(res.center, d["psf"].center, rtol=0, atol=1e-6)
    assert res.param_names == ("amplitude_x", "phase_x", "scale", "background", "center_x", "center_y")
    assert res.covariance.shape == (3, 6, 6)


def test_poisson_loss_on_photon_counts():
    d = make(N=3)
    counts_per_peak = 2000.0
    lam = d["clean"] / d["clean"].amax((-1, -2, -3), keepdim=True) * counts_per_peak + 2.0
    counts = torch.poisson(lam, generator=torch.Generator().manual_seed(1))
    psf = tb.GaussianPSF(d["psf"].center, d["psf"].cov, counts_per_peak / d["clean"].amax((-1, -2, -3)))
    res = fit_sinusoid(counts - 2.0, psf, d["win"], d["om"], loss="poisson")
    assert res.converged.all()
    assert float(((res.amplitude - d["M"]) / res.amplitude_std).abs().max()) < 4


@pytest.mark.parametrize("optimizer,loss", [("adam", "l2"), ("lbfgs", "l2"), ("lbfgs", "l1"), ("adam", "linf"), ("lm", "l1")])
def test_other_optimizers_and_losses_reach_the_solution(optimizer, loss):
    d = make(N=2, tilted=False)
    res = fit_sinusoid(d["clean"], d["psf"], d["win"], d["om"], optimizer=optimizer, loss=loss,
                       max_iter=150 if optimizer == "adam" else None)
    tol = 5e-2 if optimizer == "adam" else 1e-3
    torch.testing.assert_close(res.amplitude, d["M"], rtol=tol, atol=0)
    assert float(wrap(res.phase - d["phi"]).abs().max()) < tol


BAD = [
    ("NaN pixel", lambda d: fit_sinusoid(d["images"].index_put((torch.tensor(0), torch.tensor(0), torch.tensor(3), torch.tensor(3)), torch.tensor(float("nan"), dtype=F64)),
                                         d["psf"], d["win"], d["om"]), ParameterError, "images"),
    ("Inf pixel", lambda d: fit_sinusoid(d["images"] * float("inf"), d["psf"], d["win"], d["om"]), ParameterError, "images"),
    ("mismatched E", lambda d: fit_sinusoid(d["images"], d["psf"], tb.ExposureWindow(torch.zeros(4, 3, dtype=F64), 1e-3), d["om"]), ShapeError, "window"),
    ("omega zero", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], torch.zeros(4, dtype=F64)), ParameterError, "omega"),
    ("unknown optimizer", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], optimizer="newton"), ParameterError, "optimizer"),
    ("unknown loss", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], loss="l3"), ParameterError, "loss"),
    ("linf with lm", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], loss="linf"), ParameterError, "loss"),
    ("unknown axes", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], axes="z"), ParameterError, "axes"),
    ("images 2-D", lambda d: fit_sinusoid(d["images"][0, 0], d["psf"], d["win"], d["om"]), ShapeError, "images"),
    ("images not a tensor", lambda d: fit_sinusoid([[1.0]], d["psf"], d["win"], d["om"]), InputTypeError, "images"),
    ("psf batch mismatch", lambda d: fit_sinusoid(d["images"], d["psf"][:3], d["win"], d["om"]), ShapeError, "psf"),
    ("negative noise std", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=-1.0), ParameterError, "noise_std"),
    ("mask not bool", lambda d: fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], mask=torch.ones(4, 2, H, W)), InputTypeError, "mask"),
]


@pytest.mark.parametrize("desc,fn,exc,name", BAD, ids=[b[0] for b in BAD])
def test_fit_bad_input(desc, fn, exc, name):
    d = make(N=4)
    with pytest.raises(exc) as info:
        fn(d)
    assert type(info.value) is exc and name in str(info.value)


def test_design_helpers():
    om = torch.tensor([2 * math.pi * 100.0], dtype=F64)
    good = dual_exposure_windows(om)
    torch.testing.assert_close(alias_separation(om, good), torch.ones(1, dtype=F64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_design(om, good) == []
    same_centre = tb.ExposureWindow(torch.tensor([[0.002, 0.0015]], dtype=F64), torch.tensor([[0.002, 0.003]], dtype=F64))
    with pytest.warns(DesignWarning, match="centres"):
        check_design(om, same_centre)
    whole = dual_exposure_windows(om, fractions=(1.0, 0.25))
    with pytest.warns(DesignWarning, match="whole number"):
        check_design(om, whole)
    # trigger phase puts the alias pi away from the expected phase
    for phi in (-2.0, -0.3, 1.1):
        b = trigger_phase_for(phi, 0.5)
        w = dual_exposure_windows(om, fractions=(0.5,), trigger_phase=b)
        alias = tb.alias_phase(torch.tensor(phi, dtype=F64), om, w[..., 0])
        assert abs(abs(float(wrap(alias - phi))) - math.pi) < 1e-9


def test_continuity_resolver_through_a_resonance():
    # The paper's settings (p = pi, b = pi/2): the branches cross at -90 degrees, at the resonance.
    f = torch.linspace(5, 800, 40, dtype=F64)
    om = 2 * math.pi * f
    wn, z, tau = 2 * math.pi * 300, 0.05, 40e-6
    s = 1j * om
    Hs = wn**2 / (s**2 + 2 * z * wn * s + wn**2) * torch.exp(-s * tau)
    phi = torch.angle(Hs)
    win = dual_exposure_windows(om, fractions=(0.5,), trigger_phase=math.pi / 2)[..., 0]
    alias = tb.alias_phase(phi, om, win)
    # the fitter hands back the two branches in arbitrary order
    swap = torch.rand(40, generator=torch.Generator().manual_seed(0)) > 0.5
    a, b = torch.where(swap, alias, phi), torch.where(swap, phi, alias)
    got = resolve_branches(om, a, b, delay_s=tau)
    assert float(wrap(got - phi).abs().max()) < 1e-9
    # plain nearest-neighbour continuity (the paper's) goes wrong after the crossing
    nn = [float(a[0]) if abs(float(a[0])) < abs(float(b[0])) else float(b[0])]
    for k in range(1, 40):
        nn.append(min((float(a[k]), float(b[k])), key=lambda v: abs(math.remainder(v - nn[-1], 2 * math.pi))))
    assert float(wrap(torch.tensor(nn, dtype=F64) - phi).abs().max()) > 0.5


def test_per_frame_node_counts_follow_each_streak():
    """The analytic path gives each frame the nodes its own streak needs (the short exposure
    fewer), merging counts only where a separate splat call would cost more than the extra
    nodes; one rule of the batch's largest count for every frame gives the same estimates."""
    from torchblur.render.blur import RenderSettings

    d = make(N=160, sigma_frac=0.01, seed=7)
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    npf = res.extras["nodes_per_frame"]
    assert npf.shape == (160, 2)
    assert bool((npf[:, 0] <= npf[:, 1]).all()) and bool((npf[:, 0] < npf[:, 1]).any())
    assert len(torch.unique(npf)) >= 2
    assert int(npf.max()) == res.extras["nodes"]
    ref = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"],
                       render_settings=RenderSettings(nodes=res.extras["nodes"]))
    assert bool((ref.extras["nodes_per_frame"] == res.extras["nodes"]).all())
    assert float(((res.amplitude - ref.amplitude) / res.amplitude_std).abs().max()) < 1e-2
    assert float((wrap(res.phase - ref.phase) / res.phase_std).abs().max()) < 1e-2
    # a small batch: one call (merged to the largest count) is cheaper than several
    small = fit_sinusoid(d["images"][:6], d["psf"][:6], d["win"][:6], d["om"][:6], noise_std=d["sigma"][:6])
    assert len(torch.unique(small.extras["nodes_per_frame"])) == 1


def test_merged_panel_groups_are_the_cheapest_partition():
    """The dynamic programme over panel counts matches a brute force over every split of the
    sorted distinct counts into consecutive groups, and never gives a frame fewer panels."""
    import itertools

    from torchblur.fit.sine_model import _merge_panel_groups

    g = torch.Generator().manual_seed(3)
    for trial in range(40):
        K = 1 + trial % 6
        vals = torch.randperm(12, generator=g)[:K].sort().values + 1
        panels = vals[torch.randint(0, K, (int(torch.randint(1, 60, (1,), generator=g)), 2), generator=g)]
        call = float(torch.rand(1, generator=g)) * 400
        out = _merge_panel_groups(panels, 8, call)
        assert bool((out >= panels).all())

        def cost(p):
            v, m = torch.unique(p, return_counts=True)
            return len(v) * call + float((v * m).sum()) * 8

        v = torch.unique(panels).tolist()
        best = math.inf
        for cuts in itertools.product([0, 1], repeat=len(v) - 1):  # 1: a group ends after count k
            q = panels.clone()
            start = 0
            for k in range(len(v)):
                if k == len(v) - 1 or cuts[k]:
                    for j in range(start, k + 1):
                        q[panels == v[j]] = v[k]
                    start = k + 1
            best = min(best, cost(q))
        assert cost(out) <= best + 1e-9


def test_lm_final_gauss_newton_step_lands_on_the_optimum():
    """With gn_tol the last Gauss-Newton step (shorter than 0.1 std) is taken unevaluated:
    fewer iterations, the same optimum to a small fraction of a standard deviation."""
    from torchblur.optim import levenberg_marquardt, model_jacobian

    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 3, 60, dtype=F64)
    N = 24
    a = 1 + torch.rand(N, generator=g, dtype=F64)
    b = 0.5 + torch.rand(N, generator=g, dtype=F64)
    sigma = 0.01
    data = a[:, None] * torch.exp(-b[:, None] * t) + sigma * torch.randn(N, t.numel(), generator=g, dtype=F64)
    w = torch.full_like(data, 1 / sigma**2)

    def model(th, idx):
        return th[:, :1] * torch.exp(-th[:, 1:2] * t)

    theta0 = torch.stack([a * 1.3, b * 0.7], -1)
    ref = levenberg_marquardt(model, theta0, data, weight=w, tol=1e-15, max_iter=200)
    fast = levenberg_marquardt(model, theta0, data, weight=w, gn_tol=1e-2)
    assert bool(ref.converged.all()) and bool(fast.converged.all())
    assert int(fast.n_iter.sum()) < int(ref.n_iter.sum())
    _, J = model_jacobian(model, ref.theta, torch.arange(N))
    std = torch.linalg.inv(J.transpose(-1, -2) @ J / sigma**2).diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((fast.theta - ref.theta) / std).abs().max()) < 0.02
    # the reported cost is the optimum's to the same order (the predicted decrease was subtracted)
    assert float(((fast.cost - ref.cost) / ref.cost).abs().max()) < 1e-4


def test_final_step_from_the_observed_rate_lands_on_the_optimum(monkeypatch):
    """The fitter stops once the convergence rate it observed says the next Gauss-Newton step
    lands within 0.1 std (gn_tol 1e-2); that step, taken unevaluated, lands within a small
    fraction of a std of the fully converged optimum, in fewer iterations."""
    import torchblur.fit.sinusoid as fit_mod

    d = make(N=60, sigma_frac=0.01, seed=11)
    res = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"])
    monkeypatch.setattr(fit_mod, "GN_TOL", 1e-14)
    ref = fit_sinusoid(d["images"], d["psf"], d["win"], d["om"], noise_std=d["sigma"], tol=1e-15)
    assert bool(res.converged.all()) and bool(ref.converged.all())
    assert int(res.n_iter.sum()) < int(ref.n_iter.sum())
    assert float(((res.amplitude - ref.amplitude) / ref.amplitude_std).abs().max()) < 0.05
    assert float((wrap(res.phase - ref.phase) / ref.phase_std).abs().max()) < 0.05
    # the reported cost is the optimum's to well under one unit of chi^2
    assert float((res.cost - ref.cost).abs().max()) < 0.05


def test_fit_along_a_rotated_image_direction():
    """An actuator axis rotated in the camera's image (25 deg): fitted along that direction
    the estimates are honest (errors match the reported stds); fitted along x they are not.
    axes="x" is exactly axes=(1, 0); bad directions are refused naming ``axes``."""
    from torchblur.errors import ParameterError, ShapeError

    g = torch.Generator().manual_seed(5)
    N, ang = 40, math.radians(25.0)
    u = torch.tensor([math.cos(ang), math.sin(ang)], dtype=F64)
    om = 2 * math.pi * (20 + 780 * torch.rand(N, generator=g, dtype=F64))
    M = 3 + 4 * torch.rand(N, generator=g, dtype=F64)
    phi = (2 * torch.rand(N, generator=g, dtype=F64) - 1) * math.pi
    win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=2 * math.pi * torch.rand(N, generator=g, dtype=F64))
    cen = torch.tensor([19.5, 15.5], dtype=F64).expand(N, 2)
    psf = tb.GaussianPSF.from_axes(cen, torch.full((N,), 2.2, dtype=F64), torch.full((N,), 1.5, dtype=F64), torch.full((N,), 0.5, dtype=F64))
    traj = tb.Sinusoid((M[:, None] * u)[:, None], torch.stack([phi, phi], -1)[:, None], om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=H, width=W)
    sigma = 0.01 * clean.amax((-1, -2, -3))
    images = clean + sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64)

    res = fit_sinusoid(images, psf, win, om, axes=(float(u[0]) * 3, float(u[1]) * 3), noise_std=sigma)  # normalised
    assert res.param_names[:2] == ("amplitude_u", "phase_u")
    assert bool(res.converged.all())
    zM = (res.amplitude - M) / res.amplitude_std
    zP = wrap(res.phase - phi) / res.phase_std
    assert float(zM.abs().max()) < 4.5 and float(zP.abs().max()) < 4.5
    assert 0.6 < float(zM.square().mean().sqrt()) < 1.5 and 0.6 < float(zP.square().mean().sqrt()) < 1.5
    per_item = fit_sinusoid(images, psf, win, om, axes=u.expand(N, 2), noise_std=sigma)
    assert torch.allclose(per_item.amplitude, res.amplitude, rtol=0, atol=1e-12)
    # along x the model cannot explain the image: a far larger cost, amplitudes off by many std
    along_x = fit_sinusoid(images, psf, win, om, noise_std=sigma)
    assert float((along_x.cost / res.cost).median()) > 10
    assert float(((along_x.amplitude - M) / along_x.amplitude_std).abs().median()) > 10
    # "x" is the direction (1, 0), bit for bit
    x_named = fit_sinusoid(images[:6], psf[:6], win[:6], om[:6], noise_std=sigma[:6])
    x_dir = fit_sinusoid(images[:6], psf[:6], win[:6], om[:6], axes=(1.0, 0.0), noise_std=sigma[:6])
    assert torch.equal(x_named.amplitude, x_dir.amplitude) and torch.equal(x_named.phase, x_dir.phase)
    for bad, err in (((0.0, 0.0), ParameterError), ((1.0, 2.0, 3.0), ShapeError), ((float("nan"), 1.0), ParameterError),
                     (torch.ones(3, 2, dtype=F64), ShapeError)):
        with pytest.raises(err, match="axes"):
            fit_sinusoid(images[:2], psf[:2], win[:2], om[:2], axes=bad)


def test_alias_refit_that_improves_nothing_keeps_the_first_solution():
    """With two exposures, items whose alias costs less than the solution are refitted from
    it; when no refit is better the first solutions stand (this used to raise on the empty
    update). A model that cannot fit (a Lissajous motion with an offset, fitted along x with
    the Poisson loss) makes the alias look better for some items."""
    g = torch.Generator().manual_seed(0)
    n = 8
    om = 2 * math.pi * (20 + 300 * torch.rand(n, generator=g, dtype=F64))
    M = 3 + 5 * torch.rand(n, generator=g, dtype=F64)
    phi = (2 * torch.rand(n, generator=g, dtype=F64) - 1) * math.pi
    win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=2 * math.pi * torch.rand(n, generator=g, dtype=F64))
    cen = torch.tensor([23.5, 19.5], dtype=F64) + torch.rand(n, 2, generator=g, dtype=F64) - 0.5
    psf = tb.GaussianPSF.from_axes(cen, torch.full((n,), 2.4, dtype=F64), torch.full((n,), 1.6, dtype=F64), torch.full((n,), 0.5, dtype=F64))
    traj = tb.Sinusoid(torch.stack([M * 0.8, M * 0.5], -1)[:, None], torch.stack([phi, phi + 0.7], -1)[:, None], om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=40, width=48)
    sigma = 0.01 * clean.amax((-1, -2, -3))
    images = clean + sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64) + 0.02
    res = fit_sinusoid(images, psf, win, om, loss="poisson")
    assert bool(torch.isfinite(res.amplitude).all()) and bool(torch.isfinite(res.alias_cost).all())
    # the refit was tried and kept nothing: an item whose alias still costs less
    assert bool((res.alias_cost < res.cost).any())


def test_lm_dof_is_the_data_s_count_when_rows_stand_for_several():
    """``dof`` sets the degrees of freedom behind gn_tol's std: the same fit of data given as
    repeats, or as their weighted mean plus one row holding the cost's constant, lands at the same
    point in the same iterations once ``dof`` counts the repeats; a wrong shape names ``dof``."""
    from torchblur.errors import ShapeError
    from torchblur.optim import levenberg_marquardt

    g = torch.Generator().manual_seed(6)
    t = torch.linspace(0, 3, 40, dtype=F64)
    N, R, sigma = 16, 10, 0.02  # at 10 repeats the rows' own count (41 - 2 against 400 - 2) changes the iterations
    a, b = 1 + torch.rand(N, generator=g, dtype=F64), 0.5 + torch.rand(N, generator=g, dtype=F64)
    clean = a[:, None] * torch.exp(-b[:, None] * t)
    rep = clean[:, None] + sigma * torch.randn(N, R, t.numel(), generator=g, dtype=F64)  # [N, R, T]

    def model(th, idx):
        return th[:, :1] * torch.exp(-th[:, 1:2] * t)

    def model_r(th, idx):
        return model(th, idx).repeat(1, R)

    def model_m(th, idx):
        return torch.cat([model(th, idx), th.new_zeros(th.shape[0], 1)], -1)
    theta0 = torch.stack([a * 1.2, b * 0.8], -1)
    w = 1 / sigma ** 2
    full = levenberg_marquardt(model_r, theta0, rep.reshape(N, -1), weight=torch.full((N, R * t.numel()), w, dtype=F64), gn_tol=1e-2)
    mean = rep.mean(1)
    const = (w * (rep - mean[:, None]).square().sum((1, 2))).sqrt()[:, None]
    W = torch.cat([torch.full((N, t.numel()), R * w, dtype=F64), torch.ones(N, 1, dtype=F64)], -1)
    merged = levenberg_marquardt(model_m, theta0, torch.cat([mean, const], -1), weight=W, gn_tol=1e-2,
                                 dof=torch.full((N,), float(R * t.numel() - 2), dtype=F64))
    torch.testing.assert_close(merged.theta, full.theta, rtol=1e-9, atol=0)
    torch.testing.assert_close(merged.cost, full.cost, rtol=1e-9, atol=0)
    assert torch.equal(merged.n_iter, full.n_iter)
    rows = levenberg_marquardt(model_m, theta0, torch.cat([mean, const], -1), weight=W, gn_tol=1e-2)  # dof from the rows: another path
    assert not torch.equal(rows.n_iter, full.n_iter)
    with pytest.raises(ShapeError, match="dof"):
        levenberg_marquardt(model_m, theta0, torch.cat([mean, const], -1), weight=W, gn_tol=1e-2, dof=torch.ones(N + 1, dtype=F64))
