"""Every machine-readable file of a run folder reads back, and the copies agree: the check the
tests that already made a run (default, direct, MIMO, DM, outside recording) call on it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from torchblur.identify.config import config_to_yaml
from torchblur.identify.read_outputs import read_outputs
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import TransferFunctionFit


def assert_reads_back(out: Path) -> dict:
    """Read ``out`` with :func:`read_outputs`; frf.json, frf.mat and frf.csv give the same
    response (csv: to its printed precision, stds too), the model evaluates where the response
    was measured, config.yaml is the config it reads as, DM matrices match the DM response.
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
    if "config.yaml" in got:
        text = (out / "config.yaml").read_text()
        assert config_to_yaml(got["config.yaml"]) == "".join(ln for ln in text.splitlines(True) if not ln.startswith("#"))
    if "dm/frf.json" in got:
        d, act = got["dm/frf.json"], got["dm/actuators.csv"]
        assert got["dm/interaction_matrix.npy"].shape == d.response.shape[:2] == (d.n_outputs, act["actuator"].size)
        assert got["dm/command_matrix.npy"].shape == (d.n_inputs, d.n_outputs)
        assert got["dm/command_matrix.json"]["n_kept"] + got["dm/command_matrix.json"]["n_unseen"] == d.n_inputs
        if "dm/registration.json" in got:  # the registration fitted to D0 (torchblur.dm.registration)
            assert got["dm/registration.json"]["registration"].magnification > 0
    return got
