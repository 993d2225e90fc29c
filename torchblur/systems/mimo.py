"""A multi-input multi-output plant (a tip-tilt mirror) and the spot's motion when one of its
inputs is driven by a sine (docs/mimo_and_spots.md).

Channel ``(o, i)`` (output o from input i) is a SISO :class:`~torchblur.systems.lti.Plant`
with its own delay, ``y_o(t) = sum_i H_oi u_i``; conventions as in :mod:`torchblur.systems.lti`
(``omega`` rad/s, phases rad, a response ``[O, I, F]``, frequency last). With input ``i``
driven by ``amplitude sin(omega t)`` from rest at t = 0 (the other inputs held at 0), the image
of the spot moves by ``d(t) = G @ y(t)``, ``G [2, O]`` the image motion per output unit (the
identity for one tip-tilt spot; its own per spot of a Shack-Hartmann sensor,
:mod:`torchblur.image.spots`): :class:`MIMOSineTrajectory`, exact with transients.

This module is not imported by ``import torchblur`` (it needs scipy through ``lti``).
"""
from __future__ import annotations

import math  # noqa: F401  (docstring examples)
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_finite, check_type
from torchblur.systems.lti import LTISineTrajectory, Plant
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Trajectory

__all__ = ["PlantMatrix", "MIMOSineTrajectory", "plant_from_coefficients", "AXIS_LABELS"]

AXIS_LABELS = ("x", "y")


def _is_nested(value) -> bool:
    """True for a list of lists of coefficient lists (a MIMO ``num``/``den``)."""
    return (isinstance(value, (list, tuple)) and len(value) > 0 and isinstance(value[0], (list, tuple))
            and len(value[0]) > 0 and isinstance(value[0][0], (list, tuple)))


