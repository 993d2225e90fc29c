"""Lenslet-like spots that are not Gaussian: a grid of sinc^2 spots whose wings reach the
neighbouring subapertures (a crosstalk floor), blurred by a sine per spot, for the DM spot fitter
(issue 23). Used by tests/test_dm_kernel.py (small) and benchmarks/bench_dm_kernel.py (full).

A square lenslet's far field is ``sinc^2(x / a) sinc^2(y / a)`` (first zero ``a`` px from the
centre); between spots ``pitch`` px apart the wings leave about ``(a / (pi pitch / 2))^2`` of
the peak (1.4 % for ``a = 3``, ``pitch = 16``; HCIPy's lenslets measured 0.85 %, MEASURED.md).
Every spot is a full-frame :class:`~torchblur.render.psf.KernelPSF` (its wings cross the other
cells) rendered by torchblur's kernel renderer (a Fourier shift, exact for a band-limited image);
a frame is the sum of the spots, each moving on its own sine per axis, so the wings that cross a
cell move with their own spot, not with the cell's. Noise: shot plus read noise, Gaussian.

Shapes: M spots (``n_side^2``), F points (one frequency and one motion size each), E exposures.
"""
from __future__ import annotations

import math

import torch

from torchblur.design.windows import dual_exposure_windows
from torchblur.render.blur import render_blur
from torchblur.render.camera import camera_noise_std
from torchblur.render.psf import KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

F64 = torch.float64


def sinc2_image(center, height: int, width: int, zero_px: float) -> torch.Tensor:
    """``[M, H, W]`` unit-peak sinc^2 spots at ``center [M, 2]`` (x, y px), first zero ``zero_px``."""
    y = torch.arange(height, dtype=F64)[None, :, None]
    x = torch.arange(width, dtype=F64)[None, None, :]
    return torch.sinc((x - center[:, 0, None, None]) / zero_px) ** 2 * torch.sinc((y - center[:, 1, None, None]) / zero_px) ** 2


def sinc2_case(motion_px, *, n_side: int = 3, n_rows: int | None = None, pitch: int = 16, zero_px: float = 3.0, peak_e: float = 2000.0, read_e: float = 3.0,
               n_still: int = 256, freq_hz=None, fractions=(0.3, 0.8), seed: int = 0) -> dict:
    """Frames of a grid of sinc^2 spots (``n_side`` across, ``n_rows`` down, default square) at F points, point ``f`` moving every spot ``motion_px[f]``
    px (amplitude per axis, random phases), and still frames.

    Returns a dict: ``crops [1, F, M, E, pitch, pitch]`` (e-, noisy), ``noise [1, F, M, E, h, w]``
    (the true per-pixel std), ``offset [M, 2]`` long crop corners, ``window`` (ExposureWindow
    ``[1, F, E]``), ``omega [F]``, ``amplitude [F, M, 2]`` and ``phase [F, M, 2]`` (the truth, px
    and rad), ``still [n_still, H, W]`` (e-, noisy) and its exposure ``still_s``, ``kernel_true``
    ``[M, h, w]`` (e-/s, the spot alone in its crop) and ``center [M, 2]`` (crop coordinates).
    """
    g = torch.Generator().manual_seed(seed)
    motion = torch.as_tensor(motion_px, dtype=F64).reshape(-1)
    rows = n_side if n_rows is None else n_rows
    F, M, H, Wd = motion.numel(), n_side * rows, rows * pitch, n_side * pitch
    freq = torch.as_tensor(freq_hz if freq_hz is not None else torch.linspace(60.0, 600.0, F), dtype=F64).reshape(F)
    omega = 2 * math.pi * freq
    win = dual_exposure_windows(omega, fractions=fractions)  # [F, E]
    corner = torch.stack(torch.meshgrid(torch.arange(n_side), torch.arange(rows), indexing="xy"), -1).reshape(M, 2) * pitch
    centre = corner.to(F64) + (pitch - 1) / 2 + torch.rand(M, 2, generator=g, dtype=F64) - 0.5
    rate = peak_e / win.duration.max()  # e-/s at the peak: a still spot over the longest exposure peaks at peak_e
    spots = sinc2_image(centre, H, Wd, zero_px) * rate  # [M, H, W] e-/s
    amp = motion[:, None, None].expand(F, M, 2).clone()
    ph = (torch.rand(F, M, 2, generator=g, dtype=F64) - 0.5) * 2 * math.pi
    traj = Sinusoid(amp[:, :, None], ph[:, :, None], omega[:, None, None, None].expand(F, M, 1, 2))  # [F, M, E]
    w_b = ExposureWindow(win.start[:, None], win.duration[:, None])
    clean = render_blur(traj, KernelPSF(spots[:, None]), w_b, height=H, width=Wd).sum(1)  # [F, E, H, W]
    noise = camera_noise_std(clean, read_e)
    frames = clean + noise * torch.randn(clean.shape, generator=g, dtype=F64)
    still_s = float(win.duration.max())
    still_clean = spots.sum(0) * still_s
    still = still_clean + camera_noise_std(still_clean, read_e) * torch.randn((n_still, H, Wd), generator=g, dtype=F64)
    idx_y = corner[:, 1, None] + torch.arange(pitch)  # [M, h]
    idx_x = corner[:, 0, None] + torch.arange(pitch)

    def crop(img):  # [..., H, W] -> [..., M, h, w]
        return img[..., idx_y[:, :, None], idx_x[:, None, :]]

    return dict(crops=crop(frames).transpose(1, 2)[None],
                noise=crop(noise).transpose(1, 2)[None], offset=corner.long(), window=ExposureWindow(win.start[None], win.duration[None]),
                omega=omega, amplitude=amp, phase=ph, still=still, still_s=still_s, still_crops=crop(still),
                kernel_true=crop(spots)[torch.arange(M), torch.arange(M)], center=centre - corner.to(F64))
