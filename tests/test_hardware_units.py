"""Units of the hardware adapter without a separate process: the emulated device's replies,
the camera channel's wire format, the experiment directory (atomic writes, repair, replay),
the SDK camera's counter mapping, and the config keys of rig.kind=serial."""
import json
import os
import threading
import time

import numpy as np
import pytest
import torch

from torchblur.config import load_config
from torchblur.errors import ConfigError
from torchblur.hardware import CameraInfo, Experiment, SDKCamera
from torchblur.hardware.emulator import EmulatedDevice, EmulatorConfig, _LineBuffer, load_emulator_config
from torchblur.hardware.errors import FrameTimeout, GarbageReply, RecordingError
from torchblur.hardware.frames import WireDecoder, decode_frame, encode_message, frame_message
from torchblur.hardware.protocol import parse_reply
from torchblur.hardware.recording import atomic_write_bytes
from torchblur.rig.base import Capture

# ---------------------------------------------------------------------- the emulated device


@pytest.fixture
def device():
    """A device whose camera holds every frame until released (so 'pending' is deterministic)."""
    gate = threading.Event()
    sent = []

    def send(msg):
        gate.wait(10)
        sent.append(msg)

    cfg = load_emulator_config(None, ["camera.height=16", "camera.width=16"])
    dev = EmulatedDevice(cfg, send)
    dev.sent, dev.gate = sent, gate
    yield dev
    gate.set()


def ask(dev, line):
    r = parse_reply(dev.handle(line.encode() + b"\n"))
    return r


def test_device_replies_and_state(device):
    r = ask(device, "ID?")
    assert r.ok and r.fields["protocol"] == "3" and r.fields["axes"] == "x"
    st = ask(device, "STATUS?").fields
    assert st["state"] == "IDLE" and st["frames"] == "0" and st["pending"] == "0"
    assert ask(device, "WAVE y SINE 10 1").code == 5  # the emulator has axis x only
    assert ask(device, "ARM 0 5 1").code == 4  # longer than the camera's max exposure (1 s)
    assert ask(device, "ARM -1 0.01 1").code == 4  # no waveform: the offset is a delay >= 0
    assert ask(device, "WAVE x SINE 10 1").ok and ask(device, "STATUS?").fields["state"] == "RUNNING"
    assert ask(device, "PULSE 0 0 2e-5 2e-4 2").code == 6  # PULSE needs the mirror still
    r = ask(device, "ARM 0.001 0.01 3")
    assert r.ok and r.fields == {"first": "0", "count": "3"}
    assert ask(device, "STATUS?").fields["state"] == "ARMED"
    assert ask(device, "ARM 0.001 0.01 3").code == 6  # frames pending: BUSY
    assert ask(device, "WAVE x SINE 20 1").code == 6
    assert ask(device, "STOP").ok
    st = ask(device, "STATUS?").fields
    assert st["state"] == "IDLE" and st["frames"] == "3" and st["pending"] == "0" and float(st["clock"]) > 0
    boot = st["boot"]
    r = ask(device, "RESET")
    assert r.ok and r.fields["boot"] != boot
    st = ask(device, "STATUS?").fields
    assert st["frames"] == "0" and st["boot"] == r.fields["boot"] and float(st["clock"]) == 0
    assert ask(device, "PING t1").fields["token"] == "t1"
    assert ask(device, "SETTLE AUTO").fields["s"] == "AUTO"


def test_device_schedule_matches_the_simulated_rig(device):
    """ARM's triggers fall where SimulatedRig.sine puts them: whole periods + offset."""
    device.gate.set()
    f, off = 50.0, 0.003
    ask(device, "POWER 0.5")
    ask(device, "SETTLE 0.1")
    ask(device, "WAVE x SINE 50 0.2")
    first = int(ask(device, f"ARM {off} 0.004 2").fields["first"])
    for _ in range(500):
        if len(device.sent) >= 2:
            break
        time.sleep(0.01)
    frames = [decode_frame(*decode_one(m)) for m in device.sent[:2]]
    assert [fr.counter for fr in frames] == [first, first + 1]
    for fr in frames:
        k = (fr.trigger_time_s - off) * f
        assert abs(k - round(k)) < 1e-9 and fr.trigger_time_s >= 0.1
        assert fr.exposure_s == 0.004 and fr.dtype == "uint16" and fr.boot == ask(device, "STATUS?").fields["boot"]
    assert ask(device, "STATUS?").fields["pending"] == "0"


