"""A Shack-Hartmann wavefront sensor behind a deformable mirror: its subapertures, their spots on
the sensor camera and the geometry matrix G (px per input unit).

The pupil is a disc of diameter ``pupil_diameter`` (actuator pitches) covered by an
``n_across x n_across`` grid of square subapertures; one is valid when at least
``min_illumination`` of it is lit (a midpoint grid), and valid subaperture ``m`` is the m-th
valid cell in row-major order. ``G[m, j]`` and ``G[M + m, j]`` are ``slope_px`` times the mean x
and y slope of ``phi_j`` (:mod:`torchblur.dm.mirror`) over the lit part of subaperture m,
integrated row by row (:func:`lit_rows`: exact along a row, Gauss-Legendre across). The spots'
positions, the rule and its accuracy against scipy ``quad``: docs/deformable_mirrors.md, "The
model".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchblur.errors import ParameterError, check_int, check_real_scalar
from torchblur.dm.mirror import influence

__all__ = ["ShackHartmann", "lit_rows", "mean_slopes", "subaperture_grid"]


def _offsets(oversample: int) -> np.ndarray:
    """Midpoints ``[q*q, 2]`` of a q x q grid over the unit square centred on 0."""
    u = (np.arange(oversample) + 0.5) / oversample - 0.5
    y, x = np.meshgrid(u, u, indexing="ij")
    return np.stack([x.reshape(-1), y.reshape(-1)], -1)


def subaperture_grid(n_across: int, pupil_diameter: float, oversample: int = 32):
    """Every cell of the subaperture grid: centres ``[n*n, 2]`` (pitches, row-major), the side
    ``d`` and the illuminated fractions ``[n*n]`` (module docstring)."""
    n = check_int(n_across, "n_across", low=1)
    D = check_real_scalar(pupil_diameter, "pupil_diameter", positive=True)
    q = check_int(oversample, "oversample", low=1)
    d = D / n
    c = (np.arange(n, dtype=np.float64) - (n - 1) / 2) * d
    y, x = np.meshgrid(c, c, indexing="ij")
    centres = np.stack([x.reshape(-1), y.reshape(-1)], -1)
    pts = centres[:, None, :] + d * _offsets(q)  # [n*n, q*q, 2]
    inside = np.hypot(pts[..., 0], pts[..., 1]) <= D / 2
    return centres, d, inside.mean(-1)


def lit_rows(centres, side: float, pupil_radius: float, nodes: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A quadrature over the lit part of each square subaperture, row by row (module docstring):
    ``(t, weight, lo, hi)``, each ``[M, K]``: row k of subaperture m lies at ``t`` of the SECOND
    coordinate (y for ``centres`` given as (x, y); pass ``centres[:, ::-1]`` for columns), with
    quadrature weight ``weight`` and its lit interval ``[lo, hi]`` of the first coordinate (square
    and pupil disc; empty rows have ``lo = hi``). The rows are Gauss-Legendre nodes, ``nodes`` per
    piece, the side cut into pieces where the lit interval's ends change formula (the disc meets a
    vertical side of the square, or the disc's top or bottom), so every piece is smooth inside."""
    centres = np.asarray(centres, dtype=np.float64)
    n = check_int(nodes, "nodes", low=1)
    R, h = float(pupil_radius), side / 2
    x_gl, w_gl = np.polynomial.legendre.leggauss(n)
    rows = []
    for c1, c2 in centres:
        cuts = [c2 - h, c2 + h, R, -R] + [sgn * math.sqrt(R * R - a * a) for a in (c1 - h, c1 + h) if abs(a) < R for sgn in (1, -1)]
        cuts = np.unique(np.clip(cuts, c2 - h, c2 + h))
        mid, half = (cuts[1:] + cuts[:-1]) / 2, (cuts[1:] - cuts[:-1]) / 2
        t = (mid[:, None] + half[:, None] * x_gl).ravel()
        w = (half[:, None] * w_gl).ravel()
        s = np.sqrt(np.maximum(R * R - t * t, 0.0))
        lo, hi = np.maximum(c1 - h, -s), np.minimum(c1 + h, s)
        rows.append((t, w, lo, np.maximum(hi, lo)))
    K = max(r[0].size for r in rows)
    out = np.zeros((4, len(rows), K))
    for m, r in enumerate(rows):
        for i, v in enumerate(r):
            out[i, m, :v.size] = v
    return out[0], out[1], out[2], out[3]


