"""A measured frequency response with per-point uncertainty, in python-control's layout.

Conventions (python-control's): ``omega`` is in rad/s, magnitude is absolute (output units
per input unit, never dB), phase is in radians. Hz and degrees appear only in the CSV columns
named ``freq_hz`` and ``*_deg``.

Shapes, from the glossary: F frequencies, O outputs, I inputs.

* ``response[o, i, f]`` = complex gain from input ``i`` to output ``o`` at ``omega[f]``.
* ``cov[o, i, f]`` = 2x2 covariance of (magnitude, phase) of that estimate:
  ``[[var_mag, cov_mag_phase], [cov_mag_phase, var_phase]]`` in (output/input)^2,
  (output/input) rad and rad^2. NaN means unknown.

File formats:

* CSV (``to_csv``/``from_csv``): one plain header row, no comment lines, floats written with
  ``repr`` (shortest string that reads back to the same float64). SISO columns are
  ``freq_hz,magnitude,phase_deg,magnitude_std,phase_std_deg``; MIMO adds two leading columns
  ``output,input`` holding the labels, rows ordered by output, input, then frequency.
  Phase is wrapped to (-180, 180]. ``from_csv`` ignores extra columns after these (the
  CLI's frf.csv adds ``torchblur_version,seed``). CSV keeps the standard deviations but **loses the
  magnitude-phase correlation**: ``from_csv`` returns a diagonal covariance (correlation 0).
  A SISO CSV also drops the labels, and no CSV keeps ``meta``.
* MAT (``to_mat``/``from_mat``): MATLAB variables for ``idfrd``/``tfest`` (see :meth:`to_mat`),
  phase and its std in radians, a ``units`` struct.
* JSON (``to_json``/``from_json``): everything, bit-exact, under a versioned schema
  ``{"schema": "torchblur.sysid.frequency_response", "schema_version": 2, "units": {...}, ...}``
  (version 1, without ``units``, still reads; a newer one is refused by name). Non-finite
  numbers (failed points, unknown covariance) are written as ``null`` so the file is strict
  JSON.

Per-point adequacy (:attr:`FrequencyResponse.flags`, :attr:`FrequencyResponse.reduced_chi2`,
bits in :mod:`torchblur.sysid.flags`): where a response carries it (a flag set or a reduced
chi2 known: :attr:`FrequencyResponse.has_adequacy`), the CSV gets two more columns
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
import re
from typing import Any, Sequence

import numpy as np

from torchblur.errors import InputTypeError, ParameterError, ShapeError, TorchblurError, excerpt
from torchblur.files import read_bounded
from torchblur.sysid.flags import flag_names, parse_flags

__all__ = ["FrequencyResponse", "control_names"]

#: characters python-control (0.10) refuses in a signal or system name: it reads ``"sys.signal"``
_CONTROL_REFUSED = re.compile(r"\.")


def control_names(labels: Sequence[str]) -> list[str]:
    """The names python-control gets for ``labels`` (the labels themselves are unchanged).

    Every character python-control refuses in a name (``"."``) becomes ``"_"``: ``"s0.x"`` ->
    ``"s0_x"``. A name that would then repeat a label or an earlier name gets ``"_2"``,
    ``"_3"``, ... (python-control would merge repeated names into one signal without a word).
    Name ``k`` is label ``k``'s: the order is kept.

    >>> control_names(["s0.x", "s0.y", "s0_x"])
    ['s0_x_2', 's0_y', 's0_x']
    """
    labels = [str(lab) for lab in labels]
    reserved = {lab for lab in labels if not _CONTROL_REFUSED.search(lab)}
    names: list[str] = []
    used: set[str] = set()
    for lab in labels:
        base = _CONTROL_REFUSED.sub("_", lab)
        name, k = base, 2
        while name in used or (name != lab and name in reserved):
            name, k = f"{base}_{k}", k + 1
        used.add(name)
        names.append(name)
    return names

_SCHEMA = "torchblur.sysid.frequency_response"
#: the version :meth:`FrequencyResponse.to_dict` writes (2: with ``units``; 1 files still read)
SCHEMA_VERSION = 2
_SUPPORTED_SCHEMA_VERSIONS = (1, 2)
#: the units of frf.json's and frf.mat's numbers (version 2 writes them; version 1 meant the
#: same): the output and input units themselves are ``meta["output_unit"]`` / ``meta["input_unit"]``
UNITS = {"omega": "rad/s", "freq_hz": "Hz", "response": "output unit per input unit (absolute, not dB)",
         "magnitude_std": "output unit per input unit", "phase": "rad", "phase_std": "rad",
         "cov": "[[magnitude^2, magnitude rad], [magnitude rad, rad^2]]"}
_JSON_KEYS = {
    "units",
    "schema",
    "schema_version",
    "omega",
    "response_real",
    "response_imag",
    "cov",
    "output_labels",
    "input_labels",
    "meta",
    "flags",
    "reduced_chi2",
}
_CSV_SISO_HEADER = ["freq_hz", "magnitude", "phase_deg", "magnitude_std", "phase_std_deg"]
_CSV_MIMO_HEADER = ["output", "input"] + _CSV_SISO_HEADER
_CSV_ADEQUACY = ["reduced_chi2", "flags"]  # written after the five where the response carries them


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _as_real_array(value, name: str) -> np.ndarray:
    if value is None or isinstance(value, (str, bytes)):
        raise InputTypeError(f"{name}: expected an array of real numbers, got {type(value).__name__}")
    try:
        a = np.array(value)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name}: expected an array of real numbers, got {type(value).__name__}") from exc
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise InputTypeError(f"{name}: expected an array of real numbers, got dtype {a.dtype}")
    return a.astype(np.float64)


def _as_complex_array(value, name: str) -> np.ndarray:
    if value is None or isinstance(value, (str, bytes)):
        raise InputTypeError(f"{name}: expected an array of complex numbers, got {type(value).__name__}")
    try:
        a = np.array(value)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name}: expected an array of complex numbers, got {type(value).__name__}") from exc
    if a.dtype == bool or not (
        np.issubdtype(a.dtype, np.integer)
        or np.issubdtype(a.dtype, np.floating)
        or np.issubdtype(a.dtype, np.complexfloating)
    ):
        raise InputTypeError(f"{name}: expected an array of complex numbers, got dtype {a.dtype}")
    return a.astype(np.complex128)


def _check_labels(labels, n: int, name: str, prefix: str) -> tuple[str, ...]:
    if labels is None:
        return tuple(f"{prefix}{k}" for k in range(n))
    if isinstance(labels, (str, bytes)) or not isinstance(labels, Sequence):
        raise InputTypeError(f"{name}: expected a sequence of {n} strings, got {type(labels).__name__}")
    labels = tuple(labels)
    for lab in labels:
        if not isinstance(lab, str):
            raise InputTypeError(f"{name}: expected strings, got an entry of type {type(lab).__name__}")
    if len(labels) != n:
        raise ShapeError(f"{name}: expected {n} labels (one per {excerpt(prefix)} channel), got {len(labels)}")
    if len(set(labels)) != len(labels):
        raise ParameterError(f"{name}: expected distinct labels, got {list(labels)}")
    return labels


def _wrap_phase(phase: np.ndarray) -> np.ndarray:
    """Wrap radians to (-pi, pi] (``np.angle`` returns -pi for a negative real with -0 imag)."""
    out = np.array(phase, dtype=np.float64, copy=True)
    out = np.where(np.isfinite(out), np.mod(out + np.pi, 2.0 * np.pi) - np.pi, out)
    out[out <= -np.pi] = np.pi
    return out


def _json_floats(a: np.ndarray):
    """Nested lists of float, with ``None`` in place of NaN/Inf."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 0:
        v = float(a)
        return v if math.isfinite(v) else None
    return [_json_floats(x) for x in a]


