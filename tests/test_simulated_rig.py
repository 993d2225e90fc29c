"""SimulatedRig: frames, timing, noise and reproducibility of the simulated laboratory."""
import math

import numpy as np
import pytest
import torch

from torchblur import ExposureWindow, GaussianPSF, ParameterError, RenderSettings, Sinusoid, render_blur
from torchblur.render.camera import CameraModel
from torchblur.systems.lti import LTISineTrajectory, Plant
from torchblur.rig import Capture, Rig, SimulatedRig

F64 = torch.float64
HW = (32, 40)


def resonant2():
    wn = 2 * math.pi * 300
    return Plant(num=(wn**2,), den=(1.0, 2 * 0.05 * wn, wn**2), delay_s=40e-6)


def noise_free_camera():
    return CameraModel(dark_level_adu=100.0, read_noise_e=0.0, shot_noise=False, quantize=False,
                       bit_depth=32, full_well_e=1e12, gain_e_per_adu=2.0)


def make_rig(camera=None, **kw):
    args = dict(plant=resonant2(), camera=camera or CameraModel(bit_depth=16), frame_shape=HW, psf_sigma_px=1.6,
                trigger_delay_s=5e-6, latency_s=12e-6, jitter_s=0.2e-6, peak_e_per_s=2e5, seed=3)
    args.update(kw)
    return SimulatedRig(**args)


def still_expected_e(rig, exposure_s):
    """The still spot rendered independently: a zero-amplitude sinusoid."""
    H, W = rig.frame_shape
    psf = GaussianPSF.isotropic(torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64), torch.tensor(1.6, dtype=F64),
                                amplitude=torch.tensor(2e5, dtype=F64))
    still = Sinusoid(torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64), torch.tensor(1.0, dtype=F64))
    return render_blur(still, psf, ExposureWindow(torch.tensor(0.0, dtype=F64), exposure_s), height=H, width=W,
                       settings=RenderSettings(pixel_integration=True))


def test_rig_satisfies_protocol_and_shapes():
    rig = make_rig()
    assert isinstance(rig, Rig)
    assert rig.frame_shape == HW
    cap = rig.sine(200.0, 2.0, [1.5e-3, 4e-3, 2e-3], [0.0, 1e-3, 2e-3], 2)
    assert isinstance(cap, Capture)
    assert cap.frames.shape == (3, 2) + HW
    for t in (cap.exposure_s, cap.trigger_offset_s, cap.trigger_time_s, cap.frame_counter, cap.meta["actual_start_s"]):
        assert t.shape == (3, 2)
    assert cap.frame_counter.dtype == torch.long
    torch.testing.assert_close(cap.exposure_s[:, 0], torch.tensor([1.5e-3, 4e-3, 2e-3], dtype=F64))
    assert rig.dark(4, 1e-3).frames.shape == (4,) + HW
    assert rig.pulse(1e-3, [[0.0, 1e-4, 2e-4]], 5e-4, 1e-4, 2).frames.shape == (1, 3, 2) + HW


def test_still_mean_equals_rendered_image_plus_dark():
    cam = CameraModel(bit_depth=16, read_noise_e=5.0, gain_e_per_adu=1.5, dark_level_adu=100.0)
    rig = make_rig(camera=cam)
    te, n = 4e-3, 400
    cap = rig.still(n, te)
    expected_e = still_expected_e(rig, te)
    mean_adu = expected_e / 1.5 + 100.0
    var_adu = (expected_e + 25.0) / 1.5**2 + 1 / 12
    z = (cap.frames.mean(0) - mean_adu) / (var_adu / n).sqrt()
    assert float(z.abs().max()) < 5.5
    assert float(z.mean().abs()) < 5 / math.sqrt(z.numel())
    assert float(expected_e.max()) > 500  # the spot is well above the noise
    dark = rig.dark(n, te).frames
    assert float(dark.mean()) == pytest.approx(100.0, abs=0.05)


def test_frame_counters_are_consecutive_across_calls():
    rig = make_rig()
    caps = [rig.dark(3, 1e-3), rig.still(2, 1e-3), rig.sine(150.0, 1.0, [1e-3, 2e-3], 0.0, 2),
            rig.pulse(1e-3, [0.0, 1e-4], 5e-4, 1e-4, 2), rig.still(1, 1e-3)]
    counters = torch.cat([c.frame_counter.reshape(-1) for c in caps])
    assert torch.equal(counters, torch.arange(counters.numel()))
    assert rig.frames_taken == counters.numel()


def test_same_seed_reproduces_and_calls_differ():
    def session(seed):
        rig = make_rig(seed=seed)
        return [rig.still(2, 2e-3).frames, rig.sine(180.0, 1.5, [2e-3], 1e-3, 2).frames, rig.still(2, 2e-3).frames]

    a, b, c = session(11), session(11), session(12)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    assert not torch.equal(a[0], c[0])
    assert not torch.equal(a[0], a[2])  # the same request twice gives fresh noise


