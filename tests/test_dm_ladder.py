"""The DM run's static holds (issue 23, dm_plan.spot_model): the optional rig method
``pattern_ladder`` (the simulated rig's, checked before any frame where the config needs it), the
config keys, and the test of whether a shifted still explains a held spot
(:func:`torchblur.dm.static_hold.fit_shifted_still`). Small and seeded, CPU."""
import json
import math
import os
import re

import numpy as np
import pytest
import torch

from torchblur.config import load_config
from torchblur.config.budget import dm_geometry
from torchblur.dm.static_hold import chi2_threshold, fit_shifted_still
from torchblur.errors import ConfigError, ParameterError, ShapeError
from torchblur.image.spots import crop_spots
from torchblur.render.camera import camera_noise_std
from torchblur.rig.dm_contract import check_dm_rig
from torchblur.rig.factory import build_dm

from test_dm_run import SMALL

_F64 = torch.float64


@pytest.mark.parametrize("override,key", [("dm_plan.spot_model=moving", "dm_plan.spot_model"), ("dm_plan.ladder_levels=3", "dm_plan.ladder_levels"),
                                          ("dm_plan.ladder_frames=0", "dm_plan.ladder_frames"), ("dm_plan.ladder_reach=0", "dm_plan.ladder_reach"),
                                          ("dm_plan.ladder_levels=7.5", "dm_plan.ladder_levels")])
def test_the_spot_model_keys_are_checked(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, SMALL + [override])


class _NoLadder:
    """A rig with the required contract and no ``pattern_ladder``; every frame call fails the test."""

    frame_shape, frame_rate_hz, max_exposure_s, readout_s, input_limit, n_actuators = (64, 64), 30.0, 1.0, 1e-3, 10.0, 9

    def dark(self, *a, **k):
        raise AssertionError("a frame was taken before the rig was checked")

    still = pattern_sine = dark


def test_a_ladder_needs_pattern_ladder_before_any_frame():
    import torchblur as tb

    cfg = load_config(None, SMALL + ["dm_plan.spot_model=ladder", "camera.latency_s=1e-5", "camera.latency_std_s=1e-7"])
    with pytest.raises(ConfigError, match=r"dm_plan\.spot_model: ladder needs static holds .* _NoLadder has no pattern_ladder\(\)"):
        tb.identify(cfg, _NoLadder(), progress=False)
    check_dm_rig(build_dm(cfg)[2], cfg)  # the simulated rig has it
    for model in ("auto", "shifted"):  # these run without it (auto then keeps the shifted still)
        check_dm_rig(_NoLadder(), load_config(None, SMALL + [f"dm_plan.spot_model={model}"]))


@pytest.fixture(scope="module")
def small_rig():
    cfg = load_config(None, SMALL)
    mirror, wfs, rig = build_dm(cfg)
    return cfg, wfs, rig


def test_a_simulated_hold_is_the_still_moved_by_the_static_shift(small_rig):
    cfg, wfs, rig = small_rig
    N = rig.n_actuators
    p = np.zeros(N)
    p[4], p[0] = 1.0, -0.5
    te, n = 2e-3, 8
    cap = rig.pattern_ladder(pattern=p, levels=[-2.0, 0.0, 2.0], n=n, exposure_s=te)
    assert cap.frames.shape == (3, n, 64, 64) and cap.exposure_s.shape == (3, n) and cap.frame_counter.unique().numel() == 3 * n
    c = cfg.camera
    e = (cap.frames - c.dark_level) * c.gain  # [3, n, H, W] e-
    off = torch.as_tensor(np.floor(wfs.rest_px - 7.5)).long()
    rate, var = e.mean(1) / te, camera_noise_std(e.mean(1), c.read_noise) ** 2 / (n * te**2)
    imgs, vars_ = crop_spots(rate, off, (16, 16)), crop_spots(var, off, (16, 16))
    still = crop_spots(rig._still_image_per_s(), off, (16, 16))  # the noiseless still (e-/s): the shift alone is tested
    red, shift, scale, dof = fit_shifted_still(imgs, vars_, still)
    G = rig.truth_D(0.0).real  # [2M, N] px per unit at DC
    M = G.shape[0] // 2
    want = np.stack([(G @ (u * p)).reshape(2, M).T for u in (-2.0, 0.0, 2.0)])  # [3, M, 2]
    assert np.abs(want).max() > 1.0  # the spots move by more than a pixel
    np.testing.assert_allclose(shift.numpy(), want, atol=0.03)  # a shifted still, where the mirror holds it
    assert torch.all(red < chi2_threshold(dof, red.numel())) and abs(float(scale.mean()) - 1) < 0.01
    with pytest.raises(ParameterError, match="levels"):
        rig.pattern_ladder(pattern=p, levels=[100.0], n=1, exposure_s=te)  # beyond the input limit
    with pytest.raises(ShapeError, match="pattern"):
        rig.pattern_ladder(pattern=p[:3], levels=[1.0], n=1, exposure_s=te)


