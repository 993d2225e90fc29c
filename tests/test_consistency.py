"""BlurConsistencyLoss: the renderer as a measurement-consistency loss (issue 7)."""
import math

import pytest
import torch

import torchblur as tb
from torchblur.fit.consistency import BlurConsistencyLoss, blur_consistency
from torchblur.design.windows import dual_exposure_windows
from torchblur.errors import InputTypeError, ParameterError, ShapeError

F64 = torch.float64
H, W = 24, 28
F_HZ = 150.0
OMEGA = 2 * math.pi * F_HZ


def setup(B=3, E=2, seed=0, dtype=F64, nodes=None):
    g = torch.Generator().manual_seed(seed)
    settings = {} if nodes is None else {"nodes": nodes}
    renderer = tb.BlurRenderer(height=H, width=W, **settings)
    psf = tb.GaussianPSF.from_axes(torch.tensor([13.5, 11.5], dtype=dtype), torch.tensor(1.9, dtype=dtype),
                                   torch.tensor(1.4, dtype=dtype), torch.tensor(0.3, dtype=dtype),
                                   amplitude=torch.tensor(500.0, dtype=dtype))  # peak ~1 in an exposure
    window = dual_exposure_windows(torch.tensor(OMEGA, dtype=dtype), fractions=(0.3, 0.8)[:E])  # [E]
    M = 3 + 3 * torch.rand(B, generator=g, dtype=dtype)
    phi = (2 * torch.rand(B, generator=g, dtype=dtype) - 1) * math.pi
    params = {"amplitude": torch.stack([M, 0.5 * M], -1), "phase": torch.stack([phi, phi + 0.4], -1),
              "omega": torch.full((B,), OMEGA, dtype=dtype)}
    observed = renderer(tb.Sinusoid(**params)[:, None], psf, window)  # [B, E, H, W]
    return renderer, psf, window, params, observed


def test_zero_at_the_truth_positive_elsewhere():
    renderer, psf, window, params, observed = setup()
    value = blur_consistency(params, observed, renderer=renderer, psf=psf, window=window)
    assert value.shape == (3,)
    assert float(value.abs().max()) < 1e-20
    off = dict(params, phase=params["phase"] + 0.2)
    worse = blur_consistency(off, observed, renderer=renderer, psf=psf, window=window)
    assert bool((worse > 1e-3).all())


def test_pred_forms_agree():
    renderer, psf, window, params, observed = setup()
    crit = dict(renderer=renderer, psf=psf, window=window, noise_std=0.02)
    off = {k: v + 0.1 for k, v in params.items()}
    a = blur_consistency(off, observed, **crit)
    b = blur_consistency(tb.Sinusoid(**off), observed, **crit)
    t5 = torch.cat([off["amplitude"], off["phase"], off["omega"][:, None]], -1)
    c = blur_consistency(t5, observed, **crit)
    d = blur_consistency(t5[:, :4], observed, omega=off["omega"], **crit)
    e = blur_consistency({"amplitude": off["amplitude"], "phase": off["phase"]}, observed, omega=off["omega"], **crit)
    for other in (b, c, d, e):
        torch.testing.assert_close(other, a, rtol=1e-12, atol=0)


def test_a_batch_of_two_samples_keeps_one_frequency_per_sample():
    """omega [2] of two samples is per sample, not (x, y): each sample is zero at its own truth."""
    renderer, psf, window, params, _ = setup(B=2)
    om = torch.tensor([OMEGA, 1.7 * OMEGA], dtype=F64)
    truth = dict(params, omega=om)
    observed = torch.stack([renderer(tb.Sinusoid(truth["amplitude"][b], truth["phase"][b], om[b]), psf, window)
                            for b in range(2)])  # [2, E, H, W], each sample rendered alone
    t5 = torch.cat([truth["amplitude"], truth["phase"], om[:, None]], -1)
    for pred, extra in ((truth, {}), (t5, {}), (t5[:, :4], {"omega": om})):
        value = blur_consistency(pred, observed, renderer=renderer, psf=psf, window=window, **extra)
        assert float(value.abs().max()) < 1e-20


