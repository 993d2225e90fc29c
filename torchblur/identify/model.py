"""The model stage's pieces: the transfer-function model of the frequency response
(:func:`fit_model`, without the points the images' model does not explain:
:func:`model_exclusions`) and, with ``model.direct``, the model fitted to every image at once
(:func:`fit_direct_model`)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import torch

from torchblur.fit.status import POOR_FIT_CHI2, POOR_FIT_FLAG
from torchblur.identify.record import LOGGER
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.sysid.direct import fit_direct
from torchblur.sysid.flags import ALIAS, POOR_FIT
from torchblur.sysid.tf_fit import fit_transfer_function

__all__ = ["common_delay_std", "fit_direct_model", "fit_model", "model_exclusions", "model_parameter_lines", "modes_outside_band", "points_needed", "with_common_delay"]


def points_needed(model_cfg) -> int:
    """The fewest valid points per channel the smallest model of ``model_cfg`` (``cfg.model``)
    can be fitted to: its real parameters (``n_poles``, or 1 when the order is selected;
    ``n_zeros`` or 0; the gain; the delay where fitted) plus one, two real observations a point."""
    n_par = (1 if model_cfg.n_poles is None else int(model_cfg.n_poles)) + int(model_cfg.n_zeros or 0) + 1
    n_par += 1 if model_cfg.fit_delay else 0
    return math.ceil((n_par + 1) / 2)


def model_exclusions(frf, cfg) -> tuple[np.ndarray, list]:
    """Which points the transfer-function fit leaves out: ``(left_out, kept)``.

    The rule: a valid point flagged ``ALIAS`` (one exposure, its phase branch not decided: its
    phase may be the alias, far beyond any std) always gets weight 0. A valid point flagged
    ``POOR_FIT`` (its images' model does not explain them) gets weight 0, unless its channel
    would keep fewer than :func:`points_needed` valid points; then the channel's poor-fit points
    are all kept (at their inflated stds).

    Returns:
        ``left_out`` bool ``[O, I, F]``; ``kept``: ``(output label, input label, n poor-fit
        points kept)`` for each channel where the rule kept them.
    """
    alias = ((frf.flags & ALIAS) != 0) & frf.valid
    poor = ((frf.flags & POOR_FIT) != 0) & frf.valid & ~alias
    need = points_needed(cfg.model)
    left_out = np.array(alias)
    kept = []
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            if not poor[o, i].any():
                continue
            if int((frf.valid[o, i] & ~poor[o, i] & ~alias[o, i]).sum()) >= need:
                left_out[o, i] |= poor[o, i]
            else:
                kept.append((frf.output_labels[o], frf.input_labels[i], int(poor[o, i].sum())))
    return left_out, kept


def _without(frf, left_out):
    """``frf`` with the ``left_out`` points set to NaN (weight 0 in the fit), each logged by its reason."""
    alias = left_out & ((frf.flags & ALIAS) != 0)
    for pts, what in ((left_out & ~alias, "poor-fit point(s)"), (alias, "alias point(s) (phase branch not decided)")):
        if pts.any():
            f = ", ".join(f"{v:.4g}" for v in frf.freq_hz[pts.any(axis=(0, 1))])
            LOGGER.info(f"model: {int(pts.sum())} {what} left out of the fit ({f} Hz)")
    return frf.replace(response=np.where(left_out, np.nan, frf.response)) if left_out.any() else frf


def fit_model(cfg, frf):
    """Stage 7 of :func:`identify`: the transfer-function model of ``frf`` under
    ``cfg.model`` (None, with the reason logged, when the fit fails)."""
    left_out, kept = model_exclusions(frf, cfg)
    for out, inp, n in kept:
        LOGGER.info(f"model: warning: output {out} from input {inp}: leaving its {n} poor-fit point(s) out would leave fewer "
                    f"than {points_needed(cfg.model)} points; they are kept, at their inflated stds")
    frf = _without(frf, left_out)
    # Outputs with a channel that has no valid point at all (a spot flagged at every
    # frequency) are left out, so they do not take the other outputs' models with them.
    keep = frf.valid.any(-1).all(-1)  # [O]
    if not keep.any():
        LOGGER.info("model: fit failed: no output has a valid point in every channel")
        return None
    if not keep.all():
        dropped = [lab for lab, k in zip(frf.output_labels, keep) if not k]
        LOGGER.info(f"model: output(s) {', '.join(dropped)} have a channel with no valid point and are left out of the model")
        frf = frf.select_outputs(keep)
    try:
        model = fit_transfer_function(frf, n_poles=cfg.model.n_poles, n_zeros=cfg.model.n_zeros,
                                      delay_s=None if cfg.model.fit_delay else 0.0, max_order=int(cfg.model.max_order),
                                      common_delay_std_s=common_delay_std(frf, cfg))
    except Exception as exc:  # the FRF is still a result; say why the model failed
        LOGGER.info(f"model: fit failed: {exc}")
        return None
    if model.is_siso:
        LOGGER.info(f"model: {model.n_poles} poles, {model.n_zeros} zeros, delay {model.delay_s * 1e6:.2f} us, "
                    f"reduced chi2 {model.reduced_chi2:.3f}")
    else:  # one model per channel (output o from input i)
        for o, out in enumerate(model.output_labels):
            for i, inp in enumerate(model.input_labels):
                LOGGER.info(f"model {out} from {inp}: {model.n_poles[o][i]} poles, {model.n_zeros[o][i]} zeros, delay "
                            f"{model.delay_s[o][i] * 1e6:.2f} us, reduced chi2 {model.reduced_chi2[o][i]:.3f}")
    return model


def common_delay_std(frf, cfg) -> float:
    """The std (s) of the timing error every point of ``frf`` shares: the latency calibration's
    (``frf.meta["timing"]["latency_std_s"]``, which the points' phase variance holds), for
    :func:`~torchblur.sysid.tf_fit.fit_transfer_function`'s ``common_delay_std_s`` where the
    delay is fitted (``model.fit_delay``); 0 otherwise or where the response does not say."""
    lat = frf.meta.get("timing", {}).get("latency_std_s", 0.0) if cfg.model.fit_delay else 0.0
    return float(lat) if lat is not None and math.isfinite(float(lat)) else 0.0


def _pm(value: float, std: float, fmt: str) -> str:
    """``"419.853 +- 0.12"`` (``"+- ?"`` where the std is unknown)."""
    return f"{value:{fmt}} +- {std:.2g}" if math.isfinite(std) else f"{value:{fmt}} +- ?"


def model_parameter_lines(model, o: int = 0, i: int = 0) -> list[str]:
    """The report's lines on channel (o, i) of a two-step model (a TransferFunctionFit): its
    parameters with their stds (modes, DC gain, delay, real poles and zeros) and the table of
    the orders compared, the chosen one marked, under the stated criterion."""
    pick = (lambda v: v) if model.is_siso else (lambda v: v[o][i])
    lines = []
    for kind, word in (("poles", "mode"), ("zeros", "anti-resonance")):
        modes = model.modal_parameters(kind)
        for m in pick(modes):
            lines.append(f"  {word}: {_pm(m['freq_hz'], m['freq_hz_std'], '.3f')} Hz, damping {_pm(m['zeta'], m['zeta_std'], '.4f')}")
    names = model.channel_parameters(o, i)[0]
    for name in names:
        v, sd = model.parameter(name, o, i)
        if name == "dc_gain":
            lines.append(f"  dc gain: {_pm(v, sd, '.5g')}")
        elif name == "delay_s":
            lines.append(f"  delay: {_pm(v * 1e6, sd * 1e6, '.3f')} us")
        elif name.endswith("_rate"):
            lines.append(f"  real {'pole' if name[0] == 'p' else 'zero'} at -{_pm(v / (2 * math.pi), sd / (2 * math.pi), '.4g')} Hz")
    if not names:
        lines.append("  (no parameter covariance)")
    rows = pick(model.candidates)
    if rows:
        crit = model.order_criterion
        how = ("orders fixed by the config" if crit == "fixed" else
               "order chosen by the smallest BIC = chi2 + P ln(2 N) (N points, P parameters; chi2 after a short polish, the "
               "chosen one's after the full one; the scan stops once larger orders cannot win)")
        lines.append(f"  {how}:")
        lines.append(f"    {'poles':>5} {'zeros':>5} {'P':>3} {'chi2':>11} {'dof':>4} {'red chi2':>9} {'BIC':>11}")
        for r in rows:
            lines.append(f"    {r['n_poles']:5d} {r['n_zeros']:5d} {r['n_params']:3d} {r['chi2']:11.4g} {r['dof']:4d} "
                         f"{r['reduced_chi2']:9.3g} {r['bic']:11.4g}" + ("  <- chosen" if r["chosen"] else ""))
    return lines


def modes_outside_band(modes, f_lo_hz: float, f_hi_hz: float, factor: float = 3.0) -> list:
    """The modes (dicts with ``freq_hz``, as ``modal_parameters()`` gives) more than ``factor``
    beyond the swept band ``[f_lo_hz, f_hi_hz]``: the images cannot constrain them (a fitted
    mode there may run away while the fit reports convergence)."""
    return [m for m in modes if not (f_lo_hz / factor <= m["freq_hz"] <= factor * f_hi_hz)]


def fit_direct_model(cfg, model, images, windows, omega, amps, psf, power_t, noise, mask, fit, direction, still_psf=None,
                     latency_std_s: float = 0.0):
    """The direct model (one axis, one spot): every image at once, weighted by the camera's
    noise model ``noise`` (:class:`~torchblur.render.camera.CameraNoise`; the fit's own rule:
    :func:`~torchblur.sysid.direct.fit_direct` with ``noise``) and the sweep's mask; dark or
    out-of-frame points are left out. None, logged, if it fails. The direct fit is a least
    squares whatever ``fit.loss`` (the two-step points use it): a warning says so.
    With ``still_psf`` (the calibration's :class:`~torchblur.image.psf_from_still.StillPSF`)
    choosing the measured kernel, the images are fitted with it, and the stds include the
    kernel's own noise (:func:`direct_kernel_noise_factor`). ``latency_std_s`` (s): the latency
    calibration's std, an error every window shares, which the fitted delay absorbs exactly: its
    variance is added to the delay's (:func:`with_common_delay`)."""
    F = images.shape[0]
    t_direct = time.perf_counter()
    if cfg.fit.loss != "l2":
        LOGGER.info(f"direct: warning: fit.loss={cfg.fit.loss} applies to the two-step points only; the direct model "
                    f"(model.direct) is fitted by least squares (l2) weighted by the camera's noise model")
    kernel = still_psf is not None and isinstance(still_psf.psf, KernelPSF)
    if kernel:
        k = still_psf.psf.kernel.to(images.dtype)
        psf_pts = KernelPSF(k.expand((F,) + tuple(k.shape)) * power_t.to(k)[:, None, None])
    else:
        psf_pts = GaussianPSF(psf.center.expand(F, 2), psf.cov.expand(F, 2, 2), psf.amplitude * power_t)
    A_t = torch.tensor(amps, dtype=torch.float64)
    try:
        d = fit_direct(images, psf_pts, windows, omega, A_t, model, form=cfg.model.direct_form, fit_delay=bool(cfg.model.fit_delay),
                       axis=direction,
                       noise=noise, mask=mask,
                       valid=(fit.status != 1) & (fit.status != 3), fit_scale=cfg.fit.fit_scale,
                       fit_background=cfg.fit.fit_background, max_iter=int(cfg.model.direct_max_iter))
    except Exception as exc:  # the two-step model is still a result; say why the direct fit failed
        LOGGER.info(f"direct: fit failed: {exc}")
        return None
    if kernel:
        d = with_kernel_noise(d, direct_kernel_noise_factor(still_psf, windows, power_t, d.used))
    d = with_common_delay(d, latency_std_s)
    modal = d.modal_parameters()
    modes = ", ".join(f"{m['freq_hz']:.3f} +- {m['freq_hz_std']:.3f} Hz (zeta {m['zeta']:.4f} +- {m['zeta_std']:.4f})"
                      for m in modal)
    f_lo, f_hi = float(omega.min()) / (2 * math.pi), float(omega.max()) / (2 * math.pi)
    for m in modes_outside_band(modal, f_lo, f_hi):
        LOGGER.info(f"direct: warning: a mode at {m['freq_hz']:.4g} Hz lies far outside the swept band "
                    f"({f_lo:.4g}-{f_hi:.4g} Hz); the images do not constrain it (std {m['freq_hz_std']:.3g} Hz)")
    poor = (np.asarray(d.flags) & POOR_FIT_FLAG) != 0
    if poor.any():
        hz = ", ".join(f"{v:.4g}" for v in np.asarray(omega, dtype=np.float64)[poor] / (2 * math.pi))
        LOGGER.info(f"direct: warning: the model does not explain {int(poor.sum())} point(s) ({hz} Hz): their reduced "
                    f"chi2 is above {POOR_FIT_CHI2:g}")
    LOGGER.info(f"direct: {d.form} model from {int(d.used.sum())} points ({d.n_excluded} excluded), {d.n_iter} iterations, "
                f"converged {d.converged}, reduced chi2 {d.reduced_chi2:.3f}, {time.perf_counter() - t_direct:.2f} s; "
                f"modes: {modes or 'none'}")
    return d


def direct_kernel_noise_factor(still_psf, windows, power_t, used) -> float:
    """The factor by which the direct model's stds grow from the measured kernel's own noise:
    :meth:`~torchblur.image.psf_from_still.StillPSF.kernel_noise_factor` of one point's light
    (the mean over the used points ``used [F]`` of their exposures ``windows [F, E]`` times their
    laser power ``power_t [F]``), the rule of the sweep's points, whose values the model's
    parameters pool (benchmarks/bench_hcipy_routes.py checks it)."""
    light = (windows.duration.to(torch.float64) * torch.as_tensor(power_t, dtype=torch.float64)[:, None])
    use = torch.as_tensor(np.asarray(used), dtype=torch.bool)
    per_point = light[use].sum(-1).mean() if bool(use.any()) else light.sum(-1).mean()
    return float(still_psf.kernel_noise_factor(per_point[None]))


def with_common_delay(d, std_s: float):
    """The :class:`~torchblur.sysid.direct.DirectModelFit` ``d`` with ``std_s**2`` added to its
    ``delay_s`` variance (a timing error every point shares; unchanged without a fitted delay)."""
    if not std_s or "delay_s" not in d.param_names:
        return d
    k = list(d.param_names).index("delay_s")
    cov = np.array(d.covariance)
    cov[k, k] += float(std_s) ** 2
    return dataclasses.replace(d, covariance=cov, std=np.sqrt(np.clip(np.diag(cov), 0, None)))


def with_kernel_noise(d, factor: float):
    """The :class:`~torchblur.sysid.direct.DirectModelFit` ``d`` with its stds times ``factor`` (covariance times its square)."""
    return dataclasses.replace(d, covariance=d.covariance * factor**2, std=d.std * factor)
