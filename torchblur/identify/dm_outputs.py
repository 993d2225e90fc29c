"""A DM identification's outputs in ``OUT/dm/`` (issue 17), written from a :class:`DMEstimate`
by :func:`write_dm_outputs`: ``actuators.csv`` (:class:`~torchblur.dm.actuator_fit.ActuatorTable`,
one row per actuator), ``interaction_matrix.npy`` ``[2M, N]`` (D0, px per input unit) with its
``_std.npy`` and ``.fits`` (astropy, optional), ``command_matrix.npy`` ``[N, 2M]`` and
``unseen_modes.npy`` ``[K, N]`` (:func:`command_matrix`, its rule in ``command_matrix.json``:
:data:`COMMAND_MATRIX_SCHEMA`), ``frf.json`` (D(jw) as a
:class:`~torchblur.sysid.frequency_response.FrequencyResponse`, 2M outputs ``s{m}_x`` then
``s{m}_y``, N inputs ``a{j}``), ``README.txt`` (:func:`dm_readme`: what ``dc_gain`` is relative
to) and ``actuator_maps.png`` (:func:`actuator_maps_figure`; none without matplotlib or with
``figures=False``). The columns and files: README.md, "Deformable mirrors read by a Shack-Hartmann
sensor"; every file reads back (:func:`read_actuators_csv`, ``numpy.load``,
:func:`torchblur.identify.read_outputs.read_outputs`).
"""
from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchblur.dm.actuator_fit import PARAMS, ActuatorTable
from torchblur.identify.verdict import failed_actuators
from torchblur.errors import ParameterError, ShapeError
from torchblur.sysid.frequency_response import FrequencyResponse

__all__ = ["DMEstimate", "command_matrix", "magnitude_phase_cov", "dm_frequency_response", "write_dm_outputs", "CSV_COLUMNS",
           "RCOND", "actuator_maps_figure", "dm_readme", "DC_GAIN_NOMINAL", "STATUS_STYLES", "read_actuators_csv", "COMMAND_MATRIX_SCHEMA"]

#: command_matrix.json's schema and the versions read (1: with ``schema``; its keys in :func:`command_matrix`)
COMMAND_MATRIX_SCHEMA = ("torchblur.dm.command_matrix", (1,))

#: singular values of D0 below RCOND times the largest are dropped from the command matrix
RCOND = 0.05
CSV_COLUMNS = ("actuator", "x", "y", "dc_gain", "dc_gain_std", "mode_hz", "mode_hz_std", "damping", "damping_std", "delay_s",
               "delay_s_std", "status", "reduced_chi2", "poor_fit", "dc_gain_unverified")
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DMEstimate:
    """What a DM identification estimated.

    Attributes:
        freq_hz: ``[F]``.
        D: ``[2M, N, F]`` complex, the dynamic interaction matrix (px per input unit).
        D_cov: ``[2M, N, F, 2, 2]`` covariance of ``(Re, Im) D``.
        table: the :class:`ActuatorTable` (its ``static_column`` is D0 ``[2M, N]``).
        meta: strict-JSON extras written into ``frf.json`` (plan, seed, ...).
        gains_unverified: the actuators whose DC gain the registration's edge test could not verify
            (``registration.json``'s ``gains_unverified``: their stds do not hold); actuators.csv's
            ``dc_gain_unverified`` column is 1 for them.
    """

    freq_hz: np.ndarray
    D: np.ndarray
    D_cov: np.ndarray
    table: ActuatorTable
    meta: dict = field(default_factory=dict)
    gains_unverified: tuple = ()

    @property
    def D0(self) -> np.ndarray:
        """``[2M, N]`` the static interaction matrix."""
        return self.table.static_column


