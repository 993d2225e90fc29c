"""model.json of a direct fit read back: the document :meth:`torchblur.sysid.direct.DirectModelFit.to_dict`
writes, checked key by key, into the fields of a :class:`~torchblur.sysid.direct.DirectModelFit`.

Schema ``torchblur.direct_model_fit``:

* version 2 (written now): the fit's parameters, stds, covariance and start; ``structure`` (the
  model's factors, :class:`~torchblur.sysid.parametric._Structure`), ``units``, and the per-point
  ``used``, ``scale`` and ``background``; read back exactly.
* version 1 (before ``structure`` and the per-point results were written): refused by name
  here (the model cannot be rebuilt from it); :func:`torchblur.identify.read_outputs.read_outputs`
  still reads it as a checked document.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from torchblur.errors import InputTypeError, ParameterError, check_schema_version, excerpt
from torchblur.sysid.parametric import _Structure

__all__ = ["DIRECT_SCHEMA", "DIRECT_SCHEMA_VERSION", "DIRECT_UNITS", "direct_fields_from_dict"]

DIRECT_SCHEMA = "torchblur.direct_model_fit"
#: the version :meth:`DirectModelFit.to_dict` writes (1: before ``structure`` and the per-point results)
DIRECT_SCHEMA_VERSION = 2
#: the units of the document's numbers
DIRECT_UNITS = {"params": "by name: *_omega_n and *_rate rad/s, *_zeta 1, delay_s s, gains and feedthrough output unit per "
                          "input unit", "covariance": "products of the params' units", "delay_s": "s", "poles": "rad/s",
                "zeros": "rad/s", "modes": "omega_n rad/s, freq_hz Hz, zeta 1, gain output unit per input unit",
                "scale": "1 (per point)", "background": "ADU (per point)"}
_REQUIRED = frozenset({"schema", "schema_version", "units", "form", "structure", "param_names", "params", "std", "covariance",
                       "start_params", "num", "den", "delay_s", "poles", "zeros", "modes", "cost", "dof", "reduced_chi2",
                       "noise_estimated", "converged", "n_iter", "n_points_used", "n_excluded", "used", "scale", "background"})
#: what the CLI writes beside the fit in model.json (read, checked for type, not kept)
_CLI_KEYS = frozenset({"torchblur_version", "seed", "judgement", "model_passed"})


def _floats(v, key: str, shape=None) -> np.ndarray:
    try:
        a = np.array([[math.nan if x is None else x for x in r] for r in v] if shape is not None and len(shape) == 2 else
                     [math.nan if x is None else x for x in v], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{key}: expected a list of numbers as to_dict writes it, got {excerpt(v)} ({exc})") from None
    if shape is not None and a.shape != shape:
        raise ParameterError(f"{key}: expected shape {shape}, got {a.shape}")
    return a


def _scalar(doc: dict, key: str, kind):
    v = doc[key]
    if kind is float:
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ParameterError(f"{key}: expected a number or null, got {excerpt(v)}")
        return math.nan if v is None else float(v)
    if not isinstance(v, kind) or (kind is int and isinstance(v, bool)):
        raise ParameterError(f"{key}: expected {kind.__name__}, got {excerpt(v)}")
    return v


def _structure(doc: dict, names: tuple) -> _Structure:
    s = doc["structure"]
    fields = {f.name for f in dataclasses.fields(_Structure)}
    if not isinstance(s, dict) or set(s) != set(fields):
        raise ParameterError(f"structure: expected the keys {sorted(fields)}, got {excerpt(s)}")
    for k, v in s.items():
        want = str if k == "form" else bool if k in ("feedthrough", "fit_delay") else int
        if not isinstance(v, want) or (want is int and (isinstance(v, bool) or v < -64 or v > 64)):
            raise ParameterError(f"structure.{k}: expected {want.__name__}{' in [-64, 64]' if want is int else ''}, got {excerpt(v)}")
    struct = _Structure(**s)
    if struct.form != doc["form"] or tuple(n for n, _ in struct.names_transforms()) != names:
        raise ParameterError(f"structure: its parameters {[n for n, _ in struct.names_transforms()]} are not param_names {list(names)}")
    return struct


def direct_fields_from_dict(doc) -> dict:
    """The :class:`~torchblur.sysid.direct.DirectModelFit` fields (``_struct`` included) of a
    version-2 document; ParameterError naming the key otherwise."""
    if not isinstance(doc, dict):
        raise InputTypeError(f"doc: expected a JSON object, got {type(doc).__name__}")
    if doc.get("schema") != DIRECT_SCHEMA:
        raise ParameterError(f"schema: expected {DIRECT_SCHEMA!r}, got {excerpt(doc.get('schema'))}")
    v = doc.get("schema_version")
    if v == 1:
        raise ParameterError("schema_version: 1 (written before the model's structure and per-point results were kept) cannot "
                             "rebuild a DirectModelFit; read it as a document with torchblur.identify.read_outputs.read_outputs")
    check_schema_version(v, (DIRECT_SCHEMA_VERSION,))
    unknown, missing = set(doc) - _REQUIRED - _CLI_KEYS, _REQUIRED - set(doc)
    if unknown or missing:
        raise ParameterError(f"doc: unknown keys {sorted(unknown)}, missing keys {sorted(missing)} for schema_version 2")
    if doc["units"] != DIRECT_UNITS:
        raise ParameterError(f"units: expected {DIRECT_UNITS}, got {excerpt(doc['units'])}")
    names = doc["param_names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ParameterError(f"param_names: expected a list of strings, got {excerpt(names)}")
    names, P = tuple(names), len(names)
    used = doc["used"]
    if not isinstance(used, list) or not all(isinstance(x, bool) for x in used):
        raise ParameterError(f"used: expected a list of true/false, got {excerpt(used)}")
    F = len(used)
    background = None if doc["background"] is None else _floats(doc["background"], "background", (F,))
    return {"form": _scalar(doc, "form", str), "param_names": names, "params": _floats(doc["params"], "params", (P,)),
            "covariance": _floats(doc["covariance"], "covariance", (P, P)), "std": _floats(doc["std"], "std", (P,)),
            "start_params": _floats(doc["start_params"], "start_params", (P,)), "delay_s": _scalar(doc, "delay_s", float),
            "cost": _scalar(doc, "cost", float), "dof": _scalar(doc, "dof", int), "reduced_chi2": _scalar(doc, "reduced_chi2", float),
            "noise_estimated": _scalar(doc, "noise_estimated", bool), "converged": _scalar(doc, "converged", bool),
            "n_iter": _scalar(doc, "n_iter", int), "used": np.array(used, dtype=bool), "n_excluded": _scalar(doc, "n_excluded", int),
            "scale": _floats(doc["scale"], "scale", (F,)), "background": background, "_struct": _structure(doc, names)}
