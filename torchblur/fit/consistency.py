"""The renderer as a loss: measurement consistency of a predicted motion with observed images.

A model (a network, an optimiser, anything) predicts the spot's motion; the loss renders it
with the very same :class:`~torchblur.render.blur.BlurRenderer`, PSF and exposure windows that
describe the measurement and compares the rendering with the observed images, one value per
sample (as ``deepinv.loss.MCLoss`` does with ``metric(physics.A(x), y)``). No labels are
needed: a network trained on it alone is trained self-supervised.

Shapes (glossary): ``[...]`` batch, ``E`` exposures of the same motion, ``H, W`` pixels.
``observed[..., e, i, j]`` is the integrated intensity of exposure ``e`` at row i, column j
(x = j, y = i), in the units of the PSF times seconds, dark level subtracted.
"""
from __future__ import annotations

from typing import Mapping

import torch
from torch import nn

from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_choice, check_finite, check_type
from torchblur.losses import LOSSES, image_loss
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.blur import BlurRenderer
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid, Trajectory

__all__ = ["BlurConsistencyLoss", "blur_consistency", "REDUCTIONS"]

REDUCTIONS = ("none", "mean", "sum")


class _ExposureAxis(Trajectory):
    """A trajectory of batch ``[...]`` seen with a trailing exposure axis, batch ``[..., 1]``:
    the same motion for every exposure window ``[..., E]``."""

    __slots__ = ("base",)

    def __init__(self, base: Trajectory):
        self.base = base

    @property
    def shape(self) -> torch.Size:
        return self.base.shape + (1,)

    def position(self, t: torch.Tensor) -> torch.Tensor:
        # t [..., E, S] -> [..., E*S] (the base's batch broadcasts against [...]).
        E, S = t.shape[-2:]
        return self.base.position(t.flatten(-2)).unflatten(-2, (E, S))

    def path_length(self, window: ExposureWindow) -> torch.Tensor:
        # window [..., E]: one bound per exposure, each from the base trajectory.
        E = window.shape[-1]
        return torch.stack([self.base.path_length(window[..., e]) for e in range(E)], -1)

    def phase_span(self, window: ExposureWindow) -> torch.Tensor:
        E = window.shape[-1]
        return torch.stack([self.base.phase_span(window[..., e]) for e in range(E)], -1)


def _as_trajectory(pred, omega, like: torch.Tensor) -> Trajectory:
    """Normalise ``pred`` (see :func:`blur_consistency`) to a :class:`Trajectory`."""
    if isinstance(pred, Trajectory):
        return pred
    if isinstance(pred, Mapping):
        unknown = set(pred) - {"amplitude", "phase", "omega"}
        if unknown:
            raise ParameterError(f"pred: unknown keys {sorted(unknown)}; expected 'amplitude', 'phase' and optionally 'omega'")
        for key in ("amplitude", "phase"):
            if key not in pred:
                raise ParameterError(f"pred: missing key {key!r}; expected 'amplitude' [..., 2], 'phase' [..., 2], 'omega' [...]")
        amp = as_tensor(pred["amplitude"], "pred['amplitude']", like=like)
        phase = as_tensor(pred["phase"], "pred['phase']", like=amp)
        om = pred.get("omega", omega)
        if om is None:
            raise ParameterError("pred: no 'omega' key and no omega argument; give the frequency (rad/s) one way or the other")
        for name, t in (("pred['amplitude']", amp), ("pred['phase']", phase)):
            if t.dim() < 1 or t.shape[-1] != 2:
                raise ShapeError(f"{name}: expected shape [..., 2] (x, y), got {tuple(t.shape)}")
        return Sinusoid(amp, phase, _both_axes(as_tensor(om, "omega", like=amp)))
    if isinstance(pred, torch.Tensor):
        p = as_tensor(pred, "pred", like=like)
        if p.dim() < 1 or p.shape[-1] not in (4, 5):
            raise ShapeError(
                "pred: expected a parameter tensor [..., 4] (amplitude_x, amplitude_y, phase_x, phase_y; omega given) "
                f"or [..., 5] (..., omega), got {tuple(p.shape)}"
            )
        if p.shape[-1] == 5:
            om = p[..., 4]
        elif omega is None:
            raise ParameterError("pred: a [..., 4] parameter tensor needs the omega argument (rad/s)")
        else:
            om = as_tensor(omega, "omega", like=p)
        return Sinusoid(p[..., 0:2], p[..., 2:4], _both_axes(om))
    raise InputTypeError(
        f"pred: expected a Trajectory, a dict of sinusoid parameters or a parameter tensor, got {type(pred).__name__}"
    )


