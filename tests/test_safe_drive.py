"""The safe drive (issue 15): an input range always in force. The simulated plant and the
emulator refuse a command beyond it, the serial protocol reports it (RANGE?), and every plan
(the sine sweep's adaptation, the axis calibration, the multisine's peak, each input of a 2x2
plant) keeps within it; a point that cannot reach its target is driven at the limit, fitted
at the smaller motion and reported as limited. Seeded, small frames, few points."""
import math

import numpy as np
import pytest

import torch

from background import started_fleet, stop_fleet
from torchblur.errors import ConfigError, ParameterError
from torchblur.fit.status import NO_MOTION
from torchblur.hardware.errors import RecordingError
from torchblur.config import PlantConfig, load_config
from torchblur.identify.drive import check_recorded_drive, drive_limit, is_limited
from torchblur.identify.run import identify
from torchblur.rig.base import DRIVE_RTOL, check_drive, check_slew, command_peak, within_drive
from torchblur.rig.factory import build_simulated_rig
from torchblur.rig.simulated import DEFAULT_INPUT_LIMIT

SMALL = ["camera.height=40", "camera.width=40", "seed=3", "sweep.images_per_point=1"]


class LoggingRig:
    """A rig that forwards every call and keeps the peak |command| of each ``sine`` and
    ``multisine`` it received (the truth the run is checked against)."""

    def __init__(self, rig):
        self._rig = rig
        self.peaks = []

    def __getattr__(self, name):
        return getattr(self._rig, name)

    def sine(self, **kw):
        self.peaks.append(abs(float(kw["amplitude"])))
        return self._rig.sine(**kw)

    def multisine(self, **kw):
        f = np.asarray(kw["freq_hz"], dtype=float)
        a = np.asarray(kw["amplitude"], dtype=float)
        p = np.asarray(kw["phase_rad"], dtype=float)
        t = np.linspace(0, 1 / float(kw["base_freq_hz"]), 200_001)
        self.peaks.append(float(np.abs((a[:, None] * np.sin(2 * np.pi * f[:, None] * t + p[:, None])).sum(0)).max()))
        return self._rig.multisine(**kw)


# ------------------------------------------------------------------ the command's peak


def test_command_peak_bounds_the_true_peak_closely():
    """The bound is never below the peak found by a 1e6-sample scan refined by scipy, and
    within 2e-3 of it; one tone gives |a|; tones off a common grid give sum |a|."""
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(0)
    for _ in range(5):
        n = np.sort(rng.choice(np.arange(1, 40), size=4, replace=False))
        a, p = rng.uniform(0.1, 2.0, 4), rng.uniform(-np.pi, np.pi, 4)
        f0 = 7.0
        x = lambda t: np.sum(a * np.sin(2 * np.pi * n * f0 * t + p))  # noqa: E731
        t = np.linspace(0, 1 / f0, 1_000_001)
        s = np.abs((a[:, None] * np.sin(2 * np.pi * n[:, None] * f0 * t + p[:, None])).sum(0))
        t0 = t[s.argmax()]
        r = minimize_scalar(lambda u: -abs(x(u)), bounds=(t0 - 1e-6 / f0, t0 + 1e-6 / f0), method="bounded")
        true = max(float(s.max()), -float(r.fun))
        bound = command_peak(n * f0, a, p, f0)
        assert true <= bound <= true * (1 + 2e-3)
    assert command_peak([5.0], [-3.0], [1.0]) == 3.0
    assert command_peak([5.0, 5.5 * math.pi], [1.0, 2.0], [0.0, 0.0]) == 3.0


def test_check_drive_refuses_beyond_the_range_only():
    check_drive(2.0, 2.0)
    check_drive(-2.0, None)
    with pytest.raises(ParameterError, match="amplitude"):
        check_drive(2.001, 2.0)


def test_peak_and_slew_share_one_tolerance():
    # within_drive is the one test: |value| <= limit (1 + DRIVE_RTOL), NaN beyond, None no limit.
    edge = 2.0 * (1 + DRIVE_RTOL)
    assert within_drive(edge, 2.0) and within_drive(-edge, 2.0) and within_drive(1e300, None)
    assert not within_drive(2.0 * (1 + 10 * DRIVE_RTOL), 2.0) and not within_drive(float("nan"), 2.0)
    for check, words in ((check_drive, "of peak .* beyond the input range"), (check_slew, "slewing at .* beyond the slew limit")):
        check(-edge, 2.0)
        check(float("nan"), None)
        with pytest.raises(ParameterError, match=f"^levels: a command {words}"):
            check(float("nan"), 2.0, "levels")


