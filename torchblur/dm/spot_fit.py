"""The batched fitter of a DM sweep's spot problems, and the pattern responses ``Y``.

One problem is (pattern, frequency, spot): the spot's crop in that point's ``E*R`` frames, fitted
by :func:`~torchblur.fit.sinusoid.fit_sinusoid` with ``axes="xy"``. :func:`fit_spot_problems`
fits them in chunks of bounded memory (:func:`chunk_size`), each problem flagged in its
own ``status``; the PSF is each spot's own (:class:`GaussianPSF`, :class:`KernelPSF` or
:class:`PerSpotPSF`, a kernel fit's stds times its ``kernel_noise``). :func:`pattern_responses`
turns the fits into ``Y [P, 2M, F]`` and ``Y_cov [P, 2M, F, 2, 2]`` at ``exp(i w t)``. The
problems, the phase convention and the PSF per spot: docs/deformable_mirrors.md, "The spot
problems" and "Each spot's PSF".

Shapes: P patterns, F frequencies, M spots (slopes ``s = m`` for x, ``s = M + m`` for y),
``E*R`` exposures, ``h x w`` crop pixels.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_int, check_type
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.fit.status import NOT_FITTED
from torchblur.image.spots import crop_spots, crop_valid
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.window import ExposureWindow

__all__ = ["PerSpotPSF", "SpotFits", "crop_problems", "fit_spot_problems", "left_out", "pattern_responses", "chunk_size", "free_memory_bytes",
           "BYTES_PER_PIXEL"]

#: Peak bytes one problem's fit holds per exposure-pixel (``E*R*h*w``) in float64. Measured on
#: CPU as the rise of the peak RSS over one ``fit_sinusoid(axes="xy")`` of n moving-spot problems
#: (12x12 px crops, 4 exposures): 534, 218, 142 B at n = 256, 1024, 4096 (a fixed overhead plus
#: about 116 B per exposure-pixel from 1024 to 4096); taken as 256 (about twice the marginal
#: cost, so a chunk's fixed overhead fits too). float32 halves it.
BYTES_PER_PIXEL = 256
#: the share of the free memory one chunk may take
MEMORY_FRACTION = 0.25
#: the most bytes one chunk takes, on any machine: the chunks (and so the fits' round-off, which depends
#: on how the problems are grouped) do not follow the free memory wherever it holds 1 / MEMORY_FRACTION
#: times this (a re-fit of the HCIPy ladder run differed from its live run by 1.6e-7 when they did); the
#: shipped DM config's 5120 problems of a frequency stay one chunk
CHUNK_BYTES = 2 ** 31
#: names of the four parameters kept per problem, in ``SpotFits.covariance`` order
_KEPT = ("amplitude_x", "phase_x", "amplitude_y", "phase_y")


@dataclass(frozen=True)
class PerSpotPSF:
    """Each spot's PSF, chosen per spot: spot ``m`` is fitted with ``kernel`` where
    ``use_kernel[m]``, else with ``gaussian`` (crop coordinates, intensity per second).

    Attributes:
        gaussian: :class:`GaussianPSF` of batch ``[M]``.
        kernel: :class:`KernelPSF` of batch ``[M]`` (kernels ``[M, h, w]``, the spots' crops).
        use_kernel: ``[M]`` bool.
    """

    gaussian: GaussianPSF
    kernel: KernelPSF
    use_kernel: torch.Tensor

    def __post_init__(self):
        if not isinstance(self.gaussian, GaussianPSF) or not isinstance(self.kernel, KernelPSF):
            raise InputTypeError(f"PerSpotPSF: expected a GaussianPSF and a KernelPSF, got {type(self.gaussian).__name__} and "
                                 f"{type(self.kernel).__name__}")
        u = self.use_kernel
        if not isinstance(u, torch.Tensor) or u.dtype != torch.bool or u.dim() != 1:
            raise ShapeError(f"use_kernel: expected a bool tensor [M], got {getattr(u, 'dtype', type(u).__name__)} "
                             f"{tuple(getattr(u, 'shape', ()))}")
        if tuple(self.kernel.shape) != tuple(u.shape) or tuple(self.gaussian.shape) != tuple(u.shape):
            raise ShapeError(f"PerSpotPSF: expected gaussian [M], kernel [M, h, w] and use_kernel [M] with one M, got "
                             f"{list(self.gaussian.shape)}, {list(self.kernel.kernel.shape)}, {list(u.shape)}")

    def scaled(self, power) -> "PerSpotPSF":
        """The same PSFs at laser power ``power`` (a number: amplitudes and kernels times it)."""
        g = self.gaussian
        return PerSpotPSF(GaussianPSF(g.center, g.cov, g.amplitude * power), KernelPSF(self.kernel.kernel * power), self.use_kernel)


@dataclass(frozen=True)
class SpotFits:
    """The fits of every problem, batch ``[P, F, M]``.

    Attributes:
        amplitude: ``[P, F, M, 2]`` px (x, y); phase: ``[P, F, M, 2]`` rad.
        covariance: ``[P, F, M, 4, 4]`` over ``(amplitude_x, phase_x, amplitude_y, phase_y)``.
        status: ``[P, F, M]`` int (:data:`torchblur.fit.status.STATUS`; non-zero: NaN estimates).
        flags: ``[P, F, M]`` int bits (:data:`torchblur.fit.status.FLAGS`).
        reduced_chi2: ``[P, F, M]``.
        n_chunks: how many chunks the fit took.
    """

    amplitude: torch.Tensor
    phase: torch.Tensor
    covariance: torch.Tensor
    status: torch.Tensor
    flags: torch.Tensor
    reduced_chi2: torch.Tensor
    n_chunks: int


def crop_problems(frames: torch.Tensor, offset: torch.Tensor, size) -> tuple[torch.Tensor, torch.Tensor]:
    """Every spot's crop of whole sensor frames.

    Args:
        frames: ``[P, F, E*R, H, W]`` dark-subtracted sensor frames (electrons).
        offset: ``[M, 2]`` long crop corners (x0, y0) (:func:`~torchblur.image.spots.locate_spots`).
        size: ``(h, w)``.

    Returns:
        ``(crops [P, F, M, E*R, h, w], in_frame [M, h, w] bool)``: ``crops[p, f, m, e]`` = spot
        ``m``'s crop of exposure ``e`` of point ``(p, f)``, 0 beyond the frame; ``in_frame``
        marks the crop pixels inside the frame (pass it as the fit's mask).
    """
    if not isinstance(frames, torch.Tensor) or frames.dim() != 5:
        raise ShapeError(f"frames: expected a tensor [P, F, E*R, H, W], got {getattr(frames, 'shape', type(frames).__name__)}")
    crops = crop_spots(frames, offset, size)  # [P, F, E*R, M, h, w]
    return crops.permute(0, 1, 3, 2, 4, 5), crop_valid(tuple(frames.shape[-2:]), offset, size).to(frames.device)


def free_memory_bytes(device) -> int:
    """Free memory (bytes) on ``device``: CUDA ``torch.cuda.mem_get_info``; CPU psutil's
    ``available`` where psutil is installed, else ``os.sysconf`` available pages."""
    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        import psutil
    except ImportError:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    return int(psutil.virtual_memory().available)


def chunk_size(n_exposures: int, h: int, w: int, *, device="cpu", dtype=torch.float64, memory_fraction: float = MEMORY_FRACTION,
               free_bytes: int | None = None) -> int:
    """Problems per chunk: :data:`CHUNK_BYTES`, or ``memory_fraction`` of the free memory (``free_bytes``,
    default :func:`free_memory_bytes` of ``device``) where that is less, over the measured per-problem bytes
    ``BYTES_PER_PIXEL * n_exposures * h * w`` (scaled by the dtype's size against float64); at least 1."""
    per = BYTES_PER_PIXEL * n_exposures * h * w * torch.empty((), dtype=dtype).element_size() / 8
    free = free_memory_bytes(device) if free_bytes is None else int(free_bytes)
    return max(1, int(min(CHUNK_BYTES, memory_fraction * free) // per))


def _spot_psfs(psf, P, F, M, h, w, like):
    """``(GaussianPSF [n] or None, kernels [n, h, w] or None, use_kernel [n] bool)`` of every problem."""
    n = P * F * M
    gauss = kern = None
    use = torch.zeros(M, dtype=torch.bool, device=like["device"])
    if isinstance(psf, PerSpotPSF):
        gauss, kern, use = psf.gaussian, psf.kernel, psf.use_kernel.to(like["device"])
    elif isinstance(psf, KernelPSF):
        kern, use = psf, torch.ones(M, dtype=torch.bool, device=like["device"])
    elif isinstance(psf, GaussianPSF):
        gauss = psf
    else:
        raise InputTypeError(f"psf: expected a GaussianPSF, a KernelPSF or a PerSpotPSF of batch [M] (crop coordinates), got "
                             f"{type(psf).__name__}")
    if use.shape != (M,):
        raise ShapeError(f"psf: expected use_kernel [M={M}], got {tuple(use.shape)}")
    out = [None, None, use[None, None].expand(P, F, M).reshape(n)]
    if gauss is not None:
        out[0] = GaussianPSF(gauss.center.to(**like).expand(P, F, M, 2).reshape(n, 2), gauss.cov.to(**like).expand(P, F, M, 2, 2).reshape(n, 2, 2),
                             gauss.amplitude.to(**like).expand(P, F, M).reshape(n))
    if kern is not None:
        k = kern.kernel.to(**like)
        try:
            out[1] = k.expand(P, F, M, h, w).reshape(n, h, w)
        except RuntimeError as e:
            raise ShapeError(f"psf: expected kernels broadcastable to [P, F, M, h, w] = {[P, F, M, h, w]}, got {list(k.shape)}") from e
    return tuple(out)


def _problem_inputs(crops, psf, window, omega, noise_std, mask):
    """Broadcast and flatten: ``[n, E*R, h, w]`` data, the PSFs (:func:`_spot_psfs`), ``[n, E*R]`` window, ``[n]`` omega."""
    if not isinstance(crops, torch.Tensor) or crops.dim() != 6:
        raise ShapeError(f"crops: expected a tensor [P, F, M, E*R, h, w], got {getattr(crops, 'shape', type(crops).__name__)}")
    check_type(window, "window", ExposureWindow, "an ExposureWindow of batch [P, F, E*R]")
    P, F, M, ER, h, w = crops.shape
    like = dict(dtype=crops.dtype, device=crops.device)
    n = P * F * M
    psfs = _spot_psfs(psf, P, F, M, h, w, like)
    try:
        start = window.start.to(**like).expand(P, F, ER)[:, :, None].expand(P, F, M, ER).reshape(n, ER)
        dur = window.duration.to(**like).expand(P, F, ER)[:, :, None].expand(P, F, M, ER).reshape(n, ER)
    except RuntimeError as e:
        raise ShapeError(f"window: expected a batch broadcastable to [P, F, E*R] = {[P, F, ER]}, got {list(window.shape)}") from e
    om = torch.as_tensor(omega, **like)
    if om.shape != (F,):
        raise ShapeError(f"omega: expected [F={F}] rad/s, got shape {tuple(om.shape)}")
    om = om[None, :, None].expand(P, F, M).reshape(n)
    ns = None if noise_std is None else torch.as_tensor(noise_std, **like).expand(P, F, M, ER, h, w).reshape(n, ER, h, w)
    mk = None if mask is None else torch.as_tensor(mask, device=crops.device).expand(P, F, M, ER, h, w).reshape(n, ER, h, w)
    return crops.reshape(n, ER, h, w), psfs, (start, dur), om, ns, mk


def _kernel_noise(kernel_noise, P, F, M, like):
    """The std factor of every problem ``[n]`` (1 where None)."""
    if kernel_noise is None:
        return torch.ones(P * F * M, **like)
    k = torch.as_tensor(kernel_noise, **like)
    try:
        k = k.expand(P, F, M).reshape(-1)
    except RuntimeError as e:
        raise ShapeError(f"kernel_noise: expected a factor broadcastable to [P, F, M] = {[P, F, M]}, got {list(k.shape)}") from e
    if not bool(torch.isfinite(k).all()) or bool((k < 1).any()):
        raise ParameterError(f"kernel_noise: expected finite factors >= 1, got minimum {float(k.min()):g}")
    return k


def _empty(n, like):
    nan = torch.full((n,), float("nan"), **like)
    return dict(amplitude=nan[:, None].repeat(1, 2), phase=nan[:, None].repeat(1, 2), covariance=nan[:, None, None].repeat(1, 4, 4),
                status=torch.zeros(n, dtype=torch.long, device=like["device"]),
                flags=torch.zeros(n, dtype=torch.long, device=like["device"]), reduced_chi2=nan.clone())


def left_out(status, only, shape):
    """``status [n]`` (flat over ``shape`` ``(P, F, M)``) with the problems ``only`` leaves out set
    :data:`~torchblur.fit.status.NOT_FITTED` (``only``: bool broadcastable to ``shape``, None:
    none left out; a ShapeError naming ``only`` otherwise)."""
    if only is None:
        return status
    t = torch.as_tensor(only, device=status.device)
    if t.dtype != torch.bool:
        raise InputTypeError(f"only: expected a bool tensor broadcastable to {list(shape)}, got {t.dtype}")
    try:
        keep = t.expand(shape).reshape(-1)
    except RuntimeError as e:
        raise ShapeError(f"only: expected a bool tensor broadcastable to {list(shape)}, got {list(t.shape)}") from e
    return torch.where(keep, status, torch.full_like(status, NOT_FITTED))


def fit_spot_problems(crops, psf, window, omega, *, noise_std=None, mask=None, chunk: int | None = None, kernel_noise=None,
                      only=None, **fit_options) -> SpotFits:
    """Fit every (pattern, frequency, spot) problem, in chunks bounded in memory.

    Args:
        crops: ``[P, F, M, E*R, h, w]`` (:func:`crop_problems`), electrons; dtype and device
            of the fit.
        psf: each spot's PSF in crop coordinates, intensity in electrons per second (the laser
            power folded in): :class:`GaussianPSF` of batch ``[M]`` (or broadcastable to
            ``[P, F, M]``), :class:`KernelPSF` of kernels ``[M, h, w]`` (or broadcastable to
            ``[P, F, M, h, w]``; every spot its measured kernel), or :class:`PerSpotPSF` (spot
            ``m`` its kernel where ``use_kernel[m]``, else its Gaussian). The Gaussian and the
            kernel problems are fitted in separate chunks.
        window: :class:`ExposureWindow` broadcastable to ``[P, F, E*R]`` (s).
        omega: ``[F]`` rad/s.
        noise_std: pixel noise std broadcastable to the crops (e.g.
            :func:`~torchblur.render.camera.camera_noise_std` of the expected signal), or None
            (unweighted; the noise is estimated from the residuals).
        mask: bool broadcastable to the crops (False: excluded; e.g. ``in_frame``).
        chunk: problems per chunk; None: :func:`chunk_size` for the crops' device and dtype.
        kernel_noise: the kernel's own noise, a factor (>= 1) broadcastable to ``[P, F, M]`` by
            which the amplitude and phase stds of the problems fitted with a kernel grow
            (``covariance`` times its square): :meth:`~torchblur.identify.calibration.SpotKernels.kernel_noise_factor`
            of each point's exposures times its laser power; None: 1.
        only: bool broadcastable to ``[P, F, M]``: the problems to fit (None: every one); the
            others are :data:`~torchblur.fit.status.NOT_FITTED`, NaN.
        **fit_options: passed on to :func:`~torchblur.fit.sinusoid.fit_sinusoid` (``optimizer``,
            ``loss``, ``fit_background``, ``outliers``, ...).

    Returns:
        :class:`SpotFits` of batch ``[P, F, M]``; a problem whose fit failed has a non-zero
        ``status`` and NaN estimates, the others are as fitted alone (to round-off).
    """
    data, (gauss, kern, use_k), (start, dur), om, ns, mk = _problem_inputs(crops, psf, window, omega, noise_std, mask)
    P, F, M, ER, h, w = crops.shape
    like = dict(dtype=crops.dtype, device=crops.device)
    factor = _kernel_noise(kernel_noise, P, F, M, like)
    chunk = chunk_size(ER, h, w, device=crops.device, dtype=crops.dtype) if chunk is None else check_int(chunk, "chunk", low=1)
    if "axes" in fit_options:
        raise ParameterError("fit_options: axes is always 'xy' for DM spot problems")
    out = _empty(data.shape[0], like)
    out["status"] = left_out(out["status"], only, (P, F, M))
    fitted = out["status"] != NOT_FITTED
    n_chunks = 0
    for kind in ("gaussian", "kernel"):
        rows = torch.nonzero((use_k if kind == "kernel" else ~use_k) & fitted).reshape(-1)
        for i0 in range(0, rows.numel(), chunk):
            s = rows[i0:i0 + chunk]
            p = KernelPSF(kern[s]) if kind == "kernel" else GaussianPSF(gauss.center[s], gauss.cov[s], gauss.amplitude[s])
            fit = fit_sinusoid(data[s], p, ExposureWindow(start[s], dur[s]), om[s], axes="xy",
                               noise_std=None if ns is None else ns[s], mask=None if mk is None else mk[s], **fit_options)
            idx = [fit.param_names.index(k) for k in _KEPT]
            f2 = factor[s, None, None] ** 2 if kind == "kernel" else 1.0
            out["amplitude"][s], out["phase"][s] = fit.amplitude, fit.phase
            out["covariance"][s] = fit.covariance[:, idx][:, :, idx] * f2
            out["status"][s], out["flags"][s] = fit.status, fit.flags
            if fit.reduced_chi2 is not None:
                out["reduced_chi2"][s] = fit.reduced_chi2
            n_chunks += 1
    shaped = {k: v.reshape((P, F, M) + tuple(v.shape[1:])) for k, v in out.items()}
    return SpotFits(**shaped, n_chunks=n_chunks)


def pattern_responses(fits: SpotFits, amplitude, *, command_phase=0.0, phase_var=None):
    """The pattern responses from the fits (phase convention in the module docstring).

    Args:
        fits: :class:`SpotFits` ``[P, F, M]``.
        amplitude: command amplitude (input units) per point, broadcastable to ``[P, F]``.
        command_phase: rad, broadcastable to ``[P, F]``.
        phase_var: extra phase variance (rad^2) broadcastable to ``[P, F]`` (the trigger jitter
            and latency calibration, see :func:`~torchblur.identify.assemble.phase_std`), or None.

    Returns:
        ``(Y [P, 2M, F] complex128, Y_cov [P, 2M, F, 2, 2] float64)``, numpy arrays; NaN for a
        problem whose fit failed. ``Y[p, m]`` is spot ``m``'s x response, ``Y[p, M + m]`` its y.
        The covariance of each slope is from its axis' (amplitude, phase) block; the x-y
        correlation of one spot is dropped (the demultiplexing treats slopes as independent).
    """
    P, F, M = fits.status.shape
    A = np.broadcast_to(np.asarray(torch.as_tensor(amplitude, dtype=torch.float64).cpu()), (P, F))[:, :, None, None]
    c_ph = np.broadcast_to(np.asarray(torch.as_tensor(command_phase, dtype=torch.float64).cpu()), (P, F))[:, :, None, None]
    mag = fits.amplitude.detach().cpu().double().numpy()  # [P, F, M, 2]
    phi = fits.phase.detach().cpu().double().numpy() - c_ph
    C = fits.covariance.detach().cpu().double().numpy().reshape(P, F, M, 2, 2, 2, 2)  # (axis, [amp, phase]) x (axis, [amp, phase])
    C = np.stack([C[:, :, :, a, :, a, :] for a in range(2)], 3)  # [P, F, M, 2 axes, 2, 2]: the (amp, phase) block per axis
    if phase_var is not None:
        C = C.copy()
        C[..., 1, 1] += np.broadcast_to(np.asarray(phase_var, dtype=np.float64), (P, F))[:, :, None, None]
    Y = mag / A * np.exp(1j * phi)
    Jac = np.stack([np.stack([np.cos(phi), -mag * np.sin(phi)], -1), np.stack([np.sin(phi), mag * np.cos(phi)], -1)], -2) / A[..., None, None]
    Yc = Jac @ C @ np.swapaxes(Jac, -1, -2)  # [P, F, M, 2, 2, 2]
    bad = fits.status.cpu().numpy() != 0
    Y[bad], Yc[bad] = np.nan, np.nan
    Y = np.moveaxis(Y, 3, 2).reshape(P, F, 2 * M)  # [P, F, (axis, m)]
    Yc = np.moveaxis(Yc, 3, 2).reshape(P, F, 2 * M, 2, 2)
    return np.moveaxis(Y, 1, 2), np.moveaxis(Yc, 1, 2)
