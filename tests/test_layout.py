"""The package's layout: the public surface, and every dotted path the README and the guides
quote is a real one (there are no alias module paths: each name is quoted where it lives)."""
import importlib
import re
from pathlib import Path

import pytest

import torchblur as tb

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("**/*.md")), *sorted((ROOT / "configs").glob("*.yaml"))]
# not in a quoted string, nor after "schema: " (a file's schema name, e.g. config.yaml's)
DOTTED = re.compile(r"(?<![\w./\"'-])(?<!schema: )torchblur(?:\.[A-Za-z_]\w*)+")


def quoted_paths() -> list[tuple[str, str]]:
    """(file, dotted path) for every ``torchblur.x.y`` the docs quote (file paths like
    ``torchblur/fit/...`` are not dotted, and quoted strings such as a file's schema name
    ``"torchblur.model_fit"`` are not paths: neither is read here)."""
    found = set()
    for path in DOCS:
        for m in DOTTED.finditer(path.read_text(encoding="utf-8")):
            found.add((path.relative_to(ROOT).as_posix(), m.group(0)))
    return sorted(found)


def resolve(dotted: str):
    """The object a dotted path names: the longest importable module prefix, then attributes."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError:
            continue
        for attr in parts[k:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


def test_the_docs_quote_dotted_paths():
    assert len(quoted_paths()) > 50


@pytest.mark.parametrize("where, dotted", quoted_paths())
def test_every_dotted_path_the_docs_quote_resolves(where, dotted):
    try:
        resolve(dotted)
    except (ImportError, AttributeError) as exc:
        pytest.fail(f"{where}: {dotted} does not resolve ({exc})")


def test_the_flat_layout_paths_are_gone():
    """0.1.0 was never released: the pre-subpackage module paths are not kept as aliases."""
    for old in ("torchblur.preprocess", "torchblur.model_fit", "torchblur.coded_exposure", "torchblur.psf"):
        with pytest.raises(ModuleNotFoundError):
            importlib.import_module(old)


@pytest.mark.parametrize("name", tb.__all__)
def test_public_names_resolve_and_are_documented(name):
    obj = getattr(tb, name)
    assert obj.__doc__ and obj.__doc__.strip(), name
    assert name in dir(tb)


def test_identify_is_the_package_and_runs_the_pipeline():
    import torchblur.identify as ident
    from torchblur.identify.run import identify

    assert tb.identify is ident and ident.identify is identify
    assert callable(tb.identify)


def test_unknown_attribute_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        tb.no_such_name  # noqa: B018
