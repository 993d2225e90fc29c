"""The experiment directory: written as a run goes, read back to resume or re-fit it.

The layout (schema :data:`SCHEMA_VERSION`: ``experiment.json``, ``config.yaml``,
``manifest.jsonl``, ``frames/<group>.tif``), the groups, the atomic writes and the repair on
opening are docs/protocol.md's "The experiment directory". A group is the unit of storage and
of resumption, stored whole or not at all.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import inspect
import io
import json
import math
import os
import time
from contextlib import suppress
from pathlib import Path

import numpy as np
import torch

from torchblur.errors import excerpt
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.frames import CameraInfo, CameraProperties, raw_pixels
from torchblur.hardware.manifest import (MAX_FRAME_SIDE, MAX_MANIFEST_BYTES, MAX_META_BYTES, INTEGRITY_KEY, METHODS, SCHEMA_VERSION, SETTINGS_KEY, ManifestScan,
                                         check_meta, expected_file, load_json, meta_digest, read_bounded, scan_manifest,
                                         settings_digest)
from torchblur.hardware.run_folder import RunLock, inside
from torchblur import __version__
from torchblur.rig.base import Capture, Rig
from torchblur.sysid.frequency_response_io import json_floats

__all__ = ["SCHEMA_VERSION", "Experiment", "ReplayRig", "atomic_write_bytes"]

_TMP = ".tmp"
_F64 = torch.float64


# ---------------------------------------------------------------------- atomic files


def _fsync_dir(path: Path) -> None:
    with suppress(OSError):  # best effort: not every platform or file system syncs a folder
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes, *, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically: a temporary name in the same folder, flush,
    fsync, ``os.replace``. An exception (KeyboardInterrupt included) removes the temporary."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}{_TMP}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with suppress(OSError):
            tmp.unlink()
        raise
    if fsync:
        _fsync_dir(path.parent)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _jsonable(v):
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu()
        return v.item() if v.dim() == 0 else v.tolist()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return repr(v)


def _same(a, b) -> bool:
    """Argument equality for replay: numbers to 1e-9 relative, lists element-wise."""
    if isinstance(a, list) or isinstance(b, list):
        a_l = a if isinstance(a, list) else [a]
        b_l = b if isinstance(b, list) else [b]
        return len(a_l) == len(b_l) and all(_same(x, y) for x, y in zip(a_l, b_l))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-15)
    return a == b


def _bind(method: str, args: tuple, kwargs: dict) -> dict:

    if not hasattr(Rig, method):  # a command of one kind of rig (pattern_sine: a DM rig's): called by keyword only
        if args:
            raise RecordingError(f"{method}: a recorded {method} call passes its arguments by keyword, got {len(args)} positional")
        return {k: _jsonable(v) for k, v in kwargs.items()}
    sig = inspect.signature(getattr(Rig, method))
    bound = sig.bind(None, *args, **kwargs)
    bound.apply_defaults()
    return {k: _jsonable(v) for k, v in bound.arguments.items() if k != "self"}


# ---------------------------------------------------------------------- rig proxies


class _RecordingRig:
    """Forwards every rig call and keeps ``(method, args, capture)`` of the rig methods
    (:data:`~torchblur.hardware.manifest.METHODS`)."""

    def __init__(self, rig):
        self._rig = rig
        self.calls: list = []

    def __getattr__(self, name):
        attr = getattr(self._rig, name)
        if name not in METHODS:
            return attr

        def call(*args, **kwargs):
            cap = attr(*args, **kwargs)
            self.calls.append((name, _bind(name, args, kwargs), cap))
            return cap

        return call


class _ReplayCalls(CameraProperties):
    """Serves recorded calls in order; a call that differs from the recording is an error."""

    def __init__(self, info: CameraInfo, calls: list, key: str):
        self.info = info
        self._calls, self._key, self._i = calls, key, 0

    def __getattr__(self, name):
        if name not in METHODS:
            raise AttributeError(name)
        return lambda *args, **kwargs: self._next(name, args, kwargs)

    def _next(self, method, args, kwargs):
        want = _bind(method, args, kwargs)
        if self._i >= len(self._calls):
            raise RecordingError(f"{self._key}: the pipeline asks for more rig calls than the recording holds "
                                 f"({len(self._calls)}); was it recorded with another version or config?")
        m, got, cap = self._calls[self._i]
        if m != method or set(got) != set(want) or not all(_same(got[k], want[k]) for k in want):
            diff = [k for k in want if k not in got or not _same(got[k], want[k])]
            raise RecordingError(f"{self._key}: rig call {self._i} is {method}({', '.join(f'{k}={excerpt(want[k])}' for k in diff)}), "
                                 f"the recording holds {m}({', '.join(f'{k}={excerpt(got.get(k))}' for k in diff)})")
        self._i += 1
        return cap


class ReplayRig(CameraProperties):
    """A rig that only knows the recording: every live call raises :class:`RecordingError`
    (the run is incomplete; resume it first). Used by ``torchblur fit``."""

    def __init__(self, experiment: "Experiment"):
        self.info = experiment.camera_info
        self._dir = experiment.path

    def _missing(self, *a, **k):
        raise RecordingError(f"{self._dir}: the recording is incomplete (a group the pipeline needs is missing); "
                             f"resume it first: torchblur identify --resume {self._dir.parent if self._dir.name == 'experiment' else self._dir} "
                             f"rig.port=... rig.frames=...")

    dark = still = sine = pulse = multisine = pattern_sine = pattern_ladder = _missing


# ---------------------------------------------------------------------- the directory


class Experiment:
    """An experiment directory (see the module docstring). Create with :meth:`create`, open
    an existing one with :meth:`open`.

    Attributes:
        path: the directory.
        meta: the content of ``experiment.json``.
        lines: the manifest lines of the complete groups, in order.
        groups: group key -> its manifest lines.
        writable: False for a read-only view (``torchblur fit``).
    """

    def __init__(self, path: Path, meta: dict, lines: list, *, writable: bool):
        self.path = Path(path)
        self.meta = meta
        self.lines = lines
        self.writable = writable
        self.groups: dict[str, list] = {}
        for ln in lines:
            self.groups.setdefault(ln["group"], []).append(ln)
        self._session: int | None = None
        self._lock = None
        self.stats = {"groups_written": 0, "groups_reused": 0, "write_s": 0.0}
        self._frames_seen: dict = {}  # frame digest -> its name, over the groups read (check_distinct_frames)
        self._groups_seen: set = set()

    def read_group(self, key: str) -> np.ndarray:
        """The frames ``[N, H, W]`` of group ``key`` (:func:`read_stack`), refused when one
        repeats a frame of another group read before (byte for byte: a copy)."""
        gl = self.groups[key]
        stack = read_stack(self.path, gl[0], tuple(self.camera_info.frame_shape))
        if key not in self._groups_seen:
            check_distinct_frames(stack, [f"{gl[0]['file']} page {p}" for p in range(stack.shape[0])], self._frames_seen)
            self._groups_seen.add(key)
        return stack

    # ------------------------------------------------------------------ create / open

    @classmethod
    def create(cls, path: str | Path, *, config_yaml: str, camera: CameraInfo) -> "Experiment":
        """A new, empty experiment directory (it must not hold a manifest yet)."""
        path = Path(path)
        (path / "frames").mkdir(parents=True, exist_ok=True)
        lock = RunLock(path)
        mf = path / "manifest.jsonl"  # an empty manifest without experiment.json (written last): a creation cut short
        if (path / "experiment.json").exists() or mf.is_symlink() or (mf.exists() and mf.stat().st_size > 0):
            lock.release()
            raise RecordingError(f"{path}: already holds a recording; resume it with torchblur identify --resume, "
                                 f"or choose another --out")
        meta = {"schema_version": SCHEMA_VERSION, "torchblur_version": __version__, "created": _now(), "camera": camera.to_dict(),
                "status": "running", "sessions": [], INTEGRITY_KEY: {CONFIG_KEY: hashlib.sha256(config_yaml.encode()).hexdigest()}}
        atomic_write_bytes(path / "config.yaml", config_yaml.encode())
        (path / "manifest.jsonl").touch()
        exp = cls(path, meta, [], writable=True)
        exp._lock = lock
        exp._write_meta()
        return exp

    @classmethod
    def open(cls, path: str | Path, *, writable: bool = True, verify: bool = True) -> "Experiment":
        """Open a recording, treated as untrusted input (:mod:`torchblur.hardware.manifest`).
        Writable (a resume): take the run's lock, then repair it (docs/protocol.md, "The
        experiment directory"; ``repaired`` names every group set aside). Read-only: an
        incomplete group at the end (a crash during an append) is left out; any other problem
        raises. ``verify`` checks every group's file hash.

        Raises:
            RecordingError: no recording there, an unknown schema, a bad experiment.json, the
                run locked by another process, or (read-only) a damaged manifest.
        """
        path = Path(path)
        if not (path / "experiment.json").is_file() and (path / "experiment" / "experiment.json").is_file():
            path = path / "experiment"
        mp = path / "experiment.json"
        if not mp.is_file():
            raise RecordingError(f"{path}: no experiment.json here (not a torchblur experiment directory)")
        for name in ("experiment.json", "manifest.jsonl", "config.yaml", "frames", "quarantine"):
            inside(path, name, name)  # none of them a symlink out of the folder
        meta = load_json(read_bounded(mp, MAX_META_BYTES, str(mp)), str(mp))
        check_meta(meta, str(mp))
        _check_config_digest(path, meta)
        if writable and not os.access(path, os.W_OK | os.X_OK):
            raise RecordingError(f"{path}: not writable, and a resume writes the recording (copy the run elsewhere to "
                                 f"resume it, or re-fit it with torchblur fit)")
        lock = RunLock(path) if writable else None
        mf = path / "manifest.jsonl"
        raw = read_bounded(mf, MAX_MANIFEST_BYTES, str(mf)) if mf.exists() or mf.is_symlink() else b""
        scan = scan_manifest(raw, path, verify=verify)
        if not writable and not scan.tail_only:
            raise RecordingError(f"{mf}: damaged ({'; '.join(p[2] for p in scan.problems[:5])}"
                                 f"{'; ...' if len(scan.problems) > 5 else ''}); torchblur identify --resume quarantines it")
        exp = cls(path, meta, scan.lines, writable=writable)
        exp._lock = lock
        exp.repaired = {"dropped_groups": list(scan.dropped), "torn_line": scan.torn_line, "removed_files": [],
                        "problems": [p[2] for p in scan.problems], "quarantine": None}
        if writable:
            _repair(exp, scan)
        return exp

    def close(self) -> None:
        """Give back the run's lock (a writable experiment holds it from create/open)."""
        if getattr(self, "_lock", None) is not None:
            self._lock.release()

    # ------------------------------------------------------------------ metadata

    @property
    def camera_info(self) -> CameraInfo:
        return CameraInfo.from_dict(self.meta["camera"])

    @property
    def config_yaml(self) -> str:
        return read_bounded(self.path / "config.yaml", MAX_META_BYTES, "config.yaml").decode("utf-8", "replace")

    def _write_meta(self) -> None:
        atomic_write_bytes(self.path / "experiment.json", (json.dumps(self.meta, indent=2) + "\n").encode())

    def set_meta(self, key: str, value) -> None:
        """Store ``value`` (JSON-able) as ``key`` of ``experiment.json``, atomically (e.g. a DM
        run's plan, ``dm_plan``); the schema's own keys are refused."""
        self._need_writable()
        if key in ("schema_version", "torchblur_version", "created", "camera", "status", "sessions", INTEGRITY_KEY):
            raise RecordingError(f"{key}: a key of the experiment's schema, not settable")
        value = json.loads(json.dumps(value))  # as it will be read back
        self.meta[key] = value
        self.meta.setdefault(INTEGRITY_KEY, {})[key] = meta_digest(value)  # checked at every open (check_meta)
        self._write_meta()

    def start_session(self, rig: dict) -> int:
        """Note a new session (a run or a resume) with its rig details."""
        self._need_writable()
        s = {"index": len(self.meta["sessions"]), "started": _now(), "rig": rig, "status": "running",
             "groups_at_start": len(self.groups)}
        self.meta["sessions"].append(s)
        self.meta["status"] = "running"
        self._session = s["index"]
        self._write_meta()
        return s["index"]

    def end_session(self, status: str, reason: str = "") -> None:
        """``status``: complete | stopped | interrupted | failed."""
        if not self.writable or self._session is None:
            return
        s = self.meta["sessions"][self._session]
        s.update({"ended": _now(), "status": status, "groups_at_end": len(self.groups)})
        if reason:
            s["reason"] = reason
        self.meta["status"] = status
        self._write_meta()
        self.close()

    def _need_writable(self):
        if not self.writable:
            raise RecordingError(f"{self.path}: opened read-only")
        if self._lock is None or not self._lock.held:
            self._lock = RunLock(self.path)  # released at the end of a session: written again, so owned again

    # ------------------------------------------------------------------ groups

    def has(self, key: str) -> bool:
        return key in self.groups

    def _call_lines(self, key: str) -> list[list]:
        """The manifest lines of group ``key``, one list per rig call (in call order), each in frame order."""
        by_call: dict[int, list] = {}
        for ln in self.groups[key]:
            by_call.setdefault(int(ln["call"]), []).append(ln)
        return [sorted(by_call[ci], key=lambda ln: ln["index"]) for ci in sorted(by_call)]

    def call_values(self, key: str, name: str) -> list[torch.Tensor]:
        """The per-frame value ``name`` of the manifest (``"exposure_s"``, ``"trigger_time_s"``,
        ``"trigger_offset_s"``: s) of each rig call of group ``key``: float64 tensors shaped as the
        call (``call_shape``), NaN where the manifest holds null; the values :meth:`load_calls` puts
        in its Captures, read from the manifest alone (no frame decoded)."""
        return [_line_values(cl, name) for cl in self._call_lines(key)]

    def load_calls(self, key: str) -> list:
        """The recorded rig calls of a group: ``[(method, args, Capture), ...]``."""

        H, W = self.camera_info.frame_shape
        stack = self.read_group(key)
        calls = []
        for cl in self._call_lines(key):
            shape = tuple(cl[0]["call_shape"])
            frames = torch.from_numpy(np.stack([stack[ln["page"]] for ln in cl]).astype(np.float64)).reshape(shape + (H, W))
            meta = dict(cl[0].get("meta", {}))
            meta["recorded"] = True
            cap = Capture(frames=frames, exposure_s=_line_values(cl, "exposure_s"), trigger_offset_s=_line_values(cl, "trigger_offset_s"),
                          trigger_time_s=_line_values(cl, "trigger_time_s"),
                          frame_counter=torch.tensor([int(ln["frame_counter"]) for ln in cl], dtype=torch.long).reshape(shape),
                          meta=meta)
            calls.append((cl[0]["method"], cl[0]["args"], cap))
        self.stats["groups_reused"] += 1
        return calls

    def record(self, key: str, kind: str, calls: list, *, labels: dict | None = None) -> None:
        """Store a complete group: its TIFF (atomic), then its manifest lines (one fsync'ed
        append). ``calls``: ``[(method, args dict, Capture), ...]``; ``labels`` are added to
        every line (e.g. ``input``, ``freq_hz``, ``amplitude``)."""
        import tifffile

        self._need_writable()
        if key in self.groups:
            raise RecordingError(f"{key}: already recorded")
        t0 = time.perf_counter()
        labels = dict(labels or {})
        frames, lines = [], []
        n_total = sum(int(np.prod(c[2].shape)) if len(c[2].shape) else 1 for c in calls)
        fname = expected_file(key)
        page = 0
        for ci, (method, args, cap) in enumerate(calls):
            shape = tuple(cap.shape)
            H, W = cap.frame_shape
            fr = cap.frames.detach().cpu().reshape(-1, H, W).to(_F64).numpy()
            flat = lambda x: x.detach().cpu().reshape(-1).tolist()  # noqa: E731
            exp_s, off_s, trig_s, cnt = flat(cap.exposure_s), flat(cap.trigger_offset_s), flat(cap.trigger_time_s), flat(cap.frame_counter)
            ts = flat(cap.meta["timestamp_s"]) if isinstance(cap.meta.get("timestamp_s"), torch.Tensor) else [None] * len(cnt)
            meta = {k: _jsonable(v) for k, v in cap.meta.items() if not isinstance(v, torch.Tensor)}
            for i in range(fr.shape[0]):
                idx = np.unravel_index(i, shape) if shape else ()
                e_idx = int(idx[0]) if len(shape) == 2 else None
                rep = int(idx[-1]) if len(shape) >= 1 else 0
                frames.append(fr[i])
                ln = {"group": key, "kind": kind, "group_frames": n_total, "call": ci, "method": method, "index": i,
                      "call_shape": list(shape), "input": labels.get("input"), "freq_hz": labels.get("freq_hz"),
                      "exposure_s": exp_s[i], "exposure_index": e_idx, "repeat": rep, "file": fname, "page": page,
                      "frame_counter": int(cnt[i]), "boot": meta.get("boot"), "session": self._session, "timestamp_s": ts[i],
                      "trigger_time_s": json_floats(trig_s[i]), "trigger_offset_s": json_floats(off_s[i]),
                      "args": args, "meta": meta}
                for k, v in labels.items():
                    if k not in ln:
                        ln[k] = _jsonable(v)
                lines.append(ln)
                page += 1
        stack = raw_pixels(np.stack(frames))
        for ln in lines:
            ln["dtype"] = stack.dtype.name
        lines = [json.loads(json.dumps(ln)) for ln in lines]  # as they will be read back
        settings = settings_digest(lines)  # the group's settings, hashed now and checked at every read
        buf = io.BytesIO()
        tifffile.imwrite(buf, stack, photometric="minisblack", metadata=None,
                         description=json.dumps({"torchblur_group": key, "kind": kind, "frames": len(lines), SETTINGS_KEY: settings}))
        data = buf.getvalue()
        sha = hashlib.sha256(data).hexdigest()
        for ln in lines:
            ln["sha256"] = sha
            ln[SETTINGS_KEY] = settings
        atomic_write_bytes(self.path / fname, data)
        blob = b"".join(json.dumps(ln, separators=(",", ":")).encode() + b"\n" for ln in lines)
        with open(self.path / "manifest.jsonl", "ab") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        self.lines += lines
        self.groups[key] = lines
        self.stats["groups_written"] += 1
        self.stats["write_s"] += time.perf_counter() - t0

    def stage(self, key: str, kind: str, rig, fn, *, labels: dict | None = None):
        """Run ``fn(rig)`` as group ``key``: from the recording if it is there (the calls are
        replayed in order and checked), else on ``rig``, recording every call. Returns
        ``(fn's result, reused)``."""
        if key in self.groups:
            return fn(_ReplayCalls(self.camera_info, self.load_calls(key), key)), True
        proxy = _RecordingRig(rig)
        out = fn(proxy)
        if self.writable:
            self.record(key, kind, proxy.calls, labels=labels)
        return out, False