def test_exposure_longer_than_max_raises():
    rig = make_rig(max_exposure_s=0.01)
    calls = [lambda: rig.still(1, 0.02), lambda: rig.dark(1, 0.02), lambda: rig.sine(100.0, 1.0, [5e-3, 0.02], 0.0, 1),
             lambda: rig.pulse(0.02, 0.0, 1e-3, 1e-4, 1)]
    for call in calls:
        with pytest.raises(ParameterError, match="exposure_s"):
            call()
    assert rig.frames_taken == 0


def test_sine_windows_start_at_commanded_phase_plus_latency():
    f, Td, lat, jit = 170.0, 5e-6, 12e-6, 0.2e-6
    period = 1 / f
    rig = make_rig(trigger_delay_s=Td, latency_s=lat, jitter_s=jit)
    offsets = [0.1 * period, 0.6 * period, 1.3 * period]
    te = [0.3 * period, 0.8 * period, 0.5 * period]
    cap = rig.sine(f, 1.0, te, offsets, 4)
    trig = cap.trigger_time_s
    settle = cap.meta["settle_s"]
    ts = rig.plant.settling_time_s()
    assert ts <= settle < ts + period and abs(settle / period - round(settle / period)) < 1e-9
    # every trigger is an upward zero crossing plus the offset (mod one period)
    phase = torch.remainder(trig, period)
    want = torch.tensor([o % period for o in offsets], dtype=F64)[:, None]
    assert float((phase - want).abs().max()) < 1e-12
    torch.testing.assert_close(cap.trigger_offset_s, want.expand(3, 4))
    # triggers after settling, in order, each the first slot once the camera is ready
    flat, te_flat = trig.reshape(-1), cap.exposure_s.reshape(-1)
    assert float(flat[0]) >= settle
    ready = flat[:-1] + torch.clamp(Td + te_flat[:-1] + rig.readout_s, min=1 / rig.frame_rate_hz)
    gap = flat[1:] - ready
    assert bool((gap >= -1e-12).all()) and bool((gap < period).all())
    # exposure starts: trigger + Td + latency + jitter
    err = cap.meta["actual_start_s"] - trig - Td - lat
    assert float(err.abs().max()) < 6 * jit and float(err.abs().max()) > 0
    exact = make_rig(trigger_delay_s=Td, latency_s=lat, jitter_s=0.0).sine(f, 1.0, te, offsets, 2)
    torch.testing.assert_close(exact.meta["actual_start_s"], exact.trigger_time_s + Td + lat, rtol=0, atol=1e-15)


def test_noise_free_sine_frames_equal_steady_state_render():
    cam = noise_free_camera()
    rig = make_rig(camera=cam, direction=(0.8, 0.6))
    f, amp = 260.0, 4.0
    cap = rig.sine(f, amp, [0.3 / f, 0.8 / f], 0.2 / f, 2)
    h = rig.truth(f)
    M, phi, omega = amp * abs(h), float(np.angle(h)), 2 * math.pi * f
    H, W = rig.frame_shape
    psf = GaussianPSF.isotropic(torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=F64), torch.tensor(1.6, dtype=F64),
                                amplitude=torch.tensor(2e5, dtype=F64))
    traj = Sinusoid(torch.tensor([0.8 * M, 0.6 * M], dtype=F64), torch.full((2,), phi, dtype=F64), torch.tensor(omega, dtype=F64))
    win = ExposureWindow(cap.meta["actual_start_s"], cap.exposure_s)
    ref = render_blur(traj, psf, win, height=H, width=W, settings=RenderSettings(pixel_integration=True))
    got = (cap.frames - 100.0) * 2.0
    assert float((got - ref).abs().max()) <= 1e-6 * float(ref.max())
    # with no settling wait the transient is in the frames, exactly as the LTI response says
    early = rig.sine(f, amp, [0.3 / f], 0.2 / f, 1, settle_s=0.0)
    win = ExposureWindow(early.meta["actual_start_s"], early.exposure_s)
    ref_ss = render_blur(traj, psf, win, height=H, width=W, settings=RenderSettings(pixel_integration=True))
    exact = LTISineTrajectory(rig.plant, amp, omega, direction=(0.8, 0.6))
    ref_tr = render_blur(exact, psf, win, height=H, width=W, settings=RenderSettings(pixel_integration=True))
    got = (early.frames - 100.0) * 2.0
    assert float((got - ref_tr).abs().max()) <= 1e-6 * float(ref_tr.max())
    assert float((got - ref_ss).abs().max()) > 0.05 * float(ref_ss.max())


