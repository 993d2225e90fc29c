"""A deformable mirror over the serial link (issue 17): the emulator in DM mode (a separate
process on a real pseudo-terminal, frames over TCP) renders whole Shack-Hartmann frames with
SimulatedDMRig's own renderer; protocol 2 loads a pattern in chunks (PAT, PAT?) and drives it
(WAVE pat), protocol 3 holds it still (WAVE pat HOLD: the rig's pattern_ladder, issue 23);
SerialDMRig runs the DM plan (torchblur.identify) over the link. Small mirror: 9 actuators (one dead),
4 x 4 subapertures (12 valid), 4 frequencies."""
import dataclasses
import json
import os
import subprocess
import sys
import threading
import tty

import numpy as np
import pytest

import torch

from background import started_fleet, stop_fleet
from torchblur.errors import ConfigError, ParameterError, ShapeError
from torchblur.hardware.controller import Controller
from torchblur.hardware.errors import AcquisitionStopped, DeviceError, PatternMismatch
from torchblur.hardware.protocol import (E_ARGS, E_AXIS, E_BUSY, E_NUMBER, E_RANGE, MAX_COUNT, MAX_LINE, PROTOCOL_VERSION, parse_command,
                                         pattern_checksum, pattern_lines)
from torchblur.config import load_config

SMALL_YAML = """\
seed: 3
dm: {n_across: 3, mode_hz: 600.0, damping: 0.1, mode_spread: 0.05, dead: [2], input_limit: 10.0}
wfs: {n_across: 4, pitch_px: 16.0, sigma_px: 1.2}
dm_plan: {kind: hadamard, budget_frames: null, n_repeats: 1}
sweep: {f_min_hz: 50.0, f_max_hz: 1500.0, n: 4, exposures: [0.3, 0.8]}
excitation: {target_px: 3.0}
fit: {psf: gaussian}
"""


