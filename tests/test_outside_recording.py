"""Outside recordings (issue 15): a lab's own folder (frames.csv, TIFF frames, recording.yaml;
docs/outside_recordings.md) through `torchblur fit FOLDER`: the same numbers as identify on the
same frames, the same numbers as psf_from_still + fit_sinusoid called directly on HCIPy frames,
and bad folders refused with the file, line and column named."""
import csv
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from outside_folder import write_outside
from torchblur.errors import ConfigError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.hardware.errors import RecordingError
from torchblur.hardware.outside import read_outside_recording
from torchblur.hardware.recording import Experiment
from torchblur.cli import main
from torchblur.config import load_config
from torchblur.identify.outside import fitted_direction, identify_outside, outside_config
from torchblur.identify.run import identify
from torchblur.identify.sweep import inflate_std
from torchblur.image.preprocess import dark_frame, subtract_dark
from torchblur.image.psf_from_still import psf_from_still
from torchblur.render.camera import CameraNoise, camera_noise_std
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow
from torchblur.sysid.frequency_response import FrequencyResponse
from readback import assert_reads_back

ANGLE = 0.3  # rad: the simulated spot moves along (cos, sin) of it
DIRECTION = [math.cos(ANGLE), math.sin(ANGLE)]
SIM = ["sweep.freq_hz=[20,200,600]", "camera.height=40", "camera.width=40", "seed=5",
       f"plant.direction=[{DIRECTION[0]!r},{DIRECTION[1]!r}]", f"fit.axis=[{DIRECTION[0]!r},{DIRECTION[1]!r}]"]


def export(exp: Experiment, res, cfg, folder: Path, *, trigger_phase: bool = False) -> Path:
    """identify's own recording ``exp`` (its dark, still and sweep frames, as recorded) written
    as an outside recording, with the windows, amplitudes and laser powers identify used."""
    (_, _, dark), = exp.load_calls("dark")
    (_, args, still), = exp.load_calls("psf")
    points = []
    for k in range(len(res.amplitude)):
        (_, a, cap), = exp.load_calls(f"sweep/x/{k:03d}")
        E, R, H, W = cap.frames.shape
        points.append(dict(freq_hz=a["freq_hz"], amplitude=float(res.amplitude[k]), power=float(res.power[k]), R=R,
                           frames=cap.frames.reshape(E * R, H, W).numpy(), start_s=res.windows.start[k].numpy(),
                           duration_s=res.windows.duration[k].numpy()))
    camera = dict(gain_e_per_adu=cfg.camera.gain, saturation_adu=float(res.saturation.saturation_adu), latency_s=res.latency_s,
                  latency_std_s=res.latency_std_s, jitter_s=cfg.camera.jitter_s, trigger_delay_s=1e-4)
    return write_outside(folder, dark=dark.frames.numpy(), still=still.frames.numpy(), still_exposure_s=args["exposure_s"],
                         points=points, camera=camera, dtype=np.uint16, trigger_phase=trigger_phase)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    cfg = load_config(None, SIM)
    res = identify(cfg, progress=False, record=d / "run")
    exp = Experiment.open(d / "run", writable=False)
    return dict(cfg=cfg, res=res, folder=export(exp, res, cfg, d / "outside"),
                phase_folder=export(exp, res, cfg, d / "phase", trigger_phase=True), root=d)


