"""A deformable mirror: actuators on a square grid in a circular pupil, Gaussian influence
functions and one resonance per actuator.

Lengths in actuator pitches, 0 at the pupil centre, x to the right, y down; actuator ``j`` is the
j-th kept cell of the ``n_across x n_across`` grid in row-major order. Actuator j's influence is
``phi_j = exp(-r_j^2 / (2 w^2))``, ``w = 1 / sqrt(-2 ln coupling)``, and its dynamics
``H_j(s) = gain_j wn_j^2 / (s^2 + 2 zeta_j wn_j s + wn_j^2) exp(-s delay_j)``, ``wn_j = 2 pi
mode_hz_j`` (gain 1 nominal, 0 dead). :meth:`DeformableMirror.build` draws the seeded spread,
the weak and dead actuators and the table's (:func:`read_actuator_table`): docs/deformable_mirrors.md,
"The model".
"""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass

import numpy as np

from torchblur.errors import ConfigError, ParameterError, ShapeError, check_int, check_real_scalar, excerpt
from torchblur.files import read_bounded
from torchblur.systems.lti import Plant

__all__ = ["DeformableMirror", "actuator_grid", "influence", "influence_width", "read_actuator_table"]

TABLE_COLUMNS = ("actuator", "mode_hz", "damping", "gain", "delay_s")
TABLE_MAX_BYTES = 1 << 20  #: an actuator table's largest size (bytes)


def actuator_grid(n_across: int) -> np.ndarray:
    """Actuator positions ``[N, 2]`` (x, y in pitches) of an ``n_across`` grid (module docstring)."""
    n = check_int(n_across, "n_across", low=1)
    c = np.arange(n, dtype=np.float64) - (n - 1) / 2
    y, x = np.meshgrid(c, c, indexing="ij")
    keep = np.hypot(x, y) <= n / 2 + 0.1
    return np.stack([x[keep], y[keep]], -1)


def influence_width(coupling: float) -> float:
    """Gaussian width w (pitches) of an influence function that is ``coupling`` one pitch away."""
    c = check_real_scalar(coupling, "coupling", positive=True)
    if c >= 1:
        raise ParameterError(f"coupling: expected a value in (0, 1), got {c:g}")
    return 1.0 / math.sqrt(-2.0 * math.log(c))


def influence(points, actuator_xy, coupling: float) -> np.ndarray:
    """``phi[..., j]``: actuator j's surface at ``points [..., 2]`` (x, y pitches) per unit command, ``[..., N]``."""
    w = influence_width(coupling)
    d = np.asarray(points, dtype=np.float64)[..., None, :] - np.asarray(actuator_xy, dtype=np.float64)
    return np.exp(-(d ** 2).sum(-1) / (2 * w * w))


TABLE_HIGH = {"mode_hz": 1e7, "damping": 1e3, "gain": 1e6, "delay_s": 1.0}  #: the largest value of each column a table may give


def _table_number(text: str, row: int, column: str, path: str, *, low: float, strict: bool) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ConfigError(f"dm.actuator_table: {path} row {row}, column {column}: expected a number, got {excerpt(text)}") from None
    high = TABLE_HIGH[column]
    if not math.isfinite(v) or v < low or (strict and v == low) or v > high:
        what = (f"> {low:g}" if strict else f">= {low:g}") + f" and <= {high:g}"
        raise ConfigError(f"dm.actuator_table: {path} row {row}, column {column}: expected a finite number {what}, got {excerpt(text)}")
    return v


