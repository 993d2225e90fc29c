"""Command line: ``torchblur <command> ...``.

Commands:
    identify [--config FILE] --out DIR [key=value ...]
                        identify the frequency response and a model of the rig (simulated, or
                        rig.kind=serial rig.port=... rig.frames=...: tcp://, pylon://SERIAL?...
                        or package.module:Class); writes frf.csv, frf.mat, frf.json, model.json,
                        bode.png, residuals.png, config.yaml and report.txt into DIR, and
                        records the raw frames as it goes in DIR/experiment/. DIR holding
                        files of its own (not a torchblur run's) is refused unless --force.
                        With model.direct=true model.json holds the model fitted directly
                        to every image and model_two_step.json the two-step model.
                        --port PORT --frames URL: rig.kind=serial rig.port=PORT
                        rig.frames=URL. A DM config (dm.n_across > 0) writes OUT/dm/, from
                        the simulated DM rig or, with --port/--frames, a DM controller
                        (docs/deformable_mirrors.md, "Over the serial link").
    identify --resume DIR [key=value ...]
                        continue an interrupted run from DIR/experiment/ (rig.*, fit.*,
                        model.* and report.* may be given anew, e.g. the new rig.port).
    fit DIR --out NEW [fit.*=... model.*=... report.*=...]
                        re-fit a recorded run offline; DIR is never written. DIR may
                        also be an outside recording (a folder with frames.csv, TIFF
                        frames and recording.yaml: docs/outside_recordings.md).
    emulator [--config FILE] [key=value ...]
                        a bench emulator on a pseudo-terminal; prints one JSON line with
                        'serial' (for rig.port) and 'frames' (for rig.frames), then serves.
    config [--config FILE] [key=value ...]
                        list every config key with its value (the defaults, or the file and
                        overrides resolved) and its unit; nothing is run.
    demo --out DIR      render a blurred laser spot (the paper's "peanut"), its motion and
                        its alias, and save DIR/demo.png and DIR/demo.json.

Output: the run's messages go to the ``torchblur`` logger, shown on stderr one line each
(``--quiet``: warnings only; progress bars only on a terminal); report.txt holds them all.
The report's table then goes to stdout, or with ``--json`` to stderr while stdout gets exactly
one JSON line: ``out``, ``points``, ``valid_points``, ``max_magnitude_error_pct``,
``max_phase_error_deg``, ``max_error_over_std`` (null without a known truth), ``status`` and
``flags`` (counts by name, :mod:`torchblur.fit.status`), ``elapsed_s``, ``torchblur_version``,
``verdict`` (the verdict line), ``point_flags``, ``flagged_points``, ``trustworthy`` and
``timing_limit_hz`` (:mod:`torchblur.identify.verdict`). ``torchblur --version`` prints the version.

Every identify and fit run ends with one verdict line (:func:`torchblur.identify.verdict.verdict`),
the last line on stdout (on stderr with ``--json``) and in report.txt.

Exit codes: 0 done and trustworthy (or only points limited by the drive), 2 bad input (config,
recording), 3 the rig stopped the run (its recording is saved; resume it), 4 done with points
flagged poor_fit, timing, failed, no_motion or alias, or, with a known truth (a simulated rig),
points or a model beyond 5 std of it (results written; the verdict names them), 130 interrupted
(Ctrl-C; resume it).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from pathlib import Path


def _demo(args) -> int:
    import torch
    from matplotlib.figure import Figure  # not pyplot: the caller's backend stays as it was

    import torchblur as tb

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
    from torchblur.render.camera import CameraModel

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
    from torchblur.identify.read_outputs import DEMO_SCHEMA

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


EXIT_STOPPED = 3
EXIT_INTERRUPTED = 130

EXIT_EPILOG = """\
The run ends with one verdict line: 'verdict: trustworthy: ...', or 'verdict: K of N points
flagged: ...' naming the points the model does not explain (poor fit: reduced chi2 above
fit.poor_fit_chi2; stds inflated, left out of the model fit), those whose timing terms exceed
report.tolerance_deg, the failed ones, and those the drive limit cut (limited; not by
themselves untrustworthy). See docs/reliability.md, "Per-point flags and the verdict". A DM
run's verdict judges its actuators instead ('verdict: K of N actuators flagged: ...': poor fit,
failed; dead and weak named, not flagged): docs/deformable_mirrors.md, "Verdict".

exit status:
  0    done; trustworthy (or only points limited by the drive)
  2    bad input (config, recording)
  3    the rig stopped the run (the recording is saved; resume it)
  4    done with points flagged poor_fit, timing or failed (results written); a DM run:
       actuators flagged poor fit or failed
  130  interrupted (Ctrl-C; resume it)"""


def _resume_hint(root: Path, cfg) -> str:
    rig = " rig.port=<controller port> rig.frames=<camera>" if cfg.rig.kind == "serial" else ""
    return f"torchblur identify --resume {root}{rig}"


def _rig_options(args) -> list[str]:
    """``--port PORT`` / ``--frames URL`` as the overrides they stand for (rig.kind=serial
    rig.port=PORT rig.frames=URL), placed before the user's own ``key=value`` overrides."""
    keys = [f"rig.{k}={getattr(args, k)}" for k in ("port", "frames") if getattr(args, k, None) is not None]
    return ["rig.kind=serial", *keys] if keys else []


def _identify(args) -> int:
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.run_folder import RunLock, check_out_folder
    from torchblur.identify.config import load_config

    args.overrides = _rig_options(args) + list(args.overrides)
    if args.resume is not None:
        return _resume(args)
    if args.out is None:
        print("torchblur identify: error: --out DIR is required (or --resume DIR)", file=sys.stderr)
        return 2
    cfg = load_config(args.config, args.overrides, force=args.force)  # ConfigError (named key) before any work
    out = Path(args.out)
    check_out_folder(out, command="identify", force=args.force)
    if (out / "experiment" / "experiment.json").exists():
        print(f"torchblur identify: error: {out} already holds a recorded run; continue it with "
              f"'torchblur identify --resume {out}' or choose another --out", file=sys.stderr)
        return 2
    if cfg.dm.enabled:  # a deformable-mirror run (dm.n_across > 0): torchblur.identify.dm_plan, recorded in OUT/experiment
        return _run_dm(cfg, out, args)
    (out / "experiment").mkdir(parents=True, exist_ok=True)
    lock = RunLock(out / "experiment")  # held for the run's life: a second run on this folder refuses
    try:
        if (out / "experiment" / "experiment.json").exists():  # created while we waited for the lock
            raise RecordingError(f"--out {out}: already holds a recorded run; resume it with torchblur identify --resume")
        return _run_identify(cfg, out, out / "experiment", args.quiet, as_json=args.json)
    finally:
        lock.release()


