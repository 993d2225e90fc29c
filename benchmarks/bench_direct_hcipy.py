"""Issue 30's case at full size: the verdict on a direct model fitted to diffraction spots.

A user rig (tests/hcipy_rig.py) whose frames are HCIPy spots (circular aperture, 0.05 wave rms
of astigmatism and coma), the plant of issue 30 (modes at 600 Hz, damping 0.08, and 2 kHz,
damping 0.05; 25 us delay; 10 px per input unit), configs/identify_direct.yaml at ``--n`` points,
through ``torchblur.identify(cfg, rig)``. Prints the two-step and direct models' delay and modes
against the truth (error / std) and the verdict line with its exit status.

    python benchmarks/bench_direct_hcipy.py [--n 12] [--threads 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import hcipy_rig as hr  # noqa: E402

import torchblur as tb  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.identify.verdict import verdict  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "identify_direct.yaml"
TRUTH = {"delay_s": 25e-6, "mode1_hz": 600.0, "mode2_hz": 2000.0, "mode1_zeta": 0.08, "mode2_zeta": 0.05}


def _params(model):
    """``{name: (value, std)}``: the delay and each mode's frequency and damping."""
    if hasattr(model, "noise_estimated"):
        k = list(model.param_names).index("delay_s")
        out = {"delay_s": (float(model.params[k]), float(model.std[k]))}
    else:
        out = {"delay_s": model.parameter("delay_s")}
    for i, m in enumerate(model.modal_parameters(), start=1):
        out[f"mode{i}_hz"] = (m["freq_hz"], m["freq_hz_std"])
        out[f"mode{i}_zeta"] = (m["zeta"], m["zeta_std"])
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=12)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    num, den, tau = hr.issue30_plant()
    cfg = load_config(str(CONFIG), [f"plant.num={num}", f"plant.den={den}", f"plant.delay_s={tau}", f"sweep.n={args.n}"])
    t0 = time.perf_counter()
    res = tb.identify(cfg, hr.hcipy_rig(cfg), progress=False)
    dt = time.perf_counter() - t0
    print(f"{args.n} points, HCIPy spots, threads={args.threads}, {dt:.0f} s")
    for name, model in (("two-step", res.model), ("direct", res.direct_model)):
        if model is None:
            print(f"{name}: none")
            continue
        p = _params(model)
        line = ", ".join(f"{k} {v * (1e6 if k == 'delay_s' else 1):.4g} +- {s * (1e6 if k == 'delay_s' else 1):.2g} "
                         f"({(v - TRUTH[k]) / s:+.1f} std)" for k, (v, s) in p.items() if k in TRUTH)
        print(f"{name} (reduced chi2 {model.reduced_chi2:.3g}): {line}")
    v = verdict(res.frf, cfg, model=res.model, direct=res.direct_model)
    print(v.line)
    print(f"exit status {v.exit_code}")


if __name__ == "__main__":
    main()
