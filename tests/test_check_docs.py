"""The quick part of benchmarks/check_docs.py: every figure it registers is still quoted in its
guide, and the claims that need no run hold (the others: `python benchmarks/check_docs.py`)."""
import importlib.util
import re
import sys

import pytest

from cli_run import ROOT

_spec = importlib.util.spec_from_file_location("check_docs", ROOT / "benchmarks" / "check_docs.py")
check_docs = sys.modules["check_docs"] = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(check_docs)


@pytest.mark.parametrize("claim", check_docs.CLAIMS, ids=[c.name for c in check_docs.CLAIMS])
def test_every_registered_figure_is_quoted_in_its_guide(claim):
    text = re.sub(r"\n\s*#?\s*", " ", (ROOT / claim.doc).read_text())
    match = re.search(claim.quote, text)
    assert match is not None, f"{claim.doc} no longer quotes: {claim.name}"


@pytest.mark.parametrize("claim", [c for c in check_docs.CLAIMS if c.speed == "instant"], ids=lambda c: c.name)
def test_the_instant_claims_hold(claim, tmp_path):
    ok, line = check_docs.check(claim, tmp_path, {})
    assert ok, line
