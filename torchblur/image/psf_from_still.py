"""The PSF identify should use, from frames of the still spot: a measured kernel by default,
a Gaussian where a Gaussian explains the averaged still to its noise.

Conventions (as everywhere in torchblur): ``still[n, i, j]`` is frame n at the centre of row
i, column j (x = j, y = i); frames are in the camera's units (electrons or ADU), with or
without the dark level (a constant level is estimated and removed); a PSF's intensity is per
second of exposure. ``N`` frames, ``H, W`` pixels.

What is done, in order (every step a pure function of the frames):

1. The frames are averaged: ``mean [H, W]``.
2. The noise of one frame, per pixel: ``noise_std`` if given; else, with two or more frames,
   the camera model ``var = c0 + c1 * value`` (read noise plus shot noise, in the frames' own
   units) fitted to the per-pixel frame-to-frame variance against the per-pixel mean; with one
   frame, a constant: the robust (MAD) scatter of the frame's 2-px border.
   The averaged still's noise is that over ``sqrt(N)``, and, where the frames had a measured
   level subtracted (a dark frame's mean), that level's own noise ``dark_std`` in quadrature:
   it is common to every frame, so neither the frame-to-frame scatter nor ``sqrt(N)`` sees it
   (identify's still, 16 frames less a 16-frame dark: it doubles the variance far from the spot).
3. The support: pixels significantly above the background (the noise-whitened mean, smoothed
   with a 1 px Gaussian, above ``support_sigma`` smoothed-noise stds:
   :func:`~torchblur.image.preprocess.threshold_mask`), grown by ``margin_px`` and kept where
   connected to the brightest pixel (Airy rings join the core). The background is the median of
   the mean outside the support (first guess: the median of the border); two passes; or the
   ``background`` given.
4. The kernel: ``(mean - background) * taper``, the taper 1 on the support and a raised cosine
   falling to 0 over ``taper_px`` pixels beyond it, so the noise far from the spot is not
   splatted along the motion and the kernel has no step where it ends (its Fourier shift does
   not ring); divided by the exposure: intensity per second (:class:`KernelPSF`).
5. The Gaussian: :func:`~torchblur.image.preprocess.fit_gaussian_psf` of ``mean - background``
   weighted by the noise, integrated over the pixels (as a camera's pixels integrate the light);
   its ``psf`` is then the point-sampled moment match the blur fits sample
   (:func:`~torchblur.image.psf_fit.point_sampled_equivalent`: cov + I/12, the same light).
6. The test: the reduced chi2 of the Gaussian over the support (``dof = pixels - 6``); the
   Gaussian explains the still when it is at most ``1 + chi2_z * sqrt(2 / dof)`` (``chi2_z = 4``:
   a correct Gaussian fails about 3e-5 of the time). The kernel's reduced chi2 is that of the
   light it leaves out (``(1 - taper) * (mean - background)``) over the pixels outside the
   support: about 1 when nothing but noise was cut.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from torchblur._compat import lstsq_solution
from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_choice, check_finite, check_positive, check_real_scalar
from torchblur.image.detection import threshold_mask
from torchblur.image.psf_fit import PSFFit, fit_gaussian_psf, point_sampled_equivalent
from torchblur.losses import chi2_limit
from torchblur.render.psf import GaussianPSF, KernelPSF

__all__ = ["StillPSF", "psf_from_still", "KINDS", "CHI2_Z"]

KINDS = ("auto", "kernel", "gaussian")
CHI2_Z = 4.0  #: a Gaussian passes when its reduced chi2 <= 1 + CHI2_Z sqrt(2 / dof)
_MAD_TO_STD = 1.482602218505602
_DETECT_SIGMA = 5.0  # a spot exists where the smoothed, whitened still exceeds this (as find_spots)


@dataclass(frozen=True)
class StillPSF:
    """Result of :func:`psf_from_still`: the chosen PSF and why.

    Attributes:
        psf: the PSF to fit blurred frames with: ``kernel`` or ``gaussian.psf``.
        kind: ``"kernel"`` or ``"gaussian"``: which one ``psf`` is.
        reason: one line: what was asked and the two reduced chi2 against the threshold.
        kernel: the measured :class:`KernelPSF` (frame ``[H, W]``, intensity per second).
        gaussian: the :class:`PSFFit` of the Gaussian (fitted pixel-integrated; its ``psf`` the
            point-sampled moment match, its ``model`` the fitted still); None
            where no Gaussian could be fitted (``reason`` says why).
        chi2_gaussian: 0-d, the Gaussian's reduced chi2 over the support (inf: no fit).
        chi2_kernel: 0-d, the reduced chi2 of the light the kernel leaves out, outside the support.
        chi2_threshold: the largest ``chi2_gaussian`` that passes, ``1 + CHI2_Z sqrt(2 / dof)``.
        background: 0-d, the level removed from every frame (frame units).
        noise_std: ``[H, W]``, the noise std of the averaged still (frame units; ``dark_std`` included).
        noise_model: ``(c0, c1)`` with one frame's variance ``c0 + c1 * value`` (value in the
            frames' units as given, background included); ``None`` when ``noise_std`` was
            given or only one frame came (then the noise is ``noise_std`` / a constant).
        frame_noise: ``[H, W]``, one still frame's noise std.
        support: bool ``[H, W]``, the pixels the kernel keeps whole.
        taper: ``[H, W]`` in [0, 1], the kernel's weight per pixel.
        touches_edge: the support reaches the frame's border (the kernel is cut there).
        n_frames: N.
        exposure_s: the still frames' exposure (s).
    """

    psf: KernelPSF | GaussianPSF
    kind: str
    reason: str
    kernel: KernelPSF
    gaussian: PSFFit | None
    chi2_gaussian: torch.Tensor
    chi2_kernel: torch.Tensor
    chi2_threshold: float
    background: torch.Tensor
    noise_std: torch.Tensor
    noise_model: tuple | None
    frame_noise: torch.Tensor
    support: torch.Tensor
    taper: torch.Tensor
    touches_edge: bool
    n_frames: int
    exposure_s: float

    def kernel_noise_factor(self, exposures_s) -> torch.Tensor:
        """The factor by which a fit's std grows from the measured kernel's own noise, for
        blurred frames of exposures ``exposures_s`` (s, ``[..., E]``: the exposures fitted
        together): ``sqrt(1 + sum_e T_e / (N T_still))``, ``[...]``; 1 for a Gaussian.

        The rule of a template match where shot noise dominates: the data's light
        ``sum_e T_e`` and the template's ``N T_still`` each give the estimate a variance
        inversely proportional to it. Multiply ``amplitude_std`` and ``phase_std`` by it
        (``benchmarks/bench_hcipy.py`` checks it: rms(error/std) 1.21 -> 1.00 with 4 still
        frames). Average enough still frames and it is near 1 (32 frames there: 1.03)."""
        t = check_positive(as_tensor(exposures_s, "exposures_s", dtype=torch.float64), "exposures_s")
        if t.dim() == 0:
            t = t[None]
        ratio = t.sum(-1) / (self.n_frames * self.exposure_s)
        return torch.ones_like(ratio) if self.kind == "gaussian" else (1 + ratio).sqrt()

    def kernel_variance(self) -> torch.Tensor:
        """The measured kernel's per-pixel variance ``[H, W]`` ((intensity per second)^2): the
        averaged still's noise times the taper, over the exposure, squared (0 where the taper is;
        the background's own error, common to every pixel, is left out). A fit given it
        (``fit_multisine(..., kernel_var=)``) propagates the kernel's noise into its covariance
        exactly (:mod:`torchblur.fit.kernel_noise`) instead of :meth:`kernel_noise_factor`'s rule."""
        return (self.noise_std * self.taper / self.exposure_s).square().to(self.kernel.kernel)

    def frame_noise_std(self, frames) -> torch.Tensor:
        """Per-pixel noise std of other frames of the same camera (e.g. the blurred ones),
        ``[..., H, W]`` like ``frames`` (in the same units and with the same offset as the
        still frames): ``sqrt(c0 + c1 * frames)`` with the fitted camera model, else the
        still's single-frame noise (broadcast)."""
        f = as_tensor(frames, "frames", like=self.frame_noise)
        if self.noise_model is None:
            return self.frame_noise.to(f).expand(f.shape)
        c0, c1 = self.noise_model
        return (c0 + c1 * f.detach()).clamp_min(c0 if c0 > 0 else torch.finfo(f.dtype).tiny).sqrt()


