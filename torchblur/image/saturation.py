"""The saturation curve (paper Fig. 4): the still spot's peak against exposure, a hinge fit that
finds where the sensor stops being linear, and a mask of saturated pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor, check_finite, check_int, check_positive, check_real_scalar

__all__ = ["SaturationCurve", "saturation_curve"]


@dataclass
class SaturationCurve:
    """Peak intensity versus exposure: ``min(offset_adu + slope_adu_per_s t, saturation_adu)``.

    Attributes (0-d tensors, the dtype of the peaks):
        slope_adu_per_s: the linear response (ADU per second of exposure).
        offset_adu: the line's value at t = 0 (the dark level plus any constant light).
        saturation_adu: the plateau; ``inf`` if no sample saturated and no full scale was given.
        linear_limit_s: the exposure where the line meets the plateau.
        residual_rms_adu: rms of the samples about the fitted curve.
        saturated_in_data: whether the samples themselves show the plateau.
    """

    slope_adu_per_s: torch.Tensor
    offset_adu: torch.Tensor
    saturation_adu: torch.Tensor
    linear_limit_s: torch.Tensor
    residual_rms_adu: torch.Tensor
    saturated_in_data: bool

    def __call__(self, exposure_s) -> torch.Tensor:
        """The curve at ``exposure_s`` (any shape), in ADU."""
        t = as_tensor(exposure_s, "exposure_s", like=self.slope_adu_per_s)
        return torch.minimum(self.offset_adu + self.slope_adu_per_s * t, self.saturation_adu)

    def mask(self, frames_adu, margin_adu: float | None = None) -> torch.Tensor:
        """Usable (unsaturated) pixels: ``frames_adu < saturation_adu - margin_adu``.

        Args:
            frames_adu: frames in ADU, any shape (raw, before dark subtraction: the same
                scale as the peaks the curve was fitted to).
            margin_adu: pixels within this distance below the plateau are excluded too
                (>= 0); default 1% of ``saturation_adu - offset_adu`` (the response bends
                before it clips).

        Returns:
            bool tensor, the shape of ``frames_adu``; NaN pixels are False.
        """
        frames = as_tensor(frames_adu, "frames_adu")
        if margin_adu is None:
            span = self.saturation_adu - self.offset_adu
            margin = torch.where(torch.isfinite(span), 0.01 * span, torch.zeros_like(span))
        else:
            margin = torch.tensor(check_real_scalar(margin_adu, "margin_adu", nonnegative=True), dtype=frames.dtype)
        level = (self.saturation_adu - margin).to(device=frames.device, dtype=frames.dtype)
        return frames < level


def _hinge_fit(t: torch.Tensor, y: torch.Tensor, knots: torch.Tensor):
    """Least squares of ``y = a + b min(t, knot)`` for each knot: ``(a, b, sse)``, each ``[M]``."""
    u = torch.minimum(t[None, :], knots[:, None])  # [M, K]
    um = u.mean(-1, keepdim=True)
    ym = y.mean()
    du = u - um
    suu = du.square().sum(-1)
    b = (du * (y - ym)).sum(-1) / suu.clamp_min(torch.finfo(t.dtype).tiny)
    a = ym - b * um[:, 0]
    sse = (y - a[:, None] - b[:, None] * u).square().sum(-1)
    sse = torch.where((suu > 0) & (b > 0), sse, torch.full_like(sse, float("inf")))
    return a, b, sse


def saturation_curve(peak_adu, exposures_s, *, full_scale_adu: float | None = None, samples_per_interval: int = 64) -> SaturationCurve:
    """Fit the peak intensity versus exposure time (paper Fig. 4): linear, then flat.

    The model ``min(offset + slope t, plateau)`` is continuous, so with the knot
    ``t_k = (plateau - offset) / slope`` it is ``offset + slope min(t, t_k)``: linear in
    (offset, slope) for a fixed knot. The knot is scanned over ``samples_per_interval``
    candidates in each interval between sorted exposures (at least two samples on the line
    and two on the plateau), then once more on a finer grid around the best, and the least
    squares fit wins. The plateau is kept only if it lowers the squared error of the plain
    line by more than 9 residual variances (about a 3 sigma improvement); else the
    samples are all linear and the plateau is ``full_scale_adu`` (or ``inf``).

    Args:
        peak_adu: peak pixel values ``[K]`` (ADU, raw: the dark level included), finite.
        exposures_s: exposure times ``[K]`` (s, >= 0), at least 3 distinct values.
        full_scale_adu: the ADC's largest value (optional); used as the plateau when no
            sample saturates.
        samples_per_interval: knot candidates per interval between exposures (>= 2).

    Returns:
        :class:`SaturationCurve`.
    """
    y = as_tensor(peak_adu, "peak_adu")
    t = as_tensor(exposures_s, "exposures_s", like=y)
    if y.dim() != 1:
        raise ShapeError(f"peak_adu: expected shape [K], got {tuple(y.shape)}")
    if t.shape != y.shape:
        raise ShapeError(f"exposures_s: expected shape {tuple(y.shape)} like peak_adu, got {tuple(t.shape)}")
    check_finite(y, "peak_adu")
    check_positive(t, "exposures_s", strict=False)
    m = check_int(samples_per_interval, "samples_per_interval", low=2)
    if full_scale_adu is not None:
        full_scale_adu = check_real_scalar(full_scale_adu, "full_scale_adu", positive=True)
    t, order = t.detach().sort()
    y = y.detach()[order]
    tu = torch.unique(t)
    if tu.numel() < 3:
        raise ParameterError(f"exposures_s: expected at least 3 distinct exposures, got {tu.numel()}")
    K = t.numel()
    dtype, device = y.dtype, y.device

    a_lin, b_lin, sse_lin = _hinge_fit(t, y, t[-1:])
    best = (a_lin[0], b_lin[0], sse_lin[0], t[-1])
    saturated = False
    if tu.numel() >= 4:
        # knots between the 2nd and the 2nd-to-last distinct exposures
        frac = torch.linspace(0, 1, m + 1, dtype=dtype, device=device)[:-1]
        lo, hi = tu[1:-2], tu[2:-1]
        knots = torch.cat([(lo[:, None] + (hi - lo)[:, None] * frac).reshape(-1), tu[-2:-1]])
        a, b, sse = _hinge_fit(t, y, knots)
        i = int(torch.argmin(sse))
        if torch.isfinite(sse[i]):
            left = knots[max(i - 1, 0)]
            right = knots[min(i + 1, knots.numel() - 1)]
            fine = torch.linspace(float(left), float(right), 4 * m + 1, dtype=dtype, device=device)
            a2, b2, sse2 = _hinge_fit(t, y, fine)
            j = int(torch.argmin(sse2))
            cand = (a2[j], b2[j], sse2[j], fine[j]) if sse2[j] <= sse[i] else (a[i], b[i], sse[i], knots[i])
            dof = max(K - 3, 1)
            if not torch.isfinite(sse_lin[0]) or float(sse_lin[0] - cand[2]) > 9 * float(cand[2]) / dof:
                best = cand
                saturated = True
    a, b, sse, knot = best
    if not torch.isfinite(sse):
        raise ParameterError("peak_adu: expected peaks that rise with exposure (no positive slope fits)")
    if saturated:
        plateau = a + b * knot
        limit = knot
    elif full_scale_adu is not None:
        plateau = torch.tensor(full_scale_adu, dtype=dtype, device=device)
        limit = (plateau - a) / b
    else:
        plateau = torch.tensor(float("inf"), dtype=dtype, device=device)
        limit = torch.tensor(float("inf"), dtype=dtype, device=device)
    rms = (sse / K).sqrt()
    return SaturationCurve(
        slope_adu_per_s=b, offset_adu=a, saturation_adu=plateau, linear_limit_s=limit,
        residual_rms_adu=rms, saturated_in_data=saturated,
    )
