"""Outside recordings: frames a lab took with its own camera and function generator
(``frames.csv``, its TIFF files and ``recording.yaml``: docs/outside_recordings.md), read as untrusted
input into one checked object; every error is a :class:`~torchblur.hardware.errors.RecordingError`
naming the file, the line and the column, and nothing is written.

:func:`read_outside_recording` gives an :class:`OutsideRecording` (one-input recordings only: an
``axis`` column is refused). A deformable mirror's recording (:mod:`torchblur.identify.dm_outside`) is
read by the same functions (:func:`read_folder`, :func:`read_csv`, :func:`number`) with its extra
columns and sections.
"""
from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import math
import os
import posixpath
from dataclasses import dataclass, fields, replace
from functools import partial
from pathlib import Path
from typing import Optional

import numpy as np

from torchblur.errors import ConfigError
from torchblur.files import excerpt, open_regular
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.manifest import MAX_FRAME_SIDE, MAX_AMPLITUDE, read_bounded
from torchblur.hardware.recording import check_distinct_frames, tiff_header_limits
from torchblur.hardware.run_folder import inside
from torchblur.config import check_declared, key, load_dataclass, whole_periods

__all__ = ["CSV_NAME", "YAML_NAME", "OutsideCamera", "OutsideFrames", "OutsidePoint", "OutsideRecording", "is_outside_recording", "number",
           "read_csv", "read_folder", "read_outside_recording"]

CSV_NAME = "frames.csv"
YAML_NAME = "recording.yaml"
MAX_CSV_BYTES = 64 * 1024 * 1024
MAX_ROWS = 200_000
MAX_TIFF_BYTES = 4 * 1024 ** 3
MAX_PIXELS = 2 ** 31  # all frames together: 16 GiB as float64
MAX_FREQ_HZ = 1e7
MAX_EXPOSURE_S = 1e3
KINDS = ("dark", "still", "sweep")
DM_KINDS = KINDS + ("ladder",)  #: a DM recording's rows: also its patterns held still (columns pattern, level)
REQUIRED = ("file", "kind")
OPTIONAL = ("page", "freq_hz", "exposure_s", "window_start_s", "trigger_phase_rad", "amplitude", "power", "repeat", "note")


@dataclass(frozen=True)
class OutsideCamera:
    """``recording.yaml``: ``gain_e_per_adu`` (electrons per ADU, required), ``read_noise_e``
    (electrons; None: measured from the dark frames), ``saturation_adu`` (raw value where the
    sensor clips; None: the integer dtype's maximum, none for float frames),
    ``trigger_delay_s`` and ``latency_s`` (the exposure begins ``trigger_delay_s +
    latency_s`` after the trigger; used with ``trigger_phase_rad``), ``latency_std_s`` (std of
    every exposure's start, common to the whole recording: enters the phase std),
    ``jitter_s`` (frame-to-frame std of the start), ``input_unit`` (a label). The bounds: beyond
    them a value is a typo, and its square overflows."""

    gain_e_per_adu: Optional[float] = key(None, positive=True, high=1e6, optional=True)
    read_noise_e: Optional[float] = key(None, nonnegative=True, high=1e6, optional=True)
    saturation_adu: Optional[float] = key(None, low=-1e12, high=1e12, optional=True)
    trigger_delay_s: float = key(0.0, low=-MAX_EXPOSURE_S, high=MAX_EXPOSURE_S)
    latency_s: float = key(0.0, low=-MAX_EXPOSURE_S, high=MAX_EXPOSURE_S)
    latency_std_s: float = key(0.0, nonnegative=True, high=MAX_EXPOSURE_S)
    jitter_s: float = key(0.0, nonnegative=True, high=MAX_EXPOSURE_S)
    input_unit: str = "input unit"


@dataclass(frozen=True)
class OutsidePoint:
    """One sweep point: ``freq_hz``, ``amplitude`` (input units), ``power`` (light relative to
    the still frames), ``frames`` ``[E*R, H, W]`` (ADU, float64, exposure-major; None where the
    reader left them in the files: a DM recording's, read by ``lines``),
    ``start_s`` and ``duration_s`` ``[E*R]`` (the window of each frame, s after the command's
    upward zero crossing), ``R`` (images per exposure) and ``lines`` (their CSV lines)."""

    freq_hz: float
    amplitude: float
    power: float
    frames: np.ndarray | None
    start_s: np.ndarray
    duration_s: np.ndarray
    R: int
    lines: tuple

    @property
    def E(self) -> int:
        return len(self.lines) // self.R


