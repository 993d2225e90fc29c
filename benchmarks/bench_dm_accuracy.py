"""DM identification against the simulated truth: do the reported stds hold? (issue 17)

Runs :func:`torchblur.identify.pipeline.identify` on ``configs/identify_dm.yaml`` (or ``--config``)
for each ``--seeds`` value (the mirror's spread, the camera noise and the jitter change with it)
and prints, over the live actuators, each estimate's largest relative error and the rms and
largest of error / reported std (rms about 1 where the stds hold; with 51 actuators an rms
within about 1 +- 0.2), D0's rms error over its largest element, whether the dead actuators are
reported dead, the registration fitted to D0 and its error against the simulated one
(``dm.registration.*`` overrides misregister the simulated mirror), and the run's time by stage.

The DC gains' errors are not independent: the registration's error moves every gain together
(its share of each ``dc_gain_std``, ``gain_var_registration``, is one error common to all), so
their rms(error/std) over the actuators is no chi2 test. :func:`dc_gain_split` prints the
common part (the gains' shift the registration's error predicts, from its ``gain_jacobian``),
the chi2 of the errors under their full covariance (per-actuator variance plus the
registration's common one) with its p, and the rms(error/std) of the actuators fitted on the
simulated (true) geometry, where no registration error enters (the per-actuator part).

    python benchmarks/bench_dm_accuracy.py [--config configs/identify_dm.yaml] [--seeds 0 1] [key=value ...]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from scipy import stats

from torchblur.dm.actuator_fit import fit_actuators
from torchblur.dm.mirror import influence_width
from torchblur.identify.dm_plan import truth_errors
from torchblur.identify.pipeline import identify
from torchblur.config import load_config


def dc_gain_split(res) -> dict:
    """The live DC gains' errors split (module docstring): ``common`` (the mean over the
    actuators of the registration error's predicted shift, in stds), ``chi2``, ``dof``, ``p`` (full
    covariance), ``true_G_rms`` and ``true_G_mean`` (error/std on the simulated geometry)."""
    m, a, fit = res.mirror, res.actuators, res.registration
    live = ~m.dead
    err = (a.dc_gain - m.gain)[live]
    out = {}
    if fit is not None and fit.ok and fit.gain_jacobian is not None and res.truth_registration is not None:
        t = res.truth_registration  # the simulator's spots are Gaussians: a mean-slope sensor, diffraction_weight 0
        theta = lambda r, c, beta: np.array([r.shift_x, r.shift_y, math.radians(r.rotation_deg), r.magnification,  # noqa: E731
                                             influence_width(c), beta])  # the order of RegistrationFit.cov
        dtheta = theta(fit.registration, fit.registration.coupling, fit.diffraction_weight) - \
            theta(t, float(m.coupling) if t.coupling is None else t.coupling, 0.0)
        Jg = fit.gain_jacobian[live]
        out["common"] = float(np.mean(Jg @ dtheta / a.dc_gain_std[live]))
        out["weighting_z"] = float(dtheta[5] / math.sqrt(fit.cov[5, 5]))
        out["registration_chi2"] = float(dtheta @ np.linalg.solve(fit.cov, dtheta))  # over 6
        out["share"] = float(np.median(fit.gain_var_registration[live] / a.dc_gain_std[live] ** 2))
        common = Jg @ fit.cov @ Jg.T  # the registration's share, one error for all gains
        own = np.asarray(a.dc_gain_std)[live] ** 2 - np.diag(common)  # the rest (edge-widened gains' extra included)
        chi2 = float(err @ np.linalg.solve(common + np.diag(own), err))
        out.update(chi2=chi2, dof=int(live.sum()), p=float(stats.chi2.sf(chi2, int(live.sum()))))
    if res.truth_G is not None:
        tab = fit_actuators(res.freq_hz, res.D, res.D_cov, res.truth_G, actuator_xy=a.actuator_xy)
        z = (tab.dc_gain - m.gain)[live] / tab.dc_gain_std[live]
        out.update(true_G_rms=float(np.sqrt(np.mean(z**2))), true_G_mean=float(z.mean()))
    if res.truth_D is not None:  # each column's scale against the truth per frequency, in stds (a bias every spot fit shares)
        x, t = (np.stack([v.real, v.imag], -1)[:, live] for v in (res.D, res.truth_D))
        w = np.stack([1 / res.D_cov[..., 0, 0], 1 / res.D_cov[..., 1, 1]], -1)[:, live]
        w = np.where(np.isfinite(w) & np.isfinite(x), w, 0.0)
        num, den = (w * t * (np.nan_to_num(x) - t)).sum((0, 3)), (w * t * t).sum((0, 3))
        out["column_scale_mean"] = float(np.mean(num[den > 0] / np.sqrt(den[den > 0])))
        zc = (num / np.sqrt(np.where(den > 0, den, np.nan)))[:, res.freq_hz < 400]  # [N live, F low]: below the modes
        zc = zc - np.nanmean(zc, axis=0)
        cc = np.corrcoef(zc.T)  # one actuator's errors at two frequencies: 0 where they are independent
        out["frequency_correlation"] = float((cc.sum() - np.trace(cc)) / (cc.size - len(cc)))
    return out


def print_errors(res) -> None:
    """Print a simulated DM run's errors against its truth (module docstring)."""
    err = truth_errors(res)
    m, a = res.mirror, res.actuators
    live = ~m.dead
    for name, est, std, true in (("dc_gain", a.dc_gain, a.dc_gain_std, m.gain), ("mode_hz", a.mode_hz, a.mode_hz_std, m.mode_hz),
                                 ("damping", a.damping, a.damping_std, m.damping), ("delay_s", a.delay_s, a.delay_s_std, m.delay_s)):
        z = (est[live] - true[live]) / std[live]
        rel = np.abs(est[live] / true[live] - 1)
        print(f"  {name:8s} largest error {rel.max() * 100:.3f} %   error/std: rms {np.sqrt(np.mean(z ** 2)):.2f}, "
              f"mean {z.mean():+.2f}, largest {np.abs(z).max():.2f}")
    split = dc_gain_split(res)
    if "chi2" in split:
        print(f"  dc_gain  the registration's error (chi2 {split['registration_chi2']:.1f} over 6; sensor weighting "
              f"{split['weighting_z']:+.2f} std) shifts every gain by {split['common']:+.2f} std (mean; its share of a gain's "
              f"variance {split['share']:.3f}, median); chi2 of the errors "
              f"under their full covariance {split['chi2']:.1f} over {split['dof']} (p {split['p']:.3g})")
    if "true_G_rms" in split:
        print(f"  dc_gain  fitted on the simulated geometry (no registration error): error/std rms {split['true_G_rms']:.2f}, "
              f"mean {split['true_G_mean']:+.2f}; D's columns against the truth per frequency: mean scale error "
              f"{split.get('column_scale_mean', math.nan):+.3f} std, one actuator's at two frequencies below 400 Hz "
              f"correlated {split.get('frequency_correlation', math.nan):+.3f} (mean)")
    print(f"  D0 rms error / largest element {err['D0_rms_error_over_max'] * 100:.3f} %; dead reported dead: "
          f"{err['dead_reported_dead']}; live reported dead: {err['live_reported_dead']}")
    if res.registration is not None:  # the registration fitted to D0 (torchblur.dm.registration) against the simulated one
        print(f"  {res.registration.line()}")
        reg = {k[len("registration_"):]: v for k, v in err.items() if k.startswith("registration_")}
        if reg:
            print("  registration error: " + ", ".join(f"{k} {reg[k + '_error']:+.4g} ({reg[k + '_z']:+.2f} std)"
                                                      for k in ("shift_x", "shift_y", "rotation_deg", "magnification", "coupling")))


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
        print(f"seed {seed}: {len(res.actuators)} actuators, {res.n_frames} sweep frames, {elapsed:.1f} s "
              f"({', '.join(f'{k} {v:.1f} s' for k, v in res.timing_s.items())})")
        print_errors(res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
