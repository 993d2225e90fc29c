"""A recording is untrusted input: the schema checks of ``experiment.json`` and of
``manifest.jsonl`` lines, and the scan that sorts a manifest into complete groups and problems
(what is checked: docs/protocol.md, "The experiment directory"). Sizes are bounded before
parsing (a line at most :data:`MAX_LINE_BYTES`, JSON nested at most :data:`MAX_JSON_DEPTH` deep).
"""
from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from torchblur.errors import check_int, check_real_scalar, excerpt
from torchblur.files import read_bounded as _read_bounded, sha256_bounded
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.run_folder import inside

__all__ = ["SCHEMA_VERSION", "MAX_LINE_BYTES", "MAX_JSON_DEPTH", "MAX_META_BYTES", "MAX_MANIFEST_BYTES", "MAX_FRAME_SIDE", "METHODS",
           "SETTINGS_KEY", "INTEGRITY_KEY", "settings_digest", "meta_digest", "ManifestScan", "check_line", "check_meta", "expected_file", "load_json", "read_bounded", "scan_manifest"]

SCHEMA_VERSION = 1
MAX_LINE_BYTES = 64 * 1024
MAX_JSON_DEPTH = 16
MAX_META_BYTES = 4 * 1024 * 1024
MAX_MANIFEST_BYTES = 512 * 1024 * 1024
MAX_FRAME_SIDE = 65536
MAX_GROUP_BYTES = 1 << 36  # one group's frame file (64 GiB): bounds the hash's read, never held whole
MAX_AMPLITUDE = 1e6  # command units: far beyond any DAC's range
METHODS = ("dark", "still", "sine", "pulse", "multisine", "pattern_sine", "pattern_ladder")  # pattern_*: a DM rig's (torchblur.identify.dm_record)
_GROUP = re.compile(r"^[A-Za-z0-9_-]{1,40}(/[A-Za-z0-9_-]{1,40}){0,3}$")
_SHA = re.compile(r"^[0-9a-f]{64}$")
SETTINGS_KEY = "settings_sha256"  # every line of a group: the digest of the group's lines (settings_digest)
INTEGRITY_KEY = "integrity"  # experiment.json: {key: digest} of every key set after creation (a DM run's dm_plan)
_SHARED = ("kind", "group_frames", "file", "sha256", "dtype", "input", "freq_hz", "amplitude", "power", "point", SETTINGS_KEY)
_SCHEMA_KEYS = ("schema_version", "torchblur_version", "created", "camera", "status", "sessions", INTEGRITY_KEY)


