"""Test helper: write an outside recording (docs/outside_recordings.md) from frames in memory,
as a lab's own tools would: one TIFF stack per kind, frames.csv, recording.yaml."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import tifffile
import yaml

__all__ = ["write_outside"]


def write_outside(folder, *, dark, still, still_exposure_s: float, points: list, camera: dict, dtype=None,
                  trigger_phase: bool = False) -> Path:
    """Write ``folder`` (created) and return it.

    Args:
        dark: ``[Nd, H, W]`` frames (ADU); still: ``[Ns, H, W]``.
        points: dicts with ``freq_hz``, ``amplitude``, ``frames`` ``[E*R, H, W]`` (exposure-major),
            ``start_s`` and ``duration_s`` ``[E*R]``, optional ``power`` and ``R``.
        camera: recording.yaml's keys.
        dtype: the TIFFs' dtype (default: the frames').
        trigger_phase: write ``trigger_phase_rad`` (from ``start_s`` and the camera's
            ``trigger_delay_s + latency_s``) instead of ``window_start_s``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cast = (lambda a: np.asarray(a)) if dtype is None else (lambda a: np.asarray(a).astype(dtype))
    gray = dict(photometric="minisblack")  # a stack of 3 or 4 frames is not a colour image
    tifffile.imwrite(folder / "dark.tif", cast(dark), **gray)
    tifffile.imwrite(folder / "still.tif", cast(still), **gray)
    sweep = np.concatenate([np.asarray(p["frames"]) for p in points])
    tifffile.imwrite(folder / "sweep.tif", cast(sweep), **gray)
    delay = float(camera.get("trigger_delay_s", 0.0)) + float(camera.get("latency_s", 0.0))
    head = ["file", "page", "kind", "freq_hz", "exposure_s", "trigger_phase_rad" if trigger_phase else "window_start_s",
            "amplitude", "power", "repeat"]
    rows = [["dark.tif", i, "dark", "", "", "", "", "", ""] for i in range(len(dark))]
    rows += [["still.tif", i, "still", "", repr(float(still_exposure_s)), "", "", "", ""] for i in range(len(still))]
    page = 0
    for p in points:
        R = int(p.get("R", 1))
        for j in range(len(p["frames"])):
            start = float(p["start_s"][j])
            when = 2 * np.pi * p["freq_hz"] * (start - delay) if trigger_phase else start
            rows.append(["sweep.tif", page, "sweep", repr(float(p["freq_hz"])), repr(float(p["duration_s"][j])), repr(float(when)),
                         repr(float(p["amplitude"])), repr(float(p.get("power", 1.0))), j % R])
            page += 1
    with open(folder / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        w.writerows(rows)
    (folder / "recording.yaml").write_text(yaml.safe_dump({k: float(v) if not isinstance(v, str) else v for k, v in camera.items()}))
    return folder
