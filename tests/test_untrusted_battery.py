"""Issue 26's battery: untrusted input on every surface torchblur reads (outside recordings,
torchblur and DM recordings, actuator tables, configs, protocol 2, the Python API).

Every case runs in a thread with a 10 s guard (a hang fails it, the suite goes on) under an
audit hook that sees every ``open``, and is judged on the same counts (:func:`judge`):

- ``hang``: not finished within 10 s;
- ``traceback``: an exception that is not a torchblur error (a ValueError/TypeError subclass);
- ``silent``: a tampered or impossible input accepted (a wrong result without a word);
- ``echo``: more than :data:`torchblur.errors.EXCERPT_CHARS` characters of a planted secret in
  the message, or a message of more than one line;
- ``outside``: a file outside the recording (the planted secret, ``/proc/self/environ``,
  ``/dev/zero``) opened;
- ``alloc``: (header bombs) more than 64 MiB allocated before the refusal;
- ``lost``: (resumes of tampered recordings) a frame file neither kept nor set aside.

Recordings are built once per module, small, and every case mutates its own copy.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch

from torchblur.errors import EXCERPT_CHARS, TorchblurError

from outside_folder import write_outside

_RNG = random.Random(26)
SECRET = "S3CR3T-" + "".join(_RNG.choice("abcdefghijklmnopqrstuvwxyz0123456789") for _ in range(73))
_OPENED: list = []
_WATCH = [False]


def _audit(event, args):
    if _WATCH[0] and event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.path.realpath(os.fsdecode(args[0])))


sys.addaudithook(_audit)


def run_guarded(fn, *, timeout_s: float = 10.0, trace: bool = False) -> dict:
    """``fn()`` in a daemon thread: ``{"done", "exc", "value", "opened", "seconds", "peak"}``."""
    out = {"done": False, "exc": None, "value": None, "peak": 0}

    def body():
        try:
            out["value"] = fn()
        except BaseException as exc:  # judged below
            out["exc"] = exc
        out["done"] = True

    _OPENED.clear()
    _WATCH[0] = True
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    th = threading.Thread(target=body, daemon=True)
    th.start()
    th.join(timeout_s)
    out["seconds"] = time.perf_counter() - t0
    if trace:
        out["peak"] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    _WATCH[0] = False
    out["opened"] = list(_OPENED)
    return out


def _echoes(msg: str) -> bool:
    n = EXCERPT_CHARS + 1
    return any(SECRET[i:i + n] in msg for i in range(len(SECRET) - n + 1))


def judge(out: dict, *, refuse: bool = True, forbidden=(), alloc_mib: float | None = None) -> list:
    """The counts this case breaks (module docstring); [] when it holds."""
    bad = []
    if not out["done"]:
        return ["hang"]
    exc = out["exc"]
    if exc is not None and not (isinstance(exc, TorchblurError) and isinstance(exc, (ValueError, TypeError))):
        bad.append(f"traceback: {type(exc).__name__}: {str(exc)[:200]}")
    if refuse and exc is None:
        bad.append("silent: accepted")
    if exc is not None and ("\n" in str(exc) or _echoes(str(exc))):
        bad.append(f"echo: {str(exc)[:300]!r}")
    reals = [os.path.realpath(f) for f in forbidden]
    opened = [p for p in out["opened"] if any(p == r or p.startswith(r.rstrip("/") + "/") for r in reals)]
    if opened:
        bad.append(f"outside: opened {opened[:3]}")
    if alloc_mib is not None and out["peak"] > alloc_mib * 2**20:
        bad.append(f"alloc: {out['peak'] / 2**20:.1f} MiB before the refusal")
    return bad


# ---------------------------------------------------------------------- shared material


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """``outside/`` (the secret files a recording must never read) and the pristine recordings."""
    root = tmp_path_factory.mktemp("battery")
    outside = root / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text(SECRET + "\n")
    (outside / "secret.csv").write_text(f"file,kind\n{SECRET}.tif,dark\n")
    (outside / "secret.tif").write_bytes(b"II*\x00" + SECRET.encode())
    return {"root": root, "outside": outside, "outside_rec": _make_outside(root / "outside_rec"),
            "exp": _make_experiment(root / "exp")}


FORBIDDEN_STATIC = ("/proc/self/environ", "/dev/zero")


def _forbidden(base):
    return (str(base["outside"]),) + FORBIDDEN_STATIC


def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copytree(src, dst, symlinks=True)
    return dst


def _frames(rng, n, H=8, W=8, level=100.0):
    return np.round(level + 5 * rng.standard_normal((n, H, W)) + 40 * np.exp(-((np.arange(W) - W / 2) ** 2)[None, None] / 4))


def _make_outside(folder: Path) -> Path:
    rng = np.random.default_rng(26)
    f = 37.0
    sweep = _frames(rng, 4)
    pt = {"freq_hz": f, "amplitude": 0.5, "frames": sweep, "start_s": np.zeros(4), "duration_s": np.array([0.3, 0.3, 0.8, 0.8]) / f,
          "R": 2}
    return write_outside(folder, dark=_frames(rng, 2, level=90.0), still=_frames(rng, 2), still_exposure_s=1e-3, points=[pt],
                         camera={"gain_e_per_adu": 2.0}, dtype=np.uint16)


def _read_outside(d):
    from torchblur.hardware.outside import read_outside_recording

    return lambda: read_outside_recording(d)


# ---------------------------------------------------------------------- outside recordings


def _fifo(p: Path):
    p.unlink(missing_ok=True)
    os.mkfifo(p)


def _dir(p: Path):
    p.unlink(missing_ok=True)
    p.mkdir()


def _link(target):
    def make(p: Path):
        p.unlink(missing_ok=True)
        p.symlink_to(target)
    return make


def _bomb(pages: int, side: int, tile=None, compression="zlib"):
    def make(p: Path):
        tifffile.imwrite(p, np.arange(pages * 256, dtype=np.uint16).reshape(pages, 16, 16), photometric="minisblack",
                         compression=compression, tile=tile, metadata=None)
        with tifffile.TiffFile(p, mode="r+b") as tf:
            for page in tf.pages:
                page.tags["ImageWidth"].overwrite(side)
                page.tags["ImageLength"].overwrite(side)
    return make


def _sparse(size: int):
    def make(p: Path):
        p.unlink(missing_ok=True)
        with open(p, "wb") as fh:
            fh.truncate(size)
    return make


def _text(text: str):
    return lambda p: p.write_text(text)


OUTSIDE_FILE_CASES = {
    "frames.csv symlink out": ("frames.csv", "secret.csv"),
    "frames.csv FIFO": ("frames.csv", _fifo),
    "frames.csv folder": ("frames.csv", _dir),
    "frames.csv /dev/zero": ("frames.csv", _link("/dev/zero")),
    "frames.csv 65 MiB": ("frames.csv", _sparse(65 * 2**20)),
    "frames.csv secret cell": ("frames.csv", _text(f"file,kind\ndark.tif,{SECRET}\n")),
    "frames.csv secret column": ("frames.csv", _text(f"file,kind,{SECRET}\ndark.tif,dark,1\n")),
    "frames.csv NUL": ("frames.csv", _text("file,kind\ndark.tif,da\x00rk\n")),
    "recording.yaml symlink out": ("recording.yaml", "secret.txt"),
    "recording.yaml FIFO": ("recording.yaml", _fifo),
    "recording.yaml folder": ("recording.yaml", _dir),
    "recording.yaml /dev/zero": ("recording.yaml", _link("/dev/zero")),
    "recording.yaml /proc/self/environ": ("recording.yaml", _link("/proc/self/environ")),
    "recording.yaml jitter 1e300": ("recording.yaml", _text("gain_e_per_adu: 2.0\njitter_s: 1.0e+300\n")),
    "recording.yaml latency -1e300": ("recording.yaml", _text("gain_e_per_adu: 2.0\nlatency_s: -1.0e+300\n")),
    "recording.yaml gain 0": ("recording.yaml", _text("gain_e_per_adu: 0\n")),
    "recording.yaml gain secret": ("recording.yaml", _text(f"gain_e_per_adu: {SECRET}\n")),
    "recording.yaml unknown secret key": ("recording.yaml", _text(f"gain_e_per_adu: 2.0\n{SECRET}: 1\n")),
    "recording.yaml read noise nan": ("recording.yaml", _text("gain_e_per_adu: 2.0\nread_noise_e: .nan\n")),
    "recording.yaml saturation 1e300": ("recording.yaml", _text("gain_e_per_adu: 2.0\nsaturation_adu: 1.0e+300\n")),
    "recording.yaml input_unit secret": ("recording.yaml", _text(f"gain_e_per_adu: 2.0\ninput_unit: {SECRET}\n")),
    "recording.yaml alias bomb": ("recording.yaml", _text("a: &a [1,1,1,1,1,1,1,1,1]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\n"
                                                          "c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\nd: [*c,*c,*c,*c,*c,*c,*c,*c,*c]\n")),
    "recording.yaml interpolation": ("recording.yaml", _text("gain_e_per_adu: ${oc.env:HOME}\n")),
    "recording.yaml a list": ("recording.yaml", _text("- 1\n- 2\n")),
    "dark.tif symlink out": ("dark.tif", "secret.tif"),
    "dark.tif FIFO": ("dark.tif", _fifo),
    "dark.tif folder": ("dark.tif", _dir),
    "dark.tif /dev/zero": ("dark.tif", _link("/dev/zero")),
    "dark.tif secret bytes": ("dark.tif", _text(SECRET * 3)),
    "dark.tif truncated": ("dark.tif", lambda p: p.write_bytes(p.read_bytes()[:100])),
    "dark.tif colour": ("dark.tif", lambda p: tifffile.imwrite(p, np.zeros((8, 8, 3), np.uint16), photometric="rgb")),
    "sweep.tif float NaN": ("sweep.tif", lambda p: tifffile.imwrite(p, np.full((4, 8, 8), np.nan), photometric="minisblack")),
}
BOMBS = {
    "tiled 60000^2 in 300 B": _bomb(1, 60000, tile=(16, 16)),
    "200 pages of 8192^2 in 100 kB": _bomb(200, 8192),
    "40000^2 compressed in 300 B": _bomb(1, 40000),
    "40000^2 uncompressed header": _bomb(1, 40000, compression=None),
    "side 70000": _bomb(1, 70000, compression=None),
    "tile 65536^2": _bomb(1, 65536, tile=(16, 16)),
}


@pytest.mark.parametrize("case", sorted(OUTSIDE_FILE_CASES))
def test_outside_recording_files(base, tmp_path, case):
    name, how = OUTSIDE_FILE_CASES[case]
    d = _copy(base["outside_rec"], tmp_path)
    p = d / name
    if isinstance(how, str):
        _link(base["outside"] / how)(p)
    else:
        how(p)
    assert judge(run_guarded(_read_outside(d)), forbidden=_forbidden(base)) == []


@pytest.mark.parametrize("case", sorted(BOMBS))
def test_outside_tiff_header_limits(base, tmp_path, case):
    d = _copy(base["outside_rec"], tmp_path)
    BOMBS[case](d / "dark.tif")
    out = run_guarded(_read_outside(d), trace=True)
    assert judge(out, forbidden=_forbidden(base), alloc_mib=64) == []
    assert "before decoding" in str(out["exc"])


def _csv_rows(d):
    import csv

    return list(csv.reader((d / "frames.csv").read_text().splitlines()))


def _write_rows(d, rows):
    (d / "frames.csv").write_text("".join(",".join(r) + "\n" for r in rows))


def _dup_symlink(d):
    (d / "dark2.tif").symlink_to("dark.tif")
    rows = _csv_rows(d)
    rows.append(["dark2.tif"] + rows[1][1:])  # a third dark frame: page 0 again, through a link to the same file
    _write_rows(d, rows)


def _dup_copy(d):
    shutil.copyfile(d / "still.tif", d / "still2.tif")
    rows = _csv_rows(d)
    rows.append(["still2.tif", "0"] + rows[3][2:])
    _write_rows(d, rows)


def _dup_dot(d):
    rows = _csv_rows(d)
    rows.append(["./dark.tif", "0"] + rows[1][2:])
    _write_rows(d, rows)


def _dup_page(d):
    st = tifffile.imread(d / "sweep.tif")
    st[1] = st[0]  # the second repeat a copy of the first
    tifffile.imwrite(d / "sweep.tif", st, photometric="minisblack")


DUPLICATES = {"symlink": _dup_symlink, "byte copy": _dup_copy, "same page as ./": _dup_dot, "page copied in its stack": _dup_page}


@pytest.mark.parametrize("case", sorted(DUPLICATES))
def test_outside_duplicate_frames_refused(base, tmp_path, case):
    d = _copy(base["outside_rec"], tmp_path)
    DUPLICATES[case](d)
    out = run_guarded(_read_outside(d))
    assert judge(out, forbidden=_forbidden(base)) == []


BAD_CELLS = ["nan", "inf", "-1", "1e400", "", "abc", SECRET, "x" * 5000, "1e-320", "0", "\x00", "9" * 400]


@pytest.mark.parametrize("seed", range(12))
def test_outside_csv_cells_fuzzed(base, tmp_path, seed):
    rng = random.Random(seed)
    d = _copy(base["outside_rec"], tmp_path)
    rows = _csv_rows(d)
    sweep = [i for i, r in enumerate(rows) if len(r) > 2 and r[2] == "sweep"]
    i = rng.choice(sweep)
    col = rng.choice([0, 1, 3, 4, 5, 6])  # file, page, freq_hz, exposure_s, window_start_s, amplitude
    rows[i][col] = rng.choice(BAD_CELLS)
    _write_rows(d, rows)
    out = run_guarded(_read_outside(d))
    header = rows[0][col]
    # a cell may happen to be a valid value (a page 0, an exposure within range): then it must read, else be refused by name
    assert judge(out, refuse=False, forbidden=_forbidden(base)) == []
    if out["exc"] is not None:
        assert "frames.csv" in str(out["exc"]) or header in str(out["exc"]) or ".tif" in str(out["exc"])


@pytest.mark.parametrize("periods", [1.0, 2.0])
def test_outside_whole_period_exposure_named(base, tmp_path, periods):
    d = _copy(base["outside_rec"], tmp_path)
    rows = _csv_rows(d)
    i = next(i for i, r in enumerate(rows) if len(r) > 2 and r[2] == "sweep")
    rows[i][4] = repr(periods / float(rows[i][3]))
    _write_rows(d, rows)
    out = run_guarded(_read_outside(d))
    assert judge(out) == [] and "column exposure_s" in str(out["exc"])


def test_outside_pristine_reads(base, tmp_path):
    out = run_guarded(_read_outside(_copy(base["outside_rec"], tmp_path)))
    assert judge(out, refuse=False, forbidden=_forbidden(base)) == [] and out["exc"] is None
    assert out["value"].points[0].frames.shape == (4, 8, 8)


# ---------------------------------------------------------------------- torchblur and DM recordings

PATTERN = [1.0, -1.0, 0.5, 0.0]
PLAN = {"kind": "hadamard", "support_threshold": 0.01, "n_repeats": 1, "patterns": [[1, 1, 1, 1], [1, -1, 1, -1]],
        "support": ["1111", "1111"]}


def _capture(n, shape, rng, start):
    from torchblur.rig.base import Capture

    N = int(np.prod(shape))
    frames = torch.from_numpy(_frames(rng, N, 6, 5)).reshape(shape + (6, 5))
    return Capture(frames=frames, exposure_s=torch.full(shape, 1e-3, dtype=torch.float64),
                   trigger_offset_s=torch.full(shape, 2e-4, dtype=torch.float64),
                   trigger_time_s=torch.arange(N, dtype=torch.float64).reshape(shape) * 0.04,
                   frame_counter=torch.arange(start, start + N).reshape(shape), meta={"kind": "x", "power": 1.0})


def _make_experiment(path: Path) -> Path:
    """A DM-like recording: dark (3 frames), two pattern sweep groups (2 exposures x 2 frames) and a plan."""
    from torchblur.hardware.frames import CameraInfo
    from torchblur.hardware.recording import Experiment

    rng = np.random.default_rng(7)
    info = CameraInfo(frame_shape=(6, 5), frame_rate_hz=30.0, max_exposure_s=0.03, readout_s=1e-3, name="battery")
    exp = Experiment.create(path, config_yaml="seed: 3\ndm:\n  actuator_table: actuator_table.csv\n", camera=info)
    (path / "actuator_table.csv").write_text("actuator,mode_hz,damping,gain,delay_s\n1,650,0.07,1.0,2e-5\n")
    exp.start_session({"kind": "test"})
    exp.set_meta("dm_plan", PLAN)
    exp.record("dark", "dark", [("dark", {"n": 3, "exposure_s": 1e-3}, _capture(3, (3,), rng, 0))])
    for k, f in enumerate((40.0, 400.0)):
        args = {"pattern": PATTERN, "freq_hz": f, "amplitude": 0.3, "power": 1.0}
        exp.record(f"dm/p0/{k:03d}", "sweep", [("pattern_sine", args, _capture(4, (2, 2), rng, 3 + 4 * k))],
                   labels={"input": "p0", "freq_hz": f, "amplitude": 0.3, "power": 1.0, "point": k})
    exp.end_session("complete")
    exp.close()
    return path


def _read_all(d):
    """Everything a re-fit reads: experiment.json (plan included), every group's calls, every frame, the config."""
    def read():
        from torchblur.hardware.recording import Experiment
        from torchblur.config import IdentifyConfig, load_dataclass

        exp = Experiment.open(d, writable=False)
        for g in exp.groups:
            exp.load_calls(g)
        load_dataclass(IdentifyConfig, str(exp.path / "config.yaml"), trusted=False)
        return exp
    return read