class DMEmulator:
    """``torchblur emulator --config FILE`` (the identify config: DM mode) in a subprocess."""

    def __init__(self, config_path, *keys):
        self.proc = subprocess.Popen([sys.executable, "-m", "torchblur.cli", "emulator", "--config", str(config_path),
                                      "exit_with_parent=true", *keys], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._info = None

    @property
    def info(self) -> dict:
        if self._info is None:
            line = self.proc.stdout.readline()
            assert line, f"the DM emulator did not start: {self.proc.stderr.read()}"
            self._info = json.loads(line)
            threading.Thread(target=self.proc.stderr.read, daemon=True).start()  # never let its stderr pipe fill
        return self._info

    def rig_keys(self):
        return ["rig.kind=serial", f"rig.port={self.info['serial']}", f"rig.frames={self.info['frames']}", "rig.timeout_s=2.0"]

    def stop(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)


def BACKGROUND_JOB(out, started):
    """SMALL_YAML written, and two DM emulators started on it at once: "frames" (whose random stream only
    the frame-by-frame test draws from) and "run" (the identification's); in the background as soon as the
    module is collected (tests/background.py), their start lines read -> ``(config path, {name: DMEmulator})``
    (they exit with this process if the module's tests never stop them)."""
    p = out / "small_dm.yaml"
    p.write_text(SMALL_YAML)
    return p, started_fleet({"frames": DMEmulator(p), "run": DMEmulator(p)})


@pytest.fixture(scope="module")
def config_path(background, request):
    return background.get(request.module.__name__)[0]


@pytest.fixture(scope="module")
def emulators(background, request):
    """The two DM emulators of :func:`BACKGROUND_JOB`."""
    emus = background.get(request.module.__name__)[1]
    yield emus
    stop_fleet(emus)


def serial_cfg(config_path, emu, *extra):
    return load_config(str(config_path), emu.rig_keys() + list(extra))


def device_on_a_pty(config_path, *keys):
    """The emulator's device (DM mode) in this process, served on a real pseudo-terminal with its
    frames on a loopback TCP channel: ``(device, port, frames_url)``. For the tests that change
    the device (a cheaper start than a process)."""
    from torchblur.hardware.emulator import EmulatedDevice, FrameServer, load_emulator_config, serve_pty

    holder = {}
    dev = EmulatedDevice(load_emulator_config(str(config_path), list(keys)), lambda msg: holder["frames"].send(msg))
    holder["frames"] = FrameServer(dev.camera_info)
    master, slave = os.openpty()
    tty.setraw(slave)
    threading.Thread(target=serve_pty, args=(dev, master), daemon=True).start()
    return dev, os.ttyname(slave), holder["frames"].url


# ---------------------------------------------------------------------- the protocol


def test_pattern_lines_and_checksum():
    rng = np.random.default_rng(0)
    p = rng.normal(size=57) * np.pi  # 17-18 digit reprs: 6 lines
    lines = pattern_lines(p)
    assert len(lines) > 1 and all(len(ln) <= MAX_LINE + 1 and ln.endswith("\n") for ln in lines)
    got = []
    for ln in lines:
        cmd = parse_command(ln)
        assert cmd.word == "PAT" and cmd.args[0] == len(got)
        got += cmd.args[1]
    assert got == p.tolist()  # every value exact
    assert pattern_checksum(p) == pattern_checksum(np.array(got))
    q = p.copy()
    q[40] = np.nextafter(q[40], np.inf)  # one bit of one value
    assert pattern_checksum(q) != pattern_checksum(p)
    assert pattern_checksum([0.0]) != pattern_checksum([-0.0])
    for bad in ("PAT", "PAT 0", "PAT -1 1.0", "PAT x 1.0", "PAT 0 nan", "PAT 100000 1.0"):
        with pytest.raises(Exception) as info:
            parse_command(bad)
        assert type(info.value).__name__ == "ProtocolViolation"


def test_protocol_round_trips_a_pattern(emulators):
    """Over the pty: ACT?, a pattern loaded in chunks, PAT? its checksum, a partial load, the
    refusals (beyond N, while the waveform runs), WAVE pat naming the pattern it drives."""
    info = emulators["frames"].info
    assert info["protocol"] == PROTOCOL_VERSION == 3
    rng = np.random.default_rng(1)
    p = rng.normal(size=9) * 1e-7 * np.pi
    assert len(pattern_lines(p)) == 2  # nine 22-character values do not fit one 200-byte line
    with Controller(info["serial"], timeout_s=2.0) as c:
        c.resync()
        ident = c.identify()
        assert ident["protocol"] == 3 and ident["axes"] == ["pat"]
        assert c.actuators() == 9
        c.stop()
        assert c.pattern() == {"n": 9, "crc": pattern_checksum(np.zeros(9))}  # zeros after the boot
        assert c.load_pattern(p) == pattern_checksum(p)
        assert c.pattern()["crc"] == pattern_checksum(p)
        c.command("PAT", 4, 0.25, -0.5)  # entries 4 and 5 only
        q = p.copy()
        q[4:6] = [0.25, -0.5]
        assert c.pattern()["crc"] == pattern_checksum(q)
        with pytest.raises(DeviceError) as info_:
            c.command("PAT", 8, 1.0, 2.0)  # entries 8..9 of 9
        assert info_.value.code == E_RANGE and "beyond the 9 actuators" in info_.value.detail
        with pytest.raises(DeviceError) as info_:
            c.wave_sine("x", 100.0, 0.1)
        assert info_.value.code == E_AXIS
        c.load_pattern(p / np.abs(p).max())
        start, crc = c.wave_pattern(200.0, 1.0)
        assert crc == pattern_checksum(p / np.abs(p).max())
        with pytest.raises(DeviceError) as info_:
            c.load_pattern(p)  # the waveform drives the pattern: refused until STOP
        assert info_.value.code == E_BUSY
        c.stop()
        assert c.pattern()["crc"] == pattern_checksum(p / np.abs(p).max())  # kept across STOP


def test_a_pattern_beyond_range_is_refused(emulators, config_path):
    """The device's RANGE (dm.input_limit = 10) bounds the peak command |a| max|pattern|: the
    device refuses it (ERR 4 RANGE, nothing started), and SerialDMRig refuses before sending."""
    from torchblur.hardware.serial_dm_rig import open_dm_rig

    info = emulators["frames"].info
    p = np.zeros(9)
    p[[0, 4]] = [2.0, -0.5]
    with Controller(info["serial"], timeout_s=2.0) as c:
        c.resync()
        c.stop()
        assert c.input_range() == 10.0
        c.load_pattern(p)
        with pytest.raises(DeviceError) as info_:
            c.wave_pattern(100.0, 6.0)  # peak 12
        assert info_.value.code == E_RANGE and "beyond the input range +-10" in info_.value.detail
        assert c.status()["state"] == "IDLE"  # nothing started
        c.wave_pattern(100.0, 4.0)  # peak 8: within
        c.stop()
    rig = open_dm_rig(serial_cfg(config_path, emulators["frames"]))
    try:
        assert rig.input_limit == 10.0 and rig.n_actuators == 9 and rig.frame_shape == (64, 64)
        n_lines = len(rig.controller.traffic)
        with pytest.raises(ParameterError, match="amplitude: a command of peak 12"):
            rig.pattern_sine(p, 100.0, 6.0, [1e-3], 0.0, 1)
        with pytest.raises(ShapeError, match="pattern"):
            rig.pattern_sine(np.ones(8), 100.0, 1.0, [1e-3], 0.0, 1)
        assert len(rig.controller.traffic) == n_lines  # refused before anything was sent
    finally:
        rig.close()


def test_open_dm_rig_checks_the_mirror_and_the_sensor(emulators, config_path):
    from torchblur.hardware.serial_dm_rig import open_dm_rig

    emu = emulators["frames"]
    with pytest.raises(ConfigError, match="dm.n_across: the config's mirror .* the rig's 9"):
        open_dm_rig(serial_cfg(config_path, emu, "dm.n_across=4"))
    with pytest.raises(ConfigError, match="wfs.pitch_px: .* the rig's camera 64x64"):
        open_dm_rig(serial_cfg(config_path, emu, "wfs.pitch_px=20.0"))


# ---------------------------------------------------------------------- the frames


def test_frames_over_the_link_equal_the_simulated_rig(emulators, config_path):
    """Call by call (each one ARM, so the seeded random stream is drawn in the same order), the
    frames over the link are the SimulatedDMRig's of the same config and seed, bit for bit, at
    the same trigger times: the emulator renders with that rig's own renderer."""
    from torchblur.rig.factory import build_dm
    from torchblur.dm.plans import hadamard_plan
    from torchblur.hardware.serial_dm_rig import open_dm_rig

    _, _, sim = build_dm(load_config(str(config_path)))
    rig = open_dm_rig(serial_cfg(config_path, emulators["frames"]))
    rows = hadamard_plan(sim.geometry).patterns
    calls = [("dark", dict(n=3, exposure_s=0.01)), ("still", dict(n=2, exposure_s=2e-3, power=0.5)),
             ("pattern_sine", dict(pattern=rows[3], freq_hz=250.0, amplitude=0.3, exposures_s=[0.3 / 250], trigger_offset_s=1e-4,
                                   n_repeats=3, power=2.0)),
             ("pattern_sine", dict(pattern=rows[5], freq_hz=37.0, amplitude=0.5, exposures_s=[0.8 / 37], trigger_offset_s=0.0,
                                   n_repeats=2, power=0.5)),
             ("sine", dict(freq_hz=600.0, amplitude=0.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=2, input="a4")),
             ("pulse", dict(exposure_s=1e-4, trigger_offset_s=[0.0], pulse_time_s=2e-5, pulse_width_s=2e-5, n=2, power=50.0))]
    try:
        for name, kw in calls:
            a, b = getattr(sim, name)(**kw), getattr(rig, name)(**kw)
            assert a.frames.shape == b.frames.shape, name
            assert torch.equal(a.frames.to(torch.float64), b.frames.to(torch.float64)), name
            assert float(a.frames.max()) > float(a.frames.min()), name
            np.testing.assert_allclose(b.trigger_time_s.numpy(), a.trigger_time_s.numpy(), rtol=0, atol=1e-12, err_msg=name)
        moving = sim.pattern_sine(rows[3], 250.0, 0.3, [1.2e-3], 0.0, 1).frames
        still = sim.still(n=1, exposure_s=1.2e-3, power=1.0).frames
        assert float((moving - still).abs().max()) > 10  # the pattern moved the spots
    finally:
        rig.close()


def test_a_pattern_the_device_holds_wrong_stops_the_run(config_path):
    """A device (the emulator's state machine on a real pty, frames over TCP) that stores one
    weight wrong: PAT? after the load tells, the call is redone, then the run stops with an
    error that names the pattern."""
    from torchblur.hardware.serial_dm_rig import SerialDMRig

    dev, port, frames = device_on_a_pty(config_path)
    store = dev._pat

    def flip_sign_of_entry_0(start=None, values=()):
        out = store(start, values)
        if start == 0:
            dev.pattern[0] = -dev.pattern[0]
        return out

    dev._pat = flip_sign_of_entry_0
    rig = SerialDMRig.open(port, frames, timeout_s=2.0, retries=1)
    try:
        p = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0])
        with pytest.raises(AcquisitionStopped, match=r"gave up after 2 attempt\(s\).*PatternMismatch: pattern \[1, -1, 1, -1, 1, -1, "
                                                     rf"\.\.\.\] \(9 weights, crc {pattern_checksum(p)}\): after loading it") as info:
            rig.pattern_sine(p, 100.0, 1.0, [1e-3], 0.0, 1)
        assert isinstance(info.value.cause, PatternMismatch)
        assert not any(ln.startswith(b"WAVE") for d, ln in rig.controller.traffic if d == ">")  # never driven
    finally:
        rig.close()