def test_multi_tone_waveform_renders_like_the_sine(device):
    """A one-tone MULTI (steady state) and a SINE of the same tone, triggered at the same phase
    after a long settle, put the spot's centroid at the same place."""
    device.gate.set()

    def centroid_x(wave):
        device.sent.clear()
        ask(device, "STOP")
        ask(device, "POWER 1")
        ask(device, "SETTLE 0.5")
        assert ask(device, wave).ok
        assert ask(device, "ARM 0.0007 0.0005 1").ok
        for _ in range(500):
            if device.sent:
                break
            time.sleep(0.01)
        img = decode_frame(*decode_one(device.sent[0])).data - 100.0
        img = img.clamp_min(0)
        return float((img.sum(0) * torch.arange(16.0, dtype=img.dtype)).sum() / img.sum())

    x_sine = centroid_x("WAVE x SINE 100 0.2")
    x_multi = centroid_x("WAVE x MULTI 100:0.2:0")
    x_still = centroid_x("WAVE x MULTI 100:0:0")
    assert abs(x_sine - x_still) > 1.0  # the spot moved ...
    assert abs(x_sine - x_multi) < 0.05  # ... to the same place
    assert ask(device, "WAVE x MULTI 100:0.1:0,300:0.05:1.2").fields["tones"] == "2"
    assert ask(device, "STOP").ok
    assert ask(device, "WAVE x MULTI 100:0.1:0,150:0.05:0").code == 4  # 150 Hz is off the first tone's grid


def decode_one(msg):
    d = WireDecoder()
    d.feed(msg)
    return d.next()


def test_line_buffer_splits_and_flags_long_lines():
    lb = _LineBuffer()
    assert lb.feed(b"ID?\nSTA") == [b"ID?\n"]
    assert lb.feed(b"TUS?\n") == [b"STATUS?\n"]
    assert lb.feed(b"x" * 300) == []
    assert lb.feed(b"yyy\nSTOP\n") == [None, b"STOP\n"]  # None: answer ERR 7 for the long line


def test_emulator_config_names_the_key():
    with pytest.raises(ConfigError, match=r"^transport"):
        load_emulator_config(None, ["transport=usb"])
    with pytest.raises(ConfigError, match=r"^fault\.drop_frame"):
        load_emulator_config(None, ["fault.drop_frame=-5"])
    with pytest.raises(ConfigError, match=r"^camera\.height"):
        load_emulator_config(None, ["camera.height=2"])
    with pytest.raises(ConfigError, match=r"^sweep"):
        load_emulator_config(None, ["sweep.n=3"])  # identify-only keys are not emulator keys
    assert isinstance(load_emulator_config(None, ["plant.delay_s=1e-5", "seed=4"]), EmulatorConfig)


# ---------------------------------------------------------------------- wire format


def test_wire_format_round_trip_and_garbage():
    arr = (np.arange(12).reshape(3, 4) * 300).astype(np.uint16)
    msg = frame_message(arr, counter=7, timestamp_s=1.25, trigger_time_s=0.5, trigger_offset_s=1e-3, exposure_s=2e-3, boot="ab")
    dec = WireDecoder()
    for b in [msg[:3], msg[3:20], msg[20:]]:  # arrives in pieces
        dec.feed(b)
    fr = decode_frame(*dec.next())
    assert fr.counter == 7 and fr.exposure_s == 2e-3 and fr.dtype == "uint16" and fr.boot == "ab"
    assert torch.equal(fr.data, torch.from_numpy(arr.astype(np.float64)))
    assert dec.next() is None
    hello = encode_message({"type": "hello"})
    dec.feed(hello)
    assert dec.next()[0] == {"type": "hello"}
    dec.feed(b"JUNK" + msg)
    with pytest.raises(GarbageReply):
        dec.next()
    bad = WireDecoder()
    bad.feed(encode_message({"type": "frame", "shape": [5, 5], "dtype": "uint16", "counter": 0, "exposure_s": 1.0}, b"12"))
    with pytest.raises(GarbageReply):
        decode_frame(*bad.next())


