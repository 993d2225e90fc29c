"""identify with excitation.kind=multisine on the simulated rig (3 tones, one designed image
set), the CLI outputs, the recording replayed offline, the config keys, and the serial rig's
multisine call against the emulator."""
import json
import math

import numpy as np
import pytest

from torchblur.config import load_config
from torchblur.errors import ConfigError
from torchblur.identify.run import identify
from readback import assert_reads_back
from reference import truth_errors

KEYS = ["excitation.kind=multisine", "excitation.tones=3", "sweep.freq_hz=[150,200,250]", "camera.height=32", "camera.width=64",
        "model.max_order=2", "seed=4"]




@pytest.fixture(scope="module")
def run(tmp_path_factory):
    cfg = load_config("configs/identify_multisine.yaml", KEYS)  # the shipped config, reduced (its keys are the defaults but the sweep)
    rec = tmp_path_factory.mktemp("ms") / "experiment"
    return cfg, identify(cfg, progress=False, record=rec), rec


def test_three_tones_from_one_designed_image_set(run):
    cfg, res, _ = run
    em, ep, z = truth_errors(res)
    np.testing.assert_allclose(res.frf.freq_hz, [150, 200, 250])
    assert em.max() < 0.01 and ep.max() < 1.0 and z.max() < 5  # 1 %, 1 degree, 5 stds: as the sine sweep
    assert len(res.groups) == 1 and len(res.fit) == 1 and bool(res.fit[0].converged)
    g = res.groups[0]
    assert g["harmonics"] == [3, 4, 5] and g["base_freq_hz"] == 50.0
    n_fitted = g["images"].stop - g["images"].start
    assert res.images.shape[0] == n_fitted and res.images_used == n_fitted + g["pilot_images"]
    assert n_fitted <= cfg.excitation.max_images  # the design's size (a sine sweep takes 12 for 3 points)
    d = g["design"]
    assert np.all(d.amplitude_rel_std < 0.01) and np.all(d.phase_std < math.radians(1))
    assert any("multisine group 0" in m for m in res.log)


def test_cli_outputs_and_replay_of_the_recording(run, tmp_path):
    from torchblur.hardware.recording import Experiment, ReplayRig
    from torchblur.identify.outputs import write_outputs
    from torchblur.identify.report import run_summary, verdict_summary

    cfg, res, rec = run
    v = write_outputs(cfg, res, tmp_path, 1.0, "test")
    assert_reads_back(tmp_path, json.dumps({**run_summary(res, tmp_path, 1.0), **verdict_summary(v)}))  # every output
    names = {p.name for p in tmp_path.iterdir()}
    assert {"frf.csv", "frf.json", "bode.png", "model.json", "report.txt", "residuals.png"} <= names
    assert "multisine group 0" in (tmp_path / "report.txt").read_text()
    model = json.loads((tmp_path / "model.json").read_text())
    assert model["seed"] == 4 and [j["name"] for j in model["judgement"]] == ["two-step"]  # the verdict's judgement
    summary = json.loads(json.dumps(run_summary(res, tmp_path, 1.0)))  # the --json line of a multisine run
    assert summary["points"] == res.frf.valid.size and summary["valid_points"] >= 1 and summary["elapsed_s"] == 1.0
    exp = Experiment.open(rec, writable=False)
    assert exp.has("sweep/multisine/000")
    again = identify(cfg, rig=ReplayRig(exp), record=exp, progress=False)
    np.testing.assert_allclose(again.frf.response, res.frf.response, rtol=1e-9)


@pytest.mark.parametrize("key, value", [("kind", "chirp"), ("tones", 0), ("tones", 16), ("images", 1), ("max_images", 1),
                                        ("target_std", 0), ("snap_tol", 0.5), ("tone_px", -1)])
def test_config_rejects_bad_multisine_keys(key, value):
    with pytest.raises(ConfigError, match=f"excitation.{key}"):
        load_config(None, [f"excitation.{key}={value}"])


def test_config_defaults_keep_the_sine_sweep():
    cfg = load_config(None, [])
    assert cfg.excitation.kind == "sine"
    ms = load_config("configs/identify_multisine.yaml", [])
    assert ms.excitation.kind == "multisine" and ms.excitation.tones >= 2


def test_serial_rig_multisine_matches_the_simulated_rig():
    """The serial rig's multisine call through the emulator (MULTI with the base tone first,
    one POWER per exposure) gives the simulated rig's frames and trigger times."""
    from test_hardware_emulator import Emu

    from torchblur.hardware.serial_rig import SerialRig
    from torchblur.identify.run import build_simulated_rig

    emu = Emu()
    try:
        rig = SerialRig.open(emu.info["serial"], emu.info["frames"], timeout_s=5.0)
        kw = dict(freq_hz=[150.0, 250.0], amplitude=[0.05, 0.03], phase_rad=[0.25, -1.0], exposures_s=[2e-3],
                  trigger_offset_s=[3e-3], n_repeats=2, base_freq_hz=50.0, power=[1.5])
        try:
            cap = rig.multisine(**kw)
        finally:
            rig.close()
    finally:
        emu.stop()
    ref = build_simulated_rig(load_config(None, ["camera.height=40", "camera.width=40", "seed=1"])).multisine(**kw)
    assert cap.frames.shape == ref.frames.shape == (1, 2, 40, 40)
    np.testing.assert_allclose(cap.trigger_time_s.numpy(), ref.trigger_time_s.numpy(), atol=1e-9)
    assert float((cap.frames - ref.frames).abs().max()) <= 1.0  # the same frames (to 1 ADU: 10-digit tones on the wire)
    assert cap.meta["kind"] == "multisine" and cap.meta["base_freq_hz"] == 50.0