def _resume(args) -> int:
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.recording import Experiment
    from torchblur.hardware.run_folder import check_out_folder
    from torchblur.identify.config import load_config, load_dataclass
    from torchblur.identify.run import check_resume_config

    root = Path(args.resume)
    if not root.exists():
        raise RecordingError(f"--resume {root}: does not exist")
    top = root.parent if root.name == "experiment" and (root / "experiment.json").is_file() else root
    done = _finished(top)
    if done is not None and args.out is None:
        print(f"torchblur identify: {top} is a finished run ({done}); nothing to resume. Re-fit it with "
              f"'torchblur fit {top} --out NEW', or start a new run with --out NEW", file=sys.stderr)
        return 0
    exp = Experiment.open(root)  # RecordingError if none or locked; sets aside what it cannot keep
    try:
        if exp.path == root:  # given the experiment folder itself
            root = root.parent
        out = Path(args.out) if args.out is not None else root
        check_out_folder(out, command="identify", own_run=root, force=args.force)
        cfg = load_config(str(exp.path / "config.yaml"), args.overrides, trusted=False, force=args.force)
        check_resume_config(load_dataclass(type(cfg), str(exp.path / "config.yaml"), trusted=False), cfg)  # before connecting
        rep = exp.repaired
        if rep["dropped_groups"] or rep["removed_files"] or rep.get("quarantine"):
            where = f"; set aside (nothing deleted) in {rep['quarantine']}" if rep.get("quarantine") else ""
            print(f"torchblur identify: resume: {len(rep['problems'])} manifest problem(s); group(s) to take again: "
                  f"{', '.join(rep['dropped_groups']) or 'none'}; removed {len(rep['removed_files'])} temporary file(s){where}",
                  file=sys.stderr)
        out.mkdir(parents=True, exist_ok=True)
        if cfg.dm.enabled:  # a DM recording: torchblur.dm resumes it
            return _run_dm(cfg, out, args, record=exp, root=root)
        return _run_identify(cfg, out, exp, args.quiet, root=root, as_json=args.json)
    finally:
        exp.close()


def _run_identify(cfg, out: Path, record, quiet: bool, root: Path | None = None, as_json: bool = False) -> int:
    import time

    import torch

    import torchblur as tb
    from torchblur.identify.config import config_to_yaml
    from torchblur.hardware.errors import HardwareError
    from torchblur.identify.run import identify

    root = out if root is None else root
    stamp = f"torchblur {tb.__version__}, seed {cfg.seed}"
    (out / "config.yaml").write_text(f"# {stamp}\n" + config_to_yaml(cfg))
    torch.manual_seed(cfg.seed)
    exp_dir = record.path if hasattr(record, "path") else Path(record)
    t0 = time.perf_counter()
    try:
        res = identify(cfg, progress=not quiet, record=record)
    except (KeyboardInterrupt, HardwareError) as exc:
        return _stopped(exc, exp_dir, root, cfg)
    elapsed = time.perf_counter() - t0
    try:
        return _write_outputs(cfg, res, out, elapsed, stamp, as_json=as_json).exit_code
    except KeyboardInterrupt as exc:  # the recording is complete; a resume fits it again and writes every output
        return _stopped(exc, exp_dir, root, cfg)


def _finished(root: Path) -> str | None:
    """Why the run in ``root`` needs no resume (its recording complete and report.txt, the
    output written last, there), or None."""
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.recording import Experiment

    report = root / "report.txt"
    if not report.is_file():
        return None
    try:
        exp = Experiment.open(root, writable=False, verify=False)
    except RecordingError:
        return None
    try:
        return "its recording is complete and report.txt was written" if exp.meta.get("status") == "complete" else None
    finally:
        exp.close()


