"""The assemble stage's pieces: a :class:`~torchblur.sysid.frequency_response.FrequencyResponse`
with covariances from the fits of the sweep's points (:func:`assemble_siso`,
:func:`assemble_mimo`; the phase std adds the trigger jitter and the latency calibration,
:func:`phase_std`), the true response where the rig knows it (:func:`truth_of`), and each
point's adequacy (:func:`adequacy`, the rule: ``FAILED``, ``POOR_FIT``, ``TIMING``, ``LIMITED``,
``ALIAS`` of :mod:`torchblur.sysid.flags`; :func:`adequacy_stage` applies it to a run). What sets
each flag and what it does: docs/reliability.md, "Per-point flags and the verdict".
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from torchblur.design.windows import MIN_SEPARATION, alias_separation, continuity_branches
from torchblur.errors import ShapeError
from torchblur.image.spots import spot_labels
from torchblur.fit.status import BRANCH_UNDECIDED as FIT_BRANCH_UNDECIDED
from torchblur.fit.status import NO_MOTION as FIT_NO_MOTION
from torchblur.render.window import ExposureWindow
from torchblur.sysid.alias_resolution import model_branches
from torchblur.sysid.flags import ALIAS, FAILED, LIMITED, NO_MOTION, POOR_FIT, TIMING
from torchblur.sysid.frequency_response import FrequencyResponse

__all__ = ["adequacy", "adequacy_stage", "alias_stage", "resolve_single_exposure", "single_exposure_points", "assemble_mimo",
           "assemble_siso", "limited_mask", "mark_limited", "phase_std", "timing_limit_hz", "timing_phase_std", "truth_of"]


def timing_phase_std(omega, jitter_s, latency_std_s, n_frames):
    """Phase std (rad) of the timing alone: ``|omega| sqrt(jitter_s^2 / n_frames + latency_std_s^2)``,
    the trigger jitter per frame averaged over the point's ``n_frames`` and the latency
    calibration's std (both s). Broadcasts ``omega`` (rad/s) against ``n_frames``."""
    return np.abs(np.asarray(omega, dtype=np.float64)) * np.sqrt(jitter_s ** 2 / np.asarray(n_frames, dtype=np.float64)
                                                                  + latency_std_s ** 2)


def timing_limit_hz(tolerance_rad: float, jitter_s: float, latency_std_s: float, n_frames) -> float:
    """The frequency (Hz) above which :func:`timing_phase_std` exceeds ``tolerance_rad``:
    ``tolerance_rad / (2 pi sqrt(jitter_s^2 / n_frames + latency_std_s^2))``; inf when both
    timing terms are 0."""
    s = math.sqrt(jitter_s ** 2 / float(n_frames) + latency_std_s ** 2)
    return math.inf if s == 0 else float(tolerance_rad) / (2 * math.pi * s)


def phase_std(fit_phase_std, omega, camera, latency_std, n_frames):
    """Phase std (rad): the fit, the trigger jitter (per frame, averaged) and the latency calibration."""
    return np.sqrt(fit_phase_std ** 2 + timing_phase_std(omega, camera.jitter_s, latency_std, n_frames) ** 2)


def assemble_siso(fit, amps, omega, camera, latency_std, n_frames, meta):
    """The 1x1 FrequencyResponse of a one-axis, one-spot sweep (fit batch ``[F]``)."""
    A_t = torch.tensor(amps, dtype=torch.float64)
    mag = (fit.amplitude / A_t).numpy()
    phase = fit.phase.numpy()
    mag_std = (fit.amplitude_std / A_t).numpy()
    ph_std = phase_std(fit.phase_std.numpy(), omega.numpy(), camera, latency_std, n_frames)
    i_m, i_p = 0, 1  # (amplitude, phase) of the one fitted axis
    corr = (fit.covariance[:, i_m, i_p] / (fit.amplitude_std * fit.phase_std).clamp_min(1e-300)).numpy()
    F = mag.shape[0]
    cov = np.zeros((F, 2, 2))
    cov[:, 0, 0] = mag_std**2
    cov[:, 1, 1] = ph_std**2
    cov[:, 0, 1] = cov[:, 1, 0] = corr * mag_std * fit.phase_std.numpy()
    response = mag * np.exp(1j * phase)
    bad = ~fit.converged.numpy()
    response[bad] = np.nan
    cov[bad] = np.nan
    return FrequencyResponse(omega.numpy(), response, cov=cov, input_labels=[input_label("x")], output_labels=["x"], meta=meta)


