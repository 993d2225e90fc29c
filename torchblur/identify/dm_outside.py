"""Outside DM recordings: frames a lab took of its deformable mirror with its own software, in
a folder that ``torchblur fit FOLDER`` identifies like a live DM run. The format (the one-spot
outside format of :mod:`torchblur.hardware.outside` plus ``patterns.csv``, a ``pattern`` column,
optional ``ladder`` rows and the ``dm``, ``wfs``, ``dm_plan`` sections of ``recording.yaml``):
docs/outside_recordings.md, "Deformable-mirror recordings".

:func:`read_dm_recording` reads and checks a folder into a :class:`DMRecording`;
:func:`dm_recording_config` makes the run's config of it; :func:`identify_dm_recording` runs a
live DM run's stages on it (:func:`torchblur.identify.pipeline.identify` with the plan
:class:`DMOutsidePlan`); :func:`write_dm_recording` writes the format from arrays and
:func:`export_dm_recording` from a torchblur DM run's own recording (``OUT/experiment``).
"""
from __future__ import annotations

import csv
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from torchblur.config import WFSConfig, load_config, load_dataclass
from torchblur.config.checks import check_declared
from torchblur.config.schema import key
from torchblur.config.budget import dm_geometry, dm_sensor
from torchblur.dm.plans import Plan, driven_spots, one_at_a_time_plan, plan_cost
from torchblur.dm.shack_hartmann import ShackHartmann
from torchblur.errors import ConfigError, InputTypeError, check_type
from torchblur.files import excerpt
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.frames import whole_adu
from torchblur.hardware.outside import CSV_NAME, YAML_NAME, FrameStore, OutsideCamera, OutsideFrames, _points, number, read_csv, read_folder
from torchblur.hardware.recording import Experiment, ReplayRig
from torchblur.identify.calibration import Calibration, spots_from_still, still_rate
from torchblur.identify.dm_ladder import TEST_KEY, hold_images, pattern_ladder, slope_noise
from torchblur.identify.dm_plan import (AMPLITUDE_LAG, DMPlan, DMResult, _calibrate, _fit_frequency, _fit_options, check_dm_config,
                                        collect_fits, fit_pool, sensor_config, sensor_spots)
from torchblur.identify.dm_record import PLAN_KEY, SWEEP_KIND, plan_support
from torchblur.identify.outside import check_no_rig, check_overrides, outside_record, recording_levels
from torchblur.identify.pipeline import identify
from torchblur.identify.record import LOGGER
from torchblur.image.saturation import SaturationCurve
from torchblur.render.window import ExposureWindow

__all__ = ["PATTERNS_NAME", "DMOutsidePlan", "DMRecording", "dm_recording_config", "export_dm_recording", "identify_dm_recording",
           "is_dm_recording", "read_dm_recording", "recording_calibration", "RecordedFrames", "write_dm_recording"]

PATTERNS_NAME = "patterns.csv"
MAX_PATTERNS_BYTES = 64 * 1024 * 1024
MAX_ACTUATORS = 20000  # patterns.csv's columns: beyond any deformable mirror made
_F64 = torch.float64
_PLAN_KINDS = ("hadamard", "sparse", "one_at_a_time")


@dataclass(frozen=True)
class _DMGeometry:
    """``recording.yaml``'s ``dm`` section: the actuator grid and its influence (the dynamics are what is measured)."""

    n_across: int = key(0, integer=True)
    coupling: float = key(0.15, positive=True, high=0.99)


@dataclass(frozen=True)
class _PlanInfo:
    """``recording.yaml``'s ``dm_plan`` section."""

    kind: str = key("hadamard", choice=_PLAN_KINDS)
    support_threshold: float = key(0.01, nonnegative=True, high=1.0)
    #: the fitted geometry's support check (``dm_plan.support_threshold`` of the fit; None: ``support_threshold``): a
    #: plan chosen at a smaller threshold than it is checked at (a sparse plan for the ladder, ``SPARSE_MARGIN``) keeps both
    check_threshold: float | None = key(None, nonnegative=True, high=1.0, optional=True)


@dataclass(frozen=True)
class _Layout:
    """``recording.yaml``'s sensor layout (the camera keys are :class:`~torchblur.hardware.outside.OutsideCamera`'s)."""

    dm: _DMGeometry = field(default_factory=_DMGeometry)
    wfs: WFSConfig = field(default_factory=WFSConfig)
    dm_plan: _PlanInfo = field(default_factory=_PlanInfo)


_SECTIONS = tuple(f.name for f in fields(_Layout))