def test_more_still_frames_than_one_arm_fires(config_path, monkeypatch):
    """configs/identify_dm.yaml's calibration takes 1024 still frames and an ARM fires at most
    MAX_COUNT (1000) triggers (the README's DM run over the serial link stopped with ERR 4 RANGE):
    the rig arms as many times as it takes, each within the limit (here lowered to 3 in the rig, for
    a cheap test), and the frames come back in order, one per trigger."""
    from torchblur.hardware import serial_rig
    from torchblur.hardware.serial_dm_rig import SerialDMRig

    assert serial_rig.MAX_COUNT == MAX_COUNT  # the rig's limit is the protocol's
    monkeypatch.setattr(serial_rig, "MAX_COUNT", 3)
    _, port, frames = device_on_a_pty(config_path)
    rig = SerialDMRig.open(port, frames, timeout_s=5.0, retries=0)
    try:
        cap = rig.still(7, 1e-4)
        arms = [ln.split()[-1] for d, ln in rig.controller.traffic if d == ">" and ln.startswith(b"ARM")]
        assert arms == [b"3", b"3", b"1"]
        assert cap.frames.shape[0] == 7 and (cap.frame_counter.diff() == 1).all()
    finally:
        rig.close()


def test_a_controller_reset_loads_the_pattern_again(config_path):
    """A controller that reboots in the middle of a pattern_sine forgets its pattern (zeros):
    the redone call finds that with PAT?, loads the pattern again and takes the frames, which are
    the SimulatedDMRig's second identical call (the first attempt rendered its frames too)."""
    from torchblur.rig.factory import build_dm
    from torchblur.dm.plans import hadamard_plan
    from torchblur.hardware.serial_dm_rig import SerialDMRig

    _, _, sim = build_dm(load_config(str(config_path)))
    p = hadamard_plan(sim.geometry).patterns[6]
    args = (p, 180.0, 0.4, [0.5 / 180], 2e-4, 2)
    _, port, frames = device_on_a_pty(config_path, "fault.start=wave", "fault.reset_after=1")
    rig = SerialDMRig.open(port, frames, timeout_s=2.0)
    try:
        cap = rig.pattern_sine(*args, power=1.5)
        sent = [ln for d, ln in rig.controller.traffic if d == ">"]
    finally:
        rig.close()
    assert rig.stats["resets"] == 1 and rig.stats["retries"] == 1
    assert sum(ln.startswith(b"PAT 0 ") for ln in sent) == 2  # loaded, lost in the reboot, loaded again
    sim.pattern_sine(*args, power=1.5)
    again = sim.pattern_sine(*args, power=1.5)
    assert torch.equal(cap.frames.to(torch.float64), again.frames.to(torch.float64))


