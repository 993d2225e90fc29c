"""Issue 16: limits before work, every config value range-checked with its key named, and
every CLI failure one line (exit 2 bad input) without a traceback."""
from __future__ import annotations

import json
import shutil

import pytest

from torchblur.errors import ConfigError
from torchblur import cli
from torchblur.config import LIMITS, check_limits, estimate_run, load_config


@pytest.mark.parametrize("override,key", [
    ("sweep.n=1e7", "sweep.n"),
    ("excitation.target_px=1e9", "excitation.target_px"),
    ("sweep.images_per_point=1e6", "sweep.images_per_point"),
    ("camera.height=1e6", "camera.height"),
])
def test_huge_runs_are_refused_with_the_estimate(override, key):
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    msg = str(info.value)
    assert msg.startswith(key + ":") and "estimate:" in msg and "frames" in msg and "--force" in msg


def test_force_goes_past_the_limits_and_the_estimate_is_sane():
    cfg = load_config(None, ["sweep.n=1e7"], force=True)
    assert cfg.sweep.n == 10_000_000 and isinstance(cfg.sweep.n, int)
    est = estimate_run(cfg)
    assert est["frames"] == 10_000_000 * 2 * 2 + 100 and est["frames"] > LIMITS["frames"]
    base = check_limits(load_config())  # the default run: well inside every limit
    assert base["frames"] == 30 * 2 * 2 + 100 and base["disk_bytes"] == 2 * base["frames"] * 64 * 64
    assert 0 < base["bench_s"] < LIMITS["bench_s"] and base["memory_bytes"] < LIMITS["memory_bytes"]


@pytest.mark.parametrize("override,key", [
    ("seed=1e20", "seed"),
    ("seed=-1", "seed"),
    ("sweep.n=2.5", "sweep.n"),
    ("camera.height=64.5", "camera.height"),
    ("camera.psf_sigma_px=1e-6", "camera.psf_sigma_px"),
    ("spots.rows=2", None),  # valid: a control
    ("plant.num=[" + ",".join(["1"] * 10_000) + "]", "plant.num"),
    ("sweep.exposures=[" + ",".join(["0.1"] * 10_000) + "]", "sweep.exposures"),
    ("sweep.freq_hz=[" + ",".join(["10"] * 10_000) + "]", "sweep.freq_hz"),
    ("spots.missing=[" + ",".join(["0"] * 10_000) + "]", "spots.missing"),
])
def test_config_values_are_range_checked_by_key(override, key):
    if key is None:
        load_config(None, [override, "spots.cols=2", "camera.height=96", "camera.width=96", "spots.pitch_px=40"])
        return
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    assert str(info.value).startswith(key), str(info.value)[:200]


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefg", "bcdefgh"))


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


@pytest.mark.parametrize("what", ["bomb", "recursive", "binary", "a list", "missing", "a folder"])
def test_cli_bad_config_files_are_one_line(what, tmp_path, capsys):
    p = tmp_path / "c.yaml"
    if what == "bomb":
        p.write_text(BOMB)
    elif what == "recursive":
        p.write_text("a: &a [*a]\n")
    elif what == "binary":
        p.write_bytes(bytes(range(256)) * 8)
    elif what == "a list":
        p.write_text("- 1\n")
    elif what == "a folder":
        p.mkdir()
    assert cli.main(["identify", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    assert str(p) in _one_line(capsys)
    assert not (tmp_path / "o").exists()


def test_cli_out_paths_are_checked_before_work(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("x")
    for out in (f, f / "sub"):
        assert cli.main(["identify", "--out", str(out), "sweep.freq_hz=[5]"]) == 2
        assert "--out" in _one_line(capsys)
    assert cli.main(["identify", "--out", str(tmp_path / "big"), "sweep.n=1e7"]) == 2
    assert "sweep.n" in _one_line(capsys) and not (tmp_path / "big").exists()


def test_cli_out_inside_a_run_and_fit_over_results(tmp_path, capsys):
    from test_recording_safety import make_recording

    run = tmp_path / "R"
    make_recording(run / "experiment")
    (run / "frf.json").write_text("{}")
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert cli.main(["identify", "--out", str(run / "experiment"), "sweep.freq_hz=[5]"]) == 2
    assert "record of the run" in _one_line(capsys)
    assert cli.main(["fit", str(run), "--out", str(run)]) == 2
    assert "--force" in _one_line(capsys)
    other = tmp_path / "other"
    other.mkdir()
    (other / "model.json").write_text("{}")
    assert cli.main(["fit", str(run), "--out", str(other)]) == 2
    assert "--force" in _one_line(capsys)
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != "run.lock"} == \
        {p: b for p, b in before.items() if p.name != "run.lock"}


def test_cli_resume_of_a_locked_run_is_refused(tmp_path, capsys):
    import os
    import subprocess
    import sys
    from pathlib import Path

    from test_recording_safety import _HOLD, make_recording

    run = tmp_path / "R"
    make_recording(run / "experiment")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(run / "experiment")], stdout=subprocess.PIPE, env=env, text=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        assert cli.main(["identify", "--resume", str(run)]) == 2
        assert f"pid {p.pid}" in _one_line(capsys)
    finally:
        p.kill()
        p.wait()


def test_cli_tampered_recording_is_one_line(tmp_path, capsys):
    from test_recording_safety import make_recording

    run = tmp_path / "R"
    make_recording(run / "experiment")
    m = run / "experiment" / "manifest.jsonl"
    lines = [json.loads(x) for x in m.read_text().splitlines()]
    lines[1]["page"] = -1
    m.write_text("".join(json.dumps(ln) + "\n" for ln in lines))
    assert cli.main(["fit", str(run), "--out", str(tmp_path / "o")]) == 2
    assert "page" in _one_line(capsys)
    shutil.rmtree(run / "experiment" / "frames")
    (run / "experiment" / "experiment.json").write_bytes(b"\x00\xff")
    assert cli.main(["fit", str(run), "--out", str(tmp_path / "o2")]) == 2
    assert "experiment.json" in _one_line(capsys)


def test_cli_resume_of_a_read_only_run_is_one_line(tmp_path, capsys, monkeypatch):
    """(Checked through os.access: a test running as root cannot make a folder read-only.)"""
    import os

    from test_recording_safety import make_recording

    run = tmp_path / "R"
    make_recording(run / "experiment")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p).endswith("experiment") else real(p, mode, **kw))
    assert cli.main(["identify", "--resume", str(run)]) == 2
    assert "not writable" in _one_line(capsys)
