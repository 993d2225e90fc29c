"""A measured frequency response with per-point uncertainty, in python-control's layout.

Conventions (python-control's): ``omega`` is in rad/s, magnitude is absolute (output units
per input unit, never dB), phase is in radians. Hz and degrees appear only in the CSV columns
named ``freq_hz`` and ``*_deg``.

Shapes, from the glossary: F frequencies, O outputs, I inputs.

* ``response[o, i, f]`` = complex gain from input ``i`` to output ``o`` at ``omega[f]``.
* ``cov[o, i, f]`` = 2x2 covariance of (magnitude, phase) of that estimate:
  ``[[var_mag, cov_mag_phase], [cov_mag_phase, var_phase]]`` in (output/input)^2,
  (output/input) rad and rad^2. NaN means unknown.

Files (CSV, JSON, MAT; ``to_csv``/``from_csv`` and the like): the formats are described, written
and read in :mod:`torchblur.sysid.frequency_response_io`. Per-point adequacy
(:attr:`FrequencyResponse.flags`, :attr:`FrequencyResponse.reduced_chi2`, bits in
:mod:`torchblur.sysid.flags`) goes into each of them.
"""
from __future__ import annotations

import json
import os
import re
from typing import Any, Sequence

import numpy as np

from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_type, excerpt
import torchblur.sysid.frequency_response_io as frf_io

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


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _as_array(value, name: str, *, complex_ok: bool = False) -> np.ndarray:
    """``value`` as a float64 (or, ``complex_ok``, complex128) array; InputTypeError naming
    ``name`` for anything but numbers (bool, strings, objects)."""
    what = "complex" if complex_ok else "real"
    if value is None or isinstance(value, (str, bytes)):
        raise InputTypeError(f"{name}: expected an array of {what} numbers, got {type(value).__name__}")
    try:
        a = np.array(value)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name}: expected an array of {what} numbers, got {type(value).__name__}") from exc
    if a.dtype.kind not in ("iufc" if complex_ok else "iuf"):
        raise InputTypeError(f"{name}: expected an array of {what} numbers, got dtype {a.dtype}")
    return a.astype(np.complex128 if complex_ok else np.float64)


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


def unwrap_along_frequency(phase: np.ndarray) -> np.ndarray:
    """``phase [..., F]`` (rad) unwrapped along its last axis, each curve on its own; NaN
    points stay NaN and are bridged."""
    out = np.full(phase.shape, np.nan)
    flat_p, flat_o = phase.reshape(-1, phase.shape[-1]), out.reshape(-1, phase.shape[-1])
    for r in range(flat_p.shape[0]):
        ok = np.isfinite(flat_p[r])
        if ok.any():
            flat_o[r, ok] = np.unwrap(flat_p[r, ok])
    return out


def _per_point(value, name: str, shape: tuple, integer: bool) -> np.ndarray:
    """``value`` ([F] for a 1x1 response, or [O, I, F] = ``shape``) as a read-only array of that
    shape: int64 bit masks >= 0 (``integer``), else float64 >= 0 or NaN."""
    if integer:
        a = np.array(value)
        if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
            raise InputTypeError(f"{name}: expected an array of integer bit masks, got dtype {a.dtype}")
        a = a.astype(np.int64)
    else:
        a = _as_array(value, name)
    if a.shape == shape[-1:] and shape[:2] == (1, 1):
        a = a.reshape(shape)
    if a.shape != shape:
        raise ShapeError(f"{name}: expected shape [O, I, F] = {shape} like the response, got {a.shape}")
    if integer and np.any(a < 0):
        raise ParameterError(f"{name}: expected bit masks >= 0, got minimum {a.min()}")
    if not integer and (np.any(np.isinf(a)) or np.any(a < 0)):
        raise ParameterError(f"{name}: expected values >= 0 or NaN (unknown), got {a[np.isinf(a) | (a < 0)][0]:g}")
    return _readonly(a.copy())


def _check_omega(omega) -> np.ndarray:
    """``omega`` as float64 [F]: finite, > 0, strictly increasing."""
    w = _as_array(omega, "omega")
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
    return w


def _check_response(response, n_f: int) -> tuple[np.ndarray, bool]:
    """``(response as complex128 [O, I, F], whether it came as SISO [F])``; NaN allowed, Inf not."""
    h = _as_array(response, "response", complex_ok=True)
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
    return h, siso_input


def _check_cov(cov, shape: tuple, siso_input: bool) -> np.ndarray:
    """``cov`` as [O, I, F, 2, 2] (``shape`` = (O, I, F); NaN where None): symmetric, variances
    >= 0, |correlation| <= 1."""
    n_o, n_i, n_f = shape
    if cov is None:
        return np.full((n_o, n_i, n_f, 2, 2), np.nan)
    c = _as_array(cov, "cov")
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
    return c


