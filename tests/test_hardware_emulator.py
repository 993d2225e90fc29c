"""The bench emulator as a separate process, driven over a real pseudo-terminal with pyserial:
agreement with the simulated rig, kill and resume, every fault, Ctrl-C, and re-fitting a
recording offline. Short sweeps (3 points, 40x40 frames)."""
import hashlib
import json
import math
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest


from background import started_fleet, stop_fleet
from torchblur import cli
from torchblur.config import load_config
from torchblur.hardware import AcquisitionStopped, Experiment
from torchblur.identify.calibration import N_DARK
from torchblur.identify.run import identify

BASE = ["camera.height=40", "camera.width=40", "seed=1"]
SWEEP = ["sweep.freq_hz=[5,200,600]"]
F = 3  # sweep points
# The fault clock (fault.start=wave) counts frames from the first WAVE. The sweep takes 5 calls
# of 4 frames: a probe of point 0 (its first amplitude is a guess), point 0, point 1, a probe
# of point 2, point 2. MID is in point 1, after point 0 is stored.
MID = 9
# One run with five faults, each in a different call. On the fault clock: the probe of point 0
# loses its 2nd ARM's reply (timeout after frames 0-1; redone as 2-5); point 0 gets garbage
# before its STOP reply (6-9, redone as 10-13); point 1's controller resets after its first ARM
# (14-15, then 2 frames of the rebooted device, 16-17, discarded; redone as 18-21); the probe
# of point 2 drops its first frame (22, a gap at 23; redone as 26-29); point 2 repeats frame 30
# in place of 31 (a stale frame; redone as 34-37).
# The fault runs fit along x (fit.axis=x): the axis calibration's tracking would otherwise
# send the first WAVE and move the fault clock off the sweep. The reference run measures the
# axis over the serial link.
ALONG_X = ["fit.axis=x"]
FAULTS = ("fault.start=wave", "fault.timeout_after=1", "fault.garbage_after=9", "fault.reset_after=16", "fault.drop_frame=22",
          "fault.stale_frame=31")


class Emu:
    """``torchblur emulator`` in a subprocess; ``info`` is its JSON start line."""

    def __init__(self, *keys):
        self.keys = keys
        self.proc = subprocess.Popen([sys.executable, "-m", "torchblur.cli", "emulator", "exit_with_parent=true", *BASE, *keys],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.stderr: list[str] = []
        self._info = None

    @property
    def info(self) -> dict:
        if self._info is None:
            line = self.proc.stdout.readline()
            assert line, f"emulator {self.keys} did not start: {self.proc.stderr.read()}"
            self._info = json.loads(line)
            threading.Thread(target=self._pump, daemon=True).start()
        return self._info

    def _pump(self):
        for line in self.proc.stderr:
            self.stderr.append(line)

    def rig_keys(self, timeout_s=0.5):
        return ["rig.kind=serial", f"rig.port={self.info['serial']}", f"rig.frames={self.info['frames']}", f"rig.timeout_s={timeout_s}"]

    def wait_stderr(self, text, timeout_s=60):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if any(text in ln for ln in self.stderr):
                return
            time.sleep(0.02)
        raise AssertionError(f"emulator never said {text!r}: {self.stderr}")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)


FLEET = {
    "ref": (),  # the reference run, then the new device of the resumed run
    "kill": ("fault.start=wave", f"fault.exit_after={MID}"),
    "faults": FAULTS,
    "persistent": ("fault.start=wave", f"fault.drop_frame={MID}", "fault.repeat=1000", "transport=socket"),
    "sigint": ("fault.start=wave", f"fault.hang_after={MID}"),
    "disconnect": ("fault.disconnect_after=2", "transport=socket"),
}


def BACKGROUND_JOB(out, started):
    """Every emulator of this module started at once (their start-up overlaps), in the background as soon as
    the module is collected (tests/background.py), their start lines read -> ``{name: Emu}``. They exit with
    this process (``exit_with_parent``) if the module's tests never run."""
    return started_fleet({name: Emu(*keys) for name, keys in FLEET.items()})


@pytest.fixture(scope="module")
def fleet(background, request):
    """Every emulator of this module, started in the background (:func:`BACKGROUND_JOB`)."""
    emus = background.get(request.module.__name__)
    yield emus
    stop_fleet(emus)


def sweep_key(ln):
    return (ln["input"], ln["freq_hz"], ln["exposure_index"], ln["repeat"])


