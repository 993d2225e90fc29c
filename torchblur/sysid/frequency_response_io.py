"""The files of a :class:`~torchblur.sysid.frequency_response.FrequencyResponse`: CSV, JSON and MAT.

Writers take the response ``frf``; readers take the class to build (``cls``, the caller's
``FrequencyResponse`` or a subclass) and a path, and treat the file as untrusted input: a file
that is not of its format raises :class:`~torchblur.errors.ParameterError` (or
``InputTypeError``/``ShapeError``) naming ``path``. The response's own methods
(``to_csv``/``from_csv``, ``to_json``/``from_json``, ``to_dict``/``from_dict``,
``to_mat``/``from_mat``) call these.

* CSV (:func:`write_csv`/:func:`read_csv`): one plain header row, no comment lines, floats
  written with ``repr`` (shortest string that reads back to the same float64). SISO columns are
  ``freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg``; MIMO adds two leading columns
  ``output,input`` holding the labels, rows ordered by output, input, then frequency.
  Phase is wrapped to (-180, 180]. The reader ignores extra columns after these (the
  CLI's frf.csv adds ``torchblur_version,seed``). CSV keeps the standard deviations but **loses the
  magnitude-phase correlation**: the reader returns a diagonal covariance (correlation 0).
  A SISO CSV also drops the labels, and no CSV keeps ``meta``.
* MAT (:func:`write_mat`/:func:`read_mat`): MATLAB variables for ``idfrd``/``tfest`` (see
  :func:`write_mat`), phase and its std in radians, a ``units`` struct.
* JSON (:func:`write_json`/:func:`read_json`, the document :func:`to_dict`/:func:`from_dict`):
  everything, bit-exact, under a versioned schema
  ``{"schema": "torchblur.sysid.frequency_response", "schema_version": 2, "units": {...}, ...}``
  (version 1, without ``units``, still reads; a newer one is refused by name). Non-finite
  numbers (failed points, unknown covariance) are written as ``null`` so the file is strict
  JSON.

Per-point adequacy (``frf.flags``, ``frf.reduced_chi2``, bits in :mod:`torchblur.sysid.flags`):
where a response carries it (``frf.has_adequacy``), the CSV gets two more columns
``reduced_chi2,flags`` after the five (``flags`` as names, ``"poor_fit|timing"``, empty for
none), the JSON the keys ``flags`` and ``reduced_chi2`` ([O, I, F] nested lists), the MAT file
the variables ``flags`` (int32) and ``reduced_chi2`` (always). Files without them load with
flags 0 and reduced chi2 NaN.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from typing import Any

import numpy as np

from torchblur.errors import ParameterError, ShapeError, TorchblurError, check_schema_version, check_type, excerpt
from torchblur.files import read_bounded
from torchblur.sysid.flags import flag_names, parse_flags

__all__ = ["MAX_FILE_BYTES", "SCHEMA_VERSION", "UNITS", "check_document", "from_dict", "json_floats", "read_csv", "read_json", "read_mat",
           "to_dict", "write_csv", "write_json", "write_mat"]

_SCHEMA = "torchblur.sysid.frequency_response"
#: the version :meth:`FrequencyResponse.to_dict` writes (2: with ``units``; 1 files still read)
SCHEMA_VERSION = 2
#: the units of frf.json's and frf.mat's numbers (version 2 writes them; version 1 meant the
#: same): the output and input units themselves are ``meta["output_unit"]`` / ``meta["input_unit"]``
UNITS = {"omega": "rad/s", "freq_hz": "Hz", "response": "output unit per input unit (absolute, not dB)",
         "magnitude_std": "output unit per input unit", "phase": "rad", "phase_std": "rad",
         "cov": "[[magnitude^2, magnitude rad], [magnitude rad, rad^2]]"}
_JSON_REQUIRED = frozenset({"schema", "schema_version", "omega", "response_real", "response_imag"})
_JSON_OPTIONAL = frozenset({"cov", "output_labels", "input_labels", "meta", "flags", "reduced_chi2"})
#: frf.json's keys by schema_version, ``{version: (required, optional)}`` (:func:`check_document`)
_JSON_KEYS = {1: (_JSON_REQUIRED, _JSON_OPTIONAL), 2: (_JSON_REQUIRED | {"units"}, _JSON_OPTIONAL)}
_CSV_SISO_HEADER = ["freq_hz", "magnitude", "phase_deg", "magnitude_std", "phase_std_deg"]
_CSV_MIMO_HEADER = ["output", "input"] + _CSV_SISO_HEADER
_CSV_ADEQUACY = ["reduced_chi2", "flags"]  # written after the five where the response carries them

MAX_FILE_BYTES = 256 * 2**20  # the largest frf.csv / frf.json read (a 10,000-point 8x8 response is ~30 MB)


def _naming_path(exc: Exception, path) -> Exception:
    """``exc`` again (same class), its message led by the file's ``path``."""
    msg = str(exc)
    msg = msg[len("path: "):] if msg.startswith("path: ") else msg
    return type(exc)(f"path {os.fspath(path)!r}: {msg}")


