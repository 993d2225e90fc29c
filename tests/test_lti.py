"""Plant and LTISineTrajectory: the exact sine response against scipy's simulation."""
import math

import numpy as np
import pytest
import torch

from torchblur.errors import InputTypeError, ParameterError
from torchblur.systems.lti import LTISineTrajectory, Plant
from torchblur.render.window import ExposureWindow


def _quad(w, zeta):
    return np.array([1.0, 2 * zeta * w, w * w])


def resonant2():
    wn = 2 * math.pi * 300
    return Plant(num=(wn**2,), den=tuple(_quad(wn, 0.05)), delay_s=40e-6)


def antiresonant4():
    """Resonances at 300 Hz and 900 Hz, an anti-resonance at 550 Hz, unit DC gain."""
    w1, w2, wz = 2 * math.pi * 300, 2 * math.pi * 900, 2 * math.pi * 550
    num = np.polymul([w1**2 * w2**2 / wz**2], _quad(wz, 0.02))
    den = np.polymul(_quad(w1, 0.05), _quad(w2, 0.03))
    return Plant(num=tuple(num), den=tuple(den), delay_s=25e-6)


def triple_pole():
    a = 2 * math.pi * 200
    return Plant(num=(a**3,), den=tuple(np.poly([-a, -a, -a])), delay_s=10e-6)


def _lsim_reference(plant, amplitude, omega, dt, n):
    """scipy.signal.lsim of num/den (no delay) on t = k dt, then shifted by the delay
    (a whole number of steps)."""
    import scipy.signal

    t = np.arange(n) * dt
    _, y, _ = scipy.signal.lsim((plant.num, plant.den), amplitude * np.sin(omega * t), t)
    k = round(plant.delay_s / dt)
    assert abs(k * dt - plant.delay_s) < 1e-15
    return t, np.concatenate([np.zeros(k), y[: n - k]])


@pytest.mark.parametrize(
    "make, freq_hz",
    [(resonant2, 230.0), (resonant2, 610.0), (antiresonant4, 230.0), (antiresonant4, 610.0), (triple_pole, 230.0)],
    ids=["resonant2-230Hz", "resonant2-610Hz", "antiresonant4-230Hz", "antiresonant4-610Hz", "triple_pole-230Hz"],
)
def test_sine_response_matches_lsim(make, freq_hz):
    plant = make()
    amp, omega = 1.7, 2 * math.pi * freq_hz
    t, y_ref = _lsim_reference(plant, amp, omega, dt=5e-7, n=12001)  # 6 ms: delay and transient
    traj = LTISineTrajectory(plant, amp, omega)
    y = traj.output(torch.tensor(t, dtype=torch.float64)).numpy()
    assert np.abs(y - y_ref).max() <= 1e-6 * np.abs(y_ref).max()
    assert np.all(y[t < plant.delay_s] == 0)
    assert traj.method == ("expm" if make is triple_pole else "modal")
    # position = direction * y
    traj2 = LTISineTrajectory(plant, amp, omega, direction=(0.6, -0.8))
    pos = traj2.position(torch.tensor(t[:500], dtype=torch.float64))
    np.testing.assert_allclose(pos.numpy(), np.stack([0.6 * y[:500], -0.8 * y[:500]], -1), rtol=1e-12, atol=1e-15)


def test_modal_and_expm_agree_batched():
    plant = antiresonant4()
    omega = 2 * math.pi * torch.tensor([[50.0, 300.0], [555.0, 1200.0]], dtype=torch.float64)
    amp = torch.tensor([1.0, -2.5], dtype=torch.float64)
    t = torch.linspace(0, 6e-3, 3001, dtype=torch.float64).expand(2, 2, 3001)
    a = LTISineTrajectory(plant, amp, omega, method="modal").position(t)
    b = LTISineTrajectory(plant, amp, omega, method="expm").position(t)
    assert a.shape == (2, 2, 3001, 2)
    assert (a - b).abs().max() <= 1e-9 * a.abs().max()


def test_batch_equals_stacked_singles():
    plant = resonant2()
    amp = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    omega = 2 * math.pi * torch.tensor([100.0, 290.0, 700.0], dtype=torch.float64)
    t = torch.linspace(0, 4e-3, 257, dtype=torch.float64)
    batched = LTISineTrajectory(plant, amp, omega).position(t.expand(3, -1))
    singles = torch.stack([LTISineTrajectory(plant, amp[i], omega[i]).position(t) for i in range(3)])
    assert torch.equal(batched, singles) or (batched - singles).abs().max() < 1e-13
    win = ExposureWindow(torch.full((3,), 1e-3, dtype=torch.float64), 2e-3)
    pb = LTISineTrajectory(plant, amp, omega).path_length(win)
    ps = torch.stack([LTISineTrajectory(plant, amp[i], omega[i]).path_length(win[i]) for i in range(3)])
    torch.testing.assert_close(pb, ps, rtol=1e-12, atol=0)


