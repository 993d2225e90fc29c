"""DM identification against the simulated truth: do the reported stds hold? (issue 17)

Runs :func:`torchblur.identify.pipeline.identify` on ``configs/identify_dm.yaml`` (or ``--config``)
for each ``--seeds`` value (the mirror's spread, the camera noise and the jitter change with it)
and prints, over the live actuators, each estimate's largest relative error and the rms and
largest of error / reported std (rms about 1 where the stds hold; with 51 actuators an rms
within about 1 +- 0.2), D0's rms error over its largest element, whether the dead actuators are
reported dead, the registration fitted to D0 and its error against the simulated one
(``dm.registration.*`` overrides misregister the simulated mirror), and the run's time by stage.

    python benchmarks/bench_dm_accuracy.py [--config configs/identify_dm.yaml] [--seeds 0 1] [key=value ...]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchblur.config import load_config
from torchblur.identify.dm_plan import truth_errors
from torchblur.identify.pipeline import identify


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/identify_dm.yaml")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("overrides", nargs="*", help="dotted key=value overrides")
    args = ap.parse_args(argv)
    for seed in args.seeds:
        cfg = load_config(args.config, [*args.overrides, f"seed={seed}"])
        torch.manual_seed(seed)
        t0 = time.perf_counter()
        res = identify(cfg, progress=False)
        elapsed = time.perf_counter() - t0
        err = truth_errors(res)
        stages = ", ".join(f"{k} {v:.1f} s" for k, v in res.timing_s.items())
        print(f"seed {seed}: {len(res.actuators)} actuators, {res.n_frames} sweep frames, {elapsed:.1f} s ({stages})")
        m, a = res.mirror, res.actuators
        live = ~m.dead
        for name, est, std, true in (("dc_gain", a.dc_gain, a.dc_gain_std, m.gain), ("mode_hz", a.mode_hz, a.mode_hz_std, m.mode_hz),
                                     ("damping", a.damping, a.damping_std, m.damping), ("delay_s", a.delay_s, a.delay_s_std, m.delay_s)):
            z = (est[live] - true[live]) / std[live]
            rel = np.abs(est[live] / true[live] - 1)
            print(f"  {name:8s} largest error {rel.max() * 100:.3f} %   error/std: rms {np.sqrt(np.mean(z ** 2)):.2f}, "
                  f"mean {z.mean():+.2f}, largest {np.abs(z).max():.2f}")
        print(f"  D0 rms error / largest element {err['D0_rms_error_over_max'] * 100:.3f} %; dead reported dead: "
              f"{err['dead_reported_dead']}; live reported dead: {err['live_reported_dead']}")
        if res.registration is not None:  # the registration fitted to D0 (torchblur.dm.registration) against the simulated one
            print(f"  {res.registration.line()}")
            reg = {k[len("registration_"):]: v for k, v in err.items() if k.startswith("registration_")}
            if reg:
                print("  registration error: " + ", ".join(f"{k} {reg[k + '_error']:+.4g} ({reg[k + '_z']:+.2f} std)"
                                                          for k in ("shift_x", "shift_y", "rotation_deg", "magnification", "coupling")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