def _frames(still) -> tuple[torch.Tensor, torch.dtype]:
    """The frames ``[N, H, W]`` in float64 (checked) and the dtype results are returned in."""
    if not isinstance(still, torch.Tensor):
        still = as_tensor(still, "still")
    if still.is_complex() or still.dtype == torch.bool:
        raise InputTypeError(f"still: expected a real tensor [N, H, W] or [H, W], got dtype {still.dtype}")
    if still.dim() not in (2, 3):
        raise ShapeError(f"still: expected shape [N, H, W] or [H, W], got {tuple(still.shape)}")
    if still.dim() == 2:
        still = still[None]
    N, H, W = still.shape
    if N < 1 or H < 5 or W < 5:
        raise ShapeError(f"still: expected at least one frame of at least 5 x 5 px in [N, H, W], got {tuple(still.shape)}")
    check_finite(still, "still")
    in_dtype = still.dtype if still.is_floating_point() else torch.get_default_dtype()
    return still.detach().to(torch.float64), in_dtype


def _border(H: int, W: int, device) -> torch.Tensor:
    b = torch.zeros(H, W, dtype=torch.bool, device=device)
    b[:2, :] = b[-2:, :] = b[:, :2] = b[:, -2:] = True
    return b


def _frame_noise(f: torch.Tensor, mean: torch.Tensor, noise_std):
    """One frame's noise std ``[H, W]`` and the camera model ``(c0, c1)`` (or None)."""
    N, H, W = f.shape
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=mean), "noise_std")
        if s.dim() not in (0, 2) or (s.dim() == 2 and tuple(s.shape) != (H, W)):
            raise ShapeError(f"noise_std: expected a number or a map [H, W] = [{H}, {W}] (one frame's noise), got {tuple(s.shape)}")
        return s.to(mean).expand(H, W), None
    if N == 1:
        v = f[0][_border(H, W, f.device)]
        s = _MAD_TO_STD * (v - v.median()).abs().median()
        if not s > 0:
            raise ParameterError("noise_std: one still frame with a noise-free border; give noise_std or more frames")
        return s.expand(H, W), None
    var = f.var(0, unbiased=True).reshape(-1)
    x = mean.reshape(-1)
    A = torch.stack([torch.ones_like(x), x], -1)
    keep = torch.ones_like(var, dtype=torch.bool)
    w = torch.ones_like(var)
    # var = c0 + c1 x by least squares weighted by 1 / model^2 (a sample variance's std is
    # proportional to its mean), iterated; pixels beyond 5 of those stds (hot ones) dropped.
    for _ in range(5):
        sw = (w * keep)[:, None]
        c = lstsq_solution(A * sw, var[:, None] * sw)[:, 0]
        model = (c[0] + c[1] * x).clamp_min(float(var.median()) * 1e-3)
        w = 1 / model
        keep = (var - model).abs() <= 5 * model * math.sqrt(2 / (N - 1))
    c0, c1 = float(c[0]), max(float(c[1]), 0.0)
    floor = float(var.median()) * 1e-3
    if c0 <= floor:  # no read-noise floor: the smallest measured variance sets it
        c0 = max(float(var[keep].min()), floor) if bool(keep.any()) else max(float(var.median()), 1e-30)
    return (c0 + c1 * mean).clamp_min(c0).sqrt(), (c0, c1)


