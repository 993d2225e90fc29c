"""BlurConsistencyLoss as a proper nn.Module (buffers, .to(), state_dict, reductions) and the
property that blur_consistency has no NaN gradient where its value is finite (issue 16)."""
import math

import pytest
import torch

import torchblur as tb
from torchblur.fit.consistency import REDUCTIONS, BlurConsistencyLoss, blur_consistency
from torchblur.losses import LOSSES

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

F64 = torch.float64
H, W = 14, 16
OMEGA = 2 * math.pi * 150.0


def _gaussian_setup(dtype=F64):
    renderer = tb.BlurRenderer(height=H, width=W)
    psf = tb.GaussianPSF.from_axes(torch.tensor([[7.5, 6.5], [8.0, 7.0]], dtype=dtype), torch.tensor(1.7, dtype=dtype),
                                   torch.tensor(1.2, dtype=dtype), torch.tensor(0.3, dtype=dtype),
                                   amplitude=torch.tensor(400.0, dtype=dtype))  # batch [2]
    window = tb.ExposureWindow(torch.tensor([1e-3, 2e-3], dtype=dtype), torch.tensor([2e-3, 5e-3], dtype=dtype))  # [E=2]
    return renderer, psf, window


def _observed(renderer, psf, window, dtype=F64):
    g = torch.Generator().manual_seed(3)
    amp = torch.tensor([[3.0, 1.0], [2.0, -1.0]], dtype=dtype)
    phase = torch.tensor([[0.3, 0.5], [-1.0, 1.2]], dtype=dtype)
    clean = renderer(tb.Sinusoid(amp, phase, torch.tensor(OMEGA, dtype=dtype))[:, None], tb.GaussianPSF(
        psf.center[:, None], psf.cov[:, None], psf.amplitude[:, None]), window)
    return (clean + 0.01 * torch.rand(clean.shape, generator=g, dtype=dtype)).clamp_min(0)  # [2, 2, H, W]


PRED = torch.tensor([[2.8, 0.9, 0.2, 0.6], [2.1, -0.8, -0.9, 1.1]], dtype=F64)  # [B=2, 4]


def test_tensors_are_buffers_and_state_dict_round_trips():
    renderer, psf, window = _gaussian_setup()
    noise = torch.full((2, 1, 1, 1), 0.02, dtype=F64)
    crit = BlurConsistencyLoss(renderer, psf, window, loss="l1", noise_std=noise, omega=torch.tensor(OMEGA, dtype=F64))
    sd = crit.state_dict()
    assert set(sd) == {"psf_center", "psf_cov", "psf_amplitude", "window_start", "window_duration", "noise_std", "omega"}
    torch.testing.assert_close(sd["psf_center"], psf.center, rtol=0, atol=0)
    torch.testing.assert_close(sd["window_duration"], window.duration, rtol=0, atol=0)
    # a fresh module, built with other values of the same kinds and shapes, loads them back
    other_psf = tb.GaussianPSF.isotropic(torch.zeros(2, 2, dtype=F64) + 5.0, 2.5)
    other_win = tb.ExposureWindow(torch.zeros(2, dtype=F64), torch.full((2,), 1e-3, dtype=F64))
    fresh = BlurConsistencyLoss(renderer, other_psf, other_win, loss="l1", noise_std=torch.ones(2, 1, 1, 1, dtype=F64),
                                omega=torch.tensor(1.0, dtype=F64))
    observed = _observed(renderer, psf, window)
    assert not torch.equal(fresh(PRED, observed), crit(PRED, observed))
    fresh.load_state_dict(sd)
    torch.testing.assert_close(fresh(PRED, observed), crit(PRED, observed), rtol=0, atol=0)


def test_buffers_are_detached_copies():
    renderer, psf, window = _gaussian_setup()
    center = psf.center.clone().requires_grad_(True)
    crit = BlurConsistencyLoss(renderer, tb.GaussianPSF(center, psf.cov, psf.amplitude), window, omega=OMEGA)
    assert not crit.psf_center.requires_grad
    with torch.no_grad():
        center += 1.0  # the module keeps its own copy
    torch.testing.assert_close(crit.psf_center, psf.center, rtol=0, atol=0)


def test_to_dtype_moves_every_tensor():
    renderer, psf, window = _gaussian_setup()
    crit = BlurConsistencyLoss(renderer, psf, window, omega=OMEGA, noise_std=torch.tensor(0.02, dtype=F64))
    crit32 = crit.to(torch.float32)
    assert crit32 is crit  # nn.Module.to works in place
    for name, buf in crit.named_buffers():
        assert buf.dtype == torch.float32, name
    assert crit.psf.center.dtype == torch.float32 and crit.window.start.dtype == torch.float32
    observed = _observed(renderer, psf, window).float()
    value = crit(PRED.float(), observed)
    assert value.dtype == torch.float32 and value.shape == (2,)
    ref = blur_consistency(PRED, observed.double(), renderer=renderer, psf=psf, window=window, omega=OMEGA,
                           noise_std=0.02)
    torch.testing.assert_close(value.double(), ref, rtol=2e-3, atol=1e-3)