def test_spline_trajectory_prediction():
    renderer, psf, window, params, observed = setup(B=2)
    # A spline through the true sinusoid's samples is (almost) consistent; a flat one is not.
    t = torch.linspace(0, float(window.end.max()), 41, dtype=F64)
    vals = tb.Sinusoid(**params).position(t.expand(2, 41))  # [2, 41, 2]
    near = blur_consistency(tb.SplineTrajectory(t, vals), observed, renderer=renderer, psf=psf, window=window)
    far = blur_consistency(tb.SplineTrajectory(t, 0 * vals), observed, renderer=renderer, psf=psf, window=window)
    assert near.shape == (2,)
    assert bool((near < 1e-4 * far).all())


def test_batch_equals_stacked_singles():
    renderer, psf, window, params, observed = setup(B=4)
    off = {k: v * 1.05 for k, v in params.items()}
    noise = 0.01 + 0.02 * torch.rand(4, 1, 1, 1, dtype=F64)
    batch = blur_consistency(off, observed, renderer=renderer, psf=psf, window=window, noise_std=noise, loss="l1")
    singles = torch.stack([
        blur_consistency({k: v[i] for k, v in off.items()}, observed[i], renderer=renderer, psf=psf, window=window,
                         noise_std=noise[i], loss="l1")
        for i in range(4)])
    # the batch shares one node count (its longest path): equal to the quadrature's accuracy
    torch.testing.assert_close(batch, singles, rtol=1e-9, atol=0)


def test_single_exposure_and_broadcast_windows():
    renderer, psf, window, params, observed = setup(B=2, E=1)
    assert observed.shape == (2, 1, H, W)
    v = blur_consistency(params, observed, renderer=renderer, psf=psf, window=window)
    assert v.shape == (2,) and float(v.max()) < 1e-20
    # A per-sample window batch [B, E] broadcasts the same way.
    w2 = tb.ExposureWindow(window.start.expand(2, 1), window.duration.expand(2, 1))
    torch.testing.assert_close(blur_consistency(params, observed, renderer=renderer, psf=psf, window=w2), v)


