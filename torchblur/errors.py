"""Exceptions and the input checks used at public entry points.

Every check raises an exception whose message names the argument, says what was
expected and what came. ``ShapeError`` and ``ParameterError`` subclass ``ValueError``;
``InputTypeError`` subclasses ``TypeError``, so callers may catch the builtin classes.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

__all__ = [
    "TorchblurError",
    "ShapeError",
    "ParameterError",
    "InputTypeError",
    "ConfigError",
    "as_tensor",
    "check_finite",
    "check_positive",
    "check_trailing_shape",
    "check_choice",
    "broadcast_batch",
    "as_unit_direction",
    "as_frequency_grid",
    "check_real_scalar",
    "check_int",
    "check_bool",
    "check_type",
    "check_schema_version",
    "as_image",
    "as_noise_std",
    "excerpt",
    "key_excerpt",
    "EXCERPT_CHARS",
]


EXCERPT_CHARS = 40  #: the most characters of an untrusted value an error message quotes


def excerpt(value, limit: int = EXCERPT_CHARS) -> str:
    """A short, sanitised quote of an untrusted ``value`` for an error message: a string (or
    bytes) as at most ``limit`` characters, control and non-ASCII characters as ``?``, quoted;
    anything else as its ``repr`` cut to ``limit`` characters; ``...`` where cut."""
    if isinstance(value, (bytes, bytearray)):
        value = bytes(value[: 4 * limit]).decode("utf-8", "replace")
    if isinstance(value, str):
        clean = "".join(c if " " <= c <= "~" else "?" for c in value[:limit])
        return repr(clean) + ("..." if len(value) > limit else "")
    r = repr(value)
    return r if len(r) <= limit else r[:limit] + "..."


def key_excerpt(key) -> str:
    """An untrusted key for an error message: as it is when it looks like a config key (at most
    60 characters of letters, digits, ``_.-[]``), else its :func:`excerpt`."""
    k = str(key)
    if len(k) <= 60 and all(c.isascii() and (c.isalnum() or c in "_.-[]") for c in k):
        return k
    return excerpt(k)


class TorchblurError(Exception):
    """Base class of every error torchblur raises on purpose."""


class ShapeError(TorchblurError, ValueError):
    """A tensor has the wrong number of dimensions, trailing shape, or batch shape."""


class ParameterError(TorchblurError, ValueError):
    """A value is impossible: NaN/Inf, non-positive where positive is required, etc."""


class InputTypeError(TorchblurError, TypeError):
    """An argument has the wrong Python or tensor type."""


class ConfigError(TorchblurError, ValueError):
    """A configuration key is unknown or its value is invalid (the message names the key)."""


def as_tensor(
    value,
    name: str,
    *,
    like: torch.Tensor | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Convert ``value`` to a floating tensor, keeping a tensor's dtype/device and autograd.

    Python numbers and sequences take the dtype/device of ``like`` when given, else the
    default dtype. Integer tensors are promoted to the default float dtype. Boolean and
    complex tensors, strings and other objects raise :class:`InputTypeError` (a bool is a
    mask, not a number; a complex value would lose its imaginary part).
    """
    if isinstance(value, torch.Tensor):
        t = value
        if t.is_complex() or t.dtype == torch.bool:
            raise InputTypeError(f"{name}: expected a real floating tensor, got dtype {t.dtype}")
        if not t.is_floating_point():
            t = t.to(dtype or (like.dtype if like is not None else torch.get_default_dtype()))
        if dtype is not None and t.dtype != dtype:
            t = t.to(dtype)
        if device is not None:
            t = t.to(device)
        return t
    if isinstance(value, (bool, str, bytes)) or value is None or str(getattr(value, "dtype", "")) == "bool":
        raise InputTypeError(
            f"{name}: expected a number, sequence of numbers or tensor, got {type(value).__name__}"
        )
    if dtype is None:
        dtype = like.dtype if like is not None else torch.get_default_dtype()
    if device is None and like is not None:
        device = like.device
    try:
        return torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputTypeError(
            f"{name}: expected a number, sequence of numbers or tensor, got {type(value).__name__}"
        ) from exc


def check_finite(t: torch.Tensor, name: str) -> torch.Tensor:
    """Raise :class:`ParameterError` if ``t`` holds NaN or Inf."""
    d = t.detach()
    # A NaN or Inf entry makes the sum non-finite, so a finite sum (one reduction, no mask)
    # clears the tensor; a non-finite sum (a bad entry, or an overflow) gets the full check.
    if d.is_floating_point() and d.numel() > 4096 and bool(torch.isfinite(d.sum())):
        return t
    if not bool(torch.isfinite(d).all()):
        n_bad = int((~torch.isfinite(t.detach())).sum())
        raise ParameterError(f"{name}: expected finite values, got {n_bad} NaN/Inf entries")
    return t