def meta_digest(value) -> str:
    """SHA-256 of a JSON value (keys sorted): a value ``experiment.json`` holds beside its schema (a DM run's plan)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def settings_digest(lines: list) -> str:
    """SHA-256 of a group's manifest ``lines`` (every field but the file's and this digest, in
    page order, keys sorted): written with the group, checked at every read, so a group whose
    amplitudes, timing or arguments were edited is refused, not re-fitted."""
    body = [{k: v for k, v in ln.items() if k not in ("sha256", SETTINGS_KEY)} for ln in sorted(lines, key=lambda ln: ln["page"])]
    return meta_digest(body)


class _Bad(Exception):
    """One field of one line is invalid (internal: becomes a problem or a RecordingError)."""


def read_bounded(path: Path, limit: int, what: str, *, root: Path | None = None) -> bytes:
    """:func:`torchblur.files.read_bounded` (the opening rule: a regular file, inside ``root``
    when given, at most ``limit`` bytes) raising :class:`RecordingError`.

    Raises:
        RecordingError: naming ``what``.
    """
    return _read_bounded(path, limit, what, root=root, error=RecordingError)


def _depth(v, d=0) -> int:
    if d > MAX_JSON_DEPTH:
        return d
    if isinstance(v, dict):
        return max((_depth(x, d + 1) for x in v.values()), default=d + 1)
    if isinstance(v, list):
        return max((_depth(x, d + 1) for x in v), default=d + 1)
    return d


def load_json(data: bytes, what: str):
    """Parse JSON from an untrusted source: UTF-8, nested at most :data:`MAX_JSON_DEPTH`.

    Raises:
        RecordingError: naming ``what``.
    """
    if data.count(b"[") + data.count(b"{") > 100_000 or re.search(rb"[\[{]{%d}" % (MAX_JSON_DEPTH + 1), data):
        raise RecordingError(f"{what}: JSON nested deeper than {MAX_JSON_DEPTH} levels; refused")
    try:
        value = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as exc:
        raise RecordingError(f"{what}: not valid JSON ({str(exc).splitlines()[0][:120]})") from None
    if _depth(value) > MAX_JSON_DEPTH:
        raise RecordingError(f"{what}: JSON nested deeper than {MAX_JSON_DEPTH} levels; refused")
    return value


def _float(v, key, *, positive=False, nonnegative=False, optional=False):
    if v is None and optional:
        return None
    return check_real_scalar(v, key, positive=positive, nonnegative=nonnegative, error=_Bad)


def _str(v, key, *, optional=False, limit=200):
    if v is None and optional:
        return None
    if not isinstance(v, str) or len(v) > limit:
        raise _Bad(f"{key}: expected a string of at most {limit} characters, got {excerpt(v)}")
    return v


def expected_file(group: str) -> str:
    """The frame file of a group: ``frames/<group with / as _>.tif``."""
    return "frames/" + group.replace("/", "_") + ".tif"


def check_line(ln, root: Path) -> str:
    """Check one manifest line; return its group.

    Raises:
        _Bad: the first invalid field, named.
    """
    if not isinstance(ln, dict):
        raise _Bad(f"expected a JSON object, got {type(ln).__name__}")
    g = ln.get("group")
    if not isinstance(g, str) or not _GROUP.match(g):
        raise _Bad(f"group: expected a group key like 'dark' or 'sweep/x/003', got {excerpt(g)}")
    n = check_int(ln.get("group_frames"), "group_frames", low=1, high=1_000_000, error=_Bad)
    _str(ln.get("kind"), "kind", limit=32)
    check_int(ln.get("call"), "call", low=0, high=n - 1, error=_Bad)
    shape = ln.get("call_shape")
    if not isinstance(shape, list) or len(shape) > 4:
        raise _Bad(f"call_shape: expected a list of at most 4 sizes, got {excerpt(shape)}")
    size = math.prod(check_int(s, "call_shape", low=1, high=n, error=_Bad) for s in shape)
    if size > n:
        raise _Bad(f"call_shape: {shape} holds {size} frames, more than the group's {n}")
    check_int(ln.get("index"), "index", low=0, high=size - 1, error=_Bad)
    if ln.get("method") not in METHODS:
        raise _Bad(f"method: expected one of {METHODS}, got {excerpt(ln.get('method'))}")
    check_int(ln.get("page"), "page", low=0, high=n - 1, error=_Bad)
    if ln.get("file") != expected_file(g):
        raise _Bad(f"file: expected {excerpt(expected_file(g))} (the group's frame file), got {excerpt(ln.get('file'))}")
    inside(root, ln["file"], "file")
    if ln.get("dtype") not in ("uint16", "float64"):
        raise _Bad(f"dtype: expected 'uint16' or 'float64', got {excerpt(ln.get('dtype'))}")
    if not isinstance(ln.get("sha256"), str) or not _SHA.match(ln["sha256"]):
        raise _Bad(f"sha256: expected 64 lowercase hex digits, got {excerpt(ln.get('sha256'))}")
    check_int(ln.get("frame_counter"), "frame_counter", low=-(2**62), high=2**62, error=_Bad)
    _float(ln.get("exposure_s"), "exposure_s", positive=True)
    for k in ("timestamp_s", "trigger_time_s", "trigger_offset_s"):
        _float(ln.get(k), k, optional=True)
    for k in ("exposure_index", "session"):
        if ln.get(k) is not None:
            check_int(ln[k], k, low=0, high=1_000_000, error=_Bad)
    check_int(ln.get("repeat"), "repeat", low=0, high=n - 1, error=_Bad)
    _str(ln.get("input"), "input", optional=True, limit=16)
    _float(ln.get("freq_hz"), "freq_hz", positive=True, optional=True)
    if not isinstance(ln.get("args"), dict) or not isinstance(ln.get("meta", {}), dict):
        raise _Bad("args: expected an object (and meta an object)")
    if ln.get("method") in ("pattern_sine", "pattern_ladder"):
        _check_pattern(ln["args"].get("pattern"))
    if ln.get("method") == "pattern_ladder":
        _check_pattern(ln["args"].get("levels"), "levels")  # the static levels: a list of finite numbers too
    if (ln.get("kind") == "sweep" and ln.get("method") == "sine") or ln.get("method") == "pattern_sine":
        _float(ln.get("freq_hz"), "freq_hz", positive=True)
        if not 0 < _float(ln.get("amplitude"), "amplitude", positive=True) <= MAX_AMPLITUDE:
            raise _Bad(f"amplitude: expected a value in (0, {MAX_AMPLITUDE:g}] command units, got {excerpt(ln['amplitude'])}")
        _float(ln.get("power"), "power", nonnegative=True)
        for k in ("amplitude", "freq_hz", "power"):  # the labels repeat the rig call's arguments
            if k in ln["args"] and not (isinstance(ln["args"][k], (int, float)) and not isinstance(ln["args"][k], bool)
                                        and math.isclose(ln["args"][k], ln[k], rel_tol=1e-12)):
                raise _Bad(f"{k}: {excerpt(ln[k])} differs from the rig call's args.{k} = {excerpt(ln['args'][k])}")
        if ln.get("point") is not None:
            check_int(ln["point"], "point", low=0, high=1_000_000, error=_Bad)
        if ln.get("attempts") is not None:
            check_int(ln["attempts"], "attempts", low=1, high=1000, error=_Bad)
    return g


def _check_pattern(p, name: str = "pattern") -> None:
    """A DM pattern (``args.pattern`` of a ``pattern_sine`` line): a list of finite numbers, each
    actuator's command per unit amplitude."""
    if not isinstance(p, list) or not 1 <= len(p) <= MAX_FRAME_SIDE:
        raise _Bad(f"args.{name}: expected a list of 1 to {MAX_FRAME_SIDE} commands, got {excerpt(p)}")
    for v in p:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > MAX_AMPLITUDE:
            raise _Bad(f"args.{name}: expected finite commands within +-{MAX_AMPLITUDE:g}, got {excerpt(v)}")


