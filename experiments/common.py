"""Shared plumbing of the experiment scripts: arguments, configs, outputs.

Every script: ``python experiments/<name>.py [--config configs/<name>.yaml] --out DIR
[--quick] [key=value ...]``; it writes PNG figures and ``metrics.json`` into DIR.
``--quick`` runs a reduced version (about 15 s on 2 CPU cores) used by the tests.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def parse(description: str, default_config: str):
    """Arguments and the merged config (YAML defaults, then ``key=value`` overrides; with
    ``--quick`` the config's ``quick:`` section is merged on top). Unknown keys are errors."""
    from omegaconf import OmegaConf

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--config", default=str(ROOT / "configs" / default_config))
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true", help="reduced run (~15 s) for tests")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    cfg = OmegaConf.load(args.config)
    quick = cfg.pop("quick", None)
    OmegaConf.set_struct(cfg, True)
    if args.quick and quick is not None:
        cfg = OmegaConf.merge(cfg, quick)
    if args.overrides:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(args.overrides))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return args, cfg, out


def save_figure(fig, out: Path, name: str) -> str:
    import torchblur

    path = out / name
    fig.savefig(path, dpi=110, metadata={"Description": f"torchblur {torchblur.__version__}"})
    return str(path)


def write_metrics(out: Path, metrics: dict, *, started: float, cfg=None, quick: bool = False) -> None:
    """``metrics.json``: the figures' numbers, the config, version, wall time."""
    import torchblur
    from omegaconf import OmegaConf

    payload = {"torchblur_version": torchblur.__version__, "quick": quick, "elapsed_s": round(time.time() - started, 3)}
    if cfg is not None:
        payload["config"] = OmegaConf.to_container(cfg, resolve=True)
    payload.update(metrics)
    (out / "metrics.json").write_text(json.dumps(payload, indent=2, default=float))


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def periodic_minima(phase, cost) -> list[tuple[float, float]]:
    """Local minima of a cost on a uniform periodic phase grid (rad), refined by a parabola
    through each minimum and its neighbours: ``[(phase, cost)]``, deepest first."""
    import numpy as np

    left, right = np.roll(cost, 1), np.roll(cost, -1)
    idx = np.nonzero((cost < left) & (cost <= right))[0]
    step = phase[1] - phase[0]
    out = []
    for i in idx:
        cm, c0, cp = left[i], cost[i], right[i]
        den = cm - 2 * c0 + cp
        d = float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5)) if den > 0 else 0.0
        out.append((float(math.remainder(phase[i] + d * step, 2 * math.pi)), float(c0 - 0.25 * (cm - cp) * d)))
    return sorted(out, key=lambda m: m[1])


def x_sinusoid(amplitude, phase, omega):
    """``amplitude sin(omega t + phase)`` along x (px, rad; broadcast), as a
    :class:`torchblur.Sinusoid` in float64."""
    import torch

    import torchblur as tb

    amplitude, phase = torch.broadcast_tensors(torch.as_tensor(amplitude, dtype=torch.float64),
                                               torch.as_tensor(phase, dtype=torch.float64))
    zero = torch.zeros_like(amplitude)
    return tb.Sinusoid(torch.stack([amplitude, zero], -1), torch.stack([phase, zero], -1), omega)


def wrapped(x):
    """Phase(s) ``x`` (rad) wrapped to (-pi, pi], as numpy."""
    import torch

    import torchblur as tb

    return tb.wrap_phase(torch.as_tensor(x, dtype=torch.float64)).numpy()


def wrapped_distance(a: float, b: float) -> float:
    """``|wrap(a - b)|`` (rad)."""
    return abs(float(wrapped(a - b)))