def _listing(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def test_fit_folder_equals_identify_on_the_same_frames(sim, capsys):
    folder, out = sim["folder"], sim["root"] / "fit_out"
    before = _listing(folder)
    rc = main(["fit", str(folder), "--out", str(out), "--quiet", "--json", f"fit.axis=[{DIRECTION[0]!r},{DIRECTION[1]!r}]"])
    last = (out / "report.txt").read_text().strip().splitlines()[-1]
    # 3 points: the model may have too few degrees of freedom for the verdict's model rule (exit 4); the points never
    assert rc == 0 or (rc == 4 and last.startswith("verdict: all 3 points within tolerance; the two-step model fails (")), last
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["points"] == 3 and summary["valid_points"] == 3 and summary["max_error_over_std"] is None
    frf, ref = FrequencyResponse.from_json(out / "frf.json"), sim["res"].frf
    np.testing.assert_allclose(frf.response, ref.response, rtol=1e-10, atol=0)
    np.testing.assert_allclose(frf.cov, ref.cov, rtol=1e-10, atol=1e-300)
    assert frf.meta["recording"] == "outside" and frf.meta["input_unit"] == "input unit"
    assert {"frf.csv", "frf.json", "frf.mat", "model.json", "report.txt", "bode.png", "residuals.png", "config.yaml",
            "source.json"} <= {p.name for p in out.iterdir()}
    model = json.loads((out / "model.json").read_text())
    assert "error" not in model and model["den"] == pytest.approx(sim["res"].model.to_dict()["den"], rel=1e-8)
    assert _listing(folder) == before  # the recording is never written
    assert "fit of the outside recording" in (out / "report.txt").read_text()
    assert "seed" not in (out / "report.txt").read_text().splitlines()[0]  # frames from outside have no seed to stamp
    assert assert_reads_back(out)["source.json"]["frames"] > 0  # every output reads back


def test_trigger_phase_and_delays_give_the_same_windows(sim):
    """frames.csv's trigger_phase_rad with recording.yaml's trigger_delay_s + latency_s is the
    same window as window_start_s: the same response to round-off."""
    a, b = (read_outside_recording(sim[k]) for k in ("folder", "phase_folder"))
    for pa, pb in zip(a.points, b.points):
        np.testing.assert_allclose(pb.start_s, pa.start_s, rtol=0, atol=1e-15)
    cfg = outside_config(b, [f"fit.axis=[{DIRECTION[0]!r},{DIRECTION[1]!r}]"])
    res = identify_outside(b, cfg, progress=False)
    np.testing.assert_allclose(res.frf.response, sim["res"].frf.response, rtol=1e-7)


def test_measured_axis_agrees_with_the_true_direction(sim):
    """fit.axis=measure (the default) on an outside recording: the direction fitted on both
    image axes is within 0.5 deg of the true one, and the response moves by a small fraction
    of its std."""
    rec = read_outside_recording(sim["folder"])
    res = identify_outside(rec, outside_config(rec), progress=False)
    got = math.atan2(res.direction[1], res.direction[0])
    assert abs(math.degrees(got - ANGLE)) < 0.5
    ref = sim["res"].frf
    z_m = np.abs(res.frf.magnitude - ref.magnitude) / ref.magnitude_std
    z_p = np.abs(res.frf.phase - ref.phase) / ref.phase_std
    assert z_m.max() < 0.3 and z_p.max() < 0.3
    assert any(line.startswith("axis: ") and "both image axes" in line for line in res.log)
    # identify's 256 dark frames (calibration.N_DARK) for 16 still frames: more than the 4 per still frame the dark's own
    # noise needs, so no warning (with the former 16 it said "16 dark frames for 16 still frames ... at least 64")
    assert not any(line.startswith("dark: warning") for line in res.log)


def test_fitted_direction_of_line_motions():
    """Points of one line motion (any phase, either sign of the amplitude) give its direction,
    pointed toward +x; the std follows the amplitude stds; no converged point gives None."""
    import types

    th = -2.0  # the motion along (cos, sin) of it: toward -x, so the answer is its opposite
    M = torch.tensor([[3.0], [5.0], [2.0]], dtype=torch.float64) * torch.tensor([abs(math.cos(th)), abs(math.sin(th))], dtype=torch.float64)
    # cos and sin < 0: both axes move in phase (the same sign), at any phase; the last point's amplitude is negative
    phi = torch.tensor([[0.3, 0.3], [1.0, 1.0], [-2.0 + math.pi, -2.0 - math.pi]], dtype=torch.float64)
    fit = types.SimpleNamespace(amplitude=M, phase=phi, amplitude_std=torch.full_like(M, 0.01), converged=torch.ones(3, dtype=torch.bool))
    u, std, ratio = fitted_direction(fit)
    assert u[0] > 0 and math.atan2(u[1], u[0]) == pytest.approx(th + math.pi, abs=1e-12) and ratio == pytest.approx(0, abs=1e-12)
    assert 0 < std < 0.01 / 2
    fit.converged = torch.zeros(3, dtype=torch.bool)
    assert fitted_direction(fit)[0] is None


# ------------------------------------------------------------------------------ HCIPy frames


@pytest.fixture(scope="module")
def hcipy_folders(tmp_path_factory):
    hf = pytest.importorskip("hcipy_frames")
    d = tmp_path_factory.mktemp("hcipy")
    out = []
    for k in range(2):
        p = hf.make_problem(300 + k, rotated=bool(k % 2), n_time=1000, n_still=16)
        rng = np.random.default_rng(50 + k)
        dark = hf.camera_noise(np.zeros((16,) + p["frames"].shape[-2:]), rng)
        folder = write_outside(d / f"p{k}", dark=dark, still=p["still"], still_exposure_s=p["still_exposure"],
                               camera=dict(gain_e_per_adu=1.0),
                               points=[dict(freq_hz=p["freq_hz"], amplitude=1.0, frames=p["frames"], start_s=p["window"].start.numpy(),
                                            duration_s=p["window"].duration.numpy())])
        out.append((p, folder, dark))
    return out


def _direct(p, dark_frames, direction):
    """psf_from_still + fit_sinusoid called directly, as identify's steps do: dark frame and
    read noise from the darks, the PSF of the dark-subtracted still (background 0, camera noise),
    the fit weighted by the camera's noise model (fit_sinusoid's model-weighted refit), the kernel's own noise in the std."""
    dark = dark_frame(torch.as_tensor(dark_frames))
    rn = float(dark.read_noise)
    still = subtract_dark(torch.as_tensor(p["still"]), dark)
    sp = psf_from_still(still, p["still_exposure"], camera_noise_std(still.mean(0), rn), kind="auto", background=0.0)
    frames = subtract_dark(torch.as_tensor(p["frames"]), dark)
    psf = KernelPSF(sp.psf.kernel) if sp.kind == "kernel" else sp.psf
    fit = fit_sinusoid(frames, psf, p["window"], torch.tensor(p["omega"], dtype=torch.float64), axes=direction,
                       noise=CameraNoise(read_noise_e=rn), mask=torch.ones(frames.shape, dtype=torch.bool), fit_scale=True)
    return inflate_std(fit, sp.kernel_noise_factor(p["window"].duration)), sp.kind


def test_hcipy_frames_through_fit_folder_equal_the_direct_call(hcipy_folders, tmp_path):
    for k, (p, folder, dark) in enumerate(hcipy_folders):
        axis = f"fit.axis=[{p['direction'][0]!r},{p['direction'][1]!r}]"
        # one point: no model can be fitted, and a run without its model is not trustworthy (exit 4); the point is fine
        assert main(["fit", str(folder), "--out", str(tmp_path / f"o{k}"), "--quiet", axis, "report.figures=false"]) == 4
        last = (tmp_path / f"o{k}" / "report.txt").read_text().strip().splitlines()[-1]
        assert last.startswith("verdict: all 1 points within tolerance; the two-step model fails (its fit failed"), last
        frf = FrequencyResponse.from_json(tmp_path / f"o{k}" / "frf.json")
        fit, kind = _direct(p, dark, torch.tensor(p["direction"], dtype=torch.float64))
        assert frf.meta["psf"] == kind == "kernel"
        assert frf.magnitude[0, 0, 0] == pytest.approx(float(fit.amplitude), rel=1e-9)
        assert frf.phase[0, 0, 0] == pytest.approx(float(fit.phase), abs=1e-9)
        assert frf.magnitude_std[0, 0, 0] == pytest.approx(float(fit.amplitude_std), rel=1e-7)
        # and against HCIPy's truth (the direct benchmark's bounds)
        assert abs(frf.magnitude[0, 0, 0] / p["M"] - 1) < 0.01
        dphi = math.remainder(frf.phase[0, 0, 0] - p["phi"], 2 * math.pi)
        assert abs(math.degrees(dphi)) < 1.0
        assert abs(frf.magnitude[0, 0, 0] - p["M"]) < 4 * frf.magnitude_std[0, 0, 0] and abs(dphi) < 4 * frf.phase_std[0, 0, 0]


# ------------------------------------------------------------------------------ bad folders


@pytest.fixture
def good(tmp_path):
    rng = np.random.default_rng(0)
    frames = lambda n: rng.integers(90, 110, size=(n, 12, 16)).astype(np.uint16)  # noqa: E731
    pts = [dict(freq_hz=f, amplitude=0.5, R=2, frames=frames(4), start_s=[1e-3, 1e-3, 1e-3, 1e-3], duration_s=[2e-3, 2e-3, 5e-3, 5e-3])
           for f in (50.0, 100.0)]
    return write_outside(tmp_path / "rec", dark=frames(3), still=frames(2), still_exposure_s=1e-3, points=pts,
                         camera=dict(gain_e_per_adu=2.0))


def _edit_csv(folder: Path, fn) -> None:
    with open(folder / "frames.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    rows = fn(rows)
    with open(folder / "frames.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)


def _set(line: int, col: str, value):
    """Set column ``col`` of file line ``line`` (1 = the header)."""
    def fn(rows):
        rows[line - 1][rows[0].index(col)] = value
        return rows
    return fn


def test_a_good_folder_reads(good):
    rec = read_outside_recording(good)
    assert rec.frame_shape == (12, 16) and rec.dark.shape == (3, 12, 16) and rec.still.shape == (2, 12, 16)
    assert [p.freq_hz for p in rec.points] == [50.0, 100.0] and all(p.E == 2 and p.R == 2 for p in rec.points)
    assert rec.camera.saturation_adu == 65535.0  # uint16 frames, none given
    assert "uint16 maximum" in rec.saturation_source


# the data lines: 2-4 dark, 5-6 still, 7-10 the 50 Hz point, 11-14 the 100 Hz point
@pytest.mark.parametrize("edit, words", [
    (_set(2, "kind", "flat"), ["line 2", "column kind", "flat"]),
    (_set(7, "freq_hz", "nan"), ["line 7", "column freq_hz", "finite"]),
    (_set(8, "freq_hz", ""), ["line 8", "column freq_hz", "required"]),
    (_set(9, "exposure_s", "-1e-3"), ["line 9", "column exposure_s", "> 0"]),
    (_set(9, "amplitude", "abc"), ["line 9", "column amplitude", "number"]),
    (_set(10, "amplitude", "0.7"), ["line 10", "column amplitude", "one amplitude per frequency"]),
    (_set(10, "page", "99"), ["line 10", "column page", "page 99"]),
    (_set(10, "page", "1.5"), ["line 10", "column page", "integer"]),
    (_set(11, "file", "../sweep.tif"), ["line 11", "column file", "leaves"]),
    (_set(11, "file", "missing.tif"), ["line 11", "column file", "missing.tif"]),
    (_set(8, "page", "0"), ["line 8", "file / page", "already line 7"]),
    (_set(12, "window_start_s", "2e-3"), ["lines", "100 Hz", "repeats"]),
    (_set(6, "exposure_s", "2e-3"), ["line", "exposure_s", "still"]),
    (lambda rows: [[c for i, c in enumerate(r) if i != rows[0].index("kind")] for r in rows], ["line 1", "'kind'", "missing"]),
    (lambda rows: [rows[0] + ["axis"]] + [r + ["x"] for r in rows[1:]], ["column axis", "two-input"]),
    (lambda rows: [rows[0] + ["temp"]] + [r + ["1"] for r in rows[1:]], ["column 'temp'", "unknown column"]),
    (lambda rows: rows[:2] + rows[4:], ["1 row(s) of kind 'dark'", "at least 2"]),
    (lambda rows: rows + [rows[-1][:3]], ["line 15", "cells"]),
])
def test_bad_csv_is_refused_with_its_place_named(good, edit, words):
    _edit_csv(good, edit)
    with pytest.raises(RecordingError) as err:
        read_outside_recording(good)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_both_window_columns_on_one_row_are_refused(good):
    _edit_csv(good, lambda rows: [rows[0] + ["trigger_phase_rad"]] + [r + (["0.5"] if i == 6 else [""]) for i, r in enumerate(rows[1:])])
    with pytest.raises(RecordingError, match=r"line 8, columns window_start_s / trigger_phase_rad: .*exactly one"):
        read_outside_recording(good)


@pytest.mark.parametrize("text, words", [
    ("read_noise_e: 3.0\n", ["gain_e_per_adu", "required"]),
    ("gain_e_per_adu: -2\n", ["gain_e_per_adu", "> 0"]),
    ("gain_e_per_adu: .nan\n", ["gain_e_per_adu", "finite"]),
    ("gain_e_per_adu: 2\ngain: 3\n", ["recording.yaml", "gain", "unknown"]),
    ("gain_e_per_adu: 2\njitter_s: -1e-6\n", ["jitter_s", ">= 0"]),
    ("gain_e_per_adu: 2\nlatency_s: ${oc.env:HOME}\n", ["recording.yaml", "interpolation"]),
    ("- 1\n- 2\n", ["recording.yaml", "mapping"]),
])
def test_bad_yaml_is_refused_with_the_key_named(good, text, words):
    (good / "recording.yaml").write_text(text)
    with pytest.raises(RecordingError) as err:
        read_outside_recording(good)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_colour_tiffs_are_refused(good):
    import tifffile

    tifffile.imwrite(good / "still.tif", np.zeros((12, 16, 3), dtype=np.uint16), photometric="rgb")
    with pytest.raises(RecordingError, match=r"still.tif: colour frames"):
        read_outside_recording(good)


def test_missing_yaml_and_bad_tiff_are_refused(good):
    (good / "sweep.tif").write_bytes(b"not a tiff at all")
    with pytest.raises(RecordingError, match=r"sweep.tif: not a readable TIFF"):
        read_outside_recording(good)
    os.remove(good / "recording.yaml")
    with pytest.raises(RecordingError, match=r"recording.yaml: missing; .*gain_e_per_adu"):
        read_outside_recording(good)


def test_nan_pixels_are_refused(good):
    import tifffile

    a = np.full((4, 12, 16), 100.0)
    a[2, 3, 4] = np.nan
    tifffile.imwrite(good / "still.tif", a, photometric="minisblack")
    _edit_csv(good, lambda rows: rows)  # unchanged: still.tif pages 0-1 now float, the others uint16
    with pytest.raises(RecordingError, match=r"one shape and dtype"):
        read_outside_recording(good)
    for name in ("dark.tif", "sweep.tif"):
        tifffile.imwrite(good / name, np.full((8, 12, 16), 100.0), photometric="minisblack")
    tifffile.imwrite(good / "still.tif", a[[2, 0]], photometric="minisblack")
    with pytest.raises(RecordingError, match=r"still.tif page 0 \(frames.csv line 5\): NaN"):
        read_outside_recording(good)


def test_cli_refuses_a_folder_that_is_neither(tmp_path, capsys):
    (tmp_path / "rec").mkdir()
    assert main(["fit", str(tmp_path / "rec"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "neither a torchblur run" in err and "frames.csv" in err
    assert not (tmp_path / "o").exists()


def test_cli_refuses_out_inside_the_recording_and_other_overrides(good, capsys):
    before = _listing(good)
    assert main(["fit", str(good), "--out", str(good / "res")]) == 2
    assert "inside the recording" in capsys.readouterr().err
    assert main(["fit", str(good), "--out", str(good.parent / "o"), "camera.gain=3"]) == 2
    assert "camera.gain: an outside recording takes only fit.*, model.*, report.* and seed" in capsys.readouterr().err
    assert _listing(good) == before


def test_outside_config_refuses_other_sections(good):
    rec = read_outside_recording(good)
    with pytest.raises(ConfigError, match=r"sweep.n: an outside recording"):
        outside_config(rec, ["sweep.n=3"])
    cfg = outside_config(rec, ["fit.loss=poisson", "seed=3"])
    assert cfg.fit.loss == "poisson" and cfg.seed == 3 and cfg.camera.gain == 2.0 and cfg.sweep.freq_hz == [50.0, 100.0]


def test_saturated_still_frames_are_refused(good):
    """A clipped still spot would give a wrong PSF, and every fit with it a wrong answer: refused."""
    (good / "recording.yaml").write_text("gain_e_per_adu: 2.0\nsaturation_adu: 105\n")
    rec = read_outside_recording(good)
    with pytest.raises(RecordingError, match=r"still frames have \d+ saturated pixel\(s\).*shorter exposure_s"):
        identify_outside(rec, progress=False)


def test_an_outside_recording_with_one_exposure_is_resolved_or_flagged(sim):
    """Issue 24: the same frames with only the first exposure (30 % of the period) of each point:
    `torchblur fit FOLDER` chooses each phase branch by continuity; every point is within 5 of
    its stds of the simulated truth or flagged alias (then the run is not trustworthy)."""
    from torchblur.sysid.flags import ALIAS

    exp, res, cfg = Experiment.open(sim["root"] / "run", writable=False), sim["res"], sim["cfg"]
    (_, _, dark), = exp.load_calls("dark")
    (_, args, still), = exp.load_calls("psf")
    points = []
    for k in range(len(res.amplitude)):
        (_, a, cap), = exp.load_calls(f"sweep/x/{k:03d}")
        E, R, H, W = cap.frames.shape
        points.append(dict(freq_hz=a["freq_hz"], amplitude=float(res.amplitude[k]), power=float(res.power[k]), R=R,
                           frames=cap.frames[:1].reshape(R, H, W).numpy(), start_s=res.windows.start[k, :R].numpy(),
                           duration_s=res.windows.duration[k, :R].numpy()))
    camera = dict(gain_e_per_adu=cfg.camera.gain, saturation_adu=float(res.saturation.saturation_adu), latency_s=res.latency_s,
                  latency_std_s=res.latency_std_s, jitter_s=cfg.camera.jitter_s, trigger_delay_s=1e-4)
    folder = write_outside(sim["root"] / "one_exposure", dark=dark.frames.numpy(), still=still.frames.numpy(),
                           still_exposure_s=args["exposure_s"], points=points, camera=camera, dtype=np.uint16)
    rec = read_outside_recording(folder)
    out = identify_outside(rec, outside_config(rec, [f"fit.axis=[{DIRECTION[0]!r},{DIRECTION[1]!r}]"]), progress=False)
    assert any(line.startswith("alias: 3 point(s) with one exposure") for line in out.log)
    _, _, z = out.frf.errors_against(res.truth)
    flagged = ((out.frf.flags & ALIAS) != 0)[0, 0]
    assert not (z[0, 0] > 5)[~flagged].any(), (z, flagged)
    from torchblur.identify.verdict import verdict

    assert verdict(out.frf, truth=res.truth).trustworthy == (not flagged.any() and not (z > 5).any())
