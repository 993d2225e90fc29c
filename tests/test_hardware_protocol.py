"""The controller's line protocol: every command, every error reply, and the pyserial client
(real pyserial on a real pseudo-terminal against an in-process fake device)."""
import math
import os
import threading
import time
import tty

import pytest

from torchblur.hardware import Controller
from torchblur.hardware.errors import ConnectionLost, DeviceError, GarbageReply, ReplyTimeout
from torchblur.hardware.protocol import (E_ARGS, E_AXIS, E_LINE, E_NUMBER, E_RANGE, E_UNKNOWN, ERROR_CODES, MAX_LINE,
                                         Command, ProtocolViolation, format_command, format_err, format_ok, parse_command,
                                         parse_reply)

# ---------------------------------------------------------------------- grammar

GOOD = [
    ("ID?", Command("ID?")),
    ("STATUS?", Command("STATUS?")),
    ("RESET", Command("RESET")),
    ("STOP", Command("STOP")),
    ("PING abc-1_2", Command("PING", ("abc-1_2",))),
    ("POWER 0", Command("POWER", (0.0,))),
    ("POWER 2.5e-1", Command("POWER", (0.25,))),
    ("SETTLE AUTO", Command("SETTLE", (None,))),
    ("SETTLE 0.125", Command("SETTLE", (0.125,))),
    ("WAVE x SINE 200 0.5", Command("WAVE", ("x", "SINE", 200.0, 0.5))),
    ("WAVE y SINE 1e3 -0.25", Command("WAVE", ("y", "SINE", 1000.0, -0.25))),
    ("WAVE x MULTI 100:0.5:0,200:0.25:1.5", Command("WAVE", ("x", "MULTI", ((100.0, 0.5, 0.0), (200.0, 0.25, 1.5))))),
    ("ARM 0.00124 0.0015 2", Command("ARM", (0.00124, 0.0015, 2))),
    ("ARM -1e-4 .5 1000", Command("ARM", (-1e-4, 0.5, 1000))),
    ("PULSE 0 -2e-05 2e-05 0.0002 2", Command("PULSE", (0.0, -2e-05, 2e-05, 2e-4, 2))),
    ("STOP\r\n", Command("STOP")),
]


@pytest.mark.parametrize("line,cmd", GOOD, ids=[g[0].strip() for g in GOOD])
def test_every_command_parses(line, cmd):
    assert parse_command(line) == cmd
    assert parse_command(line.encode()) == cmd  # the device parses bytes the same way


BAD = [
    ("", E_UNKNOWN),
    ("FOO", E_UNKNOWN),
    ("id?", E_UNKNOWN),  # case matters
    ("ID? x", E_ARGS),
    ("STATUS? 1", E_ARGS),
    ("STOP now", E_ARGS),
    ("RESET 1", E_ARGS),
    ("PING", E_ARGS),
    ("PING a b", E_ARGS),
    ("PING bad!token", E_ARGS),
    ("POWER", E_ARGS),
    ("POWER one", E_NUMBER),
    ("POWER -1", E_RANGE),
    ("POWER nan", E_NUMBER),
    ("POWER inf", E_NUMBER),
    ("POWER 0x10", E_NUMBER),
    ("POWER 1_000", E_NUMBER),
    ("POWER 1e999", E_RANGE),
    ("SETTLE", E_ARGS),
    ("SETTLE -1", E_RANGE),
    ("SETTLE auto", E_NUMBER),
    ("WAVE", E_ARGS),
    ("WAVE x", E_ARGS),
    ("WAVE z SINE 1 1", E_AXIS),
    ("WAVE x SQUARE 1 1", E_ARGS),
    ("WAVE x SINE 1", E_ARGS),
    ("WAVE x SINE 1 1 1", E_ARGS),
    ("WAVE x SINE 0 1", E_RANGE),
    ("WAVE x SINE -5 1", E_RANGE),
    ("WAVE x SINE abc 1", E_NUMBER),
    ("WAVE x MULTI", E_ARGS),
    ("WAVE x MULTI 100:1", E_ARGS),
    ("WAVE x MULTI 100:1:0,", E_ARGS),
    ("WAVE x MULTI 0:1:0", E_RANGE),
    ("WAVE x MULTI " + ",".join(["10:1:0"] * 17), E_RANGE),
    ("ARM 0 0.001", E_ARGS),
    ("ARM 0 0.001 2 3", E_ARGS),
    ("ARM x 0.001 2", E_NUMBER),
    ("ARM 0 0 2", E_RANGE),
    ("ARM 0 -0.001 2", E_RANGE),
    ("ARM 0 0.001 0", E_RANGE),
    ("ARM 0 0.001 1001", E_RANGE),
    ("ARM 0 0.001 2.0", E_NUMBER),
    ("ARM 0 0.001 -2", E_NUMBER),
    ("ARM  0 0.001 2", E_ARGS),  # two spaces: an empty field
    ("ARM 0 0.001 2 ", E_ARGS),
    ("PULSE 0 0 2e-5 2e-4", E_ARGS),
    ("PULSE 0 0 0 2e-4 2", E_RANGE),
    ("PULSE 0 0 2e-5 2e-4 0", E_RANGE),
    ("PULSE 0 x 2e-5 2e-4 2", E_NUMBER),
    ("STOP\x00", E_LINE),
    ("ARM 0 0.001 " + "1" * MAX_LINE, E_LINE),
]