def _lines(d):
    return [json.loads(x) for x in (d / "manifest.jsonl").read_text().splitlines()]


def _put_lines(d, lines):
    (d / "manifest.jsonl").write_text("".join(json.dumps(ln) + "\n" for ln in lines))


def _edit_group(group, fn):
    def edit(d):
        lines = _lines(d)
        for ln in lines:
            if ln["group"] == group:
                fn(ln)
        _put_lines(d, lines)
    return edit


def _double_amplitude(ln):
    ln["amplitude"] *= 2
    ln["args"]["amplitude"] *= 2


def _set(key, value):
    def fn(ln):
        ln[key] = value
    return fn


def _meta_edit(fn):
    def edit(d):
        meta = json.loads((d / "experiment.json").read_text())
        fn(meta)
        (d / "experiment.json").write_text(json.dumps(meta))
    return edit


def _flip_support(meta):
    meta["dm_plan"]["support"][0] = "0111"


def _redigest_after(fn, group="dm/p0/001"):
    """Edit a group, then recompute its settings digest (the TIFF's description still holds the old one)."""
    from torchblur.hardware.manifest import SETTINGS_KEY, settings_digest

    def edit(d):
        lines = _lines(d)
        gl = [ln for ln in lines if ln["group"] == group]
        for ln in gl:
            fn(ln)
        digest = settings_digest(gl)
        for ln in gl:
            ln[SETTINGS_KEY] = digest
        _put_lines(d, lines)
    return edit


