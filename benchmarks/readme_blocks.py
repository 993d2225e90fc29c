"""Run README.md's code blocks in order, as a new user copies them, and say how each ended.

    python benchmarks/readme_blocks.py [--root DIR] [--skip-install] [--with-tests] [--skip TEXT ...] [--lines N ...]

Run it in a fresh clone (``git clone REPO DIR``): every ```bash block runs in one bash in
``--root`` (the Quick start's ``python3 -m venv .venv && . .venv/bin/activate`` stays active for
the blocks after it), every ```python block with that venv's python. Skipped, and said so:
blocks that need something this machine lacks (a CUDA index, the emulator's ``/dev/pts/N`` and
``PORT`` placeholders, the user's ``my_recording/``, a command left running with ``&``) and,
with ``--skip-install``, the ``pip install`` lines. A block ends ok when its exit status is 0, or
the one its comments announce (``exit status 4``, a refusal's one line). Prints one line per
block; exit status 1 if any block that ran failed. The figures the blocks quote are compared by
``benchmarks/check_docs.py``.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_SKIP = (("--index-url", "a CUDA build of torch from the network"), ("/dev/pts/N", "the emulator's port placeholder"),
         ("tcp://127.0.0.1:PORT", "the emulator's port placeholder"), ("my_recording/", "the user's own recording"),
         ("torchblur emulator", "the emulator keeps running"))


def blocks(readme: Path) -> list[tuple[str, str, int]]:
    """``[(language, code, line)]`` of every fenced block, in order."""
    out, lang, buf, start = [], None, [], 0
    for k, line in enumerate(readme.read_text().splitlines(), start=1):
        m = re.match(r"^```(\w*)\s*$", line)
        if m and lang is None:
            lang, buf, start = m.group(1) or "text", [], k
        elif line.startswith("```") and lang is not None:
            out.append((lang, "\n".join(buf) + "\n", start))
            lang = None
        elif lang is not None:
            buf.append(line)
    return out


def expected_exit(code: str) -> set:
    """Exit statuses a block may end with: 0, and any its comments announce."""
    ok = {0}
    ok |= {int(x) for x in re.findall(r"exit status (\d+)", code)}
    if re.search(r"# one line: ", code):  # a refusal shown with its line
        ok.add(2)
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=str(ROOT), help="the clone to run in (default: this tree)")
    ap.add_argument("--skip-install", action="store_true", help="skip pip install lines (a venv already there)")
    ap.add_argument("--timeout", type=float, default=1800)
    ap.add_argument("--with-tests", action="store_true", help="run the test block too (the whole suite)")
    ap.add_argument("--skip", action="append", default=[], help="skip blocks containing this text (repeatable)")
    ap.add_argument("--lines", type=int, nargs="*", default=None, help="run only the blocks that start at these README lines")
    args = ap.parse_args(argv)
    root = Path(args.root).resolve()
    failed = 0
    prelude = ". .venv/bin/activate 2>/dev/null; "
    for lang, code, line in blocks(root / "README.md"):
        if lang not in ("bash", "python") or (args.lines is not None and line not in args.lines):
            continue
        skips = list(_SKIP) + [(k, "asked (--skip)") for k in args.skip]
        if not args.with_tests:
            skips.append(("python -m pytest", "the whole test suite (--with-tests runs it)"))
        why = next((w for key, w in skips if key in code), None)
        if why:
            print(f"skip  README.md:{line} ({lang}): {why}")
            continue
        run = code
        if args.skip_install:
            run = re.sub(r"python3 -m venv \.venv && \. \.venv/bin/activate && pip install [^&\n]*(&& )?", "", run)
            run = re.sub(r"(\. \.venv/bin/activate && )?pip install [^&\n]*(&& )?", "", run)
        t0 = time.perf_counter()
        if lang == "bash":
            cmd = ["bash", "-c", prelude + "set -e\n" + run]
        else:
            cmd = ["bash", "-c", prelude + "python - <<'PYEOF'\n" + run + "PYEOF\n"]
        p = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=args.timeout)
        ok = p.returncode in expected_exit(code)
        failed += not ok
        last = (p.stdout + p.stderr).strip().splitlines()[-1:] or [""]
        print(f"{'ok  ' if ok else 'FAIL'}  README.md:{line} ({lang}): exit {p.returncode} in {time.perf_counter() - t0:.0f} s; "
              f"last line: {last[0][:160]}", flush=True)
    print(f"{failed} block(s) failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
