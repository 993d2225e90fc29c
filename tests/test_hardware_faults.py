"""Issue 16: the protocol's recovery as documented (resync on ERR 7, retry on ERR 8), a frame
server that no client can block, malformed frame messages and NaN pixels as transport
errors, the emulator's argument ranges."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from torchblur.hardware import emulator
from torchblur.hardware.emulator import EmulatedDevice, FrameServer, load_emulator_config
from torchblur.hardware.errors import AcquisitionStopped, DeviceError, GarbageReply
from torchblur.hardware.frames import CameraInfo, WireDecoder, decode_frame, encode_message, frame_message
from torchblur.hardware.protocol import E_RANGE, parse_reply
from torchblur.hardware.serial_rig import SerialRig

INFO = CameraInfo(frame_shape=(4, 3), frame_rate_hz=30.0, max_exposure_s=1.0, readout_s=1e-3, name="unit")
GOOD = {"type": "frame", "counter": 3, "exposure_s": 1e-3, "shape": [4, 3], "dtype": "uint16", "boot": "b"}


@pytest.mark.parametrize("change", [
    {"counter": "3"}, {"counter": None}, {"counter": 3.5}, {"exposure_s": None}, {"exposure_s": "soon"},
    {"exposure_s": -1.0}, {"shape": [4]}, {"shape": "4x3"}, {"shape": [0, 3]}, {"dtype": "object"},
    {"trigger_time_s": "x"}, {"timestamp_s": [1]},
])
def test_malformed_frame_headers_are_garbage(change):
    header = {**GOOD, **change}
    payload = np.zeros((4, 3), np.uint16).tobytes()
    with pytest.raises(GarbageReply):
        decode_frame(header, payload)
    assert decode_frame(GOOD, payload).counter == 3


def test_non_object_headers_and_nan_pixels_are_garbage_and_the_stream_stays_in_step():
    dec = WireDecoder()
    dec.feed(encode_message([1, 2], b""))  # a header that is a list
    with pytest.raises(GarbageReply):
        dec.next()
    nan = np.full((4, 3), np.nan)
    dec.feed(frame_message(nan, counter=1, exposure_s=1e-3))
    with pytest.raises(GarbageReply, match="NaN"):
        decode_frame(*dec.next())


@pytest.mark.parametrize("code,recovers", [(1, False), (2, False), (3, False), (4, False), (5, False),
                                           (6, True), (7, True), (8, True)])
def test_err_7_resyncs_and_err_8_retries(code, recovers):
    """SerialRig._call: ERR 6/7/8 redo the transaction after a resync; 1-5 stop at once."""
    rig = SerialRig.__new__(SerialRig)
    rig.stats = {"calls": 0, "retries": 0}
    rig.retries, rig.reconnects, rig._dirty = 2, 1, False
    resyncs = []
    rig._recover = lambda: resyncs.append(1)
    rig._note = lambda msg: None
    calls = []

    def once():
        calls.append(1)
        if len(calls) == 1:
            raise DeviceError(code, "X", "noise", "ARM 1 2 3")
        return "done"

    if recovers:
        assert rig._call("point", once) == "done" and resyncs == [1]
    else:
        with pytest.raises(AcquisitionStopped):
            rig._call("point", once)
        assert len(calls) == 1


def _wait_for_client(srv, old=None):
    deadline = time.monotonic() + 10
    while (srv._conn is None or srv._conn is old) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert srv._conn is not None and srv._conn is not old
    return srv._conn


def test_a_client_that_never_reads_does_not_block_the_channel(monkeypatch):
    monkeypatch.setattr(emulator, "SEND_TIMEOUT_S", 0.3)
    srv = FrameServer(INFO)
    stuck = socket.create_connection(("127.0.0.1", srv.port))
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    _wait_for_client(srv)
    big = frame_message(np.zeros((1024, 1024), np.uint16), counter=0, exposure_s=1e-3)
    results = [srv.send(big) for _ in range(64)]  # 128 MB to a client that never reads
    assert False in results  # the client was dropped (after SEND_TIMEOUT_S), not waited for
    fresh = socket.create_connection(("127.0.0.1", srv.port))
    fresh.settimeout(0.5)
    dec = WireDecoder()
    deadline = time.monotonic() + 20
    got = []
    small = frame_message(np.ones((4, 3), np.uint16), counter=7, exposure_s=1e-3)
    while len(got) < 2 and time.monotonic() < deadline:
        srv.send(small)
        try:
            dec.feed(fresh.recv(1 << 16))
        except socket.timeout:
            pass
        while (m := dec.next()) is not None:
            got.append(m[0])
    assert got[0]["type"] == "hello" and any(h.get("counter") == 7 for h in got[1:])
    stuck.close()
    fresh.close()


def test_the_frame_server_send_never_holds_the_lock_across_sendall(monkeypatch):
    srv = FrameServer(INFO)
    c = socket.create_connection(("127.0.0.1", srv.port))
    _wait_for_client(srv)
    inside = threading.Event()
    release = threading.Event()

    class SlowConn:
        def settimeout(self, t):
            pass

        def sendall(self, data):
            inside.set()
            release.wait(5)

        def close(self):
            pass

    srv._conn = SlowConn()
    t = threading.Thread(target=srv.send, args=(b"x",))
    t.start()
    assert inside.wait(5)
    assert srv._lock.acquire(timeout=1)  # free while a send is under way
    srv._lock.release()
    release.set()
    t.join(5)
    c.close()


@pytest.mark.parametrize("line", ["SETTLE 1e300", "POWER 1e300", "WAVE x SINE 1e300 1", "WAVE x SINE 10 1e300"])
def test_emulator_range_checks_its_arguments(line):
    cfg = load_emulator_config(None, ["camera.height=16", "camera.width=16"])
    dev = EmulatedDevice(cfg, lambda msg: None)
    r = parse_reply(dev.handle(line.encode() + b"\n"))
    assert r.code == E_RANGE
    assert parse_reply(dev.handle(b"SETTLE 0.5\n")).word == "SETTLE"


def test_junk_on_the_camera_channel_is_skipped_to_the_next_message():
    dec = WireDecoder()
    good = frame_message(np.ones((4, 3), np.uint16), counter=5, exposure_s=1e-3)
    dec.feed(b"\x00junk TBF noise" + good)
    with pytest.raises(GarbageReply):
        dec.next()
    assert decode_frame(*dec.next()).counter == 5


@pytest.mark.parametrize("hello", [
    encode_message([1, 2]), encode_message({"type": "hello", "camera": {"frame_shape": "big"}}),
    encode_message({"type": "hello"}), b"TBF1" + b"\xff" * 8,
])
def test_a_hostile_camera_greeting_is_a_hardware_error(hello):
    from torchblur.hardware.errors import HardwareError
    from torchblur.hardware.frames import EmulatorFrames

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def serve():
        conn, _ = srv.accept()
        conn.sendall(hello)
        time.sleep(1.0)
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    with pytest.raises(HardwareError):
        EmulatorFrames(f"tcp://127.0.0.1:{srv.getsockname()[1]}", connect_timeout_s=0.5)
    srv.close()