def mean_slopes(centres, side: float, pupil_radius: float, actuator_xy, coupling: float, oversample: int = 32,
                chunk: int = 64, *, registration=None) -> np.ndarray:
    """Mean influence-function slope over the illuminated part of each subaperture:
    ``[2M, N]`` (rows: x slopes of the M subapertures, then y), per pitch per unit command
    (module docstring: by rows, :func:`lit_rows`). With ``registration`` (a
    :class:`~torchblur.dm.registration.Registration`) the actuators sit at
    ``registration.actuators(actuator_xy)`` and their influence functions are
    ``registration.magnification`` times wider (its ``coupling``, when set, replaces ``coupling``).

    Args:
        centres: ``[M, 2]`` subaperture centres (pitches).
        side: subaperture side (pitches).
        pupil_radius: points farther from 0 are dark (pitches).
        actuator_xy: ``[N, 2]`` actuator positions (pitches).
        coupling: the influence functions' coupling at one pitch.
        oversample: Gauss-Legendre rows per smooth piece of a subaperture's side.
        chunk: subapertures per step (memory: chunk * 8 * oversample * N * 2 doubles).
        registration: the mirror's registration on the sensor (None: nominal).
    """
    if registration is not None:
        actuator_xy, coupling = registration.actuators(actuator_xy), registration.sensor_coupling(coupling)
    centres = np.asarray(centres, dtype=np.float64)
    M = centres.shape[0]
    out = np.zeros((2, M, np.asarray(actuator_xy).shape[0]))
    for a in range(2):  # a = 0: x slopes, rows along y; a = 1: y slopes, columns along x (coordinates swapped)
        t, w, lo, hi = lit_rows(centres[:, ::-1] if a else centres, side, pupil_radius, oversample)
        area = np.maximum((w * (hi - lo)).sum(-1), 1e-300)
        for s in range(0, M, chunk):
            ends = [np.stack([e, t[s:s + chunk]], -1) for e in (hi[s:s + chunk], lo[s:s + chunk])]  # [m, K, 2] (first, second)
            if a:
                ends = [e[..., ::-1] for e in ends]
            diff = influence(ends[0], actuator_xy, coupling) - influence(ends[1], actuator_xy, coupling)  # [m, K, N]
            out[a, s:s + chunk] = np.einsum("mk,mkn->mn", w[s:s + chunk], diff) / area[s:s + chunk, None]
    return out.reshape(2 * M, -1)