@dataclass(frozen=True)
class DMRecording(OutsideFrames):
    """A checked outside DM recording: :class:`~torchblur.hardware.outside.OutsideFrames` and

    Attributes:
        layout: the sensor layout (``dm``, ``wfs``, ``dm_plan`` sections of ``recording.yaml``).
        patterns: ``[P, N]`` (``patterns.csv``).
        freq_hz, amplitude, power: ``[F]``, increasing frequency.
        frames: ``[F]`` arrays ``[P, E*R, H, W]`` ADU (exposure-major: the R repeats of an exposure in a row), a
            :class:`RecordedFrames`: each frequency's read from the TIFF files when indexed, in the camera's dtype.
        start_s, duration_s: ``[F, P, E*R]``: each frame's window (s after the sine's upward zero crossing).
        R: frames per exposure window.
        ladder_levels: ``[P, K]`` each pattern's held levels (input units, increasing; rows of kind
            ``ladder``), or None (no ladder: the shifted still); ladder_frames: ``[P]`` arrays
            ``[K, n, H, W]`` ADU (a :class:`RecordedFrames`: each pattern's read when indexed); ladder_exposure_s, ladder_power: theirs.
    """

    layout: _Layout
    patterns: np.ndarray
    freq_hz: np.ndarray
    amplitude: np.ndarray
    power: np.ndarray
    frames: "RecordedFrames"
    start_s: np.ndarray
    duration_s: np.ndarray
    R: int
    ladder_levels: np.ndarray | None = None
    ladder_frames: "RecordedFrames | None" = None
    ladder_exposure_s: float | None = None
    ladder_power: float = 1.0


class RecordedFrames(Sequence):
    """Frames of a checked recording, read group by group as they are used: item ``i`` is
    ``store.load(lines[i])`` as ``[*lines.shape[1:], H, W]`` in the camera's dtype (``lines``: an int
    array of ``frames.csv`` lines, the group first), so a run holds one group (a frequency, a held
    pattern) at a time, never the recording."""

    def __init__(self, store: FrameStore, lines: np.ndarray):
        self.store, self.lines = store, np.asarray(lines, dtype=np.int64)

    def __len__(self) -> int:
        return self.lines.shape[0]

    @property
    def item_shape(self) -> tuple:
        """One item's shape, without reading it."""
        return tuple(self.lines.shape[1:]) + tuple(self.store.frame_shape)

    def __getitem__(self, i):
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        return self.store.load(self.lines[i]).reshape(self.item_shape)


def is_dm_recording(path) -> bool:
    """Whether ``path`` is a folder with a ``frames.csv`` and a ``patterns.csv`` (an outside DM recording)."""
    return (Path(path) / CSV_NAME).is_file() and (Path(path) / PATTERNS_NAME).is_file()


# ---------------------------------------------------------------------- reading


def _read_layout(root: Path) -> _Layout:
    """``recording.yaml``'s ``dm``, ``wfs`` and ``dm_plan`` sections, every value checked as the
    config's keys are (:func:`~torchblur.config.checks.check_declared`)."""
    camera_keys = tuple(f.name for f in fields(OutsideCamera))
    try:
        lay = load_dataclass(_Layout, str(root / YAML_NAME), ignore_file_sections=camera_keys, trusted=False)
        for sec in _SECTIONS:
            check_declared(getattr(lay, sec), sec)
    except ConfigError as exc:
        raise RecordingError(f"{YAML_NAME}: {exc}") from None
    if int(lay.dm.n_across) < 1:
        raise RecordingError(f"{YAML_NAME}: dm.n_across: the mirror's actuators across (the sensor layout) is required, got "
                             f"{excerpt(lay.dm.n_across)}")
    return lay


def _read_patterns(root: Path) -> np.ndarray:
    """``patterns.csv`` as ``[P, N]``: a header ``pattern,a0,...,a{N-1}``, rows 0..P-1 in order
    (read as ``frames.csv`` is: :func:`~torchblur.hardware.outside.read_csv`)."""
    def check(head):
        if len(head) - 1 > MAX_ACTUATORS:
            raise RecordingError(f"{PATTERNS_NAME} line 1: {len(head) - 1} actuator columns, more than {MAX_ACTUATORS}; refused")
        if head != ["pattern"] + [f"a{j}" for j in range(len(head) - 1)] or len(head) < 2:
            raise RecordingError(f"{PATTERNS_NAME} line 1: expected the header pattern,a0,a1,...; got {excerpt(','.join(head))}")

    head, rows = read_csv(root, PATTERNS_NAME, MAX_PATTERNS_BYTES, check)
    out = np.zeros((len(rows), len(head) - 1))
    for p, (line, cells) in enumerate(rows):
        for j, (col, cell) in enumerate(zip(head, cells)):
            v = number(cell, line, col, integer=col == "pattern", low=-1e3, high=1e3 if col != "pattern" else None, name=PATTERNS_NAME)
            if v is None:
                raise RecordingError(f"{PATTERNS_NAME} line {line}, column {col}: expected a number, got an empty cell")
            if col == "pattern" and v != p:
                raise RecordingError(f"{PATTERNS_NAME} line {line}, column pattern: expected {p} (the patterns in order from 0), got {v}")
            if col != "pattern":
                out[p, j - 1] = v
    return out


