"""The ``torchblur identify`` and ``torchblur fit`` commands: a new run, a resumed one, a re-fit of
a recording or a fit of an outside recording, each into its folder (:mod:`torchblur.cli`
parses the arguments; :mod:`torchblur.identify.outputs` writes the files). A run the rig stops
or Ctrl-C interrupts says where its recording is and how to resume it.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

import torchblur as tb
from torchblur.cli import _NOTHING_RECORDED, EXIT_INTERRUPTED, EXIT_STOPPED
from torchblur.dm.mirror import TABLE_MAX_BYTES
from torchblur.identify.dm_outside import DMOutsidePlan, dm_recording_config, is_dm_recording, read_dm_recording
from torchblur.errors import ConfigError
from torchblur.files import read_bounded, resolve_inside
from torchblur.hardware.errors import HardwareError, RecordingError
from torchblur.hardware.outside import CSV_NAME, is_outside_recording, read_outside_recording
from torchblur.hardware.recording import Experiment, ReplayRig, atomic_write_bytes
from torchblur.hardware.run_folder import RunLock, check_out_folder
from torchblur.config import config_to_yaml, load_config, load_dataclass
from torchblur.identify.outputs import write_outputs
from torchblur.identify.outside import OutsidePlan, outside_config
from torchblur.identify.read_outputs import SOURCE_SCHEMA
from torchblur.identify.rigs import check_refit_config
from torchblur.identify.run import check_resume_config, identify

__all__ = ["TABLE_COPY", "fit_command", "identify_command"]


def _resume_hint(root: Path, cfg) -> str:
    rig = " rig.port=<controller port> rig.frames=<camera>" if cfg.rig.kind == "serial" else ""
    return f"torchblur identify --resume {root}{rig}"


def _rig_options(args) -> list[str]:
    """``--port PORT`` / ``--frames URL`` as the overrides they stand for (rig.kind=serial
    rig.port=PORT rig.frames=URL), placed before the user's own ``key=value`` overrides."""
    keys = [f"rig.{k}={getattr(args, k)}" for k in ("port", "frames") if getattr(args, k, None) is not None]
    return ["rig.kind=serial", *keys] if keys else []


def identify_command(args) -> int:
    """``torchblur identify``: a new run into ``--out``, or ``--resume`` one; the exit status."""
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


def _run_identify(cfg, out: Path, record, quiet: bool, root: Path | None = None, as_json: bool = False, *, rig=None,
                  base_dir: str | None = None, plan=None, stamp: str | None = None, source: str = "run") -> int:
    """Run ``cfg`` (any plan; ``rig``, ``base_dir``, ``plan``: :func:`~torchblur.identify.pipeline.identify`'s)
    recorded in ``record`` (None: nowhere), write its outputs into ``out`` headed by ``stamp``; stopped by the
    rig or interrupted, say where the recording is (:func:`_stopped`). The exit status."""
    root = out if root is None else root
    stamp = f"torchblur {tb.__version__}, seed {cfg.seed}" if stamp is None else stamp
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(f"# {stamp}\n" + config_to_yaml(cfg))
    torch.manual_seed(cfg.seed)
    exp_dir = record.path if hasattr(record, "path") else Path(record or out / "experiment")
    t0 = time.perf_counter()
    try:
        res = identify(cfg, rig, progress=not quiet, record=record, base_dir=base_dir, plan=plan)
    except (KeyboardInterrupt, HardwareError) as exc:
        if source != "run":  # a fit of a recording: nothing to resume (the CLI's own line)
            raise
        return _stopped(exc, exp_dir, root, cfg)
    elapsed = time.perf_counter() - t0
    try:
        return write_outputs(cfg, res, out, elapsed, stamp, as_json=as_json, source=source).exit_code
    except KeyboardInterrupt as exc:  # the recording is complete; a resume fits it again and writes every output
        if source != "run":
            raise
        return _stopped(exc, exp_dir, root, cfg)