@pytest.mark.parametrize("make", [resonant2, antiresonant4])
def test_settling_time_and_steady_state(make):
    plant = make()
    tol = 1e-7
    omega = 2 * math.pi * 280.0
    traj = LTISineTrajectory(plant, 1.3, omega)
    ts = plant.settling_time_s(tol)
    p = plant.poles()
    assert ts == pytest.approx(math.log(1 / tol) / np.abs(p.real).min() + plant.delay_s, rel=1e-12)
    # every mode has decayed by tol: |y_tr| <= tol * sum_k |c_k| from ts on
    c_total = float(torch.linalg.vector_norm(traj._c, dim=-1).sum())
    t = torch.linspace(ts, ts + 0.01, 4001, dtype=torch.float64)
    assert float(traj.transient(t).abs().max()) <= tol * c_total
    t_half = torch.linspace(0.4 * ts, 0.5 * ts, 4001, dtype=torch.float64)
    assert float(traj.transient(t_half).abs().max()) > 10 * tol * c_total  # it is a real transient
    # steady state: M sin(omega t + angle H), angle incl. the delay
    h = plant.frequency_response(omega)
    assert float(traj.steady_state_amplitude()) == pytest.approx(1.3 * abs(h), rel=1e-12)
    assert float(traj.steady_state_phase()) == pytest.approx(np.angle(h), abs=1e-12)
    y = traj.output(t).numpy()
    ref = 1.3 * abs(h) * np.sin(omega * t.numpy() + np.angle(h))
    assert np.abs(y - ref).max() <= tol * c_total + 1e-12 * abs(h)


def test_frequency_response_matches_python_control():
    plant = antiresonant4()
    omega = 2 * math.pi * np.array([1.0, 120.0, 300.0, 550.0, 900.0, 2000.0])
    h = plant.frequency_response(omega)
    hc = plant.to_control()(1j * omega) * np.exp(-1j * omega * plant.delay_s)
    np.testing.assert_allclose(h, hc, rtol=1e-10)
    hp = plant.to_control(pade_order=6)(1j * omega)
    np.testing.assert_allclose(hp[:4], h[:4], rtol=1e-6)  # Pade is good while omega * delay is small
    assert plant.dc_gain() == pytest.approx(1.0)
    np.testing.assert_allclose(np.sort_complex(plant.poles()), np.sort_complex(plant.to_control().poles()), rtol=1e-9)


def test_path_length_is_a_tight_upper_bound():
    plant = resonant2()
    traj = LTISineTrajectory(plant, 2.0, 2 * math.pi * 410.0, direction=(0.6, 0.8))
    start = torch.tensor([0.0, 20e-6, 1e-3, 6e-3, 0.25], dtype=torch.float64)
    dur = torch.tensor([30e-6, 3e-3, 10e-3, 1e-3, 2e-3], dtype=torch.float64)
    bound = traj.path_length(ExposureWindow(start, dur))
    t = start[:, None] + dur[:, None] * torch.linspace(0, 1, 200001, dtype=torch.float64)
    true = traj.position(t).diff(dim=-2).norm(dim=-1).sum(-1)
    assert bool((bound >= true * (1 - 1e-9)).all())
    # useful, not just safe: loose only where the transient cancels the steady state early on
    assert bool((bound[1:] <= 5 * true[1:]).all())
    assert float(bound[-1]) <= 1.001 * float(true[-1])  # settled: the exact sine variation
    assert float(bound[0]) == 0.0  # before the delay


def test_output_is_zero_before_delay_and_continuous():
    plant = Plant(num=(3.0, 4000.0), den=(1.0, 2000.0), delay_s=1e-4)  # biproper: D = 3
    traj = LTISineTrajectory(plant, 1.0, 2 * math.pi * 100)
    t = torch.tensor([0.0, 5e-5, 1e-4 - 1e-12, 1e-4, 1e-4 + 1e-12], dtype=torch.float64)
    y = traj.output(t)
    assert torch.all(y[:3] == 0)
    assert float(y[3:].abs().max()) < 1e-7
    static = Plant(num=(2.5,), den=(1.0,), delay_s=3e-5)
    y = LTISineTrajectory(static, 2.0, 1000.0).output(torch.tensor([1e-3], dtype=torch.float64))
    assert float(y) == pytest.approx(5.0 * math.sin(1000.0 * (1e-3 - 3e-5)), rel=1e-14)


@pytest.mark.parametrize(
    "kwargs, exc, field",
    [
        (dict(num=(1.0, 0.0, 0.0), den=(1.0, 1.0)), ParameterError, "num"),  # improper
        (dict(num=(1.0,), den=(1.0, -1.0)), ParameterError, "den"),  # unstable
        (dict(num=(1.0,), den=(1.0, 0.0, 1.0)), ParameterError, "den"),  # marginal
        (dict(num=(float("nan"),), den=(1.0, 1.0)), ParameterError, "num"),
        (dict(num=(1.0,), den=(1.0, float("inf"))), ParameterError, "den"),
        (dict(num=(1.0,), den=(0.0, 1.0)), ParameterError, "den"),  # zero leading coefficient
        (dict(num=(), den=(1.0, 1.0)), ParameterError, "num"),
        (dict(num=(1.0,), den=()), ParameterError, "den"),
        (dict(num=(1.0,), den=(1.0, 1.0), delay_s=-1e-6), ParameterError, "delay_s"),
        (dict(num=(1.0,), den=(1.0, 1.0), delay_s=float("nan")), ParameterError, "delay_s"),
        (dict(num="1", den=(1.0, 1.0)), InputTypeError, "num"),
    ],
)
def test_plant_validation_names_the_field(kwargs, exc, field):
    with pytest.raises(exc) as info:
        Plant(**kwargs)
    assert str(info.value).startswith(field + ":")


def test_trajectory_validation():
    plant = resonant2()
    with pytest.raises(ParameterError, match="omega"):
        LTISineTrajectory(plant, 1.0, 0.0)
    with pytest.raises(ParameterError, match="method"):
        LTISineTrajectory(plant, 1.0, 1.0, method="euler")
    with pytest.raises(InputTypeError, match="plant"):
        LTISineTrajectory((1.0, 1.0), 1.0, 1.0)