def _sweep(rows: list, frames: FrameStore, camera: OutsideCamera, P: int):
    """The sweep rows as ``(freq [F], amplitude [F], power [F], frames (F x [P, E*R, H, W], read when indexed), start [F, P, E*R],
    duration [F, P, E*R], R)``: every pattern at every frequency, one amplitude and power per frequency; the R repeats of an
    exposure are its frames of one pattern and frequency (their starts differ by the jitter), numbered 0..R-1 by ``repeat`` if given."""
    for r in rows:
        if r["pattern"] is None or r["pattern"] >= P:
            raise RecordingError(f"{CSV_NAME} line {r['line']}, column pattern: a sweep frame needs the row of {PATTERNS_NAME} it was "
                                 f"driven with (0..{P - 1}), got {r['pattern']}")
    given = [r for r in rows if r["repeat"] is not None]
    if given and len(given) != len(rows):
        bad = next(r for r in rows if r["repeat"] is None)
        raise RecordingError(f"{CSV_NAME} line {bad['line']}, column repeat: empty, given on line {given[0]['line']}; number the "
                             f"repeats of every sweep frame (0..R-1 for each pattern, frequency and exposure) or of none")
    per = [_points(mine, None, camera, by_exposure=True) if (mine := [r for r in rows if r["pattern"] == p]) else () for p in range(P)]
    ref = per[0]
    for p, pts in enumerate(per):
        if len(pts) != len(ref) or not pts:
            raise RecordingError(f"{CSV_NAME}: pattern {p} of {PATTERNS_NAME} has sweep frames at {len(pts)} frequencies, pattern 0 at "
                                 f"{len(ref)}; every pattern at every frequency")
        for a, b in zip(pts, ref):
            for col in ("freq_hz", "amplitude", "power", "E", "R"):
                if getattr(a, col) != getattr(b, col):
                    raise RecordingError(f"{CSV_NAME} line {a.lines[0]}, column {col}: pattern {p} at {a.freq_hz:g} Hz has "
                                         f"{getattr(a, col):g}, pattern 0 at {b.freq_hz:g} Hz {getattr(b, col):g}; every pattern needs "
                                         f"the same frequencies, amplitude, power, exposures and repeats")
    F = len(ref)
    stack = RecordedFrames(frames, [[per[p][k].lines for p in range(P)] for k in range(F)])
    start = np.array([[per[p][k].start_s for p in range(P)] for k in range(F)])
    dur = np.array([[per[p][k].duration_s for p in range(P)] for k in range(F)])
    return (np.array([q.freq_hz for q in ref]), np.array([q.amplitude for q in ref]), np.array([q.power for q in ref]), stack, start,
            dur, ref[0].R)


def read_dm_recording(path) -> DMRecording:
    """Read and check the outside DM recording in folder ``path`` (module docstring; untrusted:
    sizes bounded before reading, every cell checked).

    Raises:
        RecordingError: naming the file, line and column of the first problem.
    """
    root = Path(path)
    if not root.is_dir() or not is_dm_recording(root):
        raise RecordingError(f"{root}: not an outside DM recording (a folder with {CSV_NAME} and {PATTERNS_NAME}: "
                             f"docs/outside_recordings.md)")
    if not (root / YAML_NAME).is_file():
        raise RecordingError(f"{root / YAML_NAME}: missing; it gives the camera's gain and the sensor layout (dm, wfs, dm_plan)")
    common, by_kind, frames = read_folder(root, _SECTIONS, ("pattern", "level"))
    layout = _read_layout(root)
    patterns = _read_patterns(root)
    freq, amp, power, stack, start, dur, R = _sweep(by_kind["sweep"], frames, common["camera"], patterns.shape[0])
    return DMRecording(layout=layout, patterns=patterns, freq_hz=freq, amplitude=amp, power=power, frames=stack, start_s=start,
                       duration_s=dur, R=R, **common, **_ladder(by_kind["ladder"], frames, patterns.shape[0]))


def _ladder(rows: list, frames: FrameStore, P: int) -> dict:
    """The ``ladder`` rows as DMRecording's ``ladder_*`` fields (none: {}); RecordingError naming
    the line and column of a ladder that is not every pattern at the same K >= 4 levels, n frames
    each, one exposure and power."""
    if not rows:
        return {}
    where = lambda r, col: f"{CSV_NAME} line {r['line']}, column {col}"  # noqa: E731
    for col in ("exposure_s", "power"):
        first = rows[0][col]
        for r in rows:
            if r[col] != first:
                raise RecordingError(f"{where(r, col)}: every ladder frame needs the same {col} ({first}), got {r[col]}")
    bad = next((r for r in rows if r["pattern"] >= P), None)
    if bad is not None:
        raise RecordingError(f"{where(bad, 'pattern')}: expected a row of {PATTERNS_NAME} (0..{P - 1}), got {bad['pattern']}")
    per = []
    for p in range(P):
        mine = [r for r in rows if r["pattern"] == p]
        levels = sorted({r["level"] for r in mine})
        by_level = [[r for r in mine if r["level"] == u] for u in levels]
        ref = per[0][0] if per else None
        if len(levels) < 4 or (ref is not None and len(levels) != len(ref)):
            r = mine[0] if mine else rows[-1]
            first = f", pattern 0 at {len(ref)}" if ref is not None else ""
            raise RecordingError(f"{where(r, 'level')}: pattern {p} is held at {len(levels)} levels{first}; every pattern of "
                                 f"{PATTERNS_NAME} needs the same number, at least 4 (a cubic spline)")
        n = {len(b) for b in by_level}
        if len(n) != 1 or (per and n != {len(per[0][1][0])}):
            r = min(by_level, key=len)[0]
            raise RecordingError(f"{where(r, 'level')}: pattern {p} has {sorted(n)} frames per level; every level of every pattern "
                                 f"needs the same number")
        per.append((levels, [[r["line"] for r in b] for b in by_level]))
    return {"ladder_levels": np.array([lv for lv, _ in per]), "ladder_frames": RecordedFrames(frames, [ln for _, ln in per]),
            "ladder_exposure_s": float(rows[0]["exposure_s"]), "ladder_power": float(rows[0]["power"] or 1.0)}


