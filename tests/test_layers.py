"""The layers of docs/architecture.md, checked on the subpackage graph read from the source
(tests/import_graph.py; imports inside functions count): no cycle between subpackages, no edge
upward, no torchblur import inside a function but the listed ones."""
import re
from pathlib import Path

from import_graph import cycles, edges_with_place, imported

# From the bottom; a unit is a subpackage (torchblur.X.*) or a top-level module (torchblur.X);
# "torchblur" is the package's __init__. A module may import its own layer or below.
LAYERS = (
    ("torchblur", "errors", "files", "_compat", "_console", "optim", "losses"),  # 0 base
    ("render",),  # 1 image formation
    ("systems",),  # 2 actuator models
    ("image",),  # 3 real frames
    ("fit",),  # 4 fitting images
    ("design",),  # 5 experiment design
    ("sysid",),  # 6 from points to models
    ("dm",),  # 7 deformable-mirror physics and estimators
    ("config",),  # 8 the run's settings
    ("rig",),  # 9 where frames come from: rigs
    ("hardware",),  # 10 serial, cameras, recording, emulator
    ("identify",),  # 11 the pipeline
    ("cli",),  # 12 the command
)
LAYER = {unit: k for k, names in enumerate(LAYERS) for unit in names}
# The public facade: `import torchblur` gives render's names at once and the rest through its
# lazy table (importlib, on first use), so its own imports may point up.
FACADE = "torchblur"
# Imports of a torchblur module inside a function, allowed for a heavy dependency: (module, target): why.
ALLOWED_IN_FUNCTION = {
    ("torchblur.rig.simulated", "torchblur.image.spots"): "torchblur.image loads kornia (~1.5 s); a rig without spots does not",
}
DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _unit_edges() -> dict:
    """``{"a -> b": ["module -> module", ...]}`` between different units."""
    out: dict = {}
    for m, targets in edges_with_place().items():
        for t in targets:
            if _unit(m) != _unit(t):
                out.setdefault(f"{_unit(m)} -> {_unit(t)}", []).append(f"{m} -> {t}")
    return out


def _in_function() -> dict:
    """``{module: [targets imported only inside a function]}`` (torchblur modules)."""
    return {m: sorted(t for t, inside in ts.items() if inside) for m, ts in edges_with_place().items()
            if any(ts.values())}


def _upward(edge: str) -> bool:
    a, b = edge.split(" -> ")
    return a != FACADE and LAYER[b] > LAYER[a]


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in edges_with_place()}
    assert units - set(LAYER) == set()


def test_the_checks_see_what_they_look_for(tmp_path):
    """Each rule fires on an example: an upward edge, a cycle, an import inside a function."""
    assert _upward("render -> fit") and not _upward("fit -> render") and not _upward("torchblur -> render")
    assert cycles({"fit": {"image"}, "image": {"fit"}}) == [["fit", "image"]]
    src = tmp_path / "m.py"
    src.write_text("import torchblur.errors\n\ndef f():\n    from torchblur.render import psf\n")
    assert imported("torchblur.x.m", src) == {"torchblur.errors": False, "torchblur.render": True, "torchblur.render.psf": True}


def test_no_upward_edge():
    found = {e: ms for e, ms in _unit_edges().items() if _upward(e)}
    assert found == {}


def test_no_cycle_between_subpackages():
    graph: dict = {}
    for e in _unit_edges():
        a, b = e.split(" -> ")
        graph.setdefault(a, set()).add(b)
    assert cycles(graph) == []


def test_imports_inside_functions_are_listed():
    found = {m: [t for t in ts if (m, t) not in ALLOWED_IN_FUNCTION] for m, ts in _in_function().items()}
    assert {m: ts for m, ts in found.items() if ts} == {}


def test_allowed_entries_still_exist():
    inside = _in_function()
    stale = [k for k in ALLOWED_IN_FUNCTION if k[1] not in inside.get(k[0], ())]
    assert stale == []  # remove these entries: what they excused is gone


def test_architecture_doc_lists_the_layers_in_order():
    text = DOC.read_text()
    block = re.search(r"```text\n(.*?)```", text, re.S).group(1)
    rows = [re.match(r"\s*(\d+)\s+(.*)", line) for line in block.splitlines()]
    doc = {int(r.group(1)): r.group(2) for r in rows if r}
    assert sorted(doc) == list(range(len(LAYERS)))
    for k, names in enumerate(LAYERS):
        listed = re.findall(r"[A-Za-z_]+", doc[k].split(":")[-1] if k == 0 else doc[k].split()[0])
        assert set(names) <= set(listed), (k, names, doc[k])

