"""The ``torchblur`` console script's start: Ctrl-C before its ``main`` runs is one line.

Installed by ``torchblur/__init__.py`` only when the program is the ``torchblur`` command (not a
user's own program importing torchblur), before torch loads: a SIGINT handler that is Python's
own (raise KeyboardInterrupt) but remembers that it came (a Ctrl-C inside a C extension's
import surfaces as an ImportError), and an excepthook that turns such an interruption into the
command's one line. :func:`torchblur.cli.main` handles every Ctrl-C once it runs.
Imports the standard library only.
"""
from __future__ import annotations

import atexit
import os
import signal
import sys

__all__ = ["install", "STARTING_LINE"]

STARTING_LINE = "torchblur: interrupted while starting; nothing was written: run the same command again"
_SEEN: list = []


def _sigint(signum, frame):
    _SEEN.append(signum)
    raise KeyboardInterrupt


def _excepthook(kind, value, tb, _default=sys.excepthook):
    if issubclass(kind, KeyboardInterrupt) or _SEEN:
        print(f"\n{STARTING_LINE}", file=sys.stderr)
        sys.stderr.flush()
        os._exit(130)
    _default(kind, value, tb)


def install() -> None:
    """The handler and the excepthook; SIGINT left alone when the command was started with it
    ignored (``nohup``). Once the command has returned, a Ctrl-C is ignored (it would otherwise
    kill the interpreter's shutdown without a word; the work is done)."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _sigint)
        atexit.register(signal.signal, signal.SIGINT, signal.SIG_IGN)
    sys.excepthook = _excepthook
