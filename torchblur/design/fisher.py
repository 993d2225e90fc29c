"""Design of the image set that identifies a multisine: Fisher information, greedy D-optimal.

One image records where the spot spent its time during its window, not in what order. For
N tones the unknowns are ``theta = (M_1..M_N, phi_1..phi_N[, scale])`` and the Fisher
information of an image set is the sum over its images of ``J^T diag(1 / var) J``
(``J = d image / d theta`` through the differentiable renderer, ``var`` = read noise^2 + the
expected electrons, shot noise). Some windows are blind in some directions: an exposure of
whole common periods ``T0`` cannot see a time shift (``phi_k -> phi_k + omega_k tau``), so its
Fisher matrix is singular; one image (any window) also has the discrete alias of the time
reversal about its centre. A set of windows at different positions and exposures makes the
matrix regular, and its inverse predicts the stds a fit reaches.

:func:`design_acquisition` chooses the set greedily from candidate (window start, exposure)
pairs within a common period and the camera's longest exposure: at each step the candidate
that most increases ``log det F`` (averaged over a few hypotheses of the unknown phases, so
the design does not depend on a guess) is added (repeats allowed: a repeat is one more
frame), until ``n_images`` or until the predicted stds of every ``|H|`` (relative) and phase
(rad) reach ``target_std`` in every hypothesis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from torchblur.errors import ParameterError, ShapeError, as_tensor, check_finite, check_int, check_positive, check_real_scalar
from torchblur.fit.inputs import unit_direction
from torchblur.fit.multisine import render_multisine_with_jacobian
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import RenderSettings, choose_node_count
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Multisine

__all__ = ["AcquisitionDesign", "candidate_windows", "image_fisher", "predicted_std", "design_acquisition"]


def candidate_windows(period_s: float, *, max_exposure_s: float, n_offsets: int = 16,
                      exposure_fractions=(0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0), dtype=torch.float64) -> ExposureWindow:
    """Candidate windows ``[C]``: starts at ``n_offsets`` equally spaced points of the common
    period ``period_s`` times the exposures ``exposure_fractions * period_s`` (capped at
    ``max_exposure_s``, duplicates removed); ``C = n_offsets * n_exposures``, start-major."""
    T0 = check_real_scalar(period_s, "period_s", positive=True)
    tmax = check_real_scalar(max_exposure_s, "max_exposure_s", positive=True)
    n_offsets = check_int(n_offsets, "n_offsets", low=1)
    fr = np.asarray(exposure_fractions, dtype=np.float64).reshape(-1)
    if fr.size == 0 or np.any(fr <= 0) or not np.all(np.isfinite(fr)):
        raise ParameterError(f"exposure_fractions: expected fractions > 0, got {fr.tolist()}")
    te = np.unique(np.round(np.minimum(fr * T0, tmax), 15))
    starts = np.arange(n_offsets) * T0 / n_offsets
    s, t = np.meshgrid(starts, te, indexing="ij")
    return ExposureWindow(torch.as_tensor(s.reshape(-1), dtype=dtype), torch.as_tensor(t.reshape(-1), dtype=dtype))


def _crop(amplitude_bound: float, psf: GaussianPSF, H: int, W: int, u: torch.Tensor):
    """The pixels a motion of up to ``amplitude_bound`` px along the unit ``u`` reaches."""
    sd = torch.diagonal(psf.cov, dim1=-2, dim2=-1).sqrt()
    c = psf.center
    rx, ry = amplitude_bound * float(u[0].abs()), amplitude_bound * float(u[1].abs())
    x0 = max(0, int(math.floor(float(c[0] - rx - 7 * sd[0]))))
    x1 = min(W, int(math.ceil(float(c[0] + rx + 7 * sd[0]))) + 1)
    y0 = max(0, int(math.floor(float(c[1] - ry - 7 * sd[1]))))
    y1 = min(H, int(math.ceil(float(c[1] + ry + 7 * sd[1]))) + 1)
    return y0, y1, x0, x1


def image_fisher(theta, omega, psf: GaussianPSF, window: ExposureWindow, *, frame_shape, read_noise_e: float,
                 peak_e: float | None = None, settings: RenderSettings | None = None, direction=None) -> torch.Tensor:
    """Fisher information of each image of a multisine motion, ``[n, C, P, P]``.

    Args:
        theta: ``[n, P]`` parameter hypotheses ``(M_1..M_N px, phi_1..phi_N rad[, scale])``.
        omega: tone frequencies (rad/s), ``[N]``.
        psf: the spot at rest (a single PSF; amplitude in electrons per second, laser power
            included).
        window: candidate windows ``[C]`` (s, command clock).
        frame_shape: ``(H, W)``.
        read_noise_e: read noise (electrons); shot noise is added from the model.
        peak_e: None: every image at the PSF's amplitude; a number: the laser power follows
            the exposure so that a still spot would collect ``peak_e`` electrons at its peak in
            every image (PSF amplitude ``peak_e / exposure``).
        settings: renderer settings (nodes from the motion, panels of 3.5 PSF widths).
        direction: the motion's image direction (x, y) (normalised); None: +x.

    ``F[h, c] = J_hc^T diag(1 / (read_noise^2 + image_hc)) J_hc`` over the pixels of image c
    under hypothesis h (pixels beyond 7 PSF stds of the motion are left out: their
    derivatives are below e^-24 of the peak).
    """
    theta = check_finite(as_tensor(theta, "theta", dtype=torch.float64), "theta")
    if theta.dim() == 1:
        theta = theta[None]
    omega = check_positive(as_tensor(omega, "omega", like=theta), "omega").reshape(-1)
    N = omega.numel()
    n, P = theta.shape
    if P not in (2 * N, 2 * N + 1):
        raise ShapeError(f"theta: expected a last dim of 2N = {2 * N} or {2 * N + 1}, got {P}")
    if not isinstance(psf, GaussianPSF) or psf.shape != ():
        raise ParameterError("psf: expected a single GaussianPSF (batch shape [])")
    H, W = (int(v) for v in frame_shape)
    dtype = theta.dtype
    psf = psf.to(dtype)
    C = window.shape[0]
    u = unit_direction(direction, theta).reshape(2)
    bound = float(theta[:, :N].abs().sum(-1).max()) * 1.2 + 0.5
    y0, y1, x0, x1 = _crop(bound, psf, H, W, u)
    center = psf.center - torch.tensor([x0, y0], dtype=dtype)
    settings = settings or RenderSettings(panel_path_sigmas=3.5)
    M_b = theta[:, :N].abs().amax(0) * 1.2 + 0.5
    traj = Multisine(torch.stack([M_b, torch.zeros_like(M_b)], -1), torch.zeros(N, 2, dtype=dtype), omega)
    S = settings.nodes or choose_node_count(traj.path_length(ExposureWindow(torch.zeros_like(window.duration), window.duration)),
                                            psf.sigma_min(), settings)
    out = []
    # one hypothesis at a time, candidates in chunks (bounded memory)
    chunk = max(1, int(4e7 // max(1, S * (y1 - y0 + x1 - x0) * (2 * N + 1))))
    for h in range(n):
        Fh = []
        for i in range(0, C, chunk):
            c = min(C, i + chunk) - i
            th = theta[h].expand(c, P)
            amp = psf.amplitude.expand(c) if peak_e is None else peak_e / window.duration[i:i + c].to(dtype)
            p = GaussianPSF(center.expand(c, 2), psf.cov.expand(c, 2, 2), amp)
            win = ExposureWindow(window.start[i:i + c, None].to(dtype), window.duration[i:i + c, None].to(dtype))
            img, J = render_multisine_with_jacobian(th, omega.expand(c, N), p, win, height=y1 - y0, width=x1 - x0, nodes=S,
                                                    nodes_per_panel=settings.nodes_per_panel, direction=u)
            var = read_noise_e**2 + img.clamp_min(0)
            J = J.reshape(c, -1, P)
            Fh.append((J / var.reshape(c, -1, 1)).transpose(-1, -2) @ J)
        out.append(torch.cat(Fh, 0))
    return torch.stack(out, 0)


def predicted_std(fisher: torch.Tensor, amplitude) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted (Cramer-Rao) stds from a Fisher matrix ``[..., P, P]``: the relative std of
    each amplitude ``std(M_k) / M_k`` (= that of ``|H_k|``) and the phase std (rad), each
    ``[..., N]`` (inf where the matrix is singular)."""
    amplitude = as_tensor(amplitude, "amplitude", like=fisher)
    N = amplitude.shape[-1]
    cov, info = torch.linalg.inv_ex(fisher)
    d = torch.diagonal(cov, dim1=-2, dim2=-1)
    bad = (info != 0)[..., None] | (d <= 0) | ~torch.isfinite(d)
    # a nearly singular matrix: relative condition below round-off
    ev = torch.linalg.eigvalsh(fisher / torch.sqrt(torch.diagonal(fisher, dim1=-2, dim2=-1).clamp_min(1e-300)[..., :, None]
                                                  * torch.diagonal(fisher, dim1=-2, dim2=-1).clamp_min(1e-300)[..., None, :]))
    bad = bad | (ev[..., :1] <= 1e-12 * ev[..., -1:])
    std = torch.where(bad, torch.full_like(d, float("inf")), d.clamp_min(0).sqrt())
    return std[..., :N] / amplitude.abs(), std[..., N:2 * N]