CONFIG_KEY = "config.yaml"  # experiment.json's integrity entry for the recorded config


def _line_values(lines: list, name: str) -> torch.Tensor:
    """The value ``name`` of one rig call's manifest ``lines`` (in frame order) as float64 shaped as
    the call (``call_shape``), NaN where null."""
    return torch.tensor([float(ln[name]) if ln[name] is not None else float("nan") for ln in lines],
                        dtype=_F64).reshape(tuple(lines[0]["call_shape"]))


def _check_config_digest(path: Path, meta: dict) -> None:
    """The recorded ``config.yaml`` must have the digest ``experiment.json`` noted at creation.

    Raises:
        RecordingError: naming ``config.yaml`` (edited, or a recording without the digest).
    """
    want = meta.get(INTEGRITY_KEY, {}).get(CONFIG_KEY)
    if not isinstance(want, str):
        raise RecordingError(f"{path / CONFIG_KEY}: no digest in experiment.json's {INTEGRITY_KEY} (recorded by a torchblur before "
                             f"metadata digests, or edited): the recorded config cannot be checked; refused")
    got = hashlib.sha256(read_bounded(path / CONFIG_KEY, MAX_META_BYTES, CONFIG_KEY)).hexdigest()
    if got != want:
        raise RecordingError(f"{path / CONFIG_KEY}: changed after it was recorded (its digest differs from experiment.json's); refused")