def _rewrite_tiff(group, change):
    """Rewrite a group's TIFF (its description kept) with ``change(stack)`` and its hash updated in the manifest."""
    import hashlib

    def edit(d):
        lines = _lines(d)
        f = d / next(ln["file"] for ln in lines if ln["group"] == group)
        with tifffile.TiffFile(f) as tf:
            desc, stack = tf.pages.first.description, tf.asarray()
        stack = change(d, stack)
        tifffile.imwrite(f, stack, photometric="minisblack", metadata=None, description=desc)
        sha = hashlib.sha256(f.read_bytes()).hexdigest()
        for ln in lines:
            if ln["group"] == group:
                ln["sha256"] = sha
        _put_lines(d, lines)
    return edit


def _copy_page_within(d, st):
    st[1] = st[0]
    return st


def _copy_page_across(d, st):
    st[0] = tifffile.imread(d / "frames" / "dm_p0_000.tif")[2]
    return st


def _file_of(group, how):
    def edit(d):
        f = d / "frames" / (group.replace("/", "_") + ".tif")
        how(f)
    return edit


def _strip(meta):
    meta.pop("integrity", None)


def _strip_all(d):
    from torchblur.hardware.manifest import SETTINGS_KEY

    lines = _lines(d)
    for ln in lines:
        ln.pop(SETTINGS_KEY, None)
    _put_lines(d, lines)
    _meta_edit(_strip)(d)


