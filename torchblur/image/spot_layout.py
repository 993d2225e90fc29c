"""Spots found on a sensor's known layout (issue 23): a Shack-Hartmann sensor declares where its
subapertures are, so its spots are cropped there instead of found by thresholding the frame.

Thresholding fails on real lenslet spots: the sinc^2 wings and the crosstalk between lenslets
leave a floor of ~1 % of a spot's peak between spots, and any threshold low enough for the dim,
partly lit edge subapertures joins all spots into one connected component.

Model. The declared rest positions ``rest_px [M, 2]`` (x, y px) map to the frame by a similarity
about the frame centre ``c0 = ((W - 1) / 2, (H - 1) / 2)``:

    p_k = c0 + scale R(rotation) (rest_k - c0) + offset

The registration (:func:`register_layout`) maximises the correlation of the still frame (its
floor, the median, removed) with the predicted grid, ``sum_k g_k . still`` with ``g_k`` a
Gaussian of std ``sigma_px`` at ``p_k`` (separable: one ``[K, H] x [H, W] x [W, K]`` product):
first on a grid of rotations and scales (the offset of each from an FFT cross-correlation, whole
pixels), then Nelder-Mead on the four parameters from the best. Every spot's centre is then its
own centroid in a window of half-side ``pitch_px / 2`` around its prediction, then twice in
one of ``pitch_px / 4`` around the last centroid, above the window's floor (its lowest quartile): robust to the floor and to partly
lit edge subapertures. A spot with less than :data:`DARK_FRACTION` of the median spot's light
is flagged ``dark``, one whose centroid leaves its cell ``off_cell``, one whose light in its cell
(above the floor) has an rms radius beyond :data:`SPREAD_FRACTION` of the pitch ``not_compact``
(a ring, two spots in one cell): these keep the predicted position and are not fitted (a
Gaussian fit of such a crop wanders for its 100 iterations). Flagged by name, never raised.

:func:`layout_spots` crops every declared spot there and fits its Gaussian PSF
(:func:`~torchblur.image.psf_fit.fit_gaussian_psf`, one batch): a
:class:`~torchblur.image.spots.SpotPSFs` in the declared order, plus the per-spot flags
(``not_gaussian``: the fit did not converge or leaves a residual above
:data:`POOR_RESIDUAL` of its peak; ``no_light``: the fitted amplitude is 0). Conventions: x =
column, y = row, px; ``M`` declared spots.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import minimize

from torchblur.errors import ShapeError, as_tensor, check_finite, check_real_scalar
from torchblur.image.psf_fit import PSFFit, fit_gaussian_psf, point_sampled_equivalent
from torchblur.image.spots import SpotPSFs, crop_spots, crop_valid
from torchblur.render.psf import GaussianPSF

__all__ = ["DARK_FRACTION", "POOR_RESIDUAL", "SPREAD_FRACTION", "LayoutRegistration", "layout_spots", "predict_layout", "register_layout"]

DARK_FRACTION = 0.05  #: a spot with less light than this fraction of the median spot's is flagged dark
SPREAD_FRACTION = 0.25  #: a spot whose light's rms radius in its cell exceeds this fraction of the pitch is flagged
POOR_RESIDUAL = 0.05  #: a Gaussian fit whose residual rms exceeds this fraction of its peak is flagged


@dataclass(frozen=True)
class LayoutRegistration:
    """The layout registered to a still frame (module docstring).

    Attributes:
        offset_px: ``(x, y)`` px; rotation_rad; scale: the similarity.
        predicted_px: ``[M, 2]`` the declared positions mapped to the frame.
        center_px: ``[M, 2]`` every spot's refined centre (the prediction where flagged).
        light: ``[M]`` each spot's light above its cell's floor (image units).
        status: ``[M]`` ``"ok"``, ``"dark"``, ``"off_cell"`` or ``"not_compact"``.
        radius: ``[M]`` rms radius of each spot's light in its cell (px).
        score: the normalised correlation of the frame with the registered grid.
    """

    offset_px: tuple
    rotation_rad: float
    scale: float
    predicted_px: np.ndarray
    center_px: np.ndarray
    light: np.ndarray
    status: list
    radius: np.ndarray
    score: float

    def describe(self) -> str:
        bad = {s: [k for k, v in enumerate(self.status) if v == s] for s in ("dark", "off_cell", "not_compact")}
        flags = "; ".join(f"{s}: {', '.join(f's{k}' for k in ks)}" for s, ks in bad.items() if ks)
        return (f"layout registered: offset ({self.offset_px[0]:+.2f}, {self.offset_px[1]:+.2f}) px, rotation "
                f"{math.degrees(self.rotation_rad):+.3f} deg, scale {self.scale:.4f}, correlation {self.score:.3f}; "
                f"{self.status.count('ok')} of {len(self.status)} spots centred in their cells" + (f" ({flags})" if flags else ""))


def predict_layout(rest_px, frame_shape, offset_px=(0.0, 0.0), rotation_rad: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """``[M, 2]`` the declared rest positions ``rest_px [M, 2]`` mapped by the similarity of the
    module docstring on a frame of ``frame_shape = (H, W)``."""
    H, W = frame_shape
    c0 = np.array([(W - 1) / 2, (H - 1) / 2])
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    R = np.array([[c, -s], [s, c]])
    return c0 + scale * (np.asarray(rest_px, dtype=float) - c0) @ R.T + np.asarray(offset_px, dtype=float)


def _patches(p, sigma):
    """Every predicted spot's Gaussian on its own window: ``(rows [K, n, 1], cols [K, 1, n],
    values [K, n, n])`` with ``n = 2 ceil(4 sigma) + 1`` (beyond 4 sigma the template is < 3.4e-4)."""
    r = int(math.ceil(4 * sigma))
    base = np.floor(p).astype(int) - r  # [K, 2] window corner (x, y)
    idx = np.arange(2 * r + 2)
    xs, ys = base[:, 0, None] + idx, base[:, 1, None] + idx  # [K, n]
    gx = np.exp(-0.5 * ((xs - p[:, 0, None]) / sigma) ** 2)
    gy = np.exp(-0.5 * ((ys - p[:, 1, None]) / sigma) ** 2)
    return ys[:, :, None], xs[:, None, :], gy[:, :, None] * gx[:, None, :]


def _score(img, p, sigma) -> float:
    """The correlation of ``img`` (zero beyond the frame) with the template of the spots at ``p``."""
    H, W = img.shape
    ys, xs, v = _patches(p, sigma)
    inside = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
    return float((img[ys.clip(0, H - 1), xs.clip(0, W - 1)] * v * inside).sum())


def _template(shape, p, sigma) -> np.ndarray:
    H, W = shape
    ys, xs, v = _patches(p, sigma)
    ys, xs = np.broadcast_arrays(ys, xs)
    keep = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
    out = np.zeros(shape)
    np.add.at(out, (ys[keep], xs[keep]), v[keep])
    return out


def _best_offset(img_f, shape, p, sigma, max_offset: float):
    """Whole-pixel offset (x, y) within +-max_offset that maximises the correlation, and its value."""
    H, W = shape
    t = _template((2 * H, 2 * W), p, sigma)
    corr = np.fft.irfft2(img_f * np.conj(np.fft.rfft2(t)), s=(2 * H, 2 * W))
    r = int(math.floor(max_offset))
    dy = np.r_[0:r + 1, -r:0] % (2 * H)
    dx = np.r_[0:r + 1, -r:0] % (2 * W)
    sub = corr[np.ix_(dy, dx)]
    i, j = np.unravel_index(int(np.argmax(sub)), sub.shape)
    oy = int(dy[i]) if dy[i] <= r else int(dy[i]) - 2 * H
    ox = int(dx[j]) if dx[j] <= r else int(dx[j]) - 2 * W
    return (float(ox), float(oy)), float(sub[i, j])


def _search(img, rest, sigma, max_offset, max_rotation, max_scale):
    """Grid of rotations and scales, FFT offsets, then Nelder-Mead: ``(offset, rotation, scale)``."""
    H, W = img.shape
    pad = np.zeros((2 * H, 2 * W))
    pad[:H, :W] = img
    img_f = np.fft.rfft2(pad)
    best = (-np.inf, (0.0, 0.0), 0.0, 1.0)
    for rot in np.linspace(-max_rotation, max_rotation, 2 * max(1, round(max_rotation / math.radians(0.5))) + 1):
        for sc in np.linspace(1 - max_scale, 1 + max_scale, 2 * max(1, round(max_scale / 0.01)) + 1):
            off, val = _best_offset(img_f, (H, W), predict_layout(rest, (H, W), (0.0, 0.0), rot, sc), sigma, max_offset)
            if val > best[0]:
                best = (val, off, rot, sc)
    x0 = np.array([best[1][0], best[1][1], best[2], best[3]])
    res = minimize(lambda v: -_score(img, predict_layout(rest, (H, W), v[:2], v[2], v[3]), sigma), x0, method="Nelder-Mead",
                   options={"xatol": 1e-4, "fatol": 1e-10 * abs(best[0]) + 1e-300, "initial_simplex": x0 + np.vstack(
                       [np.zeros(4), np.diag([0.5, 0.5, math.radians(0.1), 0.002])]), "maxiter": 400})
    v = res.x if -res.fun >= best[0] else x0
    return (float(v[0]), float(v[1])), float(v[2]), float(v[3])


def _refine(img, pred, half: float):
    """Centroids ``[M, 2]`` in windows about ``pred``, each above its window's lowest quartile,
    the light ``[M]`` above that floor and the rms radius ``[M]`` of that light (px), from the
    first pass: three passes, of half-side ``half`` then ``half / 2`` twice (a narrower window
    sees less of the neighbours' wings)."""
    H, W = img.shape
    cen = pred.copy()
    light, radius = np.zeros(len(pred)), np.full(len(pred), np.inf)
    for i, hw in enumerate((half, half / 2, half / 2)):
        for k, (x, y) in enumerate(cen):
            x0, x1 = max(0, int(math.floor(x - hw))), min(W, int(math.ceil(x + hw)) + 1)
            y0, y1 = max(0, int(math.floor(y - hw))), min(H, int(math.ceil(y + hw)) + 1)
            win = img[y0:y1, x0:x1]
            if win.size == 0:
                continue
            v = (win - np.quantile(win, 0.25)).clip(0)
            light[k] = v.sum()
            if light[k] > 0:
                xs, ys = np.arange(x0, x1), np.arange(y0, y1)
                c = np.array([(v.sum(0) * xs).sum(), (v.sum(1) * ys).sum()]) / light[k]
                if i == 0:
                    radius[k] = math.sqrt((v.sum(0) * (xs - c[0]) ** 2).sum() / light[k] + (v.sum(1) * (ys - c[1]) ** 2).sum() / light[k])
                cen[k] = c
    return cen, light, radius


def register_layout(still, rest_px, *, pitch_px: float, sigma_px: float = 1.5, max_offset_px: float | None = None,
                    max_rotation_deg: float = 2.0, max_scale: float = 0.03) -> LayoutRegistration:
    """Register the declared layout ``rest_px [M, 2]`` to a dark-subtracted still frame
    ``still [H, W]`` and centre every spot in its cell (module docstring).

    Args:
        still: ``[H, W]`` the mean still frame (dark subtracted).
        rest_px: ``[M, 2]`` declared rest positions (x, y px).
        pitch_px: the spot spacing (px): the refinement window and the default offset range.
        sigma_px: the template's Gaussian std (px).
        max_offset_px: the offset searched, +- (default ``pitch_px / 2``).
        max_rotation_deg, max_scale: the rotation (+- deg) and relative scale (+-) searched.

    Raises:
        ShapeError: ``still`` not [H, W] or ``rest_px`` not [M, 2]; ParameterError: non-finite
        values or non-positive sizes. Data never raises: flagged spots are named in ``status``.
    """
    img = check_finite(as_tensor(still, "still"), "still").detach().to(torch.float64).cpu().numpy()
    if img.ndim != 2:
        raise ShapeError(f"still: expected shape [H, W], got {img.shape}")
    rest = np.asarray(rest_px, dtype=float)
    if rest.ndim != 2 or rest.shape[1] != 2 or rest.shape[0] == 0:
        raise ShapeError(f"rest_px: expected shape [M, 2] (x, y px), got {rest.shape}")
    pitch = check_real_scalar(pitch_px, "pitch_px", positive=True)
    sigma = check_real_scalar(sigma_px, "sigma_px", positive=True)
    max_off = pitch / 2 if max_offset_px is None else check_real_scalar(max_offset_px, "max_offset_px", nonnegative=True)
    img = img - np.median(img)
    off, rot, sc = _search(img, rest, sigma, max_off, math.radians(max_rotation_deg), max_scale)
    pred = predict_layout(rest, img.shape, off, rot, sc)
    cen, light, radius = _refine(img, pred, pitch / 2)
    med = float(np.median(light)) if light.size else 0.0
    status = []
    for k in range(len(rest)):
        if not light[k] > DARK_FRACTION * med:
            status.append("dark")
        elif np.abs(cen[k] - pred[k]).max() > pitch / 4:
            status.append("off_cell")
        elif radius[k] > SPREAD_FRACTION * pitch:
            status.append("not_compact")
        else:
            status.append("ok")
    bad = np.array([s != "ok" for s in status])
    cen[bad] = pred[bad]
    t = _template(img.shape, pred, sigma)
    score = float((img * t).sum() / max(np.linalg.norm(img) * np.linalg.norm(t), 1e-300))
    return LayoutRegistration(offset_px=off, rotation_rad=rot, scale=sc, predicted_px=pred, center_px=cen, light=light, status=status, radius=radius,
                              score=score)


def layout_spots(still, *, exposure_s: float, noise_std, rest_px, pitch_px: float, sigma_px: float = 1.5, crop_px: int | None = None,
                 mask=None):
    """The declared spots of a still frame, registered and fitted: ``(SpotPSFs, registration,
    flags)`` (module docstring). ``still``, ``exposure_s``, ``noise_std``, ``pitch_px``,
    ``crop_px`` and ``mask`` as :func:`~torchblur.image.spots.locate_spots`; ``rest_px [M, 2]``
    the declared rest positions. ``flags [M]``: the registration's status where it is not ``ok``,
    else the fit's (``ok``, ``not_gaussian``, ``no_light``). Spots in the declared order."""
    still = check_finite(as_tensor(still, "still"), "still")
    reg = register_layout(still, rest_px, pitch_px=pitch_px, sigma_px=sigma_px)
    H, W = still.shape
    side = int(math.floor(pitch_px)) if crop_px is None else int(crop_px)
    size = (min(side, H), min(side, W))
    centre = torch.as_tensor(reg.center_px, dtype=still.dtype)
    half = (torch.tensor(size[::-1], dtype=still.dtype) - 1) / 2
    offset = torch.floor(centre - half + 0.5).long()
    crops = crop_spots(still, offset, size)
    valid = crop_valid((H, W), offset, size)
    m = valid if mask is None else valid & crop_spots(mask.to(still.dtype), offset, size).gt(0.5)
    fit = _fit_registered(crops, m, [s == "ok" for s in reg.status], exposure_s, noise_std, sigma_px, size)
    fitted = point_sampled_equivalent(fit.psf)
    psf = GaussianPSF(fitted.center + offset.to(still.dtype), fitted.cov, fitted.amplitude)
    light = (fit.model - fit.background[..., None, None]).clamp_min(0)
    inside = (light * valid).sum((-1, -2)) / light.sum((-1, -2)).clamp_min(torch.finfo(light.dtype).tiny)
    flags = []
    for k, s in enumerate(reg.status):
        if s != "ok":
            flags.append(s)
        elif not float(fit.psf.amplitude[k]) > 0:
            flags.append("no_light")
        elif not bool(fit.converged[k]) or not float(fit.relative_residual[k]) <= POOR_RESIDUAL:
            flags.append("not_gaussian")
        else:
            flags.append("ok")
    spots = SpotPSFs(psf=psf, offset=offset, size=size, fit=fit, clipped=~valid.all(-1).all(-1), inside_fraction=inside)
    return spots, reg, flags


def _fit_registered(crops, mask, fit_it, exposure_s, noise_std, sigma_px, size):
    """:func:`~torchblur.image.psf_fit.fit_gaussian_psf` of the crops ``[M, h, w]`` whose spot the
    registration centred (``fit_it [M]``, one batch); the others (dark, off their cell) get a
    placeholder of no light: a round Gaussian of ``sigma_px`` at the crop centre, amplitude 0."""
    idx = torch.as_tensor(np.flatnonzero(fit_it), dtype=torch.long)
    M, dt = crops.shape[0], crops.dtype
    h, w = size
    nan = float("nan")
    centre = torch.tensor([(w - 1) / 2, (h - 1) / 2], dtype=dt).expand(M, 2).clone()
    cov = (sigma_px ** 2 * torch.eye(2, dtype=dt)).expand(M, 2, 2).clone()
    out = dict(amp=torch.zeros(M, dtype=dt), bg=torch.zeros(M, dtype=dt), rms=torch.full((M,), nan, dtype=dt),
               rel=torch.full((M,), nan, dtype=dt), cov_std=torch.full((M, 2, 2), nan, dtype=dt), c_std=torch.full((M, 2), nan, dtype=dt),
               a_std=torch.full((M,), nan, dtype=dt), conv=torch.zeros(M, dtype=torch.bool), model=torch.zeros_like(crops))
    if idx.numel():
        ns = noise_std[idx] if isinstance(noise_std, torch.Tensor) and noise_std.dim() > 0 and noise_std.shape[0] == M else noise_std
        f = fit_gaussian_psf(crops[idx], exposure_s=exposure_s, noise_std=ns, mask=mask[idx], pixel_integration=True)
        centre[idx], cov[idx], out["amp"][idx] = f.psf.center, f.psf.cov, f.psf.amplitude
        for key, v in (("bg", f.background), ("rms", f.residual_rms), ("rel", f.relative_residual), ("cov_std", f.cov_std),
                       ("c_std", f.center_std), ("a_std", f.amplitude_std), ("conv", f.converged), ("model", f.model)):
            out[key][idx] = v
    return PSFFit(psf=GaussianPSF(centre, cov, out["amp"]), background=out["bg"], residual_rms=out["rms"], relative_residual=out["rel"],
                  cov_std=out["cov_std"], center_std=out["c_std"], amplitude_std=out["a_std"], converged=out["conv"], model=out["model"])