# ---------------------------------------------------------------------- static holds (protocol 3)


@pytest.fixture(scope="module")
def hold_device(config_path):
    """The emulator's device (DM mode) in this process on a real pty, for the static-hold tests."""
    return device_on_a_pty(config_path)


def test_a_ladder_over_the_link_is_the_simulated_rigs(hold_device, config_path, monkeypatch):
    """pattern_ladder over the link is one transaction: the pattern loaded once, then per level
    ``WAVE pat HOLD u`` and its ARMs (chunked at MAX_COUNT, lowered to 3 here), STOP; its frames
    ``[K, n, H, W]`` are bit for bit the SimulatedDMRig's of the same config and seed called once per
    ARM (the emulator renders each ARM of a hold with that rig's pattern_ladder, one level, from the
    holds' own noise stream), and the held spots moved."""
    from torchblur.hardware import serial_rig
    from torchblur.rig.factory import build_dm
    from torchblur.dm.plans import hadamard_plan
    from torchblur.hardware.serial_dm_rig import SerialDMRig

    _, _, sim = build_dm(load_config(str(config_path)))
    p = hadamard_plan(sim.geometry).patterns[3]
    levels, n, te = [-1.5, 0.0, 1.5], 4, 2e-3
    monkeypatch.setattr(serial_rig, "MAX_COUNT", 3)
    rig = SerialDMRig.open(hold_device[1], hold_device[2], timeout_s=5.0, retries=0)
    try:
        cap = rig.pattern_ladder(pattern=p, levels=levels, n=n, exposure_s=te, power=1.5)
        sent = [ln.decode().strip() for d, ln in rig.controller.traffic if d == ">"]
    finally:
        rig.close()
    sent = sent[sent.index("POWER 1.5") - 2:]  # the transaction
    assert sent[:4] == ["STATUS?", "STOP", "POWER 1.5", "SETTLE AUTO"] and sent[-1] == "STOP"
    assert [ln for ln in sent if ln.startswith("WAVE")] == [f"WAVE pat HOLD {u!r}" for u in levels]
    assert [ln for ln in sent if ln.startswith("ARM")] == ["ARM 0.0 0.002 3", "ARM 0.0 0.002 1"] * 3
    assert sum(ln.startswith("PAT 0 ") for ln in sent) == 1  # loaded once, checked (PAT?) before every hold
    want = torch.cat([torch.cat([sim.pattern_ladder(pattern=p, levels=[u], n=m, exposure_s=te, power=1.5).frames for m in (3, 1)], 1)
                      for u in levels])
    assert cap.frames.shape == (3, n, 64, 64) and torch.equal(cap.frames.to(torch.float64), want.to(torch.float64))
    assert bool((cap.exposure_s == te).all()) and bool((cap.frame_counter.flatten().diff() == 1).all())
    assert cap.meta["kind"] == "pattern_ladder" and cap.meta["levels"] == levels
    moved = cap.frames[2].to(torch.float64).mean(0) - cap.frames[0].to(torch.float64).mean(0)
    assert float(moved.abs().max()) > 100  # the spots held at -1.5 and +1.5 are apart (2.5 px)