@dataclass(frozen=True)
class OutsideFrames:
    """What both outside formats hold (:func:`read_folder`): ``path``, ``camera``
    (:class:`OutsideCamera`, saturation resolved), ``dark`` ``[Nd, H, W]`` and ``still``
    ``[Ns, H, W]`` (ADU, float64), ``still_exposure_s``, ``frame_shape`` (H, W), ``n_frames``
    (rows read) and ``saturation_source`` (where ``camera.saturation_adu`` came from, in words)."""

    path: Path
    camera: OutsideCamera
    dark: np.ndarray
    still: np.ndarray
    still_exposure_s: float
    frame_shape: tuple
    n_frames: int
    saturation_source: str


@dataclass(frozen=True)
class OutsideRecording(OutsideFrames):
    """A checked outside recording: :class:`OutsideFrames` and ``points`` (:class:`OutsidePoint`, increasing frequency)."""

    points: tuple


def is_outside_recording(path) -> bool:
    """Whether ``path`` is a folder with a ``frames.csv`` (an outside recording)."""
    return (Path(path) / CSV_NAME).is_file()


def read_outside_recording(path) -> OutsideRecording:
    """Read and check the outside recording in folder ``path`` (docs/outside_recordings.md).

    Raises:
        RecordingError: naming the file, line and column of the first problem.
    """
    root = Path(path)
    if not root.is_dir():
        raise RecordingError(f"{root}: not a folder")
    if not (root / CSV_NAME).is_file():
        raise RecordingError(f"{root}: no {CSV_NAME}; not an outside recording (docs/outside_recordings.md)")
    common, by_kind, frames = read_folder(root)
    return OutsideRecording(points=_points(by_kind["sweep"], frames, common["camera"]), **common)


def read_folder(root: Path, sections: tuple = (), extra: tuple = ()) -> tuple[dict, dict, dict]:
    """What both outside formats share, read and checked: ``recording.yaml``'s camera keys (its
    other top-level ``sections`` are the caller's), ``frames.csv``'s rows (``extra``: the columns a
    DM recording adds) and their frames, checked. Returns ``(the fields of OutsideFrames, rows by kind,
    the FrameStore that reads the frames by line)``."""
    camera = _read_camera(root, sections)
    rows = _read_rows(root, extra)
    frames = _read_frames(root, rows)
    dtype = frames.dtype
    given = camera.saturation_adu is not None
    camera = _resolved_saturation(camera, dtype)
    if given:
        source = f"{camera.saturation_adu:.6g} ADU ({YAML_NAME})"
    elif camera.saturation_adu is not None:
        source = (f"{camera.saturation_adu:.6g} ADU (the {np.dtype(dtype).name} maximum; give saturation_adu in {YAML_NAME} if the "
                  f"sensor clips lower)")
    else:
        source = f"none (float frames and no saturation_adu in {YAML_NAME}: no pixel is masked)"
    by_kind = {k: [r for r in rows if r["kind"] == k] for k in DM_KINDS}
    for kind, least in (("dark", 2), ("still", 1), ("sweep", 1)):
        if len(by_kind[kind]) < least:
            raise RecordingError(f"{CSV_NAME}: {len(by_kind[kind])} row(s) of kind {excerpt(kind)}; at least {least} needed")
    te = {r["exposure_s"] for r in by_kind["still"]}
    if None in te or len(te) != 1:
        line = next(r["line"] for r in by_kind["still"] if r["exposure_s"] is None or r["exposure_s"] != by_kind["still"][0]["exposure_s"])
        raise RecordingError(f"{CSV_NAME} line {line}, column exposure_s: every still frame needs one and the same exposure_s "
                             f"(the PSF's light per second), got {sorted(map(str, te))}")
    take = lambda kind: frames.load([r["line"] for r in by_kind[kind]]).astype(np.float64)  # noqa: E731
    return (dict(path=root, camera=camera, dark=take("dark"), still=take("still"), still_exposure_s=te.pop(),
                 frame_shape=frames.frame_shape, n_frames=len(rows), saturation_source=source), by_kind, frames)


