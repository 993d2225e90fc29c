"""The ``torchblur config`` and ``torchblur emulator`` commands: the resolved settings, and the
bench emulator (:mod:`torchblur.hardware.emulator`). Neither loads the identification pipeline.
"""
from __future__ import annotations

from torchblur.cli import EXIT_INTERRUPTED
from torchblur.hardware.emulator import main as emulator_main
from torchblur.config import load_config
from torchblur.config.keys import format_config_keys

__all__ = ["config_command", "emulator_command"]


def config_command(args) -> int:
    """``torchblur config``: every key, its resolved value and its unit, one line each on stdout."""
    print(format_config_keys(load_config(args.config, list(args.overrides), force=True)), end="")
    return 0


def emulator_command(args) -> int:
    """``torchblur emulator``: serve the bench emulator until stopped (Ctrl-C: exit 130)."""
    try:
        return emulator_main(args.overrides, config_path=args.config)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
