"""Camera model: turns expected photo-electrons into noisy, clipped, quantized frames.

A slow CCD/CMOS camera looking at a laser spot. The renderer gives the noise-free
expected number of photo-electrons per pixel; :class:`CameraModel` adds what the sensor
does to it (hot pixels, shot noise, full well, read noise, gain, dark level, quantization,
ADC range) and gives the tools a fitter needs to undo it (:meth:`CameraModel.to_electrons`,
:attr:`CameraModel.noise`, :meth:`CameraModel.saturated_mask`).

Glossary: ``...`` batch dims, ``H, W`` pixels; ``image[..., i, j]`` is the pixel at row
``i``, column ``j`` (x = j, y = i). Charge is in electrons (``_e``), digital values in
ADU (analogue-to-digital units), time in seconds (``_s``).

Every method is pure: tensors in, tensors out, with dtype and device taken from the
input. Every random draw uses the ``generator`` passed in (a ``torch.Generator`` on the
input's device; ``None`` uses PyTorch's global RNG), so a seeded generator gives
bit-identical frames. The hot-pixel pattern is a property of the sensor, not of a frame:
it comes from its own generator seeded with ``hot_pixel_seed``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchblur.errors import (ParameterError, ShapeError, as_tensor, check_bool, check_finite, check_int, check_real_scalar,
                              check_type)
from torchblur.render.window import ExposureWindow

__all__ = ["CameraModel", "CameraNoise", "camera_noise_std", "noise_sets_weights"]


def camera_noise_std(expected_e, read_noise_e: float):
    """Standard deviation of a measured pixel, in electrons: ``sqrt(read_noise_e**2 +
    max(expected_e, 0))`` (read noise and shot noise; the noise model every fit of the
    identification weights its residuals with, the expected charge estimated by the
    dark-subtracted image itself).

    Args:
        expected_e: expected (or measured) photo-electrons per pixel: a tensor ``[...]`` (any
            shape; negative values count as 0) or a number.
        read_noise_e: read noise (electrons, >= 0).

    Returns:
        A tensor of the same shape, dtype and device (a float for a number).

    Example:
        >>> camera_noise_std(torch.tensor([-2.0, 0.0, 16.0]), 3.0)
        tensor([3., 3., 5.])
    """
    if isinstance(expected_e, torch.Tensor):
        return torch.sqrt(read_noise_e**2 + expected_e.clamp_min(0))
    return math.sqrt(read_noise_e**2 + max(float(expected_e), 0.0))


@dataclass(frozen=True)
class CameraNoise:
    """The noise of a camera's pixels, in electrons: the one noise model every loss of a fit
    weighs its residuals with.

    A pixel's dark-subtracted charge ``d = (adu - offset_adu) * gain_e_per_adu`` is the sum of
    a Poisson count of mean ``m`` (the expected photo-electrons, shot noise) and Gaussian read
    noise of std ``read_noise_e`` (the dark frames' std, rounding to whole ADU included):
    ``E d = m``, ``var d = m + read_noise_e**2`` (:meth:`std`). For the Poisson likelihood,
    ``d + read_noise_e**2`` is close to ``Poisson(m + read_noise_e**2)`` (same mean and
    variance; the "shifted Poisson" of Snyder et al., 1993, for CCDs with read noise):
    :attr:`poisson_shift_e` is that shift.

    Args:
        gain_e_per_adu: conversion gain, electrons per ADU (> 0).
        offset_adu: the dark level, ADU (a number; the mean of a dark frame).
        read_noise_e: read noise std, electrons (>= 0).

    Example:
        >>> noise = CameraNoise(gain_e_per_adu=2.0, offset_adu=100.0, read_noise_e=3.0)
        >>> noise.std(torch.tensor([0.0, 16.0]))
        tensor([3., 5.])
        >>> noise.poisson_shift_e
        9.0
    """

    gain_e_per_adu: float = 1.0
    offset_adu: float = 0.0
    read_noise_e: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "gain_e_per_adu", check_real_scalar(self.gain_e_per_adu, "gain_e_per_adu", positive=True))
        object.__setattr__(self, "offset_adu", check_real_scalar(self.offset_adu, "offset_adu"))
        object.__setattr__(self, "read_noise_e", check_real_scalar(self.read_noise_e, "read_noise_e", nonnegative=True))

    def std(self, expected_e):
        """Std of a pixel's dark-subtracted charge, electrons: :func:`camera_noise_std`
        (``sqrt(read_noise_e**2 + max(expected_e, 0))``), ``expected_e`` a tensor ``[...]`` or a number."""
        return camera_noise_std(expected_e, self.read_noise_e)

    @property
    def poisson_shift_e(self) -> float:
        """``read_noise_e**2`` (electrons): the shift that makes ``d + shift`` a Poisson count of
        mean ``m + shift`` to two moments (the Poisson loss adds it to data and model)."""
        return self.read_noise_e**2

    def to_electrons(self, frames_adu) -> torch.Tensor:
        """``(frames_adu - offset_adu) * gain_e_per_adu``: dark-subtracted charge, electrons,
        same shape, dtype and device as ``frames_adu`` ``[...]``."""
        frames = check_finite(as_tensor(frames_adu, "frames_adu"), "frames_adu")
        return (frames - self.offset_adu) * self.gain_e_per_adu


def noise_sets_weights(noise, noise_std) -> bool:
    """Check ``noise`` (a :class:`CameraNoise` or None) -> whether a fit's weights come from the
    noise model (``noise`` given, ``noise_std`` not); ParameterError when they would and
    ``read_noise_e`` is 0 (a pixel with no expected light would get infinite weight)."""
    if noise is None:
        return False
    check_type(noise, "noise", CameraNoise, "a CameraNoise or None")
    if noise_std is None and noise.read_noise_e == 0:
        raise ParameterError("noise: read_noise_e is 0, so a pixel with no expected light would get zero std (infinite weight); "
                             "pass noise_std")
    return noise_std is None


def _check_generator(generator, device: torch.device) -> None:
    """Raise unless ``generator`` is ``None`` or a ``torch.Generator`` on ``device``."""
    if generator is None:
        return
    check_type(generator, "generator", torch.Generator, "a torch.Generator or None")
    if generator.device.type != device.type:
        raise ParameterError(
            f"generator: expected a generator on the input's device ({device.type}), "
            f"got one on {generator.device.type}"
        )


def _check_electrons(expected_e, name: str) -> torch.Tensor:
    """Convert to a floating tensor; raise unless every value is finite and >= 0."""
    t = as_tensor(expected_e, name)
    check_finite(t, name)
    d = t.detach()
    if d.numel() and bool((d < 0).any()):
        raise ParameterError(f"{name}: expected every value >= 0 electrons, got minimum {float(d.min()):g}")
    return t


@dataclass(frozen=True)
class CameraModel:
    """Frozen settings of a camera sensor, with the methods that simulate and invert it.

    Args:
        dark_level_adu: offset added to every pixel, in ADU (>= 0).
        read_noise_e: standard deviation of the Gaussian read noise, in electrons (>= 0).
        gain_e_per_adu: conversion gain, electrons per ADU (> 0).
        full_well_e: charge at which a pixel saturates, in electrons (> 0).
        bit_depth: ADC resolution in bits (1..32); output values lie in
            ``[0, 2**bit_depth - 1]`` ADU.
        shot_noise: draw the photo-electron count from a Poisson distribution.
        hot_pixel_fraction: fraction of pixels that are hot (0..1), a fixed pattern.
        hot_pixel_e: extra electrons a hot pixel collects per frame (>= 0); Poisson
            distributed like the signal when ``shot_noise`` is on.
        hot_pixel_seed: seed of the hot-pixel pattern (an integer in ``[0, 2**64 - 1]``);
            the pattern is the same for every frame, call and device.
        jitter_s: rms trigger jitter in seconds (>= 0), see :meth:`jitter_window`.
        quantize: round the output to integer ADU.

    Numbers are stored as ``float`` (``bit_depth`` and ``hot_pixel_seed`` as ``int``).
    Every bad value raises :class:`~torchblur.errors.ParameterError` (impossible value) or
    :class:`~torchblur.errors.InputTypeError` (wrong type) naming the field.

    Example:
        >>> cam = CameraModel(read_noise_e=0.0, shot_noise=False)
        >>> frame = cam.expose(torch.full((2, 4, 5), 1000.0))
        >>> frame.shape
        torch.Size([2, 4, 5])
        >>> float(frame[0, 0, 0])
        1100.0
    """

    dark_level_adu: float = 100.0
    read_noise_e: float = 5.0
    gain_e_per_adu: float = 1.0
    full_well_e: float = 20000.0
    bit_depth: int = 12
    shot_noise: bool = True
    hot_pixel_fraction: float = 0.0
    hot_pixel_e: float = 5000.0
    hot_pixel_seed: int = 0
    jitter_s: float = 0.0
    quantize: bool = True

    def __post_init__(self):
        checked = {
            "dark_level_adu": check_real_scalar(self.dark_level_adu, "dark_level_adu", nonnegative=True),
            "read_noise_e": check_real_scalar(self.read_noise_e, "read_noise_e", nonnegative=True),
            "gain_e_per_adu": check_real_scalar(self.gain_e_per_adu, "gain_e_per_adu", positive=True),
            "full_well_e": check_real_scalar(self.full_well_e, "full_well_e", positive=True),
            "bit_depth": check_int(self.bit_depth, "bit_depth", low=1, high=32),
            "shot_noise": check_bool(self.shot_noise, "shot_noise"),
            "hot_pixel_fraction": check_real_scalar(self.hot_pixel_fraction, "hot_pixel_fraction", low=0.0, high=1.0),
            "hot_pixel_e": check_real_scalar(self.hot_pixel_e, "hot_pixel_e", nonnegative=True),
            "hot_pixel_seed": check_int(self.hot_pixel_seed, "hot_pixel_seed", low=0, high=2**64 - 1),
            "jitter_s": check_real_scalar(self.jitter_s, "jitter_s", nonnegative=True),
            "quantize": check_bool(self.quantize, "quantize"),
        }
        if checked["dark_level_adu"] >= 2 ** checked["bit_depth"] - 1:
            raise ParameterError(
                f"dark_level_adu: expected a value below the ADC's maximum 2**bit_depth - 1 = {2 ** checked['bit_depth'] - 1} ADU "
                f"(else every pixel is saturated), got {checked['dark_level_adu']:g}")
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ levels

    @property
    def max_adu(self) -> float:
        """Largest value the ADC can output, ``2**bit_depth - 1`` ADU."""
        return float(2**self.bit_depth - 1)

    @property
    def saturation_adu(self) -> float:
        """ADU value of a saturated pixel:
        ``min(2**bit_depth - 1, full_well_e / gain_e_per_adu + dark_level_adu)``.

        A pixel reading at or above this value (less half an ADU of rounding, see
        :meth:`saturated_mask`) has been clipped, by the full well or by the ADC range.
        """
        return min(self.max_adu, self.full_well_e / self.gain_e_per_adu + self.dark_level_adu)

    # ------------------------------------------------------------------ forward model

    def expose(self, expected_e, *, generator: torch.Generator | None = None) -> torch.Tensor:
        """Simulate frames from the expected photo-electrons.

        Args:
            expected_e: noise-free expected number of photo-electrons per pixel, shape
                ``[..., H, W]``; every value finite and >= 0. ``expected_e[..., i, j]``
                is the mean charge of row ``i``, column ``j``.
            generator: ``torch.Generator`` on ``expected_e``'s device used for every random
                draw; ``None`` uses the global RNG.

        Returns:
            Frames in ADU, shape ``[..., H, W]``, same dtype and device as ``expected_e``;
            ``frames[..., i, j]`` is the digital value of row ``i``, column ``j``.

        Steps, per pixel with charge ``q`` in electrons:

        1. ``q = expected_e + hot_pixel_e * hot`` (``hot`` from :meth:`hot_pixel_mask`,
           the same for every batch element);
        2. ``q ~ Poisson(q)`` if ``shot_noise``;
        3. ``q = min(q, full_well_e)``; a pixel whose well is full is saturated;
        4. ``q = q + read_noise_e * N(0, 1)`` for pixels that are not saturated, and
           ``q = min(q, full_well_e)``; a saturated pixel reads exactly ``full_well_e``,
           as the analogue chain clips after the read noise;
        5. ``adu = q / gain_e_per_adu + dark_level_adu``;
        6. ``adu = round(adu)`` if ``quantize``;
        7. ``adu = clip(adu, 0, 2**bit_depth - 1)``.

        Without noise and clipping, ``mean(adu) = expected_e / gain + dark`` and
        ``var(adu) = (expected_e + read_noise_e**2) / gain**2 + 1/12`` (the ``1/12`` from
        rounding); see :attr:`noise`.

        Not differentiable (Poisson sampling and rounding); use it to make data.
        """
        q = _check_electrons(expected_e, "expected_e")
        if q.dim() < 2:
            raise ShapeError(f"expected_e: expected shape [..., H, W] (at least 2 dims), got {tuple(q.shape)}")
        _check_generator(generator, q.device)
        q = q.detach()
        height, width = q.shape[-2], q.shape[-1]

        if self.hot_pixel_fraction > 0 and self.hot_pixel_e > 0:
            hot = self.hot_pixel_mask(height, width, device=q.device)
            q = q + self.hot_pixel_e * hot.to(q.dtype)
        if self.shot_noise:
            q = torch.poisson(q, generator=generator)
        full = q >= self.full_well_e
        q = q.clamp(max=self.full_well_e)
        if self.read_noise_e > 0:
            noise = torch.randn(q.shape, generator=generator, dtype=q.dtype, device=q.device)
            q = torch.where(full, q, (q + self.read_noise_e * noise).clamp(max=self.full_well_e))
        adu = q / self.gain_e_per_adu + self.dark_level_adu
        if self.quantize:
            adu = torch.round(adu)
        return adu.clamp(0.0, self.max_adu)

    def hot_pixel_mask(self, height: int, width: int, *, device=None) -> torch.Tensor:
        """The fixed hot-pixel pattern of an ``H x W`` sensor.

        Args:
            height: ``H``, number of pixel rows (integer >= 1).
            width: ``W``, number of pixel columns (integer >= 1).
            device: device of the returned mask (default CPU).

        Returns:
            Boolean mask, shape ``[H, W]``; ``mask[i, j]`` is True if the pixel at row
            ``i``, column ``j`` is hot. Exactly ``round(hot_pixel_fraction * H * W)``
            pixels are hot, chosen by a CPU ``torch.Generator`` seeded with
            ``hot_pixel_seed``, so the pattern is the same on every call and device.
        """
        height = check_int(height, "height", low=1, high=2**62)
        width = check_int(width, "width", low=1, high=2**62)
        n_pixels = height * width
        n_hot = round(self.hot_pixel_fraction * n_pixels)
        mask = torch.zeros(n_pixels, dtype=torch.bool)
        if n_hot > 0:
            rng = torch.Generator(device="cpu")
            rng.manual_seed(self.hot_pixel_seed)
            mask[torch.randperm(n_pixels, generator=rng)[:n_hot]] = True
        return mask.reshape(height, width).to(device)

    # ------------------------------------------------------------------ inverse model

    def saturated_mask(self, frames_adu) -> torch.Tensor:
        """Where frames are clipped.

        Args:
            frames_adu: frames in ADU, shape ``[..., H, W]`` (any shape works).

        Returns:
            Boolean tensor, same shape and device; True where
            ``frames_adu >= saturation_adu - 0.5`` (the half ADU allows for rounding).
        """
        frames = check_finite(as_tensor(frames_adu, "frames_adu"), "frames_adu")
        return frames >= self.saturation_adu - 0.5

    def to_electrons(self, frames_adu) -> torch.Tensor:
        """Map ADU back to electrons: ``(frames_adu - dark_level_adu) * gain_e_per_adu``.

        Args:
            frames_adu: frames in ADU, shape ``[..., H, W]`` (any shape works).

        Returns:
            Charge in electrons, same shape, dtype and device; differentiable.
        """
        return self.noise.to_electrons(frames_adu)

    @property
    def noise(self) -> CameraNoise:
        """This sensor's :class:`CameraNoise`: its gain and dark level, and as read noise
        ``sqrt(read_noise_e**2 + gain_e_per_adu**2 / 12 [if quantize])`` (rounding to whole ADU
        adds ``1/12`` ADU^2, as a dark frame's std measures it). Assumes ``shot_noise``."""
        q = self.gain_e_per_adu**2 / 12.0 if self.quantize else 0.0
        return CameraNoise(gain_e_per_adu=self.gain_e_per_adu, offset_adu=self.dark_level_adu, read_noise_e=math.sqrt(self.read_noise_e**2 + q))

    # ------------------------------------------------------------------ timing

    def jitter_window(self, window: ExposureWindow, *, generator: torch.Generator | None = None) -> ExposureWindow:
        """Shift the exposure starts by the trigger jitter.

        Args:
            window: exposure windows, batch shape ``[...]``, times in seconds.
            generator: ``torch.Generator`` on the window's device; ``None`` uses the
                global RNG.

        Returns:
            A new :class:`~torchblur.render.window.ExposureWindow` with
            ``start[...] + jitter_s * N(0, 1)``, one independent draw per batch element,
            and the same ``duration``; ``window`` itself when ``jitter_s == 0``.
            Differentiable in ``window.start``.
        """
        check_type(window, "window", ExposureWindow, "an ExposureWindow")
        if self.jitter_s == 0:
            return window
        start = window.start
        _check_generator(generator, start.device)
        noise = torch.randn(start.shape, generator=generator, dtype=start.dtype, device=start.device)
        return ExposureWindow(start + self.jitter_s * noise, window.duration)