def test_gradient_matches_finite_differences():
    renderer, psf, window, params, observed = setup(B=2, nodes=64)
    noisy = observed + 0.01 * torch.randn(observed.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    amp = (params["amplitude"] * 0.97).requires_grad_(True)
    ph = (params["phase"] + 0.1).requires_grad_(True)

    def f(a, p):
        return blur_consistency({"amplitude": a, "phase": p, "omega": params["omega"]}, noisy, renderer=renderer, psf=psf,
                                window=window, noise_std=0.01, normalize=True)

    assert torch.autograd.gradcheck(f, (amp, ph), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_module_equals_function_with_non_default_arguments():
    renderer, psf, window, params, observed = setup(B=3)
    off = {"amplitude": params["amplitude"] + 0.3, "phase": params["phase"] - 0.2}
    kw = dict(loss="l1", reduction="sum", noise_std=torch.full((3, 1, 1, 1), 0.05, dtype=F64), normalize=True, omega=params["omega"])
    crit = BlurConsistencyLoss(renderer, psf, window, **kw)
    expected = blur_consistency(off, observed, renderer=renderer, psf=psf, window=window, **kw)
    torch.testing.assert_close(crit(off, observed), expected, rtol=0, atol=0)
    # every option reaches the function: each one changes the value
    for key, val in (("loss", "l2"), ("reduction", "mean"), ("noise_std", None), ("normalize", False)):
        other = BlurConsistencyLoss(renderer, psf, window, **dict(kw, **{key: val}))
        assert not torch.allclose(other(off, observed), expected), key
    crit_none = BlurConsistencyLoss(renderer, psf, window, **dict(kw, reduction="none"))
    assert crit_none(off, observed).shape == (3,)
    assert "l1" in repr(crit)


def test_gradient_descent_recovers_the_parameters():
    renderer, psf, window, params, observed = setup(B=3, seed=5)
    g = torch.Generator().manual_seed(11)
    noisy = observed + 0.005 * observed.amax() * torch.randn(observed.shape, generator=g, dtype=F64)
    M_true, phi_true = params["amplitude"][:, 0], params["phase"][:, 0]
    crit = BlurConsistencyLoss(renderer, psf, window, omega=OMEGA, reduction="sum")
    theta = torch.stack([M_true * 1.15, phi_true + 0.25], -1).requires_grad_(True)  # a nearby start
    opt = torch.optim.Adam([theta], lr=0.03)
    # 150 steps: measured, the errors settle by ~120 steps (0.0059 px, 0.0053 rad from then to 300 steps; 300 cost 2x)
    for _ in range(150):
        opt.zero_grad()
        M, phi = theta[:, 0], theta[:, 1]
        loss = crit({"amplitude": torch.stack([M, 0.5 * M], -1), "phase": torch.stack([phi, phi + 0.4], -1)}, noisy)
        loss.backward()
        opt.step()
    theta = theta.detach()
    assert float((theta[:, 0] - M_true).abs().max()) < 0.03
    assert float(tb.wrap_phase(theta[:, 1] - phi_true).abs().max()) < 0.01


def test_float32_and_dtype_follow_inputs():
    renderer, psf, window, params, observed = setup(B=2, dtype=torch.float32)
    v = blur_consistency({k: v.float() for k, v in params.items()}, observed, renderer=renderer, psf=psf, window=window)
    assert v.dtype == torch.float32
    assert float(v.max()) < 1e-6 * float(observed.square().sum())


def test_bad_input():
    renderer, psf, window, params, observed = setup(B=2)
    kw = dict(renderer=renderer, psf=psf, window=window)
    with pytest.raises(ShapeError, match="observed"):
        blur_consistency(params, observed[..., :-1], **kw)
    with pytest.raises(ShapeError, match="window"):
        blur_consistency(params, observed, renderer=renderer, psf=psf, window=tb.ExposureWindow(0.0, torch.full((3,), 1e-3)))
    with pytest.raises(ShapeError, match="pred"):
        blur_consistency(torch.zeros(2, 3), observed, **kw)
    with pytest.raises(ShapeError, match=r"pred\['amplitude'\]"):
        blur_consistency(dict(params, amplitude=params["amplitude"][:, :1]), observed, **kw)
    with pytest.raises(ShapeError, match="batch shapes"):
        blur_consistency({k: v[:1].expand(3, *v.shape[1:]) for k, v in params.items()}, observed, **kw)
    with pytest.raises(ShapeError, match="noise_std"):
        blur_consistency(params, observed, noise_std=torch.ones(5, 1, 1, 1), **kw)
    with pytest.raises(ParameterError, match="noise_std"):
        blur_consistency(params, observed, noise_std=-1.0, **kw)
    with pytest.raises(ParameterError, match="omega"):
        blur_consistency(torch.zeros(2, 4), observed, **kw)
    with pytest.raises(ParameterError, match="pred"):
        blur_consistency({"amplitude": params["amplitude"]}, observed, **kw)
    with pytest.raises(ParameterError, match="loss"):
        blur_consistency(params, observed, loss="l3", **kw)
    with pytest.raises(ParameterError, match="reduction"):
        BlurConsistencyLoss(renderer, psf, window, reduction="avg")
    with pytest.raises(InputTypeError, match="pred"):
        blur_consistency("sine", observed, **kw)
    with pytest.raises(InputTypeError, match="renderer"):
        BlurConsistencyLoss(object(), psf, window)
    with pytest.raises(InputTypeError, match="observed"):
        blur_consistency(params, observed.numpy(), **kw)


def test_measured_kernel_psf_and_batched_psf():
    renderer, psf, window, params, observed = setup(B=2)
    # a measured kernel: the still spot's image (per second), shared by the exposures
    still = renderer(tb.Sinusoid(torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64), OMEGA), psf,
                     tb.ExposureWindow(torch.tensor(0.0, dtype=F64), torch.tensor(1.0, dtype=F64)))
    kpsf = tb.KernelPSF(still)
    obs_k = renderer(tb.Sinusoid(**params)[:, None], kpsf, window)
    v = blur_consistency(params, obs_k, renderer=renderer, psf=kpsf, window=window)
    assert v.shape == (2,) and float(v.max()) < 1e-16 * float(obs_k.square().sum())
    # a PSF batch [B] (one spot per sample) broadcasts against the exposures
    psf_b = tb.GaussianPSF(psf.center.expand(2, 2), psf.cov.expand(2, 2, 2), psf.amplitude.expand(2))
    torch.testing.assert_close(blur_consistency(params, observed, renderer=renderer, psf=psf_b, window=window),
                               blur_consistency(params, observed, renderer=renderer, psf=psf, window=window))
