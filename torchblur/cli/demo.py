"""``torchblur demo``: the paper's "peanut": a blurred laser spot, its motion and its alias
phase, which renders the same image (Proposition 3), as a figure and a JSON summary.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

import torchblur as tb
from torchblur.identify.read_outputs import DEMO_SCHEMA
from torchblur.render.camera import CameraModel

__all__ = ["demo_command"]


def demo_command(args) -> int:
    """``torchblur demo --out DIR``: render a blurred laser spot at the paper's settings, its motion
    and its alias, a noisy camera frame of it; save DIR/demo.png and DIR/demo.json (read back by
    :func:`torchblur.identify.read_outputs.read_outputs`)."""
    from matplotlib.figure import Figure  # optional, heavy: not pyplot (the caller's backend stays as it was)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    f_hz, te_frac, b = 300.0, 0.5, math.pi / 2  # the paper's settings: p = half a period, w tcam = pi/2
    omega = 2 * math.pi * f_hz
    window = tb.ExposureWindow(b / omega, te_frac / f_hz)
    psf = tb.GaussianPSF.from_axes(torch.tensor([48.0, 40.0], dtype=torch.float64), 2.6, 1.8, 0.4, amplitude=1.0)
    phase = torch.tensor(-0.6, dtype=torch.float64)
    direction = torch.tensor([0.9, 0.45], dtype=torch.float64)
    amp = 14.0 * direction
    alias = tb.alias_phase(phase, omega, window)
    renderer = tb.BlurRenderer(height=80, width=96)
    imgs = [renderer(tb.Sinusoid(amp, p.expand(2), omega), psf, window) for p in (phase, alias)]
    still = renderer(tb.Sinusoid(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), omega), psf, window)
    camera = CameraModel(read_noise_e=8.0, full_well_e=60000.0, bit_depth=16)
    scale = 40000.0 / float(imgs[0].max())
    noisy = camera.expose(imgs[0] * scale, generator=torch.Generator().manual_seed(args.seed))

    t = torch.linspace(0, 2 / f_hz, 400, dtype=torch.float64)
    fig = Figure(figsize=(16, 3.8))
    ax = fig.subplots(1, 4)
    for p, style in ((phase, "-"), (alias, "--")):
        y = (amp.norm() * torch.sin(omega * t + p)).numpy()
        ax[0].plot(t.numpy() * 1e3, y, style, label=f"phase {math.degrees(float(p)):.1f} deg")
    ax[0].axvspan(float(window.start) * 1e3, float(window.end) * 1e3, color="0.85", label="exposure")
    ax[0].set(xlabel="time (ms)", ylabel="displacement (px)", title=f"{f_hz:.0f} Hz motion")
    ax[0].legend(fontsize=8)
    for a, im, title in ((ax[1], still, "still spot (PSF x Te)"), (ax[2], imgs[0], "blurred: true phase"), (ax[3], noisy, "camera frame (ADU)")):
        a.imshow(im.detach().numpy(), cmap="inferno")
        a.set_title(title)
        a.set_axis_off()
    fig.suptitle("torchblur demo: a fast steering mirror seen by a slow camera; the alias phase gives the same image")
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=110)
    summary = {
        "schema": DEMO_SCHEMA[0],
        "schema_version": DEMO_SCHEMA[1][-1],
        "torchblur_version": tb.__version__,
        "seed": args.seed,
        "freq_hz": f_hz,
        "phase_rad": float(phase),
        "alias_phase_rad": float(alias),
        "max_abs_difference_true_vs_alias_image": float((imgs[0] - imgs[1]).abs().max()),
        "image_peak": float(imgs[0].max()),
    }
    (out / "demo.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote {out / 'demo.png'} and {out / 'demo.json'}")
    print(f"true phase {math.degrees(float(phase)):.2f} deg and alias {math.degrees(float(alias)):.2f} deg render the same image "
          f"(max difference {summary['max_abs_difference_true_vs_alias_image']:.1e} of peak {summary['image_peak']:.3g})")
    return 0