@dataclass(frozen=True)
class PlantMatrix:
    """An ``O x I`` matrix of SISO plants (a tip-tilt mirror: 2 x 2).

    Args:
        channels: ``channels[o][i]`` = the :class:`~torchblur.systems.lti.Plant` from input i to
            output o (px per input unit), O, I >= 1 rows and columns.
        output_labels, input_labels: channel names, default ``("x", "y")`` for two.

    Raises :class:`~torchblur.errors.InputTypeError` for a channel that is not a Plant and
    :class:`~torchblur.errors.ShapeError` for ragged rows.

    Example:
        >>> d = Plant((1.0,), (1e-3, 1.0))
        >>> c = Plant((0.2,), (1e-3, 1.0))
        >>> pm = PlantMatrix(((d, c), (c, d)))
        >>> pm.frequency_response(np.array([1.0, 10.0])).shape
        (2, 2, 2)
    """

    channels: tuple
    output_labels: tuple = ()
    input_labels: tuple = ()

    def __post_init__(self):
        rows = self.channels
        if isinstance(rows, (str, bytes)) or not isinstance(rows, Sequence) or not rows:
            raise ShapeError(f"channels: expected O rows of I plants ([o][i]), got {type(rows).__name__}")
        rows = tuple(tuple(r) if isinstance(r, Sequence) and not isinstance(r, (str, bytes)) else r for r in rows)
        for o, r in enumerate(rows):
            if not isinstance(r, tuple) or not r:
                raise ShapeError(f"channels[{o}]: expected a non-empty row of plants, got {r!r}")
        n_in = len(rows[0])
        if any(len(r) != n_in for r in rows):
            raise ShapeError(f"channels: expected every row to hold {n_in} plants, got rows of lengths {[len(r) for r in rows]}")
        for o, r in enumerate(rows):
            for i, p in enumerate(r):
                if not isinstance(p, Plant):
                    raise InputTypeError(f"channels[{o}][{i}]: expected a torchblur.systems.lti.Plant, got {type(p).__name__}")
        O, I = len(rows), n_in

        def labels(given, n, name):
            if not given:
                if n > len(AXIS_LABELS):
                    return tuple(f"{name[0]}{k}" for k in range(n))
                return AXIS_LABELS[:n]
            given = tuple(given)
            if len(given) != n or not all(isinstance(v, str) for v in given) or len(set(given)) != n:
                raise ShapeError(f"{name}: expected {n} distinct strings, got {given!r}")
            return given

        object.__setattr__(self, "channels", rows)
        object.__setattr__(self, "output_labels", labels(self.output_labels, O, "output_labels"))
        object.__setattr__(self, "input_labels", labels(self.input_labels, I, "input_labels"))

    @classmethod
    def from_coefficients(cls, num, den, delay_s=0.0) -> "PlantMatrix":
        """From nested coefficient lists ``num[o][i]``, ``den[o][i]`` (highest power first) and
        a delay that is one number (shared) or nested ``delay_s[o][i]`` (s)."""
        if not _is_nested(num):
            raise ShapeError("num: expected nested lists num[o][i] of coefficients (output o from input i)")
        if not _is_nested(den):
            raise ShapeError("den: expected nested lists den[o][i] of coefficients like num")
        O, I = len(num), len(num[0])
        for name, v in (("num", num), ("den", den)):
            if len(v) != O or any(len(r) != I for r in v):
                raise ShapeError(f"{name}: expected {O} rows of {I} channels, got rows of lengths {[len(r) for r in v]}")
        if isinstance(delay_s, (list, tuple)):
            if len(delay_s) != O or any(not isinstance(r, (list, tuple)) or len(r) != I for r in delay_s):
                raise ShapeError(f"delay_s: expected one number or {O} rows of {I} delays")
            delays = [[delay_s[o][i] for i in range(I)] for o in range(O)]
        else:
            delays = [[delay_s] * I for _ in range(O)]
        return cls(tuple(tuple(Plant(tuple(num[o][i]), tuple(den[o][i]), float(delays[o][i])) for i in range(I)) for o in range(O)))

    # ------------------------------------------------------------------ descriptions

    @property
    def n_outputs(self) -> int:
        return len(self.channels)

    @property
    def n_inputs(self) -> int:
        return len(self.channels[0])

    @property
    def order(self) -> int:
        """Largest channel order (number of poles)."""
        return max(p.order for r in self.channels for p in r)

    @property
    def delay_s(self) -> float:
        """Smallest channel delay (s)."""
        return min(p.delay_s for r in self.channels for p in r)

    def channel(self, output, input) -> Plant:
        """The SISO plant from ``input`` to ``output`` (indices or labels)."""
        o = self._index(output, self.output_labels, "output")
        i = self._index(input, self.input_labels, "input")
        return self.channels[o][i]

    def input_index(self, input) -> int:
        """Index of an input given by label (``"x"``) or index."""
        return self._index(input, self.input_labels, "input")

    @staticmethod
    def _index(value, labels, name) -> int:
        if isinstance(value, str):
            if value not in labels:
                raise ParameterError(f"{name}: expected one of {labels}, got {value!r}")
            return labels.index(value)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value < len(labels):
            raise ParameterError(f"{name}: expected one of {labels} or an index in [0, {len(labels)}), got {value!r}")
        return int(value)

    def frequency_response(self, omega) -> np.ndarray:
        """``H(j omega)`` with delays, complex ``[O, I, ...]`` for ``omega`` (rad/s) of shape ``[...]``."""
        return np.stack([np.stack([p.frequency_response(omega) for p in r]) for r in self.channels])

    def settling_time_s(self, tol: float = 1e-7) -> float:
        """The slowest channel's :meth:`~torchblur.systems.lti.Plant.settling_time_s` (s)."""
        return max(p.settling_time_s(tol) for r in self.channels for p in r)

    def to_control(self, pade_order: int | None = None):
        """A ``control.TransferFunction`` with O outputs and I inputs (labels kept); each
        channel as :meth:`Plant.to_control` (its delay as a Pade approximation of
        ``pade_order``, or left out)."""
        import control

        return control.combine_tf([[p.to_control(pade_order) for p in r] for r in self.channels],
                                  inputs=list(self.input_labels), outputs=list(self.output_labels))


def plant_from_coefficients(num, den, delay_s=0.0):
    """A :class:`~torchblur.systems.lti.Plant` for flat coefficient lists, a :class:`PlantMatrix` for
    nested ones (``num[o][i]``)."""
    if _is_nested(num) or _is_nested(den):
        return PlantMatrix.from_coefficients(num, den, delay_s)
    return Plant(tuple(float(v) for v in num), tuple(float(v) for v in den), float(delay_s))