# ---------------------------------------------------------------------- experiment directory


INFO = CameraInfo(frame_shape=(6, 5), frame_rate_hz=30.0, max_exposure_s=1.0, readout_s=1e-3, name="unit")


def cap(n, shape=None, start=0, value=100.0):
    shape = shape or (n,)
    N = int(np.prod(shape))
    # each frame its own pixels (a frame repeated byte for byte is refused as a copy): + 7 per frame, + 3 per start
    ramp = torch.arange(N * 30, dtype=torch.float64) % 50 + 7 * torch.arange(N, dtype=torch.float64).repeat_interleave(30) + 3 * start
    frames = (value + ramp.reshape(shape + (6, 5))).round()
    return Capture(frames=frames, exposure_s=torch.full(shape, 1e-3, dtype=torch.float64), trigger_offset_s=torch.zeros(shape, dtype=torch.float64),
                   trigger_time_s=torch.arange(N, dtype=torch.float64).reshape(shape) * 0.04,
                   frame_counter=torch.arange(start, start + N).reshape(shape), meta={"kind": "x", "power": 0.5})


def make_experiment(path):
    exp = Experiment.create(path, config_yaml="seed: 0\n", camera=INFO)
    exp.start_session({"kind": "test"})
    exp.record("dark", "dark", [("dark", {"n": 3, "exposure_s": 1e-3}, cap(3))])
    exp.record("sweep/x/000", "sweep", [("sine", {"freq_hz": 5.0}, cap(4, (2, 2), start=3))],
               labels={"input": "x", "freq_hz": 5.0, "amplitude": 0.3, "power": 0.5})
    return exp


def test_experiment_round_trip(tmp_path):
    exp = make_experiment(tmp_path / "e")
    lines = [json.loads(x) for x in (tmp_path / "e" / "manifest.jsonl").read_text().splitlines()]
    assert len(lines) == 7
    sw = [ln for ln in lines if ln["kind"] == "sweep"]
    assert [(ln["exposure_index"], ln["repeat"]) for ln in sw] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all(ln["input"] == "x" and ln["freq_hz"] == 5.0 and ln["amplitude"] == 0.3 for ln in sw)
    assert {ln["dtype"] for ln in lines} == {"uint16"}
    meta = json.loads((tmp_path / "e" / "experiment.json").read_text())
    assert meta["schema_version"] == 1 and meta["camera"]["frame_shape"] == [6, 5]
    again = Experiment.open(tmp_path / "e")
    (m, args, c), = again.load_calls("sweep/x/000")
    want = cap(4, (2, 2), start=3)
    assert m == "sine" and args == {"freq_hz": 5.0} and torch.equal(c.frames, want.frames)
    assert torch.equal(c.frame_counter, want.frame_counter) and torch.equal(c.trigger_time_s, want.trigger_time_s)
    assert again.camera_info == INFO
    with pytest.raises(RecordingError):
        again.record("dark", "dark", [("dark", {}, cap(1))])
    with pytest.raises(RecordingError):
        Experiment.create(tmp_path / "e", config_yaml="", camera=INFO)


def test_torn_manifest_and_leftovers_are_repaired(tmp_path):
    make_experiment(tmp_path / "e")
    d = tmp_path / "e"
    good = (d / "manifest.jsonl").read_bytes()
    # a crash mid-append of the next group: two of its four lines, the second torn
    lines = good.splitlines(keepends=True)
    torn = lines[-4].replace(b"sweep/x/000", b"sweep/x/001")
    (d / "manifest.jsonl").write_bytes(good + torn + lines[-3][:40])
    (d / "frames" / ".sweep_x_001.tif.123.tmp").write_bytes(b"half")  # a temporary left by a killed writer
    (d / "frames" / "sweep_x_002.tif").write_bytes(b"orphan")  # a file whose lines never made it
    ro = Experiment.open(d, writable=False)
    assert set(ro.groups) == {"dark", "sweep/x/000"}
    assert (d / "manifest.jsonl").read_bytes() != good  # read-only: nothing changed yet
    exp = Experiment.open(d)
    assert exp.repaired["dropped_groups"] == ["sweep/x/001"] and exp.repaired["torn_line"]
    assert (d / "manifest.jsonl").read_bytes() == good
    assert sorted(p.name for p in (d / "frames").iterdir()) == ["dark.tif", "sweep_x_000.tif"]
    # a corrupted file invalidates its group
    f = d / "frames" / "dark.tif"
    f.write_bytes(f.read_bytes()[:-10] + b"0123456789")
    exp = Experiment.open(d)
    assert "dark" not in exp.groups and exp.repaired["dropped_groups"] == ["dark"]