# ---------------------------------------------------------------------- the run


def dm_recording_config(rec: DMRecording, overrides=()):
    """The DM config that fits ``rec``: the defaults with the ``fit.*`` / ``model.*`` /
    ``report.*`` ``overrides`` (and ``seed``, ``camera.gain_from``), the sensor layout, the
    camera's gain and timing from ``recording.yaml``, the frequencies and exposures from
    ``frames.csv``; checked against the frames (their shape is the sensor's, a pattern has one
    value per actuator).

    Raises:
        ConfigError: an override outside those (named); RecordingError: the layout does not fit the frames.
    """
    check_overrides(overrides, "a DM recording", f"mirror, sensor, camera and sweep are in {YAML_NAME}, {PATTERNS_NAME} and {CSV_NAME}")
    lay, c = rec.layout, rec.camera
    E = rec.start_s.shape[2] // rec.R
    own = [f"dm.{f.name}={getattr(lay.dm, f.name)!r}" for f in fields(lay.dm)]
    own += [f"wfs.{k}={v!r}" for k, v in asdict(lay.wfs).items()]
    check = lay.dm_plan.support_threshold if lay.dm_plan.check_threshold is None else lay.dm_plan.check_threshold
    own += [f"dm_plan.kind={lay.dm_plan.kind}", f"dm_plan.support_threshold={check!r}",
            "dm_plan.budget_frames=null", f"dm_plan.n_repeats={rec.R}",
            f"sweep.freq_hz=[{','.join(repr(float(f)) for f in rec.freq_hz)}]",
            f"sweep.exposures=[{','.join(repr(float(d * rec.freq_hz[0])) for d in rec.duration_s[0, 0, ::rec.R][:E])}]",
            f"camera.gain={float(c.gain_e_per_adu)!r}", f"camera.jitter_s={float(c.jitter_s)!r}",
            f"camera.trigger_delay_s={float(c.trigger_delay_s)!r}", f"camera.latency_s={float(c.latency_s)!r}",
            f"camera.latency_std_s={float(c.latency_std_s)!r}",
            "excitation.target_px=0.1"]  # no acquisition: the amplitudes are the recording's (the config's check wants one that fits)
    if rec.ladder_levels is None:
        own.append("dm_plan.spot_model=shifted")  # no held frames: the shifted still
    else:
        own += ["dm_plan.spot_model=ladder", f"dm_plan.ladder_levels={rec.ladder_levels.shape[1]}",
                f"dm_plan.ladder_frames={rec.ladder_frames.item_shape[1]}"]
    try:
        cfg = load_config(None, own + list(overrides), force=True)
    except ConfigError as exc:
        raise RecordingError(f"{YAML_NAME}: {exc}") from None
    cfg = replace(cfg, rig=replace(cfg.rig, kind="outside"))
    N, shape = dm_geometry(cfg).shape[1], dm_sensor(cfg)[1].frame_shape
    if rec.patterns.shape[1] != N:
        raise RecordingError(f"{PATTERNS_NAME} line 1: {rec.patterns.shape[1]} actuators (a0..), the mirror of {YAML_NAME} (dm.n_across "
                             f"{lay.dm.n_across}) has {N} inside the pupil")
    if tuple(shape) != tuple(rec.frame_shape):
        raise RecordingError(f"{YAML_NAME}: wfs: the sensor (n_across {lay.wfs.n_across} x pitch_px {lay.wfs.pitch_px:g}) has "
                             f"{shape[0]}x{shape[1]} px frames, the recording's are {rec.frame_shape[0]}x{rec.frame_shape[1]}")
    _plan(rec, cfg, dm_geometry(cfg))
    return cfg