class MIMOSineTrajectory(Trajectory):
    """The image motion ``d(t) = sum_o G[..., :, o] y_o(t)`` when ``input`` of ``plant`` is
    driven by ``amplitude sin(omega t)`` from rest at t = 0 (every other input at 0): exact,
    transients and delays included.

    Args:
        plant: a :class:`PlantMatrix` (or a :class:`~torchblur.systems.lti.Plant`, seen as 1 x 1).
        amplitude: command amplitude (input units), ``[...]``.
        omega: rad/s, ``[...]``, > 0.
        input: the driven input, a label (``"x"``, ``"y"``) or an index.
        image_matrix: ``G``, image motion per output unit (px per px), ``[2, O]`` or
            ``[..., 2, O]``; default the identity (O = 2: output x along x, y along y) or
            ``[[1], [0]]`` (O = 1).

    Batch ``[...]`` = broadcast of amplitude, omega and the leading dims of ``image_matrix``.
    ``position(t)[..., s, :]`` = displacement (px) from the rest position at time
    ``t[..., s]`` (s).

    :meth:`path_length` is the sum of the channels' bounds (each
    :meth:`LTISineTrajectory.path_length`): by the triangle inequality an upper bound of the
    path of the sum.

    Example:
        >>> d = Plant((1.0,), (1e-3, 1.0)); c = Plant((0.2,), (1e-3, 1.0))
        >>> traj = MIMOSineTrajectory(PlantMatrix(((d, c), (c, d))), 3.0, 2 * math.pi * 50, input="y")
        >>> traj.position(torch.zeros(5, dtype=torch.float64)).shape
        torch.Size([5, 2])
    """

    __slots__ = ("plant", "input", "parts", "image_matrix")

    def __init__(self, plant, amplitude, omega, *, input="x", image_matrix=None):
        if isinstance(plant, Plant):
            plant = PlantMatrix(((plant,),), output_labels=("x",), input_labels=("x",))
        check_type(plant, "plant", PlantMatrix, "a PlantMatrix or a Plant")
        j = plant.input_index(input)
        O = plant.n_outputs
        if image_matrix is None:
            g = torch.zeros(2, O, dtype=torch.float64)
            g[0, 0] = 1.0
            if O >= 2:
                g[1, 1] = 1.0
        else:
            g = check_finite(as_tensor(image_matrix, "image_matrix", dtype=torch.float64), "image_matrix")
            if g.dim() < 2 or tuple(g.shape[-2:]) != (2, O):
                raise ShapeError(f"image_matrix: expected shape [..., 2, {O}] (px per output unit), got {tuple(g.shape)}")
        self.plant = plant
        self.input = plant.input_labels[j]
        self.image_matrix = g
        self.parts = [LTISineTrajectory(plant.channels[o][j], amplitude, omega, direction=g[..., :, o]) for o in range(O)]

    @property
    def shape(self) -> torch.Size:
        return torch.broadcast_shapes(*(p.shape for p in self.parts))

    def outputs(self, t: torch.Tensor) -> torch.Tensor:
        """The plant outputs ``y_o(t)`` (output units) ``[..., S, O]`` at times ``t`` ``[..., S]``."""
        return torch.stack([p.output(t) for p in self.parts], -1)

    def position(self, t: torch.Tensor) -> torch.Tensor:
        """Displacement (px) ``[..., S, 2]`` at absolute command times ``t`` (s) ``[..., S]``."""
        return sum((p.position(t) for p in self.parts[1:]), self.parts[0].position(t))

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        """Upper bound of the path (px) during ``window``: the sum of the channels' bounds."""
        return sum((p.path_length(window) for p in self.parts[1:]), self.parts[0].path_length(window))

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        """``omega * duration`` (every channel oscillates at the command's frequency)."""
        return self.parts[0].phase_span(window)

    def __repr__(self) -> str:
        return f"MIMOSineTrajectory(shape={tuple(self.shape)}, input={self.input!r}, outputs={self.plant.n_outputs})"