# ------------------------------------------------------------------ the simulated plant


def test_the_config_default_is_the_simulated_rigs():
    assert PlantConfig().input_limit == DEFAULT_INPUT_LIMIT
    assert build_simulated_rig(load_config(None, ["plant.input_limit=3.5"])).input_limit == 3.5


def test_simulated_rig_refuses_a_command_beyond_its_range():
    rig = build_simulated_rig(load_config(None, ["plant.input_limit=2.0", "camera.height=24", "camera.width=24"]))
    rig.sine(freq_hz=50.0, amplitude=-2.0, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=1)  # at the limit: taken
    with pytest.raises(ParameterError, match="amplitude"):
        rig.sine(freq_hz=50.0, amplitude=2.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=1)
    # two tones of 1.5 each: every tone within the range, their peak (about 2.9) beyond it
    with pytest.raises(ParameterError, match="amplitude"):
        rig.multisine(freq_hz=[50.0, 100.0], amplitude=[1.5, 1.5], phase_rad=[0.0, 0.0], exposures_s=[1e-3], trigger_offset_s=0.0,
                      n_repeats=1)


@pytest.mark.parametrize("keys, key", [
    (["plant.input_limit=0"], "plant.input_limit"),
    (["plant.input_limit=-3"], "plant.input_limit"),
    (["plant.input_limit=10", "excitation.max_amplitude=20"], "excitation.max_amplitude"),
])
def test_config_refuses_a_bad_range(keys, key):
    with pytest.raises(ConfigError, match=f"^{key}"):
        load_config(None, keys)


class _NoRange:
    def __repr__(self):
        return "an old controller"


class _Range:
    input_limit = 5.0


def test_drive_limit_narrows_never_widens():
    assert drive_limit(_Range(), None).limit == 5.0
    assert drive_limit(_Range(), 2.0).limit == 2.0
    with pytest.raises(ConfigError, match="^excitation.max_amplitude: 6.*may only narrow"):
        drive_limit(_Range(), 6.0)
    with pytest.raises(ConfigError, match="^excitation.max_amplitude: the rig .*does not report its input range"):
        drive_limit(_NoRange(), None)
    assert drive_limit(_NoRange(), 1.5).limit == 1.5
    assert is_limited(5.0, float("nan"), 8.0, 5.0) and is_limited(5.0, 2.0, 8.0, 5.0)
    assert not is_limited(5.0, 7.0, 8.0, 5.0) and not is_limited(4.0, 2.0, 8.0, 5.0)


# ------------------------------------------------------------------ the plans


def test_sweep_beyond_the_range_never_commands_more_and_says_which_points():
    """A sweep to 200 kHz on a small range: no command beyond it (axis calibration included),
    the points that cannot reach the target are driven at the limit and reported (result,
    frf.meta, log), and their fits stay honest within their std (or are NaN)."""
    cfg = load_config(None, SMALL + ["sweep.freq_hz=[5,3000,20000]", "plant.input_limit=20"])
    rig = LoggingRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    assert rig.peaks and max(rig.peaks) <= 20.0
    assert res.limited.dtype == np.bool_ and res.limited.tolist() == [False, True, True]
    assert res.amplitude[1:].tolist() == [20.0, 20.0]
    assert res.frf.meta["input_limit"] == 20.0
    assert res.frf.meta["limited_hz"] == [3000.0, 20000.0]
    assert res.moved_px.shape == (3,) and res.moved_px[0] > 6 and res.moved_px[1] < 6
    assert any(m.startswith("drive: 2 of 3 points limited") for m in res.log)
    _, _, z = res.frf.errors_against(rig.truth(np.array([5.0, 3000.0, 20000.0])))
    no_motion = (res.fit.flags & NO_MOTION) != 0
    assert np.isfinite(z[0, 0, :2]).all() and (z[0, 0, :2] < 5).all()  # 3 kHz: 5 px at the limit, fitted honestly
    assert no_motion[2] or z[0, 0, 2] < 5  # 20 kHz (0.02 px): honest, or flagged as no significant motion
    assert not no_motion[:2].any()