def test_holds_leave_the_sweep_frames_as_they_were():
    cfg = load_config(None, SMALL)
    a, b = build_dm(cfg)[2], build_dm(cfg)[2]
    a.pattern_ladder(pattern=np.ones(a.n_actuators), levels=[-1.0, 1.0], n=3, exposure_s=1e-3)
    fa = a.pattern_sine(pattern=np.ones(a.n_actuators), freq_hz=200.0, amplitude=0.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=2)
    fb = b.pattern_sine(pattern=np.ones(b.n_actuators), freq_hz=200.0, amplitude=0.5, exposures_s=[1e-3], trigger_offset_s=0.0, n_repeats=2)
    assert torch.equal(fa.frames, fb.frames) and torch.equal(fa.trigger_time_s, fb.trigger_time_s)  # the holds draw their own noise



def test_the_holds_keep_one_pattern_s_raw_frames_at_a_time(small_rig):
    """``acquire_holds`` with one group per pattern reduces each pattern's frames to their cropped mean and
    variance before the next pattern is held (the whole ladder of issue 23's Hadamard plan held raw was
    5.5 GB of its estimated 8.44 GiB): when a pattern is held, no earlier pattern's frames are alive. The
    images are those of the frames held all at once (:func:`hold_images` of the list)."""
    import gc
    import weakref
    from types import SimpleNamespace

    from torchblur.identify.dm_ladder import acquire_holds, hold_images, ladder_key
    from torchblur.image.dark import DarkFrame

    cfg, wfs, rig = small_rig
    c = cfg.camera

    class Tracking:
        def __init__(self):
            self.refs, self.alive_before, self.copies = [], [], []

        def pattern_ladder(self, **kw):
            gc.collect()
            self.alive_before.append(sum(r() is not None for r in self.refs))
            cap = rig.pattern_ladder(**kw)
            self.refs.append(weakref.ref(cap.frames))
            self.copies.append(cap.frames.clone())
            return cap

    P, N = 4, rig.n_actuators
    patterns = np.sign(np.random.default_rng(2).normal(size=(P, N)))
    levels = np.tile([-1.0, -0.3, 0.3, 1.0], (P, 1))
    H, W = rig.frame_shape
    cal = SimpleNamespace(dark=DarkFrame(mean=torch.full((H, W), float(c.dark_level), dtype=_F64), read_noise=torch.tensor(1.0),
                                         hot_pixels=torch.zeros((H, W), dtype=torch.bool), n_frames=1),
                          gain=float(c.gain), read_noise_e=float(c.read_noise))
    offset, size = torch.as_tensor(np.floor(wfs.rest_px - 7.5)).long(), (16, 16)
    track = Tracking()
    got = acquire_holds(track, None, [ladder_key(p) for p in range(P)], patterns, levels, 3, 1e-3, cal, offset, size)
    assert track.alive_before == [0, 0, 0, 0]  # held one pattern at a time
    want = hold_images(track.copies, levels, 1e-3, cal, offset, size)  # the list form: every pattern's frames at once
    assert got.images.shape == (P, 4, wfs.n_valid, 16, 16) and bool(got.images.abs().sum() > 0)
    assert torch.equal(got.images, want.images) and torch.equal(got.variance, want.variance) and torch.equal(got.levels, want.levels)

def _gauss(h, cx, cy, sx, sy, total):
    y, x = torch.meshgrid(torch.arange(h, dtype=_F64), torch.arange(h, dtype=_F64), indexing="ij")
    return total / (2 * math.pi * sx * sy) * torch.exp(-((x - cx) ** 2 / (2 * sx**2) + (y - cy) ** 2 / (2 * sy**2)))


