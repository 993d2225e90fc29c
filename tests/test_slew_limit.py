"""Issue 28: the amplifier's slew-rate limit beside its range. The simulated plant and the
emulator refuse a command slewing beyond it, the serial protocol reports it (SLEW?; an older
firmware without the query still works), a config key narrows it, and every plan (the sine
sweep, the multisine) keeps ``amplitude * omega`` within it, naming the points it limits.
Seeded, small frames, few points."""
import math

import numpy as np
import pytest

from test_safe_drive import SMALL, LoggingRig
from torchblur.errors import ConfigError, ParameterError
from torchblur.config import load_config
from torchblur.identify.drive import DriveLimit, drive_limit
from torchblur.identify.run import identify
from torchblur.rig.base import command_slew
from torchblur.rig.factory import build_simulated_rig

RTOL = 1e-9  # torchblur.rig.base.DRIVE_RTOL


class SlewRig(LoggingRig):
    """LoggingRig that also keeps each command's true slew rate (a dense scan of the derivative)."""

    def __init__(self, rig):
        super().__init__(rig)
        self.rates = []

    def sine(self, **kw):
        self.rates.append(abs(float(kw["amplitude"])) * 2 * math.pi * float(kw["freq_hz"]))
        return super().sine(**kw)

    def multisine(self, **kw):
        f, a, p = (np.asarray(kw[k], dtype=float) for k in ("freq_hz", "amplitude", "phase_rad"))
        t = np.linspace(0, 1 / float(kw["base_freq_hz"]), 200_001)
        self.rates.append(float(np.abs((a[:, None] * 2 * np.pi * f[:, None] * np.cos(2 * np.pi * f[:, None] * t + p[:, None])).sum(0)).max()))
        return super().multisine(**kw)