@pytest.mark.parametrize("line,code", BAD, ids=[repr(b[0][:30]) for b in BAD])
def test_every_error_reply(line, code):
    with pytest.raises(ProtocolViolation) as info:
        parse_command(line)
    assert info.value.code == code
    reply = info.value.reply
    assert reply.startswith(f"ERR {code} {ERROR_CODES[code]} ") and reply.endswith("\n") and reply.count("\n") == 1
    r = parse_reply(reply)
    assert not r.ok and r.code == code and r.name == ERROR_CODES[code]


def test_non_ascii_bytes_are_err_line():
    with pytest.raises(ProtocolViolation) as info:
        parse_command(b"STOP \xff\n")
    assert info.value.code == E_LINE


def test_numbers_travel_exactly():
    for v in (0.1 + 0.2, 1e-300, -7.123456789012345e-05, 2 * math.pi * 420.0, 5e-324):
        line = format_command("POWER", abs(v))
        assert parse_command(line).args[0] == abs(v)
    with pytest.raises(ValueError):
        format_command("POWER", float("nan"))


def test_reply_format_and_parse():
    line = format_ok("STATUS", state="IDLE", frames=12, pending=0, clock=0.5, boot="ab12")
    assert line == "OK STATUS state=IDLE frames=12 pending=0 clock=0.5 boot=ab12\n"
    r = parse_reply(line.encode())
    assert r.ok and r.word == "STATUS" and r.fields["frames"] == "12" and r.get_float("clock") == 0.5
    assert parse_reply(format_err(6, "busy now")).code == 6
    assert format_err(4, "bad \xff value").isascii()
    for garbage in (b"\xff\x00 OK\n", b"OK\n", b"HELLO there\n", b"OK ARM first\n", b"ERR x RANGE y\n", b"OK STOP"):
        with pytest.raises(ValueError):
            parse_reply(garbage)


# ---------------------------------------------------------------------- client on a real pty


class FakeDevice:
    """A thread answering on a pseudo-terminal with ``respond(line) -> bytes | None``."""

    def __init__(self, respond):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.respond = respond
        self.lines = []
        self._stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        buf = b""
        while not self._stop:
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self.lines.append(line)
                out = self.respond(line)
                if out:
                    try:
                        os.write(self.master, out)
                    except OSError:  # closed by the test
                        return

    def close(self):
        self._stop = True
        os.close(self.master)
        os.close(self.slave)


def default_respond(line: bytes):
    try:
        cmd = parse_command(line)
    except ProtocolViolation as v:
        return v.reply.encode()
    w = cmd.word
    if w == "ID?":
        return format_ok("ID", name="fake", firmware="1", protocol=1, axes="x").encode()
    if w == "STATUS?":
        return format_ok("STATUS", state="IDLE", frames=3, pending=0, clock=1.5, boot="b1").encode()
    if w == "PING":
        return format_ok("PING", token=cmd.args[0]).encode()
    if w == "ARM":
        return format_ok("ARM", first=3, count=cmd.args[2]).encode()
    return format_ok(cmd.reply_word).encode()


