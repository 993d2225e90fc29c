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

import csv
import io
import math
import posixpath
from dataclasses import dataclass, fields, replace
from functools import partial
from pathlib import Path
from typing import Optional

import numpy as np

from torchblur.errors import ConfigError
from torchblur.files import excerpt
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.manifest import MAX_FRAME_SIDE, MAX_AMPLITUDE, read_bounded
from torchblur.hardware.recording import check_distinct_frames, decode_tiff
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
    the still frames), ``frames`` ``[E*R, H, W]`` (ADU, float64, exposure-major),
    ``start_s`` and ``duration_s`` ``[E*R]`` (the window of each frame, s after the command's
    upward zero crossing), ``R`` (images per exposure) and ``lines`` (their CSV lines)."""

    freq_hz: float
    amplitude: float
    power: float
    frames: np.ndarray
    start_s: np.ndarray
    duration_s: np.ndarray
    R: int
    lines: tuple

    @property
    def E(self) -> int:
        return self.frames.shape[0] // self.R


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
    DM recording adds) and their frames. Returns ``(the fields of OutsideFrames, rows by kind, frames by line)``."""
    camera = _read_camera(root, sections)
    rows = _read_rows(root, extra)
    frames, dtype = _read_frames(root, rows)
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
    take = lambda kind: np.stack([frames[r["line"]] for r in by_kind[kind]])  # noqa: E731
    return (dict(path=root, camera=camera, dark=take("dark"), still=take("still"), still_exposure_s=te.pop(),
                 frame_shape=tuple(frames[rows[0]["line"]].shape), n_frames=len(rows), saturation_source=source), by_kind, frames)


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


def _read_frames(root: Path, rows: list) -> tuple[dict, np.dtype]:
    """``{line: frame [H, W] float64}`` of every row, from the TIFF files it names (each read
    once), and the files' dtype. All frames must share one shape and one dtype."""

    stacks, out, seen, seen_px = {}, {}, {}, {}
    shape = dtype = None
    for r in rows:
        where = f"{CSV_NAME} line {r['line']}, column file"
        first = seen.setdefault((posixpath.normpath(r["file"]), r["page"]), r["line"])
        if first != r["line"]:  # one frame counted twice would make its point's stds too small
            raise RecordingError(f"{CSV_NAME} line {r['line']}, columns file / page: {r['file']} page {r['page']} is already line {first}; "
                                 f"each frame may be listed once")
        if r["file"] not in stacks:
            path = inside(root, r["file"], where)
            if not path.is_file():
                raise RecordingError(f"{where}: {excerpt(r['file'])} is not a file in {root}")
            data = read_bounded(path, MAX_TIFF_BYTES, r["file"])
            budget = MAX_PIXELS - sum(a.size for a in stacks.values())
            arr = decode_tiff(data, r["file"], partial(_grayscale_frames, r["file"], budget))
            arr = arr.reshape((-1,) + arr.shape[-2:])
            if arr.dtype.kind not in "uif":
                raise RecordingError(f"{r['file']}: pixels of dtype {arr.dtype}; expected integers or floats")
            if shape is not None and (arr.shape[1:] != shape or arr.dtype != dtype):
                raise RecordingError(f"{where}: {r['file']} holds {arr.shape[1]}x{arr.shape[2]} {arr.dtype} frames, the recording's first "
                                     f"file {shape[0]}x{shape[1]} {dtype}; every frame must have one shape and dtype")
            shape, dtype = arr.shape[1:], arr.dtype
            stacks[r["file"]] = arr
            if sum(a.size for a in stacks.values()) > MAX_PIXELS:
                raise RecordingError(f"{r['file']}: the recording holds more than {MAX_PIXELS} pixels; refused")
        arr = stacks[r["file"]]
        if r["page"] >= arr.shape[0]:
            raise RecordingError(f"{CSV_NAME} line {r['line']}, column page: page {r['page']} of {r['file']}, which holds "
                                 f"{arr.shape[0]} frame(s) (pages count from 0)")
        frame = arr[r["page"]].astype(np.float64)
        if not np.isfinite(frame).all():
            raise RecordingError(f"{r['file']} page {r['page']} ({CSV_NAME} line {r['line']}): NaN or infinite pixels; refused")
        out[r["line"]] = frame
        check_distinct_frames(arr[r["page"]][None], [f"{r['file']} page {r['page']} ({CSV_NAME} line {r['line']})"], seen_px)
    return out, dtype


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


def _points(rows: list, frames: dict, camera: OutsideCamera) -> tuple:
    """The sweep rows as :class:`OutsidePoint` (one per frequency): one amplitude and power
    per point, each window repeated ``R`` times, and one ``E`` and ``R`` for every point."""
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
            windows.setdefault((round(_window_start(r, camera), 15), r["exposure_s"]), []).append(r)
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
        ordered = [r for v in windows.values() for r in v]  # exposure-major
        points.append(OutsidePoint(
            freq_hz=float(f), amplitude=float(g[0]["amplitude"]), power=float(g[0]["power"] if g[0]["power"] is not None else 1.0),
            frames=np.stack([frames[r["line"]] for r in ordered]),
            start_s=np.array([_window_start(r, camera) for r in ordered]), duration_s=np.array([r["exposure_s"] for r in ordered]),
            R=reps.pop(), lines=tuple(r["line"] for r in ordered)))
    shapes = {(p.E, p.R) for p in points}
    if len(shapes) > 1:
        p = next(p for p in points if (p.E, p.R) != (points[0].E, points[0].R))
        raise RecordingError(f"{CSV_NAME} line {p.lines[0]}: the point at {p.freq_hz:g} Hz has {p.E} exposure(s) x {p.R} repeat(s), "
                             f"the one at {points[0].freq_hz:g} Hz {points[0].E} x {points[0].R}; every point needs the same")
    return tuple(points)