def read_actuator_table(path, n_actuators: int) -> dict[int, tuple[float, float, float, float]]:
    """Read a CSV ``actuator,mode_hz,damping,gain,delay_s`` (untrusted input).

    The header must be exactly those five columns; every row has five cells: ``actuator`` an
    integer in ``[0, n_actuators)`` listed once, ``mode_hz > 0``, ``damping > 0``, ``gain >= 0``
    (0: dead), ``delay_s >= 0``. Blank lines are skipped; the file is at most 1 MiB. Rows are
    counted from 1 for the header. Returns ``{actuator: (mode_hz, damping, gain, delay_s)}``.

    Raises:
        ConfigError: naming ``dm.actuator_table``, the file, and the row and column at fault.
    """
    path = os.fspath(path)
    data = read_bounded(path, TABLE_MAX_BYTES, f"dm.actuator_table: {path}", error=ConfigError)  # the opening rule
    try:
        rows = list(csv.reader(io.StringIO(data.decode("utf-8"), newline="")))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"dm.actuator_table: {path}: not UTF-8 text (byte {exc.start})") from None
    except csv.Error as exc:
        raise ConfigError(f"dm.actuator_table: {path}: not a CSV table ({type(exc).__name__})") from None
    if not rows or [c.strip() for c in rows[0]] != list(TABLE_COLUMNS):
        got = rows[0] if rows else "an empty file"
        raise ConfigError(f"dm.actuator_table: {path} row 1: expected the header {','.join(TABLE_COLUMNS)}, got {excerpt(got)}")
    table: dict[int, tuple[float, float, float, float]] = {}
    for r, cells in enumerate(rows[1:], start=2):
        if not cells or all(not c.strip() for c in cells):
            continue
        if len(cells) != len(TABLE_COLUMNS):
            raise ConfigError(f"dm.actuator_table: {path} row {r}: expected {len(TABLE_COLUMNS)} cells, got {len(cells)}")
        text = cells[0].strip()
        if not text.lstrip("-").isdigit():
            raise ConfigError(f"dm.actuator_table: {path} row {r}, column actuator: expected an integer, got {excerpt(text)}")
        j = int(text)
        if not 0 <= j < n_actuators:
            raise ConfigError(f"dm.actuator_table: {path} row {r}, column actuator: expected an actuator in [0, {n_actuators}), got {j}")
        if j in table:
            raise ConfigError(f"dm.actuator_table: {path} row {r}, column actuator: actuator {j} is listed twice")
        mode = _table_number(cells[1].strip(), r, "mode_hz", path, low=0.0, strict=True)
        zeta = _table_number(cells[2].strip(), r, "damping", path, low=0.0, strict=True)
        gain = _table_number(cells[3].strip(), r, "gain", path, low=0.0, strict=False)
        delay = _table_number(cells[4].strip(), r, "delay_s", path, low=0.0, strict=False)
        table[j] = (mode, zeta, gain, delay)
    return table


def _index_list(value, name: str, n: int) -> tuple[int, ...]:
    out = tuple(check_int(v, name, low=0, high=n - 1) for v in value)
    if len(set(out)) != len(out):
        raise ParameterError(f"{name}: expected distinct actuator indices, got {list(value)}")
    return out