def _check_group(g: str, gl: list, root: Path, verify: bool) -> None:
    """Raise :class:`_Bad` unless the lines ``gl`` of group ``g`` form one complete group."""
    first = gl[0]
    for k in _SHARED:
        odd = [ln for ln in gl if ln.get(k) != first.get(k)]
        if odd:
            raise _Bad(f"{k}: the group's lines disagree ({excerpt(first.get(k))} and {excerpt(odd[0].get(k))})")
    n = first["group_frames"]
    if len(gl) != n:
        raise _Bad(f"incomplete: {len(gl)} of its {n} lines")
    if sorted(ln["page"] for ln in gl) != list(range(n)):
        raise _Bad("page: two lines name the same page")
    by_call: dict[int, list] = {}
    for ln in gl:
        by_call.setdefault(ln["call"], []).append(ln)
    for ci, cl in by_call.items():
        shape, size = cl[0]["call_shape"], math.prod(cl[0]["call_shape"])
        if any(ln["call_shape"] != shape or ln["method"] != cl[0]["method"] or ln["args"] != cl[0]["args"] for ln in cl):
            raise _Bad(f"call {ci}: its lines disagree on call_shape, method or args")
        if sorted(ln["index"] for ln in cl) != list(range(size)):
            raise _Bad(f"call {ci}: index: expected 0 .. {size - 1} once each")
    if not isinstance(first.get(SETTINGS_KEY), str):
        raise _Bad(f"{SETTINGS_KEY}: missing (recorded by a torchblur before settings digests, or edited): the group's settings "
                   f"cannot be checked; refused")
    if settings_digest(gl) != first[SETTINGS_KEY]:
        raise _Bad(f"{SETTINGS_KEY}: the group's settings (amplitude, timing, arguments, ...) changed after it was recorded; refused")
    f = inside(root, first["file"], "file")
    if f.is_symlink() or not f.is_file():
        raise _Bad(f"file: {first['file']} is missing (or not a regular file)")
    if verify:
        if sha256_bounded(f, MAX_GROUP_BYTES, first["file"], error=RecordingError) != first["sha256"]:
            raise _Bad(f"sha256: {first['file']} does not match its recorded hash (changed or corrupted)")


@dataclass
class ManifestScan:
    """A manifest sorted out. ``lines``/``raw``: the kept lines (complete groups), parsed and
    as their original bytes; ``problems``: ``(line number or None, group or None,
    reason)``; ``bad_raw``: the bytes of every line not kept; ``dropped``: group -> reason;
    ``torn_line``: the manifest ends without a newline; ``tail_only``: every problem lies
    after the last kept line and is a torn last line or an incomplete group (what a crash
    in the middle of an append leaves)."""

    lines: list = field(default_factory=list)
    raw: list = field(default_factory=list)
    problems: list = field(default_factory=list)
    bad_raw: list = field(default_factory=list)
    dropped: dict = field(default_factory=dict)
    torn_line: bool = False
    tail_only: bool = True


def _parse_lines(data: bytes, root: Path, scan: ManifestScan):
    """Parse and check each line; returns ``[(line number, raw, line dict, group)]`` of the
    valid ones, with the exact duplicates of a line left out (kept in ``scan.bad_raw``)."""
    parts = data.split(b"\n")
    scan.torn_line = parts[-1] != b""
    good, seen = [], {}
    for no, raw in enumerate(parts, start=1):
        if not raw.strip():
            continue
        try:
            if len(raw) > MAX_LINE_BYTES:
                raise _Bad(f"{len(raw)} bytes, more than {MAX_LINE_BYTES}")
            try:
                ln = load_json(raw, "line")
            except RecordingError as exc:
                raise _Bad(str(exc)) from None
            g = check_line(ln, root)
        except (_Bad, RecordingError) as exc:
            group = _group_hint(raw)  # a guess: the group is dropped only if incomplete without the line
            scan.problems.append((no, group, f"line {no}{f' (group {group}?)' if group else ''}: {exc}"))
            scan.bad_raw.append(raw)
            continue
        key = (g, ln["page"])
        if key in seen:
            if seen[key] == ln:  # an exact copy of an earlier line: harmless, kept aside
                scan.problems.append((no, None, f"line {no}: a duplicate of an earlier line (set aside)"))
                scan.bad_raw.append(raw)
                continue
            scan.dropped.setdefault(g, f"line {no}: a second, different line for page {ln['page']}")
        seen[key] = ln
        good.append((no, raw, ln, g))
    return good