def input_label(name: str) -> str:
    """The response's label of the rig's input ``name``: ``"u_x"`` for the command to axis x,
    distinct from the output ``"x"`` (the spot's motion along x)."""
    return f"u_{name}"


def assemble_mimo(fit, amps, omega_job, camera, latency_std, n_frames, inputs, P, many_spots, meta):
    """The ``[O, I, F]`` FrequencyResponse from a fit of batch ``[I*F, P]`` with ``axes="xy"``:
    outputs x, y (one spot) or ``s{k}.x``, ``s{k}.y`` (K = P spots), with the (magnitude,
    phase) covariance of every channel point."""
    I = len(inputs)
    J = fit.amplitude.shape[0]
    F = J // I
    A_t = torch.tensor(amps, dtype=torch.float64)[:, None, None]  # [J, 1, 1]
    mag = (fit.amplitude / A_t).numpy()  # [J, P, 2]
    phase = fit.phase.numpy()
    mag_std = (fit.amplitude_std / A_t).numpy()
    fit_ph_std = fit.phase_std.numpy()
    om = omega_job.numpy()[:, None, None]
    ph_std = phase_std(fit_ph_std, om, camera, latency_std, n_frames)
    names = fit.param_names
    corr = np.zeros_like(mag)
    for a, ax in enumerate("xy"):
        i_m, i_p = names.index(f"amplitude_{ax}"), names.index(f"phase_{ax}")
        corr[..., a] = (fit.covariance[..., i_m, i_p] / (fit.amplitude_std[..., a] * fit.phase_std[..., a]).clamp_min(1e-300)).numpy()
    cov = np.zeros(mag.shape + (2, 2))
    cov[..., 0, 0] = mag_std**2
    cov[..., 1, 1] = ph_std**2
    cov[..., 0, 1] = cov[..., 1, 0] = corr * mag_std * fit_ph_std
    response = mag * np.exp(1j * phase)
    bad = ~fit.converged.numpy()  # [J, P]
    response[bad] = np.nan
    cov[bad] = np.nan

    def arrange(x):  # [I*F, P, 2, ...] -> [P*2, I, F, ...]
        x = x.reshape((I, F, P, 2) + x.shape[3:])
        x = np.moveaxis(np.moveaxis(x, 2, 0), 3, 1)  # [P, 2, I, F, ...]
        return x.reshape((P * 2, I, F) + x.shape[4:])

    outputs = spot_labels(P) if many_spots else ["x", "y"]
    return FrequencyResponse(omega_job.numpy()[:F], arrange(response), cov=arrange(cov), input_labels=[input_label(n) for n in inputs],
                             output_labels=outputs, meta=meta)


def truth_of(rig, freqs, frf, spots, single):
    """The true response where the rig knows it (simulated rigs): ``[F]`` for a one-spot SISO
    run, else ``[O, I, F]`` in the FRF's channel order (spots matched to the rig's layout by
    their rest position; NaN where none is within 3 px)."""
    if not hasattr(rig, "truth"):
        return None
    if single:
        return np.asarray([rig.truth(float(f)) for f in freqs])
    if spots is None:
        return np.asarray(rig.truth(np.asarray(freqs, dtype=np.float64)))
    if not hasattr(rig, "spot_truth") or getattr(rig, "spots", None) is None:
        return None
    t = np.asarray(rig.spot_truth(np.asarray(freqs, dtype=np.float64)))  # [Kt, 2, I, F]
    rest = rig.spots.rest_px.numpy()
    out = np.full((len(spots), 2) + t.shape[2:], np.nan + 0j)
    for k, cxy in enumerate(spots.psf.center.numpy()):
        d = np.hypot(*(rest - cxy).T)
        if d.min() < 3.0:
            out[k] = t[int(d.argmin())]
    return out.reshape((-1,) + t.shape[2:])