def command_matrix(D0, *, rcond: float = RCOND):
    """The truncated-SVD pseudo-inverse of the interaction matrix.

    ``D0 = U diag(s) V^T``; the modes with ``s_k >= rcond * s_max`` are kept:
    ``C = V_k diag(1 / s_k) U_k^T``.

    Args:
        D0: ``[2M, N]`` (NaN refused).
        rcond: relative threshold in (0, 1).

    Returns:
        ``(C [N, 2M], unseen [K, N], info)``: ``unseen[k]`` a unit actuator-space mode the
        sensor does not see (dropped singular vectors, and the null space where N > 2M);
        ``info`` a dict: ``rule``, ``rcond``, ``singular_values``, ``n_kept``.
    """
    D0 = np.asarray(D0, dtype=np.float64)
    if D0.ndim != 2:
        raise ShapeError(f"D0: expected [2M, N], got shape {D0.shape}")
    if not np.all(np.isfinite(D0)):
        raise ParameterError("D0: expected finite values, got NaN or Inf")
    if not 0 < rcond < 1:
        raise ParameterError(f"rcond: expected a number in (0, 1), got {rcond!r}")
    U, s, Vt = np.linalg.svd(D0, full_matrices=True)
    k = int(np.sum(s >= rcond * s.max())) if s.size and s.max() > 0 else 0
    C = (Vt[:k].T / s[:k]) @ U[:, :k].T
    info = {"rule": "truncated SVD: singular values below rcond * max dropped", "rcond": float(rcond),
            "singular_values": s.tolist(), "n_kept": k, "n_unseen": int(Vt.shape[0] - k)}
    return C, Vt[k:], info


def magnitude_phase_cov(z, cov_ri):
    """``(Re, Im)`` covariances ``[..., 2, 2]`` of ``z`` ``[...]`` as (magnitude, phase)
    covariances (first-order); NaN where ``|z| = 0`` (the phase is undefined there)."""
    z = np.asarray(z)
    r = np.abs(z)
    with np.errstate(invalid="ignore", divide="ignore"):
        J = np.stack([np.stack([z.real / r, z.imag / r], -1), np.stack([-z.imag / r**2, z.real / r**2], -1)], -2)
    out = J @ cov_ri @ np.swapaxes(J, -1, -2)
    out[~(r > 0)] = np.nan
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def dm_frequency_response(est: DMEstimate) -> FrequencyResponse:
    """``D(jw)`` as a FrequencyResponse ``[2M, N, F]`` (labels in the module docstring)."""
    S, N, _ = est.D.shape
    M = S // 2
    order = np.argsort(est.freq_hz)
    outputs = [f"s{m}_x" for m in range(M)] + [f"s{m}_y" for m in range(M)]
    return FrequencyResponse(2 * math.pi * np.asarray(est.freq_hz)[order], est.D[:, :, order],
                             cov=magnitude_phase_cov(est.D, est.D_cov)[:, :, order], output_labels=outputs,
                             input_labels=[f"a{j}" for j in range(N)], meta=dict(est.meta))


def _csv_rows(t: ActuatorTable, unverified=()):
    xy = t.actuator_xy if t.actuator_xy is not None else np.full((len(t), 2), np.nan)
    flagged = {int(j) for j in unverified}
    for j in range(len(t)):
        vals = [getattr(t, k)[j] for p in PARAMS for k in (p, p + "_std")]
        yield [j, f"{xy[j, 0]:.6g}", f"{xy[j, 1]:.6g}", *(f"{v:.9g}" for v in vals), t.status[j], f"{t.reduced_chi2[j]:.4g}",
               int(t.poor_fit[j]), int(j in flagged)]


def _write_fits(path: Path, D0: np.ndarray) -> bool:
    try:
        from astropy.io import fits
    except ImportError:
        _log.info(f"dm: astropy is not installed: {path.name} skipped (pip install astropy)")
        return False
    hdu = fits.PrimaryHDU(D0)
    hdu.header["BUNIT"] = "px/unit"
    hdu.header["COMMENT"] = "torchblur static interaction matrix [2M, N]: rows x of all M subapertures, then y"
    hdu.writeto(path, overwrite=True)
    return True