def check_recording(exp_dir: Path, *, complete: bool):
    """No temporary file; every manifest line's file exists, reads back and has its hash; each
    sweep frame (input, frequency, exposure, repeat) at most once (exactly once if complete)."""
    import tifffile

    names = [p.name for p in exp_dir.rglob("*")]
    assert not [n for n in names if n.endswith(".tmp") or n.startswith(".")], names
    raw = (exp_dir / "manifest.jsonl").read_bytes()
    assert raw == b"" or raw.endswith(b"\n")
    lines = [json.loads(x) for x in raw.splitlines()]
    files = {}
    for ln in lines:
        f = exp_dir / ln["file"]
        if ln["file"] not in files:
            data = f.read_bytes()
            assert hashlib.sha256(data).hexdigest() == ln["sha256"]
            files[ln["file"]] = tifffile.imread(f).reshape(-1, 40, 40)
        assert files[ln["file"]].shape[0] == ln["group_frames"]
    referenced = {ln["file"] for ln in lines}
    assert {f"frames/{p.name}" for p in (exp_dir / "frames").iterdir()} == referenced  # no orphan
    sweep = [ln for ln in lines if ln["kind"] == "sweep"]
    counts = Counter(sweep_key(ln) for ln in sweep)
    assert all(v == 1 for v in counts.values()), counts
    for g in {ln["group"] for ln in sweep}:  # each accepted point: consecutive frame counters
        c = [ln["frame_counter"] for ln in sweep if ln["group"] == g]
        assert c == list(range(c[0], c[0] + 4))
    if complete:
        assert len(counts) == F * 2 * 2 and {ln["point"] for ln in sweep} == set(range(F))
        assert Counter(ln["kind"] for ln in lines)["dark"] == N_DARK
    return lines


def zscores(a, b):
    """Largest |difference| / combined std of two FRFs, magnitude and phase."""
    dm = np.abs(a.magnitude - b.magnitude) / np.hypot(a.magnitude_std, b.magnitude_std)
    dp = np.abs(np.angle(np.exp(1j * (a.phase - b.phase)))) / np.hypot(a.phase_std, b.phase_std)
    return float(dm.max()), float(dp.max())


@pytest.fixture(scope="module")
def ref(fleet, tmp_path_factory):
    """One identification through the emulator (pty + pyserial + TCP frames), recorded."""
    root = tmp_path_factory.mktemp("ref")
    cfg = load_config(None, BASE + SWEEP + fleet["ref"].rig_keys())
    res = identify(cfg, progress=False, record=root / "experiment")
    return root, res


def _only_the_model_flagged(out) -> bool:
    """Whether the run in ``out`` ended with its 3 points within tolerance and only its model
    flagged: a model of 3 points has too few degrees of freedom for the verdict's model rule, or
    a model of too low an order does not explain them (torchblur.sysid.model_check)."""
    last = (out / "report.txt").read_text().strip().splitlines()[-1]
    return last.startswith("verdict: all 3 points within tolerance; the ") and ("model fails (" in last or "model does not explain" in last)


def test_emulator_start_line(fleet):
    info = fleet["ref"].info
    assert info["serial"].startswith("/dev/") and info["frames"].startswith("tcp://127.0.0.1:")
    assert info["protocol"] == 3 and info["pid"] == fleet["ref"].proc.pid
    assert fleet["persistent"].info["serial"].startswith("socket://127.0.0.1:")


def test_emulator_matches_the_simulated_rig(ref):
    root, res = ref
    sim = identify(load_config(None, BASE + SWEEP), progress=False)
    assert res.fit.converged.all() and sim.fit.converged.all()
    zm, zp = zscores(res.frf, sim.frf)
    assert zm < 4 and zp < 4, (zm, zp)  # the same response within the reported uncertainties
    # the calibration frames went through the same SimulatedRig calls with the same seed: equal
    assert res.latency_s == sim.latency_s
    np.testing.assert_array_equal(res.psf.cov.numpy(), sim.psf.cov.numpy())
    # the axis was tracked over the serial link too (the simulated mirror moves along +x)
    assert res.axis is not None and abs(math.atan2(res.direction[1], res.direction[0])) < 5 * res.axis.angle_std_rad + 1e-3
    t = sim.truth
    em = np.abs(res.frf.magnitude[0, 0] - np.abs(t)) / res.frf.magnitude_std[0, 0]
    ep = np.abs(np.angle(np.exp(1j * (res.frf.phase[0, 0] - np.angle(t))))) / res.frf.phase_std[0, 0]
    assert em.max() < 5 and ep.max() < 5
    lines = check_recording(root / "experiment", complete=True)
    assert {ln["boot"] for ln in lines} == {lines[0]["boot"]} and lines[0]["boot"]
    meta = json.loads((root / "experiment" / "experiment.json").read_text())
    assert meta["status"] == "complete" and meta["schema_version"] == 1