def limited_mask(limited, shape) -> np.ndarray:
    """A per-point ``limited`` (bool ``[F]``, per job ``[I*F]``, or ``[O, I, F]``; None = none)
    as bool ``[O, I, F]`` = ``shape`` (a job's flag holds for every output it drives)."""
    n_o, n_i, n_f = shape
    if limited is None:
        return np.zeros(shape, dtype=bool)
    a = np.asarray(limited.numpy() if isinstance(limited, torch.Tensor) else limited).astype(bool)
    if a.shape == (n_f,):
        a = np.broadcast_to(a, shape)
    elif a.shape == (n_i * n_f,):
        a = np.broadcast_to(a.reshape(1, n_i, n_f), shape)
    elif a.shape != tuple(shape):
        raise ShapeError(f"limited: expected shape [F], [I*F] or [O, I, F] with O, I, F = {tuple(shape)}, got {a.shape}")
    return np.array(a)


def mark_limited(frf: FrequencyResponse, limited) -> FrequencyResponse:
    """``frf`` with ``LIMITED`` OR-ed into the flags where ``limited`` (:func:`limited_mask`)."""
    if limited is None:
        return frf
    return frf.replace(flags=frf.flags | np.where(limited_mask(limited, frf.response.shape), LIMITED, 0))


def adequacy(frf: FrequencyResponse, *, reduced_chi2, poor_fit_chi2: float, timing_std, tolerance_rad: float,
             limited=None) -> FrequencyResponse:
    """``frf`` with each point's flags, its reduced chi2 and, where POOR_FIT, its covariance
    inflated (the rule in the module docstring).

    Args:
        frf: the assembled response, [O, I, F]; its phase variance holds ``timing_std**2``.
        reduced_chi2: [O, I, F] (or [F]) reduced chi2 of each point's image fit, NaN unknown
            (an unknown one never flags).
        poor_fit_chi2: the threshold (> 0; ``fit.poor_fit_chi2``).
        timing_std: [F] or [O, I, F] phase std (rad) of the timing terms alone
            (:func:`timing_phase_std`).
        tolerance_rad: phase tolerance (rad; ``report.tolerance_deg``).
        limited: see :func:`limited_mask`.

    Returns:
        A new FrequencyResponse; flags already set on ``frf`` are kept (OR-ed).
    """
    shape = frf.response.shape
    chi2 = np.broadcast_to(np.asarray(reduced_chi2, dtype=np.float64), shape)
    t_var = np.broadcast_to(np.asarray(timing_std, dtype=np.float64), shape) ** 2
    with np.errstate(invalid="ignore"):
        poor = np.isfinite(chi2) & (chi2 > poor_fit_chi2)
    flags = np.array(frf.flags)
    flags[~frf.valid] |= FAILED
    flags[poor] |= POOR_FIT
    flags[t_var > tolerance_rad ** 2] |= TIMING
    cov = np.array(frf.cov)
    inflate = poor & frf.valid
    fit_part = cov[inflate]  # [n, 2, 2]; the timing terms add to the phase variance only
    fit_part[:, 1, 1] = np.maximum(fit_part[:, 1, 1] - t_var[inflate], 0.0)
    fit_part *= chi2[inflate][:, None, None]
    fit_part[:, 1, 1] += t_var[inflate]
    cov[inflate] = fit_part
    return mark_limited(frf.replace(cov=cov, flags=flags, reduced_chi2=np.where(np.isfinite(chi2), chi2, np.nan)), limited)


