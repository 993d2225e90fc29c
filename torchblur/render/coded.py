"""Coded exposure, the image model: one image that tells the direction of time (issue 6 part 5).

A plain exposure integrates the spot over ``[t0, t0 + Te]``; the time reversal about the window
centre maps ``M sin(omega t + phi)`` to ``M sin(omega t + pi - 2c - phi)`` (c: the phase at the
centre) and gives exactly the same image (PHYSICS.md section 2, Proposition 3), so one image has
two phase branches. A *coded* exposure opens the shutter (or pulses the laser) only during an
asymmetric set of sub-intervals of the window, ``code = [(a_1, b_1), ..., (a_K, b_K)]`` as
fractions of ``Te``: the image is the sum of the sub-windows' images,

    Y = sum_k integral_{t0 + a_k Te}^{t0 + b_k Te} Psi(eta - y(t)) dt,

and the time reversal maps the code to its mirror ``(1 - b_k, 1 - a_k)``, which is a different
code unless the code is symmetric: the alias no longer renders the same image.

:func:`render_coded` renders it (the differentiable renderer on the sub-windows of
:func:`coded_windows`); the fit, :mod:`torchblur.fit.coded`, splats the nodes of every open
interval at once with the one forward model (:func:`~torchblur.render.splat.sine_blur_with_jacobian`).
"""
from __future__ import annotations

import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_finite, check_type
from torchblur.render.blur import RenderSettings, render_blur
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

__all__ = ["check_code", "mirror_code", "coded_windows", "render_coded"]


def check_code(code, *, like: torch.Tensor | None = None) -> torch.Tensor:
    """A code as a ``[K, 2]`` tensor of open intervals ``(a_k, b_k)``, fractions of the
    exposure, ``0 <= a_1 < b_1 <= a_2 < ... <= 1``; :class:`ParameterError` naming ``code``
    otherwise."""
    c = as_tensor(code, "code", like=like) if like is not None else as_tensor(code, "code", dtype=torch.float64)
    if c.dim() != 2 or c.shape[-1] != 2 or c.shape[0] < 1:
        raise ShapeError(f"code: expected shape [K, 2] (open intervals as fractions of the exposure), got {tuple(c.shape)}")
    check_finite(c, "code")
    flat = c.reshape(-1)
    if bool((flat < 0).any()) or bool((flat > 1).any()) or bool((c[:, 1] <= c[:, 0]).any()) or bool((flat.diff() < 0).any()):
        raise ParameterError(f"code: expected increasing, non-overlapping intervals in [0, 1], got {c.tolist()}")
    return c


def mirror_code(code) -> torch.Tensor:
    """The time-reversed code ``(1 - b_k, 1 - a_k)`` (in increasing order)."""
    c = check_code(code)
    return torch.flip(1 - c, dims=(0, 1))


def coded_windows(window: ExposureWindow, code) -> ExposureWindow:
    """The open sub-windows of coded exposures: batch ``[..., K]`` from ``window`` ``[...]``."""
    c = check_code(code, like=window.start)
    te = window.duration[..., None]
    return ExposureWindow(window.start[..., None] + c[:, 0] * te, (c[:, 1] - c[:, 0]) * te)


def render_coded(trajectory, psf, window: ExposureWindow, code, *, height: int, width: int,
                 settings: RenderSettings | None = None) -> torch.Tensor:
    """The image of a coded exposure: the sum over the code's sub-windows of
    :func:`~torchblur.render.blur.render_blur`.

    Args:
        trajectory, psf: as :func:`render_blur`, batch ``[...]``.
        window: the whole exposures ``[...]`` (s).
        code: ``[K, 2]`` open intervals as fractions of the exposure (:func:`check_code`).
        height, width, settings: as :func:`render_blur`.

    Returns:
        ``[..., H, W]``. Differentiable in every parameter.
    """
    sub = coded_windows(window, code)
    traj_b = trajectory
    shape = torch.broadcast_shapes(trajectory.shape, psf.shape, window.shape)
    sub = sub.expand(shape + sub.shape[-1:])
    if isinstance(trajectory, Sinusoid):
        traj_b = Sinusoid(trajectory.amplitude[..., None, :], trajectory.phase[..., None, :], trajectory.omega[..., None, :])
    else:
        raise InputTypeError(f"trajectory: expected a Sinusoid, got {type(trajectory).__name__}")
    check_type(psf, "psf", (GaussianPSF, KernelPSF), "a GaussianPSF or KernelPSF")
    return render_blur(traj_b, psf[..., None], sub, height=height, width=width, settings=settings).sum(-3)
