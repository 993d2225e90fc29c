"""The experiment directory: written as a run goes, read back to resume or re-fit it.

Layout (schema :data:`SCHEMA_VERSION`, docs/protocol.md "Experiment directory")::

    experiment.json    schema_version, torchblur version, camera, sessions, status
    config.yaml        the resolved configuration of the run
    manifest.jsonl     one JSON line per stored frame
    frames/*.tif       one TIFF stack per group (pages = frames, raw camera values)

A *group* is the unit of storage and of resumption: the dark frames, the saturation ladder,
the PSF frames, the latency scan, and each sweep point. A group is stored when it is
complete: its TIFF is written to a temporary name, fsync'ed and renamed (``os.replace``),
then its manifest lines are appended with one write, flushed and fsync'ed. So a crash leaves
either the whole group or none of it: on opening, a manifest whose last group is
incomplete (a torn append) is rewritten without it (atomically), leftover temporary files
and unreferenced TIFFs are removed. A sweep point stores only the frames the fit uses (the
accepted amplitude), so each sweep frame (input, frequency, exposure, repeat) is stored once.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import inspect
import io
import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from torchblur.hardware.errors import FrameTimeout, RecordingError
from torchblur.hardware.frames import CameraInfo, Frame, FrameSource

__all__ = ["SCHEMA_VERSION", "Experiment", "ReplayFrames", "ReplayRig", "atomic_write_bytes", "camera_info_of"]

SCHEMA_VERSION = 1
_TMP = ".tmp"
_F64 = torch.float64


# ---------------------------------------------------------------------- atomic files


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
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
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    if fsync:
        _fsync_dir(path.parent)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def camera_info_of(rig) -> CameraInfo:
    """The :class:`CameraInfo` of any rig (its Rig properties)."""
    return CameraInfo(frame_shape=tuple(int(v) for v in rig.frame_shape), frame_rate_hz=float(rig.frame_rate_hz),
                      max_exposure_s=float(rig.max_exposure_s), readout_s=float(rig.readout_s),
                      name=getattr(getattr(rig, "info", None), "name", "") or type(rig).__name__)


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
    from torchblur.rig.base import Rig

    sig = inspect.signature(getattr(Rig, method))
    bound = sig.bind(None, *args, **kwargs)
    bound.apply_defaults()
    return {k: _jsonable(v) for k, v in bound.arguments.items() if k != "self"}


# ---------------------------------------------------------------------- rig proxies


class _RigProperties:
    def __init__(self, info: CameraInfo):
        self._info = info

    @property
    def frame_shape(self):
        return tuple(self._info.frame_shape)

    @property
    def frame_rate_hz(self):
        return self._info.frame_rate_hz

    @property
    def max_exposure_s(self):
        return self._info.max_exposure_s

    @property
    def readout_s(self):
        return self._info.readout_s


class _RecordingRig:
    """Forwards every rig call and keeps ``(method, args, capture)``."""

    def __init__(self, rig):
        self._rig = rig
        self.calls: list = []

    def __getattr__(self, name):
        return getattr(self._rig, name)

    def _call(self, method, args, kwargs):
        cap = getattr(self._rig, method)(*args, **kwargs)
        self.calls.append((method, _bind(method, args, kwargs), cap))
        return cap

    def dark(self, *a, **k):
        return self._call("dark", a, k)

    def still(self, *a, **k):
        return self._call("still", a, k)

    def sine(self, *a, **k):
        return self._call("sine", a, k)

    def pulse(self, *a, **k):
        return self._call("pulse", a, k)

    def multisine(self, *a, **k):
        return self._call("multisine", a, k)


class _ReplayCalls(_RigProperties):
    """Serves recorded calls in order; a call that differs from the recording is an error."""

    def __init__(self, info: CameraInfo, calls: list, key: str):
        super().__init__(info)
        self._calls, self._key, self._i = calls, key, 0

    def _next(self, method, args, kwargs):
        want = _bind(method, args, kwargs)
        if self._i >= len(self._calls):
            raise RecordingError(f"{self._key}: the pipeline asks for more rig calls than the recording holds "
                                 f"({len(self._calls)}); was it recorded with another version or config?")
        m, got, cap = self._calls[self._i]
        if m != method or set(got) != set(want) or not all(_same(got[k], want[k]) for k in want):
            diff = [k for k in want if k not in got or not _same(got[k], want[k])]
            raise RecordingError(f"{self._key}: rig call {self._i} is {method}({', '.join(f'{k}={want[k]!r}' for k in diff)}), "
                                 f"the recording holds {m}({', '.join(f'{k}={got.get(k)!r}' for k in diff)})")
        self._i += 1
        return cap

    def dark(self, *a, **k):
        return self._next("dark", a, k)

    def still(self, *a, **k):
        return self._next("still", a, k)

    def sine(self, *a, **k):
        return self._next("sine", a, k)

    def pulse(self, *a, **k):
        return self._next("pulse", a, k)

    def multisine(self, *a, **k):
        return self._next("multisine", a, k)


class ReplayRig(_RigProperties):
    """A rig that only knows the recording: every live call raises :class:`RecordingError`
    (the run is incomplete; resume it first). Used by ``torchblur fit``."""

    def __init__(self, experiment: "Experiment"):
        super().__init__(experiment.camera_info)
        self._dir = experiment.path

    def _missing(self, *a, **k):
        raise RecordingError(f"{self._dir}: the recording is incomplete (a group the pipeline needs is missing); "
                             f"resume it first: torchblur identify --resume {self._dir.parent if self._dir.name == 'experiment' else self._dir} "
                             f"rig.port=... rig.frames=...")

    dark = still = sine = pulse = multisine = _missing


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
        self.stats = {"groups_written": 0, "groups_reused": 0, "write_s": 0.0}

    # ------------------------------------------------------------------ create / open

    @classmethod
    def create(cls, path: str | Path, *, config_yaml: str, camera: CameraInfo) -> "Experiment":
        """A new, empty experiment directory (it must not hold a manifest yet)."""
        path = Path(path)
        if (path / "manifest.jsonl").exists():
            raise RecordingError(f"{path}: already holds a recording; resume it with torchblur identify --resume, "
                                 f"or choose another --out")
        (path / "frames").mkdir(parents=True, exist_ok=True)
        meta = {"schema_version": SCHEMA_VERSION, "torchblur_version": _version(), "created": _now(), "camera": camera.to_dict(),
                "status": "running", "sessions": []}
        atomic_write_bytes(path / "config.yaml", config_yaml.encode())
        (path / "manifest.jsonl").touch()
        exp = cls(path, meta, [], writable=True)
        exp._write_meta()
        return exp

    @classmethod
    def open(cls, path: str | Path, *, writable: bool = True, verify: bool = True) -> "Experiment":
        """Open a recording. Writable: repair it first (drop a torn last group, temporary files
        and unreferenced TIFFs). ``verify`` checks every group's file hash.

        Raises:
            RecordingError: no recording there, or an unknown schema version.
        """
        path = Path(path)
        if not (path / "experiment.json").is_file() and (path / "experiment" / "experiment.json").is_file():
            path = path / "experiment"
        mp = path / "experiment.json"
        if not mp.is_file():
            raise RecordingError(f"{path}: no experiment.json here (not a torchblur experiment directory)")
        try:
            meta = json.loads(mp.read_text())
        except ValueError as exc:
            raise RecordingError(f"{mp}: not JSON: {exc}") from None
        if meta.get("schema_version") != SCHEMA_VERSION:
            raise RecordingError(f"{mp}: schema_version {meta.get('schema_version')!r}; this torchblur reads {SCHEMA_VERSION}")
        raw = (path / "manifest.jsonl").read_bytes() if (path / "manifest.jsonl").exists() else b""
        parts = raw.split(b"\n")
        torn = parts[-1] != b""  # the last line lacks its newline: a torn append
        lines = []
        for p in parts[:-1]:
            if not p.strip():
                continue
            try:
                lines.append(json.loads(p))
            except ValueError:
                torn = True
                break
        # keep complete groups only (all their lines, their file present and intact)
        order, by = [], {}
        for ln in lines:
            g = ln.get("group")
            if g not in by:
                order.append(g)
                by[g] = []
            by[g].append(ln)
        kept, dropped = [], []
        for g in order:
            gl = by[g]
            ok = len(gl) == int(gl[0].get("group_frames", -1)) and all(ln.get("group") == g for ln in gl)
            f = path / gl[0]["file"]
            ok = ok and f.is_file()
            if ok and verify:
                ok = hashlib.sha256(f.read_bytes()).hexdigest() == gl[0].get("sha256")
            (kept if ok else dropped).append(g)
        keep_lines = [ln for g in kept for ln in by[g]]
        exp = cls(path, meta, keep_lines, writable=writable)
        exp.repaired = {"dropped_groups": dropped, "torn_line": torn, "removed_files": []}
        if writable:
            if dropped or torn:
                data = b"".join(json.dumps(ln, separators=(",", ":")).encode() + b"\n" for ln in keep_lines)
                atomic_write_bytes(path / "manifest.jsonl", data)
            referenced = {ln["file"] for ln in keep_lines}
            for folder in (path, path / "frames"):
                if not folder.is_dir():
                    continue
                for f in folder.iterdir():
                    rel = f.relative_to(path).as_posix()
                    if f.name.endswith(_TMP) or (folder.name == "frames" and f.suffix == ".tif" and rel not in referenced):
                        f.unlink()
                        exp.repaired["removed_files"].append(rel)
        return exp

    # ------------------------------------------------------------------ metadata

    @property
    def camera_info(self) -> CameraInfo:
        return CameraInfo.from_dict(self.meta["camera"])

    @property
    def config_yaml(self) -> str:
        return (self.path / "config.yaml").read_text()

    def _write_meta(self) -> None:
        atomic_write_bytes(self.path / "experiment.json", (json.dumps(self.meta, indent=2) + "\n").encode())

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

    def _need_writable(self):
        if not self.writable:
            raise RecordingError(f"{self.path}: opened read-only")

    # ------------------------------------------------------------------ groups

    def has(self, key: str) -> bool:
        return key in self.groups

    def load_calls(self, key: str) -> list:
        """The recorded rig calls of a group: ``[(method, args, Capture), ...]``."""
        from torchblur.rig.base import Capture
        import tifffile

        gl = self.groups[key]
        stack = np.asarray(tifffile.imread(self.path / gl[0]["file"]))
        H, W = self.camera_info.frame_shape
        stack = stack.reshape(-1, H, W)
        if stack.shape[0] != len(gl):
            raise RecordingError(f"{key}: {gl[0]['file']} holds {stack.shape[0]} frames, the manifest {len(gl)}")
        calls = []
        by_call: dict[int, list] = {}
        for ln in gl:
            by_call.setdefault(int(ln["call"]), []).append(ln)
        for ci in sorted(by_call):
            cl = sorted(by_call[ci], key=lambda ln: ln["index"])
            shape = tuple(cl[0]["call_shape"])
            frames = torch.from_numpy(np.stack([stack[ln["page"]] for ln in cl]).astype(np.float64)).reshape(shape + (H, W))
            t = lambda k: torch.tensor([float(ln[k]) if ln[k] is not None else float("nan") for ln in cl], dtype=_F64).reshape(shape)  # noqa: E731
            meta = dict(cl[0].get("meta", {}))
            meta["recorded"] = True
            cap = Capture(frames=frames, exposure_s=t("exposure_s"), trigger_offset_s=t("trigger_offset_s"),
                          trigger_time_s=t("trigger_time_s"),
                          frame_counter=torch.tensor([int(ln["frame_counter"]) for ln in cl], dtype=torch.long).reshape(shape),
                          meta=meta)
            calls.append((cl[0]["method"], cl[0]["args"], cap))
        self.stats["groups_reused"] += 1
        return calls

    def record(self, key: str, kind: str, calls: list, *, labels: dict | None = None) -> None:
        """Store a complete group: its TIFF (atomic), then its manifest lines (one fsync'ed
        append). ``calls``: ``[(method, args dict, Capture), ...]``; ``labels`` are added to
        every line (e.g. ``input``, ``freq_hz``, ``amplitude``)."""
        import time

        import tifffile

        self._need_writable()
        if key in self.groups:
            raise RecordingError(f"{key}: already recorded")
        t0 = time.perf_counter()
        labels = dict(labels or {})
        frames, lines = [], []
        n_total = sum(int(np.prod(c[2].shape)) if len(c[2].shape) else 1 for c in calls)
        fname = "frames/" + key.replace("/", "_") + ".tif"
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
                      "trigger_time_s": _finite_or_none(trig_s[i]), "trigger_offset_s": _finite_or_none(off_s[i]),
                      "args": args, "meta": meta}
                for k, v in labels.items():
                    if k not in ln:
                        ln[k] = _jsonable(v)
                lines.append(ln)
                page += 1
        stack = np.stack(frames)
        if np.all(stack >= 0) and np.all(stack <= 65535) and np.all(stack == np.round(stack)):
            stack = stack.astype(np.uint16)
        buf = io.BytesIO()
        tifffile.imwrite(buf, stack, photometric="minisblack", metadata=None,
                         description=json.dumps({"torchblur_group": key, "kind": kind, "frames": len(lines)}))
        data = buf.getvalue()
        sha = hashlib.sha256(data).hexdigest()
        for ln in lines:
            ln["dtype"] = stack.dtype.name
            ln["sha256"] = sha
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


def _finite_or_none(v):
    return v if v is not None and math.isfinite(v) else None


def _version() -> str:
    from torchblur import __version__

    return __version__


# ---------------------------------------------------------------------- replay as a frame source


class ReplayFrames(FrameSource):
    """A recorded experiment directory as a :class:`FrameSource`: :meth:`read` returns its
    frames in manifest order (then raises :class:`FrameTimeout`: the recording ended).

    Args:
        path: the experiment directory (or the run's output folder holding ``experiment/``).

    Attributes:
        experiment: the read-only :class:`Experiment`.
        records: its manifest lines.
    """

    def __init__(self, path: str | Path):
        self.experiment = Experiment.open(path, writable=False)
        self.records = self.experiment.lines
        self._i = 0
        self._cache: dict[str, np.ndarray] = {}

    @property
    def info(self) -> CameraInfo:
        return self.experiment.camera_info

    def _stack(self, file: str) -> np.ndarray:
        import tifffile

        if file not in self._cache:
            H, W = self.info.frame_shape
            self._cache = {file: np.asarray(tifffile.imread(self.experiment.path / file)).reshape(-1, H, W)}
        return self._cache[file]

    def frame(self, record: dict) -> Frame:
        """The :class:`Frame` of one manifest line."""
        px = self._stack(record["file"])[record["page"]]
        nan = float("nan")
        return Frame(data=torch.from_numpy(px.astype(np.float64)), counter=int(record["frame_counter"]),
                     timestamp_s=record["timestamp_s"] if record.get("timestamp_s") is not None else nan,
                     exposure_s=float(record["exposure_s"]),
                     trigger_time_s=record["trigger_time_s"] if record.get("trigger_time_s") is not None else nan,
                     trigger_offset_s=record["trigger_offset_s"] if record.get("trigger_offset_s") is not None else nan,
                     dtype=record.get("dtype", "float64"), boot=record.get("boot"),
                     meta={k: record.get(k) for k in ("kind", "group", "input", "freq_hz", "exposure_index", "repeat")})

    def select(self, **where) -> list[dict]:
        """Manifest lines whose fields equal ``where`` (e.g. ``kind="sweep"``)."""
        return [r for r in self.records if all(r.get(k) == v for k, v in where.items())]

    def read(self, timeout_s: float = 0.0) -> Frame:
        if self._i >= len(self.records):
            raise FrameTimeout("end of the recording")
        rec = self.records[self._i]
        self._i += 1
        return self.frame(rec)

    def rewind(self) -> None:
        self._i = 0

    def __len__(self) -> int:
        return len(self.records)

    def __repr__(self) -> str:
        return f"ReplayFrames({str(self.experiment.path)!r}, {len(self.records)} frames)"