def test_pulse_brightness_is_a_trapezoid_revealing_the_latency():
    Td, lat, te = 5e-6, 12e-6, 200e-6
    p0, width = 500e-6, 50e-6
    rig = make_rig(camera=noise_free_camera(), trigger_delay_s=Td, latency_s=lat, jitter_s=0.0)
    offsets = torch.arange(200e-6, 560e-6, 2.5e-6, dtype=F64)
    cap = rig.pulse(te, offsets, p0, width, 1, power=0.5)
    light = ((cap.frames - 100.0) * 2.0).sum((-1, -2))[:, 0]  # electrons per frame
    rate = 0.5 * float(still_expected_e(rig, 1.0).sum())  # electrons per second while the laser is on
    start = offsets + Td + lat
    overlap = (torch.clamp(start + te, max=p0 + width) - torch.clamp(start, min=p0)).clamp_min(0)
    torch.testing.assert_close(light / rate, overlap, rtol=1e-9, atol=1e-15)
    # a pipeline's view: fit the falling edge and read the latency off its ends
    top = float(light.max())
    assert top == pytest.approx(rate * width, rel=1e-9)  # plateau: the whole pulse inside the exposure
    falling = (light > 0.02 * top) & (light < 0.98 * top) & (offsets > offsets[light.argmax()])
    assert int(falling.sum()) >= 5
    slope, icpt = np.polyfit(offsets[falling].numpy(), light[falling].numpy(), 1)
    o_zero, o_full = -icpt / slope, (top - icpt) / slope
    assert p0 + width - o_zero - Td == pytest.approx(lat, abs=1e-10)
    assert p0 - o_full - Td == pytest.approx(lat, abs=1e-10)


def test_tilted_spot_and_truth():
    cov = torch.tensor([[4.0, 1.2], [1.2, 2.0]], dtype=F64)
    rig = make_rig(camera=noise_free_camera(), psf_cov=cov, rest_px=(17.0, 14.5), jitter_s=0.0)
    cap = rig.still(1, 1e-3)
    H, W = rig.frame_shape
    psf = GaussianPSF(torch.tensor([17.0, 14.5], dtype=F64), cov, amplitude=torch.tensor(2e5, dtype=F64))
    still = Sinusoid(torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64), torch.tensor(1.0, dtype=F64))
    ref = render_blur(still, psf, ExposureWindow(torch.tensor(0.0, dtype=F64), 1e-3), height=H, width=W,
                      settings=RenderSettings(pixel_integration=True))
    torch.testing.assert_close((cap.frames[0] - 100.0) * 2.0, ref, rtol=1e-9, atol=1e-9 * float(ref.max()))
    wn = 2 * math.pi * 300
    s = 2j * math.pi * 300
    assert rig.truth(300.0) == pytest.approx(wn**2 / (s * s + 0.1 * wn * s + wn**2) * np.exp(-s * 40e-6), rel=1e-12)
    assert rig.truth([100.0, 300.0]).shape == (2,)


def test_rig_input_errors_name_the_argument():
    from torchblur.errors import InputTypeError, ShapeError

    with pytest.raises(InputTypeError, match="^plant"):
        SimulatedRig(plant=(1.0, 1.0), camera=CameraModel())
    with pytest.raises(ShapeError, match="^frame_shape"):
        SimulatedRig(plant=resonant2(), camera=CameraModel(), frame_shape=(32,))
    rig = make_rig()
    with pytest.raises(ShapeError, match="^trigger_offset_s"):
        rig.sine(100.0, 1.0, [1e-3, 2e-3, 3e-3], [0.0, 1e-3], 1)
    with pytest.raises(ParameterError, match="^freq_hz"):
        rig.sine(0.0, 1.0, [1e-3], 0.0, 1)
    with pytest.raises(ParameterError, match="^n_repeats"):
        rig.sine(100.0, 1.0, [1e-3], 0.0, 0)
    with pytest.raises(ParameterError, match="^pulse_width_s"):
        rig.pulse(1e-3, 0.0, 1e-4, 0.0, 1)
    assert rig.frames_taken == 0


def test_a_refused_multisine_leaves_the_random_stream_alone():
    """A multisine refused for its power draws no jitter: the next capture is a fresh rig's."""
    def capture(rig):
        return rig.multisine([100.0, 200.0], [0.1, 0.1], [0.0, 0.0], [1e-4], 0.0, 2).frames

    refused = make_rig()
    with pytest.raises(ParameterError, match="power"):
        refused.multisine([100.0, 200.0], [0.1, 0.1], [0.0, 0.0], [1e-4], 0.0, 2, power=-1.0)
    assert torch.equal(capture(refused), capture(make_rig()))