def test_a_changed_shape_fails_where_a_moved_still_passes():
    """The shift of a sampled Gaussian (sigma 1.8 px) moved by (1.3, -0.7) px is found; a
    spot that also widens by 10 % along x (what a curved surface under a lenslet does) fails the threshold."""
    g = torch.Generator().manual_seed(5)
    still = _gauss(16, 7.5, 7.5, 1.8, 1.8, 4e4)[None]  # [1, h, w] e-
    moved = _gauss(16, 8.8, 6.8, 1.8, 1.8, 4e4)
    wide = _gauss(16, 8.8, 6.8, 1.98, 1.8, 4e4)
    clean = torch.stack([moved, wide])[:, None]  # [2, 1, h, w]
    noisy = torch.poisson(clean.expand(200, 2, 1, 16, 16), generator=g) + 3.0 * torch.randn((200, 2, 1, 16, 16), generator=g, dtype=_F64)
    var = camera_noise_std(clean, 3.0) ** 2
    red, shift, scale, dof = fit_shifted_still(noisy, var, still)
    thr = chi2_threshold(dof, 400)
    assert dof == 16 * 16 - 3 and thr > 1 + 4 * math.sqrt(2 / dof)
    np.testing.assert_allclose(shift[:, 0, 0].mean(0).numpy(), [1.3, -0.7], atol=2e-3)
    assert 0.85 < float(red[:, 0].mean()) < 1.15 and bool((red[:, 0] < thr).all())  # chi2 of 253 dof: mean 1
    assert bool((red[:, 1] > thr).all())  # the wider spot is not a shifted still
    with pytest.raises(ShapeError, match="still"):
        fit_shifted_still(noisy, var, still[0])


SLOW = pytest.mark.skipif(not os.environ.get("TORCHBLUR_SLOW"), reason="a whole small DM run with the ladder, a re-fit and an export (35 s alone, 221 s on the shared 2 cores); TORCHBLUR_SLOW=1")


@SLOW
def test_a_ladder_run_is_recorded_refitted_and_exported(tmp_path, capsys):
    """The small mirror with ``dm_plan.spot_model=ladder`` through ``torchblur identify``: every pattern's
    ladder is its own recorded group; a re-fit replays them to the same actuators.csv; the recording
    exported as an outside DM recording (ladder rows) fits to the same actuators.csv through ``torchblur fit``."""
    from torchblur import cli
    from torchblur.identify import export_dm_recording
    from torchblur.identify.dm_outputs import read_actuators_csv
    from torchblur.identify.dm_outside import read_dm_recording

    run = tmp_path / "run"
    assert cli.main(["identify", "--out", str(run), "--quiet", *SMALL, "sweep.n=3", "report.figures=false",
                     "dm_plan.spot_model=ladder", "dm_plan.ladder_frames=8"]) in (0, 4)
    lines = [json.loads(ln) for ln in (run / "experiment" / "manifest.jsonl").read_text().splitlines()]
    held = sorted({ln["group"] for ln in lines if ln["kind"] == "dm_ladder"})
    assert held == [f"dm_ladder/{p:03d}" for p in range(16)]
    assert all(ln["call_shape"] == [13, 8] and len(ln["args"]["levels"]) == 13 for ln in lines if ln["kind"] == "dm_ladder")
    report = (run / "report.txt").read_text()
    assert "dm spot model: ladder of 16 patterns x 13 levels x 8 frames" in report
    live = (run / "dm" / "actuators.csv").read_text()
    assert cli.main(["fit", str(run), "--out", str(tmp_path / "refit"), "--quiet"]) in (0, 4)
    assert (tmp_path / "refit" / "dm" / "actuators.csv").read_text() == live  # the held groups replayed
    folder = export_dm_recording(run, tmp_path / "outside")
    rec = read_dm_recording(folder)
    assert rec.ladder_levels.shape == (16, 13) and rec.ladder_frames[0].shape == (13, 8, 64, 64)
    assert cli.main(["fit", str(folder), "--out", str(tmp_path / "fit"), "--quiet"]) in (0, 4)
    a, b = read_actuators_csv(run / "dm" / "actuators.csv"), read_actuators_csv(tmp_path / "fit" / "dm" / "actuators.csv")
    assert list(a["status"]) == list(b["status"])
    for col in ("dc_gain", "mode_hz", "damping", "delay_s", "dc_gain_std", "mode_hz_std", "damping_std", "delay_s_std"):
        np.testing.assert_allclose(b[col], a[col], rtol=1e-8)  # actuators.csv holds 9 significant digits


