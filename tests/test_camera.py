"""Tests of torchblur.render.camera: noise statistics, clipping, reproducibility, hot pixels, jitter."""
from __future__ import annotations

import math

import pytest
import torch

from torchblur.render.camera import CameraModel
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.render.window import ExposureWindow

N_SIGMA = 5.0  # tolerance of statistical checks, in standard errors
SIDE = 200  # flat frames are SIDE x SIDE pixels

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def _gen(seed: int, device=torch.device("cpu")) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(seed)
    return g


def _flat(value: float, *, side: int = SIDE, dtype=torch.float64, device="cpu") -> torch.Tensor:
    return torch.full((side, side), value, dtype=dtype, device=device)


# --------------------------------------------------------------------------- statistics


@pytest.mark.parametrize("quantize", [True, False])
@pytest.mark.parametrize("gain", [1.0, 2.5])
def test_expose_mean_and_variance_match_theory(quantize, gain):
    e, read, dark = 1000.0, 5.0, 100.0
    cam = CameraModel(
        dark_level_adu=dark, read_noise_e=read, gain_e_per_adu=gain, full_well_e=1e5, bit_depth=16, quantize=quantize
    )
    frame = cam.expose(_flat(e), generator=_gen(1))
    n = frame.numel()
    mean_th = e / gain + dark
    var_th = (e + read**2) / gain**2 + (1.0 / 12.0 if quantize else 0.0)
    # standard error of the mean sqrt(var/n); of the variance var*sqrt(2/(n-1)) (near-Gaussian)
    assert abs(float(frame.mean()) - mean_th) < N_SIGMA * math.sqrt(var_th / n)
    assert abs(float(frame.var()) - var_th) < N_SIGMA * var_th * math.sqrt(2.0 / (n - 1))


def test_noise_std_matches_empirical_std_in_electrons():
    e = 400.0
    cam = CameraModel(read_noise_e=8.0, gain_e_per_adu=3.0, bit_depth=16, full_well_e=1e5)
    electrons = cam.to_electrons(cam.expose(_flat(e), generator=_gen(2)))
    std_th = float(cam.noise.std(torch.tensor(e, dtype=torch.float64)))
    assert std_th == pytest.approx(math.sqrt(8.0**2 + e + 3.0**2 / 12.0), rel=1e-12)
    n = electrons.numel()
    assert abs(float(electrons.std()) - std_th) < N_SIGMA * std_th / math.sqrt(2.0 * (n - 1))


