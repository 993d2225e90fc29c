"""Every Python code block in the README and the guides runs, as a reader would paste it.

Blocks of one file run in order in one namespace (a later block may use an earlier one's names).
A block that needs a file or a run made by an earlier shell command is marked by a first line
``# needs: <what>`` and is skipped with that reason.
"""
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FILES = ["README.md"] + sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def _blocks(name):
    return BLOCK.findall((ROOT / name).read_text())


@pytest.mark.parametrize("name", [f for f in FILES if _blocks(f)])
def test_python_blocks_run(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"docs_{pathlib.Path(name).stem}"}
    for i, code in enumerate(_blocks(name)):
        first = code.splitlines()[0] if code.strip() else ""
        if first.startswith("# needs:"):
            continue
        exec(compile(code, f"{name}[block {i}]", "exec"), namespace)  # noqa: S102 (our own docs)
