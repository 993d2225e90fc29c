"""What `torchblur identify` prints and writes (issue 18, items 6-8): log lines once each through
the `torchblur` logger, no progress-bar junk off a terminal, `--version`, `--json` (one summary
line, alone on stdout), frf.mat, units in the response's meta, residuals.png's exposures."""
import json
import logging
import os
import sys

import numpy as np
import pytest

from torchblur.identify import record
from torchblur.identify.record import collect_log
from torchblur.identify.pipeline import calibration_stages
from torchblur.config import load_config
from torchblur.sysid.frequency_response import FrequencyResponse
from cli_run import ROOT, SMALL


# a smaller run than SMALL (2 points, a 32 x 32 frame): what is checked is how the messages reach stderr
FROM_PYTHON = ["sweep.freq_hz=[20,200]", "camera.height=32", "camera.width=32"]


def BACKGROUND_JOB(out, started):
    """This module's fresh processes (``torchblur identify --json``, ``torchblur --version``, identify from
    Python), run in the background by tests/background.py -> ``{name: result}``."""
    from background import run

    cli, env = [sys.executable, "-m", "torchblur.cli"], {"PYTHONPATH": str(ROOT)}
    run_out = out / "run"  # no test here looks at figures
    code = ("from torchblur.config import load_config; from torchblur.identify.pipeline import identify; "
            f"identify(load_config(None, {FROM_PYTHON!r}), progress=True)")
    return {"json_run": (run_out, run([*cli, "identify", "--out", str(run_out), "--json", *SMALL, "report.figures=false"], started, env=env)),
            "version": run([*cli, "--version"], started, env=env),
            "from_python": run([sys.executable, "-c", code], started, env=env)}


@pytest.fixture(scope="module")
def fresh(background, request):
    """This module's fresh processes (:func:`BACKGROUND_JOB`) -> ``{name: result}``."""
    return background.get(request.module.__name__)


@pytest.fixture(scope="module")
def json_run(fresh):
    out, proc = fresh["json_run"]
    assert proc.returncode == 0, proc.stderr
    return out, proc


def test_version(fresh):
    import torchblur

    proc = fresh["version"]
    assert proc.returncode == 0 and proc.stdout == f"torchblur {torchblur.__version__}\n"


def test_json_is_the_only_line_on_stdout(json_run):
    out, proc = json_run
    lines = proc.stdout.splitlines()
    assert len(lines) == 1
    doc = json.loads(lines[0])
    assert doc["out"] == str(out) and doc["points"] == 4 and doc["valid_points"] == 4
    assert doc["schema"] == "torchblur.run_summary" and doc["schema_version"] == 1
    assert doc["status"] == {"ok": 4} and isinstance(doc["flags"], dict)
    assert 0 <= doc["max_magnitude_error_pct"] < 1 and 0 <= doc["max_phase_error_deg"] < 1  # the simulated truth is known
    assert doc["elapsed_s"] > 0 and doc["torchblur_version"]
    assert "against the truth" in proc.stderr and "wrote " in proc.stderr  # the human part went to stderr


def test_each_log_line_is_printed_once_without_carriage_returns(json_run):
    out, proc = json_run
    report = (out / "report.txt").read_text()
    for key in ("dark: level", "saturation:", "latency:", "recording:", "points converged"):
        assert proc.stderr.count(key) == 1, key
        assert key in report  # the report still holds the whole log
    assert "\r" not in proc.stderr  # no tqdm bars off a terminal
    assert "against the truth" in report and "elapsed" in report


def test_frf_mat_and_units_beside_frf_csv(json_run):
    import scipy.io

    out, _ = json_run
    frf = FrequencyResponse.from_json(out / "frf.json")
    assert frf.meta["output_unit"] == "px" and frf.meta["input_unit"] == "input unit"
    mat = scipy.io.loadmat(out / "frf.mat")
    np.testing.assert_allclose(mat["freq_hz"].ravel(), frf.freq_hz)
    np.testing.assert_allclose(np.asarray(mat["H"]).ravel(), frf.response.ravel())
    # report.figures=false: every number file, no figure
    assert {"frf.csv", "frf.json", "frf.mat", "model.json", "config.yaml", "report.txt"} <= {p.name for p in out.iterdir()}
    assert not sorted(out.glob("*.png"))


def test_plain_run_prints_the_table_on_stdout(small_quiet_run, tmp_path):
    from torchblur import cli

    out, proc = small_quiet_run  # identify --out OUT --quiet SMALL, in a fresh process (tests/conftest.py)
    assert "against the truth" in proc.stdout and "dark: level" not in proc.stdout + proc.stderr  # --quiet: no log lines
    assert "dark: level" in (out / "report.txt").read_text()
    assert cli.main(["identify", "--out", str(tmp_path / "bad"), "sweep.f_min_hz=-3"]) == 2
    assert not logging.getLogger("torchblur").handlers  # main's console handler is gone after each call


def test_exposure_label():
    from torchblur.identify.outputs import exposure_label
    from torchblur.render.window import ExposureWindow
    import torch

    w = ExposureWindow(torch.tensor([0.5e-3, 2e-3]), torch.tensor([1e-3, 1e-3]))
    assert exposure_label(w) == "exposure 1 of 2, 1 ms long (0.5-1.5 ms), image 1 of 1"
    # the sweep's layout [E*R]: 2 exposures (30 % and 80 % of a 10 ms period) each repeated twice in a row
    w = ExposureWindow(torch.tensor([1e-3, 1e-3, 1e-3, 1e-3]), torch.tensor([3e-3, 3e-3, 8e-3, 8e-3]))
    assert exposure_label(w, 0) == "exposure 1 of 2, 3 ms long (1-4 ms), image 1 of 2"
    assert exposure_label(w, 3) == "exposure 2 of 2, 8 ms long (1-9 ms), image 2 of 2"