def _read_camera(root: Path, sections: tuple = ()) -> OutsideCamera:
    """``recording.yaml`` as an :class:`OutsideCamera`, every value checked (its top-level
    ``sections``, a DM recording's sensor layout, are read by the caller: :mod:`torchblur.identify.dm_outside`)."""
    where = root / YAML_NAME
    if not where.is_file():
        raise RecordingError(f"{where}: missing; it must give at least gain_e_per_adu (docs/outside_recordings.md)")
    inside(root, YAML_NAME, YAML_NAME)
    try:
        cam = load_dataclass(OutsideCamera, str(where), ignore_file_sections=sections, trusted=False)
    except ConfigError as exc:
        msg = str(exc)
        if "is not in struct" in msg:  # OmegaConf's words for a key the dataclass does not have
            known = ", ".join([f.name for f in fields(OutsideCamera)] + list(sections))
            msg = f"{msg.partition(':')[0]}: unknown key (known: {known})"
        raise RecordingError(f"{YAML_NAME}: {msg}") from None
    if cam.gain_e_per_adu is None:
        raise RecordingError(f"{YAML_NAME}: gain_e_per_adu (electrons per ADU) is required")
    try:
        check_declared(cam, "")
    except ConfigError as exc:
        raise RecordingError(f"{YAML_NAME}: {exc}") from None
    if not isinstance(cam.input_unit, str) or len(cam.input_unit) > 40:
        raise RecordingError(f"{YAML_NAME}: input_unit: expected a string of at most 40 characters, got {excerpt(cam.input_unit)}")
    return cam