def _plan(rec: DMRecording, cfg, G: np.ndarray) -> tuple[Plan, float]:
    """The recorded plan (``patterns.csv`` on the support of ``dm_plan.support_threshold``) and its cost relative to
    one actuator at a time; RecordingError where the patterns cannot be demultiplexed."""
    kind = rec.layout.dm_plan.kind
    plan = Plan(kind, rec.patterns, plan_support(kind, G, float(rec.layout.dm_plan.support_threshold)))
    ratio = plan_cost(plan, G) / plan_cost(one_at_a_time_plan(G), G)
    if not math.isfinite(ratio):
        raise RecordingError(f"{PATTERNS_NAME}: the {plan.n_patterns} patterns do not separate the actuators each slope sees (their "
                             f"matrix has too low a rank on the {kind} plan's support); D cannot be demultiplexed")
    return plan, ratio


def recording_calibration(rec: DMRecording, cfg, wfs: ShackHartmann):
    """The calibration of ``rec`` and its spots in valid-subaperture order, ``(cal, psf, offset,
    size)`` as the live run's (:func:`torchblur.identify.dm_plan._calibrate` then ``sensor_spots``, the same steps on the
    recorded frames): the dark frame, the gain (the still frames' photon transfer checked against
    ``gain_e_per_adu``, ``camera.gain_from``), the read noise, the spots cropped on the sensor's
    declared layout and each spot's PSF (``fit.psf``), both by the live calibration's own
    :func:`~torchblur.identify.calibration.spots_from_still` and
    :func:`~torchblur.identify.dm_plan.sensor_spots`, the latency given by ``recording.yaml``."""
    c = rec.camera
    levels, still_e = recording_levels(rec, cfg)
    sat, read_noise_e = levels["saturation"], levels["read_noise_e"]
    _refuse_saturated(rec, sat, levels["dark"])
    LOGGER.info(f"dark: level {float(sat.offset_adu):.2f} ADU, read noise {read_noise_e:.3g} e-; "
                f"saturation: {rec.saturation_source}")
    spots, kernels = spots_from_still(sensor_config(cfg), still_e, float(rec.still_exposure_s), read_noise_e,
                                      spot_layout=wfs.rest_px)
    cal = Calibration(psf=spots.psf, peak_rate=float(spots.psf.amplitude.max()), spots=spots, spot_kernels=kernels,
                      **levels)
    cal.still_rate, cal.still_rate_var = still_rate(still_e, float(rec.still_exposure_s), read_noise_e)
    LOGGER.info(f"latency: {c.latency_s * 1e6:.3f} +- {c.latency_std_s * 1e6:.3f} us given ({YAML_NAME})")
    return (cal, *sensor_spots(cal, wfs)[1:])


def _refuse_saturated(rec: DMRecording, sat: SaturationCurve, dark) -> None:
    """RecordingError naming the first still or sweep frame with a saturated pixel (within 1 % of the
    range below ``saturation_adu``, hot pixels aside): the DM spot fit does not leave such pixels
    out, so a saturated spot would give a wrong response with a std that does not show it."""
    hot = dark.hot_pixels
    n = int((~sat.mask(torch.as_tensor(rec.still, dtype=_F64)) & ~hot).sum())
    if n:
        raise RecordingError(f"{rec.path}: the still frames have {n} saturated pixel(s) (at or within 1 % below saturation_adu "
                             f"{float(sat.saturation_adu):.6g}); take them with a shorter exposure or less light")
    for k, fr in enumerate(rec.frames):
        bad = (~sat.mask(torch.as_tensor(fr, dtype=_F64)) & ~hot).flatten(2).any(-1)  # [P, E*R]
        if bool(bad.any()):
            p, j = (int(v) for v in torch.nonzero(bad)[0])
            raise RecordingError(f"{CSV_NAME}: the sweep frame of pattern {p} at {rec.freq_hz[k]:g} Hz (its frame {j} there) has "
                                 f"saturated pixels (at or within 1 % below saturation_adu {float(sat.saturation_adu):.6g}; "
                                 f"{int(bad.sum())} frame(s) at that frequency); the DM fit does not leave them out: record with "
                                 f"less light or a shorter exposure, or give saturation_adu in {YAML_NAME} if the sensor clips higher")


def identify_dm_recording(rec: DMRecording, cfg=None, *, progress: bool = True, executor=None) -> DMResult:
    """Identify the mirror of the outside DM recording ``rec`` with a live DM run's stages
    (:func:`torchblur.identify.pipeline.identify` with the plan :class:`DMOutsidePlan`). Returns a
    :class:`~torchblur.identify.dm_plan.DMResult` (no simulated truth; its ``log``: the run's messages).

    Args:
        rec: from :func:`read_dm_recording`; cfg: from :func:`dm_recording_config` (default: its defaults).
        progress, executor: as :func:`~torchblur.identify.pipeline.identify`'s.
    """
    check_type(rec, "rec", DMRecording, "a DMRecording (read_dm_recording)")
    cfg = dm_recording_config(rec) if cfg is None else cfg
    return identify(cfg, progress=progress, executor=executor, plan=DMOutsidePlan(rec))


