"""The assemble stage's pieces: a :class:`~torchblur.sysid.frequency_response.FrequencyResponse`
with covariances from the fits of the sweep's points (:func:`assemble_siso`,
:func:`assemble_mimo`; the phase std adds the trigger jitter and the latency calibration,
:func:`phase_std`), and the true response where the rig knows it (:func:`truth_of`)."""
from __future__ import annotations

import numpy as np
import torch

from torchblur.image.spots import spot_labels
from torchblur.sysid.frequency_response import FrequencyResponse

__all__ = ["assemble_mimo", "assemble_siso", "phase_std", "truth_of"]


def phase_std(fit_phase_std, omega, camera, latency_std, n_frames):
    """Phase std (rad): the fit, the trigger jitter (per frame, averaged) and the latency calibration."""
    return np.sqrt(fit_phase_std ** 2 + (omega * camera.jitter_s) ** 2 / n_frames + (omega * latency_std) ** 2)


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
    return FrequencyResponse(omega.numpy(), response, cov=cov, input_labels=["x"], output_labels=["x"], meta=meta)


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
    return FrequencyResponse(omega_job.numpy()[:F], arrange(response), cov=arrange(cov), input_labels=list(inputs),
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
