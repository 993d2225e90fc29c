"""The controller's line protocol: grammar, error codes, reply format (docs/protocol.md).

Shared by the client (:class:`~torchblur.hardware.controller.Controller`) and the emulator,
so both sides parse with the same rules. Pure functions, no I/O.
"""
from __future__ import annotations

import math
import re
import struct
import zlib
from dataclasses import dataclass

__all__ = [
    "PROTOCOL_VERSION",
    "PROTOCOL_VERSIONS",
    "HOLD_PROTOCOL",
    "MAX_LINE",
    "MAX_ACTUATORS",
    "MAX_COUNT",
    "MAX_TONES",
    "ERROR_CODES",
    "E_UNKNOWN",
    "E_ARGS",
    "E_NUMBER",
    "E_RANGE",
    "E_AXIS",
    "E_BUSY",
    "E_LINE",
    "E_INTERNAL",
    "Command",
    "ProtocolViolation",
    "parse_command",
    "format_number",
    "format_command",
    "format_tones",
    "format_ok",
    "format_err",
    "Reply",
    "parse_reply",
    "pattern_checksum",
    "pattern_lines",
]

PROTOCOL_VERSION = 3  # 2: ACT?, PAT, PAT? and the axis ``pat`` (a deformable mirror's pattern); 3: WAVE pat HOLD (a static hold)
PROTOCOL_VERSIONS = (1, 2, 3)  # the versions this client speaks (each is the one before plus its commands, those unchanged)
HOLD_PROTOCOL = 3  # the first version with WAVE pat HOLD
MAX_LINE = 200  # bytes, without the newline
MAX_ACTUATORS = 100_000  # entries of a pattern (PAT's start index is below it)
MAX_COUNT = 1000  # frames per ARM/PULSE
MAX_TONES = 16  # tones of a MULTI waveform

E_UNKNOWN, E_ARGS, E_NUMBER, E_RANGE, E_AXIS, E_BUSY, E_LINE, E_INTERNAL = range(1, 9)
ERROR_CODES = {
    E_UNKNOWN: "UNKNOWN",  # unknown command word, or an empty line
    E_ARGS: "ARGS",  # wrong number of arguments, or an empty field (two spaces)
    E_NUMBER: "NUMBER",  # an argument is not a number of the required form
    E_RANGE: "RANGE",  # a number outside its range (generic or this device's)
    E_AXIS: "AXIS",  # an axis name that is not x or y, or an axis the device lacks
    E_BUSY: "BUSY",  # frames of an earlier ARM/PULSE are still pending
    E_LINE: "LINE",  # line too long, or bytes that are not printable ASCII
    E_INTERNAL: "INTERNAL",  # the device failed to execute a valid command
}

_FLOAT = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$")
_INT = re.compile(r"^\d+$")
_TOKEN = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
_AXES = ("x", "y", "pat")  # pat: every actuator of a DM, amplitude * pattern[j] (protocol 2)


class ProtocolViolation(Exception):
    """A command line that must be answered with ``ERR code``; ``code`` in :data:`ERROR_CODES`."""

    def __init__(self, code: int, detail: str):
        super().__init__(detail)
        self.code, self.detail = code, detail

    @property
    def reply(self) -> str:
        return format_err(self.code, self.detail)


@dataclass(frozen=True)
class Command:
    """A parsed command: ``word`` (e.g. ``"ARM"``, ``"ID?"``) and typed ``args``.

    ``args`` per word: ``PING`` (token,); ``POWER`` (p,); ``SETTLE`` (s or None for AUTO,);
    ``WAVE`` (axis, "SINE", freq_hz, amplitude), (axis, "MULTI", ((f, a, p), ...)) or (axis,
    "HOLD", level);
    ``ARM`` (trigger_offset_s, exposure_s, count); ``PULSE`` (trigger_offset_s,
    pulse_time_s, pulse_width_s, exposure_s, count); ``PAT`` (start, (v, ...)); the others
    (``ID?``, ``STATUS?``, ``RANGE?``, ``RESET``, ``STOP``, ``ACT?``, ``PAT?``) ().
    """

    word: str
    args: tuple = ()

    @property
    def reply_word(self) -> str:
        return self.word.rstrip("?")


