"""The one opening rule for every file torchblur reads from outside (recordings, configs,
actuator tables, response files, TIFF, CSV, JSON): :func:`read_bounded`.

- Only a regular file is read: the path is opened with ``O_NONBLOCK`` (so a FIFO cannot block
  the open) and checked with ``fstat`` on the open descriptor (so what is checked is what is
  read): a FIFO, a device (``/dev/zero``), a socket or a folder is refused.
- Its size is known and bounded before any byte is read, and it is read in blocks of at most
  :data:`BLOCK_BYTES` up to the limit (a file the kernel sizes 0, ``/proc/...``, cannot be read
  past the limit either); nothing is reserved up front.
- ``root``: a path that a recording names (untrusted) must resolve inside the recording's
  folder after every symlink (:func:`resolve_inside`): a recording never names a file outside
  itself.
- No file's content goes into an error message beyond :func:`~torchblur.errors.excerpt` (at
  most :data:`~torchblur.errors.EXCERPT_CHARS` printable characters).

A leaf: it imports nothing of torchblur but :mod:`torchblur.errors`, so every reader (the
hardware package's recordings, the config loader, :mod:`torchblur.sysid`) shares it without
importing each other.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import stat
from pathlib import Path, PurePosixPath

from torchblur.errors import ParameterError, excerpt

__all__ = ["BLOCK_BYTES", "open_regular", "read_bounded", "resolve_inside", "sha256_bounded"]

BLOCK_BYTES = 1 << 20
_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def resolve_inside(root, rel, what: str, *, error: type[Exception] = ParameterError) -> Path:
    """``root / rel`` for a relative POSIX path ``rel`` named by untrusted input, refused
    unless it stays inside ``root`` after resolving every symlink.

    Raises:
        error: ``rel`` is not a string, is absolute, holds ``..``, a backslash or a NUL, or
            resolves outside ``root``; the message names ``what``.
    """
    if not isinstance(rel, str) or not rel or len(rel) > 300 or "\\" in rel or "\x00" in rel:
        raise error(f"{what}: expected a relative path inside the run folder, got {excerpt(rel, 80) if isinstance(rel, str) else type(rel).__name__}")
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts:
        raise error(f"{what}: {excerpt(rel, 80)} leaves the run folder (absolute or '..'); a recording never names a file "
                    f"outside itself; refused")
    full = Path(root) / rel
    real_root = os.path.realpath(root)
    real = os.path.realpath(full)
    if os.path.commonpath([real_root, real]) != real_root:
        raise error(f"{what}: {excerpt(rel, 80)} resolves outside the run folder; a recording never names a file outside "
                    f"itself; refused")
    return full


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def open_regular(path, what: str, *, error: type[Exception] = ParameterError) -> tuple[int, int]:
    """``(fd, size)`` of the regular file ``path``, opened read-only with ``O_NONBLOCK`` (a FIFO
    cannot block the open) and checked with ``fstat`` on the descriptor (the caller closes it).

    Raises:
        error: naming ``what``: missing or unreadable, or not a regular file.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise error(f"{what}: cannot read it ({exc.strerror or type(exc).__name__})") from None
    try:
        st = os.fstat(fd)
    except OSError as exc:
        os.close(fd)
        raise error(f"{what}: cannot read it ({exc.strerror or type(exc).__name__})") from None
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise error(f"{what}: {_kind(st.st_mode)}, not a regular file; refused")
    return fd, int(st.st_size)


def _blocks(fd: int, limit: int, what: str, error):
    """The blocks of the open file ``fd``, at most :data:`BLOCK_BYTES` each and ``limit`` in all."""
    total = 0
    while True:
        block = os.read(fd, min(BLOCK_BYTES, limit + 1 - total))
        if not block:
            return
        total += len(block)
        if total > limit:
            raise error(f"{what}: larger than the {limit} bytes it may hold; refused")
        yield block


def read_bounded(path, limit: int, what: str, *, root=None, error: type[Exception] = ParameterError) -> bytes:
    """The bytes of the regular file ``path`` (relative to ``root`` and kept inside it when
    ``root`` is given), at most ``limit`` of them (module docstring: the rule).

    Raises:
        error: naming ``what``: the file is missing or unreadable, not a regular file, larger
            than ``limit``, or (``root``) outside ``root``.
    """
    if root is not None:
        path = resolve_inside(root, os.fspath(path), what, error=error)
    with _opened_blocks(path, limit, what, error) as blocks:
        return b"".join(blocks)


def sha256_bounded(path, limit: int, what: str, *, error: type[Exception] = ParameterError) -> str:
    """The SHA-256 (hex) of the regular file ``path`` of at most ``limit`` bytes, read in blocks
    under the same rule as :func:`read_bounded` (never held whole)."""
    h = hashlib.sha256()
    with _opened_blocks(path, limit, what, error) as blocks:
        for block in blocks:
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def _opened_blocks(path, limit: int, what: str, error):
    """The blocks (:func:`_blocks`) of the regular file ``path``, refused when larger than
    ``limit``; every failure, reading included, an ``error`` naming ``what``."""
    fd, size = open_regular(path, what, error=error)
    try:
        if size > limit:
            raise error(f"{what}: {size} bytes, larger than the {limit} bytes it may hold; refused")
        yield _blocks(fd, limit, what, error)
    except OSError as exc:
        raise error(f"{what}: cannot read it ({exc.strerror or type(exc).__name__})") from None
    finally:
        os.close(fd)