def test_kernel_psf_buffer():
    renderer = tb.BlurRenderer(height=H, width=W)
    _, gpsf, window = _gaussian_setup()
    still = renderer(tb.Sinusoid(torch.zeros(2), torch.zeros(2), OMEGA), gpsf[0], tb.ExposureWindow(0.0, 1e-3))
    psf = tb.KernelPSF(still, exposure_s=1e-3)
    crit = BlurConsistencyLoss(renderer, psf, window, omega=OMEGA, normalize=True)
    assert set(crit.state_dict()) == {"psf_kernel", "window_start", "window_duration"}
    observed = _observed(renderer, gpsf, window)[:1]
    want = blur_consistency(PRED[:1], observed, renderer=renderer, psf=psf, window=window, omega=OMEGA, normalize=True)
    torch.testing.assert_close(crit(PRED[:1], observed), want, rtol=0, atol=0)
    assert "KernelPSF" in repr(crit)


@pytest.mark.parametrize("reduction", REDUCTIONS)
@pytest.mark.parametrize("loss", ["l1", "poisson"])
def test_module_equals_function_with_non_default_arguments(loss, reduction):
    renderer, psf, window = _gaussian_setup()
    observed = _observed(renderer, psf, window) * 50  # counts, for the deviance
    kw = dict(loss=loss, reduction=reduction, normalize=loss == "l1", omega=torch.tensor(OMEGA, dtype=F64),
              noise_std=None if loss == "poisson" else torch.tensor([[[[0.5]]], [[[0.7]]]], dtype=F64))
    crit = BlurConsistencyLoss(renderer, psf, window, **kw)
    want = blur_consistency(PRED, observed, renderer=renderer, psf=psf, window=window, **kw)
    torch.testing.assert_close(crit(PRED, observed), want, rtol=0, atol=0)
    per_sample = blur_consistency(PRED, observed, renderer=renderer, psf=psf, window=window, **dict(kw, reduction="none"))
    assert per_sample.shape == (2,)
    expect = {"none": per_sample, "mean": per_sample.mean(), "sum": per_sample.sum()}[reduction]
    torch.testing.assert_close(crit(PRED, observed), expect, rtol=1e-12, atol=0)


# ------------------------------------------------------------------------- property (issue 16)
@settings(max_examples=60)
@given(
    loss=st.sampled_from(LOSSES),
    normalize=st.booleans(),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    cx=st.floats(-40.0, 60.0),
    cy=st.floats(-40.0, 60.0),
    amp=st.floats(0.0, 8.0),
    phase=st.floats(-math.pi, math.pi),
    observed_kind=st.sampled_from(["zero", "noise", "spot", "tiny"]),
    use_noise_std=st.booleans(),
)
def test_no_nan_gradient_where_the_loss_is_finite(loss, normalize, dtype, cx, cy, amp, phase, observed_kind, use_noise_std):
    renderer = tb.BlurRenderer(height=12, width=12)
    psf = tb.GaussianPSF.isotropic(torch.tensor([cx, cy], dtype=dtype), torch.tensor(1.5, dtype=dtype),
                                   amplitude=torch.tensor(300.0, dtype=dtype))
    window = tb.ExposureWindow(torch.tensor([1e-3], dtype=dtype), torch.tensor([2e-3, 4e-3], dtype=dtype))
    g = torch.Generator().manual_seed(0)
    if observed_kind == "zero":
        observed = torch.zeros(1, 2, 12, 12, dtype=dtype)
    elif observed_kind == "tiny":
        observed = torch.full((1, 2, 12, 12), 1e-30, dtype=dtype)
    elif observed_kind == "noise":
        observed = torch.rand(1, 2, 12, 12, generator=g, dtype=dtype)
    else:
        still = tb.GaussianPSF.isotropic(torch.tensor([6.0, 5.5], dtype=dtype), torch.tensor(1.5, dtype=dtype),
                                         amplitude=torch.tensor(300.0, dtype=dtype))
        observed = renderer(tb.Sinusoid(torch.tensor([[2.0, 1.0]], dtype=dtype), torch.zeros(1, 2, dtype=dtype),
                                        torch.tensor(OMEGA, dtype=dtype))[:, None], still, window)
    pred = torch.tensor([[amp, 0.5 * amp, phase, phase + 0.3]], dtype=dtype, requires_grad=True)
    noise_std = 0.05 if use_noise_std and loss != "poisson" else None
    value = blur_consistency(pred, observed, renderer=renderer, psf=psf, window=window, loss=loss, normalize=normalize,
                             noise_std=noise_std, omega=OMEGA)
    if not bool(torch.isfinite(value).all()):
        return
    (grad,) = torch.autograd.grad(value.sum(), pred)
    assert bool(torch.isfinite(grad).all()), grad
