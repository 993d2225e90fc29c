"""Whether a DM sweep's spot fits keep up with its camera (issue 23).

A sweep fits frequency ``k`` on one worker while frequency ``k + 1`` is acquired, and acquires
frequency ``k`` only once the fit of ``k - lag`` is done (its amplitude comes from that fit:
:data:`~torchblur.identify.dm_plan.AMPLITUDE_LAG`). :func:`sweep_schedule` replays that schedule with
measured fit times and the camera's acquisition time per frequency: the wait after the last frame and
the camera's idle time waiting for fits.
A live run measures its own wait (report.txt's "waiting for the fits"); a re-fit reads its frames at
once, so :func:`pace_line` says what its fits would cost a live sweep at the camera's frame rate (the
rig's ``frame_rate_hz``, the recorded camera's on a re-fit). An outside recording does not give its
camera's frame rate: its line gives the fit times and says that the pace is not judged. Times in s.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["sweep_schedule", "pace_line", "pace_summary"]


def sweep_schedule(fit_s, acquire_s, lag: int) -> tuple[float, float]:
    """``(wait, idle)``: the seconds from a sweep's last frame to the end of its last spot fit, and the
    seconds its camera stood idle waiting for fits (the sweep's time beyond its frames' own).

    Args:
        fit_s: ``[F]`` each frequency's spot-fit seconds on the one worker.
        acquire_s: ``[F]`` (or a number) each frequency's acquisition seconds.
        lag: frequency ``k`` is acquired once the fit of ``k - lag`` is done (>= 1).

    Fits slower than the frames do not make the wait grow without bound: the sweep waits for them
    (``idle``), and the wait stays within about ``lag`` fits. NaN for both when a fit time is not
    finite (a failed task).
    """
    fit = np.asarray(fit_s, dtype=np.float64).reshape(-1)
    acq = np.broadcast_to(np.asarray(acquire_s, dtype=np.float64), fit.shape)
    if not np.isfinite(fit).all():
        return math.nan, math.nan
    acq_end = fit_end = 0.0
    ends = []
    for k in range(fit.size):
        start = acq_end if k < lag else max(acq_end, ends[k - lag])
        acq_end = start + float(acq[k])
        fit_end = max(fit_end, acq_end) + float(fit[k])
        ends.append(fit_end)
    return fit_end - acq_end, acq_end - float(acq.sum())


def pace_summary(fit_s, frames_per_frequency: int, frame_rate_hz: float | None, lag: int) -> dict | None:
    """``{fit_median_s, fit_max_s, frames_per_frequency, frame_rate_hz, acquire_s, ratio, wait_s, idle_s,
    keeps_up}`` of a sweep's spot fits against ``frames_per_frequency`` frames per frequency at
    ``frame_rate_hz`` (the camera's, not the simulator's pace; :func:`sweep_schedule`); ``keeps_up``:
    every fit within its frames' time. Without a frame rate (None: an outside recording's camera)
    the fit times only, the rest None. None without fit times."""
    fit = np.asarray(fit_s, dtype=np.float64).reshape(-1) if fit_s is not None else np.zeros(0)
    ok = fit[np.isfinite(fit)]
    if not ok.size:
        return None
    med = float(np.median(ok))
    out = {"fit_median_s": med, "fit_max_s": float(ok.max()), "frames_per_frequency": int(frames_per_frequency),
           "frame_rate_hz": None, "acquire_s": None, "ratio": None, "wait_s": None, "idle_s": None, "keeps_up": None}
    if frame_rate_hz is None or not frame_rate_hz > 0:
        return out
    acq = frames_per_frequency / float(frame_rate_hz)
    wait, idle = sweep_schedule(fit, acq, lag)
    out.update(frame_rate_hz=float(frame_rate_hz), acquire_s=acq, ratio=med / acq, wait_s=wait, idle_s=idle,
               keeps_up=bool(np.isfinite(wait) and ok.max() <= acq))
    return out


def pace_line(pace: dict | None) -> str | None:
    """report.txt's line of :func:`pace_summary` (None without it)."""
    if pace is None:
        return None
    if pace["frame_rate_hz"] is None:
        return (f"dm fit pace: the spot fits took {pace['fit_median_s']:.1f} s per frequency (median; largest {pace['fit_max_s']:.1f} s) on "
                f"one worker ({pace['frames_per_frequency']} frames per frequency); the recording does not give its camera's frame rate, "
                f"so whether a live sweep at this pace keeps up is not judged")
    verb = "keeps up" if pace["keeps_up"] else "does not keep up"
    return (f"dm fit pace: the spot fits took {pace['fit_median_s']:.1f} s per frequency (median; largest {pace['fit_max_s']:.1f} s) on "
            f"one worker, against {pace['acquire_s']:.1f} s of frames per frequency at the camera's {pace['frame_rate_hz']:g} Hz "
            f"({pace['frames_per_frequency']} frames): the fitting {verb} (fit/acquisition {pace['ratio']:.2f}); a live sweep at this pace "
            f"would wait {pace['wait_s']:.1f} s after its last frame, its camera idle {pace['idle_s']:.1f} s before it waiting for fits")
