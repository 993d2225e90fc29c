"""Direct identification: the parameters of a parametric model fitted to ALL images at once.

The two-step route fits the motion amplitude and phase of every sweep point, then a model to
the frequency response. The direct route (the paper's future work) fits the model's
parameters ``theta`` straight to the images: for sweep point k (angular frequency
``omega_k``, input amplitude ``A_k``) the model gives the spot's motion

    y_k(t) = M_k sin(omega_k t + phi_k),   M_k = A_k |H(j omega_k; theta)|,  phi_k = angle H(j omega_k; theta),

whose images (every exposure of the point, rendered with the PSF) are compared with the
measured ones; the weighted sum of squares over every pixel of every image is minimised
(maximum likelihood under Gaussian pixel noise of std ``noise_std``, e.g. sqrt(read^2 +
signal) as :func:`torchblur.identify.run.identify` uses). Per point an intensity scale (and a
background) is a nuisance parameter, as in :func:`torchblur.fit.sinusoid.fit_sinusoid`.

Model forms (``form``), both with a pure delay ``exp(-s delay_s)``:

* ``"tf"``: ``H(s) = gain s^n0 prod_z F_z(s) / prod_p F_p(s)`` with normalised factors:
  a complex pair ``(s / omega_n)^2 + 2 zeta s / omega_n + 1`` (parameters omega_n rad/s and
  zeta), a real root ``1 + s / rate`` (rate rad/s; a pole's rate > 0, a zero's may be
  negative), ``n0`` roots at the origin kept fixed. ``gain`` is the low-frequency gain of
  the non-origin part (the DC gain when n0 = 0). Well conditioned, unlike polynomial
  coefficients.
* ``"modal"``: ``H(s) = sum_pairs g omega_n^2 / (s^2 + 2 zeta omega_n s + omega_n^2) +
  sum_real g rate / (s + rate) + D``: per resonant mode its static gain g (a real modal
  residue, as a structure with proportional damping and a collocated sensor has), omega_n
  and zeta; per real mode g and rate; D a feedthrough (only when the start has as many
  zeros as poles). The start's pairs keep their real residue part (the s-part of a general
  partial fraction is dropped): a plant outside this family is only approximated.

Efficiency: no dense Jacobian over all pixels x all parameters is formed. Per point the image
and its derivatives with respect to (M, phi) come from one splat
(:func:`torchblur.render.splat.gaussian_splat_with_jacobian`), the scale and background
derivatives are the image and 1, and ``d(M_k, phi_k) / d theta`` comes from autograd of
``H(j omega; theta)``. The normal equations are assembled blockwise (theta block plus one
small nuisance block per point) and every Levenberg-Marquardt step eliminates the nuisance
blocks (Schur complement), so the cost is one splat with 2 derivatives per image per step
whatever the number of model parameters.

Uncertainty: the inverse Fisher information at the solution (the Schur complement, i.e. the
nuisance parameters profiled out); with ``noise_std=None`` the fit is unweighted and the
covariance is scaled by the reduced chi2 (the noise estimated from the residuals).
Natural-unit covariances follow from the internal (log-) parameters by the delta method.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import numpy as np
import torch

from torchblur.errors import (InputTypeError, ParameterError, ShapeError, as_frequency_grid, as_tensor, as_unit_direction, check_choice,
                     check_finite, check_positive)
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import RenderSettings, choose_node_count, quadrature_nodes
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid

__all__ = ["AliasResolution", "DirectModelFit", "fit_direct", "resolve_alias_with_model", "FORMS"]

#: Model forms of :func:`fit_direct`.
FORMS = ("tf", "modal")
_AXES = ("x", "y")


# ------------------------------------------------------------------------ structure
@dataclasses.dataclass(frozen=True)
class _Structure:
    """Which parameters a model has. ``kinds`` lists, in parameter order, one entry per
    natural parameter: (name, transform) with transform "log" (optimised as its log, > 0)
    or "lin"."""

    form: str
    n_zero_pairs: int = 0
    n_zero_real: int = 0
    n_pole_pairs: int = 0
    n_pole_real: int = 0
    n_origin: int = 0  # tf: power of s (zeros at 0 minus poles at 0)
    feedthrough: bool = False  # modal: D
    fit_delay: bool = True

    def names_transforms(self) -> list[tuple[str, str]]:
        out: list[tuple[str, str]] = []
        if self.form == "tf":
            out.append(("gain", "lin"))
            for i in range(self.n_zero_pairs):
                out += [(f"zero_pair{i + 1}_omega_n", "log"), (f"zero_pair{i + 1}_zeta", "lin")]
            for i in range(self.n_zero_real):
                out.append((f"zero{i + 1}_rate", "lin"))
            for i in range(self.n_pole_pairs):
                out += [(f"pole_pair{i + 1}_omega_n", "log"), (f"pole_pair{i + 1}_zeta", "log")]
            for i in range(self.n_pole_real):
                out.append((f"pole{i + 1}_rate", "log"))
        else:
            for i in range(self.n_pole_pairs):
                out += [(f"mode{i + 1}_gain", "lin"), (f"mode{i + 1}_omega_n", "log"), (f"mode{i + 1}_zeta", "log")]
            for i in range(self.n_pole_real):
                out += [(f"real_mode{i + 1}_gain", "lin"), (f"real_mode{i + 1}_rate", "log")]
            if self.feedthrough:
                out.append(("feedthrough", "lin"))
        if self.fit_delay:
            out.append(("delay_s", "lin"))
        return out


def _response(struct: _Structure, p: torch.Tensor, s: torch.Tensor, delay_s: float) -> torch.Tensor:
    """H(s) [F] (complex) from natural parameters ``p`` [P] (real) at ``s`` [F] (complex)."""
    i = 0
    one = torch.ones_like(s)
    if struct.form == "tf":
        h = p[0] * one
        i = 1
        for _ in range(struct.n_zero_pairs):
            x = s / p[i]
            h = h * (x * x + 2 * p[i + 1] * x + 1)
            i += 2
        for _ in range(struct.n_zero_real):
            h = h * (1 + s / p[i])
            i += 1
        for _ in range(struct.n_pole_pairs):
            x = s / p[i]
            h = h / (x * x + 2 * p[i + 1] * x + 1)
            i += 2
        for _ in range(struct.n_pole_real):
            h = h / (1 + s / p[i])
            i += 1
        if struct.n_origin:
            h = h * s ** struct.n_origin
    else:
        h = torch.zeros_like(s)
        for _ in range(struct.n_pole_pairs):
            g, wn, z = p[i], p[i + 1], p[i + 2]
            h = h + g * wn * wn / (s * s + 2 * z * wn * s + wn * wn)
            i += 3
        for _ in range(struct.n_pole_real):
            g, a = p[i], p[i + 1]
            h = h + g * a / (s + a)
            i += 2
        if struct.feedthrough:
            h = h + p[i]
            i += 1
    tau = p[i] if struct.fit_delay else delay_s
    return h * torch.exp(-s * tau)


def _poles_zeros(struct: _Structure, p: np.ndarray):
    """(poles, zeros, high-frequency gain K) with H = K prod(s - z) / prod(s - p) (rad/s)."""
    p = np.asarray(p, dtype=np.float64)

    def pair(wn, z):
        r = -z * wn + 1j * wn * np.sqrt(complex(1 - z * z))
        return [r, np.conj(r)] if abs(1 - z * z) > 0 and z * z < 1 else [complex(-z * wn + wn * np.sqrt(z * z - 1)),
                                                                           complex(-z * wn - wn * np.sqrt(z * z - 1))]

    if struct.form == "tf":
        i, K = 1, p[0]
        zeros, poles = [], []
        for _ in range(struct.n_zero_pairs):
            zeros += pair(p[i], p[i + 1])
            K = K / p[i] ** 2
            i += 2
        for _ in range(struct.n_zero_real):
            zeros.append(complex(-p[i]))
            K = K / p[i]
            i += 1
        for _ in range(struct.n_pole_pairs):
            poles += pair(p[i], p[i + 1])
            K = K * p[i] ** 2
            i += 2
        for _ in range(struct.n_pole_real):
            poles.append(complex(-p[i]))
            K = K * p[i]
            i += 1
        if struct.n_origin > 0:
            zeros += [0j] * struct.n_origin
        elif struct.n_origin < 0:
            poles += [0j] * (-struct.n_origin)
        return np.array(poles, dtype=np.complex128), np.array(zeros, dtype=np.complex128), float(K)
    num, den = _modal_polys(struct, p)
    nz = np.trim_zeros(num, "f")
    return np.roots(den).astype(np.complex128), np.roots(nz).astype(np.complex128), float(nz[0] / den[0]) if nz.size else 0.0


def _modal_polys(struct: _Structure, p: np.ndarray):
    """num, den polynomial coefficients (highest power first) of the modal form."""
    terms, i = [], 0
    for _ in range(struct.n_pole_pairs):
        g, wn, z = p[i:i + 3]
        terms.append((np.array([g * wn * wn]), np.array([1.0, 2 * z * wn, wn * wn])))
        i += 3
    for _ in range(struct.n_pole_real):
        g, a = p[i:i + 2]
        terms.append((np.array([g * a]), np.array([1.0, a])))
        i += 2
    den = np.array([1.0])
    for _, d in terms:
        den = np.polymul(den, d)
    num = np.zeros(1)
    for k, (n, _) in enumerate(terms):
        other = np.array([1.0])
        for j, (_, d) in enumerate(terms):
            if j != k:
                other = np.polymul(other, d)
        num = np.polyadd(num, np.polymul(n, other))
    if struct.feedthrough:
        num = np.polyadd(num, p[i] * den)
    return num, den


# ---------------------------------------------------------------------- start values
def _structure_from_tf(tf_fit, form: str, fit_delay: bool):
    """(structure, natural parameters [P], delay_s) from a SISO TransferFunctionFit."""
    poles = np.asarray(tf_fit.poles, dtype=np.complex128)
    zeros = np.asarray(tf_fit.zeros, dtype=np.complex128)
    K = float(tf_fit.num[0] / tf_fit.den[0])
    delay = float(tf_fit.delay_s)
    scale = max(1.0, float(np.max(np.abs(np.concatenate([poles, zeros])))) if poles.size + zeros.size else 1.0)
    tol = 1e-9 * scale

    def split(roots):
        origin = int(np.sum(np.abs(roots) <= tol))
        rest = roots[np.abs(roots) > tol]
        upper = rest[rest.imag > 1e-9 * np.abs(rest)]
        real = rest[np.abs(rest.imag) <= 1e-9 * np.abs(rest)].real
        return origin, upper, np.sort(real)

    zo, zu, zr = split(zeros)
    po, pu, pr = split(poles)
    if np.any(pu.real >= 0) or np.any(pr >= 0):
        raise ParameterError("start: the two-step model has an unstable pole; the direct fit needs a stable start")
    if form == "tf":
        struct = _Structure("tf", len(zu), len(zr), len(pu), len(pr), zo - po, False, fit_delay)
        # H = K prod(s - z)/prod(s - p): normalised factor (s - r) = -r (1 - s/r), pair |r|^2 (...).
        gain = K
        vals = [0.0]
        for r in zu:
            vals += [abs(r), -r.real / abs(r)]
            gain *= abs(r) ** 2
        for r in zr:
            vals.append(-r)
            gain *= -r
        for r in pu:
            vals += [abs(r), -r.real / abs(r)]
            gain /= abs(r) ** 2
        for r in pr:
            vals.append(-r)
            gain /= -r
        vals[0] = gain
    else:
        if po:
            raise ParameterError("start: the modal form cannot hold a pole at the origin; use form='tf'")
        allp = np.concatenate([pu, pr.astype(np.complex128)])
        if allp.size and np.min(np.abs(allp[:, None] - allp[None, :]) + np.eye(allp.size) * 1e300) < 1e-9 * scale:
            raise ParameterError("start: the two-step model has repeated poles; the modal form needs distinct poles, use form='tf'")
        n_p, n_z = poles.size, zeros.size
        struct = _Structure("modal", 0, 0, len(pu), len(pr), 0, n_z == n_p, fit_delay)

        def residue(pk):
            others = poles[np.abs(poles - pk) > 0]
            return K * np.prod(pk - zeros) / np.prod(pk - others)

        vals = []
        for r in pu:  # the pair's numerator b1 s + b0; the modal form keeps b0 (a real modal residue)
            res = residue(r)
            wn = abs(r)
            vals += [-2 * (res * np.conj(r)).real / wn**2, wn, -r.real / wn]
        for r in pr:
            res = residue(complex(r)).real
            vals += [res / -r, -r]
        if struct.feedthrough:
            vals.append(K)
    if fit_delay:
        vals.append(delay)
    return struct, np.asarray(vals, dtype=np.float64), delay


# ------------------------------------------------------------------------ result
@dataclasses.dataclass(frozen=True, eq=False)
class DirectModelFit:
    """Result of :func:`fit_direct`.

    Attributes:
        form: "tf" or "modal" (see the module docstring).
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
        noise_estimated: True when noise_std was None (covariance scaled by reduced_chi2).
        converged: whether Levenberg-Marquardt converged.
        n_iter: its iterations.
        used: [F] bool, the points fitted (False: excluded by ``valid``).
        n_excluded: how many points were excluded.
        scale, background: [F] per-point nuisance estimates (NaN where excluded; background
            None when not fitted).
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

        def jf(x):
            x = float(x)
            return x if math.isfinite(x) else None

        def roots(r):
            return {"real": [jf(x) for x in r.real], "imag": [jf(x) for x in r.imag]}

        return {
            "schema": "torchblur.direct_model_fit",
            "schema_version": 1,
            "form": self.form,
            "param_names": list(self.param_names),
            "params": [jf(x) for x in self.params],
            "std": [jf(x) for x in self.std],
            "covariance": [[jf(x) for x in row] for row in self.covariance],
            "start_params": [jf(x) for x in self.start_params],
            "num": [jf(x) for x in self.num],
            "den": [jf(x) for x in self.den],
            "delay_s": jf(self.delay_s),
            "poles": roots(self.poles),
            "zeros": roots(self.zeros),
            "modes": [{k: jf(v) for k, v in m.items()} for m in self.modal_parameters()],
            "cost": jf(self.cost),
            "dof": int(self.dof),
            "reduced_chi2": jf(self.reduced_chi2),
            "noise_estimated": bool(self.noise_estimated),
            "converged": bool(self.converged),
            "n_iter": int(self.n_iter),
            "n_points_used": int(self.used.sum()),
            "n_excluded": int(self.n_excluded),
        }

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


