"""Frame-by-frame tracking of a sinusoid below the camera's Nyquist rate, and the
camera-to-actuator axes calibration.

Tracking: short exposures triggered at phases spread over the period; the centroid of
each frame is the mean spot position over its window, ``mu1 = M alpha sin(psi)`` with
``alpha = 2 sin(p/2)/p`` and ``psi`` the phase at the window centre (PHYSICS.md,
"Moments"), so ``centroid - rest = a alpha sin(c) + b alpha cos(c)`` is linear in
``(a, b) = (M cos phi, M sin phi)``: an exact linear least-squares problem, no blur model
needed. It agrees with the blur fit where both apply and cross-checks it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchblur.errors import ParameterError, ShapeError, check_real_scalar
from torchblur.image.dark import subtract_dark
from torchblur.image.moments import image_moments

__all__ = ["TrackingResult", "track_sine", "sine_from_centroids", "AxisCalibration", "calibrate_axes"]


@dataclass(frozen=True)
class TrackingResult:
    """``amplitude`` (px), ``phase`` (rad), their stds and correlation, ``residual_rms`` (px)
    of the linear fit, ``n_frames``; per axis when fitted on both (arrays of shape [2])."""

    amplitude: np.ndarray
    phase: np.ndarray
    amplitude_std: np.ndarray
    phase_std: np.ndarray
    correlation: np.ndarray
    residual_rms: np.ndarray
    n_frames: int


def sine_from_centroids(offset_px, omega: float, start_s, duration_s) -> TrackingResult:
    """Fit ``M sin(omega t + phi)`` to window-averaged positions.

    Args:
        offset_px: centroid minus rest position (px), ``[K]`` or ``[K, 2]`` (x, y).
        omega: rad/s.
        start_s, duration_s: each frame's window (s), ``[K]`` (start from the command's zero
            crossing).

    Returns:
        :class:`TrackingResult` (uncertainty from the residual scatter).
    """
    y = np.asarray(offset_px, dtype=float)
    if y.ndim not in (1, 2):
        raise ShapeError(f"offset_px: expected shape [K] or [K, 2], got {y.shape}")
    one_axis = y.ndim == 1
    y = y[:, None] if one_axis else y
    t0 = np.asarray(start_s, dtype=float)
    te = np.asarray(duration_s, dtype=float)
    K = y.shape[0]
    if y.ndim != 2 or K < 3 or y.shape[1] not in (1, 2):
        raise ShapeError(f"offset_px: expected shape [K] or [K, 2] with K >= 3 frames, got {np.shape(offset_px)}")
    for name, v in (("start_s", t0), ("duration_s", te)):
        if v.shape != (K,):
            raise ShapeError(f"{name}: expected shape [K] = ({K},) like offset_px, got {v.shape}")
    for name, v in (("offset_px", y), ("start_s", t0), ("duration_s", te)):
        if not np.all(np.isfinite(v)):
            raise ParameterError(f"{name}: expected finite values, got {int(np.sum(~np.isfinite(v)))} NaN/Inf entries")
    omega = check_real_scalar(float(omega) if isinstance(omega, np.floating) else omega, "omega", positive=True)
    p = omega * te
    alpha = np.where(np.abs(p) > 1e-12, 2 * np.sin(p / 2) / np.where(p == 0, 1, p), 1.0)
    c = omega * (t0 + te / 2)
    X = np.stack([alpha * np.sin(c), alpha * np.cos(c)], 1)  # [K, 2]
    if np.linalg.matrix_rank(X) < 2:
        raise ParameterError("start_s: the window phases do not span the period (spread the triggers)")
    out = {k: [] for k in ("M", "phi", "sM", "sphi", "rho", "rms")}
    XtX_inv = np.linalg.inv(X.T @ X)
    for ax in range(y.shape[1]):
        coef, *_ = np.linalg.lstsq(X, y[:, ax], rcond=None)
        a, b = coef
        r = y[:, ax] - X @ coef
        s2 = float(r @ r) / max(1, K - 2)
        cov_ab = s2 * XtX_inv
        M = math.hypot(a, b)
        phi = math.atan2(b, a)
        Jm = np.array([[a / M, b / M], [-b / M**2, a / M**2]]) if M > 0 else np.zeros((2, 2))
        cov = Jm @ cov_ab @ Jm.T
        sM, sp = math.sqrt(max(cov[0, 0], 0)), math.sqrt(max(cov[1, 1], 0))
        out["M"].append(M)
        out["phi"].append(phi)
        out["sM"].append(sM)
        out["sphi"].append(sp)
        out["rho"].append(cov[0, 1] / (sM * sp) if sM > 0 and sp > 0 else 0.0)
        out["rms"].append(math.sqrt(s2))
    sq = (lambda v: np.asarray(v[0])) if one_axis else np.asarray
    return TrackingResult(sq(out["M"]), sq(out["phi"]), sq(out["sM"]), sq(out["sphi"]), sq(out["rho"]), sq(out["rms"]), K)


def track_sine(rig, *, freq_hz: float, amplitude: float, rest_px, dark, gain: float = 1.0, exposure_fraction: float = 0.05,
               n_frames: int = 16, noise_e: float | None = None, settle_s=None, power: float = 1.0, latency_s: float = 0.0,
               trigger_delay_s: float = 0.0, axes: str = "x") -> TrackingResult:
    """Track the spot frame by frame with short exposures (``exposure_fraction`` of the
    period) triggered at ``n_frames`` phases spread evenly over the period.

    Args:
        rig: a :class:`torchblur.rig.base.Rig`.
        rest_px: the spot's rest position (x, y) px (the PSF centre).
        dark: a :class:`torchblur.image.dark.DarkFrame`.
        gain: electrons per ADU; noise_e: threshold scale for the centroids (default: 5 e-).
        latency_s, trigger_delay_s: the calibrated trigger-to-exposure delays (s).
        axes: ``"x"``, ``"y"`` or ``"xy"``.

    Returns:
        :class:`TrackingResult` of the spot's motion in px (divide by ``amplitude`` for |H|).
    """
    period = 1.0 / freq_hz
    te = exposure_fraction * period
    offsets = [(k / n_frames * period) % period for k in range(n_frames)]
    cap = rig.sine(freq_hz=float(freq_hz), amplitude=float(amplitude), exposures_s=[te] * n_frames, trigger_offset_s=offsets,
                   n_repeats=1, settle_s=settle_s, power=power)
    frames = subtract_dark(cap.frames.to(torch.float64), dark)[:, 0] * gain  # [K, H, W]
    thr = 3 * (noise_e if noise_e is not None else 5.0)
    _, cen, _ = image_moments(frames, threshold=thr)
    rest = torch.as_tensor(rest_px, dtype=torch.float64)
    offs = (cen - rest).numpy()
    starts = np.asarray(offsets) + trigger_delay_s + latency_s
    sel = {"x": offs[:, 0], "y": offs[:, 1], "xy": offs}[axes]
    return sine_from_centroids(sel, 2 * math.pi * freq_hz, starts, np.full(n_frames, te))


@dataclass(frozen=True)
class AxisCalibration:
    """The actuator input axis seen by the camera: ``angle_rad`` of the image motion from +x
    toward +y for a positive input, ``px_per_unit`` (|motion| per input unit at the
    calibration frequency), the unit ``direction`` (x, y) and its std of the angle."""

    angle_rad: float
    angle_std_rad: float
    px_per_unit: float
    px_per_unit_std: float
    direction: tuple


def calibrate_axes(rig, *, freq_hz: float, amplitude: float, rest_px, dark, gain: float = 1.0, n_frames: int = 24,
                   latency_s: float = 0.0, trigger_delay_s: float = 0.0, power: float = 1.0, noise_e=None,
                   exposure_fraction: float = 0.05) -> AxisCalibration:
    """Drive one input axis at a low frequency (well inside the actuator's flat band and
    below the camera's Nyquist rate), track the spot on both image axes (short exposures of
    ``exposure_fraction`` of the period, see :func:`track_sine`), and return the direction,
    sign and scale of that actuator axis in the image."""
    tr = track_sine(rig, freq_hz=freq_hz, amplitude=amplitude, rest_px=rest_px, dark=dark, gain=gain, n_frames=n_frames,
                    latency_s=latency_s, trigger_delay_s=trigger_delay_s, power=power, axes="xy", noise_e=noise_e,
                    exposure_fraction=exposure_fraction)
    # Both image axes move in phase (or in anti-phase): signed amplitudes along a common phase.
    ref = int(np.argmax(tr.amplitude))
    phi0 = tr.phase[ref]
    signed = tr.amplitude * np.sign(np.cos(tr.phase - phi0))
    # The sign of the input: the common phase is near 0 (a positive input moves the spot along +direction)
    if math.cos(phi0) < 0:
        signed = -signed
    angle = math.atan2(signed[1], signed[0])
    mag = math.hypot(signed[0], signed[1])
    s_ang = math.hypot(signed[0] * tr.amplitude_std[1], signed[1] * tr.amplitude_std[0]) / max(mag**2, 1e-30)
    s_mag = math.hypot(tr.amplitude_std[0], tr.amplitude_std[1])
    return AxisCalibration(angle_rad=angle, angle_std_rad=s_ang, px_per_unit=mag / amplitude, px_per_unit_std=s_mag / amplitude,
                           direction=(math.cos(angle), math.sin(angle)))