def _float(tok: str, what: str, *, positive=False, nonnegative=False) -> float:
    if not _FLOAT.match(tok):
        raise ProtocolViolation(E_NUMBER, f"{what}: not a number: {tok!r}")
    v = float(tok)
    if not math.isfinite(v):
        raise ProtocolViolation(E_RANGE, f"{what}: not finite: {tok!r}")
    if positive and v <= 0:
        raise ProtocolViolation(E_RANGE, f"{what}: must be > 0, got {tok}")
    if nonnegative and v < 0:
        raise ProtocolViolation(E_RANGE, f"{what}: must be >= 0, got {tok}")
    return v


def _count(tok: str, what: str = "count") -> int:
    if not _INT.match(tok):
        raise ProtocolViolation(E_NUMBER, f"{what}: not a non-negative integer: {tok!r}")
    v = int(tok)
    if not 1 <= v <= MAX_COUNT:
        raise ProtocolViolation(E_RANGE, f"{what}: must be in 1..{MAX_COUNT}, got {v}")
    return v


def _axis(tok: str) -> str:
    if tok not in _AXES:
        raise ProtocolViolation(E_AXIS, f"axis: expected one of {', '.join(_AXES)}, got {tok!r}")
    return tok


def _nargs(word: str, args: list, n: int, usage: str) -> None:
    if len(args) != n:
        raise ProtocolViolation(E_ARGS, f"{word}: expected {n} argument(s) ({usage}), got {len(args)}")


def _tones(spec: str) -> tuple:
    parts = spec.split(",")
    if not 1 <= len(parts) <= MAX_TONES:
        raise ProtocolViolation(E_RANGE, f"MULTI: expected 1..{MAX_TONES} tones, got {len(parts)}")
    tones = []
    for i, part in enumerate(parts):
        fields = part.split(":")
        if len(fields) != 3:
            raise ProtocolViolation(E_ARGS, f"MULTI tone {i}: expected freq_hz:amplitude:phase_rad, got {part!r}")
        tones.append((_float(fields[0], f"tone {i} freq_hz", positive=True), _float(fields[1], f"tone {i} amplitude"),
                      _float(fields[2], f"tone {i} phase_rad")))
    return tuple(tones)