class DMOutsidePlan(DMPlan):
    """The DM plan over an outside DM recording ``rec`` (as :class:`~torchblur.identify.outside.OutsidePlan` is the sine
    plan over a one-spot one): no rig, nothing recorded, :func:`recording_calibration`, and a sweep that reads the plan,
    ladder and frames of ``rec`` instead of driving a rig; fit, assemble and the result are the DM plan's."""

    truth_rig = None  # an outside mirror: no simulated truth

    def __init__(self, rec: DMRecording):
        self.rec = rec

    def check(self, cfg, rig) -> None:
        """Refuse a ``cfg`` that is not a DM run's or not ``rec``'s frequencies, and any ``rig``."""
        check_dm_config(cfg)
        check_no_rig(rig, "an outside DM recording")
        if cfg.frequencies_hz() != [float(f) for f in self.rec.freq_hz]:
            raise ConfigError(f"sweep.freq_hz: expected the recording's frequencies (dm_recording_config), got {cfg.frequencies_hz()}")

    def open(self, cfg, rig, *, progress: bool, record, base_dir: str | None = None, executor=None):
        """The run record (:func:`~torchblur.identify.outside.outside_record`), the sensor of ``cfg``."""
        self.model_mirror, self.wfs = dm_sensor(cfg)
        return outside_record(cfg, progress=progress, record=record, executor=executor, what="an outside DM recording")

    def calibrate(self, run) -> None:
        """``run.cal`` and every valid subaperture's spot PSF, crop offset and size (:func:`recording_calibration`)."""
        t0 = time.perf_counter()
        run.cal, self.psf, self.offset, self.size = recording_calibration(self.rec, run.cfg, self.wfs)
        run.timing["calibration"], run.timing["acquisition"] = time.perf_counter() - t0, 0.0

    def sweep(self, run) -> None:
        """The recorded plan and spot model, and every frequency's frames to the spot fits
        (``run.acquisition`` as the live sweep's)."""
        rec, cfg, cal = self.rec, run.cfg, run.cal
        self.G = dm_geometry(cfg)
        self.plan, ratio = _plan(rec, cfg, self.G)
        self.R, self.info = rec.R, {"cost_ratio_to_one_at_a_time": ratio}
        ladder = None
        if rec.ladder_levels is not None:
            holds = hold_images(rec.ladder_frames, rec.ladder_levels, float(rec.ladder_exposure_s), cal, self.offset, self.size,
                                float(rec.ladder_power))
            ladder = pattern_ladder(holds, cal, self.offset, self.size)
            LOGGER.info(f"dm spot model: ladder ({rec.ladder_levels.shape[1]} levels x {rec.ladder_frames.item_shape[1]} frames per "
                        f"pattern, from {CSV_NAME}'s ladder rows)")
        self.spot_model = "shifted" if ladder is None else "ladder"
        self.slope_noise = slope_noise(ladder)
        t0 = time.perf_counter()
        driven = driven_spots(self.plan)  # [P, M]: the spot problems the plan measures
        with fit_pool(run.executor) as pool:
            futures = []
            for k, f in enumerate(rec.freq_hz):
                if k >= AMPLITUDE_LAG:  # as the live sweep: frequency k's frames are read once the fit of k - AMPLITUDE_LAG is done
                    futures[k - AMPLITUDE_LAG].exception()  # waits (a task that raised is collect_fits' to report)
                futures.append(pool.submit(_fit_frequency, torch.as_tensor(rec.frames[k]), ExposureWindow(
                    torch.as_tensor(rec.start_s[k], dtype=_F64)[:, None], torch.as_tensor(rec.duration_s[k], dtype=_F64)[:, None]),
                    2 * math.pi * float(f), float(rec.amplitude[k]), float(rec.power[k]), cal, self.psf, self.offset, self.size,
                    float(cfg.camera.jitter_s), _fit_options(cfg), ladder, driven))
            Y, Y_cov, failed, chi2, out, self.fit_s = collect_fits(rec.freq_hz, futures, self.plan.n_patterns, self.G.shape[0],
                                                                   driven)
        LOGGER.info(f"recording: {len(rec.freq_hz)} frequencies x {self.plan.n_patterns} patterns, {rec.n_frames} frames, from {rec.path}")
        run.timing["fit_wait"] = time.perf_counter() - t0
        n_frames = int(rec.start_s.size)
        run.acquisition = (np.asarray(rec.amplitude), np.asarray(rec.power), Y, Y_cov, failed, chi2, n_frames, out)


# ---------------------------------------------------------------------- writing


def _tiff(path: Path, chunks, what: str) -> list[tuple]:
    """Write ``chunks`` (one array ``[..., H, W]`` ADU, or a sequence of them: a recording's groups,
    read one at a time, so one group at a time is held in memory) as one grayscale TIFF stack,
    page after page: uint16 where every value is a whole number in its range (a camera's ADU), else
    float64 (read back exactly either way). Returns each chunk's shape. Each chunk is read once
    when all are whole ADU; a chunk that is not starts the file again, every chunk float64. ``what``:
    the argument ``chunks`` came as, named by the error refusing a one-pass iterator."""
    chunks = [chunks] if hasattr(chunks, "shape") else chunks
    if iter(chunks) is chunks:  # a second pass would find it spent: a TIFF short of pages
        raise InputTypeError(f"{what}: expected an array or a sequence of arrays (read again where one is not whole ADU), "
                             f"got a one-pass {type(chunks).__name__}")
    shapes = _tiff_pages(path, chunks, np.uint16)
    return _tiff_pages(path, chunks, np.float64) if shapes is None else shapes


