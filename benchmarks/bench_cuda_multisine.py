"""The kernel multisine fit on CUDA against the CPU (issue 29): one HCIPy problem (tests/hcipy_routes.py,
seed 1000) fitted with its measured kernel and the kernel's noise propagated (``kernel_var``), on the
CPU, on CUDA, and as a batch of 32 copies on CUDA; prints each fit's tones, stds and wall time and
the CUDA-CPU differences in stds. Needs a CUDA device and hcipy.

    python benchmarks/bench_cuda_multisine.py
"""
import sys
import time
import traceback
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import hcipy_routes as hr  # noqa: E402
from torchblur.fit.multisine import fit_multisine  # noqa: E402
from torchblur.image.psf_from_still import psf_from_still  # noqa: E402
from torchblur.render.psf import KernelPSF  # noqa: E402
from torchblur.render.window import ExposureWindow  # noqa: E402

torch.set_num_threads(1)
print(torch.__version__, torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
p = hr.multisine_problem(1000)
r = psf_from_still(torch.as_tensor(p["still"]), p["still_exposure"], kind="auto", background=0.0)
pw = torch.tensor(p["power"]); raw = torch.tensor(p["frames"]); images = raw / pw[:, None, None]
noise = r.frame_noise_std(torch.tensor(p["clean"])) / pw[:, None, None]
res = {}
for dev, B in (("cpu", 1), ("cuda", 1), ("cuda", 32)):
    try:
        t = time.perf_counter()
        f = fit_multisine(images.to(dev).expand(B, -1, -1, -1), KernelPSF(r.psf.kernel.to(dev).expand(B, -1, -1)),
                          ExposureWindow(p["window"].start.to(dev).expand(B, -1), p["window"].duration.to(dev).expand(B, -1)),
                          torch.tensor(p["omega"], device=dev).expand(B, -1), noise_std=noise.to(dev).expand(B, -1, -1, -1),
                          kernel_var=r.kernel_variance().to(dev).expand(B, -1, -1))
        if dev == "cuda":
            torch.cuda.synchronize()
        dt = time.perf_counter() - t
        res[(dev, B)] = f
        print(dev, B, f"{dt:.2f} s", "M", f.amplitude[0].cpu().numpy(), "phi", f.phase[0].cpu().numpy(), "std M", f.amplitude_std[0].cpu().numpy(),
              "std phi", f.phase_std[0].cpu().numpy(), "status", f.status.reshape(-1)[:4].cpu().numpy(), flush=True)
    except Exception:
        traceback.print_exc()
if ("cpu", 1) in res and ("cuda", 1) in res:
    a, b = res[("cpu", 1)], res[("cuda", 1)]
    print("cuda - cpu, in stds: M", ((b.amplitude.cpu() - a.amplitude) / a.amplitude_std).abs().max().item(),
          "phi", ((b.phase.cpu() - a.phase) / a.phase_std).abs().max().item(),
          "std rel", ((b.amplitude_std.cpu() / a.amplitude_std) - 1).abs().max().item())