@dataclass(frozen=True, eq=False)
class DeformableMirror:
    """The mirror's actuators (module docstring: the model). Build one with :meth:`build` or
    :meth:`from_config`; the arrays are read-only.

    Attributes:
        n_across: actuators across the grid.
        coupling: an influence function's value one pitch from its actuator, in (0, 1).
        actuator_xy: ``[N, 2]`` actuator positions (x, y pitches).
        mode_hz, damping, gain, delay_s: ``[N]`` each actuator's resonance (Hz), damping ratio,
            DC gain (1 nominal, 0 dead) and pure delay (s).
        input_limit: the largest command magnitude (input units) a rig accepts.
    """

    n_across: int
    coupling: float
    actuator_xy: np.ndarray
    mode_hz: np.ndarray
    damping: np.ndarray
    gain: np.ndarray
    delay_s: np.ndarray
    input_limit: float = math.inf

    def __post_init__(self):
        check_int(self.n_across, "n_across", low=1)
        influence_width(self.coupling)
        xy = np.array(self.actuator_xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ShapeError(f"actuator_xy: expected shape [N, 2], got {xy.shape}")
        N = xy.shape[0]
        arrays = {"actuator_xy": xy}
        for name, low, strict in (("mode_hz", 0.0, True), ("damping", 0.0, True), ("gain", 0.0, False), ("delay_s", 0.0, False)):
            a = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            if a.shape != (N,):
                raise ShapeError(f"{name}: expected shape [{N}] (one per actuator), got {a.shape}")
            bad = (a <= low) if strict else (a < low)
            if not np.isfinite(a).all() or bad.any():
                raise ParameterError(f"{name}: expected finite values {'>' if strict else '>='} {low:g}, got {a}")
            arrays[name] = a
        limit = float(self.input_limit)
        if not limit > 0:
            raise ParameterError(f"input_limit: expected a value > 0, got {excerpt(self.input_limit)}")
        object.__setattr__(self, "input_limit", limit)
        for name, a in arrays.items():
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @classmethod
    def build(cls, n_across: int, *, coupling: float = 0.15, mode_hz: float = 1000.0, damping: float = 0.1,
              gain: float = 1.0, delay_s: float = 20e-6, mode_spread: float = 0.0, damping_spread: float = 0.0,
              gain_spread: float = 0.0, delay_spread_s: float = 0.0, dead=(), weak=(), weak_gain: float = 0.3,
              table: dict | None = None, seed: int = 0, input_limit: float = math.inf) -> "DeformableMirror":
        """A mirror with nominal dynamics plus a seeded spread, weak and dead actuators and a
        table's overrides (module docstring: the order). ``table``: ``{actuator: (mode_hz,
        damping, gain, delay_s)}`` as :func:`read_actuator_table` returns."""
        xy = actuator_grid(n_across)
        N = xy.shape[0]
        spreads = {k: check_real_scalar(v, k, nonnegative=True) for k, v in (
            ("mode_spread", mode_spread), ("damping_spread", damping_spread), ("gain_spread", gain_spread), ("delay_spread_s", delay_spread_s))}
        for name in ("mode_spread", "damping_spread", "gain_spread"):
            if spreads[name] >= 1 / 3:
                raise ParameterError(f"{name}: expected a relative std < 1/3 (3 std, the clip, must stay below 1), got {spreads[name]:g}")
        rng = np.random.default_rng(check_int(seed, "seed", low=0))
        z = np.clip(rng.standard_normal((4, N)), -3.0, 3.0)
        mode = check_real_scalar(mode_hz, "mode_hz", positive=True) * (1 + spreads["mode_spread"] * z[0])
        zeta = check_real_scalar(damping, "damping", positive=True) * (1 + spreads["damping_spread"] * z[1])
        g = check_real_scalar(gain, "gain", nonnegative=True) * (1 + spreads["gain_spread"] * z[2])
        delay = np.maximum(check_real_scalar(delay_s, "delay_s", nonnegative=True) + spreads["delay_spread_s"] * z[3], 0.0)
        g[list(_index_list(weak, "weak", N))] *= check_real_scalar(weak_gain, "weak_gain", nonnegative=True)
        g[list(_index_list(dead, "dead", N))] = 0.0
        for j, (m, d, gj, t) in (table or {}).items():
            j = check_int(j, "table", low=0, high=N - 1)
            mode[j], zeta[j], g[j], delay[j] = m, d, gj, t
        return cls(n_across=int(n_across), coupling=float(coupling), actuator_xy=xy, mode_hz=mode, damping=zeta,
                   gain=g, delay_s=delay, input_limit=input_limit)

    @classmethod
    def from_config(cls, dm, *, base_dir: str | None = None, seed: int = 0) -> "DeformableMirror":
        """From a :class:`~torchblur.config.DMConfig`; ``dm.actuator_table`` (a path,
        relative to ``base_dir`` when given and not absolute) is read with
        :func:`read_actuator_table`."""
        n = check_int(dm.n_across, "dm.n_across", low=1)
        table = None
        if dm.actuator_table:
            path = dm.actuator_table
            if base_dir is not None and not os.path.isabs(path):
                path = os.path.join(base_dir, path)
            table = read_actuator_table(path, actuator_grid(n).shape[0])
        return cls.build(n, coupling=dm.coupling, mode_hz=dm.mode_hz, damping=dm.damping, gain=dm.gain, delay_s=dm.delay_s,
                         mode_spread=dm.mode_spread, damping_spread=dm.damping_spread, gain_spread=dm.gain_spread,
                         delay_spread_s=dm.delay_spread_s, dead=dm.dead, weak=dm.weak, weak_gain=dm.weak_gain, table=table,
                         seed=seed, input_limit=math.inf if dm.input_limit is None else dm.input_limit)

    @property
    def n_actuators(self) -> int:
        """N."""
        return int(self.actuator_xy.shape[0])

    @property
    def dead(self) -> np.ndarray:
        """``[N]`` bool: gain 0."""
        return self.gain == 0

    def response(self, freq_hz) -> np.ndarray:
        """``H_j(j 2 pi f)`` of every actuator, complex ``[N, F]`` (``[N]`` for a number)."""
        f = np.asarray(freq_hz, dtype=np.float64)
        w = 2 * np.pi * f[..., None, :] if f.ndim else 2 * np.pi * f
        wn = 2 * np.pi * self.mode_hz[:, None] if f.ndim else 2 * np.pi * self.mode_hz
        zeta = self.damping[:, None] if f.ndim else self.damping
        g = self.gain[:, None] if f.ndim else self.gain
        d = self.delay_s[:, None] if f.ndim else self.delay_s
        return g * wn ** 2 / (wn ** 2 - w ** 2 + 2j * zeta * wn * w) * np.exp(-1j * w * d)

    def plant(self, j: int):
        """Actuator j as a :class:`~torchblur.systems.lti.Plant` (its delay included)."""
        j = check_int(j, "j", low=0, high=self.n_actuators - 1)
        wn = 2 * math.pi * float(self.mode_hz[j])
        return Plant(num=(float(self.gain[j]) * wn * wn,), den=(1.0, 2 * float(self.damping[j]) * wn, wn * wn),
                     delay_s=float(self.delay_s[j]))

    def to_control(self, pade_order: int | None = None) -> list:
        """One ``control.TransferFunction`` per actuator (python-control has no pure delay:
        with ``pade_order`` it is a Pade approximation, else left out, see ``delay_s``)."""
        return [self.plant(j).to_control(pade_order) for j in range(self.n_actuators)]

    def settling_time_s(self, tol: float = 1e-7) -> float:
        """The slowest actuator's settling time (s): ``ln(1/tol) / (zeta wn) + delay``."""
        rate = self.damping * 2 * np.pi * self.mode_hz
        return float(np.max(math.log(1.0 / tol) / rate + self.delay_s))

    def check_command(self, command, name: str = "amplitude") -> None:
        """Raise :class:`~torchblur.errors.ParameterError` naming ``name`` when any
        ``|command|`` exceeds :attr:`input_limit`."""
        c = np.abs(np.asarray(command, dtype=np.float64))
        if not np.isfinite(c).all():
            raise ParameterError(f"{name}: expected finite commands, got {excerpt(command)}")
        if c.size and c.max() > self.input_limit * (1 + 1e-12):
            raise ParameterError(f"{name}: a command of {c.max():g} exceeds the mirror's input_limit = {self.input_limit:g}")

    def __repr__(self) -> str:
        return (f"DeformableMirror(n_across={self.n_across}, N={self.n_actuators}, coupling={self.coupling:g}, "
                f"mode_hz {self.mode_hz.min():.4g}..{self.mode_hz.max():.4g}, dead={np.flatnonzero(self.dead).tolist()})")