MAX_TIFF_RATIO = 1000  #: the most a compressed TIFF's pixels may outweigh its bytes (real frames: 1-10)
MAX_TIFF_TILE_BYTES = 1 << 28  #: one decoded tile or strip, at most (256 MiB)


def tiff_header_limits(tf, series, n_bytes: int, name: str, max_bytes: int | None = None) -> int:
    """Check what a TIFF declares before any pixel is decoded (tifffile reads only its tags):
    every page's sides at most :data:`MAX_FRAME_SIDE`, the series' decoded size at most
    ``max_bytes``, at most :data:`MAX_TIFF_RATIO` times the file's ``n_bytes`` (compressed) or
    within them (uncompressed), and each tile at most :data:`MAX_TIFF_TILE_BYTES`. Returns the
    decoded size (bytes).

    Raises:
        RecordingError: naming the file ``name`` and the limit.
    """
    page = series.pages[0] if len(series.pages) and series.pages[0] is not None else tf.pages.first
    itemsize = np.dtype(series.dtype).itemsize
    decoded = math.prod(int(v) for v in series.shape) * itemsize
    sides = (int(page.imagelength), int(page.imagewidth), int(getattr(page, "imagedepth", 1) or 1))
    if max(sides) > MAX_FRAME_SIDE:
        raise RecordingError(f"{name}: declares {sides[0]}x{sides[1]} pixel pages, more than {MAX_FRAME_SIDE} a side; refused "
                             f"before decoding")
    if max_bytes is not None and decoded > max_bytes:
        raise RecordingError(f"{name}: declares {tuple(series.shape)} {np.dtype(series.dtype).name} pixels ({decoded} bytes), more "
                             f"than the {max_bytes} it may hold; refused before decoding")
    compressed = int(page.compression) != 1
    if decoded > (MAX_TIFF_RATIO if compressed else 1) * max(n_bytes, 1):
        why = f"more than {MAX_TIFF_RATIO} times its {n_bytes} bytes" if compressed else f"more than its {n_bytes} uncompressed bytes"
        raise RecordingError(f"{name}: declares {decoded} bytes of pixels, {why}; refused before decoding")
    if page.is_tiled:
        tile = int(page.tilewidth) * int(page.tilelength) * max(int(page.tiledepth or 1), 1) * int(page.samplesperpixel) * itemsize
    else:
        tile = int(page.imagewidth) * int(page.rowsperstrip or 1) * int(page.samplesperpixel) * itemsize
    if tile > MAX_TIFF_TILE_BYTES:
        raise RecordingError(f"{name}: declares tiles or strips of {tile} bytes, more than {MAX_TIFF_TILE_BYTES}; refused before decoding")
    return decoded


