"""Run README.md's code blocks in order, as a new user copies them, and check the figures each quotes.

    python benchmarks/readme_blocks.py [--root DIR] [--skip-install] [--with-tests] [--skip TEXT ...] [--lines N ...]

Run it in a fresh clone (``git clone REPO DIR``): every ```bash block runs in one bash in
``--root`` (the Quick start's ``python3 -m venv .venv && . .venv/bin/activate`` stays active for
the blocks after it), every ```python block with that venv's python. As a user would:

- ``torchblur emulator ...`` (with or without ``&``) is started in the background, the JSON line
  it prints read, and its ``serial`` and ``frames`` put for the placeholders ``/dev/pts/N``,
  ``/dev/pts/M``, ``tcp://127.0.0.1:PORT`` and ``PORT2`` of the block's other lines (a resume's
  "new" device is the same emulator, still running); the emulator is stopped after the block;
- ``my_recording/`` is written first by docs/outside_recordings.md's own example (the block that
  makes ``my_recording``), a stated substitute for the user's recording.

Skipped, and said so with the reason: a CUDA index (no GPU, no network beyond the package
registries), with ``--skip-install`` the ``pip install`` lines, without ``--with-tests`` the
whole test suite. A block ends ok when its exit status is 0, or the one its comments announce
(``exit status 4``, a refusal's one line). After each block, every claim of
``benchmarks/check_docs.py`` whose command is one of the block's ``torchblur identify`` lines
(the same keys, any ``--out``) is checked against what that line printed and its report.txt
(the claim's tolerance: the run's noise), and the README's "bit for bit" re-fit is compared
file by file. Prints one line per block and per claim; exit status 1 if any block or claim failed.
"""
from __future__ import annotations

import json
import argparse
import os
import re
import select
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_docs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
_SKIP = (("--index-url", "a CUDA build of torch from the network: no GPU here and no network beyond the package registries"),)
# placeholder (a regex) -> the key of the emulator's start line that replaces it
PLACEHOLDERS = ((r"/dev/pts/[NM]\b", "serial"), (r"tcp://127\.0\.0\.1:PORT2?\b", "frames"))
# the guide's block that writes a recording into my_recording/ (a substitute for the user's own)
RECORDING = ("docs/outside_recordings.md", 'pathlib.Path("my_recording")')
# "bit for bit" in the README: (the block's text, [(file, file)] identical byte for byte)
IDENTICAL = (("torchblur fit runs/dm --out runs/dm-refit", [("runs/dm/dm/actuators.csv", "runs/dm-refit/dm/actuators.csv"),
              ("runs/dm/dm/interaction_matrix.npy", "runs/dm-refit/dm/interaction_matrix.npy")]),)
PRELUDE = ". .venv/bin/activate 2>/dev/null; "


def blocks(text: str) -> list[tuple[str, str, int]]:
    """``[(language, code, line)]`` of every fenced block of a markdown ``text``, in order (``line``: the fence's, from 1)."""
    out, lang, buf, start = [], None, [], 0
    for k, line in enumerate(text.splitlines(), start=1):
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


def split_emulator(code: str) -> tuple[list[str], str]:
    """``(emulator commands, the rest)``: the block's ``torchblur emulator`` lines (comment and a
    trailing ``&`` taken off) and its other lines, in order."""
    emulators, rest = [], []
    for line in code.splitlines():
        cmd = line.split("#", 1)[0].strip()
        if cmd.startswith("torchblur emulator"):
            emulators.append(cmd.rstrip("&").strip())
        else:
            rest.append(line)
    return emulators, "\n".join(rest) + "\n"


def substitute(code: str, info: dict) -> str:
    """``code`` with every placeholder of :data:`PLACEHOLDERS` replaced by the emulator's ``info``
    (its start line: ``{"serial": ..., "frames": ...}``)."""
    for pattern, key in PLACEHOLDERS:
        code = re.sub(pattern, lambda _m, v=str(info[key]): v, code)
    return code


