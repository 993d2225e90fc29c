"""Every machine-readable file of a run folder reads back, and the copies agree: the check the
tests that already made a run call on it (one per shipped config, ``READBACK_TESTS``), with
each model carrying the verdict's judgement."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchblur.config import config_to_yaml
from torchblur.identify.read_outputs import SUMMARY_SCHEMA, check_document, read_outputs
from torchblur.sysid.direct import DirectModelFit
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.model_check import judge_fit
from torchblur.sysid.tf_fit import TransferFunctionFit

#: each shipped config (configs/identify_*.yaml) -> the test that reads back the outputs of a
#: reduced run of its kind, sharing a run the suite makes anyway. The runs: default, mimo,
#: multisine, antiresonance: the shipped file with a short sweep and a small frame; direct: the
#: default plant with model.direct=true (6 points); DM: a 3x3-actuator mirror on a 4x4 lenslet
#: grid (tests/test_dm_run.py's SMALL); spots: the spots route on a 1x4 row (tests/test_spots.py's EDGE).
READBACK_TESTS = {
    "identify_default.yaml": "test_read_outputs.py::test_the_default_runs_outputs_read_back",
    "identify_direct.yaml": "test_direct.py::test_cli_identify_with_direct_writes_both_models",
    "identify_mimo.yaml": "test_mimo.py::test_short_mimo_sweep_matches_the_truth",
    "identify_dm.yaml": "test_dm_record.py::test_refit_gives_the_live_outputs_bit_for_bit",
    "identify_multisine.yaml": "test_multisine_identify.py::test_cli_outputs_and_replay_of_the_recording",
    "identify_spots.yaml": "test_spots.py::test_spots_run_outputs_read_back_with_each_channels_judgement",
    "identify_antiresonance.yaml": "test_identify.py::test_cli_identify_writes_every_output",
}


def assert_judged(doc: dict, model) -> None:
    """``doc`` (a model.json document) carries the verdict's judgement of ``model`` (what it
    reads back as): one per channel (:func:`~torchblur.sysid.model_check.judge_fit`), each
    the rule applied to the model's own reduced chi2 and dof, and ``model_passed`` = all passed."""
    name = "two-step" if isinstance(model, TransferFunctionFit) else doc["judgement"][0]["name"]
    want = judge_fit(model, name)
    got = doc["judgement"]
    assert [j["name"] for j in got] == [j.name for j in want], (got, want)
    for j, w in zip(got, want):
        assert j["passed"] is w.passed and j["dof"] == w.dof and "sysid.model_check" in j["rule"]
        assert j["reduced_chi2"] is None or np.isclose(j["reduced_chi2"], w.reduced_chi2, rtol=1e-12)
    assert doc["model_passed"] is all(j["passed"] for j in got)
    if "rejected_direct_model" in doc:  # the direct model set aside: judged, failed
        rejected = doc["rejected_direct_model"]
        assert rejected["model_passed"] is False and rejected["judgement"]


def assert_reads_back(out: Path, summary: str | None = None) -> dict:
    """Read ``out`` with :func:`read_outputs`; frf.json, frf.mat and frf.csv give the same
    response (csv: to its printed precision, stds too), the model evaluates where the response
    was measured, each model carries the verdict's judgement (:func:`assert_judged`), config.yaml
    is the config it reads as, DM matrices match the DM response and every actuator has a status;
    ``summary``: the run's ``--json`` line, checked against its schema and report.txt.
    Returns what was read."""
    got = read_outputs(out)
    names = {p.name for p in out.iterdir()}
    machine = {"frf.json", "frf.csv", "frf.mat", "model.json", "model_two_step.json", "config.yaml", "source.json"} & names
    assert machine <= set(got), machine - set(got)
    if "frf.json" in got:
        frf = got["frf.json"]
        assert isinstance(frf, FrequencyResponse)
        mat, csv = got["frf.mat"], got["frf.csv"]
        np.testing.assert_array_equal(mat.response, frf.response)
        assert mat.meta == frf.meta and mat.input_labels == frf.input_labels and mat.output_labels == frf.output_labels
        np.testing.assert_array_equal(mat.flags, frf.flags)
        np.testing.assert_allclose(csv.response, frf.response, rtol=1e-12, atol=0)
        np.testing.assert_allclose(csv.magnitude_std, frf.magnitude_std, rtol=1e-12)
        np.testing.assert_array_equal(csv.flags, frf.flags)
        assert frf.input_labels != frf.output_labels or frf.n_inputs > 2  # the command labelled apart from the motion
        two_step = got.get("model_two_step.json", got.get("model.json"))
        if isinstance(two_step, TransferFunctionFit):
            h = two_step.frequency_response(frf.omega)
            assert np.isfinite(h).all() and h.shape[-1] == frf.omega.size
    for name in ("model.json", "model_two_step.json"):
        if isinstance(got.get(name), (TransferFunctionFit, DirectModelFit)):
            assert_judged(json.loads((out / name).read_text()), got[name])
    if summary is not None:  # the --json line
        doc = check_document(json.loads(summary), SUMMARY_SCHEMA, "--json")
        assert doc["out"] == str(out) and isinstance(doc["trustworthy"], bool) and doc["verdict"].startswith("verdict: ")
        assert doc["verdict"] == (out / "report.txt").read_text().rstrip().splitlines()[-1]
    if "config.yaml" in got:
        text = (out / "config.yaml").read_text()
        assert config_to_yaml(got["config.yaml"]) == "".join(ln for ln in text.splitlines(True) if not ln.startswith("#"))
    if "dm/frf.json" in got:
        d, act = got["dm/frf.json"], got["dm/actuators.csv"]
        assert got["dm/interaction_matrix.npy"].shape == d.response.shape[:2] == (d.n_outputs, act["actuator"].size)
        assert got["dm/command_matrix.npy"].shape == (d.n_inputs, d.n_outputs)
        assert got["dm/command_matrix.json"]["n_kept"] + got["dm/command_matrix.json"]["n_unseen"] == d.n_inputs
        assert set(act["status"]) <= {"ok", "weak", "dead"} and act["reduced_chi2"].size == act["actuator"].size  # each judged
        if "dm/registration.json" in got:  # the registration fitted to D0 (torchblur.dm.registration)
            assert got["dm/registration.json"]["registration"].magnification > 0
    return got
