"""The photon transfer curve (EMVA 1288): a camera's conversion gain, read noise, dark level and
linear range from its own frames.

A pixel's temporal variance grows linearly with its mean signal: in ADU, with ``K = 1 / gain``
(ADU per electron), ``var(y) = var_dark + K (mean(y) - mean_dark)`` (shot noise: a Poisson count's
variance is its mean, ``mu_e``, so ``K^2 mu_e = K mu_y``), where ``var_dark = (read_noise_e K)^2 +
1/12`` (read noise and the ADC's rounding). Frames of one illumination, several of them (a pair
per step at least), give each pixel's mean and temporal variance; the slope of variance against
mean is ``K``. The illumination may be a flat field or a still spot (its pixels span the range
from dark to its peak) and may step through a ladder of exposures or powers; fixed-pattern noise
does not enter (the variance is over frames, per pixel). Near saturation the variance collapses:
the linear range ends where the binned points leave the line.

Glossary: ``N`` frames of one step, ``D`` dark frames, ``H, W`` pixels; means and variances in ADU
and ADU^2; gain in electrons per ADU.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_image, check_finite, check_type

__all__ = ["PhotonTransfer", "photon_transfer", "photon_transfer_figure"]

_Z_LINEAR = 4.0  # a bin whose variance is more than this many stds off the line ends the linear range
_MIN_POINTS = 3  # bins with signal needed for a slope
_X_MIN_SIGMA = 20.0  # pixel points whose mean signal is below this many dark stds of a mean are left out


@dataclass(frozen=True)
class PhotonTransfer:
    """What a photon transfer curve measured (every std a 1-sigma).

    Attributes:
        gain_e_per_adu, gain_std: conversion gain (e-/ADU) and its std.
        read_noise_e, read_noise_std_e: the sensor's read noise (e-, the ADC's rounding removed
            where the frames are whole numbers) and its std.
        dark_level_adu, dark_level_std_adu: the mean dark level over the pixels (ADU) and its std.
        linear_max_adu: the largest mean signal above the dark level (ADU) on the line (the
            linear range is 0 .. this); ``saturation_adu``: the level given for clipped pixels (inf: none).
        mean_adu, var_adu2, var_std_adu2: the binned points ``[B]``: mean signal above the dark
            level, temporal variance (dark variance included) and its std; ``linear`` bool ``[B]``:
            the bins on the line (the fit's).
        dark_var_adu2: the dark frames' temporal variance (ADU^2, rounding included); ``quantization_adu2``: 1/12 or 0.
        reduced_chi2: of the linear fit over the bins on the line (about 1 when the line explains them;
            the gain's std is inflated by its square root when above 1).
        n_steps, n_pixels: the illumination steps and pixel points used.
    """

    gain_e_per_adu: float
    gain_std: float
    read_noise_e: float
    read_noise_std_e: float
    dark_level_adu: float
    dark_level_std_adu: float
    linear_max_adu: float
    saturation_adu: float
    mean_adu: np.ndarray
    var_adu2: np.ndarray
    var_std_adu2: np.ndarray
    linear: np.ndarray
    dark_var_adu2: float
    quantization_adu2: float
    reduced_chi2: float
    n_steps: int
    n_pixels: int

    @property
    def relative_gain_std(self) -> float:
        """``gain_std / gain_e_per_adu``."""
        return self.gain_std / self.gain_e_per_adu

    def gain_z(self, gain: float) -> float:
        """How many stds a gain (e-/ADU, e.g. the configured one) lies from the measured one."""
        return (float(gain) - self.gain_e_per_adu) / self.gain_std if self.gain_std > 0 else math.inf

    def describe(self) -> str:
        """One line for the log."""
        return (f"gain {self.gain_e_per_adu:.4g} +- {self.gain_std:.2g} e-/ADU, read noise {self.read_noise_e:.3g} +- "
                f"{self.read_noise_std_e:.2g} e-, dark level {self.dark_level_adu:.2f} +- {self.dark_level_std_adu:.2g} ADU, linear "
                f"to {self.linear_max_adu:.4g} ADU above dark ({int(self.linear.sum())} of {self.linear.size} bins, reduced chi2 "
                f"{self.reduced_chi2:.3g}; {self.n_steps} step(s), {self.n_pixels} pixel points)")


def _as_steps(steps) -> list[torch.Tensor]:
    if isinstance(steps, torch.Tensor) or isinstance(steps, np.ndarray):
        t = torch.as_tensor(steps)
        steps = list(t) if t.dim() == 4 else [t]
    if not isinstance(steps, (list, tuple)) or not steps:
        raise InputTypeError(f"steps: expected frames [N, H, W], [L, N, H, W] or a list of [N, H, W], got {type(steps).__name__}")
    out = []
    for i, s in enumerate(steps):
        s = check_finite(as_image(s, f"steps[{i}]", min_dim=3, desc="[N, H, W]"), f"steps[{i}]").detach().to(torch.float64)
        if s.dim() != 3 or s.shape[0] < 2:
            raise ShapeError(f"steps[{i}]: expected [N, H, W] with N >= 2 frames of one illumination, got shape {tuple(s.shape)}")
        out.append(s)
    return out


def _pixel_points(steps, dark_mean, usable, saturation_adu, var_d, K):
    """Per pixel and step: (mean above dark [P], unbiased temporal variance [P], frames - 1 [P]) of the
    pixels whose mean lies 6 expected stds (``var_d + K mean``) below ``saturation_adu``: a cut on the
    mean alone (a cut on clipped frames would keep the pixels that happened to vary less: a bias)."""
    m, v, dof = [], [], []
    for s in steps:
        mean = s.mean(0)
        keep = usable & (mean + 6 * torch.sqrt(var_d + K * (mean - dark_mean).clamp_min(0)) < saturation_adu - 0.5)
        m.append((mean - dark_mean)[keep])
        v.append(s.var(0, unbiased=True)[keep])
        dof.append(torch.full((int(keep.sum()),), float(s.shape[0] - 1), dtype=torch.float64))
    return torch.cat(m).numpy(), torch.cat(v).numpy(), torch.cat(dof).numpy()


def _bins(m, v, dof, n_bins):
    """Points (all with a mean > 0) binned by mean (geometric edges): per bin mean, variance, std of that variance."""
    top = float(m.max())
    edges = np.geomspace(float(m.min()) * (1 - 1e-9), max(top, float(m.min()) * 2) * (1 + 1e-9), n_bins + 1)
    idx = np.digitize(m, edges) - 1
    mb, vb, sb, members = [], [], [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() < 2:
            continue
        w = dof[sel]
        vm = float((v[sel] * w).sum() / w.sum())
        mb.append(float((m[sel] * w).sum() / w.sum()))
        vb.append(vm)
        sb.append(vm * math.sqrt(2.0 / float(w.sum())))  # a Gaussian's sample variance: var(s^2) = 2 sigma^4 / (n - 1)
        members.append(sel)
    return np.array(mb), np.array(vb), np.array(sb), members


def _dark_stats(dark, usable):
    """Per-pixel dark mean ``[H, W]``; the temporal variance over the usable pixels and its std (ADU^2);
    the mean dark level and its std (ADU)."""
    D, P = dark.shape[0], int(usable.sum())
    dark_mean = dark.mean(0)
    var_d = float(dark.var(0, unbiased=True)[usable].mean())
    var_d_std = math.sqrt(2.0 / ((D - 1) * P)) * var_d  # over P pixels, each a sample variance of D frames
    level = float(dark_mean[usable].mean())
    level_std = math.sqrt(var_d / (D * P) + float(dark_mean[usable].var()) / P)
    return dark_mean, var_d, var_d_std, level, level_std


def _slope(m, y, dof, var_model):
    """Weighted least squares of ``y = K m`` (through the origin), weights ``dof / (2 var_model^2)``: K, its std, chi2."""
    w = dof / (2.0 * var_model ** 2)
    sxx = float((w * m * m).sum())
    K = float((w * m * y).sum()) / sxx
    chi2 = float((w * (y - K * m) ** 2).sum())
    return K, 1.0 / math.sqrt(sxx), chi2, float((w * m).sum()) / sxx


def photon_transfer(steps, dark, *, saturation_adu: float | None = None, hot_pixels=None, n_bins: int = 40) -> PhotonTransfer:
    """The photon transfer curve of a camera from its frames.

    Args:
        steps: frames in ADU of each illumination step: ``[N, H, W]`` (one step: a still spot or a
            flat field), ``[L, N, H, W]`` or a list of ``[N_l, H, W]`` (a ladder of exposures or
            powers), N >= 2 each (a pair at least; more frames, more precision).
        dark: dark frames ``[D, H, W]`` in ADU, D >= 2, same exposure conditions.
        saturation_adu: the level at which a pixel clips (ADU; None: no clipping); a pixel at or
            above it less half an ADU in any frame of a step is left out of that step.
        hot_pixels: bool ``[H, W]`` pixels to leave out (None: none).
        n_bins: geometric bins of mean signal for the linear-range test and the figure.

    Returns:
        :class:`PhotonTransfer`.

    Raises:
        ShapeError, InputTypeError: frames of the wrong shape or type (named).
        ParameterError: fewer than 3 bins with signal (no slope to measure), or a slope that is
            not positive (the frames do not vary with the signal: not raw frames?).
    """
    steps = _as_steps(steps)
    dark = check_finite(as_image(dark, "dark", min_dim=3, desc="[D, H, W]"), "dark").detach().to(torch.float64)
    if dark.dim() != 3 or dark.shape[0] < 2 or dark.shape[-2:] != steps[0].shape[-2:]:
        raise ShapeError(f"dark: expected [D, H, W] with D >= 2 and the steps' H, W {tuple(steps[0].shape[-2:])}, got {tuple(dark.shape)}")
    for i, s in enumerate(steps):
        if s.shape[-2:] != dark.shape[-2:]:
            raise ShapeError(f"steps[{i}]: frames of {tuple(s.shape[-2:])} px, the dark frames' are {tuple(dark.shape[-2:])}")
    usable = torch.ones(dark.shape[-2:], dtype=torch.bool) if hot_pixels is None else ~torch.as_tensor(hot_pixels, dtype=torch.bool)
    sat = math.inf if saturation_adu is None else float(saturation_adu)
    whole = bool(all(torch.equal(s, s.round()) for s in steps)) and bool(torch.equal(dark, dark.round()))
    q = 1.0 / 12.0 if whole else 0.0

    dark_mean, var_d, var_d_std, level, level_std = _dark_stats(dark, usable)

    # a first pass with a generous bound on K (1 ADU per e-: gain 1) finds K; the second cuts at 6 of its stds from saturation
    K_cut = 1.0
    for _ in range(2):
        m, v, dof = _pixel_points(steps, dark_mean, usable, sat, var_d, K_cut)
        if m.size == 0:
            break
        sel = m > 1.0
        K_cut = max(float(((v[sel] - var_d) * m[sel]).sum() / max((m[sel] ** 2).sum(), 1e-300)), 1e-6) * 1.2 if sel.any() else K_cut
    # Only pixels whose mean lies far above its own noise: the slope through the origin against a noisy mean is
    # diluted by the many dark pixels (errors in the variable: a few % low on a still spot's frames).
    far = m > _X_MIN_SIGMA * np.sqrt(var_d / (dof + 1))
    m, v, dof = m[far], v[far], dof[far]
    mb, vb, sb, members = _bins(m, v, dof, n_bins) if m.size else (np.zeros(0),) * 3 + ([],)
    signal = mb > 0
    if int(signal.sum()) < _MIN_POINTS:
        raise ParameterError(f"steps: {int(signal.sum())} bin(s) of mean signal well above the noise; a photon transfer "
                             f"curve needs at least {_MIN_POINTS} (brighter, or more steps of the ladder)")
    linear = signal.copy()
    for _ in range(len(mb)):  # drop the top bins while the last one is off the line (the variance collapses near saturation)
        sel = np.any([members[b] for b in np.nonzero(linear)[0]], axis=0)
        K0 = float(np.polyfit(mb[linear], vb[linear] - var_d, 1)[0]) if linear.sum() >= 2 else 1.0
        K, K_std, chi2, dK_dvd = _slope(m[sel], v[sel] - var_d, dof[sel], np.maximum(var_d + max(K0, 1e-12) * m[sel], 1e-12))
        z = (vb - var_d - K * mb) / np.sqrt(sb ** 2 + var_d_std ** 2)
        top = np.nonzero(linear)[0][-1]
        if abs(z[top]) <= _Z_LINEAR or linear.sum() <= _MIN_POINTS:
            break
        linear[top] = False
    if not K > 0:
        raise ParameterError(f"steps: the temporal variance does not grow with the signal (slope {K:.3g} ADU per ADU); are these "
                             f"raw frames of one illumination per step?")
    dof_fit = max(int(sel.sum()) - 1, 1)
    red = chi2 / dof_fit
    K_std = math.hypot(K_std * math.sqrt(max(red, 1.0)), dK_dvd * var_d_std)
    gain, gain_std = 1.0 / K, K_std / K ** 2
    read_adu2 = max(var_d - q, 0.0)
    read_e = gain * math.sqrt(read_adu2)
    read_std = read_e * math.hypot(gain_std / gain, var_d_std / (2 * read_adu2) if read_adu2 > 0 else math.inf)
    return PhotonTransfer(gain_e_per_adu=gain, gain_std=gain_std, read_noise_e=read_e, read_noise_std_e=read_std, dark_level_adu=level,
                          dark_level_std_adu=level_std, linear_max_adu=float(mb[linear].max()), saturation_adu=sat, mean_adu=mb,
                          var_adu2=vb, var_std_adu2=sb, linear=linear, dark_var_adu2=var_d, quantization_adu2=q, reduced_chi2=red,
                          n_steps=len(steps), n_pixels=int(m.size))


def photon_transfer_figure(ptc: PhotonTransfer, *, configured_gain: float | None = None):
    """The curve as a matplotlib ``Figure`` (not shown, no backend chosen): binned temporal
    variance against mean signal (ADU, log-log) with 1-sigma bars, the bins off the line marked,
    the fitted line ``var_dark + mean / gain``, and the configured gain's line where given."""
    from matplotlib.figure import Figure

    check_type(ptc, "ptc", PhotonTransfer, "a PhotonTransfer")
    fig = Figure(figsize=(6.0, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    on, off = ptc.linear, ~ptc.linear
    ax.errorbar(ptc.mean_adu[on], ptc.var_adu2[on], yerr=ptc.var_std_adu2[on], fmt="o", ms=3, label="on the line")
    if off.any():
        ax.errorbar(ptc.mean_adu[off], ptc.var_adu2[off], yerr=ptc.var_std_adu2[off], fmt="x", ms=4, color="0.5", label="off the line")
    x = np.geomspace(max(float(ptc.mean_adu.min()), 0.1), float(ptc.mean_adu.max()), 200)
    ax.plot(x, ptc.dark_var_adu2 + x / ptc.gain_e_per_adu, "-",
            label=f"fit: gain {ptc.gain_e_per_adu:.4g} +- {ptc.gain_std:.2g} e-/ADU, read noise {ptc.read_noise_e:.3g} e-")
    if configured_gain is not None:
        ax.plot(x, ptc.dark_var_adu2 + x / float(configured_gain), "--", label=f"configured gain {float(configured_gain):.4g} e-/ADU")
    ax.axvline(ptc.linear_max_adu, color="0.7", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("mean signal above dark (ADU)")
    ax.set_ylabel("temporal variance (ADU$^2$)")
    ax.set_title("photon transfer curve")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