def test_command_slew_bounds_the_true_slew_rate():
    """One tone: |a| 2 pi f exactly; several: never below a dense scan of the derivative, within 2e-3 of it."""
    assert command_slew(100.0, -2.0, 0.3) == pytest.approx(2.0 * 2 * math.pi * 100.0, rel=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(4):
        n = np.sort(rng.choice(np.arange(1, 30), size=3, replace=False))
        f, a, p = 50.0 * n, rng.uniform(-2, 2, 3), rng.uniform(-np.pi, np.pi, 3)
        t = np.linspace(0, 1 / 50.0, 400_001)
        true = np.abs((a[:, None] * 2 * np.pi * f[:, None] * np.cos(2 * np.pi * f[:, None] * t + p[:, None])).sum(0)).max()
        bound = command_slew(f, a, p, 50.0)
        assert true <= bound * (1 + 1e-12) and bound <= true * 1.002


def test_drive_limit_at_frequency_and_narrowing():
    d = DriveLimit(200.0, 200.0, "device", slew=2e5, slew_device=2e5, slew_source="device")
    assert d.at(10.0) == 200.0 and d.at(1e4) == pytest.approx(2e5 / (2 * math.pi * 1e4))
    cfg = load_config(None, SMALL + ["plant.slew_limit=1e5"])
    rig = build_simulated_rig(cfg)
    assert drive_limit(rig, None, None, 5e4).slew == 5e4
    with pytest.raises(ConfigError, match="^excitation.max_slew: 200000.*only narrow"):
        drive_limit(rig, None, None, 2e5)
    with pytest.raises(ConfigError, match="^excitation.max_slew: .*beyond the simulated plant's slew limit"):
        load_config(None, SMALL + ["plant.slew_limit=1e5", "excitation.max_slew=2e5"])
    with pytest.raises(ConfigError, match="^plant.slew_limit"):
        load_config(None, SMALL + ["plant.slew_limit=-1"])
    with pytest.raises(ParameterError, match="amplitude: a command slewing at"):
        rig.sine(freq_hz=1000.0, amplitude=20.0, exposures_s=[1e-4], trigger_offset_s=0.0, n_repeats=1)  # 1.26e5 > 1e5


def test_the_200khz_sweep_with_a_slew_limit_never_slews_beyond_it_and_names_the_points():
    """sweep.f_max_hz=200000 on an amplifier of 2e5 units/s (its full range only to 159 Hz): no
    command's amplitude * omega above it (axis calibration included), the 200 kHz point cut to
    0.159 units by it, flagged limited and named in the log and in frf.meta."""
    slew = 2e5
    cfg = load_config(None, SMALL + ["sweep.f_max_hz=200000", "sweep.n=3", "fit.axis=x", f"plant.slew_limit={slew}"])
    rig = SlewRig(build_simulated_rig(cfg))
    res = identify(cfg, rig=rig, progress=False)
    f = res.frf.omega / (2 * np.pi)
    assert rig.rates and max(rig.rates) <= slew * (1 + RTOL) and max(rig.peaks) <= 200.0
    assert res.limited.tolist() == [False, False, True]
    assert res.amplitude[2] == pytest.approx(slew / (2 * np.pi * 2e5), rel=1e-9)
    assert res.frf.meta["slew_limit"] == slew and res.frf.meta["limited_hz"] == [pytest.approx(2e5)]
    line = [m for m in res.log if m.startswith("drive: 1 of 3 points limited")]
    assert line and f"slew limit {slew:g}" in line[0] and "2e+05 Hz" in line[0]
    assert any("slew limit 200000 input units/s" in m and "full range up to 159.2 Hz" in m for m in res.log)
    assert f[1] * 2 * np.pi * res.amplitude[1] < slew  # the middle point needed less than the limit: not flagged


def test_multisine_plan_scales_its_tones_within_the_slew_limit():
    """The multisine plan's scaling (identify.multisine._limit): the command's slew rate (not each
    tone's) at most the limit, its peak at most the range, whichever binds; untouched below both."""
    from types import SimpleNamespace

    from torchblur.identify.multisine import _limit, _use
    from torchblur.rig.base import command_peak

    grp = SimpleNamespace(f_t=np.array([100.0, 200.0, 300.0]), f0=100.0)
    a, p = np.array([1.0, 0.8, 0.5]), np.array([0.0, 1.0, 2.0])
    rate = command_slew(grp.f_t, a, p, grp.f0)
    for amax, slew, binds in ((math.inf, rate / 3, "slew"), (0.5, rate * 10, "range"), (math.inf, math.inf, None)):
        b = _limit(a, p, grp, amax, slew)
        assert command_slew(grp.f_t, b, p, grp.f0) <= slew * (1 + 1e-12) and command_peak(grp.f_t, b, p, grp.f0) <= amax * (1 + 1e-12)
        if binds is None:
            np.testing.assert_array_equal(b, a)
        else:
            assert _use(b, p, grp, amax, slew) == pytest.approx(1.0, rel=1e-12)
            np.testing.assert_allclose(b / a, (b / a)[0])  # one scale for every tone: the design's shape kept


def test_an_older_firmware_without_slew_still_answers_the_rest():
    from torchblur.hardware.emulator import EmulatedDevice, load_emulator_config

    keys = ["camera.height=24", "camera.width=24", "plant.slew_limit=1000"]
    dev = EmulatedDevice(load_emulator_config(None, keys), lambda m: None)
    assert dev.handle(b"SLEW?\n") == b"OK SLEW rate=1000.0\n"
    assert dev.handle(b"WAVE x MULTI 50:1:0,100:1.5:0\n").startswith(b"ERR 4 RANGE amplitude: a command slewing")  # 1257 units/s
    old = EmulatedDevice(load_emulator_config(None, keys + ["slew_query=false"]), lambda m: None)
    assert old.handle(b"SLEW?\n").startswith(b"ERR 1 UNKNOWN") and old.handle(b"RANGE?\n") == b"OK RANGE amplitude=200.0\n"
    assert old.handle(b"WAVE x SINE 50 3.5\n").startswith(b"ERR 4 RANGE")  # its limit still holds
    none = EmulatedDevice(load_emulator_config(None, keys[:2]), lambda m: None)
    assert none.handle(b"SLEW?\n") == b"OK SLEW rate=none\n"


def test_identify_through_the_serial_rig_reads_slew_and_keeps_within_it():
    """Over a real pseudo-terminal: SLEW? read on connecting (1000 units/s), a WAVE beyond it refused by
    the device (ERR 4) and by the client before sending; 2 kHz driven at 1000 / (2 pi 2000) units, limited."""
    from test_hardware_emulator import Emu

    from torchblur.hardware import SerialRig
    from torchblur.hardware.errors import DeviceError

    emu = Emu("plant.slew_limit=1000")
    try:
        with SerialRig.open(emu.info["serial"], emu.info["frames"], timeout_s=2.0) as rig:
            assert rig.slew_limit == 1000.0
            with pytest.raises(DeviceError) as err:
                rig.controller.command("WAVE", "x", "SINE", 50.0, 3.5)  # 1100 units/s
            assert err.value.code == 4 and "slew" in str(err.value)
            rig.controller.stop()
            with pytest.raises(ParameterError, match="slewing"):
                rig.sine(freq_hz=50.0, amplitude=3.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=1)
        # the emulated camera's latency (camera.latency_s, 12 us) given, not scanned: the report says which
        base = ["camera.height=40", "camera.width=40", "seed=1", "sweep.freq_hz=[2000]", "sweep.images_per_point=1", "fit.axis=x",
                "camera.latency_std_s=0.2e-6"]
        res = identify(load_config(None, base + emu.rig_keys(2.0)), progress=False)
        assert res.amplitude[0] == pytest.approx(1000 / (2 * math.pi * 2000), rel=1e-9)
        assert res.limited.tolist() == [True] and res.frf.meta["slew_limit"] == 1000.0
        assert res.frf.meta["latency_source"] == "given" and res.latency_s == 12e-6
    finally:
        emu.stop()


# ------------------------------------------------------------------ a latency given instead of scanned


class NoPulseRig:
    """A rig whose controller has no gated laser: every call but pulse() forwarded."""

    def __init__(self, rig):
        self._rig = rig

    def __getattr__(self, name):
        if name == "pulse":
            raise AttributeError(name)
        return getattr(self._rig, name)


def test_a_rig_without_pulse_needs_the_latency_given_and_uses_it():
    from torchblur.identify.calibration import calibrate
    from torchblur.identify.record import collect_log

    cfg = load_config(None, SMALL + ["sweep.freq_hz=[50]", "fit.axis=x"])
    rig = NoPulseRig(build_simulated_rig(cfg))
    with pytest.raises(ConfigError, match="^camera.latency_std_s: the rig .*no gated laser"):
        calibrate(cfg, rig, n_dark=4, n_still=2)
    with pytest.raises(ConfigError, match="^camera.latency_std_s"):
        load_config(None, SMALL + ["camera.latency_std_s=-1e-6"])
    given = load_config(None, SMALL + ["sweep.freq_hz=[50]", "fit.axis=x", "camera.latency_s=11e-6", "camera.latency_std_s=0.5e-6"])
    with collect_log() as log:
        cal = calibrate(given, rig, n_dark=16, n_still=4)
    assert (cal.latency_s, cal.latency_std_s, cal.latency_source) == (11e-6, 0.5e-6, "given")
    assert any(m.startswith("latency: 11.000 +- 0.500 us given") for m in log)
