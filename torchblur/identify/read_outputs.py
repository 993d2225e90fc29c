"""Read a run's output folder back into the objects that wrote it.

:func:`read_outputs` reads every machine-readable file ``torchblur identify`` and
``torchblur fit`` write (a single-spot, MIMO, spots, multisine, direct or DM run):

=========================== ==========================================================
file                        read back as
=========================== ==========================================================
``frf.json``                :class:`~torchblur.sysid.frequency_response.FrequencyResponse`
``frf.csv``                 the same (stds kept, correlation lost: the CSV has no column)
``frf.mat``                 the same (:meth:`FrequencyResponse.from_mat`)
``model.json``              :class:`~torchblur.sysid.tf_fit.TransferFunctionFit`; with
                            ``model.direct`` the :class:`~torchblur.sysid.direct.DirectModelFit`
                            (a version-1 direct document, written before its structure
                            was kept: the checked document) and ``model_two_step.json``
                            the TransferFunctionFit; a failed fit's ``{"error": ...}`` as it is
``config.yaml``             :class:`~torchblur.config.IdentifyConfig` (validated)
``source.json``             a dict (schema checked; re-fits)
``demo.json``               a dict (schema checked; ``torchblur demo``)
``dm/frf.json``             FrequencyResponse ``[2M, N, F]``
``dm/actuators.csv``        a dict of columns (:func:`torchblur.identify.dm_outputs.read_actuators_csv`)
``dm/*.npy``                numpy arrays (no pickles)
``dm/command_matrix.json``  a dict (schema checked)
``dm/registration.json``    a dict (schema checked), ``registration`` a
                            :class:`~torchblur.dm.registration.Registration`
=========================== ==========================================================

Each JSON document carries ``schema`` and ``schema_version``; a version this torchblur does
not know is refused by name (:class:`~torchblur.errors.ParameterError`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchblur.errors import ParameterError, check_schema_version
from torchblur.config import IdentifyConfig, load_dataclass, validate
from torchblur.dm.registration import read_registration_json
from torchblur.identify.dm_outputs import COMMAND_MATRIX_SCHEMA, read_actuators_csv
from torchblur.sysid.direct import DirectModelFit
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import TransferFunctionFit

__all__ = ["read_outputs", "check_document", "DIRECT_MODEL_SCHEMA", "SOURCE_SCHEMA", "SUMMARY_SCHEMA", "DEMO_SCHEMA"]

#: model.json of a direct fit (:meth:`torchblur.sysid.direct.DirectModelFit.to_dict`): versions read
DIRECT_MODEL_SCHEMA = ("torchblur.direct_model_fit", (1, 2))
#: source.json of a re-fit or of an outside recording's fit
SOURCE_SCHEMA = ("torchblur.source", (1,))
#: the ``--json`` summary line
SUMMARY_SCHEMA = ("torchblur.run_summary", (1,))
#: ``torchblur demo``'s demo.json
DEMO_SCHEMA = ("torchblur.demo", (1,))


def check_document(doc, schema: tuple, where: str) -> dict:
    """``doc`` if it is a JSON object of ``schema`` = ``(name, versions read)``; else
    ParameterError naming ``where``, the schema and the version."""
    name, versions = schema
    if not isinstance(doc, dict) or doc.get("schema") != name:
        got = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        raise ParameterError(f"{where}: schema: expected {name!r}, got {got!r}")
    check_schema_version(doc.get("schema_version"), versions, f"{where}: ")
    return doc


def _json(path: Path):
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ParameterError(f"{path}: not JSON ({exc})") from None


def _model(path: Path):
    """model.json / model_two_step.json: a TransferFunctionFit, a DirectModelFit (a version-1
    direct document: the checked document), or a failed fit's ``{"error": ...}`` document."""

    doc = _json(path)
    if isinstance(doc, dict) and "schema" not in doc and "error" in doc:
        return doc
    direct = isinstance(doc, dict) and doc.get("schema") == DIRECT_MODEL_SCHEMA[0]
    if direct and check_document(doc, DIRECT_MODEL_SCHEMA, str(path))["schema_version"] == 1:
        return doc
    try:
        if direct:
            return DirectModelFit.from_dict(doc)
        return TransferFunctionFit.from_dict(doc)
    except ParameterError as exc:
        raise ParameterError(f"{path}: {exc}") from None


def _config(path: Path):
    """config.yaml: the IdentifyConfig, validated as a run's (an outside recording's fit,
    ``rig.kind = "outside"``, is made by :func:`~torchblur.identify.outside.outside_config`, not
    by a rig: its rig section is not checked)."""
    cfg = load_dataclass(IdentifyConfig, str(path), trusted=False)
    if cfg.rig.kind != "outside":
        validate(cfg)
    return cfg


def _dm(d: Path) -> dict:
    got = {"dm/frf.json": FrequencyResponse.from_json(d / "frf.json"), "dm/actuators.csv": read_actuators_csv(d / "actuators.csv"),
           "dm/command_matrix.json": check_document(_json(d / "command_matrix.json"), COMMAND_MATRIX_SCHEMA,
                                                    str(d / "command_matrix.json"))}
    for p in sorted(d.glob("*.npy")):
        got[f"dm/{p.name}"] = np.load(p, allow_pickle=False)
    if (d / "registration.json").is_file():
        got["dm/registration.json"] = read_registration_json(d / "registration.json")
    return got


def read_outputs(out) -> dict:
    """Every machine-readable output in the run folder ``out`` -> ``{relative path: object}``
    (the table in the module docstring; files a run did not write are absent).

    Raises:
        ParameterError / ConfigError: a file that does not read back, naming it.
    """
    out = Path(out)
    got: dict = {}
    readers = {"frf.json": FrequencyResponse.from_json, "frf.csv": FrequencyResponse.from_csv, "frf.mat": FrequencyResponse.from_mat,
               "model.json": _model, "model_two_step.json": _model,
               "config.yaml": _config,
               "source.json": lambda p: check_document(_json(p), SOURCE_SCHEMA, str(p)),
               "demo.json": lambda p: check_document(_json(p), DEMO_SCHEMA, str(p))}
    for name, read in readers.items():
        if (out / name).is_file():
            got[name] = read(out / name)
    if (out / "dm").is_dir():
        got.update(_dm(out / "dm"))
    return got