def _finished(root: Path) -> str | None:
    """Why the run in ``root`` needs no resume (its recording complete and report.txt, the
    output written last, there), or None."""
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


def _run_dm(cfg, out: Path, args, *, record=None, root: Path | None = None, rig=None, stamp: str | None = None,
            source: str = "run") -> int:
    """A DM run (:func:`_run_identify`): new (recorded in ``OUT/experiment``), resumed (``record``, a
    writable Experiment) or re-fitted (``record`` read-only, ``rig`` its ReplayRig), its
    ``dm.actuator_table`` copied into the recording (:func:`_recorded_table`)."""
    cfg, base_dir = _recorded_table(cfg, out if record is None else (out if root is None else root), new=record is None)
    record = out / "experiment" if record is None else record
    return _run_identify(cfg, out, record, args.quiet, root=root, as_json=args.json, rig=rig, base_dir=base_dir,
                         stamp=stamp, source=source)


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


def _write_source(out: Path, args, **what) -> None:
    """``out/source.json`` of a re-fit or a fit of an outside recording: ``what`` (the recording,
    its status or points, its frames), the overrides, the version."""
    (out / "source.json").write_text(json.dumps({"schema": SOURCE_SCHEMA[0], "schema_version": SOURCE_SCHEMA[1][-1], **what,
                                                 "overrides": list(args.overrides), "torchblur_version": tb.__version__}, indent=2))


def _write_refit_source(out: Path, args, exp) -> None:
    _write_source(out, args, recording=str(exp.path), status=exp.meta.get("status"), frames=len(exp.lines))


def fit_command(args) -> int:
    """``torchblur fit DIR --out NEW``: re-fit a recorded run or fit an outside recording; the exit status."""
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
    check_refit_config(recorded, cfg)  # fit.*, model.*, report.* (and a DM's dm_plan.support_threshold) may change
    out.mkdir(parents=True, exist_ok=True)
    stamp = f"torchblur {tb.__version__}, seed {cfg.seed}, re-fit of {exp.path}"
    _write_refit_source(out, args, exp)
    if recorded.dm.enabled:  # a DM recording: the DM plan re-fits it
        return _run_dm(cfg, out, args, record=exp, root=root, rig=ReplayRig(exp), stamp=stamp, source="re-fit")
    return _run_identify(cfg, out, exp, args.quiet, root=root, as_json=args.json, rig=ReplayRig(exp), stamp=stamp,
                         source="re-fit")


def _is_outside(path) -> bool:
    """``path`` is an outside recording (a ``frames.csv``); RecordingError when it is neither
    that nor a torchblur run."""
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
    src, out = Path(args.dir).resolve(), Path(args.out)
    check_out_folder(out, command="fit", force=args.force)
    r_out = out.resolve()
    if r_out == src or src in r_out.parents:
        print(f"torchblur fit: error: --out {out} is inside the recording {args.dir}; it is never written, choose another folder",
              file=sys.stderr)
        return 2
    dm = is_dm_recording(src)  # a deformable mirror's: patterns.csv beside frames.csv, fitted by the DM plan
    rec = (read_dm_recording if dm else read_outside_recording)(src)  # RecordingError naming file, line and column
    cfg = (dm_recording_config if dm else outside_config)(rec, args.overrides)
    out.mkdir(parents=True, exist_ok=True)
    seeded = any(str(o).partition("=")[0] == "seed" for o in args.overrides)  # the recording itself has no seed
    stamp = f"torchblur {tb.__version__}{f', seed {cfg.seed}' if seeded else ''}, fit of the outside recording {src}"
    points = len(rec.freq_hz if dm else rec.points)
    _write_source(out, args, outside_recording=str(src), frames=rec.n_frames, points=points)
    plan = (DMOutsidePlan if dm else OutsidePlan)(rec)
    return _run_identify(cfg, out, None, args.quiet, as_json=args.json, plan=plan, stamp=stamp, source="outside")