def parse_command(line: str | bytes) -> Command:
    """Parse one command line (with or without its ``\\n``).

    Raises:
        ProtocolViolation: with the ``ERR`` code to answer (unknown word, wrong argument
            count, bad number, out of range, bad axis, bad bytes or length).
    """
    raw = line.encode("utf-8", "surrogateescape") if isinstance(line, str) else bytes(line)
    if raw.endswith(b"\n"):
        raw = raw[:-1]
    if raw.endswith(b"\r"):
        raw = raw[:-1]
    if len(raw) > MAX_LINE:
        raise ProtocolViolation(E_LINE, f"line longer than {MAX_LINE} bytes")
    if any(b < 0x20 or b > 0x7E for b in raw):
        raise ProtocolViolation(E_LINE, "line holds bytes that are not printable ASCII")
    text = raw.decode("ascii")
    if text == "":
        raise ProtocolViolation(E_UNKNOWN, "empty line")
    tokens = text.split(" ")
    word, args = tokens[0], tokens[1:]
    if word == "" or any(t == "" for t in args):
        raise ProtocolViolation(E_ARGS, "empty field: separate the fields by single spaces")
    if word in ("ID?", "STATUS?", "RANGE?", "SLEW?", "RESET", "STOP", "ACT?", "PAT?"):
        _nargs(word, args, 0, "none")
        return Command(word)
    if word == "PING":
        _nargs(word, args, 1, "token")
        if not _TOKEN.match(args[0]):
            raise ProtocolViolation(E_ARGS, f"PING: token must be 1-32 of [A-Za-z0-9_-], got {args[0]!r}")
        return Command(word, (args[0],))
    if word == "POWER":
        _nargs(word, args, 1, "power")
        return Command(word, (_float(args[0], "power", nonnegative=True),))
    if word == "SETTLE":
        _nargs(word, args, 1, "settle_s or AUTO")
        return Command(word, (None if args[0] == "AUTO" else _float(args[0], "settle_s", nonnegative=True),))
    if word == "WAVE":
        if len(args) < 2:
            raise ProtocolViolation(E_ARGS, f"WAVE: expected 'WAVE <axis> SINE <freq_hz> <amplitude>', "
                                            f"'WAVE <axis> MULTI <f:a:p,...>' or 'WAVE <axis> HOLD <level>', got {len(args)} argument(s)")
        axis, mode = _axis(args[0]), args[1]
        if mode == "SINE":
            _nargs("WAVE SINE", args, 4, "axis SINE freq_hz amplitude")
            return Command(word, (axis, mode, _float(args[2], "freq_hz", positive=True), _float(args[3], "amplitude")))
        if mode == "MULTI":
            _nargs("WAVE MULTI", args, 3, "axis MULTI f:a:p,...")
            return Command(word, (axis, mode, _tones(args[2])))
        if mode == "HOLD":
            _nargs("WAVE HOLD", args, 3, "axis HOLD level")
            return Command(word, (axis, mode, _float(args[2], "level")))
        raise ProtocolViolation(E_ARGS, f"WAVE: mode must be SINE, MULTI or HOLD, got {mode!r}")
    if word == "ARM":
        _nargs(word, args, 3, "trigger_offset_s exposure_s count")
        return Command(word, (_float(args[0], "trigger_offset_s"), _float(args[1], "exposure_s", positive=True), _count(args[2])))
    if word == "PULSE":
        _nargs(word, args, 5, "trigger_offset_s pulse_time_s pulse_width_s exposure_s count")
        return Command(word, (_float(args[0], "trigger_offset_s"), _float(args[1], "pulse_time_s"),
                              _float(args[2], "pulse_width_s", positive=True), _float(args[3], "exposure_s", positive=True),
                              _count(args[4])))
    if word == "PAT":
        return Command(word, _pattern_chunk(args))
    raise ProtocolViolation(E_UNKNOWN, f"unknown command {word!r}")


def _pattern_chunk(args: list) -> tuple:
    """``PAT <start> <v> [<v> ...]`` -> ``(start, (v, ...))``."""
    if len(args) < 2:
        raise ProtocolViolation(E_ARGS, f"PAT: expected 'PAT <start> <v> [<v> ...]' (a start index and at least one value), "
                                        f"got {len(args)} argument(s)")
    if not _INT.match(args[0]):
        raise ProtocolViolation(E_NUMBER, f"start: not a non-negative integer: {args[0]!r}")
    start = int(args[0])
    if start >= MAX_ACTUATORS:
        raise ProtocolViolation(E_RANGE, f"start: must be below {MAX_ACTUATORS}, got {start}")
    return start, tuple(_float(t, f"pattern[{start + i}]") for i, t in enumerate(args[1:]))


def pattern_checksum(values) -> str:
    """The checksum ``PAT?`` and ``WAVE pat`` report: CRC-32 (zlib's, the IEEE 802.3
    polynomial) of the pattern's values as IEEE-754 float64, little-endian, in order, as 8
    lowercase hex digits. Exact: it tells every bit of every value (``-0.0`` from ``0.0`` too);
    a firmware computes it from the doubles it holds, with no text formatting."""
    vals = [float(v) for v in values]
    return f"{zlib.crc32(struct.pack(f'<{len(vals)}d', *vals)) & 0xFFFFFFFF:08x}"


def pattern_lines(values) -> list[str]:
    """The ``PAT <start> <v> ...`` lines (with ``\\n``) that load ``values`` (the whole
    pattern, from entry 0), each at most :data:`MAX_LINE` bytes: as many values per line as
    fit, in order; every value as :func:`format_number` writes it (the exact float)."""
    toks = [format_number(v) for v in values]
    lines, i = [], 0
    while i < len(toks):
        line, j = f"PAT {i}", i
        while j < len(toks) and len(line) + 1 + len(toks[j]) <= MAX_LINE:
            line += " " + toks[j]
            j += 1
        lines.append(line + "\n")
        i = j
    return lines