def _per_point(run, r) -> np.ndarray:
    """A sine sweep's per-problem values ``r`` ([F], or [I*F, P]) on ``run.frf``'s points
    [O, I, F] (one spot's x and y outputs share their problem's value)."""
    n_o, n_i, n_f = run.frf.response.shape
    if r.ndim == 1:  # [F]: one axis, one spot
        return np.broadcast_to(r, (n_o, n_i, n_f)).copy()
    P = r.shape[1]  # [I*F, P] -> [P, I, F]
    per = np.moveaxis(r.reshape(n_i, n_f, P), 2, 0)
    return np.repeat(per, n_o // P, axis=0)


def point_reduced_chi2(run) -> np.ndarray:
    """[O, I, F] reduced chi2 of the image fit behind each point of ``run.frf`` (NaN unknown):
    a sine sweep's per-problem values (one spot's x and y outputs share their problem's), a
    multisine group's value for each of its tones."""
    out = np.full(run.frf.response.shape, np.nan)
    fits = run.fit
    if isinstance(fits, (list, tuple)):  # multisine: one fit per group, its tones at the group's "order"
        for fit, info in zip(fits, run.acquisition.groups):
            r = getattr(fit, "extras", {}).get("reduced_chi2")
            if r is not None:
                out[..., info["order"]] = float(np.asarray(r, dtype=np.float64).reshape(-1)[0])
        return out
    r = getattr(fits, "reduced_chi2", None)
    return out if r is None else _per_point(run, np.asarray(r, dtype=np.float64))


def point_no_motion(run) -> np.ndarray:
    """[O, I, F] bool: the sine sweep's image fit behind the point found no significant motion
    (its :data:`~torchblur.fit.status.NO_MOTION` flag on any fitted axis); False where unknown."""
    return point_fit_flag(run, FIT_NO_MOTION)


def point_fit_flag(run, bit: int) -> np.ndarray:
    """[O, I, F] bool: the sine sweep's image fit behind the point carries the fit flag ``bit``
    (:data:`torchblur.fit.status.FLAGS`); False where unknown (a multisine run)."""
    flags = getattr(run.fit, "flags", None) if not isinstance(run.fit, (list, tuple)) else None
    if flags is None:
        return np.zeros(run.frf.response.shape, dtype=bool)
    hit = (np.asarray(flags) & bit) != 0  # the fit batch: [F], or [I*F, P]
    return _per_point(run, hit)


def frames_per_point(run) -> np.ndarray:
    """[F] frames each point's phase averages the trigger jitter over: a sine point's
    exposures x images, a multisine tone's group's images."""
    n_f = len(run.frf.omega)
    if isinstance(run.fit, (list, tuple)):
        n = np.ones(n_f)
        for info in run.acquisition.groups:
            n[info["order"]] = info["images"].stop - info["images"].start
        return n
    return np.full(n_f, float(run.windows.start.shape[-1]))


def gain_meta(cal) -> dict:
    """The frequency response's ``camera_gain`` entry: the gain the run used (e-/ADU), where it came
    from (``camera.gain`` or ``photon transfer``) and, where measured, the photon transfer's gain, read
    noise (e-), dark level (ADU) and linear range (ADU above dark) with their stds."""
    out = {"e_per_adu": float(cal.gain), "source": getattr(cal, "gain_source", "camera.gain")}
    p = getattr(cal, "ptc", None)
    if p is not None:
        out["photon_transfer"] = {"gain_e_per_adu": p.gain_e_per_adu, "gain_std": p.gain_std, "read_noise_e": p.read_noise_e,
                                  "read_noise_std_e": p.read_noise_std_e, "dark_level_adu": p.dark_level_adu,
                                  "linear_max_adu": p.linear_max_adu, "reduced_chi2": p.reduced_chi2}
    return out


def adequacy_stage(run) -> None:
    """The stage after assemble: ``run.frf`` with each point's flags, reduced chi2 and inflated
    covariance (:func:`adequacy`, with ``fit.poor_fit_chi2``, ``report.tolerance_deg``, the
    camera's jitter, the latency calibration's std and the run's ``limited`` where it has one),
    its meta's ``timing`` entry (``jitter_s``, ``latency_std_s``, ``frames_per_point``: the
    fewest), ``latency_source`` (scanned or given), ``camera_gain`` (:func:`gain_meta`) and ``adequacy`` entry (the two thresholds) for the verdict; a log line when points
    are flagged."""
    cfg, frf = run.cfg, run.frf
    n = frames_per_point(run)
    jitter, lat = float(cfg.camera.jitter_s), float(run.cal.latency_std_s)
    limited = getattr(run, "limited", None)
    if limited is None:
        limited = getattr(getattr(run, "acquisition", None), "limited", None)
    meta = {**frf.meta, "timing": {"jitter_s": jitter, "latency_std_s": lat, "frames_per_point": int(n.min())},
            "latency_source": getattr(run.cal, "latency_source", "scanned"),
            "camera_gain": gain_meta(run.cal),
            "adequacy": {"poor_fit_chi2": float(cfg.fit.poor_fit_chi2), "tolerance_deg": float(cfg.report.tolerance_deg),
                         "tolerance_rel": float(cfg.report.tolerance_rel)}}
    run.frf = adequacy(frf.replace(meta=meta), reduced_chi2=point_reduced_chi2(run), poor_fit_chi2=float(cfg.fit.poor_fit_chi2),
                       timing_std=timing_phase_std(frf.omega, jitter, lat, n),
                       tolerance_rad=math.radians(float(cfg.report.tolerance_deg)), limited=limited)
    no_motion = point_no_motion(run)
    if no_motion.any():
        run.frf = run.frf.replace(flags=np.asarray(run.frf.flags) | np.where(no_motion, NO_MOTION, 0))
    undecided = point_fit_flag(run, FIT_BRANCH_UNDECIDED) & run.frf.valid & ((run.frf.flags & NO_MOTION) == 0)
    if undecided.any():  # two exposures, too little light to decide the phase branch: as undecided as one exposure's
        run.frf = run.frf.replace(flags=np.asarray(run.frf.flags) | np.where(undecided, ALIAS, 0))
        run.say(f"alias: {int(undecided.sum())} point(s) whose exposures did not decide the phase branch at their light (the "
                f"alias's chi2 within 4 of the fit's) flagged alias ({', '.join(f'{v:.4g}' for v in frf.freq_hz[undecided.any(axis=(0, 1))])} Hz)")
    alias_stage(run)
    poor = int(((run.frf.flags & POOR_FIT) != 0).sum())
    if poor:
        run.say(f"adequacy: {poor} point(s) with a reduced chi2 above fit.poor_fit_chi2 = {cfg.fit.poor_fit_chi2}: flagged "
                f"poor_fit, their stds multiplied by sqrt(reduced chi2)")


def resolve_single_exposure(frf: FrequencyResponse, alias_phase, single, *, axis_of=None, anchor_phase: float = 0.0) -> FrequencyResponse:
    """``frf`` with the phase branch of every single-exposure point chosen by continuity along
    the sweep (:func:`~torchblur.design.windows.continuity_branches`, with the magnitude's Bode
    term), the points it leaves undecided then by a model of the decided points and their
    magnitudes (:func:`~torchblur.sysid.alias_resolution.model_branches`), and ``ALIAS`` on the
    points neither decides.

    Args:
        frf: ``[O, I, F]`` response as the fits gave it.
        alias_phase: ``[O, I, F]`` the other branch of each point (rad; ``SinusoidFit.alias_phase``).
        single: bool ``[O, I, F]`` (or ``[F]``): the point's exposures do not resolve the alias.
        axis_of: None (every channel chooses alone), or int ``[O]`` or ``[O, I]``: the output
            whose channel decides for output ``o`` (from input ``i``): one spot's x and y outputs
            come from one fit, whose time reversal flips both, so the axis that moves most decides
            and the other follows.
        anchor_phase: the phase expected at the lowest frequency (rad; 0: a positive DC gain).

    Returns:
        A new FrequencyResponse: where the alias is taken the phase is the alias and the
        magnitude-phase covariance changes sign (the alias moves opposite to the phase).
    """
    shape = frf.response.shape
    al = np.broadcast_to(np.asarray(alias_phase, dtype=np.float64), shape)
    one = np.broadcast_to(np.asarray(single, dtype=bool), shape)
    if not one.any():
        return frf
    lead = np.arange(shape[0]) if axis_of is None else np.asarray(axis_of, dtype=int)
    lead = np.broadcast_to(lead.reshape(shape[0], -1), shape[:2])  # [O, I]: the output deciding for (o, i)
    ok = frf.valid & np.isfinite(al) & ((frf.flags & NO_MOTION) == 0)
    take = np.zeros(shape, dtype=bool)
    undecided = np.zeros(shape, dtype=bool)
    for i in range(shape[1]):
        for o in np.unique(lead[:, i]):
            other = np.where(one[o, i], al[o, i], frf.phase[o, i])  # a resolved point: one branch
            r = continuity_branches(frf.omega, frf.phase[o, i], other, frf.phase_std[o, i], magnitude=frf.magnitude[o, i],
                                    valid=ok[o, i], anchor_phase=anchor_phase)
            took, und = _with_model(frf, o, i, r.took_alias & ok[o, i], ~r.decided & ok[o, i], other, ok[o, i])
            for oo in np.flatnonzero(lead[:, i] == o):
                take[oo, i] = took & one[oo, i] & ok[oo, i]
                undecided[oo, i] = (und | ~ok[o, i]) & one[oo, i] & ok[oo, i]  # a lead point not judged: its follower neither
    return frf.with_branch(take, al).replace(flags=np.asarray(frf.flags) | np.where(undecided, ALIAS, 0))


def _with_model(frf, o: int, i: int, took, undecided, other, ok):
    """``(took, undecided)`` bool ``[F]`` of channel (o, i) after the model step of the rule
    (:func:`~torchblur.sysid.alias_resolution.model_branches`) on its points ``ok``, each on the
    branch continuity chose (``took``: ``other``, the second candidate)."""
    if not undecided.any():
        return took, undecided
    ch = FrequencyResponse(frf.omega, np.where(ok, frf.response[o, i], np.nan), cov=frf.cov[o, i]).with_branch(took, other)
    new, und = model_branches(ch, np.where(took, frf.phase[o, i], other), undecided)
    flipped = np.abs(np.angle(new.response[0, 0] * np.conj(ch.response[0, 0]))) > 1e-12
    return took ^ (flipped & ok), und


def single_exposure_points(run) -> np.ndarray:
    """bool ``[J]`` per job of a sine run (``run.windows``, ``run.acquisition.omega_job``): its
    exposures do not resolve the alias (:func:`~torchblur.design.windows.alias_separation` below
    :data:`~torchblur.design.windows.MIN_SEPARATION`: one exposure, or centres that coincide mod
    half a period)."""
    w, om = run.windows, run.acquisition.omega_job
    flat = ExposureWindow(w.start.reshape(-1, w.start.shape[-1]), w.duration.reshape(-1, w.duration.shape[-1]))
    return (alias_separation(om, flat) < MIN_SEPARATION).numpy()


def alias_stage(run) -> None:
    """The step of the adequacy stage for a sine run with one exposure per point: the branch of
    every such point by continuity (:func:`resolve_single_exposure`; one spot's two axes follow
    the axis that moves most) and a log line naming the points flagged ``alias``. Nothing for a
    multisine run (its fit is a list) or where every point's exposures resolve the alias."""
    fit = run.fit
    if isinstance(fit, (list, tuple)) or getattr(fit, "alias_phase", None) is None:
        return
    single = single_exposure_points(run)
    if not single.any():
        return
    frf = run.frf
    alias = fit.alias_phase.detach().to(torch.float64).numpy()
    if alias.ndim == 1:  # [F]: one axis, one spot
        alias_oif, single_oif, axis_of = alias[None, None], single[None, None], None
    else:  # [I*F, P, 2] -> [P*2, I, F], one spot's outputs 2p and 2p + 1
        n_o, n_i, n_f = frf.response.shape
        alias_oif = np.moveaxis(alias.reshape(n_i, n_f, -1), 2, 0)
        single_oif = np.broadcast_to(single.reshape(1, n_i, n_f), frf.response.shape)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a spot with no valid point: NaN, its x decides
            mean_mag = np.nanmean(np.where(frf.valid, frf.magnitude, np.nan), axis=2)  # [O, I]
        moves = np.nan_to_num(mean_mag, nan=-1.0).reshape(n_o // 2, 2, n_i)  # [P, axis, I]
        axis_of = np.repeat(2 * np.arange(n_o // 2)[:, None] + moves.argmax(1), 2, axis=0)  # [O, I]
    run.frf = resolve_single_exposure(frf, alias_oif, single_oif, axis_of=axis_of)
    n_alias = int(((run.frf.flags & ALIAS) != 0).sum())
    run.say(f"alias: {int(single.sum())} point(s) with one exposure (their exposures do not resolve the alias): the phase branch "
            f"chosen by continuity along the sweep, then by a model of the decided points and the magnitudes; {n_alias} point(s) "
            f"neither decides flagged alias" + (
                f" ({', '.join(f'{v:.4g}' for v in frf.freq_hz[((run.frf.flags & ALIAS) != 0).any(axis=(0, 1))])} Hz)" if n_alias else ""))
