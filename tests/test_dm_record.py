"""The DM run recorded, resumed and re-fitted (torchblur.identify.dm_record), and estimate_run counting
its frames: a small mirror (9 actuators, 4 x 4 subapertures, one dead), 3 frequencies, the
simulated rig (seeded), CPU."""
import hashlib
import json

import numpy as np
import pytest

from torchblur.hardware.errors import ConnectionLost, RecordingError
from torchblur.hardware.recording import Experiment, ReplayRig
from torchblur import cli
from torchblur.config import estimate_run, load_config
from torchblur.identify.record import collect_log

from test_dm_run import SMALL as _RUN_SMALL
from readback import assert_reads_back

SMALL = [*_RUN_SMALL, "sweep.n=3", "report.figures=false"]  # the small mirror of test_dm_run at 3 frequencies (no test here looks at actuator_maps.png)
CALIBRATION = ("dark", "saturation", "psf", "latency")
OUTPUTS = ("actuators.csv", "interaction_matrix.npy", "interaction_matrix_std.npy", "command_matrix.npy", "frf.json")


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _lines(exp_dir):
    return [json.loads(ln) for ln in (exp_dir / "manifest.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """The uninterrupted run, through the command line: ``OUT`` with its recording and outputs."""
    pytest.importorskip("torchblur.identify.dm_outputs")
    out = tmp_path_factory.mktemp("dm") / "run"
    assert cli.main(["identify", "--out", str(out), "--quiet", *SMALL]) == 0
    return out


@pytest.fixture(scope="module")
def reference(live):
    """The live run's result, read back by a re-fit of its recording (bit-identical to it:
    test_refit_gives_the_live_outputs_bit_for_bit)."""
    from torchblur.identify.pipeline import identify

    exp = Experiment.open(live / "experiment", writable=False)
    return identify(load_config(None, SMALL), ReplayRig(exp), record=exp, progress=False)


def test_recording_layout(live, reference):
    exp_dir = live / "experiment"
    meta = json.loads((exp_dir / "experiment.json").read_text())
    assert meta["status"] == "complete" and [s["status"] for s in meta["sessions"]] == ["complete"]
    assert meta["sessions"][0]["rig"]["rig"].startswith("SimulatedDMRig(") and meta["sessions"][0]["rig"]["input_limit"] == 10.0
    plan = meta["dm_plan"]
    res = reference
    assert plan["kind"] == "hadamard" and plan["n_repeats"] == 1 and plan["support_threshold"] == 0.01
    np.testing.assert_array_equal(np.array(plan["patterns"]), res.plan.patterns)
    assert len(plan["support"]) == 24 and set("".join(plan["support"])) == {"1"}
    lines = _lines(exp_dir)
    groups = {ln["group"] for ln in lines}
    assert groups == set(CALIBRATION) | {"dm_sweep/000", "dm_sweep/001", "dm_sweep/002", "dm_ladder/test"}
    # dm_plan.spot_model auto's test: every pattern held still at its two end levels (4 frames each), its own group
    gl = [ln for ln in lines if ln["group"] == "dm_ladder/test"]
    assert len(gl) == 16 * 2 * 4 and {ln["kind"] for ln in gl} == {"dm_ladder"} and {ln["method"] for ln in gl} == {"pattern_ladder"}
    assert all(ln["call_shape"] == [2, 4] and ln["args"]["pattern"] == res.plan.patterns[ln["call"]].tolist() for ln in gl)
    assert all(ln["args"]["levels"][1] == -ln["args"]["levels"][0] > 0 and ln["args"]["n"] == 4 for ln in gl)
    assert res.spot_model == "shifted" and any("dm spot model: shifted (auto" in line for line in res.log)
    for k, f in enumerate(res.freq_hz):
        gl = [ln for ln in lines if ln["group"] == f"dm_sweep/{k:03d}"]
        assert len(gl) == 16 * 2 and {ln["kind"] for ln in gl} == {"dm_sweep"} and {ln["method"] for ln in gl} == {"pattern_sine"}
        assert {ln["call"] for ln in gl} == set(range(16)) and all(ln["call_shape"] == [2, 1] for ln in gl)
        first = gl[0]
        assert first["freq_hz"] == f and first["amplitude"] == res.amplitude[k] and first["power"] == res.power[k]
        assert first["n_patterns"] == 16 and first["n_repeats"] == 1 and first["trigger_delay_s"] == 0.0 and first["point"] == k
        for ln in gl:  # every pattern's row, the exposures and each frame's trigger time: the window rebuilt
            assert ln["args"]["pattern"] == res.plan.patterns[ln["call"]].tolist() and ln["args"]["amplitude"] == res.amplitude[k]
            assert ln["args"]["n_repeats"] == 1 and ln["args"]["exposures_s"] == [0.3 / f, 0.8 / f]
            assert np.isfinite(ln["trigger_time_s"]) and ln["exposure_s"] == ln["args"]["exposures_s"][ln["exposure_index"]]
    assert (exp_dir / "frames" / "dm_sweep_001.tif").is_file() and (exp_dir / "config.yaml").is_file()


def test_estimate_counts_the_frames_the_run_takes(live):
    from torchblur.config.budget import dm_ladder_plan

    cfg = load_config(None, SMALL)
    est = estimate_run(cfg)
    lines = _lines(live / "experiment")
    took = est["by_spot_model"]["shifted"]  # spot_model auto: the Gaussian spots took the shifted still
    assert took["frames"] == len(lines)  # the frames the run took: calibration, the test's holds and sweep
    assert took["sweep_frames"] == 16 * 3 * 2 * 1 == sum(ln["kind"] == "dm_sweep" for ln in lines)
    assert sum(ln["group"] == "dark" for ln in lines) == 256 and sum(ln["group"] == "psf" for ln in lines) == 128
    assert est["frame_px"] == (64, 64)
    assert took["hold_frames"] == 16 * 2 * 4 == sum(ln["kind"] == "dm_ladder" for ln in lines)  # spot_model auto's test
    # the estimate is the most the run may take: the ladder auto may choose (its plan's holds besides the test's)
    lp = dm_ladder_plan(cfg)[0]
    assert est["frames"] == est["by_spot_model"]["ladder"]["frames"] > took["frames"]
    assert est["hold_frames"] == 16 * 2 * 4 + lp.n_patterns * 13 * 32
    # the plan's patterns, frequencies, exposures and repeats, each counted (and the holds: patterns x 2 levels x 4 frames)
    more = estimate_run(load_config(None, SMALL + ["sweep.n=5", "dm_plan.n_repeats=3", "dm_plan.kind=one_at_a_time",
                                                   "dm_plan.spot_model=shifted"]))
    assert more["sweep_frames"] == 9 * 5 * 2 * 3 and more["hold_frames"] == 0 and "by_spot_model" not in more
    ladder = estimate_run(load_config(None, SMALL + ["dm_plan.spot_model=ladder", "dm_plan.ladder_levels=9", "dm_plan.ladder_frames=3"]))
    assert ladder["hold_frames"] == lp.n_patterns * 9 * 3 and "by_spot_model" not in ladder
    shipped = load_config("configs/identify_dm.yaml")
    full = estimate_run(shipped)
    assert full["by_spot_model"]["shifted"]["sweep_frames"] == 64 * 16 * 2 * 2 and full["frame_px"] == (160, 160)
    sp, R = dm_ladder_plan(shipped)[:2]  # with the ladder: auto's sparse plan, its repeats from the same budget
    assert sp.kind == "sparse" and full["sweep_frames"] == sp.n_patterns * 16 * 2 * R


def test_refit_gives_the_live_outputs_bit_for_bit(live, tmp_path):
    before = _sha(live / "experiment" / "manifest.jsonl")
    out = tmp_path / "refit"
    assert cli.main(["fit", str(live), "--out", str(out), "--quiet"]) == 0
    for name in OUTPUTS:
        assert (out / "dm" / name).read_bytes() == (live / "dm" / name).read_bytes(), name
    assert not (live / "dm" / "actuator_maps.png").exists() and not (out / "dm" / "actuator_maps.png").exists()  # report.figures=false
    assert json.loads((out / "source.json").read_text())["recording"] == str(live / "experiment")
    assert "against the simulated truth" in (out / "report.txt").read_text()  # recorded on the simulated rig: its truth
    # the re-fit's pace is judged at the recorded camera's frame rate (the replayed rig's), not a config default
    assert "per frequency at the camera's 30 Hz" in (out / "report.txt").read_text()
    assert _sha(live / "experiment" / "manifest.jsonl") == before and not (live / "experiment" / "quarantine").exists()
    got = assert_reads_back(live)  # every output of the DM run reads back
    assert got["dm/actuators.csv"]["status"].tolist().count("dead") == 1 and got["dm/frf.json"].input_labels[0] == "a0"
    edge = json.loads((live / "dm" / "registration.json").read_text())["edge_test"] or {}  # the DC gains its edge test could not verify
    assert np.flatnonzero(got["dm/actuators.csv"]["dc_gain_unverified"]).tolist() == edge.get("gains_unverified", [])


def test_actuators_csv_flags_the_unverified_dc_gains(reference, tmp_path):
    from torchblur.identify.dm_outputs import DMEstimate, read_actuators_csv, write_dm_outputs

    res = reference
    write_dm_outputs(tmp_path, DMEstimate(freq_hz=res.freq_hz, D=res.D, D_cov=res.D_cov, table=res.actuators, gains_unverified=(1, 4)),
                     figures=False)
    back = read_actuators_csv(tmp_path / "dm" / "actuators.csv")
    assert back["dc_gain_unverified"].dtype == bool and np.flatnonzero(back["dc_gain_unverified"]).tolist() == [1, 4]
    np.testing.assert_array_equal(back["poor_fit"], res.actuators.poor_fit)


def test_refit_may_change_the_fit_and_the_support_threshold_only(live, tmp_path, capsys):
    assert cli.main(["fit", str(live), "--out", str(tmp_path / "a"), "dm_plan.kind=sparse"]) == 2
    assert "dm_plan.kind" in capsys.readouterr().err
    assert cli.main(["fit", str(live), "--out", str(tmp_path / "b"), "dm.mode_hz=700"]) == 2
    assert "dm.mode_hz" in capsys.readouterr().err
    from torchblur.identify.rigs import check_refit_config

    recorded = load_config(None, SMALL)
    check_refit_config(recorded, load_config(None, SMALL + ["dm_plan.support_threshold=0.2", "fit.loss=poisson"]))


def test_a_recorded_plan_is_kept_and_a_refit_takes_its_support_at_another_threshold(tmp_path):
    from torchblur.config.budget import dm_geometry
    from torchblur.dm.plans import hadamard_plan, sparse_plan
    from torchblur.identify.dm_record import plan_document, plan_support, recorded_plan
    from torchblur.hardware.frames import CameraInfo

    G = dm_geometry(load_config(None, SMALL))
    info = CameraInfo(frame_shape=(64, 64), frame_rate_hz=30.0, max_exposure_s=1.0, readout_s=1e-3, name="unit")
    exp = Experiment.create(tmp_path / "e", config_yaml="seed: 0\n", camera=info)
    sparse = sparse_plan(G, 0.01)
    assert recorded_plan(exp, sparse, 2, G, 0.01) == (sparse, 2)  # stored now
    assert exp.meta["dm_plan"] == plan_document(sparse, 2, 0.01)
    exp.close()
    had = hadamard_plan(G)
    for writable in (True, False):  # a resume, then a re-fit: the recorded plan, not the config's choice now
        again = Experiment.open(tmp_path / "e", writable=writable)
        plan, R = recorded_plan(again, had, 1, G, 0.01)
        assert plan.kind == "sparse" and R == 2 and np.array_equal(plan.patterns, sparse.patterns)
        assert np.array_equal(plan.support, sparse.support)
        again.close()
    refit = Experiment.open(tmp_path / "e", writable=False)
    with collect_log() as said:  # the run's log lines
        plan, _ = recorded_plan(refit, sparse, 2, G, 0.3)
    assert np.array_equal(plan.patterns, sparse.patterns) and np.array_equal(plan.support, plan_support("sparse", G, 0.3))
    assert plan.support.sum() < sparse.support.sum() and "support_threshold=0.3" in said[-1]
    doc = dict(exp.meta["dm_plan"], patterns=[[1.0, 2.0]])
    with pytest.raises(RecordingError, match="dm_plan.patterns"):
        from torchblur.identify.dm_record import plan_from_document

        plan_from_document(doc, G, "experiment.json")


class _Crashing:
    """The simulated DM rig whose link is lost after ``after`` pattern commands."""

    def __init__(self, rig, after: int):
        self._rig, self._left = rig, after

    def __getattr__(self, name):
        return getattr(self._rig, name)

    def pattern_sine(self, **kwargs):
        if self._left == 0:
            raise ConnectionLost("the controller went away (test)")
        self._left -= 1
        return self._rig.pattern_sine(**kwargs)


def test_crash_then_resume(live, reference, tmp_path, capsys, monkeypatch):
    from torchblur.identify import dm_plan as pipeline
    from torchblur.identify.pipeline import identify

    cfg = load_config(None, SMALL)
    root = tmp_path / "run"
    real = pipeline.build_dm

    def crashing(cfg, **kw):  # frequency 0 complete, frequency 1 cut after 5 of its 16 patterns
        mirror, wfs, rig = real(cfg, **kw)
        return mirror, wfs, _Crashing(rig, after=16 + 5)

    monkeypatch.setattr(pipeline, "build_dm", crashing)
    assert cli.main(["identify", "--out", str(root), "--quiet", *SMALL]) == cli.EXIT_STOPPED
    err = capsys.readouterr().err
    assert "went away" in err and f"torchblur identify --resume {root}" in err
    monkeypatch.undo()
    assert not (root / "dm").exists()
    exp_dir = root / "experiment"
    meta = json.loads((exp_dir / "experiment.json").read_text())
    assert meta["status"] == "stopped" and "ConnectionLost" in meta["sessions"][0]["reason"]
    kept = {ln["group"] for ln in _lines(exp_dir)}
    assert kept == set(CALIBRATION) | {"dm_ladder/test", "dm_sweep/000"}  # the cut frequency is not stored at all
    # what was stored is what the uninterrupted run stored (same seed, same commands)
    for g in kept:
        name = g.replace("/", "_") + ".tif"
        assert _sha(exp_dir / "frames" / name) == _sha(live / "experiment" / "frames" / name), g
    stored = {g: _sha(exp_dir / "frames" / (g.replace("/", "_") + ".tif")) for g in kept}

    assert cli.main(["fit", str(root), "--out", str(tmp_path / "early"), "--quiet"]) == 2  # incomplete: nothing to re-fit yet
    assert "resume it first" in capsys.readouterr().err
    assert cli.main(["identify", "--resume", str(root), "dm.mode_hz=700"]) == 2  # not what was recorded
    assert "dm.mode_hz" in capsys.readouterr().err
    assert cli.main(["identify", "--resume", str(root), "--quiet"]) == 0
    meta = json.loads((exp_dir / "experiment.json").read_text())
    assert meta["status"] == "complete" and [s["status"] for s in meta["sessions"]] == ["stopped", "complete"]
    assert "seed=0)" not in meta["sessions"][1]["rig"]["rig"]  # the resumed rig draws its own noise
    lines = _lines(exp_dir)
    by_session = {(ln["group"], ln["session"]) for ln in lines}
    assert {g for g, s in by_session if s == 1} == {"dm_sweep/001", "dm_sweep/002"}  # only the missing groups taken (the holds reused)
    assert {g: _sha(exp_dir / "frames" / (g.replace("/", "_") + ".tif")) for g in kept} == stored  # nothing rewritten
    assert estimate_run(cfg)["by_spot_model"]["shifted"]["frames"] == len(lines)  # auto took the shifted still

    exp = Experiment.open(exp_dir, writable=False)
    res = identify(cfg, ReplayRig(exp), record=exp, progress=False)  # the resumed run's result (a re-fit gives it bit for bit)
    assert (root / "dm" / "actuators.csv").read_text() == _actuators_csv(res, tmp_path)
    ref = reference
    # frequency 0: the same frames, so the same D bit for bit; the others: new frames, the same D within its stds
    np.testing.assert_array_equal(res.D[..., 0], ref.D[..., 0])
    live_act = ~ref.mirror.dead
    d = (res.D - ref.D)[:, live_act, 1:]
    C = res.D_cov[:, live_act, 1:] + ref.D_cov[:, live_act, 1:]
    z = np.abs(np.stack([d.real / np.sqrt(C[..., 0, 0]), d.imag / np.sqrt(C[..., 1, 1])]))
    assert np.all(np.isfinite(z)) and np.quantile(z, 0.99) < 5.0 and 0 < np.median(z) < 2.0


def _actuators_csv(res, tmp_path) -> str:
    from torchblur.identify.dm_outputs import DMEstimate, write_dm_outputs

    out = tmp_path / "written"
    write_dm_outputs(out, DMEstimate(freq_hz=res.freq_hz, D=res.D, D_cov=res.D_cov, table=res.actuators, meta={}))
    return (out / "dm" / "actuators.csv").read_text()


def test_a_pattern_line_that_disagrees_with_its_call_is_refused(live, tmp_path):
    import shutil

    d = tmp_path / "e"
    shutil.copytree(live / "experiment", d)
    raw = (d / "manifest.jsonl").read_text().splitlines()
    i = next(i for i, ln in enumerate(raw) if '"dm_sweep/001"' in ln)
    line = json.loads(raw[i])
    line["amplitude"] *= 1.5  # the label no longer what the rig was commanded
    raw[i] = json.dumps(line, separators=(",", ":"))
    (d / "manifest.jsonl").write_text("\n".join(raw) + "\n")
    with pytest.raises(RecordingError, match="amplitude"):
        Experiment.open(d, writable=False)


def test_identify_into_a_recorded_dm_run_is_refused(live, capsys):
    before = _sha(live / "experiment" / "manifest.jsonl")
    assert cli.main(["identify", "--out", str(live), "--quiet", *SMALL]) == 2
    assert "--resume" in capsys.readouterr().err
    assert _sha(live / "experiment" / "manifest.jsonl") == before


def test_set_meta_refuses_the_schemas_own_keys(tmp_path):
    from torchblur.hardware.frames import CameraInfo

    info = CameraInfo(frame_shape=(8, 8), frame_rate_hz=30.0, max_exposure_s=1.0, readout_s=1e-3, name="unit")
    exp = Experiment.create(tmp_path / "e", config_yaml="seed: 0\n", camera=info)
    with pytest.raises(RecordingError, match="status"):
        exp.set_meta("status", "complete")
    exp.set_meta("note", {"a": 1})
    exp.close()
    assert Experiment.open(tmp_path / "e", writable=False).meta["note"] == {"a": 1}


def test_ctrl_c_during_the_sweep_leaves_a_resumable_recording(tmp_path):
    from torchblur.identify.pipeline import identify
    from torchblur.rig.factory import build_dm

    class _Interrupted(_Crashing):
        def pattern_sine(self, **kwargs):
            raise KeyboardInterrupt

    cfg = load_config(None, SMALL)
    with pytest.raises(KeyboardInterrupt):
        identify(cfg, _Interrupted(build_dm(cfg)[2], after=0), record=tmp_path / "experiment", progress=False)
    meta = json.loads((tmp_path / "experiment" / "experiment.json").read_text())
    assert meta["status"] == "interrupted" and meta["dm_plan"]["kind"] == "hadamard"
    assert {ln["group"] for ln in _lines(tmp_path / "experiment")} == set(CALIBRATION) | {"dm_ladder/test"}


def test_the_truth_only_where_every_frame_is_simulated():
    from types import SimpleNamespace

    from torchblur.identify.dm_record import simulated_frames

    sim = {"rig": {"rig": "SimulatedDMRig(9 actuators, ..., seed=0)"}}
    other = {"rig": {"rig": "SerialDMRig(/dev/ttyUSB0)"}}
    rec = lambda sessions, writable: SimpleNamespace(meta={"sessions": sessions}, writable=writable)  # noqa: E731
    assert simulated_frames(True, None) and not simulated_frames(False, None)
    assert simulated_frames(True, rec([], True)) and simulated_frames(True, rec([sim], True))
    assert not simulated_frames(True, rec([other], True))  # resumed on the simulator, begun on hardware
    assert not simulated_frames(False, rec([sim], True))  # begun on the simulator, resumed on hardware
    assert simulated_frames(False, rec([sim, sim], False)) and not simulated_frames(False, rec([sim, other], False))
    assert not simulated_frames(False, rec([], False))


def test_a_resume_on_the_simulator_needs_the_same_actuator_table(tmp_path, monkeypatch):
    from torchblur.identify.pipeline import identify
    from torchblur.rig.dm import SimulatedDMRig

    table = tmp_path / "act.csv"
    table.write_text("actuator,mode_hz,damping,gain,delay_s\n4,650,0.07,1.0,2e-5\n")
    cfg = load_config(None, SMALL + [f"dm.actuator_table={table}"])

    def interrupted(self, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(SimulatedDMRig, "pattern_sine", interrupted)
        with pytest.raises(KeyboardInterrupt):
            identify(cfg, record=tmp_path / "experiment", progress=False)
    meta = json.loads((tmp_path / "experiment" / "experiment.json").read_text())
    assert meta["sessions"][0]["rig"]["dm_actuator_table_sha256"] == _sha(table)
    table.write_text("actuator,mode_hz,damping,gain,delay_s\n4,700,0.07,1.0,2e-5\n")  # another mirror under the same name
    with pytest.raises(RecordingError, match="dm.actuator_table"):
        identify(cfg, record=tmp_path / "experiment", progress=False)
    assert len(json.loads((tmp_path / "experiment" / "experiment.json").read_text())["sessions"]) == 1  # no session begun