def _check_meta(meta) -> dict:
    """A strict-JSON copy of ``meta`` (a dict; None gives {})."""
    if meta is None:
        meta = {}
    check_type(meta, "meta", dict, "a dict")
    try:
        return json.loads(json.dumps(meta, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"meta: expected strict-JSON-serialisable values (no NaN/Inf), got: {exc}") from exc


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
        w = _check_omega(omega)
        h, siso_input = _check_response(response, w.size)
        shape = h.shape
        self._omega = _readonly(w.copy())
        self._response = _readonly(h.copy())
        self._cov = _readonly(np.array(_check_cov(cov, shape, siso_input), dtype=np.float64, copy=True))
        self._flags = _per_point(np.zeros(shape, np.int64) if flags is None else flags, "flags", shape, True)
        self._reduced_chi2 = _per_point(np.full(shape, np.nan) if reduced_chi2 is None else reduced_chi2, "reduced_chi2",
                                        shape, False)
        self._output_labels = _check_labels(output_labels, shape[0], "output_labels", "y")
        self._input_labels = _check_labels(input_labels, shape[1], "input_labels", "u")
        self._meta = _check_meta(meta)

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

    def with_branch(self, take, phase) -> "FrequencyResponse":
        """A copy with the points ``take`` (bool, broadcastable to ``[O, I, F]``) on the phase
        ``phase`` (rad, broadcastable likewise; e.g. a single exposure's alias branch), their
        magnitude kept and the sign of their magnitude-phase covariance turned (the phase's
        direction is reversed on that branch); everything else kept."""
        shape = self._response.shape
        t = np.broadcast_to(np.asarray(take, dtype=bool), shape)
        ph = np.broadcast_to(np.asarray(phase, dtype=np.float64), shape)
        cov = np.array(self._cov)
        cov[t, 0, 1] *= -1
        cov[t, 1, 0] *= -1
        return self.replace(response=np.where(t, np.abs(self._response) * np.exp(1j * ph), self._response), cov=cov)

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
        return unwrap_along_frequency(np.where(self.valid, self.phase, np.nan))

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
        check_type(name, "name", str, "a string")
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

        check_type(frd, "frd", control.FrequencyResponseData, "control.FrequencyResponseData")
        data = getattr(frd, "frdata", None)
        if data is None:  # python-control 0.10.1 (the floor) has fresp only; frdata from 0.10.2
            data = frd.fresp
        return cls(
            np.array(frd.omega, dtype=np.float64),
            np.array(data, dtype=np.complex128).reshape(frd.noutputs, frd.ninputs, -1),
            input_labels=list(frd.input_labels),
            output_labels=list(frd.output_labels),
        )

    # ------------------------------------------------------------------ files
    # (the formats and their reading rules: torchblur.sysid.frequency_response_io)
    def to_mat(self, path: str | os.PathLike) -> None:
        """Write a MATLAB ``.mat`` file (:func:`~torchblur.sysid.frequency_response_io.write_mat`)."""
        frf_io.write_mat(self, path)

    @classmethod
    def from_mat(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a file written by :meth:`to_mat` (:func:`~torchblur.sysid.frequency_response_io.read_mat`)."""
        return frf_io.read_mat(cls, path)

    def to_csv(self, path: str | os.PathLike, *, extra_columns: dict | None = None) -> None:
        """Write a CSV file, the correlation lost (:func:`~torchblur.sysid.frequency_response_io.write_csv`)."""
        frf_io.write_csv(self, path, extra_columns=extra_columns)

    @classmethod
    def from_csv(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a CSV written by :meth:`to_csv` (:func:`~torchblur.sysid.frequency_response_io.read_csv`)."""
        return frf_io.read_csv(cls, path)

    def to_dict(self) -> dict[str, Any]:
        """The JSON document as a dict (:func:`~torchblur.sysid.frequency_response_io.to_dict`)."""
        return frf_io.to_dict(self)

    def to_json(self, path: str | os.PathLike) -> None:
        """Write everything (exact floats, covariance, labels, meta) to a JSON file."""
        frf_io.write_json(self, path)

    @classmethod
    def from_dict(cls, doc: dict) -> "FrequencyResponse":
        """Inverse of :meth:`to_dict`; checks ``schema`` and ``schema_version``."""
        return frf_io.from_dict(cls, doc)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> "FrequencyResponse":
        """Read a file written by :meth:`to_json`, bit-exact; the file is untrusted input
        (:func:`~torchblur.sysid.frequency_response_io.read_json`)."""
        return frf_io.read_json(cls, path)