def _stopped(exc, exp_dir: Path, root: Path, cfg) -> int:
    """A run the rig stopped (a HardwareError) or Ctrl-C interrupted: say where its recording
    is and how to resume it; the exit code."""
    if isinstance(exc, KeyboardInterrupt):
        if (exp_dir / "experiment.json").is_file():
            print(f"\ntorchblur identify: interrupted; the recording so far is saved in {exp_dir}; resume with: "
                  f"{_resume_hint(root, cfg)}", file=sys.stderr)
        else:
            print(f"\n{_NOTHING_RECORDED}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if (exp_dir / "manifest.jsonl").exists():
        print(f"torchblur identify: stopped: {exc}\nThe recording so far is saved in {exp_dir}.\n"
              f"Resume with:\n  {_resume_hint(root, cfg)}", file=sys.stderr)
    else:
        print(f"torchblur identify: stopped before anything was recorded: {exc}", file=sys.stderr)
    return EXIT_STOPPED


def _run_dm(cfg, out: Path, args, *, record=None, root: Path | None = None, rig=None) -> int:
    """A DM run (:func:`torchblur.identify.dm_report.run_cli`): new (recorded in ``OUT/experiment``),
    resumed (``record``, a writable Experiment) or re-fitted (``record`` read-only, ``rig`` its
    ReplayRig); stopped by the rig or interrupted, as :func:`_run_identify`."""
    from torchblur.identify.dm_report import run_cli as run_dm
    from torchblur.hardware.errors import HardwareError

    cfg, base_dir = _recorded_table(cfg, out if record is None else (out if root is None else root), new=record is None)
    try:
        return run_dm(cfg, out, quiet=args.quiet, as_json=args.json, record=record, rig=rig, base_dir=base_dir)
    except (KeyboardInterrupt, HardwareError) as exc:
        return _stopped(exc, out / "experiment" if record is None else record.path, out if root is None else root, cfg)


TABLE_COPY = "experiment/actuator_table.csv"  # a DM run's own copy of its dm.actuator_table


def _recorded_table(cfg, root: Path, *, new: bool):
    """``(cfg, base_dir)`` for a DM run's ``dm.actuator_table``: a new run copies the user's file
    (read under the opening rule) into its recording as :data:`TABLE_COPY` and names that, so a
    recording never names a file outside itself; a resumed or re-fitted one (its config is the
    recording's, untrusted) must name a file inside its run folder ``root``.

    Raises:
        RecordingError: naming ``dm.actuator_table`` (a recorded path outside the run folder).
        ConfigError: the user's table cannot be read (not a regular file, too large).
    """
    import dataclasses

    from torchblur.dm.mirror import TABLE_MAX_BYTES
    from torchblur.errors import ConfigError
    from torchblur.files import read_bounded, resolve_inside
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.recording import atomic_write_bytes

    path = cfg.dm.actuator_table
    if not path:
        return cfg, None
    if not new:
        resolve_inside(root, path, "dm.actuator_table (in the recorded config.yaml)", error=RecordingError)
        return cfg, str(root)
    data = read_bounded(path, TABLE_MAX_BYTES, f"dm.actuator_table: {path}", error=ConfigError)
    (root / "experiment").mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(root / TABLE_COPY, data)
    return dataclasses.replace(cfg, dm=dataclasses.replace(cfg.dm, actuator_table=TABLE_COPY)), str(root)


def _source(exp, args) -> str:
    """``source.json`` of a re-fit: the recording, its status and frames, the overrides."""
    import torchblur as tb

    from torchblur.identify.read_outputs import SOURCE_SCHEMA

    return json.dumps({"schema": SOURCE_SCHEMA[0], "schema_version": SOURCE_SCHEMA[1][-1],
                       "recording": str(exp.path), "status": exp.meta.get("status"), "frames": len(exp.lines),
                       "overrides": list(args.overrides), "torchblur_version": tb.__version__}, indent=2)


def _fit(args) -> int:
    import time

    import torchblur as tb
    from torchblur.identify.config import config_to_yaml, load_config, load_dataclass
    from torchblur.hardware.recording import Experiment, ReplayRig
    from torchblur.hardware.run_folder import check_out_folder
    from torchblur.identify.run import check_resume_config, identify

    if _is_outside(args.dir):
        return _fit_outside(args)
    exp = Experiment.open(args.dir, writable=False)
    root = exp.path.parent if exp.path.name == "experiment" else exp.path
    out = Path(args.out)
    check_out_folder(out, command="fit", force=args.force)
    r_root, r_out, r_exp = root.resolve(), out.resolve(), exp.path.resolve()
    for protected in {r_root, r_exp}:
        if r_out == protected or protected in r_out.parents:
            print(f"torchblur fit: error: --out {out} is inside the recorded run {root}; the original is never written, "
                  f"choose another folder", file=sys.stderr)
            return 2
    recorded = load_dataclass(type(load_config()), str(exp.path / "config.yaml"), trusted=False)
    cfg = load_config(str(exp.path / "config.yaml"), args.overrides, trusted=False, force=True)  # the recording is made
    if recorded.dm.enabled:  # a DM recording: torchblur.dm re-fits it (dm_plan.support_threshold may change too)
        from torchblur.identify.dm_record import check_refit_config

        check_refit_config(recorded, cfg)
        out.mkdir(parents=True, exist_ok=True)
        (out / "source.json").write_text(_source(exp, args))
        return _run_dm(cfg, out, args, record=exp, root=root, rig=ReplayRig(exp))
    check_resume_config(recorded, cfg, allowed=("fit", "model", "report"))
    out.mkdir(parents=True, exist_ok=True)
    stamp = f"torchblur {tb.__version__}, seed {cfg.seed}, re-fit of {exp.path}"
    (out / "config.yaml").write_text(f"# {stamp}\n" + config_to_yaml(cfg))
    t0 = time.perf_counter()
    res = identify(cfg, rig=ReplayRig(exp), record=exp, progress=not args.quiet)
    elapsed = time.perf_counter() - t0
    (out / "source.json").write_text(_source(exp, args))
    return _write_outputs(cfg, res, out, elapsed, stamp, as_json=args.json, source="re-fit").exit_code


def _is_outside(path) -> bool:
    """``path`` is an outside recording (a ``frames.csv``); RecordingError when it is neither
    that nor a torchblur run."""
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.outside import CSV_NAME, is_outside_recording

    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: does not exist")
    if is_outside_recording(p):
        return True
    if not any((q / "experiment.json").is_file() for q in (p, p / "experiment")):
        raise RecordingError(f"{p}: neither a torchblur run (no experiment.json in it or in its experiment/) nor an outside "
                             f"recording (no {CSV_NAME}; docs/outside_recordings.md)")
    return False


def _fit_outside(args) -> int:
    """``torchblur fit FOLDER`` of an outside recording (docs/outside_recordings.md): read and
    check it, run the identification's stages on it, write the same outputs as a re-fit."""
    import time

    import torchblur as tb
    from torchblur.hardware.outside import read_outside_recording
    from torchblur.hardware.run_folder import check_out_folder
    from torchblur.identify.config import config_to_yaml
    from torchblur.identify.dm_outside import is_dm_recording
    from torchblur.identify.outside import identify_outside, outside_config

    src, out = Path(args.dir).resolve(), Path(args.out)
    check_out_folder(out, command="fit", force=args.force)
    r_out = out.resolve()
    if r_out == src or src in r_out.parents:
        print(f"torchblur fit: error: --out {out} is inside the recording {args.dir}; it is never written, choose another folder",
              file=sys.stderr)
        return 2
    if is_dm_recording(src):  # a deformable mirror's: patterns.csv beside frames.csv
        return _fit_dm_outside(args, src, out)
    rec = read_outside_recording(src)  # RecordingError naming file, line and column
    cfg = outside_config(rec, args.overrides)
    out.mkdir(parents=True, exist_ok=True)
    seeded = any(str(o).partition("=")[0] == "seed" for o in args.overrides)  # the recording itself has no seed
    stamp = f"torchblur {tb.__version__}{f', seed {cfg.seed}' if seeded else ''}, fit of the outside recording {src}"
    (out / "config.yaml").write_text(f"# {stamp}\n" + config_to_yaml(cfg))
    t0 = time.perf_counter()
    res = identify_outside(rec, cfg, progress=not args.quiet)
    elapsed = time.perf_counter() - t0
    from torchblur.identify.read_outputs import SOURCE_SCHEMA

    (out / "source.json").write_text(json.dumps({"schema": SOURCE_SCHEMA[0], "schema_version": SOURCE_SCHEMA[1][-1],
                                                 "outside_recording": str(src), "frames": rec.n_frames, "points": len(rec.points),
                                                 "overrides": list(args.overrides), "torchblur_version": tb.__version__}, indent=2))
    return _write_outputs(cfg, res, out, elapsed, stamp, as_json=args.json, source="outside").exit_code


def _fit_dm_outside(args, src: Path, out: Path) -> int:
    """``torchblur fit FOLDER`` of an outside DM recording (docs/outside_recordings.md, "Deformable-mirror
    recordings"): read and check it, fit it with the DM run's own stages, write the DM run's outputs."""
    import torchblur as tb
    from torchblur.identify.dm_outside import dm_recording_config, read_dm_recording, run_recording
    from torchblur.identify.read_outputs import SOURCE_SCHEMA

    rec = read_dm_recording(src)  # RecordingError naming file, line and column
    cfg = dm_recording_config(rec, args.overrides)
    out.mkdir(parents=True, exist_ok=True)
    (out / "source.json").write_text(json.dumps({"schema": SOURCE_SCHEMA[0], "schema_version": SOURCE_SCHEMA[1][-1],
                                                 "outside_recording": str(src), "frames": rec.n_frames, "points": len(rec.freq_hz),
                                                 "overrides": list(args.overrides), "torchblur_version": tb.__version__}, indent=2))
    return run_recording(rec, cfg, out, quiet=args.quiet, as_json=args.json)


def _config(args) -> int:
    """``torchblur config``: every key, its resolved value and its unit, one line each on stdout."""
    from torchblur.identify.config import load_config
    from torchblur.identify.config_keys import format_config_keys

    print(format_config_keys(load_config(args.config, list(args.overrides), force=True)), end="")
    return 0


def _emulator(args) -> int:
    from torchblur.hardware.emulator import main as emulator_main

    try:
        return emulator_main(args.overrides, config_path=args.config)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


def _write_outputs(cfg, res, out: Path, elapsed: float, stamp: str, as_json: bool = False, source: str = "run"):
    """frf.csv, frf.mat, frf.json, model.json, bode.png, residuals.png, report.txt (the verdict
    its last line); then the report's table (the log lines were shown as they came), what was
    written and the verdict line, on stdout, or with ``as_json`` on stderr and one JSON summary
    line (:func:`_summary`) on stdout. ``source``: "run" (frames acquired now), "re-fit" (of a
    recording) or "outside" (an outside recording). report.txt is written last: a run whose
    report.txt is there is finished. Returns the :class:`~torchblur.identify.verdict.Verdict`."""
    import torchblur as tb

    from torchblur.identify.assemble import mark_limited
    from torchblur.identify.verdict import verdict

    frf = res.frf  # immutable: a copy with the run's stamp and units (the Bode plot's axes) in its meta
    meta = {"output_unit": "px", "input_unit": "input unit", **frf.meta, "torchblur_version": tb.__version__, "seed": int(cfg.seed)}
    frf = res.frf = mark_limited(frf.replace(meta=meta), getattr(res, "limited", None))
    v = verdict(frf, cfg, motion_px=_motion_px(res), model=getattr(res, "model", None), direct=getattr(res, "direct_model", None),
                expected=("two-step", "direct") if cfg.model.direct else ("two-step",), truth=getattr(res, "truth", None))
    frf.to_csv(out / "frf.csv", extra_columns={"torchblur_version": tb.__version__, "seed": cfg.seed})
    frf.to_mat(out / "frf.mat")
    frf.to_json(out / "frf.json")
    _write_models(cfg, res, out, v.models)
    _write_figures(cfg, res, out, stamp)
    log, table = _report(cfg, res, elapsed, stamp, source)
    (out / "report.txt").write_text(log + table + "\n" + v.line + "\n")
    human = sys.stderr if as_json else sys.stdout
    print(table, end="", file=human)
    print(f"wrote {', '.join(sorted(p.name for p in out.iterdir()))} in {out}", file=human)
    print(v.line, file=human, flush=True)
    if as_json:
        print(json.dumps({**_summary(res, out, elapsed, cfg.fit.poor_fit_chi2), **_verdict_summary(v)}), flush=True)
    return v


def _motion_px(res):
    """[O, I, F] motion each point reached (px): |H| times the point's input amplitude; None
    where the amplitudes do not map onto the response's points."""
    import numpy as np

    frf = res.frf
    n_o, n_i, n_f = frf.response.shape
    a = getattr(res, "amplitude", None)
    a = None if a is None else np.asarray(a, dtype=np.float64).reshape(-1)
    if a is None or a.size != n_i * n_f:
        return None
    return frf.magnitude * a.reshape(1, n_i, n_f)


def _verdict_summary(v) -> dict:
    """The --json summary's verdict keys: ``verdict`` (the line), ``point_flags`` (counts of
    the response's points by flag), ``flagged_points``, ``trustworthy`` and ``timing_limit_hz``
    (null: none, or unknown)."""
    d = v.to_dict()
    return {"verdict": v.line, "point_flags": {k: d[k] for k in ("poor_fit", "timing", "failed", "limited", "no_motion", "alias")},
            "beyond_truth": d["beyond_truth"], "model_beyond_truth": d["model_beyond_truth"],
            "flagged_points": v.flagged, "timing_limit_hz": d["timing_limit_hz"], "trustworthy": v.trustworthy}


def _write_models(cfg, res, out: Path, judged=()) -> None:
    """model.json (and, with ``model.direct``, model_two_step.json), each model with the
    verdict's ``judgement`` (:mod:`torchblur.sysid.model_check`, one per channel) and
    ``model_passed``; a model that failed has its stds inflated (``std_factor``). With
    ``model.direct``, model.json holds the direct model unless it failed and the two-step one
    passed: then the two-step model, the direct one under ``rejected_direct_model``."""
    import torchblur as tb
    from torchblur.sysid.model_check import inflate

    two_j = [j for j in judged if j.name.startswith("two-step")]
    d_j = [j for j in judged if not j.name.startswith("two-step")]
    model = {"torchblur_version": tb.__version__, "seed": int(cfg.seed)}
    if res.model is not None:
        model.update(inflate(res.model, two_j).to_dict())
        model.update(_left_out_points(cfg, res.frf))
        model.update(judgement=[j.to_dict() for j in two_j], model_passed=bool(two_j) and all(j.passed for j in two_j))
    else:
        model["error"] = "the model fit failed; see report.txt"
    direct = getattr(res, "direct_model", None)
    if cfg.model.direct:
        # model.json holds the direct model; the two-step one it started from is kept beside it.
        (out / "model_two_step.json").write_text(json.dumps(model, indent=2))
        two_step, model = model, {"torchblur_version": tb.__version__, "seed": int(cfg.seed)}
        if direct is not None:
            model.update(inflate(direct, d_j).to_dict())
            model.update(judgement=[j.to_dict() for j in d_j], model_passed=bool(d_j) and d_j[0].passed)
            if not model["model_passed"] and two_step.get("model_passed"):
                model = {**two_step, "rejected_direct_model": model}
        elif two_step.get("model_passed"):
            model = {**two_step, "direct_model_error": "the direct fit failed or was skipped; see report.txt"}
        else:
            model["error"] = "the direct fit failed or was skipped; see report.txt (the two-step model is in model_two_step.json)"
    (out / "model.json").write_text(json.dumps(model, indent=2))


def _left_out_points(cfg, frf) -> dict:
    """model.json's ``left_out_points`` (the poor-fit and alias points the model was not fitted to:
    freq_hz, output, input, reduced_chi2, flags) and ``poor_fit_points_kept`` (channels where too few
    points would have remained: output, input, count) by
    :func:`~torchblur.identify.model.model_exclusions`."""
    import numpy as np

    from torchblur.identify.model import model_exclusions
    from torchblur.sysid.flags import flag_names

    left_out, kept = model_exclusions(frf, cfg)
    pts = [{"freq_hz": float(frf.freq_hz[k]), "output": frf.output_labels[o], "input": frf.input_labels[i],
            "reduced_chi2": float(frf.reduced_chi2[o, i, k]), "flags": flag_names(frf.flags[o, i, k])}
           for o, i, k in zip(*np.nonzero(left_out))]
    return {"left_out_points": pts, "poor_fit_points_kept": [{"output": o, "input": i, "count": n} for o, i, n in kept]}


def _write_figures(cfg, res, out: Path, stamp: str) -> None:
    """bode.png (with the truth where known), residuals.png (the worst fits) and ptc.png; none
    with ``report.figures=false`` (every number file is written all the same)."""
    if not cfg.report.figures:
        return
    _write_bode(cfg, res, out, stamp)
    _write_residuals(res, out, stamp)
    _write_ptc_figure(cfg, res, out, stamp)


def _write_bode(cfg, res, out: Path, stamp: str) -> None:
    """bode.png: the response, the model, the truth where known."""
    from torchblur.sysid.plots import bode_figure

    frf = res.frf
    truth = None
    if res.truth is not None:
        if getattr(res, "spots", None) is not None:
            truth = res.truth  # [O, I, F] at the measured points
        else:
            from torchblur.identify.run import plant_of

            truth = plant_of(cfg).frequency_response
    frame_rate = None if cfg.rig.kind == "outside" else float(cfg.camera.frame_rate_hz)  # an outside recording's is unknown
    fig = bode_figure(frf, model=res.model, truth=truth, stamp=stamp, frame_rate_hz=frame_rate)
    fig.savefig(out / "bode.png", dpi=110 if frf.n_outputs <= 2 else 80, metadata={"Description": stamp})


def _write_residuals(res, out: Path, stamp: str) -> None:
    """residuals.png: the worst fits' data, model and residual."""
    import numpy as np

    from torchblur.sysid.flags import flag_names
    from torchblur.sysid.plots import residual_figure

    exposures = None
    if hasattr(res, "residual_panels"):  # multisine: one panel per image set
        data, models, labels = res.residual_panels(3)
        reason = f"the {len(labels)} groups with the largest fit cost per pixel"
    else:
        cost = res.fit.cost.reshape(-1).numpy()
        n_pix = res.images.shape[-3] * res.images.shape[-2] * res.images.shape[-1]
        worst = [int(q) for q in np.argsort(np.nan_to_num(cost / max(1, n_pix), nan=-np.inf))[-3:][::-1]]
        masks = _problem_flags(res)
        extra = _one_per_flag(masks, worst)
        data, models, labels, exposures = _fitted_images(res, worst + extra)
        labels = [lab + (f" [{flag_names(masks[q])}]" if masks[q] else "") for lab, q in zip(labels, worst + extra)]
        reason = f"the {len(worst)} points with the largest fit cost per pixel" + (
            f", and {len(extra)} more so that each flag kind is shown" if extra else "")
    sigma = None
    if getattr(res, "noise", None) is not None:  # the residual in units of the noise the fit weighed each pixel by
        import torch

        sigma = res.noise.std(torch.as_tensor(models, dtype=torch.float64)).numpy()
        sigma = sigma if np.all(sigma > 0) else None  # a noiseless camera model: the residual in e- instead
    fig = residual_figure(data, models, labels, stamp=stamp, unit="e-", exposures=exposures, reason=reason, sigma=sigma)
    fig.savefig(out / "residuals.png", dpi=90, metadata={"Description": stamp})


def _write_ptc_figure(cfg, res, out: Path, stamp: str) -> None:
    """ptc.png: the photon transfer curve the calibration measured (where it did), with camera.gain's line."""
    ptc = getattr(res, "ptc", None)
    if ptc is None:
        return
    from torchblur.image.photon_transfer import photon_transfer_figure

    fig = photon_transfer_figure(ptc, configured_gain=float(cfg.camera.gain))
    fig.savefig(out / "ptc.png", dpi=90, metadata={"Description": stamp})


def _problem_flags(res):
    """The flag mask (:mod:`torchblur.sysid.flags`) of each problem of ``res.fit`` (flat
    index), int [n]: its point's flags, OR-ed over the outputs of its input."""
    import numpy as np

    frf = res.frf
    F = len(frf.omega)
    if res.fit.amplitude.dim() == 1:
        return np.asarray(frf.flags[0, 0], dtype=np.int64)
    P = res.fit.amplitude.shape[1]
    per_point = np.bitwise_or.reduce(np.asarray(frf.flags, dtype=np.int64), axis=0)  # [I, F]
    return np.array([per_point[(q // P) // F, (q // P) % F] for q in range(res.fit.cost.numel())], dtype=np.int64)


def _one_per_flag(masks, shown: list, most: int = 3) -> list:
    """Problems (flat indices) to show besides ``shown`` so that each flag kind present in
    ``masks`` appears at least once (the first problem carrying it), at most ``most``."""
    extra = []
    for b in range(63):
        bit = 1 << b
        if len(extra) >= most or not any(int(m) & bit for m in masks) or any(int(masks[q]) & bit for q in shown + extra):
            continue
        extra.append(next(q for q, m in enumerate(masks) if int(m) & bit))
    return extra


def _summary(res, out: Path, elapsed: float, threshold: float | None = None) -> dict:
    """The ``--json`` line: out dir, points (valid of all), the largest errors against the
    truth where it is known (else null), the fits' status and flag counts by name, the fit
    quality against ``threshold`` (``fit.poor_fit_chi2``), elapsed s, version."""
    import numpy as np

    import torchblur as tb
    from torchblur.fit.status import FLAGS, STATUS

    from torchblur.identify.read_outputs import SUMMARY_SCHEMA

    frf = res.frf
    doc = {"schema": SUMMARY_SCHEMA[0], "schema_version": SUMMARY_SCHEMA[1][-1],
           "out": str(out), "points": int(frf.valid.size), "valid_points": int(frf.valid.sum()),
           "max_magnitude_error_pct": None, "max_phase_error_deg": None, "max_error_over_std": None}
    if res.truth is not None:
        em, ep, z = frf.errors_against(res.truth)  # NaN where there is no true motion
        for key, v in (("max_magnitude_error_pct", np.abs(em) * 100), ("max_phase_error_deg", np.degrees(np.abs(ep))),
                       ("max_error_over_std", z)):
            v = v[np.isfinite(em) & np.isfinite(v)]
            doc[key] = float(v.max()) if v.size else None
    doc["status"], doc["flags"] = _fit_counts(res.fit, STATUS, FLAGS)
    doc.update(_fit_quality(res.fit, threshold)[0])
    doc.update({"elapsed_s": round(float(elapsed), 3), "torchblur_version": tb.__version__})
    return doc


def _fit_counts(fits, status_names: dict, flag_names: dict) -> tuple[dict, dict]:
    """``({status name: count}, {flag name: count})`` over every fit of the run (a fit result
    or a list of them, as the multisine plan has); zero counts left out."""
    import numpy as np

    fits = fits if isinstance(fits, (list, tuple)) else [fits]
    codes = [np.asarray(f.status).reshape(-1) for f in fits if getattr(f, "status", None) is not None]
    bits = [np.asarray(f.flags).reshape(-1) for f in fits if getattr(f, "flags", None) is not None]
    codes = np.concatenate(codes) if codes else np.zeros(0, dtype=int)
    bits = np.concatenate(bits) if bits else np.zeros(0, dtype=int)
    status = {status_names.get(int(c), str(int(c))): int((codes == c).sum()) for c in np.unique(codes)}
    flags = {name: int(((bits.astype(np.int64) & bit) != 0).sum()) for bit, name in flag_names.items()}
    return status, {k: v for k, v in flags.items() if v}


#: a point whose fit has a reduced chi2 above this is reported as one the model does not explain
POOR_FIT_CHI2 = 1.5


def _reduced_chi2(fits):
    """Every fitted problem's reduced chi2, flat (NaN where unknown: no noise given, not l2)."""
    import numpy as np

    fits = fits if isinstance(fits, (list, tuple)) else [fits]
    vals = []
    for f in fits:
        r = getattr(f, "reduced_chi2", None)
        if r is None:
            r = getattr(f, "extras", {}).get("reduced_chi2")
        if r is not None:
            vals.append(np.asarray(r, dtype=float).reshape(-1))
    return np.concatenate(vals) if vals else np.zeros(0)


def _fit_quality(fits, threshold: float | None = None) -> tuple[dict, str | None]:
    """``({max_reduced_chi2, poor_fit_problems}, one report line or None)``: whether the model
    explains the images to their noise (reduced chi2 at most ``threshold``, the run's
    ``fit.poor_fit_chi2``; default :data:`POOR_FIT_CHI2`). The stds hold only where it does."""
    import numpy as np

    red = _reduced_chi2(fits)
    red = red[np.isfinite(red)]
    if not red.size:
        return {"max_reduced_chi2": None, "poor_fit_problems": None}, None
    threshold = POOR_FIT_CHI2 if threshold is None else float(threshold)
    poor = int((red > threshold).sum())
    doc = {"max_reduced_chi2": float(red.max()), "poor_fit_problems": poor}
    if poor:
        line = (f"warning: {poor} of {red.size} fitted problems have a reduced chi2 above {threshold:g} (max "
                f"{red.max():.2f}): the model does not explain their images, and their stds understate the error")
    else:
        line = (f"fit quality: reduced chi2 median {np.median(red):.2f}, max {red.max():.2f} over {red.size} fitted problems "
                f"(all below {threshold:g}: the model explains the images to their noise)")
    return doc, line


def _fitted_images(res, idx):
    """The first frame of problems ``idx`` (flat indices of ``res.fit``), its fitted model, a
    label and its exposure each (for the residual figure): ``(data [n, h, w], models [n, h, w],
    labels, exposures)``, an exposure like ``"exposure 1 of 2 (0.5-3 ms)"``."""
    import numpy as np
    import torch

    import torchblur as tb

    frf = res.frf
    single = res.fit.amplitude.dim() == 1
    F = len(frf.omega)
    P = 1 if single else res.fit.amplitude.shape[1]
    data, out, labels, exposures = [], [], [], []
    for q in idx:
        q = int(q)
        j, p = divmod(q, P)
        k = j % F
        if single:
            img_d = res.images[j, 0]
            w_point = res.windows[j]
            label = f"{frf.freq_hz[k]:.4g} Hz"
        else:
            ii = j // F
            img_d = res.images[ii, k, p, 0]
            w_point = res.windows[ii, k]
            label = f"{frf.freq_hz[k]:.4g} Hz, input {res.inputs[ii]}" + (f", spot s{p}" if res.spots is not None else "")
        data.append(img_d.numpy())
        labels.append(label)
        w = w_point[0]
        exposures.append(_exposure_label(w_point))
        fit = res.fit
        at = (j,) if single else (j, p)
        if not bool(fit.converged[at]):
            out.append(np.zeros_like(img_d.numpy()))
            continue
        if single:
            amp = torch.stack([fit.amplitude[j], torch.zeros_like(fit.amplitude[j])])
            ph = fit.phase[j].expand(2)
            psf = res.psf
        else:
            amp, ph = fit.amplitude[j, p], fit.phase[j, p]
            psf = res.spots.psf_in_crops()[p] if res.spots is not None else res.psf
        scale = res.power[j] * (fit.scale[at] if fit.scale is not None else 1.0)
        psf = tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * scale)
        om = 2 * math.pi * float(frf.freq_hz[k])
        img = tb.render_blur(tb.Sinusoid(amp, ph, om), psf, w, height=img_d.shape[-2], width=img_d.shape[-1])
        if fit.background is not None:
            img = img + fit.background[at]
        out.append(img.detach().numpy())
    return np.stack(data), np.stack(out), labels, exposures


def _exposure_label(window, index: int = 0) -> str:
    """``"exposure e of E, L ms long (start-end ms), image r of R"`` of image ``index`` of one
    point's ``window`` ``[E*R]``: E distinct exposures (start, duration), each repeated R times
    in a row (the sweep's layout)."""
    start, dur = window.start.reshape(-1).tolist(), window.duration.reshape(-1).tolist()
    distinct = list(dict.fromkeys(zip(start, dur)))
    R = max(1, len(start) // max(1, len(distinct)))
    e = distinct.index((start[index], dur[index]))
    r = sum(1 for q in range(index) if (start[q], dur[q]) == distinct[e])
    s, d = start[index] * 1e3, dur[index] * 1e3
    return f"exposure {e + 1} of {len(distinct)}, {d:.3g} ms long ({s:.3g}-{s + d:.3g} ms), image {r + 1} of {R}"


def _method_line(cfg, res) -> str:
    """What was done: the route, the loss and the PSF (the gain is on the dark line above)."""
    from torchblur.render.psf import KernelPSF

    route = (f"multisine ({cfg.excitation.tones} tones per image set)" if cfg.excitation.kind == "multisine"
             else f"sine sweep, {len(cfg.sweep.exposures)} exposure(s) x {cfg.sweep.images_per_point} image(s) per point")
    psf = ("a measured kernel" if isinstance(res.psf, KernelPSF) else
           "a Gaussian per spot" if getattr(res, "spots", None) is not None else "a Gaussian (point-sampled)")
    model = "fitted directly to every image (model.direct)" if cfg.model.direct else "two-step (fitted to the response)"
    return f"method: {route}; fit.loss={cfg.fit.loss}; PSF {psf} (fit.psf={cfg.fit.psf}); model {model}"


def _report(cfg, res, elapsed, stamp, source: str = "run") -> tuple[str, str]:
    """report.txt in two parts: ``(title, table)``: the title and the run's log (shown on the
    terminal as it came), then the table of points, the errors against the truth, the models
    and the timing."""
    import numpy as np

    frf = res.frf
    title = "\n".join([f"torchblur identify report ({stamp})", "", *res.log]) + "\n"
    lines = []
    truth = None
    if res.truth is not None:
        truth = res.truth if res.truth.ndim == 3 else res.truth[None, None]
        err_m, err_p, err_z = frf.errors_against(truth)  # [O, I, F]; NaN where the truth is 0
    head = (f"{'freq_hz':>10} {'|H|':>10} {'+-':>9} {'phase_deg':>10} {'+-':>7}"
            + (f" {'|H| err %':>9} {'ph err deg':>10} {'err/std':>8}" if truth is not None else ""))
    summary = []
    for o in range(frf.n_outputs):
        for i in range(frf.n_inputs):
            if not frf.is_siso:
                lines += ["", f"output {frf.output_labels[o]} from input {frf.input_labels[i]}:"]
            lines += ["", head] if frf.is_siso else [head]
            for k in range(len(frf.omega)):
                m, ms = frf.magnitude[o, i, k], frf.magnitude_std[o, i, k]
                p, ps = np.degrees(frf.phase[o, i, k]), np.degrees(frf.phase_std[o, i, k])
                line = f"{frf.freq_hz[k]:10.4g} {m:10.5g} {ms:9.2g} {p:10.3f} {ps:7.3f}"
                if truth is not None:
                    line += f" {err_m[o, i, k] * 100:9.3f} {np.degrees(err_p[o, i, k]):10.3f} {err_z[o, i, k]:8.2f}"
                lines.append(line)
            if truth is not None:
                em, ep, z = np.abs(err_m[o, i]), np.degrees(np.abs(err_p[o, i])), err_z[o, i]
                with np.errstate(invalid="ignore"):
                    summary.append((frf.output_labels[o], frf.input_labels[i], np.nanmax(em) if np.isfinite(em).any() else np.nan,
                                    np.nanmax(ep) if np.isfinite(ep).any() else np.nan, np.nanmax(z) if np.isfinite(z).any() else np.nan))
    if summary:
        if frf.is_siso:
            _, _, em, ep, z = summary[0]
            lines += ["", f"against the truth: max |H| error {em * 100:.3f}% (goal 1%), max phase error "
                          f"{ep:.3f} deg (goal 1 deg), max error/std {z:.2f} (goal 5){_goal_note(em, ep, z, 0.01, 1.0)}"]
        else:
            lines += ["", "against the truth, per channel (goal 2% and 2 deg):"]
            for (out_l, in_l, em, ep, z), (o, i) in zip(summary, [(o, i) for o in range(frf.n_outputs) for i in range(frf.n_inputs)]):
                if np.all(np.abs(truth[o, i]) == 0):  # no true motion on this channel: say how small the estimate is
                    lines.append(f"  {out_l:>6} from {in_l}: true response 0, max |H| {np.nanmax(frf.magnitude[o, i]):.3g} "
                                 f"(max |H| / std {np.nanmax(frf.magnitude[o, i] / frf.magnitude_std[o, i]):.2f})")
                    continue
                lines.append(f"  {out_l:>6} from {in_l}: max |H| error {em * 100:.3f}%, max phase error {ep:.3f} deg, "
                             f"max error/std {z:.2f}{_goal_note(em, ep, z, 0.02, 2.0)}")
    quality = _fit_quality(res.fit, cfg.fit.poor_fit_chi2)[1]
    if quality is not None:
        lines += ["", quality]
    from torchblur.identify.model import model_parameter_lines
    from torchblur.identify.verdict import report_lines

    lines += ["", *report_lines(frf, cfg)]
    if res.model is not None and res.model.is_siso:
        m = res.model
        lines += ["", f"model: {m.n_poles} poles, {m.n_zeros} zeros, delay {m.delay_s * 1e6:.3f} us, reduced chi2 "
                      f"{m.reduced_chi2:.3f} (dof {m.dof}), rms relative error {m.rms_relative_error:.2e}",
                  f"  num = {list(map(float, m.num))}", f"  den = {list(map(float, m.den))}"]
        lines += model_parameter_lines(m)
        if cfg.model.direct:
            lines.append("  (the two-step model: model_two_step.json)")
    elif res.model is not None:
        m = res.model
        for o, out_l in enumerate(m.output_labels):
            for i, in_l in enumerate(m.input_labels):
                lines += ["", f"model {out_l} from {in_l}: {m.n_poles[o][i]} poles, {m.n_zeros[o][i]} zeros, delay "
                              f"{m.delay_s[o][i] * 1e6:.3f} us, reduced chi2 {m.reduced_chi2[o][i]:.3f} (dof {m.dof[o][i]}), "
                              f"rms relative error {m.rms_relative_error[o][i]:.2e}",
                          f"  num = {list(map(float, m.num[o][i]))}", f"  den = {list(map(float, m.den[o][i]))}"]
                lines += model_parameter_lines(m, o, i)
    d = getattr(res, "direct_model", None)
    if d is not None:
        lines += ["", f"direct model ({d.form}, fitted to every image; model.json): delay {d.delay_s * 1e6:.3f} us, reduced chi2 "
                      f"{d.reduced_chi2:.3f} (dof {d.dof}), {d.n_iter} iterations, converged {d.converged}, "
                      f"{int(d.used.sum())} points used, {d.n_excluded} excluded",
                  f"  num = {d.num}", f"  den = {d.den}"]
        for mode in d.modal_parameters():
            lines.append(f"  mode: {mode['freq_hz']:.3f} +- {mode['freq_hz_std']:.3f} Hz, damping {mode['zeta']:.4f} +- "
                         f"{mode['zeta_std']:.4f}, gain {mode['gain']:.4g} +- {mode['gain_std']:.2g}")
        from torchblur.sysid.model_check import judge_fit

        for j in judge_fit(d, "direct"):
            if not j.passed:
                lines.append(f"  the direct model fails the verdict's rule ({j.reason}): the stds above understate its error; "
                             "see the verdict for the model model.json holds")
    elif cfg.model.direct:
        lines += ["", "direct model: none (see the log above); model.json holds the two-step model where it passed the verdict's "
                      "rule (else the error), model_two_step.json the two-step model"]
    what = {"re-fit": "re-fit of recorded frames: no acquisition", "outside": "fit of an outside recording: no acquisition"}.get(
        source, "simulated acquisition and fitting" if cfg.rig.kind == "simulated" else "acquisition and fitting")
    t = getattr(res, "timing", {}) or {}
    lines += ["", _method_line(cfg, res), f"elapsed {elapsed:.1f} s ({what})"]
    if t:
        sweep = "sweep" if source == "run" else "reading the sweep"
        lines.append(f"  calibration {t['calibration_s']:.2f} s, {sweep} {t['sweep_s']:.2f} s, fitting {t['fit_s']:.2f} s in "
                     f"{t['fit_chunks']} chunk(s) of which {t['fit_overlapped_s']:.2f} s during the sweep, "
                     f"{t['after_sweep_s']:.2f} s after the last frame")
    return title, "\n".join(lines) + "\n"


def _goal_note(err_rel, err_deg, z, goal_rel, goal_deg) -> str:
    """What a goal line says beside its figures, so that it never contradicts the verdict: nothing
    when the relative goals are met; else whether the errors are within 5 of their stds (the
    channel's precision does not reach the goal: its stds say so, the figures are not wrong) or
    beyond them (wrong beyond its stds)."""
    if not (math.isfinite(err_rel) and math.isfinite(err_deg) and math.isfinite(z)) or (err_rel <= goal_rel and err_deg <= goal_deg):
        return ""
    if z <= 5:
        return "; goal not met: the points' stds are larger than the goal (within 5 std of the truth: imprecise, not wrong)"
    return "; goal not met: beyond 5 std of the truth (wrong beyond its stds)"


class _Version(argparse.Action):
    """``--version``: print ``torchblur X.Y.Z`` on stdout and exit 0 (torchblur imported only then)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        import torchblur

        print(f"torchblur {torchblur.__version__}")
        parser.exit(0)


class _Parser(argparse.ArgumentParser):
    """argparse that suggests the closest option or command for a mistyped one (difflib;
    argparse's own ``suggest_on_error`` exists from Python 3.14 only). ``argv``: the command
    line being parsed (set by :func:`main`)."""

    argv: tuple = ()

    def error(self, message):
        super().error(message + _suggestion(self, type(self).argv))


def _suggestion(parser: argparse.ArgumentParser, argv) -> str:
    """``" (--output: did you mean --out?)"`` for the first word of ``argv`` that is neither an option
    nor a command of ``parser`` but close to one; "" if none is."""
    import difflib

    options = [o for a in parser._actions for o in a.option_strings]
    commands = [c for a in parser._actions if isinstance(a, argparse._SubParsersAction) for c in a.choices]
    for word in argv:
        if word.startswith("--") and word.split("=")[0] not in options:
            close = difflib.get_close_matches(word.split("=")[0], options, n=1, cutoff=0.6)
        elif commands and not word.startswith("-"):
            if word in commands:
                return ""
            close = difflib.get_close_matches(word, commands, n=1, cutoff=0.6)
        else:
            continue
        if close:
            return f" ({word.split('=')[0]}: did you mean {close[0]}?)"
    return ""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="torchblur", description="Identify fast actuator dynamics from camera motion blur.")
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True)
    ident = sub.add_parser("identify", help="identify the frequency response and a model (default: the built-in simulated mirror)",
                           epilog=EXIT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    ident.add_argument("--config", default=None, help="YAML config (see configs/); default: built-in")
    ident.add_argument("--out", default=None, help="output directory (the recording goes to OUT/experiment/)")
    ident.add_argument("--resume", default=None, metavar="DIR",
                       help="continue the interrupted run recorded in DIR (its --out folder or DIR/experiment)")
    ident.add_argument("--quiet", action="store_true", help="no progress bar and no log lines (warnings only; report.txt has the log)")
    ident.add_argument("--json", action="store_true",
                       help="at the end print one JSON summary line on stdout (out, points, errors vs truth, status/flag counts, "
                            "elapsed_s, version) and nothing else there; everything else goes to stderr")
    ident.add_argument("--force", action="store_true", help="run even beyond the size limits (docs/reliability.md), or into a folder that holds other files")
    ident.add_argument("--port", default=None, help="the controller's serial port or pyserial URL: the same as rig.kind=serial "
                                                    "rig.port=PORT (with --frames)")
    ident.add_argument("--frames", default=None, help="the camera (tcp://HOST:PORT of the emulator, pylon://..., or "
                                                      "package.module:Class): the same as rig.frames=URL")
    ident.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. sweep.n=20 plant.delay_s=5e-5")
    ident.set_defaults(func=_identify)
    fit = sub.add_parser("fit", help="re-fit a recorded run offline with other fit.* / model.* / report.* settings",
                         epilog=EXIT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    fit.add_argument("dir", help="the recorded run (its --out folder, or its experiment/ folder), or an outside recording "
                                 "(a folder with frames.csv: docs/outside_recordings.md)")
    fit.add_argument("--out", required=True, help="a new output directory (never inside DIR)")
    fit.add_argument("--quiet", action="store_true", help="no progress bar and no log lines (warnings only; report.txt has the log)")
    fit.add_argument("--json", action="store_true", help="one JSON summary line on stdout at the end, as identify --json")
    fit.add_argument("--force", action="store_true", help="overwrite the results a folder already holds, or write beside other files")
    fit.add_argument("overrides", nargs="*", help="fit.* and model.* overrides, e.g. fit.loss=poisson model.max_order=4")
    fit.set_defaults(func=_fit)
    emu = sub.add_parser("emulator", help="emulate the bench (controller on a pseudo-terminal, camera on loopback TCP)")
    emu.add_argument("--config", default=None, help="YAML config (plant.*, camera.*, seed; identify-only sections are ignored)")
    emu.add_argument("overrides", nargs="*", help="plant.*, camera.*, seed, transport=pty|socket, fault.*=N, ...")
    emu.set_defaults(func=_emulator)
    conf = sub.add_parser("config", help="list every config key with its value (the defaults, or a --config file and "
                                         "overrides resolved) and its unit")
    conf.add_argument("--config", default=None, help="YAML config (see configs/); default: built-in")
    conf.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. sweep.n=20")
    conf.set_defaults(func=_config)
    demo = sub.add_parser("demo", help="render a blurred spot and its alias; save a figure")
    demo.add_argument("--out", required=True, help="output directory")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)
    return parser


_NOTHING_RECORDED = "torchblur identify: interrupted before anything was recorded; run the same command again to start over"


def _interrupted_line(args) -> str:
    """The one line of a Ctrl-C outside a run's own handler: what to run next."""
    out = getattr(args, "out", None)
    if args.command == "identify" and getattr(args, "resume", None) is not None:
        return f"torchblur identify: interrupted; resume with: torchblur identify --resume {args.resume}"
    if args.command == "identify" and out is not None:
        if (Path(out) / "experiment" / "experiment.json").is_file():
            return (f"torchblur identify: interrupted; the recording so far is saved in {Path(out) / 'experiment'}; "
                    f"resume with: torchblur identify --resume {out}")
        return _NOTHING_RECORDED
    if args.command == "fit" and out is not None and Path(out).exists():
        return f"torchblur fit: interrupted; {out} may hold partial results: run the same command again with --force"
    return f"torchblur {args.command}: interrupted"


def main(argv: list[str] | None = None) -> int:
    from torchblur.errors import TorchblurError
    from torchblur.identify.record import console_logging

    parser = build_parser()
    _Parser.argv = tuple(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(argv)
    if extra:  # key=value overrides after an option (argparse stops filling a '*' positional there)
        if hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
            args.overrides = list(args.overrides) + extra
        else:
            sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
            sub.error(f"unrecognized arguments: {' '.join(extra)}")
    level = logging.WARNING if getattr(args, "quiet", False) else logging.INFO
    try:
        with console_logging(level):  # the run's messages on stderr, one line each, above the bars
            return args.func(args)
    except TorchblurError as exc:
        print(f"torchblur {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path the user gave: missing, a file, read-only, full disk
        where = f" {exc.filename}" if exc.filename else ""
        print(f"torchblur {args.command}: error:{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # one line, at any moment (the run's own handler names its recording)
        print(f"\n{_interrupted_line(args)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SystemExit:
        raise
    except Exception as exc:  # a bug: one line for the user, the traceback on request
        if os.environ.get("TORCHBLUR_DEBUG"):
            raise
        print(f"torchblur {args.command}: internal error: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''} "
              f"(set TORCHBLUR_DEBUG=1 for the traceback; please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
