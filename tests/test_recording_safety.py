"""Issue 16: a recording is untrusted input, nothing recorded is ever lost, a run folder is
owned. The fault battery: tampered recordings (paths, pages, hashes, fields, configs,
experiment.json), every manifest line corrupted or duplicated then repaired, two processes
on one run folder. Seeded, CPU, fast (small hand-made recordings)."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from torchblur.errors import TorchblurError
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.frames import CameraInfo
from torchblur.hardware.recording import Experiment
from torchblur.rig.base import Capture

INFO = CameraInfo(frame_shape=(6, 5), frame_rate_hz=30.0, max_exposure_s=1.0, readout_s=1e-3, name="unit")
ROOT = Path(__file__).resolve().parents[1]

# ---------------------------------------------------------------------- reads outside a run

_OPENED: list[str] = []
_WATCH: list[bool] = [False]


def _audit(event, args):
    if _WATCH[0] and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.fsdecode(args[0]))


sys.addaudithook(_audit)


def cap(n, shape=None, start=0, value=100.0):
    shape = shape or (n,)
    N = int(np.prod(shape))
    # each frame its own pixels (a frame repeated byte for byte is refused as a copy): + 7 per frame, + 3 per start
    ramp = torch.arange(N * 30, dtype=torch.float64) % 50 + 7 * torch.arange(N, dtype=torch.float64).repeat_interleave(30) + 3 * start
    frames = (value + ramp.reshape(shape + (6, 5))).round()
    return Capture(frames=frames, exposure_s=torch.full(shape, 1e-3, dtype=torch.float64),
                   trigger_offset_s=torch.zeros(shape, dtype=torch.float64),
                   trigger_time_s=torch.arange(N, dtype=torch.float64).reshape(shape) * 0.04,
                   frame_counter=torch.arange(start, start + N).reshape(shape), meta={"kind": "x", "power": 0.5})


def make_recording(path: Path) -> Path:
    """A small recording: dark (3 frames), two sweep points (2x2 frames each)."""
    exp = Experiment.create(path, config_yaml="seed: 3\n", camera=INFO)
    exp.start_session({"kind": "test"})
    exp.record("dark", "dark", [("dark", {"n": 3, "exposure_s": 1e-3}, cap(3))])
    for k, f in enumerate((5.0, 50.0)):
        exp.record(f"sweep/x/{k:03d}", "sweep", [("sine", {"freq_hz": f, "amplitude": 0.3, "power": 0.5}, cap(4, (2, 2), start=3 + 4 * k, value=10.0 * k))],
                   labels={"input": "x", "freq_hz": f, "amplitude": 0.3, "power": 0.5, "point": k, "attempts": 1})
    exp.end_session("complete")
    return path


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return make_recording(tmp_path_factory.mktemp("rec") / "e")


def read_everything(d: Path):
    """Everything a re-fit reads: each group's calls, every frame, the config (untrusted).
    Returns a digest of the data read."""
    from torchblur.config import load_dataclass, IdentifyConfig

    exp = Experiment.open(d, writable=False)
    h = hashlib.sha256()
    for g in exp.groups:
        for m, args, c in exp.load_calls(g):
            h.update(m.encode() + json.dumps(args, sort_keys=True).encode() + c.frames.numpy().tobytes())
            h.update(str(tuple(c.frames.shape)).encode())
            h.update(c.exposure_s.numpy().tobytes() + c.frame_counter.numpy().tobytes())
    h.update(json.dumps([{k: r[k] for k in ("group", "page", "amplitude", "freq_hz", "exposure_s") if k in r}
                         for r in exp.lines], sort_keys=True).encode())
    cfg = load_dataclass(IdentifyConfig, str(exp.path / "config.yaml"), trusted=False)
    h.update(repr(cfg).encode())
    return h.hexdigest()


def lines_of(d):
    return [json.loads(x) for x in (d / "manifest.jsonl").read_text().splitlines()]


def write_lines(d, lines):
    (d / "manifest.jsonl").write_text("".join(json.dumps(ln) + "\n" for ln in lines))


def edit(i, **fields):
    def f(d):
        ls = lines_of(d)
        ls[i].update(fields)
        write_lines(d, ls)
    return f


def edit_group(which, **fields):
    def f(d):
        ls = lines_of(d)
        for ln in ls:
            if ln["group"] == which:
                ln.update(fields)
        write_lines(d, ls)
    return f


def raw_line(i, data: bytes):
    def f(d):
        raw = (d / "manifest.jsonl").read_bytes().split(b"\n")
        raw[i] = data
        (d / "manifest.jsonl").write_bytes(b"\n".join(raw))
    return f


def outside_copy(d):
    """A copy of dark.tif outside the run (same bytes, same hash)."""
    out = d.parent.parent / "outside"
    out.mkdir(exist_ok=True)
    shutil.copy(d / "frames" / "dark.tif", out / "dark.tif")
    return out / "dark.tif"


def file_abs(d):
    edit_group("dark", file=str(outside_copy(d)))(d)


def file_rel(rel):
    def f(d):
        outside_copy(d)
        edit_group("dark", file=rel)(d)
    return f


def symlink_frame(d):
    target = outside_copy(d)
    (d / "frames" / "dark.tif").unlink()
    (d / "frames" / "dark.tif").symlink_to(target)


def symlink_frames_dir(d):
    out = d.parent.parent / "outside_frames"
    shutil.copytree(d / "frames", out)
    shutil.rmtree(d / "frames")
    (d / "frames").symlink_to(out)


def symlink_file(name):
    def f(d):
        out = d.parent.parent / ("outside_" + name)
        shutil.copy(d / name, out)
        (d / name).unlink()
        (d / name).symlink_to(out)
    return f


def other_group_file(d):
    edit_group("dark", file="frames/sweep_x_000.tif")(d)


def flip_tiff(d):
    f = d / "frames" / "sweep_x_001.tif"
    b = bytearray(f.read_bytes())
    b[-3] ^= 0xFF
    f.write_bytes(bytes(b))


def consistent_swap_tiff(d):
    """Another valid TIFF (2 frames) in place of dark's, the manifest's hashes updated."""
    import io

    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.zeros((2, 6, 5), np.uint16))
    (d / "frames" / "dark.tif").write_bytes(buf.getvalue())
    edit_group("dark", sha256=hashlib.sha256(buf.getvalue()).hexdigest())(d)


def nan_tiff(d):
    import io

    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.full((3, 6, 5), np.nan))
    (d / "frames" / "dark.tif").write_bytes(buf.getvalue())
    edit_group("dark", sha256=hashlib.sha256(buf.getvalue()).hexdigest(), dtype="float64")(d)


def config_text(text):
    def f(d):
        (d / "config.yaml").write_text(text)
    return f


def meta_edit(fn):
    def f(d):
        p = d / "experiment.json"
        m = json.loads(p.read_text())
        fn(m)
        p.write_text(json.dumps(m))
    return f


def meta_bytes(b):
    def f(d):
        (d / "experiment.json").write_bytes(b)
    return f


def nan_amplitude(d):
    p = d / "manifest.jsonl"
    p.write_text(p.read_text().replace('"amplitude":0.3', '"amplitude":NaN', 4))


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefg", "bcdefgh"))

# (name, tampering); line 0 is dark page 0, lines 3..6 sweep/x/000, 7..10 sweep/x/001
CASES = [
    # paths
    ("file absolute", file_abs),
    ("file ../", file_rel("../../outside/dark.tif")),
    ("file frames/../..", file_rel("frames/../../../outside/dark.tif")),
    ("file backslash", edit_group("dark", file="frames\\dark.tif")),
    ("file not a string", edit_group("dark", file=123)),
    ("file empty", edit_group("dark", file="")),
    ("file of another group", other_group_file),
    ("frame file a symlink out", symlink_frame),
    ("frames/ a symlink out", symlink_frames_dir),
    ("manifest a symlink out", symlink_file("manifest.jsonl")),
    ("config a symlink out", symlink_file("config.yaml")),
    ("group key climbs", edit_group("dark", group="../etc")),
    # pages
    ("page -1", edit(4, page=-1)),
    ("page past the file", edit(4, page=4)),
    ("page float", edit(4, page=1.0)),
    ("page string", edit(4, page="1")),
    ("page bool", edit(4, page=True)),
    ("second line on a page", edit(5, page=3)),
    ("index out of range", edit(5, index=9)),
    ("call_shape wrong", edit_group("sweep/x/000", call_shape=[3])),
    ("call_shape not a list", edit(5, call_shape="2x2")),
    ("group_frames zero", edit_group("dark", group_frames=0)),
    ("group_frames huge", edit_group("dark", group_frames=10**12)),
    # hashes
    ("sha256 of a later line", edit(6, sha256="0" * 64)),
    ("sha256 of a whole group", edit_group("sweep/x/000", sha256="1" * 64)),
    ("sha256 not hex", edit_group("dark", sha256="xyz")),
    ("TIFF bytes flipped", flip_tiff),
    ("TIFF swapped, hash updated", consistent_swap_tiff),
    ("NaN pixels, hash updated", nan_tiff),
    # fields
    ("amplitude -1", edit_group("sweep/x/000", amplitude=-1.0)),
    ("amplitude 0", edit_group("sweep/x/000", amplitude=0.0)),
    ("amplitude NaN", nan_amplitude),
    ("amplitude 1e300", edit_group("sweep/x/000", amplitude=1e300)),
    ("amplitude differs from args", edit_group("sweep/x/001", amplitude=0.6)),
    ("amplitude string", edit_group("sweep/x/000", amplitude="0.3")),
    ("freq_hz negative", edit_group("sweep/x/000", freq_hz=-5.0)),
    ("freq_hz differs from args", edit_group("sweep/x/001", freq_hz=51.0)),
    ("power NaN-like string", edit_group("sweep/x/000", power="nan")),
    ("exposure_s zero", edit(1, exposure_s=0.0)),
    ("exposure_s negative", edit(1, exposure_s=-1e-3)),
    ("method unknown", edit_group("dark", method="rm")),
    ("kind differs in a group", edit(1, kind="psf")),
    ("dtype object", edit_group("dark", dtype="object")),
    ("frame_counter string", edit(1, frame_counter="7")),
    ("timestamp_s string", edit(1, trigger_time_s="soon")),
    ("args not an object", edit(1, args=[1, 2])),
    ("line a JSON list", raw_line(1, b"[1, 2, 3]")),
    ("line deeply nested", raw_line(1, b"[" * 5000 + b"]" * 5000)),
    ("line 100 kB", raw_line(1, b'{"group": "dark", "x": "' + b"a" * 100_000 + b'"}')),
    ("line binary", raw_line(1, bytes(range(256)))),
    ("line a huge integer", raw_line(1, b'{"group": "dark", "page": ' + b"9" * 5000 + b"}")),
    # configs
    ("config oc.env", config_text("seed: ${oc.env:HOME}\n")),
    ("config interpolation", config_text("seed: 3\nrig:\n  port: ${seed}\n")),
    ("config YAML bomb", config_text(BOMB)),
    ("config recursive alias", config_text("a: &a [*a]\n")),
    ("config binary", lambda d: (d / "config.yaml").write_bytes(bytes(range(256)) * 4)),
    ("config 2 MB", config_text("# " + "x" * 2_000_000 + "\nseed: 3\n")),
    ("config a list", config_text("- 1\n- 2\n")),
    ("config unknown key", config_text("seed: 3\nsecret: 1\n")),
    # experiment.json
    ("experiment.json empty", meta_bytes(b"")),
    ("experiment.json binary", meta_bytes(bytes(range(256)))),
    ("experiment.json nested", meta_bytes(b"[" * 100_000 + b"]" * 100_000)),
    ("experiment.json a list", meta_bytes(b"[1]")),
    ("schema_version a string", meta_edit(lambda m: m.update(schema_version="1"))),
    ("camera missing", meta_edit(lambda m: m.pop("camera"))),
    ("frame_shape negative", meta_edit(lambda m: m["camera"].update(frame_shape=[-6, 5]))),
    ("frame_shape huge", meta_edit(lambda m: m["camera"].update(frame_shape=[10**6, 10**6]))),
    ("frame_shape wrong", meta_edit(lambda m: m["camera"].update(frame_shape=[5, 6]))),
    ("frame_rate NaN", meta_edit(lambda m: m["camera"].update(frame_rate_hz=float("nan")))),
]


@pytest.fixture(scope="module")
def reference(pristine):
    return read_everything(pristine)


def _outside_reads(d: Path) -> list:
    run = os.path.realpath(d)
    return [p for p in _OPENED if "outside" in p or (p.startswith(str(d.parent)) and not os.path.realpath(p).startswith(run))]


@pytest.mark.parametrize("name,tamper", CASES, ids=[c[0] for c in CASES])
def test_tampered_recording_is_refused_or_read_unchanged(name, tamper, pristine, reference, tmp_path):
    """Every tampered recording gives a clear TorchblurError or exactly the original data:
    no read outside the run, no silent wrong result, no other exception."""
    d = tmp_path / "run" / "e"
    shutil.copytree(pristine, d)
    tamper(d)
    _OPENED.clear()
    _WATCH[0] = True
    try:
        digest = read_everything(d)
    except TorchblurError as exc:
        digest = None
        assert str(exc) and "\n" not in str(exc)
    finally:
        _WATCH[0] = False
    assert _outside_reads(d) == [], f"{name}: read outside the run"
    assert digest in (None, reference), f"{name}: a silent wrong result"


def test_battery_has_enough_cases():
    assert len(CASES) >= 40


def test_fit_of_a_recording_with_an_env_interpolation_is_refused(pristine, tmp_path, monkeypatch):
    """The CLI: `torchblur fit` of a recording whose config asks for an environment
    variable is one line and exit 2; the secret never reaches the output."""
    from torchblur import cli

    d = tmp_path / "run" / "e"
    shutil.copytree(pristine, d)
    (d / "config.yaml").write_text("seed: 3\nrig:\n  port: ${oc.env:TB_SECRET}\n")
    monkeypatch.setenv("TB_SECRET", "hunter2")
    assert cli.main(["fit", str(d), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert not any("hunter2" in p.read_text(errors="replace") for p in tmp_path.rglob("*") if p.is_file())


# ---------------------------------------------------------------------- repair loses nothing


def _frame_hashes(d: Path) -> set:
    return {hashlib.sha256(p.read_bytes()).hexdigest() for p in d.rglob("*.tif")}


def _n_lines(d):
    return len((d / "manifest.jsonl").read_bytes().splitlines())


@pytest.mark.parametrize("mode", ["truncate", "garbage", "duplicate", "delete"])
def test_damaging_any_single_line_loses_no_frame(mode, pristine, tmp_path):
    """Each manifest line damaged in turn: the repair keeps every TIFF (in frames/ or in
    quarantine/), keeps every group the damage does not touch, sets the rest aside with
    a reason naming it, and a duplicated line costs nothing."""
    before = _frame_hashes(pristine)
    groups = ["dark", "sweep/x/000", "sweep/x/001"]
    owner = ["dark"] * 3 + ["sweep/x/000"] * 4 + ["sweep/x/001"] * 4
    for i in range(_n_lines(pristine)):
        d = tmp_path / f"{i}" / "e"
        shutil.copytree(pristine, d)
        raw = (d / "manifest.jsonl").read_bytes().split(b"\n")
        if mode == "truncate":
            raw[i] = raw[i][: len(raw[i]) // 2]
        elif mode == "garbage":
            raw[i] = b"\x00\xff garbage"
        elif mode == "duplicate":
            raw.insert(i, raw[i])
        else:
            del raw[i]
        (d / "manifest.jsonl").write_bytes(b"\n".join(raw))
        exp = Experiment.open(d)
        exp.close()
        assert _frame_hashes(d) == before, (mode, i)  # nothing lost, nothing altered
        if mode == "duplicate":
            assert set(exp.groups) == set(groups) and exp.repaired["dropped_groups"] == []
            continue
        assert exp.repaired["dropped_groups"] == [owner[i]], (mode, i)
        assert set(exp.groups) == set(groups) - {owner[i]}
        q = Path(exp.repaired["quarantine"])
        assert (q / "frames" / (owner[i].replace("/", "_") + ".tif")).is_file()
        assert owner[i] in json.loads((q / "reasons.json").read_text())["groups"]
        again = Experiment.open(d)  # repaired: nothing more to do
        assert again.repaired["dropped_groups"] == [] and again.repaired["quarantine"] is None
        again.close()


def test_resume_after_a_damaged_line_retakes_only_the_lost_group(pristine, tmp_path):
    """After the repair, recording the set-aside group again writes only it."""
    d = tmp_path / "e"
    shutil.copytree(pristine, d)
    raw = (d / "manifest.jsonl").read_bytes().split(b"\n")
    raw[4] = raw[4][:30]
    (d / "manifest.jsonl").write_bytes(b"\n".join(raw))
    exp = Experiment.open(d)
    assert sorted(exp.groups) == ["dark", "sweep/x/001"]
    exp.start_session({"kind": "test"})
    exp.record("sweep/x/000", "sweep", [("sine", {"freq_hz": 5.0, "amplitude": 0.3, "power": 0.5}, cap(4, (2, 2), start=3))],
               labels={"input": "x", "freq_hz": 5.0, "amplitude": 0.3, "power": 0.5, "point": 0, "attempts": 1})
    exp.end_session("complete")
    assert exp.stats["groups_written"] == 1
    assert read_everything(d) is not None and _frame_hashes(pristine) <= _frame_hashes(d)


# ---------------------------------------------------------------------- an owned run folder

_HOLD = textwrap.dedent("""
    import sys, time
    from torchblur.hardware.run_folder import RunLock
    lock = RunLock(sys.argv[1])
    print("locked", flush=True)
    time.sleep(60)
