"""Point spread functions (image kernels Psi).

Conventions: pixel (row i, column j) has its centre at x = j, y = i; positions are in
pixels (px), covariances in px^2. A PSF's ``amplitude`` is its peak intensity per second
of exposure, so a rendered image scales with the exposure time.
"""
from __future__ import annotations

import math

import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor, broadcast_batch, check_finite, check_positive, check_trailing_shape

__all__ = ["GaussianPSF", "KernelPSF"]


def _batch_index(idx, trailing: int) -> tuple:
    """An index ``idx`` of a PSF's batch dims ``[...]`` as an index of a tensor ``[..., *trailing
    dims]`` (``trailing`` whole dims appended, so ``...`` and None stay in the batch)."""
    return (idx if isinstance(idx, tuple) else (idx,)) + (slice(None),) * trailing


class GaussianPSF:
    """A 2-D Gaussian spot with full covariance (tilted ellipses allowed).

    ``Psi(eta) = amplitude * exp(-1/2 (eta - center)^T cov^-1 (eta - center))``

    Args:
        center: rest position (x, y) in px, shape ``[..., 2]``.
        cov: covariance in px^2, shape ``[..., 2, 2]``, symmetric positive definite.
        amplitude: peak intensity per second of exposure, shape ``[...]``, >= 0 (default 1).

    The three broadcast to one batch shape ``[...]``; any may require grad.

    Example:
        >>> psf = GaussianPSF(center=torch.tensor([31.5, 31.5]), cov=4.0 * torch.eye(2))
        >>> psf.shape
        torch.Size([])
    """

    __slots__ = ("center", "cov", "amplitude")

    def __init__(self, center, cov, amplitude=1.0):
        center = as_tensor(center, "center")
        cov = as_tensor(cov, "cov", like=center)
        amplitude = as_tensor(amplitude, "amplitude", like=center)
        check_trailing_shape(center, "center", (2,), "[..., 2] (x, y in px)")
        check_trailing_shape(cov, "cov", (2, 2), "[..., 2, 2] (px^2)")
        check_finite(center, "center")
        check_finite(cov, "cov")
        check_positive(amplitude, "amplitude", strict=False)
        c = cov.detach()
        asym = (c[..., 0, 1] - c[..., 1, 0]).abs()
        scale = c[..., 0, 0].abs() + c[..., 1, 1].abs()
        if bool((asym > 1e-6 * scale).any()):
            raise ParameterError("cov: expected a symmetric matrix, got cov[..., 0, 1] != cov[..., 1, 0]")
        det = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0]
        if bool(((c[..., 0, 0] <= 0) | (det <= 0)).any()):
            raise ParameterError(
                f"cov: expected a positive-definite covariance, got min det {float(det.min()):g} "
                f"and min diagonal {float(torch.minimum(c[..., 0, 0], c[..., 1, 1]).min()):g}"
            )
        shape = broadcast_batch({"center": center.shape[:-1], "cov": cov.shape[:-2], "amplitude": amplitude.shape})
        self.center = center.expand(shape + (2,))
        self.cov = cov.expand(shape + (2, 2))
        self.amplitude = amplitude.expand(shape)

    @classmethod
    def isotropic(cls, center, sigma, amplitude=1.0) -> "GaussianPSF":
        """A round spot of standard deviation ``sigma`` px (shape ``[...]``)."""
        center = as_tensor(center, "center")
        sigma = as_tensor(sigma, "sigma", like=center)
        check_positive(sigma, "sigma")
        eye = torch.eye(2, dtype=center.dtype, device=center.device)
        return cls(center, sigma[..., None, None] ** 2 * eye, amplitude)

    @classmethod
    def from_axes(cls, center, sigma_major, sigma_minor, angle, amplitude=1.0) -> "GaussianPSF":
        """An ellipse with standard deviations along its axes (px) and ``angle`` (rad) of the
        major axis from +x toward +y; each ``[...]``."""
        center = as_tensor(center, "center")
        s1 = check_positive(as_tensor(sigma_major, "sigma_major", like=center), "sigma_major")
        s2 = check_positive(as_tensor(sigma_minor, "sigma_minor", like=center), "sigma_minor")
        th = check_finite(as_tensor(angle, "angle", like=center), "angle")
        c, s = torch.cos(th), torch.sin(th)
        rot = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
        diag = torch.diag_embed(torch.stack(torch.broadcast_tensors(s1**2, s2**2), -1))
        return cls(center, rot @ diag @ rot.transpose(-1, -2), amplitude)

    @property
    def shape(self) -> torch.Size:
        """Batch shape ``[...]``."""
        return self.amplitude.shape

    def precision(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(A, B, C)`` with ``cov^-1 = [[A, B], [B, C]]``, each ``[...]`` (px^-2)."""
        sxx, sxy, syy = self.cov[..., 0, 0], self.cov[..., 0, 1], self.cov[..., 1, 1]
        det = sxx * syy - sxy * sxy
        return syy / det, -sxy / det, sxx / det

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The rest position ``[..., 2]`` (x, y px) and covariance ``[..., 2, 2]`` (px^2): the
        centre and ``cov`` themselves (with their gradient), as :meth:`KernelPSF.moments`."""
        return self.center, self.cov

    def footprint(self, sigmas: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The box that holds the spot, ``(lo, hi)``, each ``[..., 2]`` (x, y px, no gradient):
        ``sigmas`` standard deviations about the centre along x and along y."""
        sd = torch.diagonal(self.cov.detach(), dim1=-2, dim2=-1).clamp_min(0).sqrt()
        center = self.center.detach()
        return center - sigmas * sd, center + sigmas * sd

    def cropped(self, x0: int, y0: int, x1: int, y1: int) -> "GaussianPSF":
        """The spot in the frame of the crop ``[y0:y1, x0:x1]`` (px) of its frame: the centre less
        ``(x0, y0)``, the same covariance and amplitude (as :meth:`KernelPSF.cropped`)."""
        shift = torch.tensor([x0, y0], dtype=self.center.dtype, device=self.center.device)
        return GaussianPSF(self.center - shift, self.cov, self.amplitude)

    def sigma_min(self) -> torch.Tensor:
        """Smallest principal standard deviation (px), ``[...]``."""
        return torch.linalg.eigvalsh(self.cov).clamp_min(0)[..., 0].sqrt()

    def total_light(self) -> torch.Tensor:
        """Integral of the PSF over the plane per second, ``a 2 pi sqrt(det cov)``, ``[...]``."""
        return self.amplitude * 2 * math.pi * torch.linalg.det(self.cov).sqrt()

    def evaluate(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Point values at coordinates ``x``, ``y`` (px) broadcast against ``[...]``: slow
        and direct, for references and tests."""
        A, B, C = self.precision()
        dx = x - self.center[..., 0]
        dy = y - self.center[..., 1]
        return self.amplitude * torch.exp(-0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy))

    def __getitem__(self, idx) -> "GaussianPSF":
        """Items ``idx`` of the batch ``[...]`` (any tensor index of the batch dims, ``...`` and None
        included: ``psf[..., None]`` adds a trailing batch axis)."""
        return GaussianPSF(self.center[_batch_index(idx, 1)], self.cov[_batch_index(idx, 2)], self.amplitude[idx])

    def to(self, *args, **kwargs) -> "GaussianPSF":
        return GaussianPSF(self.center.to(*args, **kwargs), self.cov.to(*args, **kwargs), self.amplitude.to(*args, **kwargs))

    def __repr__(self) -> str:
        return f"GaussianPSF(shape={tuple(self.shape)}, dtype={self.center.dtype})"


class KernelPSF:
    """A measured kernel: an image of the still spot, used through Proposition 1.

    The rendered image is the kernel shifted by the motion (as a band-limited image, in
    Fourier space) and integrated over the exposure. The kernel is normalised to intensity
    per second: ``kernel = image / exposure_s``. Subtract the dark level first.

    Args:
        image: the still spot in the frame the renderer produces, ``[..., H, W]`` (its rest
            position is wherever the spot sits in that image).
        exposure_s: the exposure of ``image`` in seconds, ``[...]`` (> 0); default 1, i.e.
            ``image`` is already per second.
    """

    __slots__ = ("kernel",)

    def __init__(self, image, exposure_s=1.0):
        image = as_tensor(image, "image")
        if image.dim() < 2 or image.shape[-1] < 1 or image.shape[-2] < 1:
            raise ShapeError(f"image: expected shape [..., H, W] with H, W >= 1, got {tuple(image.shape)}")
        check_finite(image, "image")
        total = image.detach().sum((-1, -2))
        if image.numel() and bool((total <= 0).any()):
            raise ParameterError(f"image: expected a still spot with positive total light (dark level subtracted), "
                                 f"got a total of {float(total.min()):g}")
        exposure = check_positive(as_tensor(exposure_s, "exposure_s", like=image), "exposure_s")
        broadcast_batch({"image": image.shape[:-2], "exposure_s": exposure.shape})
        self.kernel = image / exposure[..., None, None]

    @property
    def shape(self) -> torch.Size:
        """Batch shape ``[...]``."""
        return self.kernel.shape[:-2]

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(H, W)`` of the kernel image."""
        return tuple(self.kernel.shape[-2:])

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Centroid ``[..., 2]`` (x, y px) and covariance ``[..., 2, 2]`` (px^2) of the kernel's
        positive part (no gradient)."""
        k = self.kernel.detach().clamp_min(0)
        H, W = k.shape[-2:]
        y = torch.arange(H, dtype=k.dtype, device=k.device)[:, None]
        x = torch.arange(W, dtype=k.dtype, device=k.device)[None, :]
        m0 = k.sum((-1, -2)).clamp_min(torch.finfo(k.dtype).tiny)
        cx = (k * x).sum((-1, -2)) / m0
        cy = (k * y).sum((-1, -2)) / m0
        dx = x - cx[..., None, None]
        dy = y - cy[..., None, None]
        sxx = (k * dx * dx).sum((-1, -2)) / m0
        syy = (k * dy * dy).sum((-1, -2)) / m0
        sxy = (k * dx * dy).sum((-1, -2)) / m0
        cov = torch.stack([torch.stack([sxx, sxy], -1), torch.stack([sxy, syy], -1)], -2)
        return torch.stack([cx, cy], -1), cov

    def footprint(self, sigmas: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The box that holds the spot, ``(lo, hi)``, each ``[..., 2]`` (x, y px, no gradient):
        the first and last column and row where the kernel is not zero, its faint wings included
        (``sigmas``, :meth:`GaussianPSF.footprint`'s width, is not used; 0 and the last pixel
        where a kernel is zero everywhere)."""
        nz = self.kernel.detach() != 0
        out = []
        for lines in (nz.any(-2), nz.any(-1)):  # [..., W] columns, [..., H] rows
            idx = torch.arange(lines.shape[-1], device=nz.device, dtype=self.kernel.dtype)
            first = torch.where(lines, idx, torch.full_like(idx, math.inf)).amin(-1)
            last = torch.where(lines, idx, torch.full_like(idx, -math.inf)).amax(-1)
            out.append((torch.where(lines.any(-1), first, idx[0]), torch.where(lines.any(-1), last, idx[-1])))
        return torch.stack([out[0][0], out[1][0]], -1), torch.stack([out[0][1], out[1][1]], -1)

    def cropped(self, x0: int, y0: int, x1: int, y1: int) -> "KernelPSF":
        """The spot in the frame of the crop ``[y0:y1, x0:x1]`` (px) of its frame: the kernel cut
        with it, ``[..., y1 - y0, x1 - x0]`` (as :meth:`GaussianPSF.cropped`)."""
        return KernelPSF(self.kernel[..., y0:y1, x0:x1])

    def sigma_min(self) -> torch.Tensor:
        """Smallest principal standard deviation of the kernel (px), ``[...]``."""
        _, cov = self.moments()
        return torch.linalg.eigvalsh(cov).clamp_min(1e-6)[..., 0].sqrt()

    def total_light(self) -> torch.Tensor:
        """Light per second, the kernel's sum over its pixels, ``[...]``."""
        return self.kernel.sum((-1, -2))

    def __getitem__(self, idx) -> "KernelPSF":
        """Items ``idx`` of the batch ``[...]``, as :meth:`GaussianPSF.__getitem__`."""
        return KernelPSF(self.kernel[_batch_index(idx, 2)])

    def to(self, *args, **kwargs) -> "KernelPSF":
        return KernelPSF(self.kernel.to(*args, **kwargs))

    def __repr__(self) -> str:
        return f"KernelPSF(shape={tuple(self.shape)}, frame={self.frame_shape}, dtype={self.kernel.dtype})"
