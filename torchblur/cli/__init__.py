"""Command line: ``torchblur <command> ...`` (also ``python -m torchblur.cli <command> ...``).

The commands (``identify``, ``identify --resume``, ``fit``, ``emulator``, ``config``, ``demo``) and
their options are :func:`build_parser`'s (``torchblur COMMAND --help``); README.md and the docs
describe each. The run's messages go to the ``torchblur`` logger, shown on stderr one line each
(``--quiet``: warnings only); report.txt holds them all. The report's table goes to stdout, or
with ``--json`` to stderr while stdout gets exactly one JSON summary line
(:mod:`torchblur.identify.report`). Every identify and fit run ends with one verdict line
(:mod:`torchblur.identify.verdict`). Exit codes: :data:`EXIT_EPILOG` (4 also for points flagged
no_motion or alias, or beyond 5 std of a known truth); 1 an internal error.
"""
from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import os
import sys
from pathlib import Path

import torchblur
from torchblur.errors import TorchblurError
from torchblur.identify.record import console_logging

__all__ = ["EXIT_INTERRUPTED", "EXIT_STOPPED", "build_parser", "main"]

#: command -> "module:function" that runs it, imported when the command runs: ``torchblur config``,
#: ``emulator`` and ``--version`` do not load the identification pipeline (a few seconds of imports)
COMMANDS = {"identify": "torchblur.cli.commands:identify_command", "fit": "torchblur.cli.commands:fit_command",
            "config": "torchblur.cli.tools:config_command", "emulator": "torchblur.cli.tools:emulator_command",
            "demo": "torchblur.cli.demo:demo_command"}

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
    """The ``torchblur`` command's parser: one sub-parser per command of :data:`COMMANDS`."""
    parser = _Parser(prog="torchblur", description="Identify fast actuator dynamics from camera motion blur.")
    parser.add_argument("--version", action="version", version=f"torchblur {torchblur.__version__}")
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
    fit = sub.add_parser("fit", help="re-fit a recorded run offline with other fit.* / model.* / report.* settings",
                         epilog=EXIT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    fit.add_argument("dir", help="the recorded run (its --out folder, or its experiment/ folder), or an outside recording "
                                 "(a folder with frames.csv: docs/outside_recordings.md)")
    fit.add_argument("--out", required=True, help="a new output directory (never inside DIR)")
    fit.add_argument("--quiet", action="store_true", help="no progress bar and no log lines (warnings only; report.txt has the log)")
    fit.add_argument("--json", action="store_true", help="one JSON summary line on stdout at the end, as identify --json")
    fit.add_argument("--force", action="store_true", help="overwrite the results a folder already holds, or write beside other files")
    fit.add_argument("overrides", nargs="*", help="fit.* and model.* overrides, e.g. fit.loss=poisson model.max_order=4")
    emu = sub.add_parser("emulator", help="emulate the bench (controller on a pseudo-terminal, camera on loopback TCP)")
    emu.add_argument("--config", default=None, help="YAML config (plant.*, camera.*, seed; identify-only sections are ignored)")
    emu.add_argument("overrides", nargs="*", help="plant.*, camera.*, seed, transport=pty|socket, fault.*=N, ...")
    conf = sub.add_parser("config", help="list every config key with its value (the defaults, or a --config file and "
                                         "overrides resolved) and its unit")
    conf.add_argument("--config", default=None, help="YAML config (see configs/); default: built-in")
    conf.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. sweep.n=20")
    demo = sub.add_parser("demo", help="render a blurred spot and its alias; save a figure")
    demo.add_argument("--out", required=True, help="output directory")
    demo.add_argument("--seed", type=int, default=0)
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


def _command(name: str):
    """The function that runs command ``name`` (:data:`COMMANDS`), its module imported now."""
    module, _, function = COMMANDS[name].partition(":")
    return getattr(importlib.import_module(module), function)


def main(argv: list[str] | None = None) -> int:
    """``torchblur ARGV`` (default: ``sys.argv[1:]``) -> the exit status (:data:`EXIT_EPILOG`)."""
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
            return _command(args.command)(args)
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
