"""model.json: the documents of a two-step fit (:class:`~torchblur.sysid.tf_fit.TransferFunctionFit`,
schema ``torchblur.transfer_function_fit``) and of a direct fit
(:class:`~torchblur.sysid.direct.DirectModelFit`, schema ``torchblur.direct_model_fit``), written
and read back key by key. Non-finite numbers are written as ``null`` and read back as NaN; complex
roots as ``{"real": [...], "imag": [...]}``.

``torchblur.transfer_function_fit``: version 2 (written now) adds ``units`` and the parameters'
uncertainty; version 1 files read too. ``torchblur.direct_model_fit``: version 2 (written now) keeps
the model's ``structure`` (:class:`~torchblur.sysid.parametric._Structure`) and the per-point
``used``, ``scale`` and ``background``, read back exactly; version 1 (written before them) is refused
by name here (the model cannot be rebuilt from it); :func:`torchblur.identify.read_outputs.read_outputs`
still reads it as a checked document.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from torchblur.errors import ParameterError, excerpt
from torchblur.sysid.frequency_response_io import check_document, json_floats
from torchblur.sysid.parametric import _Structure

__all__ = ["DIRECT_SCHEMA", "DIRECT_SCHEMA_VERSION", "DIRECT_UNITS", "direct_fields_from_dict", "direct_fit_to_dict", "TF_SCHEMA",
           "TF_SCHEMA_KEYS", "TF_SCHEMA_VERSION", "TF_UNITS", "tf_fit_fields_from_dict", "tf_fit_to_dict"]

TF_SCHEMA = "torchblur.transfer_function_fit"
#: the schema version :meth:`TransferFunctionFit.to_dict` writes
TF_SCHEMA_VERSION = 2
#: the units of model.json's numbers (version 2 writes them; version 1 files meant the same)
TF_UNITS = {"s": "rad/s", "num": "output unit per input unit (the response's), coefficients of s", "den": "coefficients of s",
            "delay_s": "s", "poles": "rad/s", "zeros": "rad/s", "dc_gain": "output unit per input unit"}
_TF_FIT_KEYS = frozenset({"num", "den", "delay_s", "n_poles", "n_zeros", "chi2", "dof", "reduced_chi2", "rms_relative_error",
                          "poles", "zeros", "dc_gain", "weighting", "delay_estimated", "input_labels", "output_labels"})
#: model.json's keys by schema_version, in one place: ``{version: (required, optional)}``. A key
#: is refused only when its file's own version does not know it; a version not listed is refused
#: by name. The optional keys are what the CLI writes beside the fit (its stamp, and the points the
#: model was not fitted to: :func:`torchblur.identify.outputs.left_out_points`); read, checked, not kept.
#: A new key goes into a new version here (and into :func:`tf_fit_to_dict`).
_TF_CLI_KEYS = frozenset({"torchblur_version", "seed", "left_out_points", "poor_fit_points_kept"})
#: the model's parameters with their uncertainty and the orders compared (all or none:
#: :func:`_uncertainty_from_dict`), and the verdict's judgement beside the fit (read, checked, not kept)
TF_UNCERTAINTY_KEYS = ("param_names", "params", "std", "covariance", "candidates", "order_criterion")
_TF_VERDICT_KEYS = ("judgement", "model_passed", "rejected_direct_model", "direct_model_error")
TF_SCHEMA_KEYS = {
    1: (_TF_FIT_KEYS | {"schema", "schema_version"}, _TF_CLI_KEYS),
    2: (_TF_FIT_KEYS | {"schema", "schema_version", "units"},
        _TF_CLI_KEYS | set(TF_UNCERTAINTY_KEYS) | set(_TF_VERDICT_KEYS)),
}
_TF_CHANNEL_KINDS = {"num": "coeffs", "den": "coeffs", "delay_s": "float", "n_poles": "int", "n_zeros": "int",
                     "chi2": "float", "dof": "int", "reduced_chi2": "float", "rms_relative_error": "float",
                     "poles": "roots", "zeros": "roots"}

DIRECT_SCHEMA = "torchblur.direct_model_fit"
#: the version :meth:`DirectModelFit.to_dict` writes (1: before ``structure`` and the per-point results)
DIRECT_SCHEMA_VERSION = 2
#: the units of the document's numbers
DIRECT_UNITS = {"params": "by name: *_omega_n and *_rate rad/s, *_zeta 1, delay_s s, gains and feedthrough output unit per "
                          "input unit", "covariance": "products of the params' units", "delay_s": "s", "poles": "rad/s",
                "zeros": "rad/s", "modes": "omega_n rad/s, freq_hz Hz, zeta 1, gain output unit per input unit",
                "scale": "1 (per point)", "background": "ADU (per point)"}
_DIRECT_REQUIRED = frozenset({"schema", "schema_version", "units", "form", "structure", "param_names", "params", "std",
                              "covariance", "start_params", "num", "den", "delay_s", "poles", "zeros", "modes", "cost",
                              "dof", "reduced_chi2", "noise_estimated", "converged", "n_iter", "n_points_used",
                              "n_excluded", "used", "scale", "background"})
#: what the CLI writes beside the direct fit in model.json (read, checked for type, not kept)
_DIRECT_CLI_KEYS = frozenset({"torchblur_version", "seed", "judgement", "model_passed"})


# ----------------------------------------------------------------------------- shared
def json_roots(r) -> dict:
    """Complex roots ``[n]`` as ``{"real": [n], "imag": [n]}``."""
    return {"real": json_floats(r.real), "imag": json_floats(r.imag)}


def _json_value(v):
    """A value of the fit (nested lists, arrays, complex roots, numbers) as JSON."""
    if isinstance(v, np.ndarray) and np.iscomplexobj(v):
        return json_roots(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_json_value(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    return json_floats(v)


def _floats(v, key: str, shape=None) -> np.ndarray:
    """A list (or, with a 2-d ``shape``, a list of lists) of numbers or None (NaN) of ``shape``."""
    try:
        a = np.array([[math.nan if x is None else x for x in r] for r in v] if shape is not None and len(shape) == 2 else
                     [math.nan if x is None else x for x in v], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{key}: expected a list of numbers as to_dict writes it, got {excerpt(v)} ({exc})") from None
    if shape is not None and a.shape != shape:
        raise ParameterError(f"{key}: expected shape {shape}, got {a.shape}")
    return a


# ------------------------------------------------------------------ the two-step fit
def tf_fit_to_dict(fit) -> dict[str, Any]:
    """The document of a :class:`~torchblur.sysid.tf_fit.TransferFunctionFit` (its ``to_dict``)."""
    doc: dict[str, Any] = {"schema": TF_SCHEMA, "schema_version": TF_SCHEMA_VERSION, "units": dict(TF_UNITS)}
    for f in ("num", "den", "delay_s", "n_poles", "n_zeros", "chi2", "dof", "reduced_chi2", "rms_relative_error", "dc_gain",
              "poles", "zeros"):
        doc[f] = _json_value(getattr(fit, f))
    doc["weighting"] = fit.weighting
    doc["delay_estimated"] = bool(fit.delay_estimated)
    doc["input_labels"] = list(fit.input_labels)
    doc["output_labels"] = list(fit.output_labels)
    if fit.params is not None:
        doc.update(_uncertainty_dict(fit))
    return doc


def _uncertainty_dict(fit) -> dict[str, Any]:
    """model.json's keys of the parameters' uncertainty and the order selection:
    ``param_names``, ``params``, ``std``, ``covariance`` (per channel, nested [O][I] for MIMO),
    ``candidates`` (rows of :attr:`candidates`) and ``order_criterion``."""

    def per_channel(f, fn):
        v = getattr(fit, f)
        return fn(v) if fit.is_siso else [[fn(x) for x in row] for row in v]

    def rows(table):
        ints = ("n_poles", "n_zeros", "n_params", "dof")
        return [{k: (bool(v) if k == "chosen" else int(v) if k in ints else json_floats(v)) for k, v in r.items()}
                for r in table]

    return {"param_names": per_channel("param_names", list), "params": per_channel("params", _json_value),
            "std": per_channel("std", _json_value), "covariance": per_channel("covariance", _json_value),
            "candidates": per_channel("candidates", rows), "order_criterion": fit.order_criterion}


def tf_fit_fields_from_dict(doc) -> dict[str, Any]:
    """The :class:`~torchblur.sysid.tf_fit.TransferFunctionFit` fields but ``dc_gain`` of a
    document (see :meth:`~torchblur.sysid.tf_fit.TransferFunctionFit.from_dict`); InputTypeError
    where ``doc`` is not a dict, ParameterError naming the key otherwise."""
    why = f" (the file says: {doc['error']})" if isinstance(doc, dict) and "error" in doc else ""
    check_document(doc, TF_SCHEMA, TF_SCHEMA_KEYS, TF_UNITS, why=why)
    for key in ("left_out_points", "poor_fit_points_kept"):
        if key in doc and not (isinstance(doc[key], list) and all(isinstance(x, dict) for x in doc[key])):
            raise ParameterError(f"{key}: expected a list of objects, got {excerpt(doc[key])}")
    labels = {k: tuple(doc[k]) for k in ("input_labels", "output_labels")}
    for k, v in labels.items():
        if not v or not all(isinstance(x, str) for x in v):
            raise ParameterError(f"{k}: expected a non-empty list of strings, got {excerpt(doc[k])}")
    n_o, n_i = len(labels["output_labels"]), len(labels["input_labels"])
    siso = n_o == n_i == 1

    def channels(key):
        v, kind = doc[key], _TF_CHANNEL_KINDS[key]
        if siso:
            return _from_json_value(v, key, kind)
        if not isinstance(v, list) or len(v) != n_o or any(not isinstance(r, list) or len(r) != n_i for r in v):
            raise ParameterError(f"{key}: expected nested lists [O][I] = [{n_o}][{n_i}] for a MIMO fit")
        return [[_from_json_value(x, key, kind) for x in row] for row in v]

    return {**{k: channels(k) for k in _TF_CHANNEL_KINDS}, "weighting": str(doc["weighting"]),
            "delay_estimated": bool(doc["delay_estimated"]), **labels, **_uncertainty_from_dict(doc, siso, n_o, n_i)}


def _uncertainty_from_dict(doc: dict, siso: bool, n_o: int, n_i: int) -> dict[str, Any]:
    """The :attr:`TransferFunctionFit.covariance` fields read back from ``doc`` (all of
    :data:`TF_UNCERTAINTY_KEYS`, or none: a file written before they existed)."""
    have = [k for k in TF_UNCERTAINTY_KEYS if k in doc]
    if not have:
        return {}
    if len(have) != len(TF_UNCERTAINTY_KEYS):
        raise ParameterError(f"doc: missing keys {sorted(set(TF_UNCERTAINTY_KEYS) - set(have))} (it has {sorted(have)})")

    def one(names, vals, std, cov, rows):
        try:
            names = tuple(str(n) for n in names)
            rows = tuple({k: (math.nan if v is None else v) for k, v in dict(r).items()} for r in rows)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"param_names, candidates: expected them as to_dict writes them ({exc})") from None
        P = len(names)
        return names, _floats(vals, "params", (P,)), _floats(std, "std", (P,)), _floats(cov, "covariance", (P, P)), rows

    keys = ("param_names", "params", "std", "covariance", "candidates")
    if siso:
        names, vals, std, cov, rows = one(*(doc[k] for k in keys))
    else:
        if any(not isinstance(doc[k], list) or len(doc[k]) != n_o or any(len(r) != n_i for r in doc[k]) for k in keys):
            raise ParameterError(f"params: expected nested lists [O][I] = [{n_o}][{n_i}] for a MIMO fit")
        chans = [[one(*(doc[k][o][i] for k in keys)) for i in range(n_i)] for o in range(n_o)]
        names, vals, std, cov, rows = ([[c[j] for c in row] for row in chans] for j in range(5))
    return {"param_names": names, "params": vals, "std": std, "covariance": cov, "candidates": rows,
            "order_criterion": str(doc["order_criterion"])}


def _from_json_value(v, key: str, kind: str):
    """One channel's value of :func:`tf_fit_to_dict` read back: ``kind`` "float" (None = NaN),
    "int", "coeffs" (a list of floats) or "roots" (``{"real", "imag"}``)."""
    try:
        if kind == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(type(v).__name__)
            return v
        if kind == "float":
            return math.nan if v is None else float(v)
        if kind == "coeffs":
            return [float(x) for x in v]
        re, im = _floats(v["real"], key), _floats(v["imag"], key)
        if re.shape != im.shape:
            raise ValueError("real and imag differ in length")
        return re + 1j * im
    except (TypeError, ValueError, KeyError) as exc:
        raise ParameterError(f"{key}: expected a {kind} value as to_dict writes it, got {excerpt(v)} ({exc})") from None


# ---------------------------------------------------------------------- the direct fit
def direct_fit_to_dict(fit) -> dict[str, Any]:
    """The document of a :class:`~torchblur.sysid.direct.DirectModelFit` (its ``to_dict``)."""
    return {
        "schema": DIRECT_SCHEMA,
        "schema_version": DIRECT_SCHEMA_VERSION,
        "units": dict(DIRECT_UNITS),
        "form": fit.form,
        "structure": dataclasses.asdict(fit._struct),
        "param_names": list(fit.param_names),
        "params": json_floats(fit.params),
        "std": json_floats(fit.std),
        "covariance": json_floats(fit.covariance),
        "start_params": json_floats(fit.start_params),
        "num": json_floats(fit.num),
        "den": json_floats(fit.den),
        "delay_s": json_floats(fit.delay_s),
        "poles": json_roots(fit.poles),
        "zeros": json_roots(fit.zeros),
        "modes": [{k: json_floats(v) for k, v in m.items()} for m in fit.modal_parameters()],
        "cost": json_floats(fit.cost),
        "dof": int(fit.dof),
        "reduced_chi2": json_floats(fit.reduced_chi2),
        "noise_estimated": bool(fit.noise_estimated),
        "converged": bool(fit.converged),
        "n_iter": int(fit.n_iter),
        "n_points_used": int(fit.used.sum()),
        "n_excluded": int(fit.n_excluded),
        "used": [bool(x) for x in fit.used],
        "scale": json_floats(fit.scale),
        "background": None if fit.background is None else json_floats(fit.background),
    }


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
    if isinstance(doc, dict) and doc.get("schema") == DIRECT_SCHEMA and doc.get("schema_version") == 1:
        raise ParameterError("schema_version: 1 (written before the model's structure and per-point results were kept) cannot "
                             "rebuild a DirectModelFit; read it as a document with torchblur.identify.read_outputs.read_outputs")
    check_document(doc, DIRECT_SCHEMA, {DIRECT_SCHEMA_VERSION: (_DIRECT_REQUIRED, _DIRECT_CLI_KEYS)}, DIRECT_UNITS)
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
