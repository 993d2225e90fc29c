"""Why a spots run's channel model fails: its points against the truth, against the model, and the
leak of the spot's other axis into them.

    torchblur identify --config configs/identify_spots.yaml --out runs/spots
    python benchmarks/spots_channels.py runs/spots [--top 6]

For each channel (output o from input i) of a finished simulated spots run (the truth is the
simulated rig's ``spot_truth``): the reduced chi2 of its points against the truth and against the
run's model (the (magnitude, phase) covariance of each point, 2 per point; the model's also over
its dof in model.json's judgement), and the complex coefficient ``c`` of the least-squares fit
``error = c * (the same spot's other axis from the same input)``: a leak of the spot's large motion
into a weak channel. A channel whose points are off the truth by as much as off its model is not
misfitted by the model's order: its points carry an error their stds do not hold. Prints the
``--top`` channels by reduced chi2 against the truth, and the median over all channels.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchblur.identify.read_outputs import read_outputs  # noqa: E402
from torchblur.identify.run import build_simulated_rig  # noqa: E402


def _chi2(frf, o: int, i: int, other: np.ndarray) -> float:
    """Reduced chi2 (per real observation) of the points of channel (o, i) against ``other`` [F]."""
    h = frf.response[o, i]
    r = np.stack([np.abs(h) - np.abs(other), np.angle(h / other)], -1)
    return float(np.einsum("fa,fab,fb->f", r, np.linalg.inv(frf.cov[o, i]), r).mean() / 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a finished spots run folder (torchblur identify --config configs/identify_spots.yaml)")
    ap.add_argument("--top", type=int, default=6)
    args = ap.parse_args(argv)
    got = read_outputs(args.run)
    frf, model = got["frf.json"], got["model.json"]
    judged = {j["name"]: j for j in json.loads((Path(args.run) / "model.json").read_text())["judgement"]}
    truth = np.asarray(build_simulated_rig(got["config.yaml"]).spot_truth(frf.freq_hz))  # [K, 2, I, F]
    T = truth.reshape(-1, *truth.shape[2:])
    H_model = model.frequency_response(frf.omega)
    rows = []
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            e, other = frf.response[o, i] - T[o, i], T[o ^ 1, i]  # o ^ 1: the same spot's other axis
            c = np.vdot(other, e) / np.vdot(other, other)
            name = f"two-step {frf.output_labels[o]} from {frf.input_labels[i]}"
            rows.append((_chi2(frf, o, i, T[o, i]), _chi2(frf, o, i, H_model[o, i]), judged[name], c, name))
    rows.sort(key=lambda r: -r[0])
    for vs_truth, vs_model, j, c, name in rows[:args.top]:
        print(f"{name[9:]}: points vs truth reduced chi2 {vs_truth:.2f}; vs model {vs_model:.2f} (model.json: {j['reduced_chi2']:.3g} "
              f"over {j['dof']} dof, {'passed' if j['passed'] else 'failed'}); leak of the other axis c = {c.real:+.4f}{c.imag:+.4f}j "
              f"(|c| {abs(c):.4f})")
    print(f"median over {len(rows)} channels: points vs truth reduced chi2 {np.median([r[0] for r in rows]):.2f}, vs model "
          f"{np.median([r[1] for r in rows]):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