def skip_install(code: str) -> str:
    """``code`` without its venv creation and ``pip install`` steps (a venv already there)."""
    code = re.sub(r"python3 -m venv \.venv && \. \.venv/bin/activate && pip install [^&\n]*(&& )?", "", code)
    return re.sub(r"(\. \.venv/bin/activate && )?pip install [^&\n]*(&& )?", "", code)


def identify_keys(cmd) -> tuple:
    """A ``torchblur identify`` command's arguments without ``--out DIR`` and the program, sorted: two
    commands with the same keys run the same identification. ``cmd``: a shell line or an argv list."""
    argv = shlex.split(cmd.split("#", 1)[0]) if isinstance(cmd, str) else [str(a) for a in cmd]
    k = argv.index("identify") if "identify" in argv else len(argv)
    args, out = argv[k + 1:], []
    while args:
        a = args.pop(0)
        if a == "--out" and args:
            args.pop(0)
        elif not a.startswith("--out="):
            out.append(a)
    return tuple(sorted(out))


def block_commands(code: str) -> list[tuple[tuple, str | None]]:
    """``[(identify_keys, --out DIR)]`` of a block's ``torchblur identify`` commands (not ``--resume``; a line's
    ``&&`` steps each)."""
    out = []
    for line in code.splitlines():
        for cmd in (c.strip() for c in line.split("#", 1)[0].split("&&")):
            if not cmd.startswith("torchblur identify") or "--resume" in cmd:
                continue
            argv = shlex.split(cmd)
            where = argv[argv.index("--out") + 1] if "--out" in argv[:-1] else None
            out.append((identify_keys(argv), where))
    return out


def start_emulator(cmd: str, root: Path, log: Path, timeout_s: float = 300.0) -> tuple[subprocess.Popen, dict]:
    """``cmd`` (a ``torchblur emulator`` line) started in the background in ``root`` -> (its process,
    its start line's JSON). Its stderr goes to ``log``. Raises RuntimeError when it prints no start line."""
    with open(log, "ab") as err:
        proc = subprocess.Popen(["bash", "-c", PRELUDE + "exec " + cmd], cwd=root, stdout=subprocess.PIPE, stderr=err,
                                start_new_session=True)
    if select.select([proc.stdout], [], [], timeout_s)[0]:
        line = proc.stdout.readline().decode()
        try:
            return proc, json.loads(line)
        except ValueError:
            pass
    stop_emulator(proc)
    raise RuntimeError(f"{cmd!r} printed no start line in {timeout_s:.0f} s (its log: {log})")


def stop_emulator(proc: subprocess.Popen) -> None:
    """Stop an emulator :func:`start_emulator` started (its own process group), and wait for it."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)


def run_block(lang: str, code: str, root: Path, timeout_s: float) -> tuple[int, str]:
    """Run one block in ``root`` -> (exit status, stdout + stderr). Its emulators run around it."""
    emulators, code = split_emulator(code)
    procs, log = [], root / ".readme_blocks_emulator.log"
    try:
        for cmd in emulators:
            proc, info = start_emulator(cmd, root, log)
            procs.append(proc)
            code = substitute(code, info)
        if lang == "bash":
            cmd = ["bash", "-c", PRELUDE + "set -e\n" + code]
        else:
            cmd = ["bash", "-c", PRELUDE + "python - <<'PYEOF'\n" + code + "PYEOF\n"]
        p = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=timeout_s)
        return p.returncode, p.stdout + p.stderr
    finally:
        for proc in procs:
            stop_emulator(proc)


def write_recording(root: Path, timeout_s: float) -> tuple[int, str]:
    """``root/my_recording/`` written by the guide's own example (:data:`RECORDING`) -> (exit status, output)."""
    guide, marker = RECORDING
    code = next(c for lang, c, _ in blocks((root / guide).read_text()) if lang == "python" and marker in c)
    return run_block("python", code, root, timeout_s)