def test_collect_log_gathers_the_run_messages_in_order_even_when_quiet(capsys):
    """The report's log (collect_log): every torchblur record at INFO and above, from the pipeline's
    and the rig's loggers, in the order they came, also under --quiet (the console shows warnings
    only); the logger's level and handlers are restored after."""
    root = logging.getLogger("torchblur")
    before = (root.level, list(root.handlers))
    with record.console_logging(logging.WARNING), collect_log() as log:
        record.LOGGER.info("dark: level 1")
        logging.getLogger("torchblur.hardware").info("serial link: retried")
        record.LOGGER.debug("not for the report")
        record.LOGGER.warning("saturated")
    assert log == ["dark: level 1", "serial link: retried", "saturated"]
    assert capsys.readouterr().err == "warning: saturated\n"
    assert (root.level, root.handlers) == before


def test_console_logging_writes_one_line_per_message_to_stderr(capsys):
    logger = logging.getLogger("torchblur.identify.test")
    with record.console_logging(logging.INFO):
        logger.info("one")
        logger.warning("two")
        logger.debug("hidden")
    logger.info("after")  # handler removed
    err = capsys.readouterr().err
    assert err == "one\nwarning: two\n"
    assert not logging.getLogger("torchblur").handlers


def test_progress_bars_only_on_a_terminal():
    assert record.progress_bar(False, total=3).disable
    assert record.progress_bar(True, total=3, file=open(os.devnull, "w")).disable  # not a terminal


def test_stage_bar_counts_run_stage_calls(monkeypatch):
    import io

    from tqdm.auto import tqdm

    shown = io.StringIO()
    monkeypatch.setattr(record, "progress_bar", lambda progress, **kw: tqdm(**kw, file=shown, disable=not progress))
    with record.stage_bar(True, "calibration", 2) as bar:
        assert record.run_stage(None, "dark", "dark", 5, lambda r: r + 1) == 6
        record.run_stage(None, "psf", "psf", 5, lambda r: r)
        assert bar.n == 2
    assert "calibration" in shown.getvalue() and "psf" in shown.getvalue()
    assert record.run_stage(None, "x", "x", 1, lambda r: r) == 1  # outside: no bar


@pytest.mark.parametrize("overrides,n", [([], 5), (["fit.axis=x"], 4)])
def test_calibration_stage_count(overrides, n):
    assert calibration_stages(load_config(None, overrides)) == n


def test_out_folder_of_the_users_own_files_is_refused_unless_force(tmp_path, capsys):
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.run_folder import check_out_folder
    from torchblur import cli

    mine = tmp_path / "thesis"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes")
    assert cli.main(["identify", "--out", str(mine), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "notes.txt" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]  # nothing written
    assert cli.main(["fit", str(tmp_path / "nowhere"), "--out", str(mine)]) == 2  # the recording is missing; still one line
    for command in ("identify", "fit"):
        with pytest.raises(RecordingError, match="notes.txt"):
            check_out_folder(mine, command=command)
        assert check_out_folder(mine, command=command, force=True) == mine.resolve()
    run = tmp_path / "run"  # a torchblur run's own outputs are not the user's files
    (run / "experiment").mkdir(parents=True)
    (run / "config.yaml").write_text("seed: 0\n")
    (run / "bode.png").write_bytes(b"")
    assert check_out_folder(run, command="identify") == run.resolve()
    assert check_out_folder(tmp_path / "new", command="identify") == (tmp_path / "new").resolve()


def test_rig_frames_pylon_url_is_accepted_and_a_bad_one_is_one_clear_error(tmp_path, capsys):
    from torchblur.errors import ConfigError
    from torchblur import cli

    cfg = load_config(None, ["rig.kind=serial", "rig.port=/dev/null", "rig.frames=pylon://0815-0000?trigger=Line1"])
    assert cfg.rig.frames == "pylon://0815-0000?trigger=Line1"
    with pytest.raises(ConfigError, match=r"^rig.frames: expected tcp://HOST:PORT, pylon://"):
        load_config(None, ["rig.kind=serial", "rig.port=/dev/null", "rig.frames=pylonx:/cam"])
    pytest.importorskip("pypylon")
    from torchblur.hardware.serial_rig import open_frame_source

    for bad in ("pylon://?gain=3", "pylon://?readout_s=soon"):
        with pytest.raises(ConfigError, match=r"^rig.frames: 'pylon://\?") as info:
            open_frame_source(bad)
        assert "\n" not in str(info.value)
    rc = cli.main(["identify", "--out", str(tmp_path / "run"), "--quiet", "rig.kind=serial", "rig.port=/dev/null",
                   "rig.frames=pylon://?gain=3", *SMALL])
    err = capsys.readouterr().err
    assert rc == 2 and "rig.frames" in err and "gain" in err and len(err.strip().splitlines()) == 1, err


def test_identify_from_python_shows_its_messages_where_logging_is_not_configured(fresh):
    proc = fresh["from_python"]  # identify(load_config(None, FROM_PYTHON), progress=True) in a fresh process
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("dark: level") == 1 and proc.stderr.count("points converged") == 1
    assert proc.stdout == "" and "\r" not in proc.stderr
