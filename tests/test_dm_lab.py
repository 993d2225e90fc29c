"""A lab's own DM (issue 23 part D): the worked vendor-SDK example (docs/examples/vendor_dm.py)
through the public ``torchblur.identify`` (a DM config and its rig) with the latency given (its rig has no pulse()),
its recording exported as an outside DM recording and fitted by ``torchblur fit FOLDER`` to the
same table, the rig contract checked before any frame, and the outside format read as untrusted
input (every error names the file, line and column)."""
import importlib.util
import json
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import torchblur as tb
from torchblur.errors import ConfigError, InputTypeError
from torchblur.hardware.errors import RecordingError
from torchblur.rig import DMRig

EXAMPLE_PATH = Path(__file__).resolve().parents[1] / "docs" / "examples" / "vendor_dm.py"


def _example():
    spec = importlib.util.spec_from_file_location("vendor_dm_example", EXAMPLE_PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def example():
    return _example()


@pytest.fixture(scope="module")
def lab_run(example, tmp_path_factory):
    """The example's run on the Acme stand-in, recorded, and its recording exported: ``(res, rig, folder)``."""
    from torchblur.identify import export_dm_recording

    root = tmp_path_factory.mktemp("lab")
    res, rig = example.identify_with_acme(record=root / "run" / "experiment")
    return res, rig, export_dm_recording(root / "run", root / "outside")


def test_the_vendor_example_identifies_its_mirror_with_the_latency_given(lab_run):
    res, rig, _ = lab_run
    assert not hasattr(rig, "pulse") and isinstance(rig, DMRig)
    assert any("given (camera.latency_s, camera.latency_std_s; not scanned)" in line for line in res.log)
    truth = rig._m._b.sim.mirror  # the stand-in's hidden hardware: for this test only
    t = res.actuators
    assert list(t.status) == ["ok"] * 4 and res.n_failed == 0
    for est, std, true, rel in ((t.mode_hz, t.mode_hz_std, truth.mode_hz, 0.005), (t.damping, t.damping_std, truth.damping, 0.05),
                                (t.dc_gain, t.dc_gain_std, truth.gain, 0.01)):
        assert np.all(np.abs(est / true - 1) < rel)
        assert np.all(np.abs(est - true) < 4 * std)  # the stds hold (4 of them: 12 numbers)


class _CountingPool(ThreadPoolExecutor):
    """One worker thread that records, at each submit, how many submitted fits had not finished (their frames held)."""

    def __init__(self):
        super().__init__(max_workers=1)
        self.futures, self.pending = [], []

    def submit(self, *a, **k):
        self.pending.append(sum(not f.done() for f in self.futures))
        self.futures.append(super().submit(*a, **k))
        return self.futures[-1]


def test_the_exported_recording_fits_to_the_same_table_through_torchblur_fit(lab_run, tmp_path, capsys, monkeypatch):
    """The same frames give the live run's D, D0 and table exactly. Reading the folder checks every frame and holds
    the dark and still ones only; the fit reads one frequency's frames at a time (each read of the store at most
    one frequency's), at most AMPLITUDE_LAG of them waiting for their fits, as the live sweep (issue 23)."""
    from torchblur.hardware.outside import FrameStore
    from torchblur.identify import dm_outside
    from torchblur.identify.dm_outputs import read_actuators_csv
    from torchblur.identify.dm_plan import AMPLITUDE_LAG
    from torchblur.cli import main
    from torchblur.sysid.frequency_response import FrequencyResponse

    res, _, folder = lab_run
    loads, load = [], FrameStore.load
    monkeypatch.setattr(FrameStore, "load", lambda self, lines: loads.append(np.size(lines)) or load(self, lines))
    pool = _CountingPool()
    monkeypatch.setattr(dm_outside, "fit_pool", lambda executor: pool)
    rec = dm_outside.read_dm_recording(folder)
    assert loads == [len(rec.dark), len(rec.still)]
    loads.clear()
    assert main(["fit", str(folder), "--out", str(tmp_path / "fit"), "--quiet", "--json"]) == 0
    F, P, ER = rec.start_s.shape
    assert loads[:2] == [len(rec.dark), len(rec.still)] and loads[2:] == [P * ER] * (2 * F)  # the saturation check, then the fit
    assert len(pool.pending) == F and max(pool.pending) <= AMPLITUDE_LAG
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["trustworthy"] and summary["frames"] == res.n_frames
    # the folder does not give its camera's frame rate: the fit times are reported, the keep-up not judged
    pace = summary["fit_pace"]
    assert pace["fit_median_s"] > 0 and pace["frame_rate_hz"] is None and pace["keeps_up"] is None
    assert "so whether a live sweep at this pace keeps up is not judged" in (tmp_path / "fit" / "report.txt").read_text()
    t, back = res.actuators, read_actuators_csv(tmp_path / "fit" / "dm" / "actuators.csv")
    assert list(back["status"]) == list(t.status)
    for col in ("dc_gain", "mode_hz", "damping", "delay_s", "dc_gain_std", "mode_hz_std", "damping_std", "delay_s_std"):
        np.testing.assert_allclose(back[col], getattr(t, col), rtol=1e-8)  # actuators.csv holds 9 significant digits
    assert np.array_equal(np.load(tmp_path / "fit" / "dm" / "interaction_matrix.npy"), t.static_column)
    frf = FrequencyResponse.from_json(tmp_path / "fit" / "dm" / "frf.json")
    assert np.array_equal(frf.response, res.D) and frf.meta["n_repeats"] == rec.R == res.n_repeats


def test_write_dm_recording_reads_back(lab_run, tmp_path):
    from torchblur.identify.dm_outside import read_dm_recording, write_dm_recording

    rec = read_dm_recording(lab_run[2])
    again = write_dm_recording(tmp_path / "again", dark=rec.dark, still=rec.still, still_exposure_s=rec.still_exposure_s,
                               patterns=rec.patterns, freq_hz=rec.freq_hz, amplitude=rec.amplitude, power=rec.power, frames=rec.frames,
                               start_s=rec.start_s, duration_s=rec.duration_s, R=rec.R,
                               camera={"gain_e_per_adu": rec.camera.gain_e_per_adu, "latency_s": rec.camera.latency_s,
                                       "latency_std_s": rec.camera.latency_std_s},
                               layout={"dm": {"n_across": 2}, "wfs": {"n_across": 2, "pitch_px": 16.0, "sigma_px": 1.2},
                                       "dm_plan": {"kind": "hadamard"}})
    back = read_dm_recording(again)
    for name in ("dark", "still", "patterns", "freq_hz", "amplitude", "power", "start_s", "duration_s"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert all(np.array_equal(a, b) for a, b in zip(back.frames, rec.frames)) and back.R == rec.R


def test_the_export_decodes_each_group_once_and_writes_the_same_bytes(lab_run, tmp_path, monkeypatch):
    """Exported again, each recorded group's TIFF is decoded once (the windows come from the manifest), every swept
    frequency's among them, and every file is the first export's byte for byte."""
    from torchblur.hardware.recording import Experiment
    from torchblur.identify import export_dm_recording
    from torchblur.identify.dm_record import SWEEP_KIND

    reads, read_group = {}, Experiment.read_group

    def counted(self, key):
        reads[key] = reads.get(key, 0) + 1
        return read_group(self, key)

    monkeypatch.setattr(Experiment, "read_group", counted)
    again = export_dm_recording(lab_run[2].parent / "run", tmp_path / "again")
    sweeps = [k for k, lines in Experiment.open(lab_run[2].parent / "run", writable=False).groups.items() if lines[0]["kind"] == SWEEP_KIND]
    assert sweeps and set(sweeps) <= set(reads)
    assert all(reads[k] == 1 for k in sweeps), reads
    names = sorted(p.name for p in lab_run[2].iterdir())
    assert names == sorted(p.name for p in again.iterdir()) and "sweep.tif" in names
    for name in names:
        assert (again / name).read_bytes() == (lab_run[2] / name).read_bytes(), name


class _Counted(list):
    """A list whose items count how often they are read (``reads``)."""

    def __init__(self, items):
        super().__init__(items)
        self.reads = [0] * len(items)

    def __getitem__(self, i):
        self.reads[i] += 1
        return super().__getitem__(i)

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def test_write_dm_recording_reads_each_frequency_once_and_stores_a_fraction_exactly(lab_run, tmp_path):
    """Whole-ADU frames: each frequency's frames read once, the sweep stored as uint16. The last frequency with a
    fractional ADU (and the dark and still frames, every file of a recording one dtype): the sweep stored as float64,
    every frame read back exactly (each frequency read twice: the file is started again at the last one)."""
    import tifffile

    from torchblur.identify.dm_outside import read_dm_recording, write_dm_recording

    rec = read_dm_recording(lab_run[2])
    for frac in (False, True):
        frames = _Counted([np.asarray(f) + (0.5 if frac and k == len(rec.frames) - 1 else 0.0) for k, f in enumerate(rec.frames)])
        half = 0.5 if frac else 0.0
        folder = write_dm_recording(tmp_path / f"frac{frac}", dark=rec.dark + half, still=rec.still + half,
                                    still_exposure_s=rec.still_exposure_s, patterns=rec.patterns, freq_hz=rec.freq_hz,
                                    amplitude=rec.amplitude, power=rec.power, frames=frames, start_s=rec.start_s,
                                    duration_s=rec.duration_s, R=rec.R, camera={"gain_e_per_adu": rec.camera.gain_e_per_adu},
                                    layout={"dm": {"n_across": 2}, "wfs": {"n_across": 2, "pitch_px": 16.0, "sigma_px": 1.2},
                                            "dm_plan": {"kind": "hadamard"}})
        assert frames.reads == ([2] * len(frames) if frac else [1] * len(frames))
        assert tifffile.TiffFile(folder / "sweep.tif").pages[0].dtype == (np.float64 if frac else np.uint16)
        back = read_dm_recording(folder)
        assert len(back.frames) == len(frames) and all(np.array_equal(a, b) for a, b in zip(back.frames, list.__iter__(frames)))
        np.testing.assert_array_equal(back.dark, rec.dark + half)


def test_write_dm_recording_refuses_frames_it_could_read_only_once(lab_run, tmp_path):
    """A generator of the frequencies' frames is refused, naming the argument: the fractional ADU of its last frequency
    would start the sweep file again with the generator spent, a TIFF short of pages."""
    from torchblur.identify.dm_outside import read_dm_recording, write_dm_recording

    rec = read_dm_recording(lab_run[2])
    frames = (np.asarray(f) + 0.5 for f in rec.frames)
    with pytest.raises(InputTypeError, match=r"^frames: expected an array or a sequence of arrays .* got a one-pass generator"):
        write_dm_recording(tmp_path / "gen", dark=rec.dark, still=rec.still, still_exposure_s=rec.still_exposure_s, patterns=rec.patterns,
                           freq_hz=rec.freq_hz, amplitude=rec.amplitude, power=rec.power, frames=frames, start_s=rec.start_s,
                           duration_s=rec.duration_s, R=rec.R, camera={"gain_e_per_adu": rec.camera.gain_e_per_adu},
                           layout={"dm": {"n_across": 2}, "wfs": {"n_across": 2, "pitch_px": 16.0, "sigma_px": 1.2},
                                   "dm_plan": {"kind": "hadamard"}})


@pytest.fixture(scope="module")
def jittered(lab_run, tmp_path_factory):
    """``(folder, start_s)``: the exported recording rewritten with R = 2 repeats per exposure (the second one's frames
    1 ADU brighter) and every frame's window start jittered by its own 1 us, as a camera's trigger jitter makes them."""
    from torchblur.identify.dm_outside import read_dm_recording, write_dm_recording

    rec = read_dm_recording(lab_run[2])
    twice = lambda a: np.repeat(a, 2, axis=2)  # noqa: E731 - [F, P, E] -> [F, P, E*R], exposure-major
    start = twice(rec.start_s) + np.random.default_rng(23).normal(0.0, 1e-6, twice(rec.start_s).shape)
    frames = [np.stack([fr, fr + 1], 2).reshape((fr.shape[0], -1) + fr.shape[2:]) for fr in rec.frames]
    folder = write_dm_recording(tmp_path_factory.mktemp("jit") / "rec", dark=rec.dark, still=rec.still, R=2,
                                still_exposure_s=rec.still_exposure_s, patterns=rec.patterns, freq_hz=rec.freq_hz,
                                amplitude=rec.amplitude, power=rec.power, frames=frames, start_s=start, duration_s=twice(rec.duration_s),
                                camera={"gain_e_per_adu": rec.camera.gain_e_per_adu, "saturation_adu": rec.camera.saturation_adu,
                                        "latency_s": rec.camera.latency_s, "latency_std_s": rec.camera.latency_std_s},
                                layout={"dm": {"n_across": 2}, "wfs": {"n_across": 2, "pitch_px": 16.0, "sigma_px": 1.2},
                                        "dm_plan": {"kind": "hadamard"}})
    return folder, start


def _set_cells(path: Path, column: str, value: str | None, pick) -> None:
    """Set ``column`` of the frames.csv rows ``pick(row)`` to ``value`` (None: drop the column)."""
    import csv

    with open(path, newline="") as fh:
        head, *rows = list(csv.reader(fh))
    j = head.index(column)
    for row in rows:
        if pick(dict(zip(head, row))):
            row[j] = value
    keep = [i for i in range(len(head)) if value is not None or i != j]
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([[r[i] for i in keep] for r in [head] + rows])


@pytest.mark.parametrize("numbered", [True, False])
def test_the_repeats_of_jittered_windows_are_counted(jittered, tmp_path, numbered):
    """Each repeat's window starts at its own time (the trigger jitter): the R a recording holds is its frames per pattern,
    frequency and exposure (numbered 0..R-1 by the repeat column or not numbered), each frame keeping its own start; the fit
    takes the config's R and exposures of it (issue 23: it found R = 1 and every frame its own exposure)."""
    from torchblur.identify.dm_outside import dm_recording_config, read_dm_recording

    folder, start = jittered
    if not numbered:
        folder = Path(shutil.copytree(folder, tmp_path / "plain"))
        _set_cells(folder / "frames.csv", "repeat", None, lambda row: True)
    rec = read_dm_recording(folder)
    np.testing.assert_array_equal(rec.start_s, start)
    cfg = dm_recording_config(rec)
    assert rec.R == cfg.dm_plan.n_repeats == 2 and rec.start_s.shape[2] == 4
    np.testing.assert_allclose(cfg.sweep.exposures, [0.3, 0.8])  # the example's (fractions of the period)


@pytest.mark.parametrize("value,error", [
    ("2", r"line (\d+), column repeat: 2, but the 0.006 s exposure at 50 Hz has 2 frame\(s\) here: number its repeats 0..1"),
    ("0", r"line (\d+), column repeat: repeat 0 is given twice"),
    ("", r"line (\d+), column repeat: empty, given on line \d+"),
    ("one", r"line (\d+), column repeat: expected an integer"),
    ("-1", r"line (\d+), column repeat: expected a value >= 0"),
])
def test_a_bad_repeat_column_is_refused_naming_it(jittered, tmp_path, value, error):
    """The repeat column is untrusted: a gap, a repeat given twice, one left empty or not a count is refused, naming the line and column."""
    import re

    from torchblur.identify.dm_outside import read_dm_recording

    folder = Path(shutil.copytree(jittered[0], tmp_path / "bad"))
    _set_cells(folder / "frames.csv", "repeat", value, lambda row: row["kind"] == "sweep" and row["page"] == "1")
    with pytest.raises(RecordingError, match=error) as err:
        read_dm_recording(folder)
    line = 1 + next(i for i, r in enumerate((folder / "frames.csv").read_text().splitlines()) if r.startswith("sweep.tif,1,"))
    assert re.search(error, str(err.value)).group(1) == str(line)


class _NoFrames:
    """A rig whose every frame call fails the test: the checks come before any frame."""

    frame_shape, frame_rate_hz, max_exposure_s, readout_s, input_limit, n_actuators = (32, 32), 30.0, 1.0, 1e-3, 10.0, 4

    def dark(self, *a, **k):
        raise AssertionError("a frame was taken before the rig was checked")

    still = pattern_sine = dark


def test_the_rig_contract_is_checked_before_any_frame(example):
    cfg = tb.load_config(None, example.EXAMPLE)
    with pytest.raises(InputTypeError, match=r"rig: a object lacks pattern_sine\(\)"):
        tb.identify(cfg, object.__new__(type("object", (), {"dark": lambda s: 0, "still": lambda s: 0})), progress=False)
    no_latency = tb.load_config(None, [o for o in example.EXAMPLE if not o.startswith("camera.latency_std_s")])
    with pytest.raises(ConfigError, match=r"camera.latency_std_s: the rig \(_NoFrames\) has no gated laser \(pulse\(\)\)"):
        tb.identify(no_latency, _NoFrames(), progress=False)
    rig = _NoFrames()
    rig.n_actuators = 5
    with pytest.raises(ConfigError, match="dm.n_across: .* 4 actuators .* the rig's 5"):
        tb.identify(cfg, rig, progress=False)
    rig = _NoFrames()
    rig.frame_shape = (64, 64)
    with pytest.raises(ConfigError, match="wfs.pitch_px: .* 32x32 px frames, the rig.s camera 64x64"):
        tb.identify(cfg, rig, progress=False)
    with pytest.raises(ConfigError, match="dm.n_across: 0, not a DM config"):
        tb.identify(tb.load_config(), _NoFrames(), progress=False)
    with pytest.raises(InputTypeError, match="cfg: expected an IdentifyConfig"):
        tb.identify({"dm": {}}, _NoFrames(), progress=False)


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize("file,old,new,error", [
    ("patterns.csv", "0,1.0,1.0", "0,1.0,nan", r"patterns.csv line 2, column a1: expected a finite number"),
    ("patterns.csv", "pattern,a0", "pattern,b0", r"patterns.csv line 1: expected the header pattern,a0,a1"),
    ("patterns.csv", "1,1.0,-1.0,1.0,-1.0", "1,1.0,1.0,1.0,1.0", r"patterns.csv: the 4 patterns do not separate the actuators"),
    ("frames.csv", "sweep.tif,0,sweep,0,", "sweep.tif,0,sweep,9,", r"frames.csv line \d+, column pattern: .* \(0..3\), got 9"),
    ("frames.csv", "sweep.tif,0,sweep,0,", "sweep.tif,0,sweep,,", r"frames.csv line \d+, column pattern: a sweep frame needs"),
    ("frames.csv", "sweep.tif,0,sweep,0,", "sweep.tif,0,sweep,x,", r"frames.csv line \d+, column pattern: expected an integer"),
    ("recording.yaml", "coupling:", "stiffness: 1\n  coupling:", r"recording.yaml: dm.stiffness"),
    ("recording.yaml", "pitch_px: 16.0", "pitch_px: 20.0", r"recording.yaml: wfs: the sensor .* 40x40 px frames, the recording.s are 32x32"),
    ("recording.yaml", "kind: hadamard", "kind: random", r"recording.yaml: dm_plan.kind: expected one of"),
    ("recording.yaml", "n_across: 2", "n_across: 3", r"patterns.csv line 1: 4 actuators .* has 9 inside the pupil"),
    ("recording.yaml", "coupling: 0.15", "coupling: 7", r"recording.yaml: dm.coupling"),
])
def test_a_bad_dm_recording_is_refused_naming_file_line_and_column(lab_run, tmp_path, file, old, new, error):
    from torchblur.identify.dm_outside import dm_recording_config, read_dm_recording

    folder = tmp_path / "bad"
    shutil.copytree(lab_run[2], folder)
    _edit(folder / file, old, new)
    with pytest.raises(RecordingError, match=error):
        dm_recording_config(read_dm_recording(folder))


def test_saturated_frames_are_refused_not_fitted(lab_run, tmp_path):
    """The DM spot fit does not leave saturated pixels out: a recording with one is refused, naming the frame."""
    import tifffile

    from torchblur.identify.dm_outside import identify_dm_recording, read_dm_recording

    folder = tmp_path / "sat"
    shutil.copytree(lab_run[2], folder)
    sweep = tifffile.imread(folder / "sweep.tif")
    sweep[5, 3, 3] = 4095  # page 5: the first frequency, pattern 2, its second frame (4 patterns x 2 exposures)
    tifffile.imwrite(folder / "sweep.tif", sweep, photometric="minisblack")
    _edit(folder / "recording.yaml", "saturation_adu:", "saturation_adu: 4095.0\nold_saturation_adu:")
    text = "\n".join(ln for ln in (folder / "recording.yaml").read_text().splitlines() if not ln.startswith("old_saturation_adu"))
    (folder / "recording.yaml").write_text(text + "\n")
    with pytest.raises(RecordingError, match=r"frames.csv: the sweep frame of pattern 2 at 50 Hz \(its frame 1 there\) has saturated"):
        identify_dm_recording(read_dm_recording(folder))


def test_a_frame_changed_after_reading_is_refused_when_read_again(lab_run, tmp_path):
    """The frames are checked when the folder is read and read again when fitted: a frame whose pixels changed in
    between (its digest differs) is refused, naming it, not fitted unchecked."""
    import tifffile

    from torchblur.identify.dm_outside import read_dm_recording

    folder = tmp_path / "changed"
    shutil.copytree(lab_run[2], folder)
    rec = read_dm_recording(folder)
    assert rec.frames[1].shape == rec.frames.item_shape == (4, 2, 32, 32)
    sweep = tifffile.imread(folder / "sweep.tif")
    sweep[9, 3, 3] += 1  # the second frequency, pattern 0, its second frame
    tifffile.imwrite(folder / "sweep.tif", sweep, photometric="minisblack")
    with pytest.raises(RecordingError, match=r"sweep.tif page 9 \(frames.csv line \d+\): its pixels changed after the recording was read"):
        rec.frames[1]


def test_a_dm_recording_takes_only_fit_overrides(lab_run):
    from torchblur.identify.dm_outside import dm_recording_config, read_dm_recording

    rec = read_dm_recording(lab_run[2])
    with pytest.raises(ConfigError, match="dm.n_across: a DM recording takes only fit"):
        dm_recording_config(rec, ["dm.n_across=3"])
    assert dm_recording_config(rec, ["fit.loss=poisson"]).fit.loss == "poisson"


def test_the_outside_plan_refuses_a_config_of_other_frequencies_a_rig_and_a_record(lab_run):
    """DMOutsidePlan runs through the one runner (identify) and refuses, before any fit, what would pair the
    recording with a sweep it does not hold, or a rig or a recording it does not use."""
    from torchblur.identify.dm_outside import DMOutsidePlan, dm_recording_config, read_dm_recording

    from dataclasses import replace

    rec = read_dm_recording(lab_run[2])
    cfg = dm_recording_config(rec)
    other = replace(cfg, sweep=replace(cfg.sweep, freq_hz=[float(f) * 1.5 for f in rec.freq_hz]))
    with pytest.raises(ConfigError, match="sweep.freq_hz: expected the recording's frequencies"):
        tb.identify(other, plan=DMOutsidePlan(rec), progress=False)
    with pytest.raises(InputTypeError, match="rig: an outside DM recording is fitted without a rig"):
        tb.identify(cfg, _NoFrames(), plan=DMOutsidePlan(rec), progress=False)
    with pytest.raises(InputTypeError, match="record: an outside DM recording is not recorded again"):
        tb.identify(cfg, plan=DMOutsidePlan(rec), record="somewhere", progress=False)