def read_csv(root: Path, name: str, max_bytes: int, check_header=None) -> tuple[list, list]:
    """The CSV file ``name`` in folder ``root``, read as untrusted input (at most ``max_bytes``,
    inside the folder, UTF-8): its header (stripped cells, passed to ``check_header`` before any
    row is read) and its non-blank rows as ``(line, stripped cells)``, at most :data:`MAX_ROWS`, each
    with the header's number of cells. RecordingError naming the file and the line."""
    data = read_bounded(name, max_bytes, name, root=root)  # inside the folder: no symlink out
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise RecordingError(f"{name}: not UTF-8 text (byte {exc.start})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise RecordingError(f"{name}: empty") from None
    except csv.Error as exc:
        raise RecordingError(f"{name} line 1: {exc}") from None
    if check_header is not None:
        check_header(header)
    rows = []
    try:
        for cells in reader:
            line = reader.line_num
            if not any(c.strip() for c in cells):
                continue
            if len(rows) >= MAX_ROWS:
                raise RecordingError(f"{name}: more than {MAX_ROWS} rows; refused")
            if len(cells) != len(header):
                raise RecordingError(f"{name} line {line}: {len(cells)} cells, the header has {len(header)}")
            rows.append((line, [c.strip() for c in cells]))
    except csv.Error as exc:
        raise RecordingError(f"{name} line {reader.line_num}: {exc}") from None
    if not rows:
        raise RecordingError(f"{name}: no rows")
    return header, rows


def _read_rows(root: Path, extra: tuple = ()) -> list:
    """The rows of ``frames.csv``, each a dict of checked values with its ``line`` (``extra``: the
    columns a DM recording adds, ``pattern``)."""
    header, rows = read_csv(root, CSV_NAME, MAX_CSV_BYTES, partial(_check_header, extra=extra))
    return [_row(dict(zip(header, cells)), line) for line, cells in rows]


def _check_header(header: list, extra: tuple = ()) -> None:
    if "axis" in header:
        raise RecordingError(f"{CSV_NAME} line 1, column axis: two-input recordings are not supported (one input per recording)")
    for name in header:
        if name not in REQUIRED + OPTIONAL + tuple(extra):
            more = " (a pattern column: a deformable-mirror recording needs its patterns.csv)" if name == "pattern" else ""
            raise RecordingError(f"{CSV_NAME} line 1, column {excerpt(name)}: unknown column (known: "
                                 f"{', '.join(REQUIRED + OPTIONAL + tuple(extra))}){more}")
    if len(set(header)) != len(header):
        raise RecordingError(f"{CSV_NAME} line 1: a column is named twice ({header})")
    for name in REQUIRED:
        if name not in header:
            raise RecordingError(f"{CSV_NAME} line 1: column {excerpt(name)} is missing (required: {', '.join(REQUIRED)})")


def number(cell: str, line: int, col: str, *, low=None, high=None, positive=False, integer=False, name: str = CSV_NAME):
    """A cell of the CSV file ``name`` as a finite number (None where empty), range-checked, or an error naming it."""
    if cell is None or cell == "":
        return None
    where = f"{name} line {line}, column {col}"
    try:
        v = int(cell) if integer else float(cell)
    except ValueError:
        raise RecordingError(f"{where}: expected {'an integer' if integer else 'a number'}, got {excerpt(cell[:40])}") from None
    if not math.isfinite(v):
        raise RecordingError(f"{where}: expected a finite number, got {excerpt(cell[:40])}")
    if (positive and v <= 0) or (low is not None and v < low) or (high is not None and v > high):
        lim = "> 0" if positive else f">= {low}"
        raise RecordingError(f"{where}: expected a value {lim}{f' and <= {high}' if high is not None else ''}, got {excerpt(cell[:40])}")
    return v


def _row(cells: dict, line: int) -> dict:
    """One CSV row checked: what every kind needs, what a sweep row needs."""
    kind = cells["kind"].lower()
    kinds = DM_KINDS if "level" in cells else KINDS
    if kind not in kinds:
        raise RecordingError(f"{CSV_NAME} line {line}, column kind: expected one of {kinds}, got {excerpt(cells['kind'][:40])}")
    if not cells["file"]:
        raise RecordingError(f"{CSV_NAME} line {line}, column file: empty")
    n = lambda col, **kw: number(cells.get(col), line, col, **kw)  # noqa: E731
    row = dict(line=line, kind=kind, file=cells["file"], page=n("page", low=0, integer=True) or 0,
               exposure_s=n("exposure_s", positive=True, high=MAX_EXPOSURE_S), freq_hz=n("freq_hz", positive=True, high=MAX_FREQ_HZ),
               amplitude=n("amplitude", positive=True, high=MAX_AMPLITUDE), power=n("power", positive=True, high=1e12),
               window_start_s=n("window_start_s", low=-MAX_EXPOSURE_S, high=MAX_EXPOSURE_S),
               trigger_phase_rad=n("trigger_phase_rad", low=-100.0, high=100.0), repeat=n("repeat", low=0, integer=True),
               pattern=n("pattern", low=0, high=MAX_ROWS, integer=True), level=n("level", low=-MAX_AMPLITUDE, high=MAX_AMPLITUDE))
    if kind == "ladder":
        for col in ("pattern", "level", "exposure_s"):
            if row[col] is None:
                raise RecordingError(f"{CSV_NAME} line {line}, column {col}: required for a ladder frame (a pattern held still)")
    if kind == "sweep":
        for col in ("freq_hz", "exposure_s", "amplitude"):
            if row[col] is None:
                raise RecordingError(f"{CSV_NAME} line {line}, column {col}: required for a sweep frame")
        if whole_periods(row["exposure_s"] * row["freq_hz"]):
            raise RecordingError(f"{CSV_NAME} line {line}, column exposure_s: {row['exposure_s']:g} s is a whole number of periods of "
                                 f"{row['freq_hz']:g} Hz: such a frame does not depend on the phase; refused")
        if (row["window_start_s"] is None) == (row["trigger_phase_rad"] is None):
            raise RecordingError(f"{CSV_NAME} line {line}, columns window_start_s / trigger_phase_rad: a sweep frame needs exactly one "
                                 f"of them")
    return row


def _grayscale_frames(name: str, budget: int, series) -> None:
    """Refuse (RecordingError, naming the file ``name``) a TIFF series that is not grayscale
    frames ``[N, H, W]`` or ``[H, W]``, or that holds more than ``budget`` pixels (what is left
    of :data:`MAX_PIXELS`), from its header, before decoding."""
    s = tuple(series.shape)
    if math.prod(s) > budget:
        raise RecordingError(f"{name}: declares {s} pixels; the recording would hold more than {MAX_PIXELS} pixels; refused "
                             f"before decoding")
    if series.axes.endswith("S"):
        raise RecordingError(f"{name}: colour frames ({series.axes} {s}); expected grayscale frames "
                             f"[N, H, W] or [H, W]")
    if len(s) < 2 or max(s[-2:]) > MAX_FRAME_SIDE or min(s[-2:]) < 1:
        raise RecordingError(f"{name}: holds an array of shape {s}; expected frames [N, H, W] or [H, W]")


#: frames decoded at a time while a recording is checked (the check holds no more than these)
CHECK_BLOCK = 256


class FrameStore:
    """The frames ``frames.csv`` lists, read from their TIFF files when asked, in the files' dtype:
    a recording is never held whole (:func:`_read_frames` checked every frame once and kept its
    digest; :meth:`load` reads them again and refuses one whose pixels changed since).

    Attributes:
        root: the recording's folder; frame_shape: ``(H, W)``; dtype: the files' pixel dtype.
        where: ``{line: (file, page)}``; digests: ``{line: bytes}``.
    """

    def __init__(self, root: Path, where: dict, digests: dict, frame_shape: tuple, dtype):
        self.root, self.where, self.digests = root, where, digests
        self.frame_shape, self.dtype = tuple(frame_shape), np.dtype(dtype).newbyteorder("=")

    def load(self, lines) -> np.ndarray:
        """The frames of ``frames.csv``'s ``lines`` (``[n]``), ``[n, H, W]`` in the files' dtype.

        Raises:
            RecordingError: a file unreadable now, or a frame whose pixels are not those checked when the recording was read.
        """
        lines = [int(v) for v in np.asarray(lines).reshape(-1)]
        out = np.empty((len(lines),) + self.frame_shape, dtype=self.dtype)
        by_file: dict = {}
        for i, ln in enumerate(lines):
            name, page = self.where[ln]
            by_file.setdefault(name, []).append((page, i, ln))
        for name, items in by_file.items():
            with _tiff_series(self.root, name, name) as (tf, series, _):
                frames = _pages(tf, [pg for pg, _, _ in items], name, self.frame_shape)
            for frame, (page, i, ln) in zip(frames, items):
                if _digest(frame) != self.digests[ln]:
                    raise RecordingError(f"{name} page {page} ({CSV_NAME} line {ln}): its pixels changed after the recording was read; "
                                         f"refused")
                out[i] = frame
        return out


def _digest(frame: np.ndarray) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(frame).tobytes(), digest_size=16).digest()