def _file_bomb(group, make):
    import hashlib

    def edit(d):
        lines = _lines(d)
        f = d / next(ln["file"] for ln in lines if ln["group"] == group)
        make(f)
        sha = hashlib.sha256(f.read_bytes()).hexdigest()
        for ln in lines:
            if ln["group"] == group:
                ln["sha256"] = sha
        _put_lines(d, lines)
    return edit


EXPERIMENT_CASES = {
    "amplitude doubled on every line, args too": _edit_group("dm/p0/001", _double_amplitude),
    "trigger offset changed on every line": _edit_group("dm/p0/001", _set("trigger_offset_s", 5e-4)),
    "exposure changed on every line": _edit_group("dm/p0/000", _set("exposure_s", 2e-3)),
    "frequency changed, args too": _edit_group("dm/p0/001", lambda ln: (ln.update(freq_hz=300.0), ln["args"].update(freq_hz=300.0))),
    "pattern changed on every line": _edit_group("dm/p0/000", lambda ln: ln["args"]["pattern"].__setitem__(0, 2.0)),
    "power changed, args too": _edit_group("dm/p0/000", lambda ln: (ln.update(power=0.5), ln["args"].update(power=0.5))),
    "dark exposure changed": _edit_group("dark", _set("exposure_s", 5e-3)),
    "frame counters shifted": _edit_group("dark", lambda ln: ln.update(frame_counter=ln["frame_counter"] + 100)),
    "settings digest removed from a group": _edit_group("dm/p0/000", lambda ln: ln.pop("settings_sha256")),
    "settings digest recomputed, TIFF not": _redigest_after(_double_amplitude),
    "timing recomputed, TIFF not": _redigest_after(_set("trigger_offset_s", 1e-3)),
    "plan support bit flipped": _meta_edit(_flip_support),
    "plan n_repeats changed": _meta_edit(lambda m: m["dm_plan"].update(n_repeats=2)),
    "plan pattern changed": _meta_edit(lambda m: m["dm_plan"]["patterns"][1].__setitem__(1, 1)),
    "plan digest removed": _meta_edit(lambda m: m["integrity"].pop("dm_plan")),
    "integrity removed": _meta_edit(_strip),
    "a key added to experiment.json": _meta_edit(lambda m: m.update(extra={"x": 1})),
    "an old recording (no digests)": _strip_all,
    "config.yaml edited": lambda d: (d / "config.yaml").write_text("seed: 4\n"),
    "config.yaml FIFO": lambda d: _fifo(d / "config.yaml"),
    "config.yaml symlink out": None,  # set in the test (needs base)
    "config.yaml /proc/self/environ": lambda d: _link("/proc/self/environ")(d / "config.yaml"),
    "experiment.json FIFO": lambda d: _fifo(d / "experiment.json"),
    "experiment.json folder": lambda d: _dir(d / "experiment.json"),
    "experiment.json symlink out": None,
    "manifest FIFO": lambda d: _fifo(d / "manifest.jsonl"),
    "manifest /dev/zero": lambda d: _link("/dev/zero")(d / "manifest.jsonl"),
    "manifest folder": lambda d: _dir(d / "manifest.jsonl"),
    "manifest symlink out": None,
    "frame file FIFO": _file_of("dm/p0/000", _fifo),
    "frame file folder": _file_of("dm/p0/000", _dir),
    "frame file /dev/zero": _file_of("dm/p0/000", _link("/dev/zero")),
    "frame file symlink out": None,
    "page copied within its group": _rewrite_tiff("dm/p0/001", _copy_page_within),
    "page copied from another group": _rewrite_tiff("dm/p0/001", _copy_page_across),
    "group file a copy of another's": lambda d: _file_bomb("dm/p0/001", lambda f: shutil.copyfile(d / "frames" / "dm_p0_000.tif", f))(d),
    "frame file a tiled 60000^2 bomb": _file_bomb("dm/p0/000", _bomb(1, 60000, tile=(16, 16))),
    "frame file 50 pages of 8192^2": _file_bomb("dm/p0/000", _bomb(50, 8192)),
    "frame file 40000^2 uncompressed header": _file_bomb("dm/p0/000", _bomb(1, 40000, compression=None)),
    "experiment.json secret schema": _meta_edit(lambda m: m.update(schema_version=SECRET)),
    "experiment.json secret camera": _meta_edit(lambda m: m["camera"].update(frame_shape=[SECRET, 5])),
    "manifest secret line": lambda d: (d / "manifest.jsonl").write_text((d / "manifest.jsonl").read_text() + SECRET + "\n"),
    "manifest secret field": _edit_group("dark", _set("kind", SECRET)),
}
_OUT_LINKS = {"config.yaml symlink out": "config.yaml", "experiment.json symlink out": "experiment.json",
              "manifest symlink out": "manifest.jsonl", "frame file symlink out": "frames/dm_p0_000.tif"}