def decode_tiff(data: bytes, name: str, check=None, *, what: str = "TIFF", max_bytes: int | None = None) -> np.ndarray:
    """The first series of the TIFF bytes ``data`` (an untrusted file's) as an array, after
    :func:`tiff_header_limits` (``max_bytes``: the most decoded bytes). ``check(series)`` (a
    tifffile ``TiffPageSeries``) may refuse it with a RecordingError before its pixels are
    decoded; any other failure of the decoder is a RecordingError naming the file (``name``:
    "not a readable ``what``")."""
    import tifffile

    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tf:
            series = tf.series[0]
            tiff_header_limits(tf, series, len(data), name, max_bytes)
            if check is not None:
                check(series)
            return np.asarray(series.asarray())
    except RecordingError:
        raise
    except Exception as exc:  # a third-party decoder on untrusted bytes: any failure is a bad file
        raise RecordingError(f"{name}: not a readable {what} ({type(exc).__name__}: {excerpt(str(exc), 100)})") from None


def read_stack(root: Path, line: dict, frame_shape: tuple) -> np.ndarray:
    """The frames ``[N, H, W]`` of the file of a group's manifest ``line`` (N its
    ``group_frames``), after checking that the bytes read have the line's SHA-256 and decode
    to N finite ``H x W`` frames of the line's dtype.

    Raises:
        RecordingError: naming the file.
    """

    n, (H, W) = int(line["group_frames"]), frame_shape
    name = line["file"]
    data = read_bounded(inside(root, name, "file"), n * H * W * 8 + (1 << 20), name)
    if hashlib.sha256(data).hexdigest() != line["sha256"]:
        raise RecordingError(f"{line['group']}: {name}: its SHA-256 is not the recorded one (the file changed after "
                             f"it was recorded); refused")
    def check(series):
        _check_description(series, line, name)
        if (math.prod(series.shape) != n * H * W or tuple(series.shape[-2:]) != (H, W)
                or np.dtype(series.dtype).name != line["dtype"]):
            raise RecordingError(f"{name}: holds {series.shape} {np.dtype(series.dtype).name} values, the manifest "
                                 f"{n} frames of {H}x{W} {line['dtype']}")

    stack = decode_tiff(data, name, check, what="TIFF stack", max_bytes=n * H * W * 8).reshape(n, H, W)
    if not np.isfinite(stack).all():
        raise RecordingError(f"{name}: holds NaN or infinite pixels; refused")
    check_distinct_frames(stack, [f"{name} page {p}" for p in range(n)])
    return stack


