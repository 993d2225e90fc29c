"""Cost landscapes: the image loss over a grid of sinusoid amplitudes and phases.

The data behind the paper's Fig. 2 (cost vs phase, one exposure), Fig. 5 (several norms),
Fig. 6 (the 2-D landscape and its local minima) and Fig. 7 (two exposures, the alias gone):
for each grid point ``(M_a, phi_p)`` the motion ``M_a sin(omega t + phi_p)`` along one axis is
rendered for every exposure window and compared with the images. Grid points are rendered in
batches of ``chunk`` (memory ``chunk * E * H * W`` values).
"""
from __future__ import annotations

import torch

from torchblur.errors import InputTypeError, ShapeError, as_tensor, check_choice, check_finite, check_positive, check_type
from torchblur.losses import LOSSES, image_loss
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.blur import RenderSettings, render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

__all__ = ["cost_landscape"]


def cost_landscape(images, psf, window: ExposureWindow, omega, amplitude, phase, *, axis: str = "x", losses=("l2",),
                   weight=None, settings: RenderSettings | None = None, chunk: int = 256) -> dict[str, torch.Tensor]:
    """Loss between ``images`` and the rendered motion at every ``(amplitude, phase)`` pair.

    Args:
        images: ``[E, H, W]``: E exposures of one motion (dark level subtracted).
        psf: ``GaussianPSF`` or ``KernelPSF`` with an empty batch shape (shared by the exposures).
        window: ``[E]`` exposure windows (s).
        omega: rad/s, a number or a 0-d tensor.
        amplitude: ``[A]`` amplitudes (px); phase: ``[P]`` phases (rad).
        axis: ``"x"`` or ``"y"``: the direction of the motion.
        losses: names from :data:`torchblur.losses.LOSSES` (``"l2"``, ``"l1"``, ``"linf"``,
            ``"poisson"``).
        weight: optional per-pixel weights ``[E, H, W]`` (``1 / sigma^2``; 0 masks a pixel).
        settings: renderer settings (default: the renderer's).
        chunk: grid points rendered per call.

    Returns:
        ``{loss: cost [A, P, E]}``, the loss of each exposure on its own; sum over the last
        dimension for the joint (maximum-likelihood, for ``l2`` with equal noise) cost.

    Example:
        >>> import math, torch, torchblur as tb
        >>> psf = tb.GaussianPSF.isotropic(torch.tensor([15.5, 11.5]), torch.tensor(2.0))
        >>> win = tb.ExposureWindow(torch.tensor([0.0, 0.0]), torch.tensor([3e-3, 8e-3]))
        >>> om = 2 * math.pi * 100.0
        >>> truth = tb.Sinusoid(torch.tensor([[5.0, 0.0]]), torch.tensor([[0.3, 0.3]]), torch.tensor([om]))
        >>> img = tb.render_blur(truth, psf, win, height=24, width=32)
        >>> land = cost_landscape(img, psf, win, om, torch.tensor([4.0, 5.0, 6.0]), torch.linspace(-3, 3, 7))
        >>> land["l2"].shape
        torch.Size([3, 7, 2])
    """
    om, amp, ph, losses, w = _checked(images, psf, window, omega, amplitude, phase, axis, losses, weight, chunk)
    E, H, W = images.shape
    A_, P_ = torch.meshgrid(amp, ph, indexing="ij")
    out = _grid_costs(images, psf, window, om, A_.reshape(-1), P_.reshape(-1), axis=axis, losses=losses, weight=w,
                      settings=settings, chunk=chunk)
    return {nm: v.reshape(amp.numel(), ph.numel(), E) for nm, v in out.items()}


def _checked(images, psf, window, omega, amplitude, phase, axis, losses, weight, chunk):
    """:func:`cost_landscape`'s inputs checked: ``(omega 0-d, amplitude [A], phase [P], the loss
    names, weight [E, H * W] or None)``; errors name the argument."""
    check_type(images, "images", torch.Tensor, "a torch.Tensor [E, H, W]")
    if images.dim() != 3:
        raise ShapeError(f"images: expected [E, H, W], got shape {tuple(images.shape)}")
    if not images.dtype.is_floating_point:
        raise InputTypeError(f"images: expected a floating tensor, got {images.dtype}")
    images = check_finite(images, "images")
    E, H, W = images.shape
    check_type(psf, "psf", (GaussianPSF, KernelPSF), "a GaussianPSF or KernelPSF")
    if psf.shape != ():
        raise ShapeError(f"psf: expected one PSF (batch shape []), got batch shape {tuple(psf.shape)}")
    check_type(window, "window", ExposureWindow, "an ExposureWindow [E]")
    if tuple(window.shape) != (E,):
        raise ShapeError(f"window: expected shape [E] = [{E}] (one window per exposure), got {tuple(window.shape)}")
    om = check_positive(as_tensor(omega, "omega", like=images), "omega")
    if om.dim() != 0:
        raise ShapeError(f"omega: expected a number, got shape {tuple(om.shape)}")
    amp = check_finite(as_tensor(amplitude, "amplitude", like=images), "amplitude")
    ph = check_finite(as_tensor(phase, "phase", like=images), "phase")
    for name, v in (("amplitude", amp), ("phase", ph)):
        if v.dim() != 1 or v.numel() == 0:
            raise ShapeError(f"{name}: expected a non-empty 1-D grid, got shape {tuple(v.shape)}")
    check_choice(axis, "axis", ("x", "y"))
    if isinstance(losses, str):
        losses = (losses,)
    for nm in losses:
        check_choice(nm, "losses", LOSSES)
    if weight is not None:
        w = as_tensor(weight, "weight", like=images)
        if tuple(w.shape) != (E, H, W):
            raise ShapeError(f"weight: expected shape [E, H, W] = {(E, H, W)}, got {tuple(w.shape)}")
        w = w.reshape(E, H * W)
    else:
        w = None
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise InputTypeError(f"chunk: expected an integer >= 1, got {chunk!r}")

    return om, amp, ph, losses, w


def _grid_costs(images, psf, window, om, fa, fp, *, axis, losses, weight, settings, chunk) -> dict:
    """``{loss: cost [G, E]}`` at the grid points ``(fa [G], fp [G])`` (amplitude px, phase rad),
    rendered ``chunk`` points per call."""
    E, H, W = images.shape
    dtype, device = images.dtype, images.device
    data = images.reshape(E, H * W)
    out = {nm: torch.empty(fa.numel(), E, dtype=dtype, device=device) for nm in losses}
    k = 0 if axis == "x" else 1
    for s in range(0, fa.numel(), chunk):
        a = fa[s:s + chunk, None]
        amp_xy = torch.zeros(a.shape[0], 1, 2, dtype=dtype, device=device)
        amp_xy[..., k] = a
        ph_xy = fp[s:s + chunk, None, None].expand(-1, 1, 2)
        with torch.no_grad():
            model = render_blur(Sinusoid(amp_xy, ph_xy, om), psf, window, height=H, width=W, settings=settings)  # [B, E, H, W]
        model = model.reshape(-1, E, H * W)
        for nm in losses:
            out[nm][s:s + chunk] = image_loss(model, data, loss=nm, weight=weight)
    return out
