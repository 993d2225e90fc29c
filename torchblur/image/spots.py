"""Many spots in one frame: a Shack-Hartmann wavefront sensor behind a deformable mirror.

Model (what :class:`SpotGrid` describes and the simulated rig renders). The sensor sees
``K`` spots on a grid of ``rows x cols`` lenslets, ``pitch_px`` apart. Spot ``k`` has

- a rest position ``rest_px[k]`` (x, y px) on the grid;
- its own PSF, a Gaussian of covariance ``cov[k]`` (px^2): lenslets far from the optical
  axis give wider and elongated (tilted) spots;
- its own response: the image motion of spot k is ``d_k(t) = G_k @ y(t)`` with ``y(t)`` the
  ``O`` plant outputs (a tip-tilt mirror: O = 2, output x and y) and ``G_k`` ``[2, O]`` its
  own matrix (px per output unit). So spots move by different amounts and in different
  directions for the same mirror motion; spot k's measured frequency response is
  ``G_k @ H(j omega)``, ``[2, I]`` (image x and y from each input).

:class:`SpotGrid` makes these vary smoothly across the grid (normalised coordinates
``u = (col - (cols-1)/2) / max(1, (cols-1)/2)``, ``v`` likewise for rows, ``rho =
hypot(u, v) / sqrt(2)`` (0 at the centre, 1 at a corner of a square grid)):

    sigma_k = sigma_px (1 + sigma_variation rho)
    cov_k   = ellipse of axes sigma_k (1 + elongation rho), sigma_k / (1 + elongation rho),
              major axis along the radial direction atan2(v, u)
    G_k     = (1 + gain_variation u) R(rotation_rad v)          (R a 2x2 rotation)

The identification pipeline (:func:`torchblur.identify.run.identify` with a ``spots`` config)
finds the spots in the still frame (:func:`locate_spots`, kornia connected components via
:func:`torchblur.image.detection.find_spots`), fits a PSF per spot on a crop (one batched
:func:`~torchblur.image.psf_fit.fit_gaussian_psf`), crops every sweep frame per spot
(:func:`crop_spots`) and fits all (point x spot) problems in one batch with ``axes="xy"``.

Conventions as everywhere: x = column, y = row, px and px^2, ``K`` spots. Not imported by
``import torchblur`` (it needs kornia through :mod:`torchblur.image.detection`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor, check_finite, check_int, check_real_scalar
from torchblur.image.detection import crop, find_spots
from torchblur.image.psf_fit import fit_gaussian_psf, point_sampled_equivalent
from torchblur.render.psf import GaussianPSF

__all__ = ["SpotGrid", "SpotLayout", "SpotPSFs", "locate_spots", "crop_spots", "crop_valid", "raster_order", "spot_labels"]


@dataclass
class SpotLayout:
    """Where the spots are, what they look like and how they move (``K`` present spots).

    Attributes:
        rest_px: ``[K, 2]`` rest positions (x, y px).
        cov: ``[K, 2, 2]`` PSF covariances (px^2).
        response: ``[K, 2, O]``: ``response[k] = G_k``, image motion (x, y px) of spot k per
            unit of each plant output.
        index: ``[K]`` long, the row-major grid index of each spot (absent spots skipped).
    """

    rest_px: torch.Tensor
    cov: torch.Tensor
    response: torch.Tensor
    index: torch.Tensor

    def __len__(self) -> int:
        return int(self.rest_px.shape[0])


@dataclass(frozen=True)
class SpotGrid:
    """A grid of spots (module docstring: the model).

    Args:
        rows, cols: grid size (>= 1).
        pitch_px: distance between neighbouring spots (px, > 0).
        center_px: (x, y) of the grid centre; None: the frame centre.
        sigma_px: PSF std at the grid centre (px, > 0).
        sigma_variation: relative growth of the PSF std from the centre to a corner (>= 0).
        elongation: axis ratio - 1 of the elliptical PSF at a corner, along the radial
            direction (>= 0; 0 = round spots).
        gain_variation: the spot's motion gain is ``1 + gain_variation u`` (u in [-1, 1]
            across the columns); |gain_variation| < 1.
        rotation_rad: the spot's motion is rotated by ``rotation_rad v`` (v in [-1, 1] down
            the rows).
        missing: row-major indices of absent spots (a dead lenslet).
    """

    rows: int
    cols: int
    pitch_px: float
    center_px: tuple | None = None
    sigma_px: float = 2.0
    sigma_variation: float = 0.0
    elongation: float = 0.0
    gain_variation: float = 0.0
    rotation_rad: float = 0.0
    missing: tuple = field(default_factory=tuple)

    def __post_init__(self):
        check_int(self.rows, "rows", low=1)
        check_int(self.cols, "cols", low=1)
        check_real_scalar(self.pitch_px, "pitch_px", positive=True)
        check_real_scalar(self.sigma_px, "sigma_px", positive=True)
        check_real_scalar(self.sigma_variation, "sigma_variation", nonnegative=True)
        check_real_scalar(self.elongation, "elongation", nonnegative=True)
        if abs(check_real_scalar(self.gain_variation, "gain_variation")) >= 1:
            raise ParameterError(f"gain_variation: expected a value in (-1, 1), got {self.gain_variation!r}")
        check_real_scalar(self.rotation_rad, "rotation_rad")
        if self.center_px is not None and (not hasattr(self.center_px, "__len__") or len(self.center_px) != 2):
            raise ShapeError(f"center_px: expected (x, y) or None, got {self.center_px!r}")
        miss = tuple(int(m) for m in self.missing)
        for m in miss:
            if not 0 <= m < self.rows * self.cols:
                raise ParameterError(f"missing: expected grid indices in [0, {self.rows * self.cols}), got {m}")
        if len(set(miss)) == self.rows * self.cols:
            raise ParameterError("missing: every spot of the grid is missing")
        object.__setattr__(self, "missing", miss)

    @property
    def n_spots(self) -> int:
        """Spots present (grid size minus the missing ones)."""
        return self.rows * self.cols - len(set(self.missing))

    def layout(self, frame_shape, n_outputs: int = 2, *, dtype=torch.float64) -> SpotLayout:
        """The :class:`SpotLayout` on a frame of ``frame_shape = (H, W)`` for a plant with
        ``n_outputs`` (1 or 2) outputs."""
        H, W = (int(v) for v in frame_shape)
        if n_outputs not in (1, 2):
            raise ParameterError(f"n_outputs: expected 1 or 2 plant outputs, got {n_outputs!r}")
        cx, cy = ((W - 1) / 2, (H - 1) / 2) if self.center_px is None else (float(self.center_px[0]), float(self.center_px[1]))
        r, c = torch.meshgrid(torch.arange(self.rows, dtype=dtype), torch.arange(self.cols, dtype=dtype), indexing="ij")
        gu = (c - (self.cols - 1) / 2).reshape(-1)  # in pitches
        gv = (r - (self.rows - 1) / 2).reshape(-1)
        u = gu / max(1.0, (self.cols - 1) / 2)
        v = gv / max(1.0, (self.rows - 1) / 2)
        rho = torch.hypot(u, v) / math.sqrt(2)
        rest = torch.stack([cx + self.pitch_px * gu, cy + self.pitch_px * gv], -1)
        sigma = self.sigma_px * (1 + self.sigma_variation * rho)
        e = 1 + self.elongation * rho
        angle = torch.atan2(v, u)
        cov = GaussianPSF.from_axes(rest, sigma * e, sigma / e, angle).cov
        gain = 1 + self.gain_variation * u
        th = self.rotation_rad * v
        rot = torch.stack([torch.stack([th.cos(), -th.sin()], -1), torch.stack([th.sin(), th.cos()], -1)], -2)
        response = (gain[:, None, None] * rot)[..., :n_outputs]
        keep = torch.ones(self.rows * self.cols, dtype=torch.bool)
        if self.missing:
            keep[list(self.missing)] = False
        idx = torch.nonzero(keep).reshape(-1)
        return SpotLayout(rest_px=rest[idx], cov=cov[idx].contiguous(), response=response[idx].contiguous(), index=idx)


def spot_labels(n_spots: int) -> list[str]:
    """Output labels of a K-spot frequency response: ``["s0.x", "s0.y", "s1.x", ...]``."""
    return [f"s{k}.{a}" for k in range(n_spots) for a in ("x", "y")]


def raster_order(centroid: torch.Tensor, pitch_px: float) -> torch.Tensor:
    """Indices that sort spots ``[K, 2]`` (x, y px) row by row (top to bottom), left to right
    within a row; spots whose y differ by less than ``pitch_px / 2`` share a row."""
    centroid = as_tensor(centroid, "centroid")
    if centroid.dim() != 2 or centroid.shape[-1] != 2:
        raise ShapeError(f"centroid: expected shape [K, 2], got {tuple(centroid.shape)}")
    K = centroid.shape[0]
    if K == 0:
        return torch.zeros(0, dtype=torch.long)
    by_y = torch.argsort(centroid[:, 1], stable=True)
    row = torch.zeros(K, dtype=torch.long)
    ys = centroid[by_y, 1]
    r, start = 0, float(ys[0])
    for n in range(K):
        if float(ys[n]) - start > pitch_px / 2:
            r, start = r + 1, float(ys[n])
        row[by_y[n]] = r
    key = row.to(centroid.dtype) * (4 * float(centroid[:, 0].abs().max()) + 4 * pitch_px + 1) + centroid[:, 0]
    return torch.argsort(key, stable=True)


@dataclass
class SpotPSFs:
    """What :func:`locate_spots` found, ``K`` spots in raster order.

    Attributes:
        psf: :class:`~torchblur.render.psf.GaussianPSF` ``[K]`` in full-frame coordinates
            (amplitude per second of exposure).
        offset: ``[K, 2]`` long, (x0, y0) of each spot's crop: crop pixel (i, j) is frame
            pixel (y0 + i, x0 + j). Crops are centred on their spot; a spot at the edge gets
            a crop that extends beyond the frame (those pixels are zero and masked out).
        size: ``(h, w)`` of the crops (px).
        fit: the batched :class:`~torchblur.image.psf_fit.PSFFit` (crop coordinates).
        clipped: ``[K]`` bool: the crop extends beyond the frame.
        inside_fraction: ``[K]`` the fraction of the spot's (fitted) light that falls in the
            frame (1 for a spot well inside).
    """

    psf: GaussianPSF
    offset: torch.Tensor
    size: tuple
    fit: object
    clipped: torch.Tensor
    inside_fraction: torch.Tensor

    def __len__(self) -> int:
        return int(self.offset.shape[0])

    def psf_in_crops(self) -> GaussianPSF:
        """The PSFs ``[K]`` in crop coordinates."""
        return GaussianPSF(self.psf.center - self.offset.to(self.psf.center.dtype), self.psf.cov, self.psf.amplitude)


def locate_spots(still, *, exposure_s: float, noise_std, pitch_px: float, crop_px: int | None = None,
                 max_spots: int | None = None, mask=None) -> SpotPSFs:
    """Find the spots of a still frame and fit a Gaussian PSF to each (one batch).

    Spots are found with :func:`torchblur.image.detection.find_spots` (kornia connected
    components), put in raster order, cropped (``crop_px`` square, centred on each spot's
    centroid; pixels beyond the frame are masked out) and fitted with one batched
    :func:`torchblur.image.psf_fit.fit_gaussian_psf`, integrated over the pixels as a camera's
    pixels integrate the light; the PSF returned is its point-sampled moment match
    (:func:`~torchblur.image.psf_fit.point_sampled_equivalent`), the model the blur fits use.

    Args:
        still: dark-subtracted still image ``[H, W]`` (the mean of still frames).
        exposure_s: its exposure (s).
        noise_std: pixel noise std of ``still`` (a number): the detection threshold and the
            fit's weights.
        pitch_px: the grid pitch (px): rows of the raster order and the default crop.
        crop_px: crop side (px); default ``floor(pitch_px)`` (at most the frame).
        max_spots: keep at most this many (the brightest).
        mask: bool ``[H, W]`` of usable pixels (False: saturated or hot), or None.

    Returns:
        :class:`SpotPSFs` in raster order (row by row, left to right).

    Raises:
        ParameterError: no spot found.
    """
    still = as_tensor(still, "still")
    if still.dim() != 2:
        raise ShapeError(f"still: expected shape [H, W], got {tuple(still.shape)}")
    check_finite(still, "still")
    pitch_px = check_real_scalar(pitch_px, "pitch_px", positive=True)
    H, W = still.shape
    side = int(math.floor(pitch_px)) if crop_px is None else check_int(crop_px, "crop_px", low=8)
    size = (min(side, H), min(side, W))
    found = find_spots(still, noise_std=noise_std, max_spots=max_spots)[0]
    if len(found) == 0:
        raise ParameterError("still: no spot found above the noise (is the laser on, is noise_std right?)")
    order = raster_order(found.centroid, pitch_px)
    centroid = found.centroid[order]
    half = (torch.tensor(size[::-1], dtype=centroid.dtype) - 1) / 2
    for _ in range(2):  # a second pass only without the duplicates the first found
        offset = torch.floor(centroid - half + 0.5).long()
        crops = crop_spots(still, offset, size)  # [K, h, w]
        valid = crop_valid((H, W), offset, size)
        clipped = ~valid.all(-1).all(-1)
        m = valid
        if mask is not None:
            m = m & crop_spots(mask.to(still.dtype), offset, size).gt(0.5)
        # the pixels integrate the spot: fit that, then hand the point-sampled fitter the moment match
        fit = fit_gaussian_psf(crops, exposure_s=exposure_s, noise_std=noise_std, mask=m, pixel_integration=True)
        fitted = point_sampled_equivalent(fit.psf)
        psf = GaussianPSF(fitted.center + offset.to(still.dtype), fitted.cov, fitted.amplitude)
        keep = _distinct_spots(psf.center.detach(), psf.total_light().detach(), pitch_px)
        if bool(keep.all()):
            break
        centroid = centroid[keep]
    light = (fit.model - fit.background[:, None, None]).clamp_min(0)
    inside = (light * valid).sum((-1, -2)) / light.sum((-1, -2)).clamp_min(torch.finfo(light.dtype).tiny)
    return SpotPSFs(psf=psf, offset=offset, size=size, fit=fit, clipped=clipped, inside_fraction=inside)


def _distinct_spots(center: torch.Tensor, light: torch.Tensor, pitch_px: float) -> torch.Tensor:
    """``keep [K]`` bool: False for a spot whose fitted centre ``center [K, 2]`` (px) lies within
    half a pitch of a brighter one's (``light [K]``; ties: the first kept). One spot found twice
    (a detached lobe of an aberrated diffraction spot is its own connected component, and its
    crop's fit converges on the spot beside it: HCIPy 3x3 grid, ``benchmarks/bench_hcipy_routes.py``
    seed 1035) is then fitted once; two grid spots are never that close."""
    K = center.shape[0]
    close = torch.cdist(center, center) < pitch_px / 2
    idx = torch.arange(K, device=center.device)
    better = (light[None, :] > light[:, None]) | ((light[None, :] == light[:, None]) & (idx[None, :] < idx[:, None]))
    return ~(close & better & (idx[None, :] != idx[:, None])).any(-1)


def _pad_for(offset: torch.Tensor, size, frame_shape) -> int:
    H, W = frame_shape
    h, w = size
    lo = int(-offset.min()) if offset.numel() else 0
    hi = max(int((offset[:, 0] + w - W).max()), int((offset[:, 1] + h - H).max())) if offset.numel() else 0
    return max(0, lo, hi)


def crop_spots(frames, offset, size) -> torch.Tensor:
    """Every frame cropped at every spot's crop: ``[..., H, W]`` -> ``[..., K, h, w]``, with
    zeros where a crop extends beyond the frame (see :func:`crop_valid`).

    Args:
        frames: ``[..., H, W]`` (float, or bool: False beyond the frame).
        offset: ``[K, 2]`` long crop corners (x0, y0) (from :func:`locate_spots`).
        size: ``(h, w)``.
    """
    if not isinstance(offset, torch.Tensor) or offset.dim() != 2 or offset.shape[-1] != 2:
        raise ShapeError(f"offset: expected a tensor [K, 2] (x0, y0), got {getattr(offset, 'shape', offset)!r}")
    h, w = size
    is_bool = frames.dtype == torch.bool
    x = frames.to(torch.float64) if is_bool else frames
    pad = _pad_for(offset, size, frames.shape[-2:])
    if pad:
        x = torch.nn.functional.pad(x.reshape((-1,) + tuple(x.shape[-2:])), (pad, pad, pad, pad)).reshape(
            tuple(x.shape[:-2]) + (x.shape[-2] + 2 * pad, x.shape[-1] + 2 * pad))
    dtype = x.dtype
    centre = (offset + pad).to(dtype) + torch.tensor([(w - 1) / 2, (h - 1) / 2], dtype=dtype)  # crop() puts x0 back at offset
    out, _ = crop(x[..., None, :, :], centre, (h, w))
    return out > 0.5 if is_bool else out


def crop_valid(frame_shape, offset, size) -> torch.Tensor:
    """``[K, h, w]`` bool: True where the crop's pixel lies in the frame."""
    H, W = frame_shape
    h, w = size
    ys = offset[:, 1, None] + torch.arange(h)
    xs = offset[:, 0, None] + torch.arange(w)
    return ((ys >= 0) & (ys < H))[:, :, None] & ((xs >= 0) & (xs < W))[:, None, :]