@contextlib.contextmanager
def _tiff_series(root: Path, rel: str, where: str):
    """``(TiffFile, its first series, the file's size)`` of the TIFF ``rel`` inside ``root``, opened under the
    one opening rule (:func:`~torchblur.files.open_regular`) and its header checked
    (:func:`~torchblur.hardware.recording.tiff_header_limits`) before any pixel is decoded."""
    import tifffile

    path = inside(root, rel, where)
    if not path.is_file():
        raise RecordingError(f"{where}: {excerpt(rel)} is not a file in {root}")
    fd, size = open_regular(path, rel, error=RecordingError)
    if size > MAX_TIFF_BYTES:
        os.close(fd)
        raise RecordingError(f"{rel}: {size} bytes, larger than the {MAX_TIFF_BYTES} bytes it may hold; refused")
    with os.fdopen(fd, "rb") as fh:
        try:
            tf = tifffile.TiffFile(fh, name=posixpath.basename(rel))
            series = tf.series[0]
            tiff_header_limits(tf, series, size, rel)
        except RecordingError:
            raise
        except Exception as exc:  # noqa: BLE001 - a third-party decoder on untrusted bytes: any failure is a bad file
            raise _unreadable(rel, exc) from None
        with tf:
            yield tf, series, size


def _unreadable(name: str, exc: Exception) -> RecordingError:
    return RecordingError(f"{name}: not a readable TIFF ({type(exc).__name__}: {excerpt(str(exc), 100)})")


