"""Multisine excitation: crest factor, the common grid, the exact LTI response, the rigs' multisine call."""
import math

import numpy as np
import pytest
import torch

from torchblur.render.camera import CameraModel
from torchblur.config import DEFAULT_PLANT
from torchblur.errors import ParameterError, ShapeError
from torchblur.systems.lti import LTISineTrajectory, Plant
from torchblur.design.multisine import (LTIMultisineTrajectory, common_grid, crest_factor, design_multisine, multisine_signal,
                                 optimise_crest_factor, schroeder_phases)
from torchblur.rig.simulated import SimulatedRig

F64 = torch.float64
PLANT = Plant(tuple(DEFAULT_PLANT[0]), tuple(DEFAULT_PLANT[1]), 30e-6)


def test_crest_factor_of_a_sine_is_sqrt2():
    assert float(crest_factor(torch.tensor(multisine_signal([3], [2.0], [0.4], 4096)))) == pytest.approx(math.sqrt(2), rel=1e-5)


@pytest.mark.parametrize("harmonics", [[1, 2, 3, 4, 5, 6, 7, 8], [3, 4, 5], [2, 5, 9, 11]])
def test_optimised_crest_factor_is_below_schroeder(harmonics):
    a = np.ones(len(harmonics))
    cf_schroeder = float(crest_factor(torch.tensor(multisine_signal(harmonics, a, schroeder_phases(a), 8192))))
    phases, cf = optimise_crest_factor(harmonics, a, n_samples=8192)
    assert cf == pytest.approx(float(crest_factor(torch.tensor(multisine_signal(harmonics, a, phases, 8192)))), rel=1e-12)
    assert cf < cf_schroeder - 0.1  # measured: 1.40 vs 1.89 (8 tones), 1.79 vs 2.12 (3 tones)
    with pytest.raises(ParameterError, match="harmonics"):
        optimise_crest_factor([1, 1, 2])


def test_schroeder_phases_closed_form():
    n = 5
    np.testing.assert_allclose(schroeder_phases(np.ones(n)), [-math.pi * k * (k + 1) / n for k in range(n)], atol=1e-12)


def test_common_grid_and_design():
    f0, n = common_grid([100.0, 127.0, 161.0], snap_tol=0.05)
    assert f0 == pytest.approx(100 / 3) and n.tolist() == [3, 4, 5]
    f0, n = common_grid([50.0, 150.0, 250.0], snap_tol=1e-9)  # exact harmonics stay exact
    assert f0 == 50.0 and n.tolist() == [1, 3, 5]
    with pytest.raises(ParameterError, match="freq_hz"):
        common_grid([100.0, 100.5], snap_tol=1e-4, max_harmonic=16)
    d = design_multisine([100.0, 127.0, 161.0], [1.0, 0.5, 0.25])
    np.testing.assert_allclose(d.freq_hz, [100, 400 / 3, 500 / 3])
    assert d.crest_factor == pytest.approx(d.peak() / math.sqrt(sum(a * a for a in d.amplitudes) / 2), rel=1e-3)


def test_lti_multisine_is_the_sum_of_sine_responses():
    om = torch.tensor([2 * math.pi * 100, 2 * math.pi * 300, 2 * math.pi * 420], dtype=F64)
    amp = torch.tensor([0.1, 0.2, 0.05], dtype=F64)
    t = torch.linspace(0, 0.03, 3001, dtype=F64)
    ms = LTIMultisineTrajectory(PLANT, amp, om)
    total = sum(LTISineTrajectory(PLANT, amp[k], om[k]).output(t) for k in range(3))
    np.testing.assert_allclose(ms.output(t).numpy(), total.numpy(), atol=1e-12 * float(total.abs().max()))
    # a phase of pi is a sign flip, and the batch equals the stacked single items
    flip = LTIMultisineTrajectory(PLANT, amp, om, torch.full((3,), math.pi, dtype=F64))
    np.testing.assert_allclose(flip.output(t).numpy(), -total.numpy(), atol=1e-11 * float(total.abs().max()))
    batch = LTIMultisineTrajectory(PLANT, torch.stack([amp, 2 * amp]), om, torch.tensor([[0.0, 1.0, 2.0], [0.5, -1.0, 3.0]], dtype=F64))
    for b in range(2):
        single = LTIMultisineTrajectory(PLANT, batch.amplitude[b], om, batch.phase[b])
        np.testing.assert_allclose(batch.position(t).numpy()[b], single.position(t).numpy(), rtol=1e-12, atol=1e-12)


