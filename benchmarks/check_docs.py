"""Compare the figures README.md and docs/*.md quote with what the commands print now.

    python benchmarks/check_docs.py              # the quick claims (a few runs of the CLI, ~2 min on 2 cores)
    python benchmarks/check_docs.py --instant    # only those that take no run (what the test suite runs)
    python benchmarks/check_docs.py --all        # every claim, benchmarks included (an hour and more)
    python benchmarks/check_docs.py --list       # the claims and where each figure comes from

Each claim names a passage of a guide (a regular expression whose groups are the quoted
numbers), the command that prints those figures (run from the repository root in a temporary
folder) and a regular expression on its output whose groups are the printed numbers; the
numbers are compared in order, each within the claim's relative tolerance (the run's noise:
seeded runs repeat to round-off, times swing with the machine's load). A quoted passage that is
no longer in its guide fails too: the registry and the guides move together. Prints one line
per claim and the counts; exit status 1 if any claim fails.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NUM = r"([0-9][0-9,]*(?:\.[0-9]+)?(?:e[-+]?[0-9]+)?)"  # a quoted or printed number (thousands commas allowed)
TB = [sys.executable, "-m", "torchblur.cli"]


@dataclass(frozen=True)
class Claim:
    """``doc``: the guide; ``quote``: a regex on it, one group per quoted number; ``cmd``: the
    command (a list; ``{out}`` a fresh folder) that prints them; ``printed``: a regex on its
    stdout + stderr, the same number of groups; ``rtol``: per number (one value for all);
    ``speed``: "instant" (no run), "quick" (a CLI run) or "slow" (a benchmark)."""

    name: str
    doc: str
    quote: str
    cmd: list
    printed: str
    rtol: tuple = (0.02,)
    speed: str = "quick"
    exit_codes: tuple = (0, 2, 4)
    source: str = field(default="")  # what to run by hand, for --list

    def where(self) -> str:
        return self.source or " ".join(str(c) for c in self.cmd[len(TB):] if True)


def _tb(*args):
    return [*TB, *args]


#: benchmarks/bench_dm_hcipy.py's "done when" lines: the live actuators' largest errors (mode, damping, delay,
#: DC gain), then rms(error/std) of D(jw) and of the four parameters; with D0's lines between them
_HCIPY_ERRORS = (r"largest error: mode " + NUM + r" % \(done when <= 0\.5 %\), damping " + NUM + r" % \(<= 5 %\), delay " + NUM
                 + r" us \(<= 2 us\), DC gain " + NUM + r" %")
_HCIPY_STDS = (r"rms\(error/std\) \(0\.8\.\.1\.3\): D\(jw\) " + NUM + "; mode " + NUM + ", damping " + NUM + ", delay " + NUM
               + ", DC gain " + NUM)
_HCIPY_FIGURES = (_HCIPY_ERRORS + r"\s+D0 rms error / max\|D0\| against the fitted-shift truth: " + NUM + r" %[^\n]*\n"
                  + r"(?:\s+D0 rms\(error/std\) against the fitted-shift truth[^\n]*\n)?\s+" + _HCIPY_STDS)

CLAIMS = [
    Claim("quick start: the default run's time", "README.md",
          r"`report\.txt` \(about " + NUM + r" s of acquisition and fitting on 2 cores",
          _tb("identify", "--out", "{out}"), r"elapsed " + NUM + r" s \(", rtol=(0.75,),  # a machine's load: within 4x
          source="torchblur identify --out runs/default (report.txt: elapsed)"),
    Claim("quick start: the PSF the default run chooses", "README.md",
          r"on its own simulated mirror the (Gaussian|kernel) [^(]*\(reduced chi2 " + NUM + r", threshold " + NUM,
          _tb("identify", "--out", "{out}"), r"psf: (gaussian|kernel): .*?reduced chi2 Gaussian " + NUM + r" over \d+ px, threshold "
          + NUM, rtol=(0.0, 0.15, 0.05), source="torchblur identify --out runs/default (the psf: line)"),
    # a seeded run repeats to round-off: the values within a few units of their last printed digit, the stds within 5 %
    Claim("the default run's mode with its stds", "README.md",
          r"`mode: " + NUM + r" \+- " + NUM + r" Hz, damping " + NUM + r" \+- " + NUM + r"` in report\.txt of the default run",
          _tb("identify", "--out", "{out}"), r"mode: " + NUM + r" \+- " + NUM + r" Hz, damping " + NUM + r" \+- " + NUM,
          rtol=(1e-5, 0.05, 1e-3, 0.5), source="torchblur identify --out runs/default (report.txt: mode)"),
    Claim("the default run's fit quality line", "README.md",
          r"`fit quality: reduced chi2 median " + NUM + r", max " + NUM + r" \.\.\.`",
          _tb("identify", "--out", "{out}"), r"fit quality: reduced chi2 median " + NUM + r", max " + NUM,
          rtol=(0.01,), source="torchblur identify --out runs/default (report.txt: fit quality)"),
    Claim("the slew-limit example's drive lines", "README.md",
          r"slew limit 200000 input units/s \(device 200000; from device\): the full range up to " + NUM + r" Hz drive: 2 of 4 points "
          r"limited by the input range \+-200 and the slew limit 200000 units/s \(\.\.\.\): " + NUM + r" Hz: " + NUM + r" px, 2e\+05 Hz: "
          + NUM + r" px",
          _tb("identify", "--out", "{out}", "sweep.f_max_hz=200000", "sweep.n=4", "plant.slew_limit=2e5", "camera.height=40",
              "camera.width=40", "seed=3", "sweep.images_per_point=1", "fit.axis=x"),
          r"slew limit 200000 input units/s \(device 200000; from device\): the full range up to " + NUM + r" Hz[\s\S]*?drive: 2 of 4 "
          r"points limited by the input range \+-200 and the slew limit 200000 units/s \([^)]*\): " + NUM + r" Hz: " + NUM
          + r" px, 2e\+05 Hz: " + NUM + r" px", rtol=(1e-3, 1e-3, 0.05, 0.1)),
    Claim("verdict of the jitter example", "README.md",
          r"(verdict: 2 of 3 points flagged: 2 timing \(above " + NUM + r" kHz, beyond 1 deg\); 2 limited by the drive \(8 kHz: "
          + NUM + r" px, 20 kHz: " + NUM + r" px\))",
          _tb("identify", "--out", "{out}", "camera.jitter_s=0.5e-6", "sweep.freq_hz=[1000,8000,20000]", "sweep.images_per_point=1"),
          r"(verdict: 2 of 3 points flagged: 2 timing \(above " + NUM + r" kHz, beyond 1 deg\); 2 limited by the drive \(8 kHz: "
          + NUM + r" px, 20 kHz: " + NUM + r" px\))", rtol=(0.0, 0.02, 0.05, 0.05)),
    Claim("verdict of the fast-sweep example", "README.md",
          r"(verdict: 2 of 6 points flagged: 2 timing \(above " + NUM + r" kHz, beyond 1 deg\), 1 no significant motion \(200 kHz: "
          r"not a measurement\); 2 limited by the drive \(17.4 kHz: " + NUM + r" px, 200 kHz: " + NUM + r" px\))",
          _tb("identify", "--out", "{out}", "sweep.f_max_hz=200000", "sweep.n=6", "sweep.images_per_point=1"),
          r"(verdict: 2 of 6 points flagged: 2 timing \(above " + NUM + r" kHz, beyond 1 deg\), 1 no significant motion \(200 kHz: "
          r"not a measurement\); 2 limited by the drive \(17.4 kHz: " + NUM + r" px, 200 kHz: " + NUM + r" px\))",
          rtol=(0.0, 0.02, 0.05, 0.1)),
    Claim("the 5 kHz sweep against the truth", "README.md",
          r"`sweep\.f_max_hz=5000` run stays within the range and holds " + NUM + r" % / " + NUM + r" deg against the truth",
          _tb("identify", "--out", "{out}", "sweep.f_max_hz=5000"),
          r"against the truth: max \|H\| error " + NUM + r"% \(goal 1%\), max phase error " + NUM + r" deg", rtol=(0.05, 0.05)),
    Claim("the size limit's estimate", "README.md",
          r"sweep\.n: the run is too large \(estimate: " + NUM + r" frames",
          _tb("identify", "--out", "{out}", "sweep.n=1e7"), r"sweep\.n: the run is too large \(estimate: " + NUM + r" frames",
          rtol=(0.0,), speed="instant"),
    Claim("the contract's case count", "README.md",
          r"`tests/test_bad_input_contract\.py` lists " + NUM + r" bad inputs with their exact exceptions and " + NUM
          + " degenerate cases",
          [sys.executable, "-c", "import sys; sys.path.insert(0, 'tests'); import test_bad_input_contract as t; "
                                 "print(len(t.BAD), 'bad inputs,', len(t.DEGENERATE), 'degenerate')"],
          NUM + r" bad inputs, " + NUM + " degenerate", rtol=(0.0,)),
    # the re-fits of one seeded run: they repeat to round-off (0.01 and 0.02 are one printed digit: within half)
    Claim("the losses against l2 on the default run", "README.md",
          r"On the default run poisson agrees with l2 within " + NUM + r" \(\|H\|\) and " + NUM + r" \(phase\) l2 std at every point "
          r"\([^)]*\), l1 within " + NUM + " and " + NUM,
          [sys.executable, "benchmarks/bench_losses.py"],
          r"fit.loss=poisson: [^\n]*?max \|diff\|/std\(l2\): \|H\| " + NUM + r", phase " + NUM + r"[\s\S]*?fit.loss=l1: [^\n]*?"
          r"max \|diff\|/std\(l2\): \|H\| " + NUM + r", phase " + NUM, rtol=(0.5, 0.5, 0.1, 0.1), speed="slow"),
    Claim("the fitter's efficiency", "README.md",
          r"RMSE / Cramer-Rao bound " + NUM + r" \(M\) and " + NUM + r" \(phase\)",
          [sys.executable, "benchmarks/bench_fit.py"], r"RMSE/CRLB: M " + NUM + r" +phi " + NUM, rtol=(0.05, 0.05), speed="slow"),
    Claim("the direct fit's resonance", "README.md",
          r"resonance frequency within " + NUM + r" % and damping within " + NUM + " %",
          [sys.executable, "benchmarks/bench_direct.py"],
          r"worst frequency error " + NUM + r"% \(goal 0.5%\), worst damping error " + NUM + "%", rtol=(0.5, 0.5), speed="slow"),
    Claim("spots: the worst channel against the truth", "README.md",
          r"of the direct motion, a few tenths of a pixel\) within " + NUM + r" % and " + NUM + r" deg; largest error/std " + NUM,
          [sys.executable, "benchmarks/bench_mimo.py", "--which", "spots"],
          r"worst channel: \|H\| " + NUM + r"% \(goal 2%\), phase " + NUM + r" deg \(goal 2 deg\), err/std " + NUM,
          rtol=(0.3, 0.3, 0.3), speed="slow"),
    Claim("the DM run's verdict", "README.md",
          r"`verdict: trustworthy: all " + NUM + r" actuators within tolerance: " + NUM + r" ok, 1 weak \(" + NUM
          + r"\), 1 dead \(" + NUM + r"\);",
          _tb("identify", "--config", "configs/identify_dm.yaml", "--out", "{out}"),
          r"verdict: trustworthy: all " + NUM + r" actuators within tolerance: " + NUM + r" ok, 1 weak \(" + NUM
          + r"\), 1 dead \(" + NUM + r"\);", rtol=(0.0,), speed="slow"),
    Claim("the DM run's size", "README.md",
          r"`configs/identify_dm\.yaml`: " + NUM + r" actuators, one dead and one weak, " + NUM + r" spots, a Hadamard plan",
          _tb("identify", "--config", "configs/identify_dm.yaml", "--out", "{out}"),
          r"dm run: " + NUM + r" actuators, " + NUM + r" spots, plan hadamard", rtol=(0.0,), speed="slow"),
    Claim("the DM run's plan", "README.md",
          r"a Hadamard plan of " + NUM + r" patterns x " + NUM + r" frequencies x " + NUM + r" exposures x " + NUM + r" repeats = "
          + NUM + r" frames, " + NUM + r" of what one actuator at a time needs",
          _tb("identify", "--config", "configs/identify_dm.yaml", "--out", "{out}"),
          r"dm plan: hadamard, " + NUM + r" patterns x " + NUM + r" frequencies x " + NUM + r" exposures x " + NUM + r" repeats = "
          + NUM + r" frames; frames for the same accuracy vs one at a time: " + NUM, rtol=(0.0,), speed="slow"),
    Claim("the DM run against the truth", "README.md",
          r"largest errors over the 51 live actuators: mode " + NUM + r" %, damping " + NUM + r" %, DC gain " + NUM + r" %; D0 " + NUM
          + r" % rms of its largest element; the dead actuator reported dead, the weak one weak; rms\(error/std\) DC gain " + NUM
          + r", mode " + NUM + r", damping " + NUM,
          _tb("identify", "--config", "configs/identify_dm.yaml", "--out", "{out}"),
          r"against the simulated truth: mode " + NUM + r" %, damping " + NUM + r" %, DC gain " + NUM + r" % \(largest over live "
          r"actuators\), D0 " + NUM + r" % rms of its largest element, dead reported dead: True; rms\(error/std\) over the live "
          r"actuators: DC gain " + NUM + r", mode " + NUM + r", damping " + NUM, rtol=(0.02,), speed="slow"),  # seeded: round-off
    # bench_dm_accuracy's seeded runs repeat to round-off: within the printed digits
    *(Claim(f"DM accuracy against the truth, seed {seed}", "docs/deformable_mirrors.md",
            before + r"DC gain " + NUM + r" % \(" + NUM + ", " + NUM + r"\), mode " + NUM + r" % \(" + NUM + ", " + NUM + r"\), damping "
            + NUM + r" % \(" + NUM + ", " + NUM + r"\), delay " + NUM + r" % \(" + NUM + ", " + NUM + r"\); D0 " + NUM + " %",
            [sys.executable, "benchmarks/bench_dm_accuracy.py", "--seeds", "0", "1"],
            rf"seed {seed}: [^\n]*\n" + "".join(rf" +{name} +largest error " + NUM + r" % +error/std: rms " + NUM
                                                 + r", mean [-+0-9.]+, largest " + NUM + r"\n" for name in ("dc_gain", "mode_hz", "damping",
                                                                                                        "delay_s"))
            + r"(?:[^\n]*\n)*? +D0 rms error / largest element " + NUM + " %", rtol=(0.02,), speed="slow")
      for seed, before in ((0, r"the shipped config \(seed 0\): largest errors and rms\(error/std\) \(largest \|error/std\|\) over the 51 "
                               r"live actuators: "),
                           (1, r"Seed 1 \(another mirror spread, noise and jitter\): "))),
    # the seeded DM run repeats to round-off: its verdict's figures exactly, the models' chi2 bound to its printed digits
    *(Claim(f"the DM run's verdict line ({where})", "docs/deformable_mirrors.md", before + r"verdict: trustworthy: all " + NUM
            + r" actuators within tolerance: " + NUM + r" ok, 1 weak \(" + NUM + r"\), 1 dead \(" + NUM + r"\); model reduced chi2 <= "
            + NUM + r" \(chi2 test p >= 0\.001 over the run's actuators\); " + NUM + " of " + NUM + " spot fits failed",
            _tb("identify", "--config", "configs/identify_dm.yaml", "--out", "{out}"),
            r"verdict: trustworthy: all " + NUM + r" actuators within tolerance: " + NUM + r" ok, 1 weak \(" + NUM + r"\), 1 dead \("
            + NUM + r"\); model reduced chi2 <= " + NUM + r" \(chi2 test p >= 0\.001 over the run's actuators\); " + NUM + " of " + NUM + " spot fits failed",
            rtol=(0.0, 0.0, 0.0, 0.0, 0.005, 0.0, 0.0), speed="slow")
      for where, before in (("the verdict's section", r"the second shows how a flagged run reads: ``` "),
                            ("the config's run", r"its last line `"))),
    Claim("HCIPy routes: the direct model with the measured kernel", "README.md",
          r"direct model of a resonance within " + NUM + r" % \(frequency\) and " + NUM + r" % \(damping\), rms\(error/std\) "
          + NUM + " / " + NUM,
          [sys.executable, "benchmarks/bench_hcipy_routes.py", "--jobs", "2"],
          r"direct: 40 sweeps[^\n]*\n[^\n]*\n  psf_from_still \(auto\) +" + NUM + " +" + NUM + " +" + NUM + " +" + NUM,
          rtol=(0.05,), speed="slow", source="python benchmarks/bench_hcipy_routes.py --jobs 2 (each route's psf_from_still line)"),
    Claim("HCIPy routes: the 3x3 grid with each spot's kernel", "README.md",
          r"a 3x3 grid within " + NUM + r" % and " + NUM + r" deg over 40 grids, rms\(error/std\) " + NUM + " / " + NUM,
          [sys.executable, "benchmarks/bench_hcipy_routes.py", "--jobs", "2"],
          r"spots: 40 grids[^\n]*\n[^\n]*\n  psf_from_still \(auto\) +" + NUM + " +" + NUM + " +" + NUM + " +" + NUM,
          rtol=(0.05,), speed="slow", source="python benchmarks/bench_hcipy_routes.py --jobs 2 (each route's psf_from_still line)"),
    Claim("HCIPy routes: multisine tones with the kernel's noise propagated", "README.md",
          r"multisine tones within " + NUM + r" % and " + NUM + r" deg, rms\(error/std\) " + NUM + " / " + NUM,
          [sys.executable, "benchmarks/bench_hcipy_routes.py", "--jobs", "2"],
          r"multisine: 40 problems[^\n]*\n[^\n]*\n  psf_from_still \(auto\) +" + NUM + " +" + NUM + " +" + NUM + " +" + NUM,
          rtol=(0.05,), speed="slow", source="python benchmarks/bench_hcipy_routes.py --jobs 2 (each route's psf_from_still line)"),

    # the DM run's cost: CPU-seconds (what the work costs; its threads spin on an idle machine and wait under load: 350 idle,
    # 261 at a load of 2-2.6, 286 at 6.4: within 1.4x), the wall time (it moves with the load: within 4x, as the default run's) and the peak memory
    Claim("the DM run's time", "docs/deformable_mirrors.md",
          r"--out runs/dm` from a fresh clone on a 2-core machine: " + NUM + r" CPU-seconds for the whole command, " + NUM
          + r" s wall, peak memory " + NUM + " GB, on an idle machine",
          [sys.executable, "benchmarks/bench_run_time.py", "--config", "configs/identify_dm.yaml"],
          r"CPU " + NUM + r" s \(user[^)]*\), wall " + NUM + r" s, CPU/wall [0-9.]+, peak memory " + NUM + " GB",
          rtol=(0.3, 0.75, 0.2), speed="slow", source="python benchmarks/bench_run_time.py (the DM config)"),
    Claim("the DM run's time (README)", "README.md",
          r"`python benchmarks/bench_run_time\.py` runs the command and prints these figures\): " + NUM + r" CPU-seconds "
          r"for the whole command, " + NUM + r" s wall, peak memory " + NUM + " GB, exit 0, on an idle machine",
          [sys.executable, "benchmarks/bench_run_time.py", "--config", "configs/identify_dm.yaml"],
          r"CPU " + NUM + r" s \(user[^)]*\), wall " + NUM + r" s, CPU/wall [0-9.]+, peak memory " + NUM + " GB",
          rtol=(0.3, 0.75, 0.2), speed="slow", source="python benchmarks/bench_run_time.py (the DM config)"),
    Claim("Ctrl-C at 20 moments of the default run", "README.md",
          r"drawn within the uninterrupted run's " + NUM + r" CPU seconds \(the smaller of a warm-up run and a timed one\), "
          r"interrupted " + NUM + r" of 20 runs",
          [sys.executable, "benchmarks/bench_ctrl_c.py", "--n", "20", "--clock", "cpu", "--jobs", "4"],
          r"20 interruptions uniform in \[0, " + NUM + r"\] CPU seconds[\s\S]*?\ninterrupted " + NUM + " of 20",
          rtol=(0.5, 0.2), speed="slow"),  # CPU seconds move with the machine (and its load) and with them the count
    Claim("model stds: the chi2 test over seeds 0..9", "docs/reliability.md",
          r"seeds 0\.\.9 give p " + NUM + ", " + NUM + ", " + NUM + ", " + NUM + " and " + NUM,
          [sys.executable, "benchmarks/bench_model_stds.py", "--seeds", "10", "--profile"],
          "".join(rf"{n} +[0-9.]+ +[0-9.]+ +\d+ +[A-Z ]*?(?:holds|HOLD) +[0-9.]+\.\.[0-9.]+ +" + NUM + r"[^\n]*\n *"
                  for n in ("dc_gain", "p1_omega_n", "p1_zeta", "p2_rate", "delay_s")), rtol=(0.1,), speed="slow"),
    Claim("model stds: pooled over 100 seeds and by blocks of 10", "docs/reliability.md",
          r"printed, pooled over the 91 seeds,\s+rms\(error/std\) dc_gain " + NUM + ", p1_omega_n " + NUM + r",\s+p1_zeta " + NUM
          + r", p2_rate " + NUM + r", delay_s " + NUM + r"[\s\S]*?lie within 0\.7\.\.1\.4, where honest stds give " + NUM
          + r" of blocks\s+each, and " + NUM + r" of 10 with all five parameters within at once",
          [sys.executable, "benchmarks/bench_model_stds.py", "--first", "0", "--seeds", "100", "--block", "10"],
          "".join(rf"{n} +" + NUM + r"[^\n]*\n *" for n in ("dc_gain", "p1_omega_n", "p1_zeta", "p2_rate", "delay_s"))
          + r"[\s\S]*?\(honest stds: " + NUM + r" each\); all parameters at once: " + NUM + " of 10 blocks",
          rtol=(0.02, 0.02, 0.02, 0.02, 0.02, 0.0, 0.0), speed="slow"),
    Claim("DM: the ladder on HCIPy's lenslet frames (quick, aligned)", "docs/deformable_mirrors.md",
          r"0\.065\)\. The former model[\s\S]*?\): mode\s+" + NUM + r" %, damping " + NUM + r" %, delay " + NUM + r" us, DC gain "
          + NUM + r" %, D0 " + NUM + r" % rms of max; rms\(error/std\)\s+D\(jw\) " + NUM + ", mode " + NUM + ", damping " + NUM
          + ", delay " + NUM + ", DC gain " + NUM,
          [sys.executable, "benchmarks/bench_dm_hcipy.py", "--quick", "--case", "aligned", "--no-checks", "--set", "dm_plan.kind=hadamard"],
          _HCIPY_FIGURES, rtol=(0.02,), speed="slow"),
    *[Claim(f"DM: {plan} plan with the ladder on HCIPy's lenslet frames (quick, both cases)", "docs/deformable_mirrors.md",
            "".join(rf"\| {case} \| {plan} \| " + NUM + " %, " + NUM + " %, " + NUM + " us, " + NUM + r" % \| " + ", ".join([NUM] * 5)
                    + r" \| [+-]" + NUM + r" \|[\s\S]*?" for case in ("aligned", "misregistered")),
            [sys.executable, "benchmarks/bench_dm_hcipy.py", "--quick", "--case", "both", "--no-checks", *extra],
            "".join(_HCIPY_ERRORS + r"[\s\S]*?" + _HCIPY_STDS + r"[\s\S]*?modes against their deviation from the live mean: slope [+-]"
                    + NUM + r"[\s\S]*?" for _ in range(2)),
            rtol=(0.02,), speed="slow")
      for plan, extra in (("Hadamard", ["--set", "dm_plan.kind=hadamard"]), ("sparse", []))],
    *[Claim(f"DM: the sparse plan with the ladder on HCIPy's whole grid ({case})", "docs/deformable_mirrors.md",
            prefix + r"every live\s+actuator within mode " + NUM + r" %, damping " + NUM + r" %, delay " + NUM
            + r" us\s+\(largest errors; DC gain " + NUM + r" %\), D0\s+" + NUM + r" % rms of max, rms\(error/std\) D\(jw\) " + NUM
            + r", mode " + NUM + r",\s+damping " + NUM + r", delay " + NUM + r", DC gain " + NUM,
            [sys.executable, "benchmarks/bench_dm_hcipy.py", "--case", case, "--no-checks"], _HCIPY_FIGURES, rtol=(0.02,), speed="slow")
      for case, prefix in (("aligned", ""), ("misregistered", r"misregistered`, 439\.9 s\): "))],
    *[Claim(f"DM: the Hadamard plan with the ladder on HCIPy's whole grid ({case})", "docs/deformable_mirrors.md",
            prefix + r": every live actuator within mode " + NUM + r" %, damping " + NUM + r" %, delay " + NUM
            + r" us \(largest errors; DC gain " + NUM + r" %\), D0 " + NUM + r" % rms of max, rms\(error/std\) D\(jw\) " + NUM
            + r", mode " + NUM + r", damping " + NUM + r", delay " + NUM + r", DC gain " + NUM,
            [sys.executable, "benchmarks/bench_dm_hcipy.py", "--case", case, "--no-checks", "--set", "dm_plan.kind=hadamard"],
            _HCIPY_FIGURES, rtol=(0.02,), speed="slow")
      for case, prefix in (("aligned", "Aligned"), ("misregistered", "Misregistered"))],
    *[Claim(f"DM: what the Hadamard plan's mode errors follow on HCIPy's whole grid ({case})", "docs/deformable_mirrors.md",
            (r"correlation \+" + NUM + r" and \+[0-9.]+ over the live actuators; there the gain errors, each actuator's mean over "
             r"frequency taken out, are " + NUM + r" and [0-9.]+ of their stds\)[\s\S]*?reduced chi2 median is " + NUM
             + r" and [0-9.]+ \(every frequency [0-9.]+-[0-9.]+\) and the demultiplexing's chi2/dof " + NUM + r" and [0-9.]+")
            if case == "aligned" else
            (r"correlation \+[0-9.]+ and \+" + NUM + r" over the live actuators; there the gain errors, each actuator's mean over "
             r"frequency taken out, are [0-9.]+ and " + NUM + r" of their stds\)[\s\S]*?reduced chi2 median is [0-9.]+ and " + NUM
             + r" \(every frequency [0-9.]+-[0-9.]+\) and the demultiplexing's chi2/dof [0-9.]+ and " + NUM),
            [sys.executable, "benchmarks/bench_dm_hcipy.py", "--case", case, "--no-checks", "--set", "dm_plan.kind=hadamard"],
            r"mode errors follow the gain errors at 986\.8 Hz \(correlation \+" + NUM + r"[^)]*\), where the gain errors are " + NUM
            + r" of their stds[^;]*; there the spot fits' reduced chi2 median is " + NUM + r" \([^)]*\) and the demultiplexing's "
            r"chi2/dof " + NUM, rtol=(0.02,), speed="slow")
      for case in ("aligned", "misregistered")],
    Claim("DM: the ladder's static shift against the fitted-shift truth (issue 23's cause 1)", "docs/deformable_mirrors.md",
          r"its first 16 patterns\) prints \+" + NUM + r" % \(sd " + NUM + r" % over\s+the patterns\) for `static_slope`[\s\S]*?into\s+\+"
          + NUM + r" % from the truth itself[\s\S]*?\+" + NUM + r" % \(sd [0-9.]+ %\) from the still's Fourier[\s\S]*?and \+" + NUM
          + r" % \(sd [0-9.]+ %\) from the cubic's",
          [sys.executable, "benchmarks/bench_dm_ladder_slope.py"],
          r"static_slope \(the run's cubic\)\s+eps mean \+" + NUM + r" %, sd " + NUM + r" %[\s\S]*?the truth's own \+-0\.05 poke \+" + NUM
          + r" \(sd [0-9.]+\) \+ the still's Fourier derivatives for the truth's tilts at 0\.01 \+" + NUM + r" \(sd [0-9.]+\) \+ the cubic "
          r"over the ladder for the slope at 0 \+" + NUM, rtol=(0.02,), speed="slow"),
    Claim("model stds: the delay's profile likelihood", "docs/reliability.md",
          r"interval reaches " + NUM + r" of the linearised std below and " + NUM + r" above, and the likelihood-ratio z at the "
          r"true delay differs from \(estimate - truth\) / std by at most " + NUM,
          [sys.executable, "benchmarks/bench_model_stds.py", "--seeds", "10", "--profile"],
          r"half-width / linearised std below " + NUM + r" \([^)]*\), above " + NUM + r" \([^)]*\);[^\n]*largest \|z_lin - "
          r"z_profile\| " + NUM, rtol=(0.01, 0.01, 0.5), speed="slow"),
    Claim("DM: the ladder spot fits lost on HCIPy's frames, before and after the second start", "docs/deformable_mirrors.md",
          r"before " + NUM + r" failed and " + NUM + r" of " + NUM + r" left the ladder, " + NUM + r" responses kept with "
          r"rms\(error/std\) " + NUM + r"\s+against the linearised truth; now " + NUM + r" failed, " + NUM + r" left, " + NUM
          + r" kept, " + NUM + r"[\s\S]*?command reaches at most " + NUM + r" of its pattern's top level",
          [sys.executable, "benchmarks/bench_dm_ladder_starts.py"],
          r"\(before\): failed " + NUM + r", out of the ladder " + NUM + r" of " + NUM + r" fits; second start on 0; kept responses "
          + NUM + r", rms\(error/std\) " + NUM + r"[\s\S]*?package: failed " + NUM + r", out of the ladder " + NUM
          + r" of [0-9]+ fits; second start on [0-9]+; kept responses " + NUM + r", rms\(error/std\) " + NUM
          + r"[\s\S]*?top level: at most " + NUM, rtol=(0.02,), speed="slow"),
    Claim("MIMO: every channel against the truth", "README.md",
          r"every channel within " + NUM + r" % and " + NUM + r" deg of the truth",
          [sys.executable, "benchmarks/bench_mimo.py", "--which", "mimo"],
          r"worst channel: \|H\| " + NUM + r"% \(goal 2%\), phase " + NUM + r" deg", rtol=(0.3, 0.3), speed="slow"),
    Claim("DM: the registration fitted to an independent D0", "docs/deformable_mirrors.md",
          r"rms\(error/std\) shift x " + NUM + r", y " + NUM + r", rotation " + NUM + r", magnification " + NUM + r", coupling "
          + NUM + r",\s+all " + NUM,
          [sys.executable, "benchmarks/bench_dm_registration.py"],
          r"rms\(error/std\): shift_x " + NUM + r", shift_y " + NUM + r", rotation_deg " + NUM + r", magnification " + NUM
          + r", coupling " + NUM + r"; all: " + NUM, rtol=(0.01,), speed="slow"),
    Claim("DM: the ladder spot model against the run's on HCIPy spots", "docs/deformable_mirrors.md",
          r"dynamics\): " + NUM + r", \*\*" + NUM + r" %, \+" + NUM + r" rad\*\*",
          [sys.executable, "benchmarks/bench_dm_spot_models.py", "--spots", "0:80:4", "--models", "ladder+delta"],
          r"ladder\+delta +noiseless reduced chi2 median " + NUM + r"; D error rms/max " + NUM + r" %; large slopes: gain [-+][0-9.]+ %, "
          r"phase \+" + NUM, rtol=(0.5, 0.05, 0.1), speed="slow"),
    Claim("multisine: the binned cost of the starts against the rendered one", "docs/multisine.md",
          r"group's " + NUM + r" starts " + NUM + r" s CPU instead of " + NUM + r" s rendering each, costs within " + NUM
          + r" of the rendered ones,\s+the same " + NUM + " best",
          [sys.executable, "benchmarks/bench_search_starts.py"],
          NUM + r" starts: binned cost " + NUM + r" s CPU, rendered " + NUM + r" s CPU \(from 160\); largest relative difference "
          + NUM + r"; the same best " + NUM + r" of 160: True", rtol=(0.0, 1.0, 1.0, 0.1, 0.0), speed="slow"),
]


def _numbers(match) -> list:
    """The match's groups that are numbers, as floats (a group that is a whole line is skipped)."""
    out = []
    for g in match.groups():
        if g is None or len(g) > 30:
            continue
        try:
            out.append(float(g.replace(",", "")))
        except ValueError:
            out.append(g.lower())  # a word (gaussian / kernel): compared exactly, whatever its case
    return out


