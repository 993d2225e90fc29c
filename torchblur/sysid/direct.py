"""Direct identification: the parameters of a parametric model fitted to ALL images at once.

For sweep point k the model ``H(s; theta)`` gives the spot's motion
``M_k sin(omega_k t + phi_k)`` with ``M_k = A_k |H(j omega_k)|``, ``phi_k = angle H(j omega_k)``;
its images are compared with the measured ones over every pixel (weighted least squares, a
per-point scale and background as nuisance parameters). The model forms ("tf", "modal"), the
blockwise Levenberg-Marquardt (Schur complement of the nuisance blocks) and the covariance
(inverse Fisher information, nuisance profiled out): docs/direct_identification.md. The forms'
parametrisation is in :mod:`torchblur.sysid.parametric`; the single-exposure start in
:mod:`torchblur.sysid.alias_resolution`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_frequency_grid, as_tensor, as_unit_direction, check_choice,
                     check_finite, check_positive)
from torchblur.fit.inputs import flat_psf
from torchblur.fit.problem import crop_box
from torchblur.fit.status import POOR_FIT_CHI2, flag_poor_fit
from torchblur.losses import pixel_weights
from torchblur.render.blur import RenderSettings, choose_node_count, quadrature_nodes
from torchblur.render.camera import CameraNoise, noise_sets_weights
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.splat import sine_blur_with_jacobian, window_nodes
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow
from torchblur.sysid.frequency_response_io import read_json_doc, write_json_doc
from torchblur.sysid.model_io import direct_fields_from_dict, direct_fit_to_dict
from torchblur.sysid.parametric import _poles_zeros, _response, _Structure, _structure_from_tf
from torchblur.sysid.tf_fit import TransferFunctionFit

__all__ = ["DirectModelFit", "fit_direct", "FORMS"]

#: Model forms of :func:`fit_direct`.
FORMS = ("tf", "modal")
_AXES = ("x", "y")


# ------------------------------------------------------------------------ result
@dataclasses.dataclass(frozen=True, eq=False)
class DirectModelFit:
    """Result of :func:`fit_direct`.

    Attributes:
        form: "tf" or "modal" (docs/direct_identification.md).
        param_names: names of the P model parameters (rad/s for omega_n and rates, seconds
            for delay_s, the gains in px per input unit).
        params: [P] the estimates (natural units).
        covariance: [P, P] inverse Fisher information (nuisance parameters profiled out).
        std: [P] sqrt of its diagonal.
        start_params: [P] the start (from the two-step model).
        delay_s: the delay (estimated, or the fixed one).
        cost: weighted sum of squared residuals over every used pixel.
        dof: used pixels minus all fitted parameters (model and nuisance).
        reduced_chi2: cost / dof (about 1 with the right noise model).
        noise_estimated: True when neither noise_std nor noise was given (covariance scaled by
            reduced_chi2).
        converged: whether Levenberg-Marquardt converged.
        n_iter: its iterations (both passes' with ``noise``).
        used: [F] bool, the points fitted (False: excluded by ``valid``).
        n_excluded: how many points were excluded.
        scale, background: [F] per-point nuisance estimates (NaN where excluded; background
            None when not fitted).
        point_reduced_chi2: [F] each point's reduced chi2 under the fitted model: its weighted
            squared residuals over the pixels the model reaches (the fit's crop) divided by
            their count less its nuisance parameters and its share ``P / n_used`` of the model's;
            NaN where excluded or where the noise was estimated (then it means nothing).
        flags: [F] int, :data:`~torchblur.fit.status.POOR_FIT_FLAG` where ``point_reduced_chi2``
            exceeds :data:`~torchblur.fit.status.POOR_FIT_CHI2` (1.5, the rule of
            :func:`~torchblur.fit.sinusoid.fit_sinusoid` and identify's ``fit.poor_fit_chi2``):
            the model does not explain that point's images (a wrong omega or exposure, a
            resonance the model lacks, a wrong PSF); 0 elsewhere.
    """

    form: str
    param_names: tuple
    params: np.ndarray
    covariance: np.ndarray
    std: np.ndarray
    start_params: np.ndarray
    delay_s: float
    cost: float
    dof: int
    reduced_chi2: float
    noise_estimated: bool
    converged: bool
    n_iter: int
    used: np.ndarray
    n_excluded: int
    scale: np.ndarray
    background: np.ndarray | None
    _struct: _Structure = dataclasses.field(repr=False)
    point_reduced_chi2: np.ndarray | None = None
    flags: np.ndarray | None = None

    # ------------------------------------------------------------------ evaluation
    def frequency_response(self, omega) -> np.ndarray:
        """The fitted model, delay included, at ``s = j omega``.

        Args:
            omega: [F] angular frequencies, rad/s (finite).

        Returns:
            complex [F].
        """
        w = as_frequency_grid(omega, "omega")
        s = torch.as_tensor(1j * w, dtype=torch.complex128)
        with torch.no_grad():
            h = _response(self._struct, torch.as_tensor(self.params, dtype=torch.float64), s, self.delay_s)
        return h.numpy()

    @property
    def poles(self) -> np.ndarray:
        """Complex poles (rad/s)."""
        return _poles_zeros(self._struct, self.params)[0]

    @property
    def zeros(self) -> np.ndarray:
        """Complex zeros (rad/s)."""
        return _poles_zeros(self._struct, self.params)[1]

    @property
    def num(self) -> list[float]:
        """Numerator coefficients of s, highest power first (with :attr:`den` monic)."""
        _, z, K = _poles_zeros(self._struct, self.params)
        return [float(v) for v in K * np.real(np.poly(z))] if z.size else [K]

    @property
    def den(self) -> list[float]:
        """Monic denominator coefficients, highest power first."""
        return [float(v) for v in np.real(np.poly(self.poles))]

    def to_control(self):
        """The rational part as a ``control.TransferFunction`` (the delay is NOT included:
        multiply by ``exp(-1j omega delay_s)`` or use :meth:`frequency_response`)."""
        import control

        return control.tf(self.num, self.den)

    def modal_parameters(self) -> list[dict[str, float]]:
        """Each resonant pair of poles, sorted by frequency: dicts with ``omega_n`` (rad/s),
        ``freq_hz``, ``zeta``, ``gain`` (the mode's static gain, ``2 Re(-r conj(p)) / |p|^2``
        for residue r at pole p) and their standard deviations ``omega_n_std``,
        ``freq_hz_std``, ``zeta_std``, ``gain_std`` (delta method on :attr:`covariance`)."""
        struct = self._struct
        P = self.params.size

        def quantities(p):
            out = []
            if struct.form == "modal":
                for k in range(struct.n_pole_pairs):
                    g, wn, z = p[3 * k:3 * k + 3]
                    out += [wn, z, g]
                return torch.stack(out) if out else p[:0]
            # tf: pole pairs and the residue of each.
            i0 = 1 + 2 * struct.n_zero_pairs + struct.n_zero_real
            for k in range(struct.n_pole_pairs):
                wn, z = p[i0 + 2 * k], p[i0 + 2 * k + 1]
                pk = -z * wn + 1j * wn * torch.sqrt((1 - z * z).to(torch.complex128))
                # residue: (s - pk) H_rational(s) at s = pk, the pair's factor divided out.
                s = pk.reshape(1)
                q = dataclasses.replace(struct, n_pole_pairs=struct.n_pole_pairs - 1, fit_delay=False)
                keep = [j for j in range(P - int(struct.fit_delay)) if j not in (i0 + 2 * k, i0 + 2 * k + 1)]
                rest = _response(q, p[keep], s, 0.0)[0]
                res = rest * wn * wn / (pk - pk.conj())
                out += [wn, z, (-2 * (res * pk.conj()).real) / (wn * wn)]
            return torch.stack(out) if out else p[:0]

        pt = torch.as_tensor(self.params, dtype=torch.float64)
        vals = quantities(pt)
        if vals.numel() == 0:
            return []
        jac = torch.autograd.functional.jacobian(quantities, pt).numpy()
        cov = jac @ self.covariance @ jac.T
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        v = vals.detach().numpy()
        modes = []
        for k in range(v.size // 3):
            wn, z, g = v[3 * k:3 * k + 3]
            if z >= 1:
                continue
            modes.append({"omega_n": float(wn), "freq_hz": float(wn / (2 * math.pi)), "zeta": float(z), "gain": float(g),
                          "omega_n_std": float(sd[3 * k]), "freq_hz_std": float(sd[3 * k] / (2 * math.pi)),
                          "zeta_std": float(sd[3 * k + 1]), "gain_std": float(sd[3 * k + 2])})
        return sorted(modes, key=lambda m: m["omega_n"])

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (model.json): parameters with stds and covariance, num/den,
        poles/zeros, modal parameters, fit statistics. Non-finite numbers become None."""
        return direct_fit_to_dict(self)

    @classmethod
    def from_dict(cls, doc: dict) -> "DirectModelFit":
        """Inverse of :meth:`to_dict` (schema version 2; the parameters, covariance, stds, start,
        structure and per-point results exactly as written; None reads back as NaN). Also reads
        the CLI's model.json, which adds ``torchblur_version``, ``seed``, ``judgement`` and
        ``model_passed`` beside the fit (checked, not kept).

        Raises:
            InputTypeError: ``doc`` is not a dict.
            ParameterError: another schema, a version 1 document (written before the model's
                structure was kept: read it as a document, :func:`torchblur.identify.read_outputs.read_outputs`),
                unknown or missing keys, malformed values; each naming the key.
        """
        return cls(**direct_fields_from_dict(doc))

    def to_json(self, path) -> None:
        """Write :meth:`to_dict` to a strict JSON file (read it back with :meth:`from_json`)."""
        write_json_doc(self.to_dict(), path, indent=2)

    @classmethod
    def from_json(cls, path) -> "DirectModelFit":
        """Read a file written by :meth:`to_json`, or the CLI's model.json of a direct run; errors
        name ``path`` (:func:`~torchblur.sysid.frequency_response_io.read_json_doc`)."""
        return read_json_doc(path, cls.from_dict, "model.json")

    def __repr__(self) -> str:
        return (f"DirectModelFit(form={self.form!r}, P={self.params.size}, delay_s={self.delay_s:.4g}, "
                f"reduced_chi2={self.reduced_chi2:.4g}, converged={self.converged})")


# ------------------------------------------------------------------------ the fit
def _unit_axis(axis, like: torch.Tensor) -> torch.Tensor:
    """``"x"``, ``"y"`` or a direction (x, y) -> the unit image direction ``[2]``."""
    if isinstance(axis, str):
        return torch.tensor([1.0, 0.0] if axis == "x" else [0.0, 1.0], dtype=like.dtype, device=like.device)
    d = as_unit_direction(axis, "axis", like=like)
    if d.shape != (2,):
        raise ShapeError(f"axis: expected 'x', 'y' or one direction (x, y) of shape [2], got shape {tuple(d.shape)}")
    return d


def _validate(images, psf, window, omega, input_amplitude, start, form, axis, valid, flags, max_iter):
    """The public entry's checks -> ``(images, window [F, E], omega [F], input amplitude [F], valid [F])``."""
    if not isinstance(images, torch.Tensor):
        raise InputTypeError(f"images: expected a tensor [F, E, H, W], got {type(images).__name__}")
    if not images.is_floating_point():
        images = images.to(torch.get_default_dtype())
    if images.dim() != 4:
        raise ShapeError(f"images: expected shape [F, E, H, W], got {tuple(images.shape)}")
    if images.numel() == 0:
        raise ShapeError(f"images: expected a non-empty set, got shape {tuple(images.shape)}")
    check_finite(images, "images")
    F, E = images.shape[:2]
    if not isinstance(psf, (GaussianPSF, KernelPSF)):
        raise InputTypeError(f"psf: expected a GaussianPSF or KernelPSF (batch [] or [F]), got {type(psf).__name__}")
    if psf.shape not in ((), (F,)):
        raise ShapeError(f"psf: expected batch shape [] or [F] = [{F}], got {tuple(psf.shape)}")
    if isinstance(psf, KernelPSF) and psf.frame_shape != tuple(images.shape[-2:]):
        raise ShapeError(f"psf: expected a kernel of the images' frame {tuple(images.shape[-2:])}, got {psf.frame_shape}")
    if not isinstance(window, ExposureWindow):
        raise InputTypeError(f"window: expected an ExposureWindow [F, E], got {type(window).__name__}")
    try:
        window = window.to(images.dtype).expand((F, E))
    except RuntimeError:
        raise ShapeError(f"window: expected a batch shape broadcastable to [F, E] = [{F}, {E}], got {tuple(window.shape)}") from None
    omega = check_positive(as_tensor(omega, "omega", like=images), "omega")
    if omega.shape != (F,):
        raise ShapeError(f"omega: expected shape [F] = [{F}], got {tuple(omega.shape)}")
    amp = check_positive(as_tensor(input_amplitude, "input_amplitude", like=images), "input_amplitude")
    if amp.dim() == 0:
        amp = amp.expand(F)
    if amp.shape != (F,):
        raise ShapeError(f"input_amplitude: expected shape [F] = [{F}] or a number, got {tuple(amp.shape)}")
    if not isinstance(start, (TransferFunctionFit, DirectModelFit)):
        raise InputTypeError(f"start: expected a TransferFunctionFit or DirectModelFit, got {type(start).__name__}")
    if isinstance(start, TransferFunctionFit) and not start.is_siso:
        raise ParameterError("start: expected a SISO TransferFunctionFit, got a MIMO one")
    check_choice(form, "form", FORMS)
    if isinstance(axis, str):
        check_choice(axis, "axis", _AXES)
    if valid is None:
        v = torch.ones(F, dtype=torch.bool, device=images.device)
    else:
        v = torch.as_tensor(valid, device=images.device)
        if v.dtype != torch.bool:
            raise InputTypeError(f"valid: expected a bool tensor [F], got dtype {v.dtype}")
        if v.shape != (F,):
            raise ShapeError(f"valid: expected shape [F] = [{F}], got {tuple(v.shape)}")
    for name, val in flags.items():
        if not isinstance(val, bool):
            raise InputTypeError(f"{name}: expected a bool, got {type(val).__name__}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ParameterError(f"max_iter: expected an integer >= 1, got {max_iter!r}")
    return images, window, omega, amp, v


def _start_values(start, form: str, fit_delay: bool):
    """``(structure, natural parameters p0 [P], delay_s)`` from a two-step model or a previous direct fit."""
    if isinstance(start, DirectModelFit):
        if start.form == form and start._struct.fit_delay == fit_delay:
            return start._struct, np.array(start.params, dtype=np.float64), float(start.delay_s)
    return _structure_from_tf(start, form, fit_delay)


@dataclasses.dataclass(frozen=True)
class _Motion:
    """The parametric model as the motion of each used point: internal parameters ``u [P]``
    (float64; the log of the "log" parameters) -> ``(M [n], phi [n])``."""

    struct: _Structure
    is_log: torch.Tensor  # [P] bool
    s: torch.Tensor  # [n] complex128, j omega
    delay_s: float
    input_amplitude: torch.Tensor  # [n]
    dtype: torch.dtype

    def natural(self, u: torch.Tensor) -> torch.Tensor:
        """Natural parameters ``[P]`` from internal ones."""
        return torch.where(self.is_log, torch.exp(u), u)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """``[2, n]``: ``M = A |H(j omega)|`` (px) and ``phi = angle H(j omega)`` (rad)."""
        h = _response(self.struct, self.natural(u), self.s, self.delay_s)
        return torch.stack([self.input_amplitude * h.abs().to(self.dtype), torch.angle(h).to(self.dtype)])


def _point_images(M, phi, omega, direction, center, precision, t, w, height: int, width: int, *, kernel=None, pad=None):
    """Unit-scale images of the used points and their derivatives with respect to ``(M, phi)``:
    the one forward model (:func:`~torchblur.render.splat.sine_blur_with_jacobian`), one sine
    ``M sin(omega t + phi)`` along the unit ``direction [2]``.

    Args:
        M, phi, omega: ``[n]`` (px, rad, rad/s); center ``[n, 2]`` px; precision ``(A, B, C)`` each ``[n]``.
        t, w: time nodes (s) and splat weights ``[n, E, S]`` (:func:`~torchblur.render.splat.window_nodes`).
        height, width: frame size.
        kernel: a measured kernel per point ``[n, H, W]`` (then ``center`` is its shift, ``precision`` None), or None.
        pad: the kernel's FFT padding (px).

    Returns:
        ``(image [n, E, H, W], jac [n, E, 2, H, W])``.
    """
    col = (slice(None), None, None)  # [n] -> [n, 1, K = 1]
    return sine_blur_with_jacobian(t, w, M[col], phi[col], omega[col], direction[None], center[:, None, :],
                                   None if precision is None else tuple(v[:, None] for v in precision), height, width,
                                   kernel=None if kernel is None else kernel[:, None], pad=pad)


@dataclasses.dataclass
class _Problem:
    """The used points' data (cropped), everything their images need, and the time nodes.

    ``data, wts [n, E, H, W]``; ``omega [n]``; ``window [n, E]``; ``psf`` (batch ``[n]``, its
    centre moved with the crop; a KernelPSF ``[n, H, W]`` cut with the frame); ``direction [2]``; ``out_cost``, ``out_n``: the cost and the
    count of the used pixels outside the crop, ``out_sq`` their plain sum of squares; ``m_limit``: the motion (px) the crop allows;
    ``tau, wq``: the quadrature rule on [0, 1] (renewed when the motion grows past ``m_bound``).
    """

    data: torch.Tensor
    wts: torch.Tensor
    omega: torch.Tensor
    window: ExposureWindow
    psf: GaussianPSF | KernelPSF
    direction: torch.Tensor
    settings: RenderSettings
    fit_scale: bool
    fit_background: bool
    out_cost: torch.Tensor
    out_n: int = 0
    out_sq: Any = 0.0
    m_limit: Any = math.inf
    m_bound: Any = None
    tau: torch.Tensor | None = None
    wq: torch.Tensor | None = None

    @property
    def q(self) -> int:
        """Nuisance parameters per point."""
        return int(self.fit_scale) + int(self.fit_background)

    def set_nodes(self, m_bound: torch.Tensor) -> None:
        """The quadrature rule for motions up to ``m_bound [n]`` px (the renderer's node count rule)."""
        self.m_bound = m_bound
        n, dtype, device = m_bound.shape[0], m_bound.dtype, m_bound.device
        amp_xy = torch.zeros(n, 1, 2, dtype=dtype, device=device)
        amp_xy[:, 0, 0] = m_bound
        win = self.window
        path = Sinusoid(amp_xy, torch.zeros_like(amp_xy), self.omega[:, None]).path_length(
            ExposureWindow(torch.zeros_like(win.duration), win.duration))
        S = choose_node_count(path, self.psf.sigma_min()[:, None], self.settings)
        m = self.settings.nodes_per_panel if S % self.settings.nodes_per_panel == 0 else S
        self.tau, self.wq = quadrature_nodes(S // m, m, dtype=dtype, device=device)

    def render(self, M, phi):
        """Unit-scale images ``[n, E, H, W]`` and d/d(M, phi) ``[n, E, 2, H, W]`` (a measured
        kernel: its Fourier shift on a grid padded for motions up to ``m_bound``)."""
        H, W = self.data.shape[-2:]
        if isinstance(self.psf, KernelPSF):
            t, w = window_nodes(self.window.start, self.window.duration, self.tau, self.wq, torch.ones_like(self.omega)[:, None])
            pad = int(math.ceil(float(self.m_bound.max()))) + 2
            return _point_images(M, phi, self.omega, self.direction, torch.zeros_like(M)[:, None].expand(-1, 2), None, t, w, H, W,
                                 kernel=self.psf.kernel, pad=pad)
        t, w = window_nodes(self.window.start, self.window.duration, self.tau, self.wq, self.psf.amplitude[:, None])
        return _point_images(M, phi, self.omega, self.direction, self.psf.center, self.psf.precision(), t, w, H, W)

    @torch.no_grad()
    def model(self, motion: "_Motion", u, nuis):
        """The model images ``[n, E, H, W]`` at ``(u, nuis)``: unit-scale images times the scale plus the background."""
        img, _ = self.render(*motion(u))
        sc, bg = self.nuisance(img, nuis)
        return img * sc[:, None, None, None] + bg[:, None, None, None]

    def nuisance(self, img, nuis):
        """``(scale [n], background [n])`` from the nuisance parameters ``nuis [n, q]``."""
        n = img.shape[0]
        sc = nuis[:, 0] if self.fit_scale else img.new_ones(n)
        bg = nuis[:, int(self.fit_scale)] if self.fit_background else img.new_zeros(n)
        return sc, bg


def _used_points(images, weight, window, omega, psf, use, direction, settings, fit_scale, fit_background) -> _Problem:
    """The points ``use [F]`` selects, as a :class:`_Problem` (no crop, no nodes yet)."""
    F = images.shape[0]
    dtype = images.dtype
    idx = torch.nonzero(use)[:, 0]
    psf_b = flat_psf(psf.to(dtype), (F,), F)[idx]
    return _Problem(data=images[idx], wts=weight[idx], omega=omega[idx], window=window[idx], psf=psf_b, direction=direction,
                    settings=settings, fit_scale=fit_scale, fit_background=fit_background,
                    out_cost=torch.zeros((), dtype=dtype, device=images.device))


def _crop(prob: _Problem, M0: torch.Tensor) -> None:
    """Crop ``prob`` to the region the model can reach (as the sinusoid fitter does): outside it
    the model is below e^-24 of its peak; the constant cost of those pixels is kept in
    ``out_cost``. Steps that would move the spot past the crop are refused (``m_limit``).
    Nothing is cropped with a fitted background, or where :func:`~torchblur.fit.problem.crop_box`
    finds no crop worth it (under 4x4, or 90% of the frame or more)."""
    if prob.fit_background:
        return
    H, W = prob.data.shape[-2:]
    device = prob.data.device
    reach = (M0 * 1.5 + 1.0)[:, None] * prob.direction.abs()  # [n, 2] (x, y) px
    lo_k, hi_k = prob.psf.footprint(7.0)
    lo = (lo_k - reach).amin(0)
    hi = (hi_k + reach).amax(0)
    box = crop_box(lo, hi, H, W)
    if box is None:
        return
    cx0, cy0, cx1, cy1 = box
    inside = torch.zeros(H, W, dtype=torch.bool, device=device)
    inside[cy0:cy1, cx0:cx1] = True
    ow = prob.wts * ~inside
    prob.out_cost = (ow * prob.data * prob.data).sum()
    prob.out_n = int(((ow > 0)).sum())
    prob.out_sq = ((ow > 0) * prob.data * prob.data).sum()
    prob.data, prob.wts = prob.data[..., cy0:cy1, cx0:cx1], prob.wts[..., cy0:cy1, cx0:cx1]
    prob.psf = prob.psf.cropped(cx0, cy0, cx1, cy1)
    prob.m_limit = M0 * 1.5 + 1.0  # along the axis


def _nuisance_start(prob: _Problem, motion: _Motion, u: torch.Tensor) -> torch.Tensor:
    """The linear least-squares scale (and background) ``[n, q]`` for the model at ``u``."""
    n, q = prob.data.shape[0], prob.q
    dtype, device = prob.data.dtype, prob.data.device
    if not q:
        return torch.zeros(n, 0, dtype=dtype, device=device)
    with torch.no_grad():
        mp = motion(u)
        img0, _ = prob.render(mp[0], mp[1])
        cols = ([img0] if prob.fit_scale else []) + ([torch.ones_like(img0)] if prob.fit_background else [])
        X = torch.stack(cols, -1).reshape(n, -1, q)
        XW = X * prob.wts.reshape(n, -1, 1)
        return torch.linalg.solve(XW.transpose(1, 2) @ X + 1e-30 * torch.eye(q, dtype=dtype, device=device),
                                  (XW * prob.data.reshape(n, -1, 1)).sum(1)[..., None])[..., 0]


def _evaluate(prob: _Problem, motion: _Motion, u, nuis, need_jac: bool = True):
    """Cost at ``(u, nuis)``, and the blocks of the normal equations ``(G [n, 2+q, 2+q],
    g [n, 2+q], D [n, 2, P], M [n])``: per point the local Gauss-Newton matrix and gradient in
    ``(M, phi, scale, background)``, and ``D = d(M, phi) / du`` by autograd."""
    n, q = prob.data.shape[0], prob.q
    with torch.no_grad():
        M, phi = motion(u)
    img, dimg = prob.render(M, phi)
    sc, bg = prob.nuisance(img, nuis)
    model = img * sc[:, None, None, None] + bg[:, None, None, None]
    r = prob.data - model
    wts = prob.wts
    cost = (wts * r * r).sum()
    if not need_jac:
        return cost, None
    # Local Jacobian columns per point: M, phi, (scale), (background)  -> [n, R, 2 + q]
    cols = [dimg[:, :, 0] * sc[:, None, None, None], dimg[:, :, 1] * sc[:, None, None, None]]
    if prob.fit_scale:
        cols.append(img)
    if prob.fit_background:
        cols.append(torch.ones_like(img))
    J = torch.stack(cols, -1).reshape(n, -1, 2 + q)
    wr = (wts * r).reshape(n, -1)
    JW = J * wts.reshape(n, -1, 1)
    G = JW.transpose(1, 2) @ J  # [n, 2+q, 2+q]
    g = (J * wr[..., None]).sum(1)  # [n, 2+q]
    D = torch.autograd.functional.jacobian(motion, u.detach()).permute(1, 0, 2).to(prob.data.dtype)  # [n, 2, P]
    return cost, (G, g, D, M)


def _solve(blocks, lam: float):
    """The damped Gauss-Newton step ``(du [P], dnu [n, q], S [P, P])`` with the nuisance blocks
    eliminated (Schur complement ``S``, the model parameters' normal matrix)."""
    G, g, D, _ = blocks
    n, q = G.shape[0], G.shape[-1] - 2
    Gmm, Gmn, Gnn = G[:, :2, :2], G[:, :2, 2:], G[:, 2:, 2:]
    A_tt = torch.einsum("kai,kab,kbj->ij", D, Gmm, D)
    A_tn = torch.einsum("kai,kab->kib", D, Gmn)  # [n, P, q]
    g_t = torch.einsum("kai,ka->i", D, g[:, :2])
    g_n = g[:, 2:]
    P = A_tt.shape[0]
    dt = torch.diagonal(A_tt).clamp_min(1e-300)
    S = A_tt + lam * torch.diag(dt) + 1e-14 * torch.diag(dt)
    rhs = g_t
    if q:
        dn = torch.diagonal(Gnn, dim1=1, dim2=2).clamp_min(1e-300)
        Bk = Gnn + (lam + 1e-14) * torch.diag_embed(dn)
        Binv_At = torch.linalg.solve(Bk, A_tn.transpose(1, 2))  # [n, q, P]
        Binv_g = torch.linalg.solve(Bk, g_n[..., None])[..., 0]  # [n, q]
        S = S - torch.einsum("kiq,kqj->ij", A_tn, Binv_At)
        rhs = rhs - torch.einsum("kiq,kq->i", A_tn, Binv_g)
    du = torch.linalg.solve(S, rhs) if P else rhs
    dnu = (Binv_g - torch.einsum("kqi,i->kq", Binv_At, du)) if q else torch.zeros(n, 0, dtype=G.dtype, device=G.device)
    return du, dnu, S


def _levenberg_marquardt(prob: _Problem, motion: _Motion, u, nuis, *, max_iter: int, tol: float, noise_known: bool):
    """Levenberg-Marquardt on ``u`` with the nuisance blocks eliminated at every step.

    A step that makes the motion non-finite or moves it past the crop (``m_limit``) is
    refused (a shorter one is tried); one past the node bound renews the nodes first (the
    cost is re-evaluated at the current point for a fair comparison).

    Returns:
        ``(u, nuis, cost, blocks, converged, n_iter)``.
    """
    cost, blocks = _evaluate(prob, motion, u, nuis)
    lam = 1e-3
    converged = False
    it = 0
    floor = (10 * torch.finfo(prob.data.dtype).eps) ** 2 * float((prob.wts * prob.data * prob.data).sum())
    # With the noise known the cost is a chi2: a decrease far below 1 per pixel means nothing.
    abs_tol = tol * float((prob.wts > 0).sum()) if noise_known else 0.0
    for it in range(1, max_iter + 1):
        du, dnu, _ = _solve(blocks, lam)
        u_t = u + du.to(torch.float64)
        nu_t = nuis + dnu
        with torch.no_grad():
            M_t = motion(u_t)[0]
        if not bool(torch.isfinite(M_t).all()) or not bool(torch.isfinite(u_t).all()) or bool((M_t > prob.m_limit).any()):
            lam *= 4
            if lam > 1e12:
                break
            continue
        if bool((M_t > prob.m_bound).any()):
            prob.set_nodes(torch.maximum(M_t * 1.3 + 0.5, M_t))
            cost, blocks = _evaluate(prob, motion, u, nuis)  # same point, new nodes: a fair comparison
        c_t, b_t = _evaluate(prob, motion, u_t, nu_t)
        if bool(torch.isfinite(c_t)) and float(c_t) <= float(cost):
            drop = float(cost) - float(c_t)
            rel = drop / max(float(cost), 1e-300)
            u, nuis, cost, blocks = u_t, nu_t, c_t, b_t
            lam = max(lam / 3, 1e-12)
            small = bool((du.abs() <= 1e-12 * (u.abs() + 1e-8)).all())
            if rel < tol or drop < abs_tol or small or float(cost) <= floor:
                converged = True
                break
        else:
            lam *= 4
            if lam > 1e12:  # no step, however short, lowers the cost: a minimum to working precision
                converged = True
                break
    return u, nuis, cost, blocks, converged, it


def _covariance(prob: _Problem, motion: _Motion, u, blocks, cost, noise_estimated: bool):
    """Fisher information of ``u`` (nuisance profiled out) and the covariance in natural units
    (delta method on the log parameters) -> ``(params [P], cov [P, P], total cost, dof, reduced chi2)``;
    with the noise estimated the covariance is scaled by the reduced chi2."""
    _, _, S = _solve(blocks, 0.0)
    n = prob.data.shape[0]
    n_pix = int((prob.wts > 0).sum()) + prob.out_n
    P = u.numel()
    total_cost = float(cost) + float(prob.out_cost)
    dof = n_pix - P - prob.q * n
    red = total_cost / max(dof, 1)
    cov_u = torch.linalg.pinv(S.to(torch.float64), hermitian=True)
    if noise_estimated:
        cov_u = cov_u * red
    p_hat = motion.natural(u)
    jac_nat = torch.where(motion.is_log, p_hat, torch.ones_like(p_hat))
    cov = (jac_nat[:, None] * cov_u * jac_nat[None, :]).detach().cpu().numpy()
    return p_hat.detach().cpu().numpy(), cov, total_cost, dof, red


def _refit_by_model(prob: _Problem, motion: _Motion, u, nuis, noise: CameraNoise, *, max_iter: int, tol: float):
    """The second pass of a fit weighted by the camera's noise model: ``prob``'s weights set in
    place to ``1 / noise.std(model)^2`` of the first pass's model images at ``(u, nuis)`` (the
    one forward model, :meth:`_Problem.render`; 0 outside the crop, so ``noise.std(0)`` there;
    masked pixels stay 0), then Levenberg-Marquardt from there -> as :func:`_levenberg_marquardt`.
    Why: the first pass's weights correlate with the noise and bias every amplitude, hence the
    gain, low (see :func:`torchblur.fit.sinusoid._reweight_by_model`)."""
    model = prob.model(motion, u, nuis)
    prob.wts = torch.where(prob.wts > 0, 1 / noise.std(model) ** 2, torch.zeros_like(model))
    prob.out_cost = prob.out_sq / noise.std(0.0) ** 2
    return _levenberg_marquardt(prob, motion, u, nuis, max_iter=max_iter, tol=tol, noise_known=True)


def _passes(prob: _Problem, motion: _Motion, u, nuis, noise, noise_known: bool, *, max_iter: int, tol: float):
    """Levenberg-Marquardt from ``(u, nuis)``, then with ``noise`` (weights from the noise model)
    the refit :func:`_refit_by_model` from there -> as :func:`_levenberg_marquardt`, the
    iterations of both passes."""
    u, nuis, cost, blocks, converged, it = _levenberg_marquardt(prob, motion, u, nuis, max_iter=max_iter, tol=tol, noise_known=noise_known)
    if noise is None:
        return u, nuis, cost, blocks, converged, it
    u, nuis, cost, blocks, converged, it2 = _refit_by_model(prob, motion, u, nuis, noise, max_iter=max_iter, tol=tol)
    return u, nuis, cost, blocks, converged, it + it2


def _per_point(nuis, use, fit_scale: bool, fit_background: bool):
    """The per-point scale and background ``[F]`` (NaN where excluded; background None when not fitted)."""
    F = use.shape[0]
    idx_np = torch.nonzero(use)[:, 0].cpu().numpy()
    scale_full = np.full(F, np.nan)
    bg_full = np.full(F, np.nan) if fit_background else None
    scale_full[idx_np] = nuis[:, 0].detach().cpu().numpy() if fit_scale else 1.0
    if fit_background:
        bg_full[idx_np] = nuis[:, int(fit_scale)].detach().cpu().numpy()
    return scale_full, bg_full


def _point_chi2(prob: _Problem, motion: _Motion, u, nuis, use, known: bool):
    """``(point_reduced_chi2 [F], flags [F])`` of :class:`DirectModelFit` (NaN and 0 where a point
    is excluded, every point NaN when the noise is not ``known``)."""
    F = use.shape[0]
    red = torch.full((F,), math.nan, dtype=torch.float64, device=use.device)
    if known:
        with torch.no_grad():
            r = prob.data - prob.model(motion, u, nuis)
            n_pix = (prob.wts > 0).sum((1, 2, 3)).to(torch.float64)
            dof = (n_pix - prob.q - u.numel() / prob.data.shape[0]).clamp_min(1.0)
            red[use] = (prob.wts * r * r).sum((1, 2, 3)).to(torch.float64) / dof
    return red.cpu().numpy(), flag_poor_fit(None, red, POOR_FIT_CHI2).cpu().numpy()


def fit_direct(
    images,
    psf: GaussianPSF | KernelPSF,
    window: ExposureWindow,
    omega,
    input_amplitude,
    start,
    *,
    form: str = "tf",
    fit_delay: bool = True,
    axis="x",
    noise_std=None,
    noise: CameraNoise | None = None,
    mask=None,
    valid=None,
    fit_scale: bool = True,
    fit_background: bool = False,
    max_iter: int = 100,
    tol: float = 1e-10,
    render_settings: RenderSettings | None = None,
) -> DirectModelFit:
    """Fit a parametric model ``H(s; theta)`` to every image of a sine sweep at once.

    Args:
        images: ``[F, E, H, W]``: E images (exposures, repeats) of each of F sweep points,
            dark level subtracted, in the units of the PSF times seconds.
        psf: ``GaussianPSF`` of batch ``[]`` or ``[F]`` (the laser power per point in its
            amplitude); its centre is the rest position. Or a ``KernelPSF`` ``[H, W]``/``[F, H, W]`` (the power in it).
        window: exposure windows, batch broadcastable to ``[F, E]`` (seconds from an upward
            zero crossing of the command).
        omega: ``[F]`` rad/s.
        input_amplitude: ``[F]`` (or a number) command amplitude A_k (input units).
        start: a SISO :class:`~torchblur.sysid.tf_fit.TransferFunctionFit` (the two-step model:
            its orders and values are the start) or a :class:`DirectModelFit`; or a list of
            them: each is fitted and the lowest cost wins (multi-start).
        form: "tf" (normalised poles/zeros) or "modal" (sum of modes); docs/direct_identification.md.
        fit_delay: estimate the delay (else it stays at the start's).
        axis: "x" or "y", or an image direction (x, y) (a pair or a tensor ``[2]``,
            normalised; an actuator axis rotated in the camera's image): the motion's
            direction in the image.
        noise_std: pixel noise std: a number, ``[F]`` or ``[F, E, H, W]``; None: from ``noise``
            (unbiased: :func:`_refit_by_model`), else unweighted, the noise from the residuals.
        noise: the camera's :class:`~torchblur.render.camera.CameraNoise` (images in e-), or None.
        mask: bool ``[F, E, H, W]``, False excludes a pixel (saturated, hot).
        valid: bool ``[F]``, False excludes a whole point (dark, out of frame); counted in
            ``n_excluded``.
        fit_scale, fit_background: per-point nuisance parameters (intensity scale, offset).
        max_iter: Levenberg-Marquardt iterations at most; tol: a cost decrease below ``tol``
            times the cost (or, with ``noise_std`` given, times the number of used pixels:
            the cost is then a chi2) counts as converged.
        render_settings: renderer settings (default: panels of 3.5 PSF widths, as the
            sinusoid fitter).

    Returns:
        :class:`DirectModelFit`.

    Raises:
        InputTypeError, ShapeError, ParameterError naming the argument.
    """
    if isinstance(start, (list, tuple)):
        return _best_of_starts((images, psf, window, omega, input_amplitude), start, dict(
            form=form, fit_delay=fit_delay, axis=axis, noise_std=noise_std, noise=noise, mask=mask, valid=valid, fit_scale=fit_scale,
            fit_background=fit_background, max_iter=max_iter, tol=tol, render_settings=render_settings))
    flags = {"fit_delay": fit_delay, "fit_scale": fit_scale, "fit_background": fit_background}
    images, window, omega, amp, use = _validate(images, psf, window, omega, input_amplitude, start, form, axis, valid, flags,
                                                max_iter)
    struct, names, is_log, p0, delay = _start_params(start, form, fit_delay, images.device)
    by_model = noise_sets_weights(noise, noise_std)
    weight, _ = pixel_weights(noise.std(images) if by_model else noise_std, mask, images)
    if not bool(use.any()):
        raise ParameterError("valid: every point is excluded; nothing to fit")

    prob = _used_points(images, weight, window, omega, psf, use, _unit_axis(axis, images),
                        render_settings or RenderSettings(panel_path_sigmas=3.5), fit_scale, fit_background)
    motion, u, nuis = _prepare_start(prob, (struct, is_log, delay, p0), amp[use], images.dtype)
    known = noise_std is not None or by_model
    u, nuis, cost, blocks, converged, it = _passes(prob, motion, u, nuis, noise if by_model else None, known, max_iter=max_iter, tol=tol)
    return _direct_result(prob, motion, (u, nuis, cost, blocks, converged, it), (struct, names, p0, delay), use, known,
                          fit_scale, fit_background)


def _direct_result(prob, motion, fitted, model, use, known: bool, fit_scale: bool, fit_background: bool) -> DirectModelFit:
    """The :class:`DirectModelFit` of the passes' result ``fitted = (u, nuisance, cost, blocks,
    converged, iterations)`` for ``model = (structure, names, start values, start delay)``:
    the covariance, the per-point nuisance on all F points (``use`` [F]) and per-point chi2."""
    u, nuis, cost, blocks, converged, it = fitted
    struct, names, p0, delay = model
    params, cov, total_cost, dof, red = _covariance(prob, motion, u, blocks, cost, not known)
    scale_full, bg_full = _per_point(nuis, use, fit_scale, fit_background)
    point_red, point_flags = _point_chi2(prob, motion, u, nuis, use, known)
    delay_hat = float(params[list(names).index("delay_s")]) if struct.fit_delay else float(delay)
    return DirectModelFit(
        form=struct.form, param_names=tuple(names), params=params, covariance=cov, std=np.sqrt(np.clip(np.diag(cov), 0, None)),
        start_params=np.asarray(p0), delay_s=delay_hat, cost=total_cost, dof=int(dof), reduced_chi2=float(red),
        noise_estimated=not known, converged=bool(converged), n_iter=int(it), used=use.cpu().numpy(), n_excluded=int((~use).sum()),
        scale=scale_full, background=bg_full, _struct=struct, point_reduced_chi2=point_red, flags=point_flags)


def _best_of_starts(args: tuple, starts, kw: dict) -> DirectModelFit:
    """Multi-start: :func:`fit_direct` ``(*args, start, **kw)`` from each of ``starts``; the fit
    of the lowest finite cost."""
    if not starts:
        raise ParameterError("start: expected a model or a non-empty list of models, got an empty list")
    fits = [fit_direct(*args, s, **kw) for s in starts]
    return min(fits, key=lambda f: f.cost if math.isfinite(f.cost) else math.inf)

def _start_params(start, form: str, fit_delay: bool, device):
    """The model to fit and where it starts: ``(structure, parameter names [P], is_log [P] bool
    tensor on ``device`` (fitted as logs), start values [P] (numpy), delay s)``; ParameterError
    naming ``start`` where the start gives a non-finite or (log parameters) non-positive value."""
    struct, p0, delay = _start_values(start, form, fit_delay)
    names, transforms = zip(*struct.names_transforms())
    is_log = torch.tensor([t == "log" for t in transforms], device=device)
    if np.any(p0[is_log.cpu().numpy()] <= 0) or not np.all(np.isfinite(p0)):
        raise ParameterError(f"start: the start gives invalid parameters {dict(zip(names, p0.tolist()))}")
    return struct, names, is_log, p0, delay


def _prepare_start(prob, model: tuple, amp, dtype):
    """The motion of ``model = (structure, is_log, delay, start values p0 [P])`` at the used
    points (command amplitudes ``amp``, images of ``dtype``) and the fit's unknowns at the
    start: ``(motion, u [P] float64, the nuisance start)``; crops ``prob`` to the start's motion
    and fixes its time nodes for a motion bound (renewed if the motion grows past it)."""
    struct, is_log, delay, p0 = model
    # complex128: H needs the precision whatever the images
    motion = _Motion(struct, is_log, 1j * prob.omega.to(torch.float64), delay, amp, dtype)
    p0_t = torch.as_tensor(p0, dtype=torch.float64, device=is_log.device)
    u = torch.where(is_log, torch.log(p0_t), p0_t)
    with torch.no_grad():
        M0 = motion(u)[0]
    _crop(prob, M0)
    prob.set_nodes(M0 * 1.3 + 0.5)
    return motion, u, _nuisance_start(prob, motion, u)