""")


def test_two_processes_cannot_write_one_run(pristine, tmp_path):
    d = tmp_path / "e"
    shutil.copytree(pristine, d)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(d)], stdout=subprocess.PIPE, env=env, text=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        with pytest.raises(RecordingError, match=f"pid {p.pid}"):
            Experiment.open(d)
        Experiment.open(d, writable=False)  # reading is fine
    finally:
        p.kill()
        p.wait()
    exp = Experiment.open(d)  # the holder died: its lock went with it
    exp.close()


_TRY = textwrap.dedent("""
    import sys
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.run_folder import RunLock
    try:
        RunLock(sys.argv[1])
        print("locked")
    except RecordingError as exc:
        print("refused:", exc)
""")


def test_identify_holds_the_run_lock_and_a_second_identify_refuses(tmp_path, monkeypatch, capsys):
    """`torchblur identify --out SAME`: while one runs, another process cannot lock the
    folder; a second identify on a folder another process holds exits 2 with one line."""
    from torchblur import cli
    from torchblur.cli import commands

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    seen = []

    def run(cfg, out, record, quiet, root=None, **options):  # options: as_json
        seen.append(subprocess.run([sys.executable, "-c", _TRY, str(record)], capture_output=True, text=True, env=env).stdout)
        return 0

    monkeypatch.setattr(commands, "_run_identify", run)
    assert cli.main(["identify", "--out", str(tmp_path / "same"), "--quiet", "sweep.freq_hz=[5]"]) == 0
    assert seen and seen[0].startswith("refused:") and f"pid {os.getpid()}" in seen[0]
    (tmp_path / "same2" / "experiment").mkdir(parents=True)
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path / "same2" / "experiment")], stdout=subprocess.PIPE,
                         env=env, text=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        assert cli.main(["identify", "--out", str(tmp_path / "same2"), "--quiet", "sweep.freq_hz=[5]"]) == 2
        err = capsys.readouterr().err
        assert f"pid {p.pid}" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    finally:
        p.kill()
        p.wait()
    assert len(seen) == 1  # the refused run never started


def test_out_inside_another_run_is_refused(pristine, tmp_path):
    from torchblur.hardware.run_folder import check_out_folder

    run = tmp_path / "R"
    shutil.copytree(pristine, run / "experiment")
    (run / "frf.json").write_text("{}")
    for bad in (run / "experiment", run / "experiment" / "sub"):
        with pytest.raises(RecordingError, match="record of the run"):
            check_out_folder(bad, command="identify")
    with pytest.raises(RecordingError, match="inside the run folder"):
        check_out_folder(run / "sub", command="fit")
    with pytest.raises(RecordingError, match="--force"):
        check_out_folder(run, command="fit")
    assert check_out_folder(run, command="fit", force=True) == run.resolve()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(RecordingError, match="is a file"):
        check_out_folder(tmp_path / "afile", command="identify")
    with pytest.raises(RecordingError, match="under the file"):
        check_out_folder(tmp_path / "afile" / "x", command="identify")
    assert check_out_folder(run, command="identify", own_run=run) == run.resolve()


def test_a_kill_during_the_repair_loses_nothing(pristine, tmp_path, monkeypatch):
    """Killed after setting frames aside but before the manifest is rewritten: the next
    open repairs again and every frame is still there."""
    from torchblur.hardware import recording

    before = _frame_hashes(pristine)
    d = tmp_path / "e"
    shutil.copytree(pristine, d)
    raw = (d / "manifest.jsonl").read_bytes().split(b"\n")
    raw[4] = raw[4][:20]
    (d / "manifest.jsonl").write_bytes(b"\n".join(raw))
    real = recording.atomic_write_bytes

    def killed(path, data, **kw):
        if Path(path).name == "manifest.jsonl" and "quarantine" not in str(path):
            raise KeyboardInterrupt
        return real(path, data, **kw)

    monkeypatch.setattr(recording, "atomic_write_bytes", killed)
    with pytest.raises(KeyboardInterrupt):
        Experiment.open(d)
    monkeypatch.undo()
    assert _frame_hashes(d) == before
    exp = Experiment.open(d)
    exp.close()
    assert exp.repaired["dropped_groups"] == ["sweep/x/000"] and _frame_hashes(d) == before
    assert sorted(exp.groups) == ["dark", "sweep/x/001"]


def test_a_quarantine_symlinked_out_of_the_run_is_refused(pristine, tmp_path):
    d = tmp_path / "run" / "e"
    shutil.copytree(pristine, d)
    (tmp_path / "elsewhere").mkdir()
    (d / "quarantine").symlink_to(tmp_path / "elsewhere")
    raw = (d / "manifest.jsonl").read_bytes().split(b"\n")
    raw[4] = raw[4][:20]
    (d / "manifest.jsonl").write_bytes(b"\n".join(raw))
    with pytest.raises(RecordingError, match="quarantine"):
        Experiment.open(d)
    assert list((tmp_path / "elsewhere").iterdir()) == [] and _frame_hashes(d) == _frame_hashes(pristine)