def test_the_200khz_sweep_of_the_issue_keeps_within_the_default_range():
    """sweep.f_max_hz=200000 (once 7e6 input units), reduced to 3 points: every command within
    the default range, the 200 kHz point limited and flagged (2e-4 px of true motion)."""
    cfg = load_config(None, SMALL + ["sweep.f_max_hz=200000", "sweep.n=3", "fit.axis=x"])
    rig = LoggingRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    assert max(rig.peaks) <= DEFAULT_INPUT_LIMIT
    assert res.limited.tolist() == [False, False, True] and res.frf.meta["limited_hz"] == [pytest.approx(2e5)]
    _, _, z = res.frf.errors_against(rig.truth(res.frf.omega / (2 * np.pi)))
    no_motion = (res.fit.flags & NO_MOTION) != 0
    assert (z[0, 0, :2] < 5).all() and (no_motion[2] or z[0, 0, 2] < 5)
    assert any("2e+05 Hz" in m and m.startswith("drive: 1 of 3 points limited") for m in res.log)


def test_the_default_range_leaves_the_5khz_run_its_accuracy():
    """The default camera to 5 kHz (reduced to its top two points): about 126 units for 8 px at
    5 kHz, within the default 200; no point limited, 1 % / 1 deg held."""
    cfg = load_config(None, ["sweep.freq_hz=[2000,5000]", "fit.axis=x"])
    rig = LoggingRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    assert max(rig.peaks) <= DEFAULT_INPUT_LIMIT and 100 < res.amplitude[1] < DEFAULT_INPUT_LIMIT
    assert not res.limited.any() and res.frf.meta["limited_hz"] == []
    mag, ph, _ = res.frf.errors_against(rig.truth(np.array([2000.0, 5000.0])))
    assert np.abs(mag).max() < 0.01 and np.degrees(np.abs(ph)).max() < 1.0


def test_max_amplitude_narrows_the_multisine_peak():
    """The multisine's PEAK (not each tone) stays within excitation.max_amplitude."""
    cfg = load_config(None, SMALL + ["sweep.freq_hz=[100,200,300]", "excitation.kind=multisine", "excitation.tones=3",
                                     "excitation.max_amplitude=0.2", "excitation.images=3", "fit.axis=x"])
    rig = LoggingRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    assert rig.peaks and max(rig.peaks) <= 0.2 * (1 + 1e-9)
    assert res.limited.tolist() == [True, True, True]
    assert res.frf.meta["limited_hz"] == pytest.approx([100.0, 200.0, 300.0])


def test_each_input_of_a_2x2_plant_keeps_within_the_range():
    """Both inputs of the tip-tilt mirror: 2 kHz needs about 11 units for 8 px, the range is 3."""
    from pathlib import Path

    mimo = str(Path(__file__).resolve().parents[1] / "configs" / "identify_mimo.yaml")
    cfg = load_config(mimo, SMALL + ["sweep.freq_hz=[5,2000]", "plant.input_limit=3", "excitation.target_px=8"])
    rig = LoggingRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    assert max(rig.peaks) <= 3.0
    assert res.limited.shape == (4,) and res.limited.tolist() == [False, True, False, True]
    assert res.frf.meta["limited_hz"] == [2000.0]


def test_a_recording_beyond_the_rigs_range_is_refused_on_resume(tmp_path):
    cfg = load_config(None, SMALL + ["sweep.freq_hz=[5,1000]", "fit.axis=x"])
    res = identify(cfg, progress=False, record=tmp_path / "run")
    top = float(np.max(res.amplitude))
    small = build_simulated_rig(load_config(None, SMALL + ["sweep.freq_hz=[5,1000]", "fit.axis=x", f"plant.input_limit={top / 2}"]))
    with pytest.raises(RecordingError, match="beyond the input range"):
        identify(cfg, rig=small, progress=False, record=tmp_path / "run")
    from torchblur.hardware import Experiment
    from torchblur.hardware.recording import ReplayRig

    exp = Experiment.open(tmp_path / "run", writable=False)
    check_recorded_drive(exp, top)  # within: no error
    # a replay plans with the range its recording session noted: the same amplitudes
    again = identify(cfg, rig=ReplayRig(exp), record=exp, progress=False)
    np.testing.assert_array_equal(again.amplitude, res.amplitude)
    assert any("from recording" in m for m in again.log)


# ------------------------------------------------------------------ the emulator and the serial protocol