@pytest.mark.parametrize("case", sorted(EXPERIMENT_CASES))
def test_recording_tampering_refused(base, tmp_path, case):
    d = _copy(base["exp"], tmp_path)
    if case in _OUT_LINKS:
        _link(base["outside"] / "secret.txt")(d / _OUT_LINKS[case])
    else:
        EXPERIMENT_CASES[case](d)
    out = run_guarded(_read_all(d), trace="bomb" in case or "8192" in case or "40000" in case)
    # a line that is no JSON after the last group reads as a torn append: left out, the groups read unchanged
    torn = case == "manifest secret line"
    assert judge(out, refuse=not torn, forbidden=_forbidden(base), alloc_mib=64) == []
    if torn:
        assert set(out["value"].groups) == {"dark", "dm/p0/000", "dm/p0/001"}


def _frame_files(d: Path) -> list:
    """Every frame file's bytes under ``d`` (kept in frames/ or set aside in quarantine/)."""
    return sorted(p.read_bytes() for p in d.rglob("*.tif") if p.is_file() and not p.is_symlink())


@pytest.mark.parametrize("case", ["amplitude doubled on every line, args too", "settings digest recomputed, TIFF not",
                                  "page copied within its group", "an old recording (no digests)", "manifest secret line"])
def test_resume_of_a_tampered_recording_loses_no_frame(base, tmp_path, case):
    from torchblur.hardware.recording import Experiment

    d = _copy(base["exp"], tmp_path)
    EXPERIMENT_CASES[case](d)
    before = _frame_files(d)

    def resume():
        exp = Experiment.open(d, writable=True)
        exp.close()
        return exp

    out = run_guarded(resume)
    assert judge(out, refuse=False, forbidden=_forbidden(base)) == []
    assert _frame_files(d) == before  # every frame file kept or set aside, byte for byte
    if out["exc"] is None:  # a tampered group the resume kept is refused when it is read (never re-fitted)
        exp = out["value"]
        for g in exp.groups:
            got = run_guarded(lambda: exp.load_calls(g))
            assert judge(got, refuse=g == "dm/p0/001" and case != "manifest secret line") == []