def test_lti_multisine_matches_a_control_simulation():
    control = pytest.importorskip("control")
    om = np.array([2 * math.pi * 120, 2 * math.pi * 360, 2 * math.pi * 480])
    amp, ph = np.array([0.1, 0.2, 0.05]), np.array([0.3, -1.2, 2.0])
    tt = np.linspace(0, 0.02, 200_001)
    u = (amp[:, None] * np.sin(om[:, None] * tt + ph[:, None])).sum(0)
    y = control.forced_response(PLANT.to_control(), tt, u).outputs
    y = np.interp(tt - PLANT.delay_s, tt, y, left=0.0)  # the pure delay
    ms = LTIMultisineTrajectory(PLANT, amp, om, ph)
    got = ms.output(torch.tensor(tt)).numpy()
    assert np.abs(got - y).max() < 1e-5 * np.abs(y).max()  # measured 2e-8 (the simulation's step)
    # steady state: each tone through H (delay included)
    h = PLANT.frequency_response(om)
    np.testing.assert_allclose(ms.steady_state_amplitude().numpy(), amp * np.abs(h), rtol=1e-12)
    np.testing.assert_allclose(np.exp(1j * ms.steady_state_phase().numpy()), np.exp(1j * (ph + np.angle(h))), atol=1e-12)
    late = torch.linspace(0.1, 0.11, 1000, dtype=F64)  # after the transients (time constant 3.2 ms)
    assert np.abs(ms.transient(late).numpy()).max() < 1e-6 * np.abs(y).max()  # the output is its steady state
    with pytest.raises(ShapeError, match="amplitude"):
        LTIMultisineTrajectory(PLANT, 1.0, om)


def _rig(**kw):
    return SimulatedRig(plant=PLANT, camera=CameraModel(read_noise_e=0.0, shot_noise=False, bit_depth=16, full_well_e=1e9), frame_shape=(24, 48),
                        jitter_s=0.0, seed=2, **kw)


def test_simulated_rig_multisine_timing_power_and_errors():
    rig = _rig()
    f0 = 50.0
    cap = rig.multisine(freq_hz=[150.0, 250.0], amplitude=[0.05, 0.02], phase_rad=[0.0, 1.0], exposures_s=[2e-3, 4e-3],
                        trigger_offset_s=[1e-3, 5e-3], n_repeats=2, base_freq_hz=f0, power=[2.0, 1.0])
    assert cap.frames.shape == (2, 2, 24, 48)
    k = (cap.trigger_time_s - cap.trigger_offset_s) * f0
    assert torch.allclose(k, k.round(), atol=1e-9) and float(cap.trigger_time_s.min()) >= cap.meta["settle_s"]
    # the frames are the exact response (transients included) rendered over the windows
    traj = LTIMultisineTrajectory(PLANT, [0.05, 0.02], [2 * math.pi * 150, 2 * math.pi * 250], [0.0, 1.0])
    from torchblur.render.window import ExposureWindow

    win = ExposureWindow(cap.meta["actual_start_s"].reshape(-1), cap.exposure_s.reshape(-1))
    expected = rig._render(traj, rig.psf, win).reshape(2, 2, 24, 48) * torch.tensor([2.0, 1.0], dtype=F64)[:, None, None, None]
    expected = expected + rig.camera.dark_level_adu
    assert float((cap.frames - expected).abs().max()) <= 0.5 + 1e-6 * float(expected.max())  # rounding to ADU
    with pytest.raises(ParameterError, match="freq_hz"):
        rig.multisine([100.0, 130.0], [1, 1], [0, 0], [1e-3], 0.0, 1, base_freq_hz=50.0)
    with pytest.raises(ShapeError, match="phase_rad"):
        rig.multisine([100.0, 200.0], [1, 1], [0], [1e-3], 0.0, 1)
    with pytest.raises(ShapeError, match="power"):
        rig.multisine([100.0, 200.0], [1, 1], [0, 0], [1e-3, 2e-3], 0.0, 1, power=[1, 2, 3])
