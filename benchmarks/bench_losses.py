"""The camera's noise (issue 15): do the poisson and l1 losses agree with l2 on the same images?

One default simulated run (``torchblur identify``), then ``torchblur fit`` re-fits its
recording with ``fit.loss=poisson`` and ``fit.loss=l1`` (same frames, same calibration). For
each loss, at every point of the response: ``|H|`` and phase against the l2 fit in units of
the l2 std (``max |diff| / std``), the ratio of the loss's reported std to l2's (median, min,
max over the points; expected ~1 for poisson, the Fisher-efficient estimator, and
``sqrt(pi / 2) = 1.25`` for l1, the least-absolute-deviations estimator under Gaussian noise),
the points that are not finite, the exit status, and the model's modes.

    python benchmarks/bench_losses.py [--out DIR] [overrides ...]

Goal: every point within 4 l2 std, no NaN, std ratios ~1 (poisson) and ~1.25 (l1).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchblur import cli  # noqa: E402
from torchblur.sysid.frequency_response import FrequencyResponse  # noqa: E402


def _modes(run: Path) -> str:
    """The model's modes (Hz) from ``model.json``'s text, or '?'."""
    try:
        report = (run / "report.txt").read_text()
    except OSError:
        return "?"
    return "; ".join(line.strip() for line in report.splitlines() if line.strip().startswith("mode:")) or "(no resonant mode)"


def _compare(ref: FrequencyResponse, other: FrequencyResponse) -> dict:
    """``|H|`` and phase of ``other`` against ``ref`` (one channel) in units of ``ref``'s std."""
    h0, h1 = ref.response.reshape(-1), other.response.reshape(-1)
    c0, c1 = ref.cov.reshape(-1, 2, 2), other.cov.reshape(-1, 2, 2)
    s0 = np.sqrt(np.stack([c0[:, 0, 0], c0[:, 1, 1]], -1))
    s1 = np.sqrt(np.stack([c1[:, 0, 0], c1[:, 1, 1]], -1))
    d_mag = np.abs(h1) - np.abs(h0)
    d_ph = np.angle(h1 * np.conj(h0))
    z = np.abs(np.stack([d_mag, d_ph], -1)) / s0
    ratio = s1 / s0
    finite = np.isfinite(h1) & np.isfinite(s1).all(-1)
    return dict(z_mag=float(np.nanmax(z[:, 0])), z_phase=float(np.nanmax(z[:, 1])),
                mag_pct=float(np.nanmax(np.abs(d_mag / np.abs(h0)))) * 100, phase_deg=float(np.nanmax(np.abs(np.degrees(d_ph)))),
                ratio_mag=(float(np.nanmedian(ratio[:, 0])), float(np.nanmin(ratio[:, 0])), float(np.nanmax(ratio[:, 0]))),
                ratio_phase=(float(np.nanmedian(ratio[:, 1])), float(np.nanmin(ratio[:, 1])), float(np.nanmax(ratio[:, 1]))),
                not_finite=int((~finite).sum()), points=int(h1.size))


def _quiet(argv) -> int:
    """``torchblur argv`` with its report (stdout) swallowed."""
    with contextlib.redirect_stdout(io.StringIO()):
        return cli.main(argv)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="folder for the runs (default: a temporary one)")
    ap.add_argument("--losses", nargs="*", default=["poisson", "l1"])
    ap.add_argument("--run", default=None, help="re-fit this l2 run instead of making one")
    ap.add_argument("overrides", nargs="*", help="config overrides of the identify run, e.g. seed=3")
    args = ap.parse_args(argv)
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_losses_"))
    run = Path(args.run) if args.run else base / "l2"
    if not args.run:
        rc = _quiet(["identify", "--out", str(run), "--quiet", *args.overrides])
        print(f"identify (l2): exit {rc}; {_modes(run)}")
    ref = FrequencyResponse.from_json(run / "frf.json")
    worst = 0.0
    for loss in args.losses:
        out = base / loss
        rc = _quiet(["fit", str(run), "--out", str(out), "--quiet", f"fit.loss={loss}"])
        if rc != 0 or not (out / "frf.json").exists():
            print(f"fit.loss={loss}: exit {rc}, no response")
            continue
        c = _compare(ref, FrequencyResponse.from_json(out / "frf.json"))
        worst = max(worst, c["z_mag"], c["z_phase"])
        print(f"fit.loss={loss}: exit {rc}; {c['points'] - c['not_finite']}/{c['points']} points finite; "
              f"max |diff|/std(l2): |H| {c['z_mag']:.2f}, phase {c['z_phase']:.2f} "
              f"(max |H| diff {c['mag_pct']:.3f} %, phase {c['phase_deg']:.3f} deg); "
              f"std ratio to l2 (median [min, max]): |H| {c['ratio_mag'][0]:.3f} [{c['ratio_mag'][1]:.3f}, {c['ratio_mag'][2]:.3f}], "
              f"phase {c['ratio_phase'][0]:.3f} [{c['ratio_phase'][1]:.3f}, {c['ratio_phase'][2]:.3f}]; {_modes(out)}")
    print(json.dumps({"worst_z": worst, "folder": str(base)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
