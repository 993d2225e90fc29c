"""Sensor timing (paper section II-A) and exposure windows.

Time is in seconds throughout. t = 0 is an upward zero crossing of the actuator command
(the controller that makes the sine also times the trigger), so an exposure window's
``start`` is measured from that origin (PHYSICS.md section 2).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchblur.errors import ParameterError, as_tensor, broadcast_batch, check_finite, check_int, check_positive, check_real_scalar

__all__ = ["ExposureWindow", "SensorTiming"]


class ExposureWindow:
    """A batch of exposure windows ``[start, start + duration]``.

    Args:
        start: exposure start ``tcam = Ta + Td`` in seconds, shape ``[...]``.
        duration: exposure time ``Te`` in seconds, shape ``[...]``, every value > 0.

    ``start`` and ``duration`` broadcast against each other; either may require grad.
    Python numbers become float64 tensors (a phase ``omega t`` needs the precision; in
    float32 keep ``start`` within a few periods of the zero crossing).
    A plain container of tensors: it holds no state beyond them.

    Example:
        >>> w = ExposureWindow(start=torch.tensor([0.0, 1e-3]), duration=5e-3)
        >>> w.shape
        torch.Size([2])
    """

    __slots__ = ("start", "duration")

    def __init__(self, start, duration):
        if not isinstance(start, torch.Tensor) and not isinstance(duration, torch.Tensor):
            start = as_tensor(start, "start", dtype=torch.float64)  # times need float64 precision
        duration_t = as_tensor(duration, "duration", like=start if isinstance(start, torch.Tensor) else None)
        start_t = as_tensor(start, "start", like=duration_t)
        check_finite(start_t, "start")
        check_positive(duration_t, "duration")
        shape = broadcast_batch({"start": start_t.shape, "duration": duration_t.shape})
        self.start = start_t.expand(shape) if start_t.shape != shape else start_t
        self.duration = duration_t.expand(shape) if duration_t.shape != shape else duration_t

    @property
    def shape(self) -> torch.Size:
        """Batch shape ``[...]``."""
        return self.start.shape

    @property
    def end(self) -> torch.Tensor:
        """Exposure end ``start + duration`` in seconds, ``[...]``."""
        return self.start + self.duration

    @property
    def center(self) -> torch.Tensor:
        """Window centre ``start + duration / 2`` in seconds, ``[...]``."""
        return self.start + 0.5 * self.duration

    def expand(self, shape) -> "ExposureWindow":
        """Broadcast to batch ``shape``."""
        return ExposureWindow(self.start.expand(shape), self.duration.expand(shape))

    def __getitem__(self, idx) -> "ExposureWindow":
        return ExposureWindow(self.start[idx], self.duration[idx])

    def to(self, *args, **kwargs) -> "ExposureWindow":
        return ExposureWindow(self.start.to(*args, **kwargs), self.duration.to(*args, **kwargs))

    def __repr__(self) -> str:
        return f"ExposureWindow(shape={tuple(self.shape)}, dtype={self.start.dtype})"


@dataclass(frozen=True)
class SensorTiming:
    """Frozen camera timing (paper section II-A), all in seconds.

    Args:
        acquisition_s: ``Ta``, when the sensor is first triggered (from t = 0).
        trigger_delay_s: ``Td``, from the trigger to the start of the exposure.
        exposure_s: ``Te``, the exposure time (> 0).
        readout_s: ``Tr``, the time to read the sensor out.
        sample_period_s: ``Ts``, between successive exposures; must satisfy
            ``Ts >= Td + Tr + Te``.

    The exposure of frame k starts at ``tcam_k = Ta + Td + k Ts``.
    """

    acquisition_s: float
    trigger_delay_s: float
    exposure_s: float
    readout_s: float
    sample_period_s: float

    def __post_init__(self):
        check_real_scalar(self.acquisition_s, "acquisition_s")
        check_real_scalar(self.trigger_delay_s, "trigger_delay_s", nonnegative=True)
        check_real_scalar(self.exposure_s, "exposure_s", positive=True)
        check_real_scalar(self.readout_s, "readout_s", nonnegative=True)
        check_real_scalar(self.sample_period_s, "sample_period_s", positive=True)
        need = self.trigger_delay_s + self.readout_s + self.exposure_s
        if self.sample_period_s < need * (1 - 1e-12):
            raise ParameterError(
                f"sample_period_s: expected Ts >= Td + Tr + Te = {need:g} s, got {self.sample_period_s:g} s"
            )

    @property
    def tcam_s(self) -> float:
        """Start of the first exposure, ``Ta + Td`` (s)."""
        return self.acquisition_s + self.trigger_delay_s

    @property
    def frame_rate_hz(self) -> float:
        """``1 / Ts``."""
        return 1.0 / self.sample_period_s

    def windows(self, n_frames: int, *, dtype=None, device=None) -> ExposureWindow:
        """The exposure windows of ``n_frames`` successive frames, batch shape ``[n_frames]``
        (float64 by default: times need the precision)."""
        n_frames = check_int(n_frames, "n_frames", low=1)
        dtype = dtype or torch.float64
        k = torch.arange(n_frames, dtype=dtype, device=device)
        start = self.tcam_s + k * self.sample_period_s
        return ExposureWindow(start, torch.full_like(start, self.exposure_s))

    def window(self, *, dtype=None, device=None) -> ExposureWindow:
        """The exposure window of the first frame, batch shape ``[]`` (float64 by default)."""
        dtype = dtype or torch.float64
        return ExposureWindow(
            torch.tensor(self.tcam_s, dtype=dtype, device=device),
            torch.tensor(self.exposure_s, dtype=dtype, device=device),
        )