def _both_axes(omega: torch.Tensor) -> torch.Tensor:
    """``omega [...]`` (one per sample) as ``[..., 2]``, the same for both axes: a batch of two
    samples' ``[2]`` must not be read as one frequency per axis."""
    return omega[..., None].expand(omega.shape + (2,))


def _check_settings(renderer, psf, window, loss, reduction, normalize) -> None:
    """The settings :func:`blur_consistency` and :class:`BlurConsistencyLoss` share."""
    check_type(renderer, "renderer", BlurRenderer, "a torchblur BlurRenderer")
    check_type(psf, "psf", (GaussianPSF, KernelPSF), "GaussianPSF or KernelPSF")
    check_type(window, "window", ExposureWindow, "an ExposureWindow")
    check_choice(loss, "loss", LOSSES)
    check_choice(reduction, "reduction", REDUCTIONS)
    check_type(normalize, "normalize", bool, "True or False")


def _unit_frobenius(x: torch.Tensor) -> torch.Tensor:
    """``x / ||x||_F`` over the last two axes ``[..., H, W]``; an all-zero image stays 0.

    ``x`` is first divided by its detached largest ``|x|``: the ratio is scale invariant, so
    this changes neither the value nor the gradient, but ``x^2`` no longer underflows (a spot
    far off the frame in float32 left tiny nonzero pixels with a zero norm: NaN gradients).
    An all-zero (or all-subnormal) image is divided by 1, so its gradient stays finite.
    """
    peak = x.detach().abs().amax((-1, -2), keepdim=True)
    y = x / torch.where(peak >= torch.finfo(x.dtype).tiny, peak, torch.ones_like(peak))
    n2 = y.square().sum((-1, -2), keepdim=True)
    return y / torch.where(n2 > 0, n2, torch.ones_like(n2)).sqrt()