def test_emulator_reports_its_range_and_refuses_beyond_it():
    from torchblur.hardware.emulator import EmulatedDevice, load_emulator_config

    dev = EmulatedDevice(load_emulator_config(None, ["plant.input_limit=2", "camera.height=24", "camera.width=24"]), lambda m: None)
    assert dev.handle(b"RANGE?\n") == b"OK RANGE amplitude=2.0\n"
    assert dev.handle(b"WAVE x SINE 50 -2\n").startswith(b"OK WAVE")
    assert dev.handle(b"WAVE x SINE 50 2.5\n").startswith(b"ERR 4 RANGE amplitude: a command of peak 2.5")
    assert dev.handle(b"WAVE x MULTI 50:1.5:0,100:1.5:0\n").startswith(b"ERR 4 RANGE")  # each tone within, the peak not
    assert dev.handle(b"WAVE x MULTI 50:1:0,100:0.5:0\n").startswith(b"OK WAVE")  # peak about 1.3
    old = EmulatedDevice(load_emulator_config(None, ["range_query=false", "camera.height=24", "camera.width=24"]), lambda m: None)
    assert old.handle(b"RANGE?\n").startswith(b"ERR 1 UNKNOWN")


def BACKGROUND_JOB(out, started):
    """Two emulators over real pseudo-terminals: a range of 3 input units, and an older firmware that
    does not answer RANGE?; started in the background as soon as the module is collected
    (tests/background.py), their start lines read -> ``{name: Emu}`` (they exit with this process)."""
    from test_hardware_emulator import Emu

    return started_fleet({"range": Emu("plant.input_limit=3"), "old": Emu("range_query=false")})


@pytest.fixture(scope="module")
def emulators(background, request):
    """The two emulators of :func:`BACKGROUND_JOB`."""
    emus = background.get(request.module.__name__)
    yield emus
    stop_fleet(emus)


def test_serial_rig_reads_the_range_and_never_sends_beyond_it(emulators):
    from torchblur.hardware import SerialRig
    from torchblur.hardware.errors import DeviceError

    emu = emulators["range"]
    with SerialRig.open(emu.info["serial"], emu.info["frames"], timeout_s=2.0) as rig:
        assert rig.input_limit == 3.0
        with pytest.raises(DeviceError) as err:  # the emulator itself refuses, over the line
            rig.controller.command("WAVE", "x", "SINE", 50.0, 3.5)
        assert err.value.code == 4
        rig.controller.stop()
        with pytest.raises(ParameterError, match="amplitude"):  # the client refuses before sending
            rig.sine(freq_hz=50.0, amplitude=3.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=1)
        with pytest.raises(ParameterError, match="amplitude"):
            rig.multisine(freq_hz=[50.0, 100.0], amplitude=[2.0, 2.0], phase_rad=[0.0, 0.0], exposures_s=[1e-3], trigger_offset_s=0.0,
                          n_repeats=1)


def test_identify_through_the_serial_rig_keeps_within_the_device_range(emulators):
    """2 kHz needs about 11 units for 8 px on the default mirror: the device's 3 limit it."""
    emu = emulators["range"]
    base = ["camera.height=40", "camera.width=40", "seed=1", "sweep.freq_hz=[5,2000]", "sweep.images_per_point=1", "fit.axis=x"]
    with pytest.raises(ConfigError, match="^excitation.max_amplitude: 4.*may only narrow"):
        identify(load_config(None, base + emu.rig_keys(2.0) + ["excitation.max_amplitude=4"]), progress=False)
    res = identify(load_config(None, base + emu.rig_keys(2.0)), progress=False)
    assert res.amplitude.max() <= 3.0 and res.amplitude[1] == 3.0
    assert res.limited.tolist() == [False, True]
    assert any("device +-3" in m for m in res.log)


def test_an_old_controller_needs_max_amplitude(emulators):
    emu = emulators["old"]
    base = ["camera.height=40", "camera.width=40", "seed=1", "sweep.freq_hz=[5]", "sweep.images_per_point=1", "fit.axis=x"]
    with pytest.raises(ConfigError, match="^excitation.max_amplitude: the rig .*does not report its input range"):
        identify(load_config(None, base + emu.rig_keys(2.0)), progress=False)
    # 0.25 units move the default mirror's spot about 5 px, clearly under 0.75 of the 8 px target (0.3 gave 6.0 px: on
    # the limited rule's edge, which the measured motion crossed either way with the noise)
    res = identify(load_config(None, base + emu.rig_keys(2.0) + ["excitation.max_amplitude=0.25"]), progress=False)
    assert res.amplitude.max() <= 0.25 and res.limited.tolist() == [True]