def _pages(tf, pages: list, name: str, frame_shape: tuple) -> np.ndarray:
    """Pages ``pages`` of the first series of ``tf`` (one frame each) as ``[n, H, W]``; RecordingError naming ``name``."""
    try:
        return np.asarray(tf.asarray(key=list(pages), series=0)).reshape((len(pages),) + tuple(frame_shape))
    except Exception as exc:  # noqa: BLE001 - a decoder on untrusted bytes
        raise _unreadable(name, exc) from None


def _read_frames(root: Path, rows: list) -> FrameStore:
    """Check every row's frame (its file inside the folder, one frame per page, one shape and dtype
    for all, the page there, finite, no frame a copy of another) and return the :class:`FrameStore`
    that reads them again when asked. The files are decoded :data:`CHECK_BLOCK` pages at a time."""
    seen, files, where, shape, dtype, total = {}, {}, {}, None, None, 0
    for r in rows:
        loc = f"{CSV_NAME} line {r['line']}, column file"
        first = seen.setdefault((posixpath.normpath(r["file"]), r["page"]), r["line"])
        if first != r["line"]:  # one frame counted twice would make its point's stds too small
            raise RecordingError(f"{CSV_NAME} line {r['line']}, columns file / page: {r['file']} page {r['page']} is already line {first}; "
                                 f"each frame may be listed once")
        if r["file"] not in files:
            with _tiff_series(root, r["file"], loc) as (tf, series, _):
                _grayscale_frames(r["file"], MAX_PIXELS - total, series)
                s, dt = tuple(int(v) for v in series.shape), np.dtype(series.dtype)
                if dt.kind not in "uif":
                    raise RecordingError(f"{r['file']}: pixels of dtype {dt}; expected integers or floats")
                if math.prod(s) != len(series.pages) * s[-2] * s[-1]:
                    raise RecordingError(f"{r['file']}: holds {s} pixels in {len(series.pages)} page(s); expected one frame per page")
                if shape is not None and (s[-2:] != shape or dt != dtype):
                    raise RecordingError(f"{loc}: {r['file']} holds {s[-2]}x{s[-1]} {dt} frames, the recording's first file "
                                         f"{shape[0]}x{shape[1]} {dtype}; every frame must have one shape and dtype")
                shape, dtype, total = s[-2:], dt, total + math.prod(s)
                files[r["file"]] = [len(series.pages), []]
        n, mine = files[r["file"]]
        if r["page"] >= n:
            raise RecordingError(f"{CSV_NAME} line {r['line']}, column page: page {r['page']} of {r['file']}, which holds "
                                 f"{n} frame(s) (pages count from 0)")
        mine.append(r)
        where[r["line"]] = (r["file"], r["page"])
    return FrameStore(root, where, _check_pixels(root, files, shape), shape, dtype)


def _check_pixels(root: Path, files: dict, shape: tuple) -> dict:
    """Decode every listed frame once (:data:`CHECK_BLOCK` at a time): finite, no copy of another; ``{line: digest}``."""
    digests, seen_px = {}, {}
    for name, (_, mine) in files.items():
        with _tiff_series(root, name, name) as (tf, _, _):
            for b in range(0, len(mine), CHECK_BLOCK):
                block = mine[b:b + CHECK_BLOCK]
                frames = _pages(tf, [r["page"] for r in block], name, shape)
                for frame, r in zip(frames, block):
                    label = f"{name} page {r['page']} ({CSV_NAME} line {r['line']})"
                    if frame.dtype.kind == "f" and not np.isfinite(frame).all():
                        raise RecordingError(f"{label}: NaN or infinite pixels; refused")
                    check_distinct_frames(frame[None], [label], seen_px)
                    digests[r["line"]] = _digest(frame)
    return digests


def _resolved_saturation(camera: OutsideCamera, dtype: np.dtype) -> OutsideCamera:
    """The camera with ``saturation_adu`` set: as given, else the integer dtype's maximum
    (float frames: None, no pixel is masked)."""
    if camera.saturation_adu is not None or np.dtype(dtype).kind == "f":
        return camera
    return replace(camera, saturation_adu=float(np.iinfo(dtype).max))