def blur_consistency(
    pred,
    observed: torch.Tensor,
    *,
    renderer: BlurRenderer,
    psf: GaussianPSF | KernelPSF,
    window: ExposureWindow,
    loss: str = "l2",
    reduction: str = "none",
    noise_std=None,
    normalize: bool = False,
    omega=None,
) -> torch.Tensor:
    """Measurement-consistency loss: ``loss(renderer(pred, psf, window), observed)`` per sample.

    Args:
        pred: the predicted motion (displacement from the rest position), one of:

            - a :class:`~torchblur.render.trajectory.Trajectory` of batch ``[...]`` (``Sinusoid``,
              ``Multisine``, ``SplineTrajectory``, ...): the same motion is rendered in each
              of the E exposure windows;
            - a dict of sinusoid parameters: ``"amplitude"`` px ``[..., 2]`` (x, y),
              ``"phase"`` rad ``[..., 2]``, ``"omega"`` rad/s ``[...]`` (or omit it and pass
              ``omega``);
            - a tensor ``[..., 5]`` = (amplitude_x, amplitude_y, phase_x, phase_y, omega) or
              ``[..., 4]`` without omega (then pass ``omega``).

            A motion along x only has ``amplitude = (M, 0)``, ``phase = (phi, phi)``.
        observed: ``[..., E, H, W]``: E exposures of the same motion (E >= 1), H, W the
            renderer's frame size.
        renderer: the :class:`~torchblur.render.blur.BlurRenderer` of the measurement.
        psf: ``GaussianPSF`` or ``KernelPSF`` with batch broadcastable to ``[...]``, shared
            by the E exposures.
        window: :class:`~torchblur.render.window.ExposureWindow` with batch broadcastable to
            ``[..., E]`` (last dim 1 or E): exposure ``e`` integrates over ``window[..., e]``.
        loss: ``"l2"`` (sum of squares; Gaussian maximum likelihood with ``noise_std``),
            ``"l1"``, ``"linf"`` or ``"poisson"`` (deviance; images in counts).
        reduction: ``"none"``: one value per sample ``[...]``; ``"mean"`` / ``"sum"`` over
            the batch (a scalar).
        noise_std: pixel noise std, a number or a tensor broadcastable to ``[..., E, H, W]``
            (use ``sigma[..., None, None, None]`` for one value per sample, ``inf`` to drop a
            pixel). Weights the residual by ``1 / noise_std`` (``"l1"``, ``"linf"``) or its
            square by ``1 / noise_std^2`` (``"l2"``: then the loss is a chi-square). Not used
            with ``"poisson"``.
        normalize: divide each rendered and each observed image by its Frobenius norm
            before comparing (the paper's eq. 8; insensitive to the intensity scale).
        omega: rad/s ``[...]``, for the parameter forms of ``pred`` that omit it.

    Returns:
        ``value[...]`` (``reduction="none"``): the loss of sample ``[...]`` summed over its E
        exposures and pixels, where ``[...]`` broadcasts the batches of ``pred``,
        ``observed``, ``psf`` and ``window``; a scalar otherwise. Differentiable in ``pred``
        (and in the PSF and window tensors); dtype and device follow the inputs.

    Example:
        >>> import math, torch, torchblur as tb
        >>> renderer = tb.BlurRenderer(height=24, width=24)
        >>> psf = tb.GaussianPSF.isotropic(torch.tensor([12.0, 12.0]), 1.5)
        >>> window = tb.ExposureWindow(torch.tensor([2.5e-3]), torch.tensor([3e-3, 8e-3]))   # E = 2
        >>> truth = {"amplitude": torch.tensor([[5.0, 0.0]]), "phase": torch.tensor([[0.4, 0.4]]),
        ...          "omega": torch.tensor([2 * math.pi * 100])}
        >>> observed = renderer(tb.Sinusoid(**truth)[:, None], psf, window)   # [1, 2, 24, 24]
        >>> blur_consistency(truth, observed, renderer=renderer, psf=psf, window=window).shape
        torch.Size([1])
    """
    _check_settings(renderer, psf, window, loss, reduction, normalize)
    observed = _as_observed(observed, renderer, window)
    traj = _as_trajectory(pred, omega, observed)
    model, data = _model_and_data(renderer, traj, psf, window, observed)
    weight = _pixel_weight(noise_std, loss, model, data)
    if normalize:
        model, data = _unit_frobenius(model), _unit_frobenius(data)
    value = image_loss(model.flatten(-3), data.flatten(-3), loss=loss, weight=None if weight is None else weight.flatten(-3))
    if reduction == "mean":
        return value.mean()
    if reduction == "sum":
        return value.sum()
    return value


def _model_and_data(renderer: BlurRenderer, traj: Trajectory, psf, window: ExposureWindow, observed: torch.Tensor):
    """``(model, data)``, both ``[..., E, H, W]`` on the broadcast batch ``[...]`` of ``traj``,
    ``psf``, ``window`` (as ``[..., E]``) and ``observed`` ``[..., E, H, W]``: the rendered
    motion in each exposure, and the observed images in the model's dtype."""
    batch_e = observed.shape[:-2]  # [..., E]
    E, H, W = batch_e[-1], renderer.height, renderer.width
    try:
        out_batch = torch.broadcast_shapes(traj.shape, psf.shape, window.shape[:-1] if window.shape else (), batch_e[:-1])
    except RuntimeError:
        raise ShapeError(
            f"batch shapes do not broadcast: pred {tuple(traj.shape)}, psf {tuple(getattr(psf, 'shape', ()))}, "
            f"window {tuple(window.shape)} (as [..., E]), observed {tuple(observed.shape)} (as [..., E, H, W])"
        ) from None
    model = renderer(_ExposureAxis(traj), psf[..., None], window if window.shape else window.expand((1,)))
    model = model.expand(out_batch + (E, H, W))
    return model, observed.to(model.dtype).expand(out_batch + (E, H, W))

