"""A camera whose gain is not the config's (issue 28): the photon transfer curve recovers it, and
identify's stds hold with it where the configured gain alone made them wrong.

The simulated rig's camera has ``--true-gain`` e-/ADU (default 2.0); the config says
``camera.gain=--config-gain`` (default 4.0, a datasheet value for another gain setting). Three runs of
``torchblur identify`` (default mirror, ``sweep.n`` points) per seed:

- ``config``: ``camera.gain_from=config`` (the configured gain used, as before issue 28): the stds
  assume twice the electrons per ADU, so they are expected to be ``sqrt(config / true)`` = 1.41 times
  too small where shot noise dominates (rms error/std about 1.41);
- ``measured``: ``camera.gain_from=auto camera.ptc_frames=N`` (a ladder of 8 exposures of N still
  frames for the photon transfer curve; the measured gain used);
- ``truth``: ``camera.gain`` set to the true gain (the reference).

Printed per run: the gain used and, for the measured run, the photon transfer's gain and read noise
against the truth (goal: within 1 % and 5 %); the rms over the points of (|H| error / |H| std) and
(phase error / phase std) (goal: 0.8-1.3 with the measured gain).

    python benchmarks/bench_gain.py [--seeds 0 1] [--ptc-frames 160] [--n 30]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchblur.config import load_config  # noqa: E402
from torchblur.identify.run import identify  # noqa: E402
from torchblur.rig.factory import build_simulated_rig  # noqa: E402


def _rms_z(res, rig) -> tuple[float, float, int]:
    """rms of |H| error / std and phase error / std over the finite points, and their number."""
    f = res.frf.omega / (2 * np.pi)
    em, ep, _ = res.frf.errors_against(rig.truth(f))
    zm = (em * np.abs(rig.truth(f)) / res.frf.magnitude_std).reshape(-1)
    zp = (ep / res.frf.phase_std).reshape(-1)
    ok = np.isfinite(zm) & np.isfinite(zp)
    return float(np.sqrt(np.mean(zm[ok] ** 2))), float(np.sqrt(np.mean(zp[ok] ** 2))), int(ok.sum())


def run(seed: int, true_gain: float, config_gain: float, ptc_frames: int, n: int) -> list[dict]:
    base = [f"seed={seed}", f"sweep.n={n}", "fit.axis=x"]
    rig_cfg = load_config(None, base + [f"camera.gain={true_gain}"])
    rows = []
    for name, keys in (("config", [f"camera.gain={config_gain}", "camera.gain_from=config"]),
                       ("measured", [f"camera.gain={config_gain}", "camera.gain_from=auto", f"camera.ptc_frames={ptc_frames}"]),
                       ("truth", [f"camera.gain={true_gain}", "camera.gain_from=config"])):
        cfg = load_config(None, base + keys)
        rig = build_simulated_rig(rig_cfg)  # the camera's true gain
        t0 = time.perf_counter()
        res = identify(cfg, rig=rig, progress=False)
        zm, zp, k = _rms_z(res, rig)
        g = res.frf.meta["camera_gain"]
        p = g.get("photon_transfer") or {}
        rows.append({"seed": seed, "run": name, "gain_used": g["e_per_adu"], "source": g["source"], "ptc_gain": p.get("gain_e_per_adu"),
                     "ptc_gain_std": p.get("gain_std"), "ptc_read_noise": p.get("read_noise_e"), "rms_z_mag": zm, "rms_z_phase": zp,
                     "points": k, "s": time.perf_counter() - t0})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--true-gain", type=float, default=2.0)
    ap.add_argument("--config-gain", type=float, default=4.0)
    ap.add_argument("--ptc-frames", type=int, default=160)
    ap.add_argument("--n", type=int, default=30)
    a = ap.parse_args(argv)
    import torch

    print(f"true gain {a.true_gain} e-/ADU, configured {a.config_gain} e-/ADU (expected rms error/std with it: up to "
          f"sqrt({a.config_gain}/{a.true_gain}) = {math.sqrt(a.config_gain / a.true_gain):.3f}); read noise 5 e-; "
          f"{a.n} points; torch threads {torch.get_num_threads()}")
    rows = [r for s in a.seeds for r in run(s, a.true_gain, a.config_gain, a.ptc_frames, a.n)]
    print(f"{'seed':>4} {'run':>8} {'gain used':>10} {'from':>16} {'ptc gain':>16} {'gain err':>9} {'read noise':>10} {'rn err':>7} "
          f"{'rms z|H|':>9} {'rms zphi':>9} {'pts':>4} {'s':>6}")
    for r in rows:
        pg = "" if r["ptc_gain"] is None else f"{r['ptc_gain']:.4f}+-{r['ptc_gain_std']:.4f}"
        ge = "" if r["ptc_gain"] is None else f"{(r['ptc_gain'] / a.true_gain - 1) * 100:+.2f}%"
        rn = "" if r["ptc_read_noise"] is None else f"{r['ptc_read_noise']:.3f}"
        re_ = "" if r["ptc_read_noise"] is None else f"{(r['ptc_read_noise'] / 5.0 - 1) * 100:+.2f}%"
        print(f"{r['seed']:>4} {r['run']:>8} {r['gain_used']:>10.4f} {r['source']:>16} {pg:>16} {ge:>9} {rn:>10} {re_:>7} "
              f"{r['rms_z_mag']:>9.3f} {r['rms_z_phase']:>9.3f} {r['points']:>4} {r['s']:>6.1f}")
    for name in ("config", "measured", "truth"):
        sel = [r for r in rows if r["run"] == name]
        zm = math.sqrt(np.mean([r["rms_z_mag"] ** 2 for r in sel]))
        zp = math.sqrt(np.mean([r["rms_z_phase"] ** 2 for r in sel]))
        print(f"{name}: rms error/std over {sum(r['points'] for r in sel)} points: |H| {zm:.3f}, phase {zp:.3f}")
    meas = [r for r in rows if r["run"] == "measured"]
    worst_g = max(abs(r["ptc_gain"] / a.true_gain - 1) for r in meas)
    worst_r = max(abs(r["ptc_read_noise"] / 5.0 - 1) for r in meas)
    print(f"photon transfer: worst gain error {worst_g * 100:.2f} % (goal 1 %), worst read noise error {worst_r * 100:.2f} % (goal 5 %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