def test_a_sparse_ladder_run_keeps_the_spots_that_barely_move(tmp_path):
    """The small mirror on a sparse plan with the ladder: in each pattern most spots see none of its
    actuators (or the dead one) and barely move, so their ladder fits' shape command is the data's
    noise and lands beyond the levels. A spot that sees none of the pattern's actuators is not fitted
    (driven_spots: the demultiplexing does not use it); a driven one that barely moves is fitted by the
    spot's shifted still instead, and one lost response costs D only its own entry (it used to cost the
    whole slope row): no actuator is flagged failed (before: all 9, 35 fits left out), the dead one is
    reported dead; the verdict counts the driven problems."""
    from torchblur import cli
    from torchblur.config.budget import dm_plan
    from torchblur.dm.plans import driven_spots
    from torchblur.identify.dm_outputs import read_actuators_csv

    run = tmp_path / "run"
    cfg = [*SMALL, "sweep.n=3", "report.figures=false", "dm_plan.kind=sparse", "dm_plan.spot_model=ladder", "dm_plan.ladder_frames=8"]
    assert cli.main(["identify", "--out", str(run), "--quiet", *cfg]) in (0, 4)
    report = (run / "report.txt").read_text()
    refit = re.search(r"dm spot model: (\d+) spot fits that left the ladder's levels on spots barely moving", report)
    left = re.search(r"(\d+) spot fits' motion left the ladder's levels \(flagged", report)
    assert refit is not None and int(refit.group(1)) >= 5, report
    driven = driven_spots(dm_plan(load_config(None, cfg))[0])
    assert not driven.all() and f"0 of {int(driven.sum()) * 3} spot fits failed" in report, report
    grown = re.search(r"dm ladder common error: .* grows the static columns' stds by x([\d.]+) \(median", report)
    assert grown is not None and float(grown.group(1)) > 1.0, report  # the ladder's s, common to every frequency
    assert left is None or int(left.group(1)) <= 2, report
    verdict = next(ln for ln in report.splitlines() if ln.startswith("verdict:"))
    assert "all 9 actuators within tolerance" in verdict and "failed (" not in verdict, verdict
    assert list(read_actuators_csv(run / "dm" / "actuators.csv")["status"]).count("dead") == 1


def test_auto_takes_a_sparse_plan_for_the_ladder_and_a_refit_replays_it(tmp_path):
    """``dm_plan.kind=auto`` with the ladder: the plan auto chose (Hadamard: every pattern moves every
    actuator a spot sees) is replaced by a sparse one, seen at ``SPARSE_MARGIN`` of the support threshold
    (so a misregistered mirror's pairs are all in it), recorded with that threshold; a re-fit takes the
    same decision from the recorded test frames and gives the same actuators.csv; exported as an outside
    recording (the misregistered mirror), its fit checks the fitted geometry's support at the config's
    threshold, not the plan's (it flagged the pairs between the two), with the re-fit's exit status."""
    from torchblur import cli
    from torchblur.dm.plans import SPARSE_MARGIN
    from torchblur.identify.dm_record import PLAN_KEY

    run = tmp_path / "run"
    cfg = [*SMALL, "sweep.n=3", "report.figures=false", "dm_plan.spot_model=ladder", "dm_plan.ladder_frames=8",
           "dm.registration.shift_x=0.25", "dm.registration.rotation_deg=1.5", "dm.registration.magnification=1.03", "dm_plan.kind=auto"]
    assert load_config(None, cfg).dm_plan.kind == "auto"
    assert cli.main(["identify", "--out", str(run), "--quiet", *cfg]) in (0, 4)
    report = (run / "report.txt").read_text()
    assert "dm plan: sparse, not hadamard (auto, and the spots change shape" in report
    doc = json.loads((run / "experiment" / "experiment.json").read_text())[PLAN_KEY]
    assert doc["kind"] == "sparse" and doc["support_threshold"] == pytest.approx(0.01 * SPARSE_MARGIN)
    from torchblur.config.budget import estimate_run  # the run-size estimate counts the frames this run took: the sparse sweep, the holds
    lines = (run / "experiment" / "manifest.jsonl").read_text().splitlines()
    est = estimate_run(load_config(None, cfg))
    assert est["frames"] == len(lines) and est["hold_frames"] == sum(json.loads(ln)["kind"] == "dm_ladder" for ln in lines)
    live_rc = cli.main(["fit", str(run), "--out", str(tmp_path / "refit"), "--quiet"])
    assert live_rc in (0, 4)
    assert (tmp_path / "refit" / "dm" / "actuators.csv").read_text() == (run / "dm" / "actuators.csv").read_text()
    # exported, the plan's support (at the recorded threshold) and the support check (at the config's) stay apart
    from torchblur.identify import export_dm_recording

    folder = export_dm_recording(run, tmp_path / "outside")
    rc = cli.main(["fit", str(folder), "--out", str(tmp_path / "fit"), "--quiet"])
    report = (tmp_path / "fit" / "report.txt").read_text()
    assert "dm plan support:" not in report and "support lacks" not in report, report  # was: the check at the plan's own threshold
    assert rc == live_rc
    shifted = tmp_path / "shifted"  # the shifted still keeps auto's own choice
    assert cli.main(["identify", "--out", str(shifted), "--quiet", *cfg[:-3], "dm_plan.kind=auto", "dm_plan.spot_model=shifted"]) in (0, 4)
    assert "not hadamard" not in (shifted / "report.txt").read_text()