def check_positive(t: torch.Tensor, name: str, *, strict: bool = True) -> torch.Tensor:
    """Raise :class:`ParameterError` unless every entry is finite and > 0 (>= 0 if not strict)."""
    check_finite(t, name)
    d = t.detach()
    bad = d <= 0 if strict else d < 0
    if bool(bad.any()):
        worst = float(d.min())
        rel = "> 0" if strict else ">= 0"
        raise ParameterError(f"{name}: expected every value {rel}, got minimum {worst:g}")
    return t


def check_trailing_shape(t: torch.Tensor, name: str, tail: Sequence[int], tail_desc: str) -> torch.Tensor:
    """Raise :class:`ShapeError` unless ``t.shape`` ends with ``tail``."""
    tail = tuple(tail)
    if t.dim() < len(tail) or tuple(t.shape[t.dim() - len(tail):]) != tail:
        raise ShapeError(f"{name}: expected shape {tail_desc}, got {tuple(t.shape)}")
    return t


def broadcast_batch(shapes: dict[str, torch.Size | tuple]) -> torch.Size:
    """Broadcast named batch shapes; raise :class:`ShapeError` naming them if incompatible."""
    try:
        return torch.broadcast_shapes(*shapes.values())
    except RuntimeError:
        desc = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        raise ShapeError(f"batch shapes do not broadcast: {desc}") from None