def test_pristine_recording_reads(base, tmp_path):
    out = run_guarded(_read_all(_copy(base["exp"], tmp_path)))
    assert judge(out, refuse=False, forbidden=_forbidden(base)) == [] and out["exc"] is None
    assert set(out["value"].groups) == {"dark", "dm/p0/000", "dm/p0/001"} and out["value"].meta["dm_plan"] == PLAN


RECORDED_TABLES = {"absolute /proc/self/environ": "/proc/self/environ", "absolute secret": None, "dot-dot": "../outside/secret.csv",
                   "symlink out": "link.csv", "backslash": "..\\secret.csv", "NUL": "a\x00b.csv"}


@pytest.fixture(scope="module")
def default_cfg():
    from torchblur.config import load_config

    return load_config(None, force=True)


@pytest.mark.parametrize("case", sorted(RECORDED_TABLES))
def test_recorded_actuator_table_stays_inside(base, tmp_path, case, default_cfg):
    import dataclasses

    from torchblur.cli.commands import _recorded_table

    d = _copy(base["exp"], tmp_path)
    (d / "link.csv").symlink_to(base["outside"] / "secret.csv")
    path = RECORDED_TABLES[case] or str(base["outside"] / "secret.csv")
    cfg = dataclasses.replace(default_cfg, dm=dataclasses.replace(default_cfg.dm, actuator_table=path))
    out = run_guarded(lambda: _recorded_table(cfg, d, new=False))
    assert judge(out, forbidden=_forbidden(base)) == [] and "dm.actuator_table" in str(out["exc"])


def test_recorded_actuator_table_inside_reads(base, tmp_path, default_cfg):
    import dataclasses

    from torchblur.dm.mirror import read_actuator_table
    from torchblur.cli.commands import _recorded_table

    d = _copy(base["exp"], tmp_path)
    cfg = dataclasses.replace(default_cfg, dm=dataclasses.replace(default_cfg.dm, actuator_table="actuator_table.csv"))
    cfg2, base_dir = _recorded_table(cfg, d, new=False)
    assert read_actuator_table(Path(base_dir) / cfg2.dm.actuator_table, 9) == {1: (650.0, 0.07, 1.0, 2e-5)}


# ---------------------------------------------------------------------- actuator tables

HEADER = "actuator,mode_hz,damping,gain,delay_s\n"
TABLES = {
    "FIFO": _fifo, "folder": _dir, "/dev/zero": _link("/dev/zero"), "/proc/self/environ": _link("/proc/self/environ"),
    "1 MiB + 1": _sparse(2**20 + 1),
    "secret header": _text(SECRET + "\n1,2,3,4,5\n"), "secret cell": _text(HEADER + f"1,{SECRET},0.1,1,0\n"),
    "mode_hz 1e308": _text(HEADER + "1,1e308,0.1,1,0\n"), "gain 1e300": _text(HEADER + "1,600,0.1,1e300,0\n"),
    "delay 10 s": _text(HEADER + "1,600,0.1,1,10\n"), "damping 1e9": _text(HEADER + "1,600,1e9,1,0\n"),
    "mode nan": _text(HEADER + "1,nan,0.1,1,0\n"), "not UTF-8": lambda p: p.write_bytes(HEADER.encode() + b"1,\xff\xfe,0.1,1,0\n"),
    "NUL cell": _text(HEADER + "1,600\x00,0.1,1,0\n"), "actuator 1e9": _text(HEADER + "1000000000,600,0.1,1,0\n"),
    "quote never closed": _text(HEADER + '1,"600,0.1,1,0\n' + "9" * 1000 + "\n"),
}


@pytest.mark.parametrize("case", sorted(TABLES))
def test_actuator_tables(base, tmp_path, case):
    from torchblur.dm.mirror import read_actuator_table

    p = tmp_path / "table.csv"
    TABLES[case](p)
    out = run_guarded(lambda: read_actuator_table(p, 9))
    assert judge(out, forbidden=(str(base["outside"]),)) == [] and "dm.actuator_table" in str(out["exc"])


# ---------------------------------------------------------------------- configs