def _tiff_pages(path: Path, chunks, dtype) -> list[tuple] | None:
    """Write the sequence ``chunks`` (arrays ``[..., H, W]``) as ``dtype`` pages of one TIFF at ``path``
    (replaced); each chunk's shape, or None (the file left incomplete) where ``dtype`` is uint16 and a
    chunk is not whole ADU (:func:`~torchblur.hardware.frames.whole_adu`)."""
    import tifffile

    shapes = []
    with tifffile.TiffWriter(path) as tw:
        for c in chunks:
            a = np.asarray(c, dtype=np.float64)
            if dtype == np.uint16 and not whole_adu(a):
                return None
            shapes.append(a.shape)
            tw.write(a.reshape((-1,) + a.shape[-2:]).astype(dtype), photometric="minisblack", metadata=None, contiguous=True)
    return shapes


class _GroupFrames(Sequence):
    """The frames of a recording's groups ``keys``, loaded one group at a time when indexed:
    ``frames_of(calls)`` of the group's calls (a held pattern ``[K, n, H, W]``, a frequency ``[P, E*R, H, W]``, ADU)."""

    def __init__(self, exp, keys, frames_of):
        self.exp, self.keys, self.frames_of = exp, list(keys), frames_of

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, i):
        return self.frames_of(self.exp.load_calls(self.keys[i]))


def _sweep_frames(calls) -> np.ndarray:
    """A swept frequency's calls (one per pattern) as frames ``[P, E*R, H, W]``."""
    return np.stack([cap.frames.reshape((-1,) + tuple(cap.frames.shape[-2:])).numpy() for _, _, cap in calls])


def write_dm_recording(folder, *, dark, still, still_exposure_s: float, patterns, freq_hz, amplitude, frames, start_s, duration_s,
                       camera: dict, layout: dict, power=None, R: int = 1, ladder: dict | None = None) -> Path:
    """Write an outside DM recording (module docstring) from arrays into ``folder`` (created;
    existing files of the format are replaced) and return it.

    Args:
        dark ``[Nd, H, W]``, still ``[Ns, H, W]``: ADU; still_exposure_s: the still frames' exposure (s).
        patterns: ``[P, N]``; freq_hz, amplitude: ``[F]`` (power ``[F]``, default 1).
        frames: ``[F, P, E*R, H, W]`` ADU (or a sequence of F arrays ``[P, E*R, H, W]``), exposure-major.
        start_s, duration_s: ``[F, P, E*R]`` each frame's window (s after the sine's upward zero crossing).
        camera: the camera keys of ``recording.yaml`` (``gain_e_per_adu`` required; ``latency_s``, ...).
        layout: ``{"dm": {...}, "wfs": {...}, "dm_plan": {...}}``.
        R: frames per exposure window (the repeats).
        ladder: the patterns held still, or None: ``{"levels": [P, K], "frames": P arrays [K, n, H, W] ADU (a sequence, read one at a time),
            "exposure_s": s, "power": relative (default 1)}`` (rows of kind ``ladder``, column ``level``).
    """
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    patterns = np.asarray(patterns, dtype=np.float64)
    F, P = len(freq_hz), patterns.shape[0]
    power = np.ones(F) if power is None else np.asarray(power, dtype=np.float64)
    _tiff(folder / "dark.tif", dark, "dark")
    _tiff(folder / "still.tif", still, "still")
    ER = _tiff(folder / "sweep.tif", frames, "frames")[0][-3]  # a chunk [P, E*R, H, W] or the whole [F, P, E*R, H, W]
    head = ["file", "page", "kind", "pattern", "freq_hz", "exposure_s", "window_start_s", "amplitude", "power", "repeat"]
    rows = [["dark.tif", i, "dark"] + [""] * 7 for i in range(len(dark))]
    rows += [["still.tif", i, "still", "", "", repr(float(still_exposure_s)), "", "", "", ""] for i in range(len(still))]
    page = 0
    for k in range(F):
        for p in range(P):
            for j in range(ER):
                rows.append(["sweep.tif", page, "sweep", p, repr(float(freq_hz[k])), repr(float(duration_s[k][p][j])),
                             repr(float(start_s[k][p][j])), repr(float(amplitude[k])), repr(float(power[k])), j % R])
                page += 1
    if ladder is not None:
        lv = np.asarray(ladder["levels"], dtype=np.float64)
        held = ladder["frames"]
        shapes = _tiff(folder / "ladder.tif", list(held) if hasattr(held, "shape") else held,  # one chunk a pattern
                       "ladder['frames']")
        head, rows, page = head + ["level"], [r + [""] for r in rows], 0
        for p in range(lv.shape[0]):
            for k in range(lv.shape[1]):
                for _ in range(shapes[p][1]):
                    rows.append(["ladder.tif", page, "ladder", p, "", repr(float(ladder["exposure_s"])), "", "",
                                 repr(float(ladder.get("power", 1.0))), "", repr(float(lv[p, k]))])
                    page += 1
    with open(folder / CSV_NAME, "w", newline="") as fh:
        csv.writer(fh).writerows([head] + rows)
    with open(folder / PATTERNS_NAME, "w", newline="") as fh:
        csv.writer(fh).writerows([["pattern"] + [f"a{j}" for j in range(patterns.shape[1])]]
                                 + [[p] + [repr(float(v)) for v in row] for p, row in enumerate(patterns)])
    doc = {k: (float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else v) for k, v in camera.items()
           if v is not None}
    doc.update({sec: dict(layout[sec]) for sec in _SECTIONS if sec in layout})
    (folder / YAML_NAME).write_text(yaml.safe_dump(doc, sort_keys=False))
    return folder


