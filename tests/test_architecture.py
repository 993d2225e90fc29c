"""The package's import graph, read from the source with ast (imports inside functions
count): nothing below the identification pipeline imports it, and no module imports one that
imports it back."""
import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "torchblur"
# May name torchblur.identify: the package's lazy table.
IDENTIFY_EXCEPTIONS = {"torchblur"}
# The identification's settings: a leaf (it imports nothing of torchblur.identify) that the
# bench emulator shares for its plant, camera and spots sections.
IDENTIFY_DATA = "torchblur.identify.config"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict:
    return {_module_name(p): p for p in ROOT.rglob("*.py")}


def _imported(name: str, path: Path) -> set:
    """Every dotted name ``name`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    out = set()
    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                stem = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join(stem + ([node.module] if node.module else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


@functools.lru_cache(maxsize=1)  # read once per session: every test below asks the same source tree (none changes it)
def _graph() -> dict:
    """``{module: {torchblur modules it imports}}`` (shared: do not modify)."""
    mods = _modules()
    edges = {}
    for name, path in mods.items():
        targets = set()
        for t in _imported(name, path):
            while t and t not in mods:
                t = t.rpartition(".")[0]
            if t and t != name and t.startswith("torchblur."):
                targets.add(t)
        edges[name] = targets
    return edges


def test_the_graph_sees_imports_inside_functions():
    edges = _graph()
    assert "torchblur.identify.pipeline" in edges["torchblur.identify.run"]
    assert "torchblur.rig.factory" in edges["torchblur.hardware.emulator"]  # build_dm: the DM mode's simulated rig


def test_nothing_below_identify_imports_it():
    offenders = sorted(
        f"{m} -> {t}"
        for m, ts in _graph().items()
        if not m.startswith("torchblur.identify") and m not in IDENTIFY_EXCEPTIONS
        for t in ts
        if (t == "torchblur.identify" or t.startswith("torchblur.identify.")) and t != IDENTIFY_DATA
    )
    assert offenders == []


def test_identify_config_is_a_leaf():
    assert not {t for t in _graph()[IDENTIFY_DATA] if t.startswith("torchblur.identify")}


def test_multisine_plan_does_not_import_the_pipeline():
    assert "torchblur.identify.pipeline" not in _graph()["torchblur.identify.multisine"]


def _cycles(edges: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return comps


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle():
    assert _cycles(_graph()) == []


@pytest.mark.parametrize("module", ["torchblur.identify.run", "torchblur.identify.multisine"])
def test_old_identify_modules_keep_their_names(module):
    import importlib

    mod = importlib.import_module(module)
    assert all(hasattr(mod, n) for n in mod.__all__)


def test_the_emulator_and_the_settings_do_not_load_the_pipeline():
    import subprocess
    import sys

    code = ("import sys, torchblur.hardware.emulator, torchblur.identify.config; "
            "print(sorted(m for m in sys.modules if m.startswith('torchblur.identify')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['torchblur.identify', 'torchblur.identify.config']"


def test_identify_package_names_load_on_use():
    import torchblur.identify as ident
    from torchblur.identify.calibration import calibrate
    from torchblur.identify.pipeline import identify

    assert ident.identify is identify and ident.calibrate is calibrate  # the function, not the calibration module
    with pytest.raises(AttributeError, match="no_such_name"):
        ident.no_such_name  # noqa: B018