@dataclass(frozen=True, eq=False)
class ShackHartmann:
    """A Shack-Hartmann sensor (module docstring: the model).

    Args:
        n_across: subapertures across the pupil.
        pupil_diameter: pupil diameter in actuator pitches.
        pitch_px: spot spacing on the camera (px).
        sigma_px: spot PSF std at the pupil centre (px).
        sigma_variation: relative growth of the PSF std at the pupil edge (>= 0).
        slope_px: spot displacement (px) per unit mean wavefront slope (influence units per pitch).
        min_illumination: smallest illuminated fraction of a valid subaperture, in (0, 1].
        oversample: integration points per subaperture side.
    """

    n_across: int
    pupil_diameter: float
    pitch_px: float = 16.0
    sigma_px: float = 1.5
    sigma_variation: float = 0.0
    slope_px: float = 1.0
    min_illumination: float = 0.5
    oversample: int = 32

    def __post_init__(self):
        check_int(self.n_across, "n_across", low=1)
        check_int(self.oversample, "oversample", low=1)
        for name in ("pupil_diameter", "pitch_px", "sigma_px", "slope_px"):
            object.__setattr__(self, name, check_real_scalar(getattr(self, name), name, positive=True))
        object.__setattr__(self, "sigma_variation", check_real_scalar(self.sigma_variation, "sigma_variation", nonnegative=True))
        f = check_real_scalar(self.min_illumination, "min_illumination", positive=True)
        if f > 1:
            raise ParameterError(f"min_illumination: expected a value in (0, 1], got {f:g}")
        centres, side, frac = subaperture_grid(self.n_across, self.pupil_diameter, self.oversample)
        valid = np.flatnonzero(frac >= f - 1e-12)
        if valid.size == 0:
            raise ParameterError(f"min_illumination: no subaperture is {f:g} illuminated")
        object.__setattr__(self, "_centres", centres[valid])
        object.__setattr__(self, "_side", side)
        object.__setattr__(self, "_fraction", frac[valid])
        object.__setattr__(self, "_index", valid)

    @classmethod
    def from_config(cls, wfs, mirror) -> "ShackHartmann":
        """From a :class:`~torchblur.config.WFSConfig` and the mirror it looks at
        (its pupil: ``mirror.n_across`` pitches across)."""
        return cls(n_across=wfs.n_across, pupil_diameter=float(mirror.n_across), pitch_px=wfs.pitch_px, sigma_px=wfs.sigma_px,
                   sigma_variation=wfs.sigma_variation, slope_px=wfs.slope_px, min_illumination=wfs.min_illumination,
                   oversample=wfs.oversample)

    @property
    def n_valid(self) -> int:
        """M, the valid subapertures."""
        return int(self._index.size)

    @property
    def centres(self) -> np.ndarray:
        """``[M, 2]`` valid subaperture centres (pitches)."""
        return self._centres.copy()

    @property
    def side(self) -> float:
        """Subaperture side (pitches)."""
        return float(self._side)

    @property
    def illuminated_fraction(self) -> np.ndarray:
        """``[M]``."""
        return self._fraction.copy()

    @property
    def grid_index(self) -> np.ndarray:
        """``[M]`` row-major index of each valid subaperture in the n_across x n_across grid."""
        return self._index.copy()

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(H, W)`` of the sensor camera's frame (px)."""
        s = int(math.ceil(self.n_across * self.pitch_px))
        return (s, s)

    @property
    def rest_px(self) -> np.ndarray:
        """``[M, 2]`` rest positions (x, y px) of the valid spots."""
        r, c = np.divmod(self._index, self.n_across)
        return np.stack([(c + 0.5) * self.pitch_px - 0.5, (r + 0.5) * self.pitch_px - 0.5], -1).astype(np.float64)

    @property
    def sigma_spots_px(self) -> np.ndarray:
        """``[M]`` PSF std of each spot (px)."""
        rho = np.hypot(self._centres[:, 0], self._centres[:, 1]) / (self.pupil_diameter / 2)
        return self.sigma_px * (1 + self.sigma_variation * rho)

    def geometry_matrix(self, mirror, registration=None) -> np.ndarray:
        """G ``[2M, N]`` in px per input unit of the nominal actuator (gain 1) of ``mirror``
        (a :class:`~torchblur.dm.mirror.DeformableMirror`; module docstring: the formula), the
        mirror at ``registration`` (a :class:`~torchblur.dm.registration.Registration`; None: nominal)."""
        return self.slope_px * mean_slopes(self._centres, self._side, self.pupil_diameter / 2, mirror.actuator_xy,
                                           mirror.coupling, self.oversample, registration=registration)

    def __repr__(self) -> str:
        return (f"ShackHartmann(n_across={self.n_across}, M={self.n_valid}, pitch_px={self.pitch_px:g}, "
                f"sigma_px={self.sigma_px:g}, frame {self.frame_shape})")