def test_bad_holds_are_refused_naming_them(hold_device):
    """The rig refuses before sending anything a ladder whose peak command is beyond RANGE (naming
    ``levels``) and bad arguments (naming them); the device refuses a hold within RANGE that would
    carry a spot out of its crop (ERR 4 naming levels: the simulated rig's own check), HOLD on an axis
    it lacks, without its level or with a level that is not a number, a negative trigger offset while
    holding, and a pattern load while holding."""
    from torchblur.hardware.serial_dm_rig import SerialDMRig

    rig = SerialDMRig.open(hold_device[1], hold_device[2], timeout_s=2.0, retries=0)
    p = np.zeros(9)
    p[[0, 4]] = [2.0, -0.5]
    try:
        c, n0 = rig.controller, len(rig.controller.traffic)
        for kw, err, match in (({"levels": [0.5, -6.0]}, ParameterError, "levels: a command of peak 12"),
                               ({"levels": []}, ParameterError, "levels: expected at least one value"),
                               ({"levels": [float("nan")]}, ParameterError, "levels: expected finite"),
                               ({"pattern": np.ones(8)}, ShapeError, r"pattern: expected \[9\]"), ({"n": 0}, ParameterError, "n: "),
                               ({"exposure_s": 5.0}, ParameterError, "exposure_s: expected at most"),
                               ({"power": -1.0}, ParameterError, "power: ")):
            with pytest.raises(err, match=match):
                rig.pattern_ladder(**{"pattern": p, "levels": [1.0], "n": 1, "exposure_s": 1e-3, **kw})
        assert len(c.traffic) == n0  # refused before anything was sent
        with pytest.raises(AcquisitionStopped, match=r"ERR 4 RANGE.*levels: spot \d+ would move 9.\d+ px"):
            rig.pattern_ladder(pattern=np.eye(9)[4], levels=[10.0], n=1, exposure_s=1e-3)  # within RANGE (10), beyond the crop
        c.stop()
        for line, code in (("WAVE x HOLD 1.0", E_AXIS), ("WAVE pat HOLD", E_ARGS), ("WAVE pat HOLD one", E_NUMBER)):
            with pytest.raises(DeviceError) as info:
                c.command(*line.split())
            assert info.value.code == code, line
        c.hold_pattern(0.5)
        with pytest.raises(DeviceError) as info:
            c.arm(-1e-3, 1e-3, 1)
        assert info.value.code == E_RANGE and "with a HOLD" in info.value.detail
        with pytest.raises(DeviceError) as info:
            c.load_pattern(p)
        assert info.value.code == E_BUSY
        c.stop()
    finally:
        rig.close()