def _as_observed(observed, renderer: BlurRenderer, window: ExposureWindow) -> torch.Tensor:
    """``observed`` checked as ``[..., E, H, W]`` floating, finite, of the renderer's frame size,
    with a window of 1 or E exposures."""
    check_type(observed, "observed", torch.Tensor, "a tensor [..., E, H, W]")
    if observed.is_complex() or observed.dtype == torch.bool:
        raise InputTypeError(f"observed: expected a real tensor [..., E, H, W], got dtype {observed.dtype}")
    if not observed.is_floating_point():
        observed = observed.to(torch.get_default_dtype())
    H, W = renderer.height, renderer.width
    if observed.dim() < 3 or tuple(observed.shape[-2:]) != (H, W):
        raise ShapeError(f"observed: expected shape [..., E, {H}, {W}] (the renderer's frame), got {tuple(observed.shape)}")
    check_finite(observed, "observed")
    E = observed.shape[-3]
    if window.shape and window.shape[-1] not in (1, E):
        raise ShapeError(f"window: expected a last dim of 1 or E={E} (one window per exposure), got shape {tuple(window.shape)}")
    return observed


def _pixel_weight(noise_std, loss: str, model: torch.Tensor, data: torch.Tensor):
    """Per-pixel weights ``[..., E, H, W]`` from ``noise_std`` (``1/s^2`` for l2, ``1/s`` for l1
    and linf), or None without a noise; refused with the Poisson deviance."""
    if noise_std is None:
        return None
    if loss == "poisson":
        raise ParameterError("noise_std: not used with loss='poisson' (the deviance carries its own variance)")
    s = as_tensor(noise_std, "noise_std", like=model)
    bad = torch.isnan(s.detach()) | (s.detach() <= 0)
    if bool(bad.any()):
        raise ParameterError(f"noise_std: expected every value > 0 (inf drops a pixel), got {int(bad.sum())} NaN or non-positive")
    try:
        fits = torch.broadcast_shapes(s.shape, data.shape) == data.shape
    except RuntimeError:
        fits = False
    if not fits:
        raise ShapeError(
            f"noise_std: expected a number or a shape broadcastable to [..., E, H, W] = {tuple(data.shape)}, "
            f"got {tuple(s.shape)}"
        )
    return (1 / s**2 if loss == "l2" else 1 / s).expand(data.shape)