@dataclass
class AcquisitionDesign:
    """An image set for one multisine.

    Attributes:
        window_start_s: start of each window after the start of a common period (s), ``(E,)``.
        exposure_s: exposure of each window (s), ``(E,)``.
        period_s: the common period T0 (s).
        fisher: Fisher information of the set under each phase hypothesis, ``[Hh, P, P]``.
        amplitude_rel_std: predicted ``std |H_k| / |H_k|``, worst hypothesis, ``(N,)``.
        phase_std: predicted phase std (rad), worst hypothesis, ``(N,)``.
        met_target: the predicted stds reached ``target_std`` (auto size).
        log_det: the criterion after each image.
        n_candidates: candidates considered.
    """

    window_start_s: tuple
    exposure_s: tuple
    period_s: float
    fisher: torch.Tensor
    amplitude_rel_std: np.ndarray
    phase_std: np.ndarray
    met_target: bool
    log_det: list = field(default_factory=list)
    n_candidates: int = 0

    @property
    def n_images(self) -> int:
        return len(self.exposure_s)

    def windows(self, dtype=torch.float64) -> ExposureWindow:
        """The windows ``[E]`` (s from the start of a common period)."""
        return ExposureWindow(torch.tensor(self.window_start_s, dtype=dtype), torch.tensor(self.exposure_s, dtype=dtype))