def _validate(images, psf, window, omega, input_amplitude, start, form, axis, valid):
    from torchblur.sysid.tf_fit import TransferFunctionFit

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
    if not isinstance(psf, GaussianPSF):
        raise InputTypeError(f"psf: expected a GaussianPSF (batch [] or [F]), got {type(psf).__name__}")
    if psf.shape not in ((), (F,)):
        raise ShapeError(f"psf: expected batch shape [] or [F] = [{F}], got {tuple(psf.shape)}")
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
    return images, window, omega, amp, v


def fit_direct(
    images,
    psf: GaussianPSF,
    window: ExposureWindow,
    omega,
    input_amplitude,
    start,
    *,
    form: str = "tf",
    fit_delay: bool = True,
    axis="x",
    noise_std=None,
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
            amplitude); its centre is the rest position.
        window: exposure windows, batch broadcastable to ``[F, E]`` (seconds from an upward
            zero crossing of the command).
        omega: ``[F]`` rad/s.
        input_amplitude: ``[F]`` (or a number) command amplitude A_k (input units).
        start: a SISO :class:`~torchblur.sysid.tf_fit.TransferFunctionFit` (the two-step model:
            its orders and values are the start) or a :class:`DirectModelFit`; or a list of
            them: each is fitted and the lowest cost wins (multi-start).
        form: "tf" (normalised poles/zeros) or "modal" (sum of modes); see the module docstring.
        fit_delay: estimate the delay (else it stays at the start's).
        axis: "x" or "y", or an image direction (x, y) (a pair or a tensor ``[2]``,
            normalised; an actuator axis rotated in the camera's image): the motion's
            direction in the image.
        noise_std: pixel noise std: a number, ``[F]`` or ``[F, E, H, W]``; None: unweighted,
            the noise is estimated from the residuals.
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
        if not start:
            raise ParameterError("start: expected a model or a non-empty list of models, got an empty list")
        kw = dict(form=form, fit_delay=fit_delay, axis=axis, noise_std=noise_std, mask=mask, valid=valid, fit_scale=fit_scale,
                  fit_background=fit_background, max_iter=max_iter, tol=tol, render_settings=render_settings)
        fits = [fit_direct(images, psf, window, omega, input_amplitude, s, **kw) for s in start]
        return min(fits, key=lambda f: f.cost if math.isfinite(f.cost) else math.inf)
    images, window, omega, amp, valid = _validate(images, psf, window, omega, input_amplitude, start, form, axis, valid)
    for name, val in (("fit_delay", fit_delay), ("fit_scale", fit_scale), ("fit_background", fit_background)):
        if not isinstance(val, bool):
            raise InputTypeError(f"{name}: expected a bool, got {type(val).__name__}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ParameterError(f"max_iter: expected an integer >= 1, got {max_iter!r}")
    dtype, device = images.dtype, images.device
    F, E, H, W = images.shape
    ud = _unit_axis(axis, images)  # [2] the motion's unit image direction

    # Start values.
    if isinstance(start, DirectModelFit):
        if start.form == form and start._struct.fit_delay == fit_delay:
            struct, p0, delay = start._struct, np.array(start.params, dtype=np.float64), float(start.delay_s)
        else:
            from torchblur.sysid.tf_fit import TransferFunctionFit

            tf_like = TransferFunctionFit(num=start.num, den=start.den, delay_s=start.delay_s, n_poles=start.poles.size,
                                          n_zeros=start.zeros.size, chi2=math.nan, dof=0, reduced_chi2=math.nan,
                                          rms_relative_error=math.nan, poles=start.poles, zeros=start.zeros, dc_gain=math.nan,
                                          weighting="uniform", delay_estimated=True, input_labels=("x",), output_labels=("x",))
            struct, p0, delay = _structure_from_tf(tf_like, form, fit_delay)
    else:
        struct, p0, delay = _structure_from_tf(start, form, fit_delay)
    names, transforms = zip(*struct.names_transforms())
    is_log = torch.tensor([t == "log" for t in transforms], device=device)
    if np.any(p0[is_log.cpu().numpy()] <= 0) or not np.all(np.isfinite(p0)):
        raise ParameterError(f"start: the start gives invalid parameters {dict(zip(names, p0.tolist()))}")

    # Weights.
    weight = torch.ones_like(images)
    if noise_std is not None:
        s = check_positive(as_tensor(noise_std, "noise_std", like=images), "noise_std")
        if s.dim() == 4:
            if s.shape != images.shape:
                raise ShapeError(f"noise_std: expected a number, [F] or [F, E, H, W] = {tuple(images.shape)}, got {tuple(s.shape)}")
        elif s.dim() == 1 and s.shape == (F,):
            s = s[:, None, None, None]
        elif s.dim() != 0:
            raise ShapeError(f"noise_std: expected a number, [F] or [F, E, H, W] = {tuple(images.shape)}, got {tuple(s.shape)}")
        weight = (1 / s**2).expand(images.shape)
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise InputTypeError("mask: expected a bool tensor [F, E, H, W] (True = use the pixel)")
        if mask.shape != images.shape:
            raise ShapeError(f"mask: expected shape [F, E, H, W] = {tuple(images.shape)}, got {tuple(mask.shape)}")
        weight = weight * mask.to(dtype)

    use = valid.clone()
    n_excluded = int((~use).sum())
    if not bool(use.any()):
        raise ParameterError("valid: every point is excluded; nothing to fit")
    idx = torch.nonzero(use)[:, 0]
    n = idx.numel()
    data, wts = images[idx], weight[idx]
    om, A_in = omega[idx], amp[idx]
    win = window[idx]
    psf_b = GaussianPSF(psf.center.to(dtype).expand(F, 2)[idx], psf.cov.to(dtype).expand(F, 2, 2)[idx],
                        psf.amplitude.to(dtype).expand(F)[idx])
    center = psf_b.center
    Ap, Bp, Cp = psf_b.precision()
    s_c = 1j * om.to(torch.float64)  # complex128: H needs the precision whatever the images

    def motion(u: torch.Tensor):
        """(M [n], phi [n]) from internal parameters u [P]."""
        p = torch.where(is_log, torch.exp(u), u)
        h = _response(struct, p, s_c, delay)
        return torch.stack([A_in * h.abs().to(dtype), torch.angle(h).to(dtype)])

    def natural(u):
        return torch.where(is_log, torch.exp(u), u)

    p0_t = torch.as_tensor(p0, dtype=torch.float64, device=device)
    u = torch.where(is_log, torch.log(p0_t), p0_t)

    # Crop to the region the model can reach (as the sinusoid fitter does): outside it the
    # model is below e^-24 of its peak; the constant cost of those pixels is added back.
    # Steps that would move the spot past the crop are refused (a shorter step is tried).
    with torch.no_grad():
        M0 = motion(u)[0]
    sd = torch.diagonal(psf_b.cov, dim1=-2, dim2=-1).sqrt()
    reach = (M0 * 1.5 + 1.0)[:, None] * ud.abs()  # [n, 2] (x, y) px
    out_cost = torch.zeros((), dtype=dtype, device=device)
    out_n = 0
    m_limit = math.inf
    if not fit_background:
        lo = (center - reach - 7 * sd).amin(0)
        hi = (center + reach + 7 * sd).amax(0)
        cx0, cy0 = max(0, int(math.floor(float(lo[0])))), max(0, int(math.floor(float(lo[1]))))
        cx1, cy1 = min(W, int(math.ceil(float(hi[0]))) + 1), min(H, int(math.ceil(float(hi[1]))) + 1)
        if cx1 - cx0 >= 4 and cy1 - cy0 >= 4 and (cx1 - cx0) * (cy1 - cy0) < 0.9 * H * W:
            inside = torch.zeros(H, W, dtype=torch.bool, device=device)
            inside[cy0:cy1, cx0:cx1] = True
            ow = wts * ~inside
            out_cost = (ow * data * data).sum()
            out_n = int(((ow > 0)).sum())
            data, wts = data[..., cy0:cy1, cx0:cx1], wts[..., cy0:cy1, cx0:cx1]
            H, W = cy1 - cy0, cx1 - cx0
            center = center - torch.tensor([cx0, cy0], dtype=dtype, device=device)
            m_limit = M0 * 1.5 + 1.0  # along the axis

    # Time nodes, fixed for a motion bound (recomputed if the motion grows past it).
    settings = render_settings or RenderSettings(panel_path_sigmas=3.5)
    smin = psf_b.sigma_min()

    def nodes_for(m_bound):
        amp_xy = torch.zeros(n, 1, 2, dtype=dtype, device=device)
        amp_xy[:, 0, 0] = m_bound
        path = Sinusoid(amp_xy, torch.zeros_like(amp_xy), om[:, None]).path_length(ExposureWindow(torch.zeros_like(win.duration),
                                                                                               win.duration))
        S = choose_node_count(path, smin[:, None], settings)
        m = settings.nodes_per_panel if S % settings.nodes_per_panel == 0 else S
        return S // m, m

    m_bound = M0 * 1.3 + 0.5
    tau_q, w_q = quadrature_nodes(*nodes_for(m_bound), dtype=dtype, device=device)

    from torchblur.render.splat import gaussian_splat_with_jacobian

    def render(M, phi):
        """Unit-scale images [n, E, H, W] and d/d(M, phi) [n, E, 2, H, W]."""
        t = win.start[..., None] + win.duration[..., None] * tau_q  # [n, E, S]
        wq = win.duration[..., None] * w_q * psf_b.amplitude[:, None, None]
        arg = om[:, None, None] * t + phi[:, None, None]
        sn, cs = torch.sin(arg), torch.cos(arg)
        disp = M[:, None, None] * sn
        d = torch.stack([sn, M[:, None, None] * cs], -1)  # [n, E, S, 2]
        cx = center[:, 0, None, None].expand(t.shape)
        cy = center[:, 1, None, None].expand(t.shape)
        px, py, dpx, dpy = cx + ud[0] * disp, cy + ud[1] * disp, ud[0] * d, ud[1] * d
        return gaussian_splat_with_jacobian(px, py, dpx, dpy, wq, Ap[:, None], Bp[:, None], Cp[:, None], H, W)

    q = int(fit_scale) + int(fit_background)  # nuisance parameters per point

    def evaluate(u, nuis, need_jac=True):
        """Cost, and the blocks of the normal equations."""
        with torch.no_grad():
            M, phi = motion(u)
        img, dimg = render(M, phi)
        sc = nuis[:, 0] if fit_scale else torch.ones(n, dtype=dtype, device=device)
        bg = nuis[:, int(fit_scale)] if fit_background else torch.zeros(n, dtype=dtype, device=device)
        model = img * sc[:, None, None, None] + bg[:, None, None, None]
        r = data - model
        cost = (wts * r * r).sum()
        if not need_jac:
            return cost, None
        # Local Jacobian columns per point: M, phi, (scale), (background)  -> [n, R, 2 + q]
        cols = [dimg[:, :, 0] * sc[:, None, None, None], dimg[:, :, 1] * sc[:, None, None, None]]
        if fit_scale:
            cols.append(img)
        if fit_background:
            cols.append(torch.ones_like(img))
        J = torch.stack(cols, -1).reshape(n, -1, 2 + q)
        wr = (wts * r).reshape(n, -1)
        JW = J * wts.reshape(n, -1, 1)
        G = JW.transpose(1, 2) @ J  # [n, 2+q, 2+q]
        g = (J * wr[..., None]).sum(1)  # [n, 2+q]
        # d(M, phi)/du by autograd: [n, 2, P]
        D = torch.autograd.functional.jacobian(motion, u.detach()).permute(1, 0, 2).to(dtype)
        return cost, (G, g, D, M)

    def solve(blocks, lam):
        G, g, D, _ = blocks
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
        dnu = (Binv_g - torch.einsum("kqi,i->kq", Binv_At, du)) if q else torch.zeros(n, 0, dtype=dtype, device=device)
        return du, dnu, S

    # Nuisance start: the linear least-squares scale (and background) for the start model.
    with torch.no_grad():
        mp = motion(u)
        img0, _ = render(mp[0], mp[1])
        cols = ([img0] if fit_scale else []) + ([torch.ones_like(img0)] if fit_background else [])
        if q:
            X = torch.stack(cols, -1).reshape(n, -1, q)
            XW = X * wts.reshape(n, -1, 1)
            nuis = torch.linalg.solve(XW.transpose(1, 2) @ X + 1e-30 * torch.eye(q, dtype=dtype, device=device),
                                      (XW * data.reshape(n, -1, 1)).sum(1)[..., None])[..., 0]
        else:
            nuis = torch.zeros(n, 0, dtype=dtype, device=device)

    cost, blocks = evaluate(u, nuis)
    lam = 1e-3
    converged = False
    it = 0
    floor = (10 * torch.finfo(dtype).eps) ** 2 * float((wts * data * data).sum())
    # With the noise known the cost is a chi2: a decrease far below 1 per pixel means nothing.
    abs_tol = tol * float((wts > 0).sum()) if noise_std is not None else 0.0
    for it in range(1, max_iter + 1):
        du, dnu, _ = solve(blocks, lam)
        u_t = u + du.to(torch.float64)
        nu_t = nuis + dnu
        with torch.no_grad():
            M_t = motion(u_t)[0]
        if not bool(torch.isfinite(M_t).all()) or not bool(torch.isfinite(u_t).all()) or bool((M_t > m_limit).any()):
            lam *= 4
            if lam > 1e12:
                break
            continue
        if bool((M_t > m_bound).any()):
            m_bound = M_t * 1.3 + 0.5
            tau_q, w_q = quadrature_nodes(*nodes_for(torch.maximum(m_bound, M_t)), dtype=dtype, device=device)
            cost, blocks = evaluate(u, nuis)  # same point, new nodes: a fair comparison
        c_t, b_t = evaluate(u_t, nu_t)
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

    # Fisher information of u (nuisance profiled out) and the covariance in natural units.
    _, _, S = solve(blocks, 0.0)
    n_pix = int((wts > 0).sum()) + out_n
    P = u.numel()
    total_cost = float(cost) + float(out_cost)
    dof = n_pix - P - q * n
    red = total_cost / max(dof, 1)
    cov_u = torch.linalg.pinv(S.to(torch.float64), hermitian=True)
    if noise_std is None:
        cov_u = cov_u * red
    p_hat = natural(u)
    jac_nat = torch.where(is_log, p_hat, torch.ones_like(p_hat))
    cov = (jac_nat[:, None] * cov_u * jac_nat[None, :]).detach().cpu().numpy()
    params = p_hat.detach().cpu().numpy()
    scale_full = np.full(F, np.nan)
    bg_full = np.full(F, np.nan) if fit_background else None
    idx_np = idx.cpu().numpy()
    if fit_scale:
        scale_full[idx_np] = nuis[:, 0].detach().cpu().numpy()
    else:
        scale_full[idx_np] = 1.0
    if fit_background:
        bg_full[idx_np] = nuis[:, int(fit_scale)].detach().cpu().numpy()
    delay_hat = float(params[list(names).index("delay_s")]) if struct.fit_delay else float(delay)
    return DirectModelFit(
        form=struct.form, param_names=tuple(names), params=params, covariance=cov, std=np.sqrt(np.clip(np.diag(cov), 0, None)),
        start_params=np.asarray(p0), delay_s=delay_hat, cost=total_cost, dof=int(dof), reduced_chi2=float(red),
        noise_estimated=noise_std is None, converged=bool(converged), n_iter=int(it), used=use.cpu().numpy(), n_excluded=n_excluded,
        scale=scale_full, background=bg_full, _struct=struct)


# ------------------------------------------------------------- single-exposure start
class AliasResolution(NamedTuple):
    """Result of :func:`resolve_alias_with_model`."""

    frf: Any
    model: Any
    flipped: np.ndarray
    candidates: list


def resolve_alias_with_model(frf, alias_phase, *, n_poles: int | None = None, n_zeros: int | None = None,
                             delay_s: float | None = None, max_order: int = 8, max_rounds: int = 20,
                             n_candidates: int = 4) -> AliasResolution:
    """Pick each point's phase branch (measured or alias) with a model: a single-exposure start.

    With one exposure window per point (Proposition 3) every phase has an alias that renders
    the same image, so a per-point fit picks its branch by chance under noise. A model over
    all points tells them apart. From each of three initial choices (as measured; continuity
    from the lowest frequency, each point taking the branch nearest the previous point's
    phase; all aliases) the model is fitted, every point then takes the branch nearer the
    model (in units of its std), and so on until no point changes; then single points and
    pairs of neighbours of the best choice are flipped and the descent repeated while that
    lowers the chi2. The choice with the smallest chi2 wins.

    Args:
        frf: SISO :class:`~torchblur.sysid.frequency_response.FrequencyResponse` of the per-point fits
            (its covariance weights the fits).
        alias_phase: [F] the other branch of each point (``SinusoidFit.alias_phase``), rad.
        n_poles, n_zeros, delay_s, max_order: passed to
            :func:`~torchblur.sysid.tf_fit.fit_transfer_function` (fixed orders are much faster).
        max_rounds: rounds of re-assignment at most per initial choice.
        n_candidates: how many of the best branch choices' models to return as ``candidates``.

    Returns:
        :class:`AliasResolution` ``(frf, model, flipped, candidates)``: the response with the
        chosen branches (an alias point's magnitude-phase correlation changes sign: the alias
        moves opposite to the phase), the TransferFunctionFit on it, bool [F] where the alias
        was taken, and the models of the best branch choices (lowest chi2 first; pass them
        all as ``start`` to :func:`fit_direct`, which keeps the one that fits the images best).
    """
    from torchblur.sysid.frequency_response import FrequencyResponse
    from torchblur.sysid.tf_fit import fit_transfer_function

    if not isinstance(frf, FrequencyResponse) or not frf.is_siso:
        raise InputTypeError(f"frf: expected a SISO FrequencyResponse, got {type(frf).__name__}")
    alias = np.asarray(alias_phase.detach().cpu().numpy() if isinstance(alias_phase, torch.Tensor) else alias_phase, dtype=np.float64)
    F = frf.omega.size
    if alias.shape != (F,):
        raise ShapeError(f"alias_phase: expected shape [F] = [{F}], got {alias.shape}")
    h = frf.response[0, 0]
    ok = np.isfinite(h) & np.isfinite(alias)
    mag = np.abs(h)
    branches = np.stack([h, mag * np.exp(1j * alias)])  # [2, F]
    cov = np.array(frf.cov[0, 0])
    cov_alias = cov.copy()
    cov_alias[:, 0, 1] *= -1
    cov_alias[:, 1, 0] *= -1

    def frf_of(choice):
        resp = np.where(choice, branches[1], branches[0])
        c = np.where(choice[:, None, None], cov_alias, cov)
        return FrequencyResponse(frf.omega, resp, cov=c, input_labels=frf.input_labels, output_labels=frf.output_labels,
                                 meta=dict(frf.meta))

    # Initial choices.
    inits = [np.zeros(F, dtype=bool), np.ones(F, dtype=bool) & ok]
    cont = np.zeros(F, dtype=bool)
    prev = None
    for k in range(F):
        if not ok[k]:
            continue
        ph = np.angle(branches[:, k])
        if prev is not None:
            d = np.abs(np.angle(np.exp(1j * (ph - prev))))
            cont[k] = bool(d[1] < d[0])
        prev = ph[int(cont[k])]
    inits.insert(1, cont)
    sig = np.sqrt(np.nan_to_num(cov[:, 0, 0]) + mag**2 * np.nan_to_num(cov[:, 1, 1]))
    sig = np.where(sig > 0, sig, np.maximum(mag, 1e-300))
    tried = []
    seen = set()

    def descend(choice):
        """Fit, re-assign every point to the nearer branch, repeat until nothing changes."""
        for _ in range(max_rounds):
            key = choice.tobytes()
            if key in seen:
                return
            seen.add(key)
            try:
                model = fit_transfer_function(frf_of(choice), n_poles=n_poles, n_zeros=n_zeros, delay_s=delay_s,
                                              max_order=max_order)
            except (ValueError, np.linalg.LinAlgError):
                return
            tried.append((model.chi2, choice.copy(), model))
            pred = model.frequency_response(frf.omega)
            dist = np.abs(branches - pred[None]) / sig[None]
            new = (dist[1] < dist[0]) & ok
            if np.array_equal(new, choice):
                return
            choice = new

    for choice in inits:
        descend(choice)
    if not tried:
        raise ParameterError("frf: no model could be fitted to any branch choice")
    # Local search: flip one point, or two neighbours, of the best choice, and descend again,
    # until no such move finds a smaller chi2 (a wrong branch at a few points can trap the
    # re-assignment: the model bends toward them).
    for _ in range(max_rounds):
        best_chi2 = min(t[0] for t in tried)
        base = min(tried, key=lambda t: t[0])[1]
        moves = [[k] for k in range(F)] + [[k, k + 1] for k in range(F - 1)]
        for mv in moves:
            c = base.copy()
            c[mv] = ~c[mv]
            descend(c & ok)
        if min(t[0] for t in tried) >= best_chi2:
            break
    tried.sort(key=lambda t: t[0])
    _, choice, model = tried[0]
    return AliasResolution(frf_of(choice), model, choice, [t[2] for t in tried[:n_candidates]])