def test_noiseless_expose_is_affine_and_to_electrons_inverts_it():
    cam = CameraModel(read_noise_e=0.0, shot_noise=False, quantize=False, gain_e_per_adu=2.0, dark_level_adu=37.5, bit_depth=16)
    expected = torch.linspace(0.0, 5000.0, 60, dtype=torch.float64).reshape(2, 5, 6)
    frames = cam.expose(expected)
    assert torch.equal(frames, expected / 2.0 + 37.5)
    assert torch.allclose(cam.to_electrons(frames), expected, rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- clipping


def test_full_well_saturation_is_exact_and_masked():
    cam = CameraModel(dark_level_adu=100.0, read_noise_e=5.0, gain_e_per_adu=1.0, full_well_e=3000.0, bit_depth=16)
    assert cam.saturation_adu == 3100.0
    frame = cam.expose(_flat(1e6, side=50), generator=_gen(3))
    assert torch.all(frame == cam.saturation_adu)
    assert bool(cam.saturated_mask(frame).all())


def test_bit_depth_clip_is_exact_and_masked():
    cam = CameraModel(dark_level_adu=100.0, full_well_e=20000.0, bit_depth=12)
    assert cam.saturation_adu == 4095.0 == 2**12 - 1
    frame = cam.expose(_flat(15000.0, side=50), generator=_gen(4))
    assert torch.all(frame == 4095.0)
    assert bool(cam.saturated_mask(frame).all())


def test_saturation_adu_formula_and_unsaturated_pixels_unmasked():
    cam = CameraModel(dark_level_adu=10.0, gain_e_per_adu=3.0, full_well_e=2000.0, bit_depth=14)
    assert cam.saturation_adu == pytest.approx(2000.0 / 3.0 + 10.0)
    frame = cam.expose(_flat(200.0, side=50), generator=_gen(5))
    assert not bool(cam.saturated_mask(frame).any())
    assert float(frame.min()) >= 0.0


# --------------------------------------------------------------------------- reproducibility


def test_same_seed_is_bit_identical_and_different_seed_differs(device):
    cam = CameraModel(hot_pixel_fraction=0.01)
    expected = torch.rand((2, 40, 50), generator=_gen(0), dtype=torch.float64).to(device) * 3000.0
    a = cam.expose(expected, generator=_gen(7, device))
    b = cam.expose(expected, generator=_gen(7, device))
    c = cam.expose(expected, generator=_gen(8, device))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_generator_must_be_a_generator():
    with pytest.raises(InputTypeError, match="generator"):
        CameraModel().expose(_flat(10.0, side=4), generator=7)


# --------------------------------------------------------------------------- hot pixels


def test_hot_pixel_pattern_is_fixed_and_has_the_right_count():
    h, w, frac = 100, 120, 0.013
    cam = CameraModel(hot_pixel_fraction=frac, hot_pixel_seed=11)
    mask = cam.hot_pixel_mask(h, w)
    assert mask.shape == (h, w) and mask.dtype == torch.bool
    assert int(mask.sum()) == round(frac * h * w)
    torch.manual_seed(123)  # the global RNG must not matter
    assert torch.equal(mask, cam.hot_pixel_mask(h, w))
    assert torch.equal(mask, CameraModel(hot_pixel_fraction=frac, hot_pixel_seed=11).hot_pixel_mask(h, w))
    assert not torch.equal(mask, CameraModel(hot_pixel_fraction=frac, hot_pixel_seed=12).hot_pixel_mask(h, w))
    assert int(CameraModel().hot_pixel_mask(h, w).sum()) == 0


def test_hot_pixels_are_brighter_by_hot_pixel_e_over_gain():
    gain, hot_e = 2.0, 2000.0
    cam = CameraModel(hot_pixel_fraction=0.02, hot_pixel_e=hot_e, gain_e_per_adu=gain, bit_depth=16, full_well_e=1e5)
    frames = cam.expose(_flat(500.0).expand(2, SIDE, SIDE), generator=_gen(9))
    mask = cam.hot_pixel_mask(SIDE, SIDE)
    hot, cold = frames[:, mask], frames[:, ~mask]
    std_hot = math.sqrt((500.0 + hot_e + 25.0) / gain**2 + 1 / 12)
    assert abs(float(hot.mean() - cold.mean()) - hot_e / gain) < N_SIGMA * std_hot / math.sqrt(hot.numel()) + 0.1
    # the same pattern in every frame of the batch, on every call
    again = cam.expose(_flat(500.0).expand(2, SIDE, SIDE), generator=_gen(10))
    assert torch.equal(again > 1000.0, frames > 1000.0) and torch.equal(frames[0] > 1000.0, mask)


def test_noiseless_hot_pixels_add_exactly_hot_pixel_e():
    cam = CameraModel(read_noise_e=0.0, shot_noise=False, hot_pixel_fraction=0.1, hot_pixel_e=300.0, gain_e_per_adu=3.0)
    frame = cam.expose(_flat(60.0, side=20))
    mask = cam.hot_pixel_mask(20, 20)
    assert torch.all(frame[mask] == 100.0 + 120.0) and torch.all(frame[~mask] == 100.0 + 20.0)


# --------------------------------------------------------------------------- jitter


def test_jitter_std_matches_jitter_s():
    n, jit = 20000, 1e-4
    cam = CameraModel(jitter_s=jit)
    window = ExposureWindow(torch.linspace(0.0, 1.0, n, dtype=torch.float64), 5e-3)
    out = cam.jitter_window(window, generator=_gen(13))
    shift = out.start - window.start
    assert abs(float(shift.std()) - jit) < N_SIGMA * jit / math.sqrt(2.0 * (n - 1))
    assert abs(float(shift.mean())) < N_SIGMA * jit / math.sqrt(n)
    assert torch.equal(out.duration, window.duration)
    assert out.start.dtype == torch.float64
    assert torch.equal(out.start, cam.jitter_window(window, generator=_gen(13)).start)


def test_zero_jitter_returns_the_window_unchanged():
    window = ExposureWindow(torch.tensor([0.0, 1e-3, 2e-3]), 1e-3)
    out = CameraModel().jitter_window(window, generator=_gen(0))
    assert out is window and torch.equal(out.start, window.start)


def test_jitter_window_rejects_non_window():
    with pytest.raises(InputTypeError, match="window"):
        CameraModel(jitter_s=1e-3).jitter_window(torch.zeros(3))


# --------------------------------------------------------------------------- dtype / device


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_and_device_follow_the_input(dtype, device):
    cam = CameraModel(hot_pixel_fraction=0.05, jitter_s=1e-3)
    expected = torch.full((3, 8, 9), 50.0, dtype=dtype, device=device)
    frame = cam.expose(expected, generator=_gen(0, device))
    assert frame.dtype == dtype and frame.device.type == device.type and frame.shape == expected.shape
    for out in (cam.to_electrons(frame), cam.noise.std(expected)):
        assert out.dtype == dtype and out.device.type == device.type
    assert cam.saturated_mask(frame).device.type == device.type
    assert cam.hot_pixel_mask(8, 9, device=device).device.type == device.type
    window = ExposureWindow(torch.zeros(4, dtype=dtype, device=device), 1e-3)
    out = cam.jitter_window(window, generator=_gen(0, device))
    assert out.start.dtype == dtype and out.start.device.type == device.type


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "kwargs, exc, field",
    [
        ({"read_noise_e": -1.0}, ParameterError, "read_noise_e"),
        ({"dark_level_adu": -0.5}, ParameterError, "dark_level_adu"),
        ({"bit_depth": 0}, ParameterError, "bit_depth"),
        ({"bit_depth": 33}, ParameterError, "bit_depth"),
        ({"bit_depth": 3.5}, InputTypeError, "bit_depth"),
        ({"gain_e_per_adu": 0.0}, ParameterError, "gain_e_per_adu"),
        ({"full_well_e": float("nan")}, ParameterError, "full_well_e"),
        ({"hot_pixel_fraction": 1.5}, ParameterError, "hot_pixel_fraction"),
        ({"hot_pixel_seed": -1}, ParameterError, "hot_pixel_seed"),
        ({"jitter_s": -1e-3}, ParameterError, "jitter_s"),
        ({"shot_noise": 1}, InputTypeError, "shot_noise"),
        ({"quantize": "yes"}, InputTypeError, "quantize"),
    ],
)
def test_bad_settings_raise_naming_the_field(kwargs, exc, field):
    with pytest.raises(exc, match=field) as info:
        CameraModel(**kwargs)
    assert type(info.value) is exc


@pytest.mark.parametrize(
    "expected_e, exc",
    [
        (torch.tensor([[1.0, float("nan")], [2.0, 3.0]]), ParameterError),
        (torch.tensor([[1.0, -2.0], [2.0, 3.0]]), ParameterError),
        (torch.ones(5), ShapeError),
        ("bright", InputTypeError),
    ],
)
def test_bad_expected_e_raises_naming_it(expected_e, exc):
    with pytest.raises(exc, match="expected_e") as info:
        CameraModel().expose(expected_e)
    assert type(info.value) is exc


def test_settings_are_frozen():
    cam = CameraModel()
    with pytest.raises(AttributeError):
        cam.read_noise_e = 1.0  # type: ignore[misc]
