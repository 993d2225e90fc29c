"""Every file a run writes reads back (:mod:`torchblur.identify.read_outputs`), and the command's
first-hour messages: a finished run's --resume, a missing folder, a mistyped option, Ctrl-C
outside a run's own handler, ``torchblur config``."""
import json

import pytest

import torchblur as tb
from torchblur.errors import ConfigError, ParameterError
from torchblur import cli
from torchblur.config import load_config
from torchblur.config.keys import config_keys, unit_of
from torchblur.identify.read_outputs import check_document, read_outputs
from readback import assert_reads_back


def _listing(folder):
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def test_the_default_runs_outputs_read_back(small_quiet_run):
    out, _ = small_quiet_run  # identify --out OUT --quiet, 4 frequencies (tests/conftest.py)
    got = assert_reads_back(out)
    model = tb.TransferFunctionFit.from_json(out / "model.json")  # the CLI's model.json, with its extra keys
    doc = json.loads((out / "model.json").read_text())
    assert doc["schema_version"] == 2 and doc["left_out_points"] == [] and doc["units"]["delay_s"] == "s"
    assert model.to_dict() == got["model.json"].to_dict() and got["frf.json"].input_labels == ("u_x",)
    assert json.loads((out / "frf.json").read_text())["units"]["phase"] == "rad"


def test_config_yaml_has_a_schema_version_and_older_ones_read(small_quiet_run, tmp_path):
    out, _ = small_quiet_run
    text = (out / "config.yaml").read_text()
    body = [ln for ln in text.splitlines(True) if not ln.startswith("#")]
    assert body[:2] == ["schema: torchblur.config\n", "schema_version: 1\n"]
    cfg = load_config(str(out / "config.yaml"), force=True)
    older = tmp_path / "older" / "config.yaml"  # a run's config.yaml from before the schema lines: version 1
    older.parent.mkdir()
    older.write_text("".join(body[2:]))
    assert read_outputs(older.parent)["config.yaml"] == cfg
    newer = tmp_path / "newer" / "config.yaml"
    newer.parent.mkdir()
    newer.write_text(text.replace("schema_version: 1", "schema_version: 2"))
    with pytest.raises(ConfigError, match=r"newer/config.yaml: schema_version: unsupported version 2 \(written by a newer torchblur"):
        read_outputs(newer.parent)
    newer.write_text(text.replace("schema: torchblur.config", "schema: torchblur.source"))
    with pytest.raises(ConfigError, match=r"schema: expected 'torchblur.config' in .*, got 'torchblur.source'"):
        load_config(str(newer))


def test_every_shipped_config_has_a_test_that_reads_its_outputs_back():
    """configs/identify_*.yaml and readback.READBACK_TESTS name the same configs, and each named
    test exists and calls assert_reads_back (a new config needs its reduced run read back)."""
    import re
    from pathlib import Path

    from readback import READBACK_TESTS

    root = Path(__file__).resolve().parents[1]
    assert {p.name for p in (root / "configs").glob("identify_*.yaml")} == set(READBACK_TESTS)
    for config, where in READBACK_TESTS.items():
        file, name = where.split("::")
        body = re.search(rf"^def {name}\(.*?(?=^\S)", (root / "tests" / file).read_text() + "\nEND", re.S | re.M)
        assert body, where
        assert "assert_reads_back(" in body.group(0), where


def test_a_newer_document_is_refused_by_name():
    with pytest.raises(ParameterError, match=r"here: schema_version: unsupported version 9 \(written by a newer torchblur"):
        check_document({"schema": "torchblur.source", "schema_version": 9}, ("torchblur.source", (1,)), "here")
    with pytest.raises(ParameterError, match="here: schema: expected 'torchblur.source', got None"):
        check_document({}, ("torchblur.source", (1,)), "here")


def test_resume_of_a_finished_run_says_so_and_changes_nothing(small_quiet_run, capsys):
    out, _ = small_quiet_run
    before = _listing(out)
    assert cli.main(["identify", "--resume", str(out)]) == 0
    err = capsys.readouterr().err
    assert "is a finished run" in err and "nothing to resume" in err and f"torchblur fit {out} --out NEW" in err
    assert _listing(out) == before


def test_a_missing_folder_does_not_exist(tmp_path, capsys):
    for argv in (["fit", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")], ["identify", "--resume", str(tmp_path / "nowhere")]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].endswith(f"{tmp_path / 'nowhere'}: does not exist"), err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, hint", [(["identify", "--output", "x"], "--output: did you mean --out?"),
                                        (["fit", "run", "--output", "x"], "--output: did you mean --out?"),
                                        (["identfy", "--out", "x"], "identfy: did you mean identify?"),
                                        (["identify", "--confg=a.yaml"], "--confg: did you mean --config?")])
def test_a_mistyped_option_or_command_suggests_the_close_one(argv, hint, capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(argv)
    assert done.value.code == 2 and hint in capsys.readouterr().err


def test_ctrl_c_before_a_run_is_one_line_saying_what_to_run(tmp_path, monkeypatch, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    for command in ("commands", "tools"):  # where the identify and config commands load it
        monkeypatch.setattr(f"torchblur.cli.{command}.load_config", interrupted)
    monkeypatch.setattr("torchblur.config.load_config", interrupted)
    assert cli.main(["identify", "--out", str(tmp_path / "r")]) == cli.EXIT_INTERRUPTED
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == ["torchblur identify: interrupted before anything was recorded; run the same command again to start over"]
    assert cli.main(["config"]) == cli.EXIT_INTERRUPTED
    assert [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()] == ["torchblur config: interrupted"]


def test_torchblur_config_lists_every_key_with_its_value_and_unit(capsys):
    assert cli.main(["config", "--config", "configs/identify_mimo.yaml", "sweep.n=7"]) == 0
    lines = capsys.readouterr().out.splitlines()
    keys = config_keys(load_config("configs/identify_mimo.yaml", ["sweep.n=7"], force=True))
    assert [ln.split(" = ")[0] for ln in lines] == [k for k, _, _ in keys]
    assert "sweep.n = 7" in lines and any(ln.startswith("sweep.f_max_hz = ") and ln.endswith("# Hz") for ln in lines)
    assert unit_of("camera.gain") == "e-/ADU" and unit_of("camera.latency_s") == "s" and unit_of("fit.loss") == "-"
    assert not cli.main(["config", "sweep.nn=3"]) == 0
    assert "sweep.nn" in capsys.readouterr().err


def test_demo_writes_a_figure_and_a_json_that_reads_back(tmp_path, capsys):
    assert cli.main(["demo", "--out", str(tmp_path)]) == 0
    doc = read_outputs(tmp_path)["demo.json"]
    assert doc["max_abs_difference_true_vs_alias_image"] < 1e-9 * doc["image_peak"]  # the alias renders the same image
    assert doc["alias_phase_rad"] != doc["phase_rad"] and (tmp_path / "demo.png").stat().st_size > 10_000
    assert "render the same image" in capsys.readouterr().out