@pytest.mark.parametrize("old,new,error", [
    (",ladder,0,", ",ladder,7,", r"frames.csv line \d+, column pattern: expected a row of patterns.csv \(0..3\), got 7"),
    (",ladder,0,", ",ladder,,", r"frames.csv line \d+, column pattern: required for a ladder frame"),
    (",ladder,0,,0.001,,,1.0,,-1.0\n", ",ladder,0,,0.001,,,1.0,,-0.8333333333333334\n",
     r"frames.csv line \d+, column level: pattern 0 has \[1, 2\] frames per level; every level"),
    (",ladder,0,,0.001,,,1.0,,-1.0\n", ",ladder,0,,0.001,,,1.0,,nan\n", r"frames.csv line 13, column level: expected a finite number"),
])
def test_bad_ladder_rows_are_refused_naming_line_and_column(tmp_path, old, new, error):
    """A tiny outside DM recording with ladder rows, edited: each error names frames.csv's line and column."""
    from torchblur.hardware.errors import RecordingError
    from torchblur.identify.dm_outside import read_dm_recording, write_dm_recording

    rng = np.random.default_rng(0)
    P, K, H = 4, 13, 32
    frames = rng.integers(100, 200, size=(1, P, 2, H, H)).astype(float)  # every frame distinct (a copy is refused)
    dark, still = rng.integers(95, 105, size=(2, H, H)).astype(float), rng.integers(100, 200, size=(1, H, H)).astype(float)
    folder = write_dm_recording(tmp_path / "rec", dark=dark, still=still, still_exposure_s=1e-3,
                                patterns=[[1, 1, 1, 1], [1, -1, 1, -1], [1, 1, -1, -1], [1, -1, -1, 1]], freq_hz=[100.0],
                                amplitude=[1.0], frames=frames, start_s=np.zeros((1, P, 2)), duration_s=np.tile([3e-3, 8e-3], (1, P, 1)),
                                camera={"gain_e_per_adu": 1.0}, layout={"dm": {"n_across": 2}, "wfs": {"n_across": 2, "pitch_px": 16.0}},
                                ladder={"levels": np.tile(np.linspace(-1, 1, K), (P, 1)), "frames": rng.integers(100, 200, size=(P, K, 1, H, H)),
                                        "exposure_s": 1e-3})
    rec = read_dm_recording(folder)
    np.testing.assert_array_equal(rec.ladder_levels, np.tile(np.linspace(-1, 1, K), (P, 1)))
    assert len(rec.ladder_frames) == P and rec.ladder_frames[2].shape == (K, 1, H, H) and rec.ladder_exposure_s == 1e-3
    text = (folder / "frames.csv").read_text()
    assert old in text
    (folder / "frames.csv").write_text(text.replace(old, new, 1))
    with pytest.raises(RecordingError, match=error):
        read_dm_recording(folder)