def test_atomic_write_leaves_nothing_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "a.bin"
    atomic_write_bytes(target, b"one")

    def boom(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b"two")
    monkeypatch.undo()
    assert target.read_bytes() == b"one" and sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_schema_version_is_checked(tmp_path):
    make_experiment(tmp_path / "e")
    p = tmp_path / "e" / "experiment.json"
    meta = json.loads(p.read_text())
    meta["schema_version"] = 99
    p.write_text(json.dumps(meta))
    with pytest.raises(RecordingError, match="schema_version"):
        Experiment.open(tmp_path / "e")
    with pytest.raises(RecordingError):
        Experiment.open(tmp_path / "nothing")


# ---------------------------------------------------------------------- SDK camera


class FakeSDK(SDKCamera):
    def __init__(self):
        self.cam_counter = 1000  # the camera counts from its own power-up
        self.queue = []
        super().__init__()

    def _connect(self):
        pass

    def _disconnect(self):
        pass

    def _camera_info(self):
        return INFO

    def _configure(self, exposure_s, count):
        self.te = exposure_s

    def _next_camera_counter(self):
        return self.cam_counter

    def _grab(self, timeout_s):
        if not self.queue:
            return None
        return self.queue.pop(0)

    def expose(self, n, drop=()):
        for i in range(n):
            c = self.cam_counter
            self.cam_counter += 1
            if i not in drop:
                self.queue.append((np.zeros((6, 5), np.uint16), c, 0.0, self.te))


def test_sdk_camera_maps_counters_before_the_first_frame():
    cam = FakeSDK()
    cam.prepare(1e-3, 3)
    cam.bind(17, 3)  # the controller armed triggers 17, 18, 19
    cam.expose(3, drop=(0,))  # the first frame is lost on the link
    fr = cam.read(0.1)
    assert fr.counter == 18 and fr.meta["camera_counter"] == 1001  # a gap the rig sees, not a silent shift
    assert cam.read(0.1).counter == 19
    with pytest.raises(FrameTimeout):
        cam.read(0.1)


# ---------------------------------------------------------------------- config


@pytest.mark.parametrize("overrides,key", [
    (["rig.kind=serial"], "rig.port"),
    (["rig.kind=serial", "rig.port=/dev/pts/9"], "rig.frames"),
    (["rig.kind=serial", "rig.port=/dev/pts/9", "rig.frames=udp://x"], "rig.frames"),
    (["rig.kind=serial", "rig.port=/dev/pts/9", "rig.frames=tcp://127.0.0.1"], "rig.frames"),
    (["rig.kind=usb"], "rig.kind"),
    (["rig.timeout_s=-1"], "rig.timeout_s"),
    (["rig.retries=1.5"], "rig.retries"),
    (["fit.chunk_points=-2"], "fit.chunk_points"),
])
def test_serial_rig_config_names_the_key(overrides, key):
    with pytest.raises(ConfigError) as info:
        load_config(None, overrides)
    assert str(info.value).startswith(key)


def test_serial_rig_config_accepts_ports_and_cameras():
    cfg = load_config(None, ["rig.kind=serial", "rig.port=socket://127.0.0.1:5000", "rig.frames=tcp://127.0.0.1:6000"])
    assert cfg.rig.kind == "serial" and cfg.rig.retries == 2
    cfg = load_config(None, ["rig.kind=serial", "rig.port=/dev/ttyACM0", "rig.frames=mylab.cameras:Basler"])
    assert cfg.rig.frames == "mylab.cameras:Basler"