ABSURD = {  # overrides of configs/identify_dm.yaml (or the default config) and the key the refusal must name
    "dm.n_across=64 wfs.n_across=128": (["dm.n_across=64", "wfs.n_across=128"], ("wfs.n_across", "dm.n_across")),
    "dm.n_across=16 wfs.n_across=32": (["dm.n_across=16", "wfs.n_across=32"], ("wfs.n_across", "dm.n_across")),
    "wfs.pitch_px=1e6": (["wfs.pitch_px=1e6"], ("wfs.pitch_px",)),
    "dm_plan.n_repeats=1e9": (["dm_plan.n_repeats=1e9"], ("dm_plan.n_repeats",)),
    "dm_plan.budget_frames=1e9": (["dm_plan.budget_frames=1e9"], ("dm_plan.budget_frames",)),
    "sweep.n=1e12 (DM)": (["sweep.n=1e12", "dm_plan.n_repeats=1"], ("sweep.n",)),
    "geometry: dm 64, wfs 64 at 8 px": (["dm.n_across=64", "wfs.n_across=64", "wfs.pitch_px=8", "wfs.sigma_px=1",
                                         "excitation.target_px=0.3", "dm_plan.budget_frames=64", "sweep.n=4"], ("dm.n_across",)),
    "wfs.oversample=256": (["dm.n_across=40", "wfs.n_across=40", "wfs.pitch_px=8", "wfs.sigma_px=1", "excitation.target_px=0.3",
                            "dm_plan.budget_frames=64", "sweep.n=4", "wfs.oversample=256"], ("wfs.oversample", "dm.n_across", "wfs.n_across")),
}
PLAIN_ABSURD = {
    "sweep.n=1e9": (["sweep.n=1e9"], ("sweep.n",)),
    "camera.height=1e6": (["camera.height=1000000", "camera.width=1000000"], ("camera.height", "camera.width")),
    "sweep.exposures=[1.0]": (["sweep.exposures=[1.0]"], ("sweep.exposures[0]",)),
    "sweep.exposures=[0.3,2.0]": (["sweep.exposures=[0.3,2.0]"], ("sweep.exposures[1]",)),
}


@pytest.mark.parametrize("case", sorted(ABSURD) + sorted(PLAIN_ABSURD))
def test_absurd_sizes_refused_naming_their_key(case, tmp_path):
    from torchblur.config import load_config

    overrides, keys = ABSURD[case] if case in ABSURD else PLAIN_ABSURD[case]
    path = "configs/identify_dm.yaml" if case in ABSURD else None
    out = run_guarded(lambda: load_config(path, overrides))
    assert judge(out) == []
    assert str(out["exc"]).split(":")[0] in keys, str(out["exc"])


CONFIG_FILES = {
    "FIFO": _fifo, "folder": _dir, "/dev/zero": _link("/dev/zero"), "2 MiB": _sparse(2 * 2**20),
    "a secret as text": _text(SECRET + "\n"),
    "not UTF-8": lambda p: p.write_bytes(b"sweep:\n  n: \xff\xfe\n"),
    "tab-indented secret": _text(f"sweep:\n\tn: {SECRET}\n"),
    "recursive alias": _text("a: &a\n  b: *a\n"),
}
SECRET_KEYS = ["sweep.n", "sweep.exposures", "camera.gain", "plant.num", "plant.delay_s", "fit.loss", "dm_plan.kind", "seed",
               "sweep.freq_hz"]


@pytest.mark.parametrize("case", sorted(CONFIG_FILES))
def test_config_files(base, tmp_path, case):
    from torchblur.config import load_config

    p = tmp_path / "c.yaml"
    CONFIG_FILES[case](p)
    out = run_guarded(lambda: load_config(str(p)))
    assert judge(out, forbidden=(str(base["outside"]),)) == []


@pytest.mark.parametrize("key", SECRET_KEYS)
def test_config_values_never_echoed(tmp_path, key):
    from torchblur.config import load_config

    section, name = key.split(".") if "." in key else (None, key)
    p = tmp_path / "c.yaml"
    p.write_text((f"{section}:\n  {name}: {SECRET}\n" if section else f"{name}: {SECRET}\n")
                 + ("dm:\n  n_across: 8\n" if section == "dm_plan" else ""))  # the dm_plan section counts in a DM run
    out = run_guarded(lambda: load_config(str(p)))
    assert judge(out) == [] and key in str(out["exc"])


def test_recorded_config_interpolation_refused(tmp_path):
    from torchblur.config import load_config

    p = tmp_path / "config.yaml"
    p.write_text("seed: ${oc.env:HOME}\n")
    out = run_guarded(lambda: load_config(str(p), trusted=False))
    assert judge(out, forbidden=FORBIDDEN_STATIC) == []


# ---------------------------------------------------------------------- protocol 2

COMMANDS = ["PAT 0 " + " ".join(["1"] * 5000), "PAT -1 1", "PAT 99999999999 1", "PAT 0 nan", "PAT 0 1e400", "PAT", "PAT x 1",
            "WAVE pat SINE nan 1", "WAVE pat SINE 10 -1", "WAVE pat MULTI 10:1:0,nan:1:0", "ACT? 3", "PAT? 1", "ARM 0 1e-3 1e12",
            "PING " + SECRET, "\x00\x01\x02", "WAVE x SINE 1e308 1e308", "SETTLE -1", "POWER 1e999", "WAVE pat HOLD nan",
            "WAVE pat HOLD 1e400 1"]