def _run(claim: Claim, tmp: Path, cache: dict) -> tuple:
    """(exit status, output) of the claim's command; identical commands run once."""
    key = tuple(claim.cmd)
    if key not in cache and claim.speed == "instant" and claim.cmd[:len(TB)] == TB:  # refused before any work: in this process
        import contextlib
        import io

        from torchblur import cli

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            rc = cli.main([str(c).replace("{out}", str(tmp / "instant")) for c in claim.cmd[len(TB):]])
        cache[key] = (rc, buf.getvalue())
    if key not in cache:
        out = tmp / f"run{len(cache)}"
        cmd = [str(c).replace("{out}", str(out)) for c in claim.cmd]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=7200)
        cache[key] = (p.returncode, p.stdout + p.stderr + ((out / "report.txt").read_text() if (out / "report.txt").is_file() else ""))
    return cache[key]


def check(claim: Claim, tmp: Path, cache: dict) -> tuple[bool, str]:
    """(holds, one line): the quoted numbers against the printed ones."""
    text = re.sub(r"\n\s*#?\s*", " ", (ROOT / claim.doc).read_text())  # one line: a sentence or a comment may wrap
    q = re.search(claim.quote, text)
    if q is None:
        return False, "the quoted passage is not in the guide any more (update the claim with the guide)"
    quoted = _numbers(q)
    rc, output = _run(claim, tmp, cache)
    if rc not in claim.exit_codes:
        return False, f"the command failed (exit {rc}): {output.strip().splitlines()[-1:]}"
    p = re.search(claim.printed, output)
    if p is None:
        return False, f"the command did not print the figure ({claim.printed[:60]}...)"
    printed = _numbers(p)
    if len(printed) != len(quoted):
        return False, f"quoted {quoted}, printed {printed}"
    rtol = claim.rtol * len(quoted) if len(claim.rtol) == 1 else claim.rtol
    bad = [(a, b) for a, b, r in zip(quoted, printed, rtol)
           if (a != b if isinstance(a, str) or isinstance(b, str) else abs(a - b) > r * max(abs(a), abs(b)))]
    return not bad, f"quoted {quoted}, printed {printed}" + (f"; outside the tolerance: {bad}" if bad else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--instant", action="store_true", help="only the claims that need no run")
    g.add_argument("--all", action="store_true", help="every claim, the benchmarks included")
    g.add_argument("--list", action="store_true", help="list the claims and their sources, run nothing")
    ap.add_argument("-k", default=None, help="only claims whose name contains this")
    args = ap.parse_args(argv)
    speeds = ("instant",) if args.instant else ("instant", "quick", "slow") if args.all else ("instant", "quick")
    claims = [c for c in CLAIMS if c.speed in speeds and (args.k is None or args.k in c.name)]
    if args.list:
        for c in CLAIMS:
            print(f"{c.doc}: {c.name} [{c.speed}] <- {c.where()}")
        return 0
    failed = 0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        cache: dict = {}
        for c in claims:
            ok, line = check(c, Path(tmp), cache)
            failed += not ok
            print(f"{'ok  ' if ok else 'FAIL'} {c.doc}: {c.name}: {line}", flush=True)
    print(f"{len(claims) - failed} of {len(claims)} claims hold ({', '.join(speeds)}; {time.perf_counter() - t0:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