def test_a_protocol_2_controller_has_no_ladder_and_says_so(config_path):
    """A protocol-2 firmware (``hold_wave=false``: ID? says 2, WAVE pat HOLD is ERR 2): the rig has
    no pattern_ladder (``getattr`` gives None; the attribute's error names the protocol) and says so
    in its events, which a run logs; a DM run with ``dm_plan.spot_model=ladder`` is refused before
    any frame, one with ``auto`` passes the rig check (and keeps the shifted still)."""
    from torchblur.hardware.serial_dm_rig import SerialDMRig
    from torchblur.identify.pipeline import identify
    from torchblur.rig.dm_contract import check_dm_rig

    _, port, frames = device_on_a_pty(config_path, "hold_wave=false")
    rig = SerialDMRig.open(port, frames, timeout_s=2.0)
    try:
        assert rig.device["protocol"] == 2 and getattr(rig, "pattern_ladder", None) is None
        with pytest.raises(AttributeError, match=r"pattern_ladder: the controller on .* speaks protocol 2; static holds need protocol 3"):
            rig.pattern_ladder(pattern=np.ones(9), levels=[1.0], n=1, exposure_s=1e-3)
        assert any("no static holds" in e and "auto keeps the shifted still" in e for e in rig.events)
        with pytest.raises(ConfigError, match=r"dm_plan\.spot_model: ladder needs static holds .* SerialDMRig has no pattern_ladder"):
            identify(load_config(str(config_path), ["dm_plan.spot_model=ladder"]), rig=rig, progress=False)
        check_dm_rig(rig, load_config(str(config_path), ["dm_plan.spot_model=auto"]))
        with pytest.raises(DeviceError) as info:
            rig.controller.hold_pattern(1.0)
        assert info.value.code == E_ARGS
        assert not any(ln.startswith(b"ARM") for d, ln in rig.controller.traffic if d == ">")  # no frame was taken
    finally:
        rig.close()


# ---------------------------------------------------------------------- the identification


@pytest.fixture(scope="module")
def runs(emulators, config_path, tmp_path_factory):
    """torchblur.identify over the link (SerialDMRig on the "run" emulator, recorded) and on the
    SimulatedDMRig, the same config and seed: ``(link, sim, the link's stats, its recording's folder)``."""
    from torchblur.identify.pipeline import identify
    from torchblur.hardware.serial_dm_rig import open_dm_rig

    cfg = serial_cfg(config_path, emulators["run"])
    rig = open_dm_rig(cfg)
    exp_dir = tmp_path_factory.mktemp("link") / "experiment"
    try:
        link = identify(cfg, rig=rig, progress=False, record=exp_dir)
        stats = dict(rig.stats)
    finally:
        rig.close()
    return link, identify(load_config(str(config_path)), progress=False), stats, exp_dir


def _z(d, C):
    """|Re|, |Im| of ``d`` over their stds from the (Re, Im) covariances ``C [..., 2, 2]``."""
    return np.abs(np.stack([d.real, d.imag], -1)) / np.sqrt(np.stack([C[..., 0, 0], C[..., 1, 1]], -1))