def format_number(value) -> str:
    """A float as the shortest text that reads back to the same float (``repr``)."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"cannot send a non-finite number: {v}")
    return repr(v)


def format_tones(tones) -> str:
    """A ``MULTI`` waveform's tones ``[(freq_hz, amplitude, phase_rad), ...]`` as ``f:a:p,...`` (each exact)."""
    return ",".join(":".join(format_number(v) for v in tone) for tone in tones)


def format_command(word: str, *args) -> str:
    """``word`` and its arguments as one line (floats via :func:`format_number`), with ``\\n``."""
    parts = [word]
    for a in args:
        if isinstance(a, bool):
            raise TypeError("no boolean arguments in this protocol")
        if isinstance(a, int):
            parts.append(str(a))
        elif isinstance(a, float):
            parts.append(format_number(a))
        else:
            parts.append(str(a))
    line = " ".join(parts)
    if len(line) > MAX_LINE:
        raise ValueError(f"command longer than {MAX_LINE} bytes: {line[:40]}...")
    return line + "\n"


def _value(v) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return format_number(v)
    s = str(v)
    if " " in s or "=" in s or not s:
        raise ValueError(f"reply value must be one non-empty token without '=': {s!r}")
    return s


def format_ok(word: str, **fields) -> str:
    """``OK <word> key=value ...\\n``."""
    return " ".join(["OK", word] + [f"{k}={_value(v)}" for k, v in fields.items()]) + "\n"


def format_err(code: int, detail: str) -> str:
    """``ERR <code> <NAME> <detail>\\n`` (the detail made printable ASCII, one line)."""
    clean = "".join(c if 0x20 <= ord(c) <= 0x7E else "?" for c in detail)[: MAX_LINE - 20]
    return f"ERR {int(code)} {ERROR_CODES.get(int(code), 'INTERNAL')} {clean}\n"


@dataclass(frozen=True)
class Reply:
    """A parsed reply: ``ok`` True for ``OK``; ``word`` (OK) ; ``fields`` key -> text (OK);
    ``code``, ``name``, ``detail`` (ERR)."""

    ok: bool
    word: str = ""
    fields: dict | None = None
    code: int = 0
    name: str = ""
    detail: str = ""

    def get_float(self, key: str) -> float:
        return float(self.fields[key])

    def get_int(self, key: str) -> int:
        return int(self.fields[key])


def parse_reply(line: bytes | str) -> Reply:
    """Parse one reply line.

    Raises:
        ValueError: the line is not a well-formed ``OK``/``ERR`` reply (the client turns this
            into :class:`~torchblur.hardware.errors.GarbageReply`).
    """
    if isinstance(line, (bytes, bytearray)):
        raw = bytes(line)
        if not raw.endswith(b"\n"):
            raise ValueError("reply without its newline")
        raw = raw[:-1]
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if any(b < 0x20 or b > 0x7E for b in raw):
            raise ValueError(f"reply holds bytes that are not printable ASCII: {raw[:60]!r}")
        text = raw.decode("ascii")
    else:
        text = line.rstrip("\n").rstrip("\r")
    tokens = text.split(" ")
    if tokens[0] == "OK" and len(tokens) >= 2 and tokens[1]:
        fields = {}
        for t in tokens[2:]:
            k, sep, v = t.partition("=")
            if not sep or not k or not v:
                raise ValueError(f"malformed field {t!r} in reply {text!r}")
            fields[k] = v
        return Reply(True, tokens[1], fields)
    if tokens[0] == "ERR" and len(tokens) >= 3 and _INT.match(tokens[1]):
        return Reply(False, code=int(tokens[1]), name=tokens[2], detail=" ".join(tokens[3:]))
    raise ValueError(f"not an OK/ERR reply: {text[:60]!r}")