def block_claims(code: str, output: str, rc: int, root: Path) -> list[tuple[bool, str]]:
    """check_docs' claims whose command is one of the block's identify lines, checked against what it
    printed (that run's report.txt first, then the block's output) -> [(holds, one line)]."""
    out = []
    for keys, where in block_commands(code):
        report = root / where / "report.txt" if where else None
        text = (report.read_text() if report is not None and report.is_file() else "") + output
        for c in check_docs.CLAIMS:
            if c.cmd[:len(check_docs.TB)] == check_docs.TB and c.cmd[len(check_docs.TB)] == "identify" \
                    and identify_keys(c.cmd) == keys:
                with tempfile.TemporaryDirectory() as tmp:
                    ok, line = check_docs.check(c, Path(tmp), {tuple(c.cmd): (rc, text)})
                out.append((ok, f"{c.doc}: {c.name}: {line}"))
    for marker, pairs in IDENTICAL:
        if marker in code:
            for a, b in pairs:
                same = (root / a).is_file() and (root / b).is_file() and (root / a).read_bytes() == (root / b).read_bytes()
                out.append((same, f"README.md: bit for bit: {a} and {b} {'identical' if same else 'DIFFER (or missing)'}"))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=str(ROOT), help="the clone to run in (default: this tree)")
    ap.add_argument("--skip-install", action="store_true", help="skip pip install lines (a venv already there)")
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--with-tests", action="store_true", help="run the test block too (the whole suite)")
    ap.add_argument("--skip", action="append", default=[], help="skip blocks containing this text (repeatable)")
    ap.add_argument("--lines", type=int, nargs="*", default=None, help="run only the blocks that start at these README lines")
    args = ap.parse_args(argv)
    root = Path(args.root).resolve()
    failed = claims = 0
    t_all = time.perf_counter()
    for lang, code, line in blocks((root / "README.md").read_text()):
        if lang not in ("bash", "python") or (args.lines is not None and line not in args.lines):
            continue
        skips = list(_SKIP) + [(k, "asked (--skip)") for k in args.skip]
        if not args.with_tests:
            skips.append(("python -m pytest", "the whole test suite (--with-tests runs it)"))
        why = next((w for key, w in skips if key in code), None)
        if why:
            print(f"skip  README.md:{line} ({lang}): {why}", flush=True)
            continue
        run = skip_install(code) if args.skip_install else code
        t0, expected = time.perf_counter(), expected_exit(code)
        if "my_recording/" in run:
            if not (root / "my_recording").exists():
                rc, out = write_recording(root, args.timeout)
                print(f"{'ok  ' if rc == 0 else 'FAIL'}  {RECORDING[0]}'s block writing my_recording/ (the user's recording's "
                      f"substitute: one point, so the model fit has too few points and the run exits 4, as the guide says): "
                      f"exit {rc}", flush=True)
                failed += rc != 0
            expected.add(4)
        try:
            rc, out = run_block(lang, run, root, args.timeout)
        except (RuntimeError, subprocess.TimeoutExpired) as e:
            rc, out = -1, str(e)
        ok = rc in expected
        failed += not ok
        last = out.strip().splitlines()[-1:] or [""]
        print(f"{'ok  ' if ok else 'FAIL'}  README.md:{line} ({lang}): exit {rc} in {time.perf_counter() - t0:.0f} s; "
              f"last line: {last[0][:160]}", flush=True)
        if not ok:  # what went wrong, as the user would see it
            print("\n".join("      | " + x[:200] for x in out.strip().splitlines()[-15:]), flush=True)
        for holds, text in block_claims(run, out, rc, root):
            claims += 1
            failed += not holds
            print(f"      {'ok  ' if holds else 'FAIL'} {text}", flush=True)
    print(f"{failed} block(s) or claim(s) failed ({claims} claims checked; {time.perf_counter() - t_all:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