def test_identify_dm_over_the_link_gives_the_simulated_rigs_D(runs):
    """The same D as on the SimulatedDMRig, to the noise: the two runs have the same mirror,
    sensor, plan, schedule and expected frames, but not the same noise draws (the link takes a
    pattern's two exposures with two ARMs and the pulse scan with one PULSE per offset, so the
    seeded stream is drawn in another order; and a frequency's amplitude follows the fits that
    have finished when it starts, on a worker thread). So D_link - D_sim is the difference of
    two independent estimates: every element within 5 of their combined std (99 %; measured
    0.62 median, 2.6 at 99 %, 3.2 largest), the median below 1 (a pattern driven wrong, a sign
    or an actuator off by one, is tens of stds), and the link's D within 5 stds of the truth."""
    link, sim, stats, _ = runs
    assert stats["retries"] == 0 and stats["resets"] == 0
    assert link.plan.kind == sim.plan.kind == "hadamard" and link.n_frames == sim.n_frames == 16 * 4 * 2
    np.testing.assert_array_equal(link.plan.patterns, sim.plan.patterns)
    assert link.n_failed == 0 and link.truth_D is None and link.mirror is None  # no truth on a real rig
    live = ~sim.mirror.dead
    z = _z((link.D - sim.D)[:, live], (link.D_cov + sim.D_cov)[:, live])
    assert np.quantile(z, 0.99) < 5.0 and np.median(z) < 1.0
    z_truth = _z((link.D - sim.truth_D)[:, live], link.D_cov[:, live])
    assert np.quantile(z_truth, 0.99) < 5.0
    assert list(link.actuators.status) == list(sim.actuators.status) and link.actuators.status[2] == "dead"
    D0 = link.G * sim.mirror.gain
    assert np.sqrt(np.mean((link.actuators.static_column - D0) ** 2)) / np.abs(D0).max() < 0.01


def test_auto_holds_the_patterns_still_over_the_link(runs):
    """``dm_plan.spot_model`` auto (the default) over the link takes its test holds through the
    rig's pattern_ladder (WAVE pat HOLD), as on the SimulatedDMRig: recorded as the group
    ``dm_ladder/test`` (every pattern at its two end levels, 4 frames each), the decision made from
    them (a shifted still explains torchblur's Gaussian spots: shifted, the simulated run's decision),
    never skipped for want of the method."""
    link, sim, _, exp_dir = runs
    lines = [json.loads(ln) for ln in (exp_dir / "manifest.jsonl").read_text().splitlines()]
    gl = [ln for ln in lines if ln["group"] == "dm_ladder/test"]
    assert len(gl) == 16 * 2 * 4 and {ln["kind"] for ln in gl} == {"dm_ladder"} and {ln["method"] for ln in gl} == {"pattern_ladder"}
    assert all(ln["call_shape"] == [2, 4] and ln["args"]["pattern"] == link.plan.patterns[ln["call"]].tolist() for ln in gl)
    assert all(ln["args"]["levels"][1] == -ln["args"]["levels"][0] > 0 and ln["args"]["n"] == 4 for ln in gl)
    assert link.spot_model == sim.spot_model == "shifted"
    assert any("dm spot model: shifted (auto: a shifted still explains the spots held still" in line for line in link.log)
    assert not any("holds no pattern_ladder" in line for line in link.log)


def test_cli_runs_a_dm_config_over_the_link(emulators, config_path, runs, tmp_path, capsys, monkeypatch):
    """``torchblur identify --config DM.yaml --port P --frames F`` opens a SerialDMRig on the
    emulator and runs the DM plan's stages on it (here returning the run above: the CLI's own
    part, the run's log carried as the plan's result carries it); no truth errors on a real rig."""
    from torchblur.identify import pipeline
    from torchblur.identify.record import LOGGER
    from torchblur.hardware.serial_dm_rig import SerialDMRig
    from torchblur.cli import main

    seen = {}

    def fake_run_stages(run):
        seen["rig"] = rig = run.rig
        assert isinstance(rig, SerialDMRig) and rig.n_actuators == 9 and rig.controller.is_open
        for line in runs[0].log:  # the run's messages, as its stages log them
            LOGGER.info(line)
        return dataclasses.replace(runs[0])

    monkeypatch.setattr(pipeline, "run_stages", fake_run_stages)
    info = emulators["frames"].info
    rc = main(["identify", "--config", str(config_path), "--out", str(tmp_path / "run"), "--json", "--port", info["serial"],
               "--frames", info["frames"], "report.figures=false"])  # no figure checked here
    assert rc == 0
    out = capsys.readouterr()
    summary = json.loads(out.out.strip().splitlines()[-1])
    assert summary["truth_errors"] is None and summary["plan"] == "hadamard"
    assert not seen["rig"].controller.is_open  # closed after the run
    assert "rig:\n  kind: serial" in (tmp_path / "run" / "config.yaml").read_text()
    assert "serial link: SerialDMRig(" in (tmp_path / "run" / "report.txt").read_text()