def _check_description(series, line: dict, name: str) -> None:
    """The TIFF's description (written with the group) must carry the settings digest of the
    group's manifest lines: lines edited with their digest recomputed are refused too."""
    try:
        desc = json.loads(series.pages[0].description or "{}")
    except (ValueError, AttributeError, IndexError, TypeError):
        desc = {}
    if not isinstance(desc, dict) or desc.get(SETTINGS_KEY) != line.get(SETTINGS_KEY):
        raise RecordingError(f"{line['group']}: {name}: its description does not carry the group's settings digest (the "
                             f"manifest's settings were changed after recording); refused")


def frame_digest(frame: np.ndarray) -> bytes | None:
    """A content digest of one frame's pixels (its dtype, shape and bytes), or None for a
    constant frame (two such are indistinguishable measurements, not copies)."""
    frame = np.ascontiguousarray(frame)
    if frame.size == 0 or frame.min() == frame.max():
        return None
    h = hashlib.blake2b(digest_size=20)
    h.update(f"{frame.dtype.str}{frame.shape}".encode())
    h.update(frame.tobytes())
    return h.digest()


def check_distinct_frames(frames, names: list, seen: dict | None = None) -> dict:
    """Refuse a frame whose pixels repeat another's byte for byte (a copy counted as an
    independent repeat makes every std too small): ``frames`` ``[N, H, W]``, ``names`` what to
    call each in the message, ``seen`` the digests met so far (digest -> name; updated and
    returned, to check across files).

    Raises:
        RecordingError: naming both frames.
    """
    seen = {} if seen is None else seen
    for frame, name in zip(frames, names):
        d = frame_digest(frame)
        if d is None:
            continue
        if d in seen:
            raise RecordingError(f"{name}: the same pixels as {seen[d]} (a copy, not an independent frame); refused")
        seen[d] = name
    return seen