def _per_point(value, name: str, shape: tuple, integer: bool) -> np.ndarray:
    """``value`` ([F] for a 1x1 response, or [O, I, F] = ``shape``) as a read-only array of that
    shape: int64 bit masks >= 0 (``integer``), else float64 >= 0 or NaN."""
    if integer:
        a = np.array(value)
        if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
            raise InputTypeError(f"{name}: expected an array of integer bit masks, got dtype {a.dtype}")
        a = a.astype(np.int64)
    else:
        a = _as_real_array(value, name)
    if a.shape == shape[-1:] and shape[:2] == (1, 1):
        a = a.reshape(shape)
    if a.shape != shape:
        raise ShapeError(f"{name}: expected shape [O, I, F] = {shape} like the response, got {a.shape}")
    if integer and np.any(a < 0):
        raise ParameterError(f"{name}: expected bit masks >= 0, got minimum {a.min()}")
    if not integer and (np.any(np.isinf(a)) or np.any(a < 0)):
        raise ParameterError(f"{name}: expected values >= 0 or NaN (unknown), got {a[np.isinf(a) | (a < 0)][0]:g}")
    return _readonly(a.copy())


class FrequencyResponse:
    """A measured frequency response H(j omega), one complex estimate per frequency.

    Args:
        omega: [F] angular frequencies in rad/s, finite, > 0, strictly increasing
            (sorting is the caller's job).
        response: complex [F] (SISO) or [O, I, F]; ``response[o, i, f]`` is the gain from input
            ``i`` to output ``o`` at ``omega[f]``, absolute (output units per input unit).
            Stored as [O, I, F] always. NaN marks a failed point (see :attr:`valid`); Inf is
            refused.
        cov: optional real [F, 2, 2] (SISO) or [O, I, F, 2, 2]: covariance of (magnitude,
            phase) of each estimate, magnitude absolute and phase in rad. ``None`` = unknown
            (stored as NaN). Must be symmetric with non-negative variances.
        input_labels: I strings, default ``["u0", "u1", ...]`` (e.g. ``["x", "y"]``).
        output_labels: O strings, default ``["y0", "y1", ...]``.
        meta: dict of strict-JSON-serialisable extras (version, seed, ...); stored as a copy.
        flags: optional int [F] (SISO) or [O, I, F] bit masks of :mod:`torchblur.sysid.flags`
            (``POOR_FIT``, ``TIMING``, ``LIMITED``, ``FAILED``); ``None`` = 0 everywhere.
        reduced_chi2: optional real [F] or [O, I, F]: the reduced chi2 of the image fit each
            point comes from (about 1 when the model explains its images); ``None`` = NaN
            (unknown) everywhere.

    Raises:
        ParameterError: omega not finite/positive/strictly increasing; Inf in response;
            asymmetric or negative-variance cov; repeated labels.
        ShapeError: shapes that do not match (each message names the argument).
        InputTypeError: non-numeric arrays, non-string labels, non-JSON meta.

    Example:
        >>> import numpy as np
        >>> w = np.array([1.0, 10.0, 100.0])
        >>> frf = FrequencyResponse(w, 1.0 / (1j * w + 1.0))
        >>> frf.magnitude.shape
        (1, 1, 3)
    """

    __slots__ = ("_omega", "_response", "_cov", "_input_labels", "_output_labels", "_meta", "_flags", "_reduced_chi2")

    def __init__(
        self,
        omega,
        response,
        *,
        cov=None,
        input_labels: Sequence[str] | None = None,
        output_labels: Sequence[str] | None = None,
        meta: dict | None = None,
        flags=None,
        reduced_chi2=None,
    ) -> None:
        w = _as_real_array(omega, "omega")
        if w.ndim != 1 or w.size == 0:
            raise ShapeError(f"omega: expected shape [F] with F >= 1, got {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ParameterError(f"omega: expected finite values, got {int(np.sum(~np.isfinite(w)))} NaN/Inf entries")
        if np.any(w <= 0):
            raise ParameterError(f"omega: expected every value > 0 rad/s, got minimum {w.min():g}")
        if np.any(np.diff(w) <= 0):
            k = int(np.argmax(np.diff(w) <= 0))
            raise ParameterError(
                f"omega: expected strictly increasing values (sort them first), "
                f"got omega[{k}]={w[k]:g} >= omega[{k + 1}]={w[k + 1]:g}"
            )
        n_f = w.size

        h = _as_complex_array(response, "response")
        siso_input = h.ndim == 1
        if siso_input:
            h = h.reshape(1, 1, -1)
        if h.ndim != 3 or h.shape[-1] != n_f:
            raise ShapeError(
                f"response: expected shape [F] or [O, I, F] with F = len(omega) = {n_f}, "
                f"got {np.shape(response)}"
            )
        if h.shape[0] == 0 or h.shape[1] == 0:
            raise ShapeError(f"response: expected O >= 1 and I >= 1, got shape {h.shape}")
        if np.any(np.isinf(h.real) | np.isinf(h.imag)):
            raise ParameterError("response: expected finite values or NaN (failed points), got Inf")
        n_o, n_i = h.shape[0], h.shape[1]

        if cov is None:
            c = np.full((n_o, n_i, n_f, 2, 2), np.nan)
        else:
            c = _as_real_array(cov, "cov")
            want = (n_o, n_i, n_f, 2, 2)
            if c.shape == (n_f, 2, 2) and n_o == n_i == 1:
                c = c.reshape(want)
            if c.shape != want:
                expect = f"[F, 2, 2] = {(n_f, 2, 2)}" if siso_input else f"[O, I, F, 2, 2] = {want}"
                raise ShapeError(f"cov: expected shape {expect}, got {c.shape}")
            if np.any(np.isinf(c)):
                raise ParameterError("cov: expected finite values or NaN (unknown), got Inf")
            d0, d1 = c[..., 0, 0], c[..., 1, 1]
            if np.any(d0 < 0) or np.any(d1 < 0):
                raise ParameterError(
                    f"cov: expected variances >= 0 on the diagonal, got minimum "
                    f"{np.nanmin(np.minimum(d0, d1)):g}"
                )
            off, off_t = c[..., 0, 1], c[..., 1, 0]
            both = np.isfinite(off) & np.isfinite(off_t)
            tol = 1e-12 * np.sqrt(np.abs(np.nan_to_num(d0 * d1))) + 1e-300
            if np.any(both & (np.abs(off - off_t) > tol)) or np.any(np.isfinite(off) != np.isfinite(off_t)):
                raise ParameterError("cov: expected symmetric 2x2 matrices (cov[..., 0, 1] == cov[..., 1, 0])")
            with np.errstate(invalid="ignore"):
                bad = np.isfinite(off) & (off * off > d0 * d1 * (1.0 + 1e-9) + 1e-300)
            if np.any(bad):
                raise ParameterError("cov: expected positive semi-definite matrices, got |correlation| > 1")
        self._omega = _readonly(w.copy())
        self._response = _readonly(h.copy())
        self._cov = _readonly(np.array(c, dtype=np.float64, copy=True))
        shape = (n_o, n_i, n_f)
        self._flags = _per_point(np.zeros(shape, np.int64) if flags is None else flags, "flags", shape, True)
        self._reduced_chi2 = _per_point(np.full(shape, np.nan) if reduced_chi2 is None else reduced_chi2, "reduced_chi2",
                                        shape, False)
        self._output_labels = _check_labels(output_labels, n_o, "output_labels", "y")
        self._input_labels = _check_labels(input_labels, n_i, "input_labels", "u")
        if meta is None:
            meta = {}
        if not isinstance(meta, dict):
            raise InputTypeError(f"meta: expected a dict, got {type(meta).__name__}")
        try:
            self._meta = json.loads(json.dumps(meta, allow_nan=False))
        except (TypeError, ValueError) as exc:
            raise InputTypeError(f"meta: expected strict-JSON-serialisable values (no NaN/Inf), got: {exc}") from exc

    # ------------------------------------------------------------------ data
    @property
    def omega(self) -> np.ndarray:
        """[F] angular frequencies, rad/s (read-only)."""
        return self._omega

    @property
    def response(self) -> np.ndarray:
        """Complex [O, I, F], absolute gain (read-only)."""
        return self._response

    @property
    def cov(self) -> np.ndarray:
        """Real [O, I, F, 2, 2] covariance of (magnitude, phase rad); NaN = unknown (read-only)."""
        return self._cov

    @property
    def input_labels(self) -> tuple[str, ...]:
        return self._input_labels

    @property
    def output_labels(self) -> tuple[str, ...]:
        return self._output_labels

    @property
    def meta(self) -> dict:
        """A copy of the JSON-serialisable extras."""
        return json.loads(json.dumps(self._meta))

    @property
    def flags(self) -> np.ndarray:
        """Int64 [O, I, F] bit masks of :mod:`torchblur.sysid.flags` (0 = none; read-only):
        test a bit with ``(frf.flags & POOR_FIT) != 0``."""
        return self._flags

    @property
    def reduced_chi2(self) -> np.ndarray:
        """[O, I, F] reduced chi2 of the image fit behind each point; NaN = unknown (read-only)."""
        return self._reduced_chi2

    @property
    def has_adequacy(self) -> bool:
        """Whether any point carries a flag or a known reduced chi2 (then the CSV and JSON
        files hold them)."""
        return bool(np.any(self._flags != 0) or np.any(np.isfinite(self._reduced_chi2)))

    def replace(self, **changes) -> "FrequencyResponse":
        """A copy with the constructor's arguments in ``changes`` replaced (``response``,
        ``cov``, ``flags``, ``reduced_chi2``, ``meta``, labels, ``omega``); everything else,
        flags and reduced chi2 included, kept. The arguments are checked as by the constructor."""
        args = {"omega": self._omega, "response": self._response, "cov": self._cov, "input_labels": self._input_labels,
                "output_labels": self._output_labels, "meta": self._meta, "flags": self._flags,
                "reduced_chi2": self._reduced_chi2}
        unknown = set(changes) - set(args)
        if unknown:
            raise ParameterError(f"changes: unknown arguments {sorted(unknown)}; expected some of {sorted(args)}")
        args.update(changes)
        omega, response = args.pop("omega"), args.pop("response")
        return FrequencyResponse(omega, response, **args)

    def select_outputs(self, keep) -> "FrequencyResponse":
        """The outputs where ``keep`` (bool [O]) is True, every per-point array (response,
        cov, flags, reduced chi2) and the labels with them."""
        k = np.asarray(keep, dtype=bool)
        if k.shape != (self.n_outputs,):
            raise ShapeError(f"keep: expected a bool array of shape [O] = ({self.n_outputs},), got {k.shape}")
        if not k.any():
            raise ParameterError("keep: expected at least one output kept, got none")
        return self.replace(response=self._response[k], cov=self._cov[k], flags=self._flags[k],
                            reduced_chi2=self._reduced_chi2[k],
                            output_labels=[lab for lab, kk in zip(self._output_labels, k) if kk])

    @property
    def n_outputs(self) -> int:
        return self._response.shape[0]

    @property
    def n_inputs(self) -> int:
        return self._response.shape[1]

    @property
    def is_siso(self) -> bool:
        return self.n_outputs == 1 and self.n_inputs == 1

    @property
    def valid(self) -> np.ndarray:
        """Bool [O, I, F]: False where the response is NaN (a failed point)."""
        return np.isfinite(self._response.real) & np.isfinite(self._response.imag)

    @property
    def freq_hz(self) -> np.ndarray:
        """[F] frequencies in Hz, ``omega / (2 pi)``."""
        return self._omega / (2.0 * np.pi)

    @property
    def magnitude(self) -> np.ndarray:
        """[O, I, F] absolute magnitude |H|."""
        return np.abs(self._response)

    @property
    def phase(self) -> np.ndarray:
        """[O, I, F] phase in rad, wrapped to (-pi, pi]."""
        return _wrap_phase(np.angle(self._response))

    @property
    def magnitude_std(self) -> np.ndarray:
        """[O, I, F] standard deviation of the magnitude (absolute units); NaN = unknown."""
        return np.sqrt(self._cov[..., 0, 0])

    @property
    def phase_std(self) -> np.ndarray:
        """[O, I, F] standard deviation of the phase, rad; NaN = unknown."""
        return np.sqrt(self._cov[..., 1, 1])

    @property
    def correlation(self) -> np.ndarray:
        """[O, I, F] correlation coefficient of magnitude and phase; NaN if unknown or a std is 0."""
        with np.errstate(invalid="ignore", divide="ignore"):
            r = self._cov[..., 0, 1] / np.sqrt(self._cov[..., 0, 0] * self._cov[..., 1, 1])
        return np.where(np.isfinite(r), r, np.nan)

    def errors_against(self, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Errors of this response against a known one (a simulation's truth).

        Args:
            truth: complex ``[O, I, F]`` (or ``[F]`` for a SISO response) at :attr:`omega`.

        Returns:
            ``(magnitude_rel [O, I, F], phase_rad [O, I, F], z [O, I, F])``: the signed relative
            magnitude error ``(|H| - |T|) / |T|``, the signed phase error wrapped to
            [-pi, pi), and the larger of ``|magnitude error| / magnitude_std`` and
            ``|phase error| / phase_std``. NaN where the truth is 0 or a std unknown.
        """
        t = np.asarray(truth, dtype=complex)
        if t.shape == self._response.shape[-1:]:
            t = np.broadcast_to(t, self._response.shape)
        if t.shape != self._response.shape:
            raise ShapeError(f"truth: expected shape {self._response.shape} (or [F] for SISO), got {t.shape}")
        with np.errstate(invalid="ignore", divide="ignore"):
            dm = self.magnitude - np.abs(t)
            em = dm / np.where(np.abs(t) > 0, np.abs(t), np.nan)
            ep = np.remainder(self.phase - np.angle(t) + np.pi, 2 * np.pi) - np.pi
            z = np.maximum(np.abs(dm) / self.magnitude_std, np.abs(ep) / self.phase_std)
        return em, ep, z

    def unwrapped_phase(self) -> np.ndarray:
        """[O, I, F] phase in rad, unwrapped along frequency per channel.

        The first valid point of each channel keeps its wrapped value in (-pi, pi]; failed
        points stay NaN and are skipped (the unwrapping bridges them).
        """
        wrapped = self.phase
        out = np.full_like(wrapped, np.nan)
        ok = self.valid
        for o in range(self.n_outputs):
            for i in range(self.n_inputs):
                m = ok[o, i]
                if np.any(m):
                    out[o, i, m] = np.unwrap(wrapped[o, i, m])
        return out

    def response_std(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Standard deviations of Re H and Im H and their correlation, by linearisation.

        With H = m exp(j phi), dH = exp(j phi) (dm + j m dphi): the (radial, tangential)
        covariance ``[[var_m, m cov_mphi], [m cov_mphi, m^2 var_phi]]`` is rotated by phi into
        (Re, Im). The total ``std_real**2 + std_imag**2 = var_m + m**2 var_phi`` is the
        expected ``|delta H|^2``. These feed the weighting of model fits
        (:func:`torchblur.sysid.tf_fit.fit_transfer_function`).

        Returns:
            ``(std_real, std_imag, corr)``, each real [O, I, F]: std of Re H and of Im H
            (absolute units) and the correlation coefficient of Re H and Im H (NaN where
            the covariance is unknown or a std is 0). An unknown magnitude-phase correlation
            (NaN off-diagonal) makes all three NaN.
        """
        m = np.abs(self._response)
        phi = np.angle(self._response)
        c00 = self._cov[..., 0, 0]
        c01 = self._cov[..., 0, 1] * m
        c11 = self._cov[..., 1, 1] * m * m
        co, si = np.cos(phi), np.sin(phi)
        var_re = co * co * c00 - 2.0 * co * si * c01 + si * si * c11
        var_im = si * si * c00 + 2.0 * co * si * c01 + co * co * c11
        cov_ri = co * si * (c00 - c11) + (co * co - si * si) * c01
        var_re = np.maximum(var_re, 0.0)
        var_im = np.maximum(var_im, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = cov_ri / np.sqrt(var_re * var_im)
        corr = np.where(np.isfinite(corr), np.clip(corr, -1.0, 1.0), np.nan)
        return np.sqrt(var_re), np.sqrt(var_im), corr

    def __repr__(self) -> str:
        f = self.freq_hz
        n_bad = int(np.sum(~self.valid))
        bad = f", {n_bad} invalid" if n_bad else ""
        return (
            f"FrequencyResponse({self.n_outputs}x{self.n_inputs}, {f.size} points, "
            f"{f[0]:.4g}..{f[-1]:.4g} Hz{bad})"
        )

    # --------------------------------------------------------- python-control
    def to_control(self, smooth: bool = False, *, name: str = "frf"):
        """Return a named ``control.FrequencyResponseData`` (1x1 for SISO, OxI for MIMO).

        The FRD carries ``name``, ``inputs=input_labels`` and ``outputs=output_labels``, so
        ``control.bode_plot``, ``control.stability_margins`` and ``control.feedback`` accept
        it (python-control 0.10.2 leaves an FRD built with labels but no name unnamed, and
        ``bode_plot`` then raises TypeError). Names python-control refuses are mapped by
        :func:`control_names` (``"s0.x"`` of a many-spot run becomes ``"s0_x"``, in the control
        object only; the order is kept).

        Args:
            smooth: passed to ``control.frd``: True builds a spline so the object can be
                evaluated between the measured frequencies (refused if any point is NaN).
            name: the system's name (``bode_plot`` legends use it).
        """
        import control

        if smooth and not np.all(self.valid):
            raise ParameterError("smooth: cannot interpolate a response that has NaN (failed) points")
        if not isinstance(name, str):
            raise InputTypeError(f"name: expected a string, got {type(name).__name__}")
        data = self._response[0, 0] if self.is_siso else self._response
        return control.frd(
            np.array(data),
            np.array(self._omega),
            smooth=bool(smooth),
            inputs=control_names(self._input_labels),
            outputs=control_names(self._output_labels),
            name=control_names([name])[0],
        )

    @classmethod
    def from_control(cls, frd) -> "FrequencyResponse":
        """Build from a ``control.FrequencyResponseData`` (labels kept, covariance unknown)."""
        import control

        if not isinstance(frd, control.FrequencyResponseData):
            raise InputTypeError(f"frd: expected control.FrequencyResponseData, got {type(frd).__name__}")
        data = getattr(frd, "frdata", None)
        if data is None:  # python-control < 0.10.1
            data = frd.fresp
        return cls(
            np.array(frd.omega, dtype=np.float64),
            np.array(data, dtype=np.complex128).reshape(frd.noutputs, frd.ninputs, -1),
            input_labels=list(frd.input_labels),
            output_labels=list(frd.output_labels),
        )

    # -------------------------------------------------------------------- MAT
    def to_mat(self, path: str | os.PathLike) -> None:
        """Write a MATLAB ``.mat`` file (``scipy.io.savemat``, format 5) for MATLAB users.

        Variables (F frequencies, O outputs, I inputs; MATLAB sees the same shapes):

        * ``freq_hz`` [1, F], ``omega`` [1, F] rad/s;
        * ``H`` complex [O, I, F] (``H(o, i, f)`` = gain from input i to output o, absolute
          units; NaN = failed point), the layout of ``idfrd(H, omega, 0)`` for ``tfest``;
        * ``magnitude_std``, ``phase_std`` (rad), ``correlation`` [O, I, F] (NaN = unknown);
        * ``input_labels`` [1, I], ``output_labels`` [1, O]: cell arrays of strings;
        * ``meta``: the JSON text of :attr:`meta` (a string);
        * ``flags`` int32 [O, I, F] (bits of :mod:`torchblur.sysid.flags`, 0 = none) and
          ``reduced_chi2`` [O, I, F] (NaN = unknown);
        * ``units``: a struct naming each variable's unit (:data:`UNITS`), ``schema`` and
          ``schema_version`` (the JSON's).

        A SISO response keeps the [1, 1, F] shape, as in MATLAB's ``idfrd``. :meth:`from_mat`
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
                "freq_hz": self.freq_hz[None, :],
                "omega": np.array(self._omega)[None, :],
                "H": np.array(self._response),
                "magnitude_std": self.magnitude_std,
                "phase_std": self.phase_std,
                "correlation": self.correlation,
                "input_labels": cell(self._input_labels),
                "output_labels": cell(self._output_labels),
                "meta": json.dumps(self._meta),
                "flags": self._flags.astype(np.int32),
                "reduced_chi2": np.array(self._reduced_chi2),
                "units": dict(UNITS),
                "schema": _SCHEMA,
                "schema_version": SCHEMA_VERSION,
            },
            do_compression=True,
        )

    @classmethod
    def from_mat(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a file written by :meth:`to_mat` (``scipy.io.loadmat``): the response, labels,
        meta, flags and reduced chi2 exactly; the covariance from ``magnitude_std``,
        ``phase_std`` and ``correlation`` (equal to the written one to round-off).

        Raises:
            ParameterError: naming ``path``, a file that is not a MAT file, or lacks a variable
                :meth:`to_mat` writes, or (files with ``units``) says other units.
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

    # -------------------------------------------------------------------- CSV
    def to_csv(self, path: str | os.PathLike, *, extra_columns: dict | None = None) -> None:
        """Write a CSV file (format in the module docstring; the correlation is lost). Phase
        in degrees in (-180, 180]. ``extra_columns``: ``{name: value}`` appended to the header
        and to every row (e.g. the CLI's ``torchblur_version`` and ``seed``;
        :meth:`from_csv` ignores them). With :attr:`has_adequacy`, the columns
        ``reduced_chi2,flags`` come after the five (before ``extra_columns``)."""
        extra = dict(extra_columns or {})
        adequacy = self.has_adequacy
        mag = self.magnitude
        phase_deg = np.degrees(self.phase)
        phase_deg[phase_deg <= -180.0] = 180.0  # -pi + 1 ulp may round to -180
        mag_std = self.magnitude_std
        phase_std_deg = np.degrees(self.phase_std)
        f_hz = self.freq_hz
        with open(path, "w", newline="") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow((_CSV_SISO_HEADER if self.is_siso else _CSV_MIMO_HEADER) + (_CSV_ADEQUACY if adequacy else [])
                            + list(extra))
            for o in range(self.n_outputs):
                for i in range(self.n_inputs):
                    lead = [] if self.is_siso else [self._output_labels[o], self._input_labels[i]]
                    for k in range(f_hz.size):
                        vals = (f_hz[k], mag[o, i, k], phase_deg[o, i, k], mag_std[o, i, k], phase_std_deg[o, i, k])
                        more = [repr(float(self._reduced_chi2[o, i, k])), flag_names(self._flags[o, i, k])] if adequacy else []
                        writer.writerow(lead + [repr(float(v)) for v in vals] + more + list(extra.values()))

    @classmethod
    def from_csv(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a CSV written by :meth:`to_csv` (or by hand in the same format).

        The covariance comes back diagonal: ``cov[..., 0, 1] = 0`` where both stds are known
        (CSV has no correlation column), NaN where either is unknown. The columns
        ``reduced_chi2`` and ``flags``, where present among the extra ones, are read back.
        """
        text = _read_text(path)
        try:
            return cls._from_csv_rows(list(csv.reader(io.StringIO(text, newline=""))))
        except csv.Error as exc:
            raise ParameterError(f"path {os.fspath(path)!r}: not a CSV file ({exc})") from None
        except TorchblurError as exc:
            raise _naming_path(exc, path) from None

    @classmethod
    def _from_csv_rows(cls, rows: list) -> "FrequencyResponse":
        """:meth:`from_csv` from the file's parsed ``rows`` (lists of strings); errors say
        ``path: ...`` (the caller puts the file's path there)."""
        if not rows:
            raise ParameterError("path: the file is empty, expected a header row")
        header = [c.strip() for c in rows[0]]
        # Extra columns after the known ones (e.g. the CLI's torchblur_version, seed) are ignored.
        if header[: len(_CSV_MIMO_HEADER)] == _CSV_MIMO_HEADER:
            mimo = True
        elif header[: len(_CSV_SISO_HEADER)] == _CSV_SISO_HEADER:
            mimo = False
        else:
            raise ParameterError(
                f"path: header {excerpt(','.join(header))}; expected {_CSV_SISO_HEADER} "
                f"(SISO) or {_CSV_MIMO_HEADER} (MIMO), optionally followed by extra columns"
            )
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
            if mimo:
                key = (row[0].strip(), row[1].strip())
                nums = row[2:n_known]
            else:
                key = ("y0", "u0")
                nums = row[:n_known]
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
        ref = None
        n_f = None
        for o in outs:
            for i in ins:
                if (o, i) not in channels:
                    raise ParameterError(f"path: missing rows for output {excerpt(o)}, input {excerpt(i)}")
                f = np.array([v[0] for v in channels[(o, i)]])
                if ref is None:
                    ref, n_f = f, f.size
                elif f.size != n_f or not np.array_equal(f, ref):
                    raise ParameterError(
                        f"path: output {excerpt(o)}, input {excerpt(i)} has frequencies that differ from "
                        f"those of the first channel"
                    )
        data = np.array([[channels[(o, i)] for i in ins] for o in outs], dtype=np.float64)  # [O, I, F, 7]
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
        omega = ref * (2.0 * np.pi)
        if not mimo:
            return cls(omega, h[0, 0], cov=cov[0, 0], **extra)
        return cls(omega, h, cov=cov, output_labels=outs, input_labels=ins, **extra)

    # ------------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """The JSON document as a dict (schema in the module docstring; ``flags`` and
        ``reduced_chi2`` only where :attr:`has_adequacy`)."""
        cov = None if np.all(np.isnan(self._cov)) else _json_floats(self._cov)
        adequacy = {"flags": self._flags.tolist(), "reduced_chi2": _json_floats(self._reduced_chi2)} if self.has_adequacy else {}
        return {
            "schema": _SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "units": dict(UNITS),
            "omega": _json_floats(self._omega),
            "response_real": _json_floats(self._response.real),
            "response_imag": _json_floats(self._response.imag),
            "cov": cov,
            "output_labels": list(self._output_labels),
            "input_labels": list(self._input_labels),
            "meta": self.meta,
            **adequacy,
        }

    def to_json(self, path: str | os.PathLike) -> None:
        """Write everything (exact floats, covariance, labels, meta) to a JSON file."""
        with open(path, "w") as fh:
            json.dump(self.to_dict(), fh, allow_nan=False)
            fh.write("\n")

    @classmethod
    def from_dict(cls, doc: dict) -> "FrequencyResponse":
        """Inverse of :meth:`to_dict`; checks ``schema`` and ``schema_version``."""
        if not isinstance(doc, dict):
            raise InputTypeError(f"doc: expected a JSON object, got {type(doc).__name__}")
        if doc.get("schema") != _SCHEMA:
            raise ParameterError(f"schema: expected {excerpt(_SCHEMA)}, got {excerpt(doc.get('schema'))}")
        version = doc.get("schema_version")
        if isinstance(version, bool) or version not in _SUPPORTED_SCHEMA_VERSIONS:
            newer = " (written by a newer torchblur: upgrade to read it)" if isinstance(version, int) and version > SCHEMA_VERSION else ""
            raise ParameterError(
                f"schema_version: unsupported version {excerpt(version)}{newer}; supported versions: "
                f"{list(_SUPPORTED_SCHEMA_VERSIONS)}"
            )
        keys = _JSON_KEYS - {"units"} if version == 1 else _JSON_KEYS  # a key is refused only when its version lacks it
        unknown = set(doc) - keys
        if unknown:
            raise ParameterError(f"doc: unknown keys {sorted(unknown)} for schema_version {version}; expected keys {sorted(keys)}")
        if version >= 2 and doc.get("units") != UNITS:
            raise ParameterError(f"units: expected {UNITS}, got {doc.get('units')!r}")
        missing = {"omega", "response_real", "response_imag"} - set(doc)
        if missing:
            raise ParameterError(f"doc: missing keys {sorted(missing)}")

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

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a file written by :meth:`to_json` (bit-exact round trip).

        The file is untrusted input: one that is empty, not UTF-8, not JSON, nested deeper
        than Python can parse, larger than ``MAX_FILE_BYTES`` or not of this schema raises
        :class:`~torchblur.errors.ParameterError` (or ``InputTypeError``/``ShapeError``)
        naming ``path``.
        """
        where = f"path {os.fspath(path)!r}"
        text = _read_text(path)
        if not text.strip():
            raise ParameterError(f"{where}: the file is empty, expected a frf.json document")
        try:
            doc = json.loads(text)
        except ValueError as exc:  # JSONDecodeError, or an integer of more digits than Python converts
            raise ParameterError(f"{where}: not JSON ({exc})") from None
        except RecursionError:
            raise ParameterError(f"{where}: JSON nested too deeply to read; not a frf.json document") from None
        try:
            return cls.from_dict(doc)
        except TorchblurError as exc:
            raise _naming_path(exc, path) from None
        except (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError, RecursionError) as exc:
            raise ParameterError(f"{where}: not a valid frf.json document ({type(exc).__name__}: {exc})") from None


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
