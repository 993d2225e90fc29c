"""The package's import graph, read from the source with ast (imports inside functions count),
shared by tests/test_architecture.py (modules) and tests/test_layers.py (subpackages)."""
import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "torchblur"


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict:
    """``{dotted module name: path}`` of every module of the package."""
    return {module_name(p): p for p in ROOT.rglob("*.py")}


def imported(name: str, path: Path) -> dict:
    """``{dotted name: inside a function?}`` for every name the module ``name`` imports (``from a
    import b`` gives ``a`` and ``a.b``); a name imported both at module level and inside a
    function counts as module level."""
    out: dict = {}
    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]

    def visit(node, in_function: bool):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                stem = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join(stem + ([node.module] if node.module else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for n in names:
            out[n] = out.get(n, True) and in_function
        inner = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(ast.parse(path.read_text()), False)
    return out


def _resolve(target: str, mods: dict) -> str | None:
    while target and target not in mods:
        target = target.rpartition(".")[0]
    return target or None


@functools.lru_cache(maxsize=1)  # read once per session: every test asks the same source tree (none changes it)
def edges_with_place() -> dict:
    """``{module: {torchblur module it imports: inside a function only?}}`` (shared: do not modify)."""
    mods = modules()
    edges = {}
    for name, path in mods.items():
        targets: dict = {}
        for t, in_function in imported(name, path).items():
            t = _resolve(t, mods)
            if t and t != name and t.startswith("torchblur"):
                targets[t] = targets.get(t, True) and in_function
        edges[name] = targets
    return edges


def graph() -> dict:
    """``{module: {torchblur modules it imports}}``, imports inside functions included."""
    return {m: set(ts) for m, ts in edges_with_place().items()}


def cycles(edges: dict) -> list:
    """Strongly connected components of more than one node (Tarjan), each sorted."""
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