def check_real_scalar(value, name: str, *, positive: bool = False, nonnegative: bool = False, integer: bool = False,
                      low: float | None = None, high: float | None = None, error: type[Exception] | None = None) -> float:
    """A real number (a Python ``int`` or ``float``, not a bool), finite, within the bounds, as a
    ``float``: the one scalar check of frozen settings' arguments and of config keys.

    ``positive``: > 0; ``nonnegative``: >= 0; ``integer``: an ``int``; ``low``, ``high``:
    inclusive bounds.

    Raises:
        InputTypeError: naming ``name``, for a value that is not a number (or not an integer);
        ParameterError: naming ``name``, for one that is not finite or out of range;
        ``error`` for both when given (a config key: :class:`ConfigError`).
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise (error or InputTypeError)(f"{name}: expected a number, got {excerpt(value)}")
    if integer and not isinstance(value, int):
        raise (error or InputTypeError)(f"{name}: expected an integer, got {excerpt(value)}")
    v = float(value)
    for bad, want in ((not math.isfinite(v), "a finite number"), (positive and v <= 0, "a value > 0"),
                      (nonnegative and v < 0, "a value >= 0"), (low is not None and v < low, f"a value >= {low}"),
                      (high is not None and v > high, f"a value <= {high}")):
        if bad:
            raise (error or ParameterError)(f"{name}: expected {want}, got {excerpt(value)}")
    return v


def check_choice(value, name: str, options) -> str:
    """Raise :class:`ParameterError` unless ``value`` is one of ``options`` (a registry choice)."""
    if value not in options:
        raise ParameterError(f"{name}: expected one of {tuple(options)}, got {value!r}")
    return value


def as_frequency_grid(value, name: str):
    """A 1-D array of finite real numbers (angular frequencies, rad/s) as float64 numpy ``[F]``."""
    import numpy as np

    try:
        w = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name}: expected an array of real numbers, got {type(value).__name__}") from exc
    if w.ndim != 1:
        raise ShapeError(f"{name}: expected shape [F], got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ParameterError(f"{name}: expected finite values")
    return w



def as_unit_direction(value, name: str, *, like: torch.Tensor) -> torch.Tensor:
    """An image direction ``(x, y)`` (a pair, or a tensor ``[2]`` or ``[..., 2]``) -> unit
    vectors ``[..., 2]`` in ``like``'s dtype and device; raises naming ``name`` for a wrong
    shape, NaN/Inf or a zero vector."""
    d = check_finite(as_tensor(value, name, like=like), name)
    if d.dim() == 0 or d.shape[-1] != 2:
        raise ShapeError(f"{name}: expected an image direction (x, y) of shape [2] or [..., 2], got shape {tuple(d.shape)}")
    norm = d.norm(dim=-1, keepdim=True)
    if bool((norm <= 0).any()):
        raise ParameterError(f"{name}: expected a nonzero direction (x, y), got (0, 0)")
    return d / norm


def check_int(value, name: str, *, low: int | None = None, high: int | None = None,
              error: type[Exception] | None = None) -> int:
    """A Python or numpy integer (not a bool) in ``[low, high]`` as an ``int``.

    Raises :class:`InputTypeError` for anything that is not an integer (``2.5``, ``"3"``,
    ``True``) and :class:`ParameterError` for an integer out of range; both name ``name`` and
    quote the value (:func:`excerpt`: it may be untrusted); ``error`` for both when given (a
    recording's manifest: its own error).
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise (error or InputTypeError)(f"{name}: expected an integer, got {type(value).__name__} {excerpt(value)}")
    v = int(value)
    if (low is not None and v < low) or (high is not None and v > high):
        rng = f">= {low}" if high is None else (f"<= {high}" if low is None else f"in [{low}, {high}]")
        raise (error or ParameterError)(f"{name}: expected an integer {rng}, got {excerpt(v)}")
    return v


def check_bool(value, name: str) -> bool:
    """``True`` or ``False`` (not 0/1, not a string), else :class:`InputTypeError` naming ``name``."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputTypeError(f"{name}: expected True or False, got {type(value).__name__}")
    return bool(value)


def check_type(value, name: str, types, what: str):
    """``value`` if it is an instance of ``types`` (a class or a tuple of them), else
    :class:`InputTypeError` ``"{name}: expected {what}, got {type}"``."""
    if not isinstance(value, types):
        raise InputTypeError(f"{name}: expected {what}, got {type(value).__name__}")
    return value


def check_schema_version(version, supported, where: str = "", *, error: type[Exception] = ParameterError) -> int:
    """``version`` if it is one of the ``supported`` versions of a document's schema, else ``error``
    naming ``schema_version`` after ``where`` (a prefix, e.g. ``"PATH: "``): what came, the versions
    read, and that a newer torchblur wrote it where it is larger."""
    if isinstance(version, bool) or version not in supported:
        newer = " (written by a newer torchblur: upgrade to read it)" if isinstance(version, int) and version > max(supported) else ""
        raise error(f"{where}schema_version: unsupported version {excerpt(version)}{newer}; supported versions: {sorted(supported)}")
    return version


def as_image(value, name: str, *, min_dim: int = 2, desc: str = "[..., H, W]") -> torch.Tensor:
    """A floating tensor of at least ``min_dim`` dims with non-empty H and W (errors name ``name``)."""
    t = as_tensor(value, name)
    if t.dim() < min_dim:
        raise ShapeError(f"{name}: expected shape {desc}, got {tuple(t.shape)}")
    if t.shape[-1] < 1 or t.shape[-2] < 1:
        raise ShapeError(f"{name}: expected non-empty H and W in {desc}, got {tuple(t.shape)}")
    return t


def as_noise_std(noise_std, name: str, like: torch.Tensor) -> torch.Tensor:
    """A per-item noise std ``[...]`` (> 0) broadcastable against the images ``like`` ``[..., H, W]``."""
    s = check_positive(as_tensor(noise_std, name, like=like), name)
    broadcast_batch({"image": like.shape[:-2], name: s.shape})
    return s


def flat_noise_and_mask(noise_std, mask, images: torch.Tensor, frame_dims: int = 3):
    """A fitter's ``noise_std`` and ``mask`` of ``images [..., *frame]`` (``frame``: the last
    ``frame_dims`` dims, ``E, H, W`` or ``H, W``) checked and flattened to ``N = prod(...)`` items:
    ``(std, keep)``, ``std`` None, ``[N]`` (a number or ``[...]``: one per item) or ``[N, *frame]``
    (one per pixel), > 0; ``keep`` None or bool ``[N, *frame]`` (True = use the pixel), on the
    images' device. Errors name ``noise_std`` or ``mask``."""
    batch, frame = images.shape[:-frame_dims], tuple(images.shape[-frame_dims:])
    N, desc = max(1, math.prod(batch)), f"[..., {', '.join('EHW'[-frame_dims:])}] = {tuple(images.shape)}"
    std = keep = None
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=images), "noise_std")
        try:
            if s.dim() >= frame_dims and tuple(s.shape[-frame_dims:]) == frame:
                std = s.expand(batch + frame).reshape((N,) + frame)
            else:
                std = s.expand(batch).reshape(N)
        except RuntimeError:
            raise ShapeError(f"noise_std: expected a number, [...] or {desc}, got {tuple(s.shape)}") from None
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError(f"mask: expected a bool tensor {desc} (True = use the pixel), got "
                                 f"{mask.dtype if isinstance(mask, torch.Tensor) else type(mask).__name__}")
        try:
            keep = mask.to(images.device).expand(batch + frame).reshape((N,) + frame)
        except RuntimeError:
            raise ShapeError(f"mask: expected shape {desc}, got {tuple(mask.shape)}") from None
    return std, keep