def _grow(mask: torch.Tensor, px: int) -> torch.Tensor:
    """Dilate a bool ``[H, W]`` mask by ``px`` pixels (3x3 steps)."""
    m = mask[None, None].to(torch.float32)
    for _ in range(px):
        m = torch.nn.functional.max_pool2d(m, 3, stride=1, padding=1)
    return m[0, 0] > 0


def _connected_to(seed: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The part of ``mask`` 8-connected to ``seed`` (morphological reconstruction), ``[H, W]``."""
    cur = seed & mask
    while True:
        nxt = _grow(cur, 1) & mask
        if bool((nxt == cur).all()):
            return cur
        cur = nxt


def _support(mean, sigma, background, support_sigma, margin_px):
    """Pixels of the spot ``[H, W]``: significant, grown by the margin, connected to the peak."""
    white = (mean - background) / sigma
    if not bool(threshold_mask(white, 1.0, _DETECT_SIGMA).any()):  # find_spots' rule: pure noise gives no spot
        raise ParameterError(f"still: expected a spot above the noise, got no pixel above {_DETECT_SIGMA:g} smoothed-noise std "
                             f"(a dark frame, or too few still frames)")
    sig = threshold_mask(white, 1.0, support_sigma)
    peak = torch.zeros_like(sig)
    peak.view(-1)[int(torch.argmax(torch.where(sig, white, torch.full_like(white, -math.inf))))] = True
    return _connected_to(peak, _grow(sig, margin_px))


def _taper(support: torch.Tensor, taper_px: int, dtype) -> torch.Tensor:
    """1 on the support, ``cos^2`` falling to 0 over ``taper_px`` pixels beyond it, ``[H, W]``."""
    w = support.to(dtype)
    grown = support
    for d in range(1, taper_px + 1):
        ring = _grow(grown, 1) & ~grown
        w = w + ring.to(dtype) * math.cos(0.5 * math.pi * d / (taper_px + 1)) ** 2
        grown = grown | ring
    return w


def _dark_std(dark_std, like: torch.Tensor) -> torch.Tensor:
    """``dark_std`` checked: 0-d or ``[H, W]`` like ``like`` (0 where None)."""
    if dark_std is None:
        return torch.zeros((), dtype=like.dtype, device=like.device)
    s = check_positive(as_tensor(dark_std, "dark_std", like=like), "dark_std", strict=False)
    if s.dim() not in (0, 2) or (s.dim() == 2 and s.shape != like.shape):
        raise ShapeError(f"dark_std: expected a number or a map [H, W] = {list(like.shape)}, got {tuple(s.shape)}")
    return s


def _measure(f, noise_std, dark_std, background, support_sigma, margin_px, taper_px):
    """Mean, noise, background, support and taper of the frames (``background`` None: estimated)."""
    N, H, W = f.shape
    mean = f.mean(0)
    frame_noise, model = _frame_noise(f, mean, noise_std)
    sigma = (frame_noise.square() / N + _dark_std(dark_std, mean).square()).sqrt()
    if background is not None:
        level = torch.as_tensor(background, dtype=mean.dtype, device=mean.device)
        support = _support(mean, sigma, level, support_sigma, margin_px)
        return mean, frame_noise, model, sigma, level, support, _taper(support, taper_px, mean.dtype)
    level = mean[_border(H, W, f.device)].median()
    for _ in range(2):
        support = _support(mean, sigma, level, support_sigma, margin_px)
        outside = ~_grow(support, taper_px)
        if int(outside.sum()) < 16:
            raise ParameterError(f"background: the spot fills the frame ({int(outside.sum())} pixels outside its support of "
                                 f"{int(support.sum())}), so its level cannot be estimated from the still; give background= "
                                 f"(e.g. from frames with the source off), or a larger frame")
        level = mean[outside].median()
    return mean, frame_noise, model, sigma, level, support, _taper(support, taper_px, mean.dtype)


def psf_from_still(
    still,
    exposure_s,
    noise_std=None,
    *,
    kind: str = "auto",
    background=None,
    support_sigma: float = 3.0,
    margin_px: int = 2,
    taper_px: int = 3,
    dark_std=None,
) -> StillPSF:
    """The PSF to fit blurred frames with, from frames of the still spot (module docstring).

    Args:
        still: frames of the still spot, ``[N, H, W]`` or ``[H, W]`` (N = 1), the same frame
            (crop) as the blurred frames the PSF will fit; a constant level (dark level, stray
            light) may remain: it is estimated and removed.
        exposure_s: their exposure in seconds (> 0): the PSF is per second.
        noise_std: one frame's noise std: a number or ``[H, W]``; None: measured from the
            frames (module docstring, step 2).
        kind: ``"auto"`` (the Gaussian where it passes the chi2 test, else the kernel),
            ``"kernel"`` or ``"gaussian"`` (forced; both chi2 are still reported).
        background: the constant level in the frames (frame units: dark level plus stray
            light, e.g. from frames with the source off); None: estimated, the median outside
            the spot's support (a spot whose wings fill the frame needs it given).
        support_sigma: significance (smoothed-noise stds) of a pixel of the spot (> 0).
        margin_px: pixels added around the significant ones (int >= 0).
        taper_px: width of the kernel's fall to 0 beyond the support (int >= 0).
        dark_std: the noise std of a level already subtracted from every frame (frame units, a
            number or ``[H, W]``), e.g. a dark frame's mean: its read noise over the square root
            of its frame count; None: nothing measured was subtracted. Added in quadrature to
            the averaged still's noise (module docstring, step 2).

    Returns:
        :class:`StillPSF`: ``psf`` (``KernelPSF`` with kernel ``[H, W]``, or ``GaussianPSF``
        of batch ``[]`` with point-sampled pixels), ``kind``, ``reason`` and the evidence.

    Example:
        >>> res = psf_from_still(still_frames, exposure_s=1e-3)        # [16, 48, 64]
        >>> fit = fit_sinusoid(images, res.psf, window, omega, noise_std=res.frame_noise_std(raw_images))
    """
    f, in_dtype = _frames(still)
    N, H, W = f.shape
    exposure, support_sigma, background = _check_options(exposure_s, kind, support_sigma, margin_px, taper_px, background)
    mean, frame_noise, model, sigma, background, support, taper = _measure(f, noise_std, dark_std, background, support_sigma, margin_px, taper_px)
    signal = mean - background
    kernel = KernelPSF((signal * taper).to(in_dtype), exposure)
    out_px = taper < 1
    chi2_k = (((1 - taper) * signal / sigma).square()[out_px].sum() / out_px.sum().clamp_min(1))

    dof = max(int(support.sum()) - 6, 1)
    threshold = chi2_limit(dof, CHI2_Z)
    gauss, chi2_g, failed = _gaussian_candidate(signal, sigma, support, dof, exposure, in_dtype)
    if kind == "gaussian" and gauss is None:
        raise ParameterError(f"kind: 'gaussian' asked for, but no Gaussian fits the still{failed}")
    passes = bool(chi2_g <= threshold)
    chosen = kind if kind != "auto" else ("gaussian" if passes else "kernel")
    why = f"asked for {kind}" if kind != "auto" else ("the Gaussian explains the still to its noise" if passes
                                                       else "the Gaussian does not explain the still")
    reason = (f"{chosen}: {why} (reduced chi2 Gaussian {float(chi2_g):.3g} over {int(support.sum())} px, threshold "
              f"{threshold:.3g}; kernel {float(chi2_k):.3g} for the light it leaves out; {N} frames{failed})")
    edge = bool((support & _border(H, W, support.device)).any())
    return StillPSF(
        psf=gauss.psf if chosen == "gaussian" else kernel, kind=chosen, reason=reason, kernel=kernel, gaussian=gauss,
        chi2_gaussian=chi2_g, chi2_kernel=chi2_k, chi2_threshold=threshold, background=background, noise_std=sigma,
        noise_model=model, frame_noise=frame_noise, support=support, taper=taper, touches_edge=edge, n_frames=N,
        exposure_s=exposure,
    )


def _check_options(exposure_s, kind, support_sigma, margin_px, taper_px, background):
    """:func:`psf_from_still`'s options checked: ``(exposure s, support_sigma, background or
    None)`` as floats; errors name the argument."""
    e = as_tensor(exposure_s, "exposure_s", dtype=torch.float64)
    if e.numel() != 1:
        raise ShapeError(f"exposure_s: expected one exposure (a number), got shape {tuple(e.shape)}")
    exposure = float(check_positive(e, "exposure_s").reshape(()))
    check_choice(kind, "kind", KINDS)
    support_sigma = check_real_scalar(support_sigma, "support_sigma", positive=True)
    for name, v in (("margin_px", margin_px), ("taper_px", taper_px)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ParameterError(f"{name}: expected an integer >= 0, got {v!r}")
    if background is not None:
        background = check_real_scalar(background, "background")
    return exposure, support_sigma, background


def _gaussian_candidate(signal, sigma, support, dof: int, exposure: float, in_dtype):
    """The Gaussian fitted to the averaged still ``signal [H, W]`` (noise ``sigma``) with pixel
    integration, then as its point-sampled equivalent (the pixel model the blur fits sample):
    ``(PSFFit or None, reduced chi2 over the support's pixels with dof degrees of
    freedom, "" or why no Gaussian fits)``; a spot no Gaussian fits (e.g. wider than the frame)
    gives None and chi2 inf (the kernel it is)."""
    try:
        gauss = fit_gaussian_psf(signal.to(in_dtype), exposure_s=exposure, noise_std=sigma.to(in_dtype), fit_background=False,
                                 pixel_integration=True)
    except ParameterError as exc:
        return None, torch.tensor(math.inf, dtype=signal.dtype), f"; the Gaussian fit failed: {exc}"
    chi2_g = ((signal - gauss.model.to(signal)) / sigma).square()[support].sum() / dof
    return replace(gauss, psf=point_sampled_equivalent(gauss.psf)), chi2_g, ""