def test_a_device_without_a_mirror_has_no_pattern_drive():
    from torchblur.hardware.emulator import EmulatedDevice, load_emulator_config
    from torchblur.hardware.protocol import parse_reply

    dev = EmulatedDevice(load_emulator_config(None, ["camera.height=16", "camera.width=16"]), lambda msg: None)
    ask = lambda line: parse_reply(dev.handle(line.encode() + b"\n"))  # noqa: E731
    assert ask("ID?").fields["axes"] == "x" and ask("ACT?").fields["n"] == "0"
    assert ask("PAT 0 1.0").code == E_AXIS and ask("PAT?").code == E_AXIS and ask("WAVE pat SINE 10 1").code == E_AXIS
    assert ask("WAVE pat HOLD 1").code == E_AXIS and ask("WAVE x HOLD 1").code == E_AXIS  # a hold drives a pattern only


def test_the_emulator_config_has_a_dm_mode(config_path):
    from torchblur.hardware.emulator import load_emulator_config

    cfg = load_emulator_config(str(config_path))  # the identify config: dm_plan, sweep, excitation skipped
    assert cfg.dm.enabled and cfg.wfs.n_across == 4 and cfg.seed == 3
    assert not load_emulator_config(None).dm.enabled
    with pytest.raises(ConfigError, match="dm.coupling"):
        load_emulator_config(str(config_path), ["dm.coupling=1.5"])
    with pytest.raises(ConfigError, match="wfs.pitch_px"):
        load_emulator_config(str(config_path), ["wfs.pitch_px=4"])


SLOW = pytest.mark.skipif(not os.environ.get("TORCHBLUR_SLOW"), reason="a whole DM run with the ladder over the link and its "
                          "re-fit (31 s on the shared 2 cores); TORCHBLUR_SLOW=1")


@SLOW
def test_a_ladder_run_over_the_link_is_recorded_and_refits(emulators, config_path, tmp_path):
    """``torchblur identify --port --frames`` with ``dm_plan.spot_model=ladder`` (the smallest ladder: 4
    levels, 2 frames each; 3 frequencies) completes over the link: every pattern's ladder is taken with
    WAVE pat HOLD and recorded as its own group ``dm_ladder/PPP``, and a re-fit replays them to the same
    actuators.csv."""
    from torchblur import cli

    info, run = emulators["run"].info, tmp_path / "run"
    keys = ["sweep.n=3", "report.figures=false", "dm_plan.spot_model=ladder", "dm_plan.ladder_levels=4", "dm_plan.ladder_frames=2"]
    assert cli.main(["identify", "--config", str(config_path), "--out", str(run), "--quiet", "--port", info["serial"],
                     "--frames", info["frames"], *keys]) in (0, 4)
    lines = [json.loads(ln) for ln in (run / "experiment" / "manifest.jsonl").read_text().splitlines()]
    held = [ln for ln in lines if ln["kind"] == "dm_ladder"]
    assert sorted({ln["group"] for ln in held}) == [f"dm_ladder/{p:03d}" for p in range(16)]
    assert all(ln["call_shape"] == [4, 2] and ln["method"] == "pattern_ladder" for ln in held) and len(held) == 16 * 4 * 2
    report = (run / "report.txt").read_text()
    assert "dm spot model: ladder of 16 patterns x 4 levels x 2 frames" in report and "serial link: SerialDMRig(" in report
    assert cli.main(["fit", str(run), "--out", str(tmp_path / "refit"), "--quiet"]) in (0, 4)
    assert (tmp_path / "refit" / "dm" / "actuators.csv").read_text() == (run / "dm" / "actuators.csv").read_text()