def _read_text(path: str | os.PathLike) -> str:
    """The UTF-8 text of the file ``path``; ParameterError naming it when it is larger than
    :data:`MAX_FILE_BYTES` or not text."""
    where = f"path {os.fspath(path)!r}"
    data = read_bounded(path, MAX_FILE_BYTES, where)  # the opening rule (torchblur.files): a regular file, bounded
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ParameterError(f"{where}: not UTF-8 text (byte {exc.start}); a binary file?") from None


def json_floats(a: np.ndarray):
    """Nested lists of float, with ``None`` in place of NaN/Inf."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 0:
        v = float(a)
        return v if math.isfinite(v) else None
    return [json_floats(x) for x in a]


# ------------------------------------------------------------------------ MAT
def write_mat(frf, path: str | os.PathLike) -> None:
    """Write ``frf`` to a MATLAB ``.mat`` file (``scipy.io.savemat``, format 5) for MATLAB users.

    Variables (F frequencies, O outputs, I inputs; MATLAB sees the same shapes):

    * ``freq_hz`` [1, F], ``omega`` [1, F] rad/s;
    * ``H`` complex [O, I, F] (``H(o, i, f)`` = gain from input i to output o, absolute
      units; NaN = failed point), the layout of ``idfrd(H, omega, 0)`` for ``tfest``;
    * ``magnitude_std``, ``phase_std`` (rad), ``correlation`` [O, I, F] (NaN = unknown);
    * ``input_labels`` [1, I], ``output_labels`` [1, O]: cell arrays of strings;
    * ``meta``: the JSON text of ``frf.meta`` (a string);
    * ``flags`` int32 [O, I, F] (bits of :mod:`torchblur.sysid.flags`, 0 = none) and
      ``reduced_chi2`` [O, I, F] (NaN = unknown);
    * ``units``: a struct naming each variable's unit (:data:`UNITS`), ``schema`` and
      ``schema_version`` (the JSON's).

    A SISO response keeps the [1, 1, F] shape, as in MATLAB's ``idfrd``. :func:`read_mat`
    reads it back (the covariance from the stds and the correlation).
    """
    import scipy.io

    def cell(labels):
        c = np.empty((1, len(labels)), dtype=object)
        c[0, :] = list(labels)
        return c

    scipy.io.savemat(
        path,
        {
            "freq_hz": frf.freq_hz[None, :],
            "omega": np.array(frf.omega)[None, :],
            "H": np.array(frf.response),
            "magnitude_std": frf.magnitude_std,
            "phase_std": frf.phase_std,
            "correlation": frf.correlation,
            "input_labels": cell(frf.input_labels),
            "output_labels": cell(frf.output_labels),
            "meta": json.dumps(frf.meta),
            "flags": frf.flags.astype(np.int32),
            "reduced_chi2": np.array(frf.reduced_chi2),
            "units": dict(UNITS),
            "schema": _SCHEMA,
            "schema_version": SCHEMA_VERSION,
        },
        do_compression=True,
    )


def read_mat(cls, path: str | os.PathLike):
    """A ``cls`` from a file written by :func:`write_mat` (``scipy.io.loadmat``): the response,
    labels, meta, flags and reduced chi2 exactly; the covariance from ``magnitude_std``,
    ``phase_std`` and ``correlation`` (equal to the written one to round-off).

    Raises:
        ParameterError: naming ``path``, a file that is not a MAT file, or lacks a variable
            :func:`write_mat` writes, or (files with ``units``) says other units.
    """
    import scipy.io

    where = f"path {os.fspath(path)!r}"
    if os.stat(path).st_size > MAX_FILE_BYTES:
        raise ParameterError(f"{where}: larger than the {MAX_FILE_BYTES} bytes a response file may have")
    try:
        m = scipy.io.loadmat(path, squeeze_me=False, chars_as_strings=True)
    except (ValueError, TypeError, NotImplementedError, OSError, scipy.io.matlab.MatReadError) as exc:
        raise ParameterError(f"{where}: not a MAT file frf.mat ({type(exc).__name__}: {exc})") from None
    need = {"omega", "H", "magnitude_std", "phase_std", "correlation", "input_labels", "output_labels", "meta"}
    if need - set(m):
        raise ParameterError(f"{where}: missing variables {sorted(need - set(m))}; expected a file written by to_mat")
    if "units" in m:
        units = {k: str(np.asarray(m["units"][k][0, 0]).reshape(-1)[0]) for k in m["units"].dtype.names}
        if units != UNITS:
            raise ParameterError(f"{where}: units: expected {UNITS}, got {units}")
    try:
        h = np.asarray(m["H"], dtype=np.complex128)
        ms, ps, rho = (np.asarray(m[k], dtype=np.float64) for k in ("magnitude_std", "phase_std", "correlation"))
        cov = np.stack([np.stack([ms * ms, rho * ms * ps], -1), np.stack([rho * ms * ps, ps * ps], -1)], -2)
        labels = {k: [str(np.asarray(c).reshape(-1)[0]) for c in m[k].reshape(-1)] for k in ("input_labels", "output_labels")}
        extra = {k: np.asarray(m[k]) for k in ("flags", "reduced_chi2") if k in m}
        return cls(np.asarray(m["omega"], dtype=np.float64).reshape(-1), h, cov=cov, meta=json.loads(str(m["meta"][0])),
                   **labels, **{k: (v.astype(np.int64) if k == "flags" else v) for k, v in extra.items()})
    except TorchblurError as exc:
        raise _naming_path(exc, path) from None
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise ParameterError(f"{where}: not a valid frf.mat ({type(exc).__name__}: {exc})") from None


# ------------------------------------------------------------------------ CSV
def write_csv(frf, path: str | os.PathLike, *, extra_columns: dict | None = None) -> None:
    """Write ``frf`` to a CSV file (format in the module docstring; the correlation is lost).
    Phase in degrees in (-180, 180]. ``extra_columns``: ``{name: value}`` appended to the header
    and to every row (e.g. the CLI's ``torchblur_version`` and ``seed``; :func:`read_csv`
    ignores them). With ``frf.has_adequacy``, the columns ``reduced_chi2,flags`` come after the
    five (before ``extra_columns``)."""
    extra = dict(extra_columns or {})
    adequacy = frf.has_adequacy
    mag = frf.magnitude
    phase_deg = np.degrees(frf.phase)
    phase_deg[phase_deg <= -180.0] = 180.0  # -pi + 1 ulp may round to -180
    mag_std = frf.magnitude_std
    phase_std_deg = np.degrees(frf.phase_std)
    f_hz = frf.freq_hz
    chi2, flags, outs, ins = frf.reduced_chi2, frf.flags, frf.output_labels, frf.input_labels
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow((_CSV_SISO_HEADER if frf.is_siso else _CSV_MIMO_HEADER) + (_CSV_ADEQUACY if adequacy else [])
                        + list(extra))
        for o in range(frf.n_outputs):
            for i in range(frf.n_inputs):
                lead = [] if frf.is_siso else [outs[o], ins[i]]
                for k in range(f_hz.size):
                    vals = (f_hz[k], mag[o, i, k], phase_deg[o, i, k], mag_std[o, i, k], phase_std_deg[o, i, k])
                    more = [repr(float(chi2[o, i, k])), flag_names(flags[o, i, k])] if adequacy else []
                    writer.writerow(lead + [repr(float(v)) for v in vals] + more + list(extra.values()))


def read_csv(cls, path: str | os.PathLike):
    """A ``cls`` from a CSV written by :func:`write_csv` (or by hand in the same format).

    The covariance comes back diagonal: ``cov[..., 0, 1] = 0`` where both stds are known
    (CSV has no correlation column), NaN where either is unknown. The columns
    ``reduced_chi2`` and ``flags``, where present among the extra ones, are read back.
    """
    text = _read_text(path)
    try:
        return _from_csv_rows(cls, list(csv.reader(io.StringIO(text, newline=""))))
    except csv.Error as exc:
        raise ParameterError(f"path {os.fspath(path)!r}: not a CSV file ({exc})") from None
    except TorchblurError as exc:
        raise _naming_path(exc, path) from None


def _from_csv_rows(cls, rows: list):
    """:func:`read_csv` from the file's parsed ``rows`` (lists of strings); errors say
    ``path: ...`` (the caller puts the file's path there)."""
    if not rows:
        raise ParameterError("path: the file is empty, expected a header row")
    header = [c.strip() for c in rows[0]]
    mimo = _csv_layout(header)
    channels, outs, ins = _csv_channels(rows, header, mimo)
    f_hz = _csv_frequencies(channels, outs, ins)
    data = np.array([[channels[(o, i)] for i in ins] for o in outs], dtype=np.float64)  # [O, I, F, 7]
    h, cov, extra = _csv_arrays(data)
    omega = f_hz * (2.0 * np.pi)
    if not mimo:
        return cls(omega, h[0, 0], cov=cov[0, 0], **extra)
    return cls(omega, h, cov=cov, output_labels=outs, input_labels=ins, **extra)


def _csv_layout(header: list) -> bool:
    """Whether the stripped ``header`` is a MIMO one (else SISO); extra columns after the known
    ones (e.g. the CLI's torchblur_version, seed) are allowed."""
    if header[: len(_CSV_MIMO_HEADER)] == _CSV_MIMO_HEADER:
        return True
    if header[: len(_CSV_SISO_HEADER)] == _CSV_SISO_HEADER:
        return False
    raise ParameterError(
        f"path: header {excerpt(','.join(header))}; expected {_CSV_SISO_HEADER} "
        f"(SISO) or {_CSV_MIMO_HEADER} (MIMO), optionally followed by extra columns"
    )


def _csv_channels(rows: list, header: list, mimo: bool):
    """The data rows by channel: ``({(output, input): [[freq_hz, magnitude, phase_deg,
    magnitude_std, phase_std_deg, reduced_chi2, flags], ...]}, outputs, inputs)`` in file order
    (SISO: the one channel ``("y0", "u0")``); blank lines skipped."""
    ncol = len(header)
    n_known = len(_CSV_MIMO_HEADER) if mimo else len(_CSV_SISO_HEADER)
    col_chi2 = header.index("reduced_chi2") if "reduced_chi2" in header[n_known:] else None
    col_flags = header.index("flags") if "flags" in header[n_known:] else None
    channels: dict[tuple[str, str], list[list[float]]] = {}
    outs: list[str] = []
    ins: list[str] = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != ncol:
            raise ParameterError(f"path: line {lineno}: expected {ncol} columns, got {len(row)}")
        key, nums = ((row[0].strip(), row[1].strip()), row[2:n_known]) if mimo else (("y0", "u0"), row[:n_known])
        try:
            vals = [float(x) for x in nums]
            vals.append(float(row[col_chi2]) if col_chi2 is not None else math.nan)
        except ValueError as exc:
            raise ParameterError(f"path: line {lineno}: expected numbers, got {nums}") from exc
        vals.append(parse_flags(row[col_flags]) if col_flags is not None else 0)
        if key[0] not in outs:
            outs.append(key[0])
        if key[1] not in ins:
            ins.append(key[1])
        channels.setdefault(key, []).append(vals)
    if not channels:
        raise ParameterError("path: no data rows")
    return channels, outs, ins


def _csv_frequencies(channels: dict, outs: list, ins: list) -> np.ndarray:
    """The frequencies [F] (Hz) every channel shares; ParameterError where a channel is missing
    or has other frequencies."""
    ref = None
    for o in outs:
        for i in ins:
            if (o, i) not in channels:
                raise ParameterError(f"path: missing rows for output {excerpt(o)}, input {excerpt(i)}")
            f = np.array([v[0] for v in channels[(o, i)]])
            if ref is None:
                ref = f
            elif f.size != ref.size or not np.array_equal(f, ref):
                raise ParameterError(
                    f"path: output {excerpt(o)}, input {excerpt(i)} has frequencies that differ from "
                    f"those of the first channel"
                )
    return ref


def _csv_arrays(data: np.ndarray):
    """``(response [O, I, F], cov [O, I, F, 2, 2] diagonal, {"reduced_chi2", "flags"})`` from
    the columns ``data [O, I, F, 7]`` (see :func:`_csv_channels`)."""
    mag, ph_deg, mstd, pstd_deg = data[..., 1], data[..., 2], data[..., 3], data[..., 4]
    if np.any(data[..., 5] < 0) or np.any(np.isinf(data[..., 5])):
        raise ParameterError("path: column 'reduced_chi2' has negative or infinite values")
    extra = {"reduced_chi2": data[..., 5], "flags": data[..., 6].astype(np.int64)}
    if np.any(mag < 0):
        raise ParameterError("path: column 'magnitude' has negative values")
    h = mag * np.exp(1j * np.radians(ph_deg))
    h[~(np.isfinite(mag) & np.isfinite(ph_deg))] = np.nan
    cov = np.full(mag.shape + (2, 2), np.nan)
    cov[..., 0, 0] = mstd * mstd
    pstd = np.radians(pstd_deg)
    cov[..., 1, 1] = pstd * pstd
    both = np.isfinite(mstd) & np.isfinite(pstd)
    cov[..., 0, 1] = np.where(both, 0.0, np.nan)
    cov[..., 1, 0] = cov[..., 0, 1]
    return h, cov, extra


# ----------------------------------------------------------------------- JSON
def to_dict(frf) -> dict[str, Any]:
    """The JSON document of ``frf`` as a dict (schema in the module docstring; ``flags`` and
    ``reduced_chi2`` only where ``frf.has_adequacy``)."""
    cov = None if np.all(np.isnan(frf.cov)) else json_floats(frf.cov)
    adequacy = {"flags": frf.flags.tolist(), "reduced_chi2": json_floats(frf.reduced_chi2)} if frf.has_adequacy else {}
    return {
        "schema": _SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "units": dict(UNITS),
        "omega": json_floats(frf.omega),
        "response_real": json_floats(frf.response.real),
        "response_imag": json_floats(frf.response.imag),
        "cov": cov,
        "output_labels": list(frf.output_labels),
        "input_labels": list(frf.input_labels),
        "meta": frf.meta,
        **adequacy,
    }


def write_json(frf, path: str | os.PathLike) -> None:
    """Write everything of ``frf`` (exact floats, covariance, labels, meta) to a JSON file."""
    write_json_doc(to_dict(frf), path)


def write_json_doc(doc: dict, path: str | os.PathLike, *, indent: int | None = None) -> None:
    """Write ``doc`` to a strict JSON file (no NaN or Inf), ending in a newline."""
    with open(path, "w") as fh:
        json.dump(doc, fh, allow_nan=False, indent=indent)
        fh.write("\n")


def check_document(doc, schema: str, keys: dict, units: dict, *, why: str = "") -> int:
    """The ``schema_version`` of ``doc``, a JSON document of ``schema`` with its version's keys
    (``keys``: ``{version: (required, optional)}``; every required one, nothing unknown: a key is
    refused only when its version lacks it) and, where its version has them, ``units``.

    Raises:
        InputTypeError: ``doc`` is not a dict.
        ParameterError: naming the key (``schema``, ``schema_version``, ``doc``, ``units``);
            ``why`` is added to a wrong schema's message.
    """
    check_type(doc, "doc", dict, "a JSON object")
    if doc.get("schema") != schema:
        raise ParameterError(f"schema: expected {excerpt(schema)}, got {excerpt(doc.get('schema'))}{why}")
    version = check_schema_version(doc.get("schema_version"), keys)
    required, optional = keys[version]
    unknown, missing = set(doc) - required - optional, required - set(doc)
    if unknown:
        raise ParameterError(f"doc: unknown keys {sorted(unknown)} for schema_version {version}; expected keys "
                             f"{sorted(required)} and optionally {sorted(optional)}")
    if missing:
        raise ParameterError(f"doc: missing keys {sorted(missing)}")
    if "units" in required and doc["units"] != units:
        raise ParameterError(f"units: expected {units}, got {excerpt(doc['units'])}")
    return version


def from_dict(cls, doc: dict):
    """A ``cls`` from the document of :func:`to_dict`; checks ``schema`` and ``schema_version``."""
    check_document(doc, _SCHEMA, _JSON_KEYS, UNITS)

    def arr(key):
        try:
            return np.array(doc[key], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{key}: expected nested lists of numbers or null") from exc

    re, im = arr("response_real"), arr("response_imag")
    if re.shape != im.shape:
        raise ShapeError(f"response_imag: expected shape {re.shape} like response_real, got {im.shape}")
    h = re + 1j * im
    h[~(np.isfinite(re) & np.isfinite(im))] = np.nan
    cov = None if doc.get("cov") is None else arr("cov")
    flags = None
    if doc.get("flags") is not None:
        try:
            flags = np.array(doc["flags"])  # the constructor refuses anything but integers
        except (TypeError, ValueError) as exc:
            raise ParameterError("flags: expected nested lists of integers") from exc
    return cls(
        arr("omega"),
        h,
        cov=cov,
        output_labels=doc.get("output_labels"),
        input_labels=doc.get("input_labels"),
        meta=doc.get("meta"),
        flags=flags,
        reduced_chi2=None if doc.get("reduced_chi2") is None else arr("reduced_chi2"),
    )


def read_json(cls, path: str | os.PathLike):
    """A ``cls`` from a file written by :func:`write_json` (bit-exact round trip); errors as
    :func:`read_json_doc`'s."""
    return read_json_doc(path, lambda doc: from_dict(cls, doc), "frf.json")


def read_json_doc(path: str | os.PathLike, from_dict, name: str):
    """``from_dict(doc)`` of the JSON document in the file ``path`` (``name``: the document it
    should be, for the messages: "frf.json", "model.json").

    The file is untrusted input: one that is empty, not UTF-8, not JSON, nested deeper
    than Python can parse, larger than ``MAX_FILE_BYTES`` or that ``from_dict`` refuses raises
    :class:`~torchblur.errors.ParameterError` (or ``from_dict``'s ``InputTypeError``/``ShapeError``)
    naming ``path``.
    """
    where = f"path {os.fspath(path)!r}"
    text = _read_text(path)
    if not text.strip():
        raise ParameterError(f"{where}: the file is empty, expected a {name} document")
    try:
        doc = json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or an integer of more digits than Python converts
        raise ParameterError(f"{where}: not JSON ({exc})") from None
    except RecursionError:
        raise ParameterError(f"{where}: JSON nested too deeply to read; not a {name} document") from None
    try:
        return from_dict(doc)
    except TorchblurError as exc:
        raise _naming_path(exc, path) from None
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError, RecursionError) as exc:
        raise ParameterError(f"{where}: not a valid {name} document ({type(exc).__name__}: {excerpt(str(exc))})") from None