def _repair(exp: "Experiment", scan: ManifestScan) -> None:
    """Set aside what ``scan`` could not keep (to ``quarantine/<stamp>/``; only ``*.tmp`` files are
    removed) and rewrite the manifest with the kept lines, last (docs/protocol.md, "The experiment
    directory")."""
    path, rep = exp.path, exp.repaired
    referenced = {ln["file"] for ln in scan.lines}
    movable = []
    for folder in (path, path / "frames"):
        if not folder.is_dir() or folder.is_symlink():
            continue
        for f in sorted(folder.iterdir()):
            rel = f.relative_to(path).as_posix()
            if f.name.endswith(_TMP) and f.is_file() and not f.is_symlink():
                f.unlink()
                rep["removed_files"].append(rel)
            elif folder.name == "frames" and folder != path and rel not in referenced:
                movable.append(f)
    if scan.bad_raw or movable:
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        q = inside(path, f"quarantine/{stamp}-{os.getpid()}", "quarantine")  # a symlinked quarantine/ is refused
        (q / "frames").mkdir(parents=True)
        atomic_write_bytes(q / "manifest.jsonl", b"".join(r + b"\n" for r in scan.bad_raw))
        reasons = {"groups": scan.dropped, "problems": rep["problems"], "files": [f"frames/{f.name}" for f in movable]}
        atomic_write_bytes(q / "reasons.json", (json.dumps(reasons, indent=2) + "\n").encode())
        for f in movable:
            os.replace(f, q / "frames" / f.name)
        _fsync_dir(q / "frames")
        rep["quarantine"] = str(q)
        rep["quarantined_files"] = reasons["files"]
    if scan.bad_raw or scan.torn_line:
        atomic_write_bytes(path / "manifest.jsonl", b"".join(r + b"\n" for r in scan.raw))