def _window_start(row: dict, camera: OutsideCamera) -> float:
    """A sweep frame's start (s after the command's upward zero crossing): ``window_start_s``,
    or the trigger at ``trigger_phase_rad`` of the command plus the delays."""
    if row["window_start_s"] is not None:
        return float(row["window_start_s"])
    return float(row["trigger_phase_rad"]) / (2 * math.pi * row["freq_hz"]) + camera.trigger_delay_s + camera.latency_s


def _points(rows: list, frames: FrameStore | None, camera: OutsideCamera, by_exposure: bool = False) -> tuple:
    """The sweep rows as :class:`OutsidePoint` (one per frequency): one amplitude and power
    per point, each window repeated ``R`` times, and one ``E`` and ``R`` for every point; their
    frames read from ``frames`` as float64 (None: ``frames`` None, the caller reads them by ``lines``).
    A window is a (start, exposure_s) pair; ``by_exposure`` (a DM recording's: its exposures start at one
    trigger) an exposure_s, each frame keeping its own start (a jittered repeat's differs), its repeats
    numbered 0..R-1 where the ``repeat`` column gives them."""
    groups: dict = {}
    for r in rows:
        groups.setdefault(r["freq_hz"], []).append(r)
    points = []
    for f in sorted(groups):
        g = groups[f]
        for col in ("amplitude", "power"):
            vals = {r[col] for r in g}
            if len(vals) > 1:
                bad = next(r for r in g if r[col] != g[0][col])
                raise RecordingError(f"{CSV_NAME} line {bad['line']}, column {col}: {bad[col]}, the point at {f:g} Hz (line "
                                     f"{g[0]['line']}) has {g[0][col]}; one {col} per frequency")
        windows: dict = {}
        for r in g:
            windows.setdefault(r["exposure_s"] if by_exposure else (round(_window_start(r, camera), 15), r["exposure_s"]), []).append(r)
        reps = {len(v) for v in windows.values()}
        if len(reps) != 1:
            raise RecordingError(f"{CSV_NAME} lines {g[0]['line']}..{g[-1]['line']}: the point at {f:g} Hz has "
                                 f"{sorted(len(v) for v in windows.values())} frames per exposure window; every window needs the "
                                 f"same number of repeats")
        for v in windows.values():
            tags = [r["repeat"] for r in v if r["repeat"] is not None]
            if len(set(tags)) != len(tags):
                raise RecordingError(f"{CSV_NAME} line {v[-1]['line']}, column repeat: repeat {tags[-1]} is given twice for one window "
                                     f"at {f:g} Hz")
            if by_exposure and tags and max(tags) >= len(v):
                bad = max(v, key=lambda r: r["repeat"] or 0)
                raise RecordingError(f"{CSV_NAME} line {bad['line']}, column repeat: {bad['repeat']}, but the {bad['exposure_s']:g} s "
                                     f"exposure at {f:g} Hz has {len(v)} frame(s) here: number its repeats 0..{len(v) - 1}")
        ordered = [r for v in windows.values() for r in v]  # exposure-major
        points.append(OutsidePoint(
            freq_hz=float(f), amplitude=float(g[0]["amplitude"]), power=float(g[0]["power"] if g[0]["power"] is not None else 1.0),
            frames=None if frames is None else frames.load([r["line"] for r in ordered]).astype(np.float64),
            start_s=np.array([_window_start(r, camera) for r in ordered]), duration_s=np.array([r["exposure_s"] for r in ordered]),
            R=reps.pop(), lines=tuple(r["line"] for r in ordered)))
    shapes = {(p.E, p.R) for p in points}
    if len(shapes) > 1:
        p = next(p for p in points if (p.E, p.R) != (points[0].E, points[0].R))
        raise RecordingError(f"{CSV_NAME} line {p.lines[0]}: the point at {p.freq_hz:g} Hz has {p.E} exposure(s) x {p.R} repeat(s), "
                             f"the one at {points[0].freq_hz:g} Hz {points[0].E} x {points[0].R}; every point needs the same")
    return tuple(points)