def test_kill_mid_sweep_then_resume(fleet, ref, tmp_path, capsys):
    out = tmp_path / "run"
    rc = cli.main(["identify", "--out", str(out), "--quiet", *BASE, *SWEEP, *ALONG_X, *fleet["kill"].rig_keys(),
                   "report.figures=false"])  # the resume inherits it: no figure is checked here
    err = capsys.readouterr().err
    assert rc == cli.EXIT_STOPPED, err
    assert f"torchblur identify --resume {out}" in err and "connection was lost" in err
    fleet["kill"].proc.wait(10)
    assert fleet["kill"].proc.returncode == 3  # the emulator really died mid-sweep
    lines = check_recording(out / "experiment", complete=False)
    assert {ln["group"] for ln in lines if ln["kind"] == "sweep"} == {"sweep/x/000"}
    assert json.loads((out / "experiment" / "experiment.json").read_text())["status"] == "stopped"
    assert not (out / "frf.csv").exists()

    assert cli.main(["identify", "--resume", str(out), "sweep.images_per_point=3"]) == 2  # not what was recorded
    assert "sweep.images_per_point" in capsys.readouterr().err
    rc = cli.main(["identify", "--resume", str(out), "--quiet", *fleet["ref"].rig_keys()])  # a new device
    captured = capsys.readouterr()
    assert rc == 0 or (rc == 4 and _only_the_model_flagged(out)), captured.err
    lines = check_recording(out / "experiment", complete=True)
    sessions = Counter((ln["kind"], ln["session"]) for ln in lines)
    assert sessions[("sweep", 0)] == 4 and sessions[("sweep", 1)] == 8  # point 0 kept, points 1 and 2 new
    assert sessions[("latency", 1)] == 0  # the calibration was reused, not retaken
    meta = json.loads((out / "experiment" / "experiment.json").read_text())
    assert meta["status"] == "complete" and [s["status"] for s in meta["sessions"]] == ["stopped", "complete"]
    assert meta["sessions"][1]["rig"]["port"] == fleet["ref"].info["serial"]
    from torchblur.sysid.frequency_response import FrequencyResponse

    frf = FrequencyResponse.from_json(out / "frf.json")
    assert np.isfinite(frf.magnitude).all()
    zm, zp = zscores(frf, ref[1].frf)
    assert zm < 5 and zp < 5, (zm, zp)


@pytest.fixture(scope="module")
def faulty_run(fleet, tmp_path_factory):
    emu = fleet["faults"]
    d = tmp_path_factory.mktemp("faults") / "experiment"
    res = identify(load_config(None, BASE + SWEEP + ALONG_X + emu.rig_keys()), progress=False, record=d)
    return emu, res, d


@pytest.mark.parametrize("fault,emulator_says,client_says", [
    ("timeout", "no reply to", "ReplyTimeout"),
    ("garbage", "garbage before the reply", "GarbageReply"),
    ("reset", "controller reset", "DeviceReset"),
    ("drop", "dropped frame", "FrameGap"),
    ("stale", "stale frame", "StaleFrame"),
])
def test_fault_is_detected_and_the_point_retried(faulty_run, ref, fault, emulator_says, client_says):
    emu, res, d = faulty_run
    emu.wait_stderr(emulator_says, timeout_s=5)  # the fault was injected ...
    log = "\n".join(res.log)
    i = log.find(client_says)
    assert i >= 0, log  # ... detected ...
    assert "retrying (1 of 2)" in log[i:i + 400], log  # ... and the call redone
    if fault == "reset":
        assert "controller reset detected" in log
    assert "retrying (2 of 2)" not in log  # each fault cost one retry of its own call
    assert res.fit.converged.all()  # ... and the result is complete and right
    check_recording(d, complete=True)
    zm, zp = zscores(res.frf, ref[1].frf)
    assert zm < 5 and zp < 5, (zm, zp)


