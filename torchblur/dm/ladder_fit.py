"""The DM spot fit on a *ladder*: each spot's image under a pattern from static frames of that
pattern held at a ladder of command levels (issue 23).

Under a Hadamard pattern the surface under a lenslet is curved, so a real (diffraction) spot
changes shape as it moves; a shifted still (:func:`~torchblur.dm.spot_fit.fit_spot_problems`)
reads the change as motion. Here the spot's crop at time ``t`` of problem (pattern ``p``,
frequency ``f``, spot ``m``) is

    power * sum_jk d(t)^j e(t)^k / (j! k!) Dn^j Ds^k L(v(t)),   k <= SHIFT_ORDER, j + k <= ORDER

- ``L(v)``: the static image (e-/s at laser power 1) of pattern ``p`` held at the scalar command
  ``v`` (every actuator ``j`` at ``v * pattern[j]``): a cubic spline in ``v`` per pixel through
  the ladder's levels (scipy's ``CubicSpline``, not-a-knot ends; beyond the ends its end cubics);
  ``Dn^j Ds^k L`` its derivatives along a shift of the image by ``n`` and by ``s`` (Fourier, of
  each level's image, splined the same way, the spline being linear in the knot values);
- ``v(t) = v_cos cos(w t) + v_sin sin(w t)``: the command the spot's SHAPE follows, and
  ``e(t) = e_cos cos(w t) + e_sin sin(w t)``: the command its position along ``s`` follows beyond
  it (the image moved by ``s e``, the Taylor series of a shift to :data:`SHIFT_ORDER`); the
  pattern's response along the ladder's path is the phasor ``G = V + E`` (``V = v_sin + i v_cos``,
  ``E`` alike). Where a pattern's actuators respond differently (above their modes) the
  curvature under a lenslet, which sets a spot's shape, follows another mix of actuators than its
  tilt, which sets its position: with the shape tied to the motion (``e = 0``, the former model)
  the fitted command was a compromise between the two and the motions came out pulled toward the
  pattern's common command (``benchmarks/bench_dm_spot_models.py --models former,fast``). Where a
  spot barely changes shape (Gaussian spots) ``v`` and ``e`` are one direction to the data: a prior
  ``e_cos, e_sin ~ N(0,`` :data:`SHAPE_PRIOR` ``x`` the ladder's largest level ``)`` (two
  pseudo-data rows) keeps the LM and the covariance regular, and the reported motion's
  covariance is marginal over it; the ladder's noise through ``s`` in ``Ds`` is left out (``e`` is small);
- ``d(t) = n_cos cos(w t) + n_sin sin(w t)``: a free motion (px) along ``n``, the unit normal of
  ``s`` (below), as the Taylor series of a shift to :data:`ORDER`. The actuators' differing
  dynamics move a spot off the ladder's path (near a resonance of the small simulated mirror by
  up to 1.2 px at 1.5 px of motion: to first order its responses were off by up to 15 stds; to
  fourth order a 1 px shift of a sigma-1.2 px spot is fitted within 0.06 %). (A free x and y
  motion to first order, without the prior, gave the spot motions a bias of +0.35 std, the DC
  gains 1 % high: along ``s`` it is the same image as a change of the command.)
- each exposure integrated by :data:`NODES` Gauss-Legendre nodes.

The model is linear in the ladder's images: an exposure is ``sum_bl c_bl(theta) (Dn^j Ds^k L_l)``, the coefficients
from the spline's basis at the nodes, so the image and its analytic Jacobian are one batched GEMM
per problem; :func:`~torchblur.optim.levenberg_marquardt` fits the six parameters. The reported
motion per axis is the phasor ``s G + N n`` (``N = n_sin + i n_cos``; ``s = (s_x, s_y)`` the spot's static shift per unit command: the slope at ``u = 0`` of the still's best shifts to the
levels' images, :func:`static_slope`, the convention of the fitted-shift truth), as amplitude and phase
with their covariance in :class:`~torchblur.dm.spot_fit.SpotFits`' order, so
:func:`~torchblur.dm.spot_fit.pattern_responses` turns it into ``Y`` unchanged.

Uncertainty: the data's part ``(J^T W J)^-1`` (with the noise given: unscaled, the reduced chi2
reported and :data:`~torchblur.fit.status.POOR_FIT_FLAG` above 1.5, as every fit here; without:
unweighted, the sandwich ``C J^T diag(r^2) J C`` of each pixel's residual, since shot noise
differs from pixel to pixel) plus the ladder's own noise, propagated to first
order through both the fit (``dtheta = -C J^T W dY/dL dL``, the implicit function theorem, as
:mod:`torchblur.fit.kernel_noise` does for a kernel) and ``s``, every ladder pixel independent
with its ``variance``. The still's noise (averaged over many more frames than a level) is left
out. The reduced chi2 weighs each pixel by the data's variance plus the model's from the ladder
(its ``L`` and ``Dn L`` terms: the higher orders' noise, as in the bias correction, is left out).

Starts: each fit from its spot's own centroids and, where they differ, from its pattern's pooled ones
(:func:`_starts`), the lower cost kept (:func:`_best_start`).

Shapes: P patterns, F frequencies, M spots, K levels, ``E*R`` exposures, ``h x w`` crop pixels;
positions and motions in px (x = column, y = row), times in s, ``omega`` rad/s.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.interpolate import CubicSpline

from torchblur.dm.spot_fit import SpotFits, chunk_size, left_out
from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_int, check_type
from torchblur.fit.status import (DARK, MASKED, NO_MOTION, NO_PIXELS, NOT_CONVERGED, OUT_OF_FRAME, OUT_OF_LADDER, SINGULAR,
                                  flag_poor_fit)
from torchblur.image.moments import image_moments
from torchblur.optim import levenberg_marquardt
from torchblur.render.blur import quadrature_nodes
from torchblur.render.splat import kernel_shift_with_jacobian
from torchblur.render.window import ExposureWindow

__all__ = ["PatternLadder", "fit_ladder_problems", "slope_covariance", "spline_basis", "static_slope", "with_slopes", "NODES"]

NODES = 96  #: Gauss-Legendre nodes per exposure (benchmarks/bench_dm_spot_models.py's; the spline is C2)
PAD = 6  #: px of zero padding around a crop for its Fourier shift derivatives
DARK_SNR = 5.0  #: a problem whose data correlate with its still below this many noise stds is DARK
MAX_ITER = 150  #: LM iterations at most (a spot that barely moves under its pattern crawled past 60 along v - e, then failed: NOT_CONVERGED)
N_PAR = 6  #: (v_cos, v_sin, n_cos, n_sin, e_cos, e_sin): the shape's command, the free motion across the static shift, the shift's command beyond the shape's
STEP_MAX = 6.0  #: std: a longer correction step is not taken
LEFT_MAX = 0.3  #: std: a fit whose Gauss-Newton step left is shorter has converged (the LM crawls along a curved valley)
BIAS_ITER = 3  #: Gauss-Newton steps on the bias-corrected cost after the fit (:func:`_bias_step`; 3 converge)
ORDER = 4  #: the free motion's Taylor order (:func:`_coefficients`)
SHIFT_ORDER = 2  #: the Taylor order of the shift ``s e`` (with ``d``'s: to :data:`ORDER` in all; :func:`_coefficients`)
PRIOR_ROWS = 2  #: the prior's pseudo-data rows after the pixels (:func:`_with_prior`)
SHAPE_PRIOR = 0.25  #: the prior std of ``e`` (each of ``e_cos, e_sin``), of the ladder's largest level
SECOND_START = 0.1  #: of the ladder's largest level: a pooled start farther than this from a spot's own is fitted too (:func:`_best_start`)


@dataclass(frozen=True)
class PatternLadder:
    """Static frames of each pattern at a ladder of command levels, cropped at the spots.

    Attributes:
        levels: ``[P, K]`` input units, increasing per row (``u``: every actuator at ``u * pattern[j]``), K >= 4.
        images: ``[P, K, M, h, w]`` e- per second at laser power 1 (dark subtracted, gain
            applied; the mean of the frames): ``images[p, k, m]`` = spot ``m``'s crop with pattern
            ``p`` held at ``levels[p, k]``.
        variance: ``[P, K, M, h, w]`` the variance of ``images`` ((e-/s)^2, of the mean).
        still: ``[M, h, w]`` the spots' still (``u = 0``), e-/s at power 1 (for ``s`` and the shift derivatives).
        slope, ds_dl: ``[P, M, 2]`` and ``[P, M, 2, K, h*w]``, :func:`static_slope` of every
            (pattern, spot), or None (each fit computes them): :func:`with_slopes` computes them
            once for every frequency of a run (they do not depend on the sweep's frames).
    """

    levels: torch.Tensor
    images: torch.Tensor
    variance: torch.Tensor
    still: torch.Tensor
    slope: torch.Tensor | None = None
    ds_dl: torch.Tensor | None = None

    def __post_init__(self):
        names = ("levels", "images", "variance", "still")
        for name in names:
            v = getattr(self, name)
            if not isinstance(v, torch.Tensor) or not v.is_floating_point():
                raise InputTypeError(f"{name}: expected a floating-point tensor, got {getattr(v, 'dtype', type(v).__name__)}")
        lv, im = self.levels, self.images
        if lv.dim() != 2 or lv.shape[1] < 4:
            raise ShapeError(f"levels: expected [P, K] with K >= 4 levels (a cubic spline), got {tuple(lv.shape)}")
        P, K = lv.shape
        if im.dim() != 5 or tuple(im.shape[:2]) != (P, K):
            raise ShapeError(f"images: expected [P={P}, K={K}, M, h, w], got {tuple(im.shape)}")
        if tuple(self.variance.shape) != tuple(im.shape):
            raise ShapeError(f"variance: expected the shape of images {tuple(im.shape)}, got {tuple(self.variance.shape)}")
        if tuple(self.still.shape) != tuple(im.shape[2:]):
            raise ShapeError(f"still: expected [M, h, w] = {tuple(im.shape[2:])}, got {tuple(self.still.shape)}")
        for name in names:
            if not bool(torch.isfinite(getattr(self, name)).all()):
                raise ParameterError(f"{name}: expected finite values, got NaN or inf")
        if not bool((lv.diff(dim=1) > 0).all()):
            raise ParameterError(f"levels: expected strictly increasing levels in every row, got {lv.tolist()}")
        if bool((self.variance < 0).any()):
            raise ParameterError(f"variance: expected values >= 0, got minimum {float(self.variance.min()):g}")
        M, h, w = im.shape[2:]
        if (self.slope is None) != (self.ds_dl is None) or (self.slope is not None and (
                tuple(self.slope.shape) != (P, M, 2) or tuple(self.ds_dl.shape) != (P, M, 2, K, h * w))):
            raise ShapeError(f"slope, ds_dl: expected both None or [P, M, 2] and [P, M, 2, K, h*w] = {(P, M, 2)}, {(P, M, 2, K, h * w)}, "
                             f"got {getattr(self.slope, 'shape', None)}, {getattr(self.ds_dl, 'shape', None)}")


def with_slopes(ladder: PatternLadder, *, batch: int = 256) -> PatternLadder:
    """``ladder`` with its ``slope`` and ``ds_dl`` (:func:`static_slope` of every (pattern, spot),
    ``batch`` ladders at a time, in the ladder's dtype): the run computes them once, not once per
    frequency (``benchmarks/bench_dm.py --ladder-points`` prints their time apart from the fit's)."""
    P, K, M, h, w = ladder.images.shape
    imgs = ladder.images.transpose(1, 2).reshape(P * M, K, h, w)  # [(p, m), K, h, w]
    pm = torch.arange(P * M, device=imgs.device)
    parts = [static_slope(imgs[i:i + batch], ladder.still[pm[i:i + batch] % M], ladder.levels[pm[i:i + batch] // M])
             for i in range(0, P * M, batch)]
    return replace(ladder, slope=torch.cat([s for s, _ in parts]).reshape(P, M, 2),
                   ds_dl=torch.cat([d for _, d in parts]).reshape(P, M, 2, K, h * w))


def slope_covariance(ladder: PatternLadder) -> torch.Tensor:
    """``[P, M, 2, 2]`` (px per input unit)^2: the covariance of each (pattern, spot)'s static shift
    ``s`` (:func:`static_slope`) from the ladder's noise, ``ds_dl diag(variance) ds_dl^T``, every
    ladder pixel independent (the still's noise left out, as in the fit). One ``s`` serves every
    frequency of its spot, so this error is common to all of them: the fits' covariances hold it
    once per frequency, the actuator fit takes the frequencies as independent, and
    :mod:`torchblur.dm.common_noise` puts it back into the static columns' stds."""
    lad = ladder if ladder.ds_dl is not None else with_slopes(ladder)
    P, K, M, h, w = lad.images.shape
    var = lad.variance.transpose(1, 2).reshape(P, M, 1, K * h * w)
    d = lad.ds_dl.reshape(P, M, 2, K * h * w)
    return (d * var) @ d.transpose(-1, -2)


def spline_basis(levels: torch.Tensor) -> torch.Tensor:
    """The cubic spline's cardinal basis of each row of ``levels [P, K]``: ``coef [P, K-1, 4, K]``
    (float64, the levels' device). On interval ``i`` (``levels[p, i] <= u < levels[p, i+1]``, the
    first and last extended) the spline through knot values ``y [K]`` is
    ``sum_j (coef[p, i, j] @ y) (u - levels[p, i])^(3 - j)`` (scipy ``CubicSpline``, not-a-knot)."""
    lv = levels.detach().cpu().double().numpy()
    K = lv.shape[1]
    c = np.stack([np.moveaxis(CubicSpline(row, np.eye(K)).c, 0, 1) for row in lv])
    return torch.as_tensor(c, device=levels.device)


def _basis_at(u, knots, coef):
    """The basis and its derivative at ``u [n, ...]``: ``(B, dB/du)`` each ``[n, ..., K]``
    (``knots [n, K]``, ``coef [n, K-1, 4, K]`` of :func:`spline_basis`)."""
    n, K = knots.shape
    flat = u.reshape(n, -1)
    i = (torch.searchsorted(knots, flat.contiguous()) - 1).clamp(0, K - 2)  # [n, Q]
    d = flat - torch.gather(knots, 1, i)
    c = coef[torch.arange(n, device=u.device)[:, None], i]  # [n, Q, 4, K]
    one, zero = torch.ones_like(d), torch.zeros_like(d)
    pw = torch.stack([d * d * d, d * d, d, one], -1)
    dpw = torch.stack([3 * d * d, 2 * d, one, zero], -1)
    B = (pw[..., None] * c).sum(-2)
    dB = (dpw[..., None] * c).sum(-2)
    return B.reshape(u.shape + (K,)), dB.reshape(u.shape + (K,))


def _integrated_basis(u, wb, wd, knots, coef):
    """``[n, E, A + D, K]``: ``sum_s wb[..., a, s] B(u_s)`` then ``sum_s wd[..., d, s] dB/du(u_s)``
    at nodes ``u [n, E, S]`` (weights ``wb [n, E, A, S]``, ``wd [n, E, D, S]``; ``knots``, ``coef``
    as :func:`_basis_at`). Each node's basis and derivative come from its interval's coefficients
    (``[4, K]``) times its offset's powers, then one GEMM per exposure with the weights."""
    n, K = knots.shape
    E, S = u.shape[1:]
    flat = u.reshape(n, -1)
    i = (torch.searchsorted(knots, flat.contiguous()) - 1).clamp(0, K - 2)  # [n, Q]
    d = flat - torch.gather(knots, 1, i)
    c = coef[torch.arange(n, device=u.device)[:, None], i]  # [n, Q, 4, K]
    one = torch.ones_like(d)
    pw = torch.stack([d * d * d, d * d, d, one, 3 * d * d, 2 * d, one, torch.zeros_like(d)], -1).reshape(n, -1, 2, 4)
    BB = (pw @ c).reshape(n, E, S, 2 * K)  # B(u_s) and dB/du(u_s)
    return torch.cat([wb @ BB[..., :K], wd @ BB[..., K:]], 2)


def shift_derivatives(img: torch.Tensor) -> torch.Tensor:
    """``[..., 2, h, w]``: the derivatives of ``img [..., h, w]`` along a shift of it by (dx, dy)
    px (``d/ds img(x - s)``): :func:`~torchblur.render.splat.kernel_shift_with_jacobian`'s at zero
    shift on a grid padded by :data:`PAD` px (odd sizes: no Nyquist bin), the renderer's exact
    derivative. Linear in ``img`` and antisymmetric (its adjoint is its negative)."""
    zero, one = img.new_zeros(img.shape[:-2] + (1,)), img.new_ones(img.shape[:-2] + (1,))
    eye = torch.eye(2, dtype=img.dtype, device=img.device)
    return kernel_shift_with_jacobian(img, zero, zero, eye[None, :1], eye[None, 1:], one, pad=PAD)[1]


@dataclass(frozen=True)
class _Problems:
    """Every problem's inputs, flat ``[n]`` in (p, f, m) order, on the fit's device and dtype."""

    data: torch.Tensor  # [n, E, hw] electrons
    weight: torch.Tensor  # [n, E, hw] 1 / std^2 (or 1), 0 where masked
    keep: torch.Tensor  # [n, E, hw] bool
    noise_given: bool
    cw: torch.Tensor  # [P, F, E, S] cos(w t) at the nodes
    sw: torch.Tensor  # [P, F, E, S]
    wq: torch.Tensor  # [P, F, E, S] node weights (s)
    power: torch.Tensor  # [F]
    amplitude: torch.Tensor  # [P, F]
    knots: torch.Tensor  # [P, K]
    coef: torch.Tensor  # [P, K-1, 4, K]
    shape: tuple  # (P, F, M, E, h, w)
    group: torch.Tensor | None = None  # [E0] long: the merged exposure each exposure of the crops went into (:func:`_merged_repeats`)
    data_all: torch.Tensor | None = None  # [n, E0, hw]: the crops' exposures before the merge (data, weight: as above)
    weight_all: torch.Tensor | None = None  # [n, E0, hw]


def _flat_problems(crops, ladder: PatternLadder, window, omega, amplitude, power, noise_std, mask, like) -> _Problems:
    """Check and broadcast the inputs of :func:`fit_ladder_problems` (errors name the argument)."""
    if not isinstance(crops, torch.Tensor) or crops.dim() != 6:
        raise ShapeError(f"crops: expected a tensor [P, F, M, E*R, h, w], got {getattr(crops, 'shape', type(crops).__name__)}")
    check_type(ladder, "ladder", PatternLadder, "a PatternLadder")
    check_type(window, "window", ExposureWindow, "an ExposureWindow of batch [P, F, E*R]")
    P, F, M, E, h, w = crops.shape
    Pl, K, Ml, hl, wl = ladder.images.shape
    if (Pl, Ml, hl, wl) != (P, M, h, w):
        raise ShapeError(f"ladder: expected images [P={P}, K, M={M}, h={h}, w={w}] like the crops, got {list(ladder.images.shape)}")

    def expand(value, name, shape, desc, **kw):
        t = torch.as_tensor(value, **(kw or like))
        try:
            return t.to(**(kw or like)).expand(shape)
        except RuntimeError as e:
            raise ShapeError(f"{name}: expected {desc} broadcastable to {list(shape)}, got {list(t.shape)}") from e
    start = expand(window.start, "window", (P, F, E), "a batch")
    dur = expand(window.duration, "window", (P, F, E), "a batch")
    om = torch.as_tensor(omega, **like)
    if om.shape != (F,):
        raise ShapeError(f"omega: expected [F={F}] rad/s, got shape {tuple(om.shape)}")
    amp = expand(amplitude, "amplitude", (P, F), "command amplitudes")
    pw = expand(power, "power", (F,), "a laser power")
    if not bool(torch.isfinite(pw).all()) or bool((pw <= 0).any()):
        raise ParameterError(f"power: expected finite values > 0, got {pw.tolist()}")
    data = crops.to(**like)
    keep = torch.isfinite(data)
    if mask is not None:
        keep = keep & expand(mask, "mask", data.shape, "a bool mask", device=like["device"]).bool()
    if noise_std is None:
        weight = keep.to(like["dtype"])
    else:
        ns = expand(noise_std, "noise_std", data.shape, "pixel stds")
        keep = keep & (ns > 0) & torch.isfinite(ns)
        weight = torch.where(keep, 1 / ns.clamp_min(torch.finfo(ns.dtype).tiny).square(), torch.zeros_like(ns))
    x, wg = quadrature_nodes(1, NODES, **like)
    t = start[..., None] + dur[..., None] * x  # [P, F, E, S]
    ph = om[None, :, None, None] * t
    n = P * F * M
    return _Problems(data=torch.where(keep, data, torch.zeros_like(data)).reshape(n, E, h * w), weight=weight.reshape(n, E, h * w),
                     keep=keep.reshape(n, E, h * w), noise_given=noise_std is not None, cw=torch.cos(ph), sw=torch.sin(ph),
                     wq=dur[..., None] * wg, power=pw, amplitude=amp, knots=ladder.levels.to(**like),
                     coef=spline_basis(ladder.levels).to(**like), shape=(P, F, M, E, h, w))


REPEAT_PHASE_TOL = 1e-7  #: rad: exposures whose nodes' phases agree this closely (and their durations, relatively) are repeats


def _merged_repeats(prob: _Problems) -> _Problems:
    """``prob`` with the repeats of each exposure merged: exposures whose windows have the same
    duration and start at the same phase of the sine (to :data:`REPEAT_PHASE_TOL`) in every
    (pattern, frequency) have the same model image, so their weighted mean (weight the sum of
    theirs) is fitted once. ``sum_r W_r (d_r - m)^2 = W (dbar - m)^2 + sum_r W_r d_r^2 - W dbar^2``:
    the same cost up to a constant (:func:`_fit_chunk` adds it as a row, so the LM's tests see the
    cost they saw unmerged), the same Jacobian, normal equations, bias term and covariances; the
    reduced chi2 and the unweighted sandwich are taken on the repeats themselves (``data_all``,
    ``weight_all``). A run's repeats share their window, so a whole grid's 2 exposures x 6 repeats
    cost 2 exposures per model evaluation; windows that differ (a recording's own timestamps)
    are not merged. ``prob`` itself where nothing merges."""
    P, F, M, E, h, w = prob.shape
    ph = torch.atan2(prob.sw, prob.cw)  # [P, F, E, S]
    group = list(range(E))
    for e in range(E):
        for g in range(e):
            if group[g] != g:
                continue
            dphi = torch.remainder(ph[:, :, e] - ph[:, :, g] + math.pi, 2 * math.pi) - math.pi
            dw = (prob.wq[:, :, e] - prob.wq[:, :, g]).abs() <= REPEAT_PHASE_TOL * prob.wq[:, :, g].abs()
            if bool((dphi.abs() <= REPEAT_PHASE_TOL).all()) and bool(dw.all()):
                group[e] = g
                break
    firsts = sorted(set(group))
    if len(firsts) == E:
        return prob
    index = torch.tensor([firsts.index(g) for g in group], device=prob.data.device)  # [E]: the merged exposure of each
    G, n = len(firsts), prob.data.shape[0]
    W = prob.weight.new_zeros(n, G, h * w).index_add_(1, index, prob.weight)
    num = prob.data.new_zeros(n, G, h * w).index_add_(1, index, prob.weight * prob.data)
    data = torch.where(W > 0, num / W.clamp_min(torch.finfo(W.dtype).tiny), torch.zeros_like(num))
    keep = torch.zeros(n, G, h * w, dtype=torch.int32, device=index.device).index_add_(1, index, prob.keep.to(torch.int32)) > 0
    pick = torch.tensor(firsts, device=prob.cw.device)
    return replace(prob, data=data, weight=W, keep=keep, cw=prob.cw[:, :, pick], sw=prob.sw[:, :, pick], wq=prob.wq[:, :, pick],
                   shape=(P, F, M, G, h, w), group=index, data_all=prob.data, weight_all=prob.weight)


@dataclass(frozen=True)
class _Chunk:
    """One chunk's problems ``rows [c]`` and the ladders they use (``u`` distinct (pattern, spot))."""

    rows: torch.Tensor  # [c] flat problem indices
    pat: torch.Tensor  # [c] pattern
    pf: torch.Tensor  # [c] flat (pattern, frequency)
    freq: torch.Tensor  # [c] frequency
    inv: torch.Tensor  # [c] -> the chunk's ladder
    lad: torch.Tensor  # [u, B K, hw]: Dn^j Ds^k L of every level (:func:`_chains`; Dn, Ds: the derivatives along a shift by n, by s)
    var: torch.Tensor  # [u, K, hw]: the variance of L
    noise: torch.Tensor  # [u, 2, K, hw]: the pixel variances of the ladder's L and Dn L (their covariance: 0)
    slope: torch.Tensor  # [c, 2] s: px per unit u
    ds_dl: torch.Tensor  # [c, 2, K, hw]: ds / dL


SHIFT_ITER = 60  #: at most this many Gauss-Newton steps of each level's shifted-still fit (:func:`static_slope`)
SHIFT_TOL = 1e-7  #: px: the steps stop once all are shorter (6 fixed steps: s 0.03 % high, bench_dm_ladder_slope.py)
SLOPE_DEGREE = 3  #: the polynomial in ``u`` of the levels' shifts whose slope at 0 is ``s``


def static_slope(images, still, levels, *, pad: int = PAD):
    """``(s [u, 2], ds_dl [u, 2, K, hw])``: each ladder's static shift per unit ``u`` (px) and its
    derivative along the ladder's images. Each level's image ``images [u, K, h, w]`` is fitted by
    its spot's still ``still [u, h, w]`` shifted by ``(dx, dy)`` (Gauss-Newton to :data:`SHIFT_TOL`,
    unweighted, the renderer's Fourier shift); ``s`` is the slope at ``u = 0`` of the least-squares
    polynomial of degree :data:`SLOPE_DEGREE` through the levels' shifts (``levels [u, K]``): the
    small-poke fitted shift where the shift is a cubic in ``u``. A lenslet spot's bends within the
    first level, which no level resolves: on HCIPy's frames ``s`` is +0.202 % above the truth (+0.033 %
    of it the truth's own poke; ``benchmarks/bench_dm_ladder_slope.py``: measured, not cured). The
    spline's ``dL/du`` at 0 took two or three levels, their noise weighed by ``1 / spacing``: 5 x the
    cubic's there, 7 x on the small simulated mirror, an error common to every frequency of a spot
    that the actuator fit takes as independent. ``ds_dl`` from the fits' Jacobians."""
    u, K, h, w = images.shape
    eye = torch.eye(2, dtype=images.dtype, device=images.device)
    shift = image_moments(images)[1] - image_moments(still)[1][:, None]  # [u, K, 2] the start: the centroids' difference
    done = False
    for i in range(SHIFT_ITER + 1):
        img, jac = kernel_shift_with_jacobian(still[:, None], shift[..., :1], shift[..., 1:], eye[None, :1], eye[None, 1:],
                                              torch.ones_like(shift[..., :1]), pad=pad)
        J = jac.reshape(u, K, 2, h * w)
        sens = torch.linalg.pinv(J @ J.transpose(-1, -2)) @ J  # [u, K, 2, hw]: the step per unit residual (0 for a dark spot)
        if i == SHIFT_ITER or done:
            break
        step = (sens @ (images - img).reshape(u, K, h * w, 1))[..., 0]
        shift = shift + step.clamp(-1, 1)
        done = bool((step.abs() < SHIFT_TOL).all())
    X = torch.stack([levels ** i for i in range(SLOPE_DEGREE + 1)], -1)  # [u, K, deg + 1]
    c = torch.linalg.pinv(X)[:, 1]  # [u, K]: the slope at 0's weights
    return (c[..., None] * shift).sum(1), c[:, None, :, None] * sens.transpose(1, 2)


def _chunk(prob: _Problems, ladder: PatternLadder, rows, like, tops=None) -> _Chunk:
    """The chunk of problems ``rows``: their ladders on the fit's device, with the shift
    derivatives (``tops`` as :func:`_chain_images`) and the static shifts ``s`` (:func:`static_slope`)."""
    P, F, M, E, h, w = prob.shape
    pat, m = rows // (F * M), rows % M
    uniq, inv = torch.unique(pat * M + m, return_inverse=True)
    up, um = (uniq // M).cpu(), (uniq % M).cpu()
    L = ladder.images[up, :, um].to(**like)  # [u, K, h, w]
    K = L.shape[1]
    var = ladder.variance[up, :, um].to(**like)
    if ladder.slope is not None:  # with_slopes: computed once for every frequency
        slope, ds_dl = ladder.slope[up, um].to(**like), ladder.ds_dl[up, um].to(**like)
    else:
        slope, ds_dl = static_slope(L, ladder.still[um].to(**like), prob.knots[up.to(prob.knots.device)])
    n = _normal(slope)  # [u, 2]
    blocks = list(_chain_images(L, n[:, None], slope[:, None], tops=tops))  # Dn^j Ds^k L (Ds: the derivative along a shift by s)
    lad = torch.cat(blocks, 1).reshape(len(uniq), len(blocks) * K, h * w)
    dn_var = _derivative_variance(var, n[:, None])  # [u, K, h, w]: the variance of Dn L (every pixel of L independent)
    var = var.reshape(len(uniq), K, h * w)
    return _Chunk(rows=rows, pat=pat, pf=rows // M, freq=(rows // M) % F, inv=inv, lad=lad, var=var,
                  noise=torch.stack([var, dn_var.reshape(var.shape)], 1), slope=slope[inv], ds_dl=ds_dl[inv])


def _derivative_variance(var, n):
    """The variance of ``Dn img`` (:func:`_along`) where ``img``'s pixels are independent of variance
    ``var [..., h, w]``: ``sum_q' Dn[q, q']^2 var[q']``, ``Dn = nx Dx + ny Dy`` with Dx acting along rows and
    Dy along columns (:func:`_derivative_factors`), so ``Dn^2 = nx^2 Dx^2 + ny^2 Dy^2`` plus the cross term on
    the diagonal (``Dx Dy`` elementwise is 0 off it)."""
    h, w = var.shape[-2:]
    mx, my = _derivative_factors(h, w, var.dtype, var.device)
    nx, ny = n[..., 0, None, None], n[..., 1, None, None]
    cross = 2 * torch.diagonal(my)[:, None] * torch.diagonal(mx)[None, :]  # [h, w]
    return (nx * nx) * (var @ (mx * mx).T) + (ny * ny) * ((var.transpose(-1, -2) @ (my * my).T).transpose(-1, -2)) + nx * ny * cross * var


def _chains():
    """``[top_0, ..., top_SHIFT_ORDER]``: the ladder's blocks are ``Dn^j Ds^k L``, ``j <= top_k``, in that order."""
    return [ORDER - k for k in range(SHIFT_ORDER + 1)]


def _chain_images(img, n, s, sign: int = 1, tops=None):
    """``Dn^j Ds^k img``, ``j <= tops[k]`` (None: :func:`_chains`), in that order (``n``, ``s`` broadcast as :func:`_along`
    takes them); ``sign=-1``: the adjoints ``(-Dn)^j (-Ds)^k img``. Each derivative is taken once, none unused."""
    tops = _chains() if tops is None else tops
    base = img
    for k, top in enumerate(tops):
        cur = base
        for j in range(top + 1):
            yield cur
            if j < top:
                cur = sign * _along(cur, n)
        if k < len(tops) - 1:
            base = sign * _along(base, s)


def _coefficients(theta, prob: _Problems, ch: _Chunk, idx):
    """``(C [n, E, 1 + N_PAR, B, K], v [n, E, S])``: the image (row 0) and its derivatives along
    the six parameters (rows 1-6) of problems ``idx`` (of the chunk) as weights of the ladder's
    blocks ``Dn^j Ds^k L`` (:func:`_chains`) of every level, already integrated over each
    exposure's nodes (s): ``sum_jk d^j e^k / (j! k!) Dn^j Ds^k L(v)`` (module docstring)."""
    cw, sw, wq = _nodes(prob, ch.pf[idx])
    v = theta[:, 0, None, None] * cw + theta[:, 1, None, None] * sw
    d = theta[:, 2, None, None] * cw + theta[:, 3, None, None] * sw  # [n, E, S] px along n
    e = theta[:, 4, None, None] * cw + theta[:, 5, None, None] * sw  # [n, E, S] command units along s
    T = [wq * d ** j / math.factorial(j) for j in range(ORDER + 1)]  # the Taylor terms' weights
    X = [e ** k / math.factorial(k) for k in range(SHIFT_ORDER + 1)]
    wb, wd, rows, b = [], [], [], 0  # the weights of B(v) and dB/dv(v), and their (row, block)
    for k, top in enumerate(_chains()):
        for j in range(top + 1):
            wb.append(T[j] * X[k])
            rows.append((0, b))
            for r, c in ((1, cw), (2, sw)):
                if j:
                    wb.append(c * T[j - 1] * X[k])
                    rows.append((r + 2, b))
                if k:
                    wb.append(c * T[j] * X[k - 1])
                    rows.append((r + 4, b))
            b += 1
    b2 = 0
    for k, top in enumerate(_chains()):
        for j in range(top + 1):
            for r, c in ((1, cw), (2, sw)):
                wd.append(c * T[j] * X[k])
                rows.append((r, b2))
            b2 += 1
    out = _integrated_basis(v, torch.stack(wb, 2), torch.stack(wd, 2), prob.knots[ch.pat[idx]], prob.coef[ch.pat[idx]])
    n, E, K = out.shape[0], out.shape[1], out.shape[-1]
    where = torch.tensor([r * b + i for r, i in rows], device=out.device)
    C = out.new_zeros(n, E, (N_PAR + 1) * b, K).index_add_(2, where, out)
    return C.reshape(n, E, N_PAR + 1, b, K), v


def _nodes(prob: _Problems, pf):
    """``(cos(w t), sin(w t), weights)`` at the nodes of the problems of (pattern, frequency) ``pf [n]``: each ``[n, E, S]``."""
    E = prob.cw.shape[2]
    return tuple(t.reshape(-1, E, t.shape[-1])[pf] for t in (prob.cw, prob.sw, prob.wq))


def _model_jacobian(theta, prob: _Problems, ch: _Chunk, idx, coefficients=None):
    """``(model [n, E*hw], J [n, E*hw, N_PAR])`` of problems ``idx`` of the chunk at ``theta [n, N_PAR]`` (electrons;
    ``coefficients``: the model's, None: :func:`_coefficients`)."""
    C, _ = (coefficients or _coefficients)(theta, prob, ch, idx)
    n, E = C.shape[:2]
    sel = ch.inv[idx]
    same = sel.numel() == ch.lad.shape[0] and bool((sel == torch.arange(sel.numel(), device=sel.device)).all())
    C = (C * prob.power[ch.freq[idx], None, None, None, None]).transpose(1, 2).reshape(n, (N_PAR + 1) * E, -1)  # [n, 7 E, (R + RW) K]
    out = (C @ (ch.lad if same else ch.lad[sel])).reshape(n, N_PAR + 1, -1)  # [n, 7, E*hw] (no copy of the ladders in order)
    return out[:, 0], out[:, 1:].transpose(1, 2)  # J: a view of [n, 6, E*hw], the layout the normal equations' GEMMs want


def _centroid_system(prob: _Problems, ladder: PatternLadder, rows, b0):
    """``(A [c, 2, 2], b [c, 2])``: the normal equations of the command phasor ``G = (g_cos, g_sin)``
    of problems ``rows [c]`` from their exposures' centroids against the ladder's centroid curve
    linearised at ``u = 0`` (least squares over both axes and every exposure; ``b0``: the spline's
    basis and its derivative at 0, ``[P, K]`` each)."""
    P, F, M, E, h, w = prob.shape
    like = dict(dtype=prob.data.dtype, device=prob.data.device)
    pat, pf = rows // (F * M), rows // M
    keep = prob.keep[rows].all(1).to(like["dtype"])  # [c, hw]
    yy, xx = torch.meshgrid(torch.arange(h, **like), torch.arange(w, **like), indexing="ij")
    xy = torch.stack([xx.reshape(-1), yy.reshape(-1)])  # [2, hw]
    L = ladder.images[pat.cpu(), :, (rows % M).cpu()].to(**like).flatten(2) * keep[:, None]  # [c, K, hw]
    cen_l = (L @ xy.T) / L.sum(-1, keepdim=True)  # [c, K, 2]
    c0 = (b0[0][pat][:, None, :] @ cen_l)[:, 0]  # [c, 2]
    slope = (b0[1][pat][:, None, :] @ cen_l)[:, 0]
    D = prob.data[rows] * keep[:, None]  # [c, E, hw]
    r = (D @ xy.T) / D.sum(-1, keepdim=True) - c0[:, None]  # [c, E, 2]
    cw, sw, wq = _nodes(prob, pf)
    v = torch.stack([(wq * cw).sum(-1), (wq * sw).sum(-1)], -1) / wq.sum(-1, keepdim=True)  # [c, E, 2]: the exposures' means of cos, sin
    A = (slope.square().sum(-1))[:, None, None] * (v.transpose(1, 2) @ v)
    return A, ((r * slope[:, None, :]).sum(-1, keepdim=True) * v).sum(1)


def _starts(prob: _Problems, ladder: PatternLadder, rows, b0, chunk: int):
    """``theta0 [c, 2, N_PAR]``: two starts of each problem ``rows [c]``, ``G`` (``v``; ``d = e = 0``)
    from its own centroids (:func:`_centroid_system`) and from those of every spot of its (pattern,
    frequency) pooled (the pattern's common command); where one fails (no centroid slope, no light)
    ``G = amplitude`` (the command's own phase); ``|G|`` kept within the levels. A spot that barely
    moves under the pattern leaves its own ``G`` to the centroids' noise, often at the ladder's end:
    started there the fit stopped in a local minimum (on HCIPy's lenslet spots, the quick run's
    patterns 0, 4, 6, 32, 38, 48, 52, 54 at 10 Hz: 34 of 640 fits with a chi2 higher by 1-63 than from
    the command's own phasor, 19 of them with their motion off the ladder, :func:`_fit_chunk`)."""
    P, F, M = prob.shape[:3]
    if rows.numel() == 0:  # every problem dark or masked: none to start (torch.cat of no parts would raise)
        return prob.data.new_zeros(0, 2, N_PAR)
    parts = [_centroid_system(prob, ladder, rows[i:i + chunk], b0) for i in range(0, rows.numel(), chunk)]
    A, b = torch.cat([a for a, _ in parts]), torch.cat([b for _, b in parts])
    pf = rows // M
    ok = torch.isfinite(A).flatten(1).all(-1) & torch.isfinite(b).all(-1)
    pool = (A.new_zeros(P * F, 2, 2).index_add_(0, pf[ok], A[ok]), b.new_zeros(P * F, 2).index_add_(0, pf[ok], b[ok]))
    amp = prob.amplitude.reshape(-1)[pf]
    top = prob.knots.abs().amax(-1)[rows // (F * M)]
    out = []
    for a, bb in ((A, b), (pool[0][pf], pool[1][pf])):
        g = (torch.linalg.pinv(a) @ bb[..., None])[..., 0]  # (gc, gs)
        bad = ~torch.isfinite(g).all(-1) | (g.square().sum(-1) == 0)
        g = torch.where(bad[:, None], torch.stack([torch.zeros_like(amp), amp], -1), g)
        g = g * (top / g.norm(dim=-1).clamp_min(torch.finfo(g.dtype).tiny)).clamp(max=1.0)[:, None]
        out.append(torch.cat([g, g.new_zeros(g.shape[0], N_PAR - 2)], -1))
    return torch.stack(out, 1)


def _along(img, n):
    """``Dn img``: the derivative of ``img [..., h, w]`` along a shift by ``n [..., 2]`` (unit,
    broadcast against ``img``'s leading dims) px, :func:`shift_derivatives` as two small GEMMs
    (:func:`_derivative_factors`: the same values, without a Fourier transform per image)."""
    h, w = img.shape[-2:]
    mx, my = _derivative_factors(h, w, img.dtype, img.device)
    dx = img @ mx.T  # [..., h, w]: along each row
    dy = (img.transpose(-1, -2) @ my.T).transpose(-1, -2)  # along each column
    return dx * n[..., 0, None, None] + dy * n[..., 1, None, None]


@functools.lru_cache(maxsize=8)
def _derivative_factors(h: int, w: int, dtype: torch.dtype, device: torch.device):
    """``(mx [w, w], my [h, h])``: :func:`shift_derivatives` is separable (on the padded grid the
    Fourier multiplier of ``d/dx`` is ``kx``'s alone, of ``d/dy`` ``ky``'s), ``Dx img = img mx^T``
    and ``Dy img = my img``: the derivatives of a row's and a column's unit images (the same values
    as the 2-D map's rows, to round-off). Cached per crop size, dtype and device."""
    dx = shift_derivatives(torch.eye(w, dtype=dtype, device=device).reshape(w, 1, w))[:, 0, 0, :]  # [j', j] = Dx[j, j']
    dy = shift_derivatives(torch.eye(h, dtype=dtype, device=device).reshape(h, h, 1))[:, 1, :, 0]  # [i', i] = Dy[i, i']
    return dx.T.contiguous(), dy.T.contiguous()


def _normal(slope):
    """``[c, 2]`` the unit normal ``(-s_y, s_x) / |s|`` of each static shift ``slope [c, 2]`` (x
    where ``s = 0``): the free motion's direction. Along ``s`` the command phasor ``G`` carries
    the motion; a free motion along ``s`` too would be the same image to first order (on a spot
    that only moves, exactly): a direction the data hardly see, which biased the fitted motion."""
    norm = slope.norm(dim=-1, keepdim=True)
    n = torch.stack([-slope[:, 1], slope[:, 0]], -1) / norm.clamp_min(torch.finfo(slope.dtype).tiny)
    return torch.where(norm > 0, n, torch.tensor([1.0, 0.0], dtype=slope.dtype, device=slope.device))


def _report_jacobians(theta, slope):
    """``(amplitude [c, 2], phase [c, 2], H_theta [c, 4, 4], H_s [c, 4, 2])``: the motion per
    axis ``s_a G + n_a N`` (``N = n_sin + i n_cos``, ``n`` :func:`_normal`, held fixed: the
    fitted ``G`` takes up a turn of it to first order) as amplitude and phase, and its Jacobians
    along ``theta`` and ``s`` in the order (amplitude_x, phase_x, amplitude_y, phase_y)."""
    c = theta.shape[0]
    gc, gs = theta[:, 0] + theta[:, 4], theta[:, 1] + theta[:, 5]  # G = v + e
    nrm = _normal(slope)
    re = slope * gs[:, None] + nrm * theta[:, 3, None]  # [c, 2]: Re of x and y
    im = slope * gc[:, None] + nrm * theta[:, 2, None]
    cart_t = torch.zeros(c, 4, N_PAR, dtype=theta.dtype, device=theta.device)  # rows Re_x, Im_x, Re_y, Im_y
    cart_s = torch.zeros(c, 4, 2, dtype=theta.dtype, device=theta.device)
    for a in range(2):
        cart_t[:, 2 * a, 1], cart_t[:, 2 * a, 3], cart_t[:, 2 * a, 5] = slope[:, a], nrm[:, a], slope[:, a]
        cart_t[:, 2 * a + 1, 0], cart_t[:, 2 * a + 1, 2], cart_t[:, 2 * a + 1, 4] = slope[:, a], nrm[:, a], slope[:, a]
        cart_s[:, 2 * a, a], cart_s[:, 2 * a + 1, a] = gs, gc
    amp = torch.hypot(re, im)
    a2 = amp.square().clamp_min(torch.finfo(amp.dtype).tiny)
    polar = torch.zeros(c, 4, 4, dtype=theta.dtype, device=theta.device)
    for a in range(2):
        polar[:, 2 * a, 2 * a], polar[:, 2 * a, 2 * a + 1] = re[:, a] / a2[:, a].sqrt(), im[:, a] / a2[:, a].sqrt()
        polar[:, 2 * a + 1, 2 * a], polar[:, 2 * a + 1, 2 * a + 1] = -im[:, a] / a2[:, a], re[:, a] / a2[:, a]
    return amp, torch.atan2(im, re), polar @ cart_t, polar @ cart_s


def _ladder_covariance(theta, prob: _Problems, ch: _Chunk, J, W, Cw, H_t, H_s, coefficients=None, tops=None):
    """``(cov [c, 4, 4], model variance [c, E, hw])`` from the ladder's noise: the reported
    motion's covariance through the fit (``dtheta = -Cw G dL``, ``G_p = J_p^T W dY/dL``, using
    ``Dx^T = -Dx``) and through ``s``; and each model pixel's variance from its ``L`` term
    (``coefficients``, ``tops``: the model's, as :func:`_model_jacobian`, :func:`_chain_images`)."""
    C, _ = (coefficients or _coefficients)(theta, prob, ch, torch.arange(theta.shape[0], device=theta.device))
    c, E, K = C.shape[0], C.shape[1], C.shape[-1]
    h, w = prob.shape[4:]
    pw = prob.power[ch.freq]
    v = (W[..., None] * J).reshape(c, E, h, w, N_PAR).permute(0, 4, 1, 2, 3)  # [c, 4, E, h, w]
    n = _normal(ch.slope)[:, None, None]  # [c, 1, 1, 2]
    G = C.new_zeros(c, K, N_PAR * h * w)  # sum_b C_b^T (the block's adjoint of v), accumulated in place: one small GEMM per block
    Ct = C[:, :, 0].permute(0, 2, 3, 1)  # [c, B, K, E]
    for b, vj in enumerate(_chain_images(v, n, ch.slope[:, None, None], sign=-1, tops=tops)):  # (Dn^j Ds^k)^T = (-Dn)^j (-Ds)^k
        G.baddbmm_(Ct[:, b], vj.reshape(c, N_PAR, E, h * w).transpose(1, 2).reshape(c, E, N_PAR * h * w))
    G = G.reshape(c, K, N_PAR, h * w).transpose(1, 2) * pw[:, None, None, None]  # [c, 6, K, hw]
    A = H_t @ (-Cw @ G.reshape(c, N_PAR, -1)) + H_s @ ch.ds_dl.reshape(c, 2, -1)  # [c, 4, K hw]
    var = ch.var[ch.inv]  # [c, K, hw]
    cov = (A * var.reshape(c, 1, -1)) @ A.transpose(1, 2)
    return cov, _model_noise(C, prob, ch, W)[0]


def _model_noise(C, prob: _Problems, ch: _Chunk, W):
    """The ladder noise in the model of a chunk's problems at their coefficients ``C`` (:func:`_coefficients`):
    ``(var [c, E, hw], grad [c, 4])``, each model pixel's variance and the gradient along
    ``theta`` of ``V = sum W var``."""
    c, E = C.shape[:2]
    nz = ch.noise[ch.inv] * prob.power[ch.freq, None, None, None] ** 2  # [c, 2, K, hw]
    pairs = ((0, 0, 0), (1, 1, 1))  # (block a, block b, noise term): L and Dn L (the higher orders' noise left out)
    var = sum((C[:, :, 0, a] * C[:, :, 0, b]) @ nz[:, t] for a, b, t in pairs)  # [c, E, hw]
    wn = W.reshape(c, 1, E, -1) @ nz.transpose(-1, -2)  # [c, 4, E, K]: sum_q W cov
    grad = 2 * sum((C[:, :, 1:, a] * C[:, :, :1, b] * wn[:, t, :, None]).sum((1, 3)) for a, b, t in pairs)
    return var, grad


def _debias(theta, data, W, s2, prob: _Problems, ch: _Chunk, jac, coefficients=None):
    """The fit with the ladder noise's bias removed to first order in its variance:
    ``(theta, model, J, Cw = (J^T W J)^-1, info, left)``, ``left`` the squared length (std^2) of
    the step still to go.

    The least-squares cost ``S`` against a noisy ladder has the expectation ``S_true + V(theta)``,
    ``V = sum W var(model)`` (:func:`_model_noise`), which depends on ``theta`` (a trajectory that
    dwells near few levels has a noisier model; a larger ``d`` draws more of the shift
    derivatives' noise), so the plain fit is biased. Up to :data:`BIAS_ITER` Gauss-Newton steps
    on ``S - V`` (``Cw (J^T W r + grad V / 2)``) from the fit, each kept only where it lowers
    ``S - V`` and is shorter than :data:`STEP_MAX` std; a refused step ends that problem's correction.
    ``jac``: :func:`_with_prior`'s; ``coefficients``: the model's (None: :func:`_coefficients`)."""
    coefficients = coefficients or _coefficients
    c = theta.shape[0]
    idx = torch.arange(c, device=theta.device)
    Wp = W[:, :math.prod(prob.shape[3:])]  # the pixels' weights (the prior's rows, and any constant row, after them)

    def state(th):
        model, J = jac(th, idx)
        var, grad = _model_noise(coefficients(th, prob, ch, idx)[0], prob, ch, Wp)
        q = (W * (data - model).square()).sum(-1) - (Wp * var.reshape(c, -1)).sum(-1)
        return [th, model, J, q, grad]
    st = state(theta)
    going = torch.ones(c, dtype=torch.bool, device=theta.device)
    for i in range(BIAS_ITER + 1):
        th, model, J, q, grad = st
        Cw, info = torch.linalg.inv_ex(J.transpose(1, 2) @ (W[..., None] * J))
        step = (Cw @ (J.transpose(1, 2) @ (W * (data - model))[..., None] + grad[..., None] / 2))[..., 0]
        left = (step[:, None, :] @ torch.linalg.pinv(Cw) @ step[..., None])[:, 0, 0] / s2
        if i == BIAS_ITER or not bool(going.any()):
            break
        trial = state(th + step)
        going = going & (trial[3] <= st[3]) & (left < STEP_MAX ** 2)
        st = [torch.where(going.reshape((c,) + (1,) * (a.dim() - 1)), a, b) for a, b in zip(trial, st)]
    return st[0], st[1], st[2], Cw, info, left


def _with_prior(prob: _Problems, ch: _Chunk, sigma, model_jacobian=None, constant_rows: int = 0):
    """The model and Jacobian of ``model_jacobian`` (None: :func:`_model_jacobian`) with the prior's
    :data:`PRIOR_ROWS` rows next: ``theta[4] / sigma``, ``theta[5] / sigma`` (``sigma [c]``, data 0, weight 1),
    then ``constant_rows`` rows of model 0 (a cost's constant, :func:`_fit_chunk`)."""
    model_jacobian = model_jacobian or _model_jacobian

    def jac(th, i):
        model, J = model_jacobian(th, prob, ch, i)
        pj = th.new_zeros(th.shape[0], N_PAR, PRIOR_ROWS + constant_rows)
        pj[:, 4, 0] = pj[:, 5, 1] = 1 / sigma[i]
        rows = [model, th[:, 4:] / sigma[i, None], th.new_zeros(th.shape[0], constant_rows)]
        return torch.cat(rows, -1), torch.cat([J.transpose(1, 2), pj], -1).transpose(1, 2)
    return jac


def _best_start(jac, theta0, data, W, top, dof=None):
    """``(theta [c, N_PAR], converged [c])``: the LM from each problem's own start (``theta0[:, 0]``,
    :func:`_starts`) and, where the pooled start ``theta0[:, 1]`` lies farther than
    :data:`SECOND_START` x the ladder's top level ``top [c]`` from it, from that one too: the lower cost
    (``dof [c]``: the LM's degrees of freedom, None: its own count of the rows)."""
    res = levenberg_marquardt(lambda th, i: jac(th, i)[0], theta0[:, 0], data, weight=W, max_iter=MAX_ITER, jacobian_fn=jac, gn_tol=1e-2,
                              dof=dof)
    theta, converged = res.theta.clone(), res.converged.clone()
    far = torch.nonzero((theta0[:, 1, :2] - theta0[:, 0, :2]).norm(dim=-1) > SECOND_START * top).reshape(-1)
    if far.numel():
        def sub(th, i):
            return jac(th, far[i])
        r2 = levenberg_marquardt(lambda th, i: sub(th, i)[0], theta0[far, 1], data[far], weight=W[far], max_iter=MAX_ITER,
                                 jacobian_fn=sub, gn_tol=1e-2, dof=None if dof is None else dof[far])
        better = r2.cost < res.cost[far]
        theta[far[better]], converged[far[better]] = r2.theta[better], r2.converged[better]
    return theta, converged


def _fit_chunk(prob: _Problems, ch: _Chunk, theta0):
    """Fit one chunk from its starts ``theta0 [c, 2, N_PAR]`` (:func:`_starts`): ``dict`` of
    ``[c]``-batched amplitude, phase, covariance, status, flags, reduced_chi2. With ``prob``'s
    repeats merged (:func:`_merged_repeats`) the cost's constant is one more row after the prior's
    (data its square root, model 0) and the LM's degrees of freedom are the repeats' pixels."""
    c = ch.rows.numel()
    data, W = prob.data[ch.rows].reshape(c, -1), prob.weight[ch.rows].reshape(c, -1)
    q = data.shape[1]
    if prob.group is None:
        data_a, W_a = data, W
        extra = data.new_zeros(c, 0)
    else:  # the repeats themselves, and the merge's constant sum_r W_r d_r^2 - W dbar^2 (>= 0 but for round-off)
        data_a, W_a = prob.data_all[ch.rows].reshape(c, -1), prob.weight_all[ch.rows].reshape(c, -1)
        extra = ((W_a * data_a.square()).sum(-1) - (W * data.square()).sum(-1)).clamp_min(0).sqrt()[:, None]
    sigma = SHAPE_PRIOR * prob.knots.abs().amax(-1)[ch.pat]  # [c] the prior std of e_cos and e_sin
    data_x = torch.cat([data, data.new_zeros(c, PRIOR_ROWS), extra], -1)
    W_x = torch.cat([W, W.new_ones(c, PRIOR_ROWS + extra.shape[1])], -1)
    jac = _with_prior(prob, ch, sigma, constant_rows=extra.shape[1])
    used = (W_a > 0).sum(-1).to(data.dtype)
    dof = (used - N_PAR + PRIOR_ROWS).clamp_min(1)
    theta, lm_converged = _best_start(jac, theta0, data_x, W_x, prob.knots.abs().amax(-1)[ch.pat], dof)
    all_c = torch.arange(c, device=theta.device)

    def residual2(model):  # [c, E0 hw]: each repeat's squared residual (the merged model is every repeat's)
        m = model[:, :q] if prob.group is None else model[:, :q].reshape(c, -1, q // prob.shape[3])[:, prob.group].reshape(c, -1)
        return (data_a - m).square()
    s2 = torch.ones(c, dtype=theta.dtype, device=theta.device) if prob.noise_given else (residual2(jac(theta, all_c)[0]) * W_a).sum(-1) / dof
    theta, model, J, Cw, info, left = _debias(theta, data_x, W_x, s2, prob, ch, jac)
    r2 = residual2(model)
    Jp = J[:, :q]
    converged = lm_converged | (left < LEFT_MAX ** 2)  # the LM's own test, or the step left is short (noiseless data too)
    amp, phase, H_t, H_s = _report_jacobians(theta, ch.slope)
    cov_l, var_model = _ladder_covariance(theta, prob, ch, Jp, W, Cw, H_t, H_s)
    if prob.noise_given:
        cov_d = Cw
    else:  # the sandwich with each pixel's own squared residual (the noise differs from pixel to pixel: shot noise), plus the prior's information
        S = W_a * W_a * r2
        if prob.group is not None:  # sum over each merged exposure's repeats (their Jacobian is one)
            S = S.new_zeros(c, prob.shape[3], q // prob.shape[3]).index_add_(1, prob.group, S.reshape(c, prob.group.numel(), -1))
        WJ = S.reshape(c, q)[..., None] * Jp
        P0 = PRIOR_ROWS + q
        cov_d = Cw @ (Jp.transpose(1, 2) @ WJ + J[:, q:P0].transpose(1, 2) @ J[:, q:P0]) @ Cw
    cov = H_t @ cov_d @ H_t.transpose(1, 2) + cov_l
    chi2 = torch.full((c,), float("nan"), dtype=theta.dtype, device=theta.device)
    if prob.noise_given:
        vm = var_model if prob.group is None else var_model[:, prob.group]
        sig2 = torch.where(W_a > 0, 1 / W_a.clamp_min(torch.finfo(W_a.dtype).tiny), torch.zeros_like(W_a)) + vm.reshape(c, -1)
        chi2 = torch.where(W_a > 0, r2 / sig2, torch.zeros_like(r2)).sum(-1) / dof
    status = torch.zeros(c, dtype=torch.long, device=theta.device)
    status[~converged] = NOT_CONVERGED
    d = torch.diagonal(cov, dim1=-2, dim2=-1)
    status[(info != 0) | ~torch.isfinite(cov).flatten(1).all(-1) | (d <= 0).any(-1) | ~torch.isfinite(theta).all(-1)] = SINGULAR
    cw, sw, _ = _nodes(prob, ch.pf)
    u = theta[:, 0, None, None] * cw + theta[:, 1, None, None] * sw  # the command at the nodes, as in _coefficients
    flags = OUT_OF_LADDER * ((u.flatten(1).amin(-1) < prob.knots[ch.pat, 0]) | (u.flatten(1).amax(-1) > prob.knots[ch.pat, -1])).long()
    flags = flags | NO_MOTION * ((amp / d[:, ::2].clamp_min(0).sqrt() < 3).any(-1)).long()
    return dict(amplitude=amp, phase=phase, covariance=cov, status=status, flags=flag_poor_fit(flags, chi2), reduced_chi2=chi2)


def _prefit_status(prob: _Problems, still):
    """``[n]`` status before fitting: :data:`NO_PIXELS` (at most 6 pixels left),
    :data:`OUT_OF_FRAME` (fewer than half the crop's pixels usable), :data:`DARK` (the data's
    correlation with the zero-mean still, in noise stds, below :data:`DARK_SNR`; the noise
    std from the median absolute deviation where none is given)."""
    P, F, M, E, h, w = prob.shape
    n = P * F * M
    keep = prob.keep
    tmpl = still.reshape(M, 1, h * w).to(prob.data)[torch.arange(n, device=keep.device) % M]  # [n, 1, hw]
    k = keep.to(prob.data.dtype)
    tmpl = (tmpl - (tmpl * k).sum(-1, keepdim=True) / k.sum(-1, keepdim=True).clamp_min(1)) * k
    W = prob.weight
    if not prob.noise_given:
        flat = torch.where(keep, prob.data, torch.full_like(prob.data, float("nan"))).flatten(1)
        med = flat.nanmedian(-1, keepdim=True).values
        mad = (flat - med).abs().nanmedian(-1).values * 1.4826
        W = k / mad.square()[:, None, None].clamp_min(torch.finfo(W.dtype).tiny)
    snr = (W * prob.data * tmpl).flatten(1).sum(-1) / (W * tmpl * tmpl).flatten(1).sum(-1).sqrt()
    status = torch.zeros(n, dtype=torch.long, device=keep.device)
    status[~(snr >= DARK_SNR)] = DARK
    status[keep.any(1).sum(-1) < 0.5 * h * w] = OUT_OF_FRAME
    status[keep.flatten(1).sum(-1) <= N_PAR] = NO_PIXELS
    return status


def fit_ladder_problems(crops, ladder: PatternLadder, window, omega, amplitude, *, power, noise_std=None, mask=None, chunk=None,
                        device=None, only=None) -> SpotFits:
    """Fit every (pattern, frequency, spot) problem with the ladder's model (module docstring).

    Args:
        crops: ``[P, F, M, E*R, h, w]`` electrons (:func:`~torchblur.dm.spot_fit.crop_problems`);
            its floating dtype is the fit's (an integer one: float64).
        ladder: :class:`PatternLadder` of the same P patterns, M spots and crop.
        window: :class:`ExposureWindow` broadcastable to ``[P, F, E*R]`` (s).
        omega: ``[F]`` rad/s.
        amplitude: the command amplitude (input units) broadcastable to ``[P, F]``: the start
            where the centroids give none.
        power: the sweep frames' laser power relative to the ladder's, ``[F]`` or a number.
        noise_std: pixel noise std broadcastable to the crops (e.g. the camera noise of the
            expected signal), or None (unweighted, the covariance from each pixel's residual;
            ``reduced_chi2`` NaN).
        mask: bool broadcastable to the crops (False: excluded), or None.
        chunk: problems per chunk; None: :func:`~torchblur.dm.spot_fit.chunk_size` with the
            chunk's ``E*R + 3K`` planes per problem (the data and the ladder's three images per level).
        device: where to fit (None: the crops').
        only: bool broadcastable to ``[P, F, M]``: the problems to fit (None: every one); the
            others are :data:`~torchblur.fit.status.NOT_FITTED`, NaN (e.g. a spot its pattern
            does not move, :func:`~torchblur.dm.plans.driven_spots`).

    Returns:
        :class:`~torchblur.dm.spot_fit.SpotFits` ``[P, F, M]`` (on ``device``): per axis the
        phasor ``s G + N n`` (module docstring) as amplitude (px) and phase (rad), the covariance of both axes
        with the ladder's noise, ``status`` (non-zero: NaN estimates), ``flags``
        (:data:`~torchblur.fit.status.OUT_OF_LADDER`, ``NO_MOTION``, ``MASKED``, ``POOR_FIT_FLAG``).
    """
    if not isinstance(crops, torch.Tensor):
        raise ShapeError(f"crops: expected a tensor [P, F, M, E*R, h, w], got {type(crops).__name__}")
    dev = torch.device(device) if device is not None else crops.device
    like = dict(dtype=crops.dtype if crops.is_floating_point() else torch.float64, device=dev)
    prob = _flat_problems(crops, ladder, window, omega, amplitude, power, noise_std, mask, like)
    P, F, M, E, h, w = prob.shape
    K = ladder.levels.shape[1]
    n = P * F * M
    b0 = _basis_at(torch.zeros(P, 1, **like), prob.knots, prob.coef)
    b0 = (b0[0][:, 0], b0[1][:, 0])  # [P, K] each: the basis and its derivative at u = 0
    chunk = chunk_size(2 * E + 4 * K, h, w, device=dev, dtype=like["dtype"]) if chunk is None else check_int(chunk, "chunk", low=1)
    status = left_out(_prefit_status(prob, ladder.still), only, (P, F, M))
    nan = torch.full((n,), float("nan"), **like)
    out = dict(amplitude=nan[:, None].repeat(1, 2), phase=nan[:, None].repeat(1, 2), covariance=nan[:, None, None].repeat(1, 4, 4),
               status=status, flags=MASKED * (~prob.keep).flatten(1).any(-1).long(), reduced_chi2=nan.clone())
    todo = torch.nonzero(status == 0).reshape(-1)
    theta0 = _starts(prob, ladder, todo, b0, chunk)
    merged = _merged_repeats(prob)  # each exposure's repeats fitted as one (the same cost but for a constant)
    n_chunks = 0
    for i0 in range(0, todo.numel(), chunk):
        ch = _chunk(merged, ladder, todo[i0:i0 + chunk], like)
        with torch.no_grad():
            r = _fit_chunk(merged, ch, theta0[i0:i0 + chunk])
        ok = r["status"] == 0
        for key in ("amplitude", "phase", "covariance"):
            r[key][~ok] = float("nan")
        for key, v in r.items():
            out[key][ch.rows] = out[key][ch.rows] | v if key == "flags" else v
        n_chunks += 1
    return SpotFits(**{k: v.reshape((P, F, M) + tuple(v.shape[1:])) for k, v in out.items()}, n_chunks=n_chunks)