def export_dm_recording(run, folder) -> Path:
    """Write the frames of a torchblur DM run's recording ``run`` (its ``--out`` folder or its
    ``experiment/``) as an outside DM recording in ``folder`` (:func:`write_dm_recording`; what is
    exported and what is not: docs/outside_recordings.md, "Deformable-mirror recordings"). The
    calibration is replayed from the recording (:func:`torchblur.identify.dm_plan._calibrate` on
    a ReplayRig) for the latency and saturation.

    Raises:
        RecordingError: not a complete DM recording.
    """
    path = Path(run)
    exp = Experiment.open(path / "experiment" if (path / "experiment" / "experiment.json").is_file() else path, writable=False)
    cfg = load_config(str(exp.path / "config.yaml"), trusted=False, force=True)
    doc = exp.meta.get(PLAN_KEY)
    if not cfg.dm.enabled or doc is None:
        raise RecordingError(f"{exp.path}: not a DM run's recording with its plan ({PLAN_KEY})")
    cal = _calibrate(cfg, ReplayRig(exp), dm_sensor(cfg)[1], exp)
    (_, _, dark), (_, args, still) = exp.load_calls("dark")[0], exp.load_calls("psf")[0]
    keys = sorted(k for k in exp.groups if exp.groups[k][0].get("kind") == SWEEP_KIND)
    if not keys:
        raise RecordingError(f"{exp.path}: holds no swept frequency ({SWEEP_KIND} group)")
    freq, amp, power, start, dur = [], [], [], [], []
    for key in keys:  # the windows from the manifest: each group's frames are decoded once, as they are written
        lab = exp.groups[key][0]
        delay = float(lab["trigger_delay_s"])
        freq.append(float(lab["freq_hz"]))
        amp.append(float(lab["amplitude"]))
        power.append(float(lab["power"]))
        start.append(np.stack([(t.reshape(-1) + delay + cal.latency_s).numpy() for t in exp.call_values(key, "trigger_time_s")]))
        dur.append(np.stack([t.reshape(-1).numpy() for t in exp.call_values(key, "exposure_s")]))
    c = cfg.camera
    held = sorted(k for k in exp.groups if k.startswith("dm_ladder/") and k != TEST_KEY)  # the ladder the run fitted with, if any
    ladder = None
    if held:
        holds = [exp.groups[k][0]["args"] for k in held]  # the manifest's: the frames are read one pattern at a time as written
        ladder = {"levels": np.array([a["levels"] for a in holds]), "frames": _GroupFrames(exp, held, lambda calls: calls[0][2].frames.numpy()),
                  "exposure_s": float(holds[0]["exposure_s"]), "power": float(holds[0]["power"])}
    camera = {"gain_e_per_adu": float(c.gain), "saturation_adu": float(cal.saturation.saturation_adu),
              "trigger_delay_s": float(c.trigger_delay_s), "latency_s": float(cal.latency_s), "latency_std_s": float(cal.latency_std_s),
              "jitter_s": float(c.jitter_s)}
    layout = {"dm": {"n_across": int(cfg.dm.n_across), "coupling": float(cfg.dm.coupling)}, "wfs": asdict(cfg.wfs),
              "dm_plan": {"kind": str(doc["kind"]), "support_threshold": float(doc["support_threshold"]),
                          "check_threshold": float(cfg.dm_plan.support_threshold)}}
    return write_dm_recording(folder, dark=dark.frames.numpy(), still=still.frames.numpy(), still_exposure_s=float(args["exposure_s"]),
                              patterns=np.asarray(doc["patterns"], dtype=np.float64), freq_hz=freq, amplitude=amp, power=power,
                              frames=_GroupFrames(exp, keys, _sweep_frames), start_s=start, duration_s=dur, camera=camera, layout=layout, R=int(doc["n_repeats"]),
                              ladder=ladder)