def _check_design_inputs(amplitude, omega, period_s, counts: dict, n_images, target_std):
    """The public entry's checks -> ``(amplitude [N], omega [N], T0, target)`` (float64)."""
    amplitude = check_finite(as_tensor(amplitude, "amplitude", dtype=torch.float64), "amplitude").reshape(-1).abs()
    omega = check_positive(as_tensor(omega, "omega", dtype=torch.float64), "omega").reshape(-1)
    N = amplitude.numel()
    if omega.numel() != N:
        raise ShapeError(f"omega: expected {N} values (one per amplitude), got {omega.numel()}")
    T0 = check_real_scalar(period_s, "period_s", positive=True)
    for name, v in counts.items():
        check_int(v, name, low=1)
    if n_images is not None:
        check_int(n_images, "n_images", low=1)
    return amplitude, omega, T0, check_real_scalar(target_std, "target_std", positive=True)


def _hypotheses(amplitude, phase, n_hypotheses: int, seed: int, fit_scale: bool) -> torch.Tensor:
    """Parameter hypotheses ``[Hh, P]``: the amplitudes with random phases (seeded; ``phase``,
    if given, the first), and a unit scale."""
    N = amplitude.numel()
    g = torch.Generator().manual_seed(int(seed))
    hyp = (torch.rand(n_hypotheses, N, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    if phase is not None:
        hyp[0] = check_finite(as_tensor(phase, "phase", dtype=torch.float64), "phase").reshape(-1)
    return torch.cat([amplitude.expand(n_hypotheses, N), hyp] + ([torch.ones(n_hypotheses, 1, dtype=torch.float64)]
                                                                 if fit_scale else []), -1)


def _whole_periods(window: ExposureWindow, T0: float) -> torch.Tensor:
    """bool ``[C]``: exposures of whole periods have no centre (they see every time shift)."""
    return (torch.remainder(window.duration / T0 + 0.5, 1.0) - 0.5).abs() < 1e-6


def _new_centre_only(crit, centre, cand_whole, real: list, T0: float) -> torch.Tensor:
    """The criterion ``[C]`` with every candidate at the one window centre so far (mod ``T0 / 2``)
    ruled out: only a new centre resolves the time-reversal alias. ``real``: the centres so far."""
    if not real:
        return crit
    d = (torch.remainder(centre - real[0] + T0 / 4, T0 / 2) - T0 / 4).abs()  # [C] centre distance mod T0/2
    d = torch.where(cand_whole, torch.zeros_like(d), d)
    if all(float((torch.remainder(r - real[0] + T0 / 4, T0 / 2) - T0 / 4).abs()) < 0.02 * T0 for r in real):
        crit = torch.where(d >= 0.02 * T0, crit, torch.full_like(crit, -float("inf")))
    return crit


def design_acquisition(amplitude, omega, psf: GaussianPSF, *, period_s: float, max_exposure_s: float, frame_shape,
                       read_noise_e: float, phase=None, n_images: int | None = None, max_images: int = 16,
                       min_images: int = 2, target_std: float = 2e-3, n_hypotheses: int = 4, fit_scale: bool = True,
                       candidates: ExposureWindow | None = None, peak_e: float | None = None,
                       taken: ExposureWindow | None = None, seed: int = 0, direction=None) -> AcquisitionDesign:
    """Greedy D-optimal image set for N tones of expected output amplitudes ``amplitude``.

    Args:
        amplitude: expected ``M_k`` (px), ``[N]``.
        omega: tone frequencies (rad/s), ``[N]``, harmonics of ``2 pi / period_s``.
        psf: the spot at rest, electrons per second (laser power included).
        period_s: the common period T0 (s).
        max_exposure_s: the camera's longest exposure (s).
        frame_shape: ``(H, W)``.
        read_noise_e: read noise (electrons).
        phase: a guess of the output phases (rad), ``[N]``: used as the first hypothesis; the
            other ``n_hypotheses - 1`` are random (seeded).
        n_images: the set's size; None: grow until the predicted stds of every tone are at
            most ``target_std`` (relative |H|, and rad) in every hypothesis, at most
            ``max_images``.
        min_images: at least this many images, with at least two distinct window centres
            (one image cannot resolve the time-reversal alias, whatever its Fisher matrix).
        fit_scale: include an intensity scale as a nuisance parameter.
        candidates: candidate windows ``[C]``; default :func:`candidate_windows`.
        peak_e: None: one laser power for all images (the PSF's amplitude); a number: a power
            per image that gives a still spot ``peak_e`` electrons at its peak whatever the
            exposure (see :func:`image_fisher`).
        taken: windows ``[T]`` of frames already taken of the same motion (a pilot): their
            information is counted, the design adds to them (they are not in the result).
        direction: the motion's image direction (x, y) (normalised); None: +x.

    Returns:
        :class:`AcquisitionDesign`.
    """
    amplitude, omega, T0, target = _check_design_inputs(
        amplitude, omega, period_s, {"max_images": max_images, "min_images": min_images, "n_hypotheses": n_hypotheses}, n_images,
        target_std)
    N = amplitude.numel()
    cand = candidates if candidates is not None else candidate_windows(T0, max_exposure_s=max_exposure_s)
    theta = _hypotheses(amplitude, phase, n_hypotheses, seed, fit_scale)
    P = theta.shape[-1]
    fisher_kw = dict(frame_shape=frame_shape, read_noise_e=read_noise_e, peak_e=peak_e, direction=direction)
    F = image_fisher(theta, omega, psf, cand, **fisher_kw)  # [Hh, C, P, P]
    D = torch.diagonal(F, dim1=-2, dim2=-1).mean((0, 1)).clamp_min(1e-300).sqrt()  # parameter scales
    DD = D[:, None] * D[None, :]
    Fn = F / DD
    eye = torch.eye(P, dtype=torch.float64) * 1e-8
    centre = torch.remainder(cand.start + cand.duration / 2, T0 / 2)
    cand_whole = _whole_periods(cand, T0)
    sel: list[int] = []
    F_sel = torch.zeros(n_hypotheses, P, P, dtype=torch.float64)
    c_ref = None
    n_taken = 0
    if taken is not None and taken.shape[0]:
        F_sel = image_fisher(theta, omega, psf, taken, **fisher_kw).sum(1) / DD
        n_taken = taken.shape[0]
        whole = _whole_periods(taken, T0)  # only the others have a centre
        if bool((~whole).any()):
            c_ref = torch.remainder(taken.start + taken.duration / 2, T0 / 2)[~whole][0]
    history: list[float] = []
    rel = ph = torch.full((N,), float("inf"), dtype=torch.float64)
    limit = n_images if n_images is not None else max_images
    met = False
    while len(sel) < limit:
        crit = torch.linalg.slogdet(F_sel[:, None] + Fn + eye)[1].mean(0)  # [C]
        real = ([c_ref] if c_ref is not None else []) + [centre[k] for k in sel if not bool(cand_whole[k])]
        crit = _new_centre_only(crit, centre, cand_whole, real, T0)
        c = int(crit.argmax())
        sel.append(c)
        F_sel = F_sel + Fn[:, c]
        history.append(float(crit[c]))
        r, p = predicted_std(F_sel * DD, amplitude)
        rel, ph = r.amax(0), p.amax(0)
        met = bool((rel <= target).all() and (ph <= target).all())
        if n_images is None and met and len(sel) + n_taken >= min_images:
            break
    return AcquisitionDesign(window_start_s=tuple(float(cand.start[c]) for c in sel),
                             exposure_s=tuple(float(cand.duration[c]) for c in sel), period_s=T0, fisher=F_sel * DD,
                             amplitude_rel_std=rel.numpy(), phase_std=ph.numpy(), met_target=met, log_det=history,
                             n_candidates=cand.shape[0])
