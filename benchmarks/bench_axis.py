"""An actuator axis rotated in the camera's image: identify with the axis measured at
calibration (fit.axis=measure, the default) against the motion fitted along x (fit.axis=x).

For each rotation of the simulated mirror's axis (plant.direction), the default 30-point
sweep (1 Hz - 1 kHz) is run both ways and the largest |H| error, phase error and
error/std against the truth are printed, with the measured angle.

    python benchmarks/bench_axis.py [--angles 0 3 10 30] [--n 30]
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from torchblur.config import load_config
from torchblur.identify.run import identify


def errors(res):
    t, f = res.truth, res.frf
    em = np.abs(f.magnitude[0, 0] - np.abs(t)) / np.abs(t)
    ep = np.abs(np.angle(np.exp(1j * (f.phase[0, 0] - np.angle(t)))))
    z = np.maximum(np.abs(f.magnitude[0, 0] - np.abs(t)) / f.magnitude_std[0, 0], ep / f.phase_std[0, 0])
    return 100 * float(np.nanmax(em)), float(np.degrees(np.nanmax(ep))), float(np.nanmax(z))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--angles", type=float, nargs="+", default=[0.0, 3.0, 10.0, 30.0])
    ap.add_argument("--n", type=int, default=30, help="sweep points")
    args = ap.parse_args()
    print(f"{'rotation':>8}  {'measured angle':>18}  {'fit.axis=measure: |H| %, deg, err/std':>38}  {'fit.axis=x: |H| %, deg, err/std':>32}")
    for deg in args.angles:
        a = math.radians(deg)
        keys = [f"sweep.n={args.n}", f"plant.direction=[{math.cos(a)},{math.sin(a)}]"]
        meas = identify(load_config(None, keys), progress=False)
        along_x = identify(load_config(None, keys + ["fit.axis=x"]), progress=False)
        ang = math.degrees(math.atan2(meas.direction[1], meas.direction[0]))
        std = math.degrees(meas.axis.angle_std_rad)
        m, x = errors(meas), errors(along_x)
        print(f"{deg:7.1f}d  {ang:9.3f} +- {std:5.3f}d  {m[0]:16.3f} {m[1]:8.3f} {m[2]:8.2f}     {x[0]:12.3f} {x[1]:8.3f} {x[2]:8.2f}")


if __name__ == "__main__":
    main()