class BlurConsistencyLoss(nn.Module):
    """The blur renderer as a loss inside any model (measurement consistency, self-supervised).

    Args:
        renderer: the :class:`~torchblur.render.blur.BlurRenderer` of the measurement.
        psf: the PSF (``GaussianPSF`` or ``KernelPSF``), batch broadcastable to ``[...]``.
        window: the exposure windows, batch broadcastable to ``[..., E]``.
        loss: ``"l2"`` | ``"l1"`` | ``"linf"`` | ``"poisson"``, see :func:`blur_consistency`.
        reduction (str, optional): the reduction applied to the output, as in torch's
            losses: ``"none"`` | ``"mean"`` | ``"sum"``. ``"none"``: no reduction, one value
            per sample ``[...]`` (each summed over its E exposures and pixels); ``"mean"``: the
            sum of the output divided by the number of samples (not by the number of pixels,
            unlike ``nn.MSELoss``); ``"sum"``: the output summed. Default: ``"none"``.
        noise_std, normalize, omega: see :func:`blur_consistency`.

    State: the PSF's tensors (``psf_center``, ``psf_cov``, ``psf_amplitude`` of a
    ``GaussianPSF``, or ``psf_kernel`` of a ``KernelPSF``), the window's (``window_start``,
    ``window_duration``) and ``noise_std`` / ``omega`` when given as tensors are buffers
    (detached copies): they follow ``.to(dtype)`` / ``.to(device)`` and live in the
    ``state_dict``, so a fresh module built with the same kinds and shapes loads them back.
    Numbers given for ``noise_std`` / ``omega`` stay plain attributes. :attr:`psf` and
    :attr:`window` rebuild the objects from the buffers.

    ``forward(pred, observed) -> [...]`` (or a scalar with ``reduction`` "mean"/"sum"),
    with ``pred`` a Trajectory, a dict of sinusoid parameters or a parameter tensor and
    ``observed`` ``[..., E, H, W]``; see :func:`blur_consistency`. The module holds the
    measurement's description and nothing else (``forward`` stores nothing).

    Example:
        >>> import math, torch, torchblur as tb
        >>> renderer = tb.BlurRenderer(height=24, width=24)
        >>> psf = tb.GaussianPSF.isotropic(torch.tensor([12.0, 12.0]), 1.5)
        >>> window = tb.ExposureWindow(torch.tensor([2.5e-3]), torch.tensor([3e-3, 8e-3]))
        >>> crit = BlurConsistencyLoss(renderer, psf, window, omega=2 * math.pi * 100, noise_std=0.01)
        >>> pred = torch.tensor([[5.0, 0.0, 0.4, 0.4], [4.0, 0.0, 0.1, 0.1]], requires_grad=True)   # [B=2, 4]
        >>> crit(pred, torch.zeros(2, 2, 24, 24)).shape
        torch.Size([2])
        >>> sorted(crit.state_dict())
        ['psf_amplitude', 'psf_center', 'psf_cov', 'window_duration', 'window_start']
    """

    def __init__(
        self,
        renderer: BlurRenderer,
        psf: GaussianPSF | KernelPSF,
        window: ExposureWindow,
        *,
        loss: str = "l2",
        reduction: str = "none",
        noise_std=None,
        normalize: bool = False,
        omega=None,
    ):
        super().__init__()
        _check_settings(renderer, psf, window, loss, reduction, normalize)  # at construction, not at the first batch
        self.renderer = renderer
        self._psf_kind = type(psf)
        if isinstance(psf, GaussianPSF):
            self._keep("psf_center", psf.center)
            self._keep("psf_cov", psf.cov)
            self._keep("psf_amplitude", psf.amplitude)
        else:
            self._keep("psf_kernel", psf.kernel)
        self._keep("window_start", window.start)
        self._keep("window_duration", window.duration)
        self._keep("noise_std", noise_std)
        self._keep("omega", omega)
        self.loss = loss
        self.reduction = reduction
        self.normalize = normalize

    def _keep(self, name: str, value) -> None:
        """A tensor becomes a buffer (a detached, contiguous copy); anything else an attribute."""
        if isinstance(value, torch.Tensor):
            self.register_buffer(name, value.detach().clone(memory_format=torch.contiguous_format))
        else:
            setattr(self, name, value)

    @property
    def psf(self) -> GaussianPSF | KernelPSF:
        """The PSF, rebuilt from the buffers (dtype and device follow the module)."""
        if self._psf_kind is GaussianPSF:
            return GaussianPSF(self.psf_center, self.psf_cov, self.psf_amplitude)
        return KernelPSF(self.psf_kernel)

    @property
    def window(self) -> ExposureWindow:
        """The exposure windows, rebuilt from the buffers."""
        return ExposureWindow(self.window_start, self.window_duration)

    def forward(self, pred, observed: torch.Tensor) -> torch.Tensor:
        return blur_consistency(
            pred=pred,
            observed=observed,
            renderer=self.renderer,
            psf=self.psf,
            window=self.window,
            loss=self.loss,
            reduction=self.reduction,
            noise_std=self.noise_std,
            normalize=self.normalize,
            omega=self.omega,
        )

    def extra_repr(self) -> str:
        return (f"psf={self._psf_kind.__name__}, loss={self.loss!r}, reduction={self.reduction!r}, "
                f"normalize={self.normalize}, noise_std={'set' if self.noise_std is not None else None}")