@pytest.fixture
def fake():
    devs = []

    def make(respond=default_respond):
        d = FakeDevice(respond)
        devs.append(d)
        return d

    yield make
    for d in devs:
        try:
            d.close()
        except OSError:
            pass


def test_controller_round_trip(fake):
    dev = fake()
    with Controller(dev.path, timeout_s=1.0) as c:
        assert c.identify() == {"name": "fake", "firmware": "1", "protocol": 1, "axes": ["x"]}
        assert c.status() == {"state": "IDLE", "frames": 3, "pending": 0, "clock": 1.5, "boot": "b1"}
        assert c.arm(0.5 / 3, 1e-3, 4) == (3, 4)
        c.stop()
        c.settle(None)
        c.power(0.1 + 0.2)
    assert dev.lines[-1] == b"POWER 0.30000000000000004" and b"SETTLE AUTO" in dev.lines
    assert b"ARM 0.16666666666666666 0.001 4" in dev.lines


def test_controller_err_reply_is_device_error(fake):
    dev = fake()
    with Controller(dev.path, timeout_s=1.0) as c:
        with pytest.raises(DeviceError) as info:
            c.command("WAVE", "z", "SINE", 1.0, 1.0)
        assert info.value.code == E_AXIS and info.value.name == "AXIS" and not info.value.recoverable
        c.ping("again")  # the link is still in step after an ERR


def test_controller_timeout_then_resync(fake):
    swallowed = []

    def respond(line):
        if line == b"STOP" and not swallowed:
            swallowed.append(line)
            return None
        return default_respond(line)

    dev = fake(respond)
    with Controller(dev.path, timeout_s=0.3) as c:
        t0 = time.monotonic()
        with pytest.raises(ReplyTimeout):
            c.stop()
        assert 0.25 < time.monotonic() - t0 < 2.0
        c.resync()
        c.stop()


def test_controller_garbage_and_stale_reply_then_resync(fake):
    state = {"n": 0}

    def respond(line):
        state["n"] += 1
        if state["n"] == 1:
            return b"\xff\x00garbage\n\xfe" + default_respond(line)  # noise, then the real reply
        if state["n"] == 2:
            return b"OK STATUS state=IDLE frames=0 pending=0 clock=0 boot=x\n"  # a reply to another command
        return default_respond(line)

    dev = fake(respond)
    with Controller(dev.path, timeout_s=0.5) as c:
        with pytest.raises(GarbageReply):
            c.stop()
        c.resync()  # discards the real reply left in the buffer
        with pytest.raises(GarbageReply):  # n == 3 is the PING; n == 4 below gets the foreign reply
            state["n"] = 1
            c.stop()
        c.resync()
        c.stop()


def test_controller_protocol_version_mismatch(fake):
    dev = fake(lambda line: format_ok("ID", name="old", firmware="0", protocol=7, axes="x").encode())
    with Controller(dev.path, timeout_s=0.5) as c:
        with pytest.raises(GarbageReply, match="protocol 7"):
            c.identify()


def test_controller_connection_lost(fake):
    dev = fake()
    c = Controller(dev.path, timeout_s=0.5)
    c.ping()
    dev.close()  # the device is gone (master and slave closed)
    time.sleep(0.05)
    with pytest.raises(ConnectionLost):
        c.ping()
        c.ping()
    c.close()
    with pytest.raises(ConnectionLost):
        Controller(dev.path, timeout_s=0.5)


def test_controller_opens_urls(fake):
    dev = fake()
    with Controller(f"spy://{dev.path}?file=/dev/null", timeout_s=0.5) as c:  # pyserial URL handlers work
        c.ping()
    with pytest.raises(ConnectionLost):
        Controller("/dev/does-not-exist", timeout_s=0.5)
    with pytest.raises(ValueError):
        Controller("", timeout_s=0.5)