#: how each actuator status / flag is marked on the maps (over the colour squares)
STATUS_STYLES = {
    "dead": dict(marker="x", color="red", s=90, linewidths=2.0, text="dead (no response; not coloured)"),
    "weak": dict(marker="o", color="orange", s=260, linewidths=1.8, facecolors="none", text="weak (DC gain < half the median)"),
    "poor_fit": dict(marker="D", color="magenta", s=330, linewidths=1.5, facecolors="none", text="poor_fit (model fails chi2 test)"),
    "failed": dict(marker="s", color="black", s=420, linewidths=1.8, facecolors="none", text="failed (see report.txt)"),
}
_MAPS = (("DC gain", "dc_gain", "× nominal (1 = nominal actuator)"), ("mode", "mode_hz", "Hz"), ("damping", "damping", "ratio ζ"))


def actuator_maps_figure(t: ActuatorTable, *, failed=()):
    """DC gain, mode frequency and damping over the actuator grid (a
    ``matplotlib.figure.Figure``; the backend and pyplot are untouched).

    Each live actuator is a square coloured by its value (dead ones are not: their dynamics
    are NaN and their DC gain about 0); every status and flag is marked on all three maps
    (:data:`STATUS_STYLES`: dead, weak, poor_fit, and ``failed``: the actuators the verdict
    flags failed, e.g. ``failed_actuators(t, D)``), each kind present named in the legend. The
    axes are the guide's (docs/deformable_mirrors.md): actuator pitches, 0 at the pupil
    centre, x right, y down (image rows).

    Args:
        t: the actuator table (``actuator_xy`` required).
        failed: indices of the actuators flagged failed.
    """
    from matplotlib.figure import Figure

    if t.actuator_xy is None:
        raise ParameterError("t: expected an ActuatorTable with actuator_xy (positions), got None")
    xy = np.asarray(t.actuator_xy, dtype=np.float64)
    marks = {"dead": np.array([s == "dead" for s in t.status]), "weak": np.array([s == "weak" for s in t.status]),
             "poor_fit": np.asarray(t.poor_fit, dtype=bool), "failed": np.isin(np.arange(len(t)), np.asarray(list(failed), dtype=int))}
    fig = Figure(figsize=(14, 4.6), layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, (name, key, unit) in zip(axes, _MAPS):
        vals = np.asarray(getattr(t, key), dtype=np.float64)
        live = ~marks["dead"] & np.isfinite(vals)
        sc = ax.scatter(xy[live, 0], xy[live, 1], c=vals[live], s=150, marker="s", cmap="viridis")
        cb = fig.colorbar(sc, ax=ax, label=f"{name} ({unit})", shrink=0.85)
        cb.ax.ticklabel_format(useOffset=False)  # 0.9999, not "+1" and 1e-4 steps
        for status, sel in marks.items():
            if sel.any():
                st = dict(STATUS_STYLES[status])
                ax.scatter(xy[sel, 0], xy[sel, 1], label=st.pop("text"), zorder=3, **st)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.margins(0.15)  # the rings of an edge actuator inside the frame
        ax.invert_yaxis()  # y down, as the guide and the camera's rows
        ax.set_xlabel("x (pitches, right)")
        ax.set_ylabel("y (pitches, down)")
    if any(sel.any() for sel in marks.values()):
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=4, fontsize=8)
    return fig


def _write_maps(path: Path, t: ActuatorTable, failed=()) -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        _log.info(f"dm: matplotlib is not installed: {path.name} skipped (pip install matplotlib)")
        return False
    if t.actuator_xy is None:
        _log.info(f"dm: no actuator positions: {path.name} skipped")
        return False
    actuator_maps_figure(t, failed=failed).savefig(path, dpi=100)
    return True


def read_actuators_csv(path) -> dict:
    """``actuators.csv`` read back: ``{column: array [N]}`` for :data:`CSV_COLUMNS` (``actuator``
    int, ``status`` str, ``poor_fit`` and ``dc_gain_unverified`` bool, the others float64; NaN where written ``nan``).

    Raises:
        ParameterError: naming ``path``, a header other than :data:`CSV_COLUMNS`, a row of
            another length, a value that is not a number.
    """
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or tuple(rows[0]) != CSV_COLUMNS:
        raise ParameterError(f"{path}: header {rows[0] if rows else None}; expected {list(CSV_COLUMNS)}")
    body = [r for r in rows[1:] if r]
    if any(len(r) != len(CSV_COLUMNS) for r in body):
        raise ParameterError(f"{path}: expected {len(CSV_COLUMNS)} columns in every row")
    cols = dict(zip(CSV_COLUMNS, zip(*body))) if body else {c: () for c in CSV_COLUMNS}
    try:
        flags = ("poor_fit", "dc_gain_unverified")
        out = {c: np.array(v, dtype=np.float64) for c, v in cols.items() if c not in ("actuator", "status", *flags)}
        out.update(actuator=np.array(cols["actuator"], dtype=np.int64), status=np.array(cols["status"], dtype=str),
                   **{c: np.array(cols[c], dtype=np.int64) != 0 for c in flags})
    except ValueError as exc:
        raise ParameterError(f"{path}: not a number ({exc})") from None
    return {c: out[c] for c in CSV_COLUMNS}