def _group_hint(raw: bytes) -> str | None:
    m = re.search(rb'"group"\s*:\s*"([A-Za-z0-9_/-]{1,160})"', raw)
    g = m.group(1).decode() if m else None
    return g if g is not None and _GROUP.match(g) else None


def scan_manifest(data: bytes, root: Path, *, verify: bool = True) -> ManifestScan:
    """Sort the manifest bytes ``data`` of the run folder ``root`` into kept lines and
    problems (see :class:`ManifestScan`). Never raises for a bad line: it becomes a problem."""
    scan = ManifestScan()
    good = _parse_lines(data, root, scan)
    order: dict[str, list] = {}
    for item in good:
        order.setdefault(item[3], []).append(item)
    for g, items in order.items():
        if g not in scan.dropped:
            try:
                _check_group(g, [it[2] for it in items], root, verify)
            except (_Bad, RecordingError) as exc:
                scan.dropped[g] = str(exc)
        if g in scan.dropped:
            scan.problems.append((items[0][0], g, f"group {g}: {scan.dropped[g]}"))
            scan.bad_raw += [it[1] for it in items]
        else:
            scan.lines += [it[2] for it in items]
            scan.raw += [it[1] for it in items]
    kept = {ln["group"] for ln in scan.lines}
    for _, g, reason in list(scan.problems):
        if g is not None and g not in kept:
            scan.dropped.setdefault(g, reason)
    last_kept = max((it[0] for it in good if it[3] not in scan.dropped), default=0)
    crash_like = scan.torn_line or all(r.startswith("incomplete") for r in scan.dropped.values())
    scan.tail_only = crash_like and all(no is not None and no > last_kept for no, _, _ in scan.problems)
    return scan


def check_meta(meta, what: str) -> None:
    """Check ``experiment.json``'s content: schema_version, camera, sessions, status.

    Raises:
        RecordingError: naming the field.
    """
    if not isinstance(meta, dict):
        raise RecordingError(f"{what}: expected a JSON object, got {type(meta).__name__}")
    if meta.get("schema_version") != SCHEMA_VERSION or isinstance(meta.get("schema_version"), bool):
        raise RecordingError(f"{what}: schema_version {excerpt(meta.get('schema_version'))}; this torchblur reads {SCHEMA_VERSION}")
    cam = meta.get("camera")
    try:
        if not isinstance(cam, dict):
            raise _Bad(f"expected an object, got {excerpt(cam)}")
        shape = cam.get("frame_shape")
        if not isinstance(shape, list) or len(shape) != 2:
            raise _Bad(f"frame_shape: expected [H, W], got {excerpt(shape)}")
        h, w = (check_int(v, "frame_shape", low=1, high=MAX_FRAME_SIDE, error=_Bad) for v in shape)
        if h * w > 2**28:
            raise _Bad(f"frame_shape: {h}x{w} pixels is more than any camera delivers")
        for k in ("frame_rate_hz", "max_exposure_s"):
            _float(cam.get(k), k, positive=True)
        _float(cam.get("readout_s"), "readout_s", nonnegative=True)
        _str(cam.get("name", ""), "name")
    except _Bad as exc:
        raise RecordingError(f"{what}: camera.{exc}") from None
    if not isinstance(meta.get("sessions", []), list) or not isinstance(meta.get("status", ""), str):
        raise RecordingError(f"{what}: sessions: expected a list (and status a string)")
    sums = meta.get(INTEGRITY_KEY, {})
    if not isinstance(sums, dict):
        raise RecordingError(f"{what}: {INTEGRITY_KEY}: expected an object of digests")
    for key in meta:
        if key in _SCHEMA_KEYS:
            continue
        if key not in sums:
            raise RecordingError(f"{what}: {key}: no digest in {INTEGRITY_KEY} (recorded by a torchblur before metadata digests, "
                                 f"or edited): it cannot be checked; refused")
        if sums[key] != meta_digest(meta[key]):
            raise RecordingError(f"{what}: {key}: changed after it was recorded (its digest differs); refused")