def test_lost_connection_is_reopened_and_the_call_redone(fleet):
    from torchblur.hardware import SerialRig

    emu = fleet["disconnect"]
    with SerialRig.open(emu.info["serial"], emu.info["frames"], timeout_s=0.5) as rig:
        cap = rig.dark(n=4, exposure_s=0.01)  # both connections drop after 2 frames
        emu.wait_stderr("closing the client connections", timeout_s=5)
        assert rig.stats["reconnects"] == 1 and any("reconnected" in e for e in rig.events), rig.events
        c = cap.frame_counter.tolist()
        assert c == list(range(c[0], c[0] + 4)) and c[0] >= 4  # the redone call's frames, not the first two
        assert cap.frames.shape == (4, 40, 40) and abs(float(cap.frames.mean()) - 100) < 1
        cap = rig.still(n=2, exposure_s=1e-3)
        assert cap.frame_counter.tolist() == [c[-1] + 1, c[-1] + 2]


def test_persistent_fault_stops_cleanly_with_state_saved(fleet, tmp_path):
    emu = fleet["persistent"]
    cfg = load_config(None, BASE + SWEEP + ALONG_X + emu.rig_keys())
    with pytest.raises(AcquisitionStopped, match="gave up after 3 attempt"):
        identify(cfg, progress=False, record=tmp_path / "experiment")
    lines = check_recording(tmp_path / "experiment", complete=False)
    assert {ln["group"] for ln in lines if ln["kind"] == "sweep"} == {"sweep/x/000"}
    meta = json.loads((tmp_path / "experiment" / "experiment.json").read_text())
    assert meta["status"] == "stopped" and "FrameTimeout" in meta["sessions"][0]["reason"]
    exp = Experiment.open(tmp_path / "experiment")  # resumable as it is
    assert not exp.repaired["dropped_groups"] and not exp.repaired["removed_files"]


def _default_sigint():
    """In the child: SIGINT back to its default, so Python turns it into KeyboardInterrupt. A test
    run started in the background of a non-interactive shell (``pytest &``) inherits SIGINT ignored,
    and a Python started with it ignored keeps ignoring it (as a user's ``nohup`` run should)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_saves_and_exits_130(fleet, tmp_path):
    emu = fleet["sigint"]
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "torchblur.cli", "identify", "--out", str(out), "--quiet", *BASE, *SWEEP, *ALONG_X,
                             *emu.rig_keys(timeout_s=60.0)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)
    try:
        emu.wait_stderr("hanging", timeout_s=90)  # the controller went silent mid-sweep; the client waits
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=180)  # saving state and stopping the fitter thread: slow on a loaded machine
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted" in err and f"torchblur identify --resume {out}" in err and "Traceback" not in err
    check_recording(out / "experiment", complete=False)
    meta = json.loads((out / "experiment" / "experiment.json").read_text())
    assert meta["status"] == "interrupted"


def tree_hash(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def test_fit_reproduces_the_recording_and_leaves_it_untouched(ref, tmp_path, capsys):
    root, res = ref
    before = tree_hash(root)
    new = tmp_path / "refit"
    rc = cli.main(["fit", str(root), "--out", str(new), "--quiet", "report.figures=false"])  # no figure checked here
    assert rc == 0 or (rc == 4 and _only_the_model_flagged(new)), rc
    from torchblur.sysid.frequency_response import FrequencyResponse

    frf = FrequencyResponse.from_json(new / "frf.json")
    np.testing.assert_allclose(frf.response, res.frf.response, rtol=1e-9)
    np.testing.assert_allclose(frf.magnitude_std, res.frf.magnitude_std, rtol=1e-9)
    assert json.loads((new / "source.json").read_text())["frames"] == len(check_recording(root / "experiment", complete=True))
    # other fit settings: one point per batch, a model of at most 2 poles
    new2 = tmp_path / "refit2"
    # a 2-pole model of the 3-pole mirror: the points are the same; the verdict may fail the model (exit 4), never the points
    rc = cli.main(["fit", str(root / "experiment"), "--out", str(new2), "--quiet", "fit.chunk_points=1", "model.max_order=2",
                   "report.figures=false"])
    assert rc == 0 or (rc == 4 and _only_the_model_flagged(new2)), rc
    frf2 = FrequencyResponse.from_json(new2 / "frf.json")
    np.testing.assert_allclose(frf2.response, res.frf.response, rtol=1e-5)
    assert json.loads((new2 / "model.json").read_text())["den"].__len__() <= 3
    capsys.readouterr()
    # refused: writing into the recording, or changing what was acquired
    assert cli.main(["fit", str(root), "--out", str(root / "inside")]) == 2
    assert cli.main(["fit", str(root), "--out", str(tmp_path / "x"), "sweep.images_per_point=3"]) == 2
    assert "sweep.images_per_point" in capsys.readouterr().err
    assert tree_hash(root) == before