REPLIES = [b"OK ACT n=1e999\n", b"OK PAT crc=" + SECRET.encode() + b"\n", b"ERR x y\n", b"OK\n", b"\xff\xfe\n", b"OK ID\x00 a=1\n",
           b"OK ACT n\n", b"ERR 99999999999999999999 E z\n"]


@pytest.mark.parametrize("i", range(len(COMMANDS) + 4))
def test_protocol2_commands(i):
    from torchblur.hardware.protocol import Command, ProtocolViolation, parse_command

    if i < len(COMMANDS):
        line = COMMANDS[i]
    else:  # seeded random lines built from protocol words and bad tokens
        rng = random.Random(i)
        line = " ".join(rng.choice(["PAT", "WAVE", "pat", "SINE", "ACT?", "PAT?", "ARM", "0", "-1", "nan", "1e400", "x" * 300, "MULTI"])
                        for _ in range(rng.randint(1, 8)))
    out = run_guarded(lambda: parse_command(line.encode("utf-8", "surrogateescape") + b"\n"))
    assert out["done"]
    assert out["exc"] is None and isinstance(out["value"], Command) or isinstance(out["exc"], ProtocolViolation), out["exc"]
    if out["exc"] is not None:
        assert "\n" not in str(out["exc"]) and len(str(out["exc"])) < 400


@pytest.mark.parametrize("i", range(len(REPLIES)))
def test_protocol2_replies(i):
    from torchblur.hardware.protocol import Reply, parse_reply

    out = run_guarded(lambda: parse_reply(REPLIES[i]))
    assert out["done"]
    assert (out["exc"] is None and isinstance(out["value"], Reply)) or type(out["exc"]) is ValueError, out["exc"]
    if out["exc"] is not None:
        assert "\n" not in str(out["exc"]) and not _echoes(str(out["exc"]))


# ---------------------------------------------------------------------- the Python API

API_FILES = {"FIFO": _fifo, "folder": _dir, "/dev/zero": _link("/dev/zero"), "/proc/self/environ": _link("/proc/self/environ"),
             "secret text": _text(SECRET), "secret JSON string": _text(json.dumps({"schema_version": SECRET})),
             "NUL bytes": lambda p: p.write_bytes(b"\x00" * 100), "nested 100000": _text("[" * 100000 + "]" * 100000)}


@pytest.mark.parametrize("reader", ["FrequencyResponse.from_json", "FrequencyResponse.from_csv", "TransferFunctionFit.from_json",
                                    "DirectModelFit.from_json"])
@pytest.mark.parametrize("case", sorted(API_FILES))
def test_response_and_model_files(tmp_path, reader, case):
    from torchblur.sysid.direct import DirectModelFit
    from torchblur.sysid.frequency_response import FrequencyResponse
    from torchblur.sysid.tf_fit import TransferFunctionFit

    fn = {"FrequencyResponse.from_json": FrequencyResponse.from_json, "FrequencyResponse.from_csv": FrequencyResponse.from_csv,
          "TransferFunctionFit.from_json": TransferFunctionFit.from_json, "DirectModelFit.from_json": DirectModelFit.from_json}[reader]
    p = tmp_path / "f.json"
    API_FILES[case](p)
    out = run_guarded(lambda: fn(p))
    assert judge(out) == [] and str(p) in str(out["exc"])


@pytest.mark.parametrize("case", ["negative variance", "indefinite", "negative variance where Y is NaN (unused)"])
def test_demultiplex_covariance(case):
    from torchblur.dm.demux import demultiplex

    P, S, F, N = 4, 2, 1, 4
    rng = np.random.default_rng(0)
    Y = rng.standard_normal((P, S, F)) + 1j * rng.standard_normal((P, S, F))
    cov = np.broadcast_to(np.eye(2) * 1e-4, (P, S, F, 2, 2)).copy()
    patterns = np.array([[1, 1, 1, 1], [1, -1, 1, -1], [1, 1, -1, -1], [1, -1, -1, 1]], dtype=float)
    if case == "negative variance":
        cov[1, 0, 0, 0, 0] = -1e-4
    elif case == "indefinite":
        cov[2, 1, 0] = [[1e-4, 1e-3], [1e-3, 1e-4]]
    else:
        Y[0, 0, 0] = np.nan
        cov[0, 0, 0, 0, 0] = -1.0
    out = run_guarded(lambda: demultiplex(Y, cov, patterns))
    if case.endswith("(unused)"):
        assert judge(out, refuse=False) == [] and out["exc"] is None
    else:
        assert judge(out) == [] and "Y_cov" in str(out["exc"])


# ---------------------------------------------------------------------- the opening rule itself


def test_read_bounded_stops_at_the_limit_of_a_file_sized_zero():
    from torchblur.errors import ParameterError
    from torchblur.files import read_bounded

    assert os.stat("/proc/self/status").st_size == 0  # the kernel sizes it 0: only the bounded read can stop it
    with pytest.raises(ParameterError, match="larger than the 16 bytes"):
        read_bounded("/proc/self/status", 16, "status")
    assert read_bounded("/proc/self/status", 1 << 20, "status").startswith(b"Name:")


def test_excerpt_is_short_and_printable():
    from torchblur.errors import excerpt

    e = excerpt("ab\x00\n" + "x" * 100)
    assert e == repr("ab??" + "x" * (EXCERPT_CHARS - 4)) + "..." and "\n" not in e
    assert excerpt(1e300) == "1e+300" and excerpt(b"\xff\xfeok") == repr("??ok")