DC_GAIN_NOMINAL = "dc_gain is relative to the nominal geometry G (the mirror model's registration and influence functions)"


def dm_readme(dc_gain_reference: str = DC_GAIN_NOMINAL) -> str:
    """The text of ``dm/README.txt``: one line per file, then what ``dc_gain`` is relative to."""
    return ("torchblur DM identification outputs\n"
            "actuators.csv: per actuator dc_gain, mode_hz, damping, delay_s with stds, status (x, y in actuator pitches)\n"
            "interaction_matrix.npy / _std.npy / .fits: the measured static interaction matrix D0 [2M, N] (px per input unit)\n"
            "command_matrix.npy, unseen_modes.npy, command_matrix.json: its truncated-SVD pseudo-inverse and the modes dropped\n"
            "frf.json: the dynamic interaction matrix D(jw) with covariances\n"
            "registration.json: the mirror's registration fitted to D0 (shift, rotation, magnification, coupling, stds) and the "
            "sensor's slope weighting\n"
            f"dc_gain: {dc_gain_reference}\n")


def write_dm_outputs(out_dir, est: DMEstimate, *, rcond: float = RCOND, figures: bool = True,
                     dc_gain_reference: str = DC_GAIN_NOMINAL) -> dict:
    """Write ``out_dir/dm/`` (see the module docstring), its log lines to this module's logger;
    ``figures=False`` (a run's ``report.figures``): no
    actuator_maps.png; ``dc_gain_reference``: what ``dc_gain`` is relative to (``README.txt``). Returns ``{name: path}`` of the files written."""
    d = Path(out_dir) / "dm"
    d.mkdir(parents=True, exist_ok=True)
    t = est.table
    paths = {}
    with open(d / "actuators.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        w.writerows(_csv_rows(t, est.gains_unverified))
    paths["actuators.csv"] = d / "actuators.csv"
    (d / "README.txt").write_text(dm_readme(dc_gain_reference))
    paths["README.txt"] = d / "README.txt"
    for name, arr in (("interaction_matrix.npy", est.D0), ("interaction_matrix_std.npy", t.static_column_std)):
        np.save(d / name, arr)
        paths[name] = d / name
    if _write_fits(d / "interaction_matrix.fits", est.D0):
        paths["interaction_matrix.fits"] = d / "interaction_matrix.fits"
    C, unseen, info = command_matrix(np.nan_to_num(est.D0), rcond=rcond)
    np.save(d / "command_matrix.npy", C)
    np.save(d / "unseen_modes.npy", unseen)
    doc = {"schema": COMMAND_MATRIX_SCHEMA[0], "schema_version": COMMAND_MATRIX_SCHEMA[1][-1], **info}
    (d / "command_matrix.json").write_text(json.dumps(doc, indent=1) + "\n")
    paths.update({k: d / k for k in ("command_matrix.npy", "unseen_modes.npy", "command_matrix.json")})
    dm_frequency_response(est).to_json(d / "frf.json")
    paths["frf.json"] = d / "frf.json"
    if figures and _write_maps(d / "actuator_maps.png", t, failed=sorted(failed_actuators(t, est.D))):
        paths["actuator_maps.png"] = d / "actuator_maps.png"
    _log.info(f"dm: {len(paths)} files in {d}; command matrix keeps {info['n_kept']} modes, {info['n_unseen']} unseen "
              f"(rcond {rcond:g})")
    return paths
