"""The package's import graph, read from the source with ast (imports inside functions
count): nothing below the identification pipeline imports it, and no module imports one that
imports it back."""
import pytest
from import_graph import cycles as _cycles
from import_graph import graph as _graph

# May name torchblur.identify: the package's lazy table.
IDENTIFY_EXCEPTIONS = {"torchblur"}
# The identification's settings: below the pipeline (they import nothing of torchblur.identify,
# nor the rigs, the hardware or the command line above them); the bench emulator shares them for
# its plant, camera and spots sections.
CONFIG = "torchblur.config"
ABOVE_CONFIG = ("torchblur.identify", "torchblur.rig", "torchblur.hardware", "torchblur.cli")


def test_the_graph_sees_imports_inside_functions():
    edges = _graph()
    assert "torchblur.identify.pipeline" in edges["torchblur.identify.run"]
    assert "torchblur.rig.factory" in edges["torchblur.hardware.emulator"]  # build_dm: the DM mode's simulated rig


def test_nothing_below_identify_imports_it():
    offenders = sorted(
        f"{m} -> {t}"
        for m, ts in _graph().items()
        if not m.startswith(("torchblur.identify", "torchblur.cli")) and m not in IDENTIFY_EXCEPTIONS  # the command is above it
        for t in ts
        if t == "torchblur.identify" or t.startswith("torchblur.identify.")
    )
    assert offenders == []


def test_config_imports_nothing_above_it():
    edges = _graph()
    modules = [m for m in edges if m == CONFIG or m.startswith(CONFIG + ".")]
    assert len(modules) > 1
    assert not {f"{m} -> {t}" for m in modules for t in edges[m]
                if any(t == a or t.startswith(a + ".") for a in ABOVE_CONFIG)}


def test_multisine_plan_does_not_import_the_pipeline():
    assert "torchblur.identify.pipeline" not in _graph()["torchblur.identify.multisine"]


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


def BACKGROUND_JOB(out, started):
    """The fresh process of the test below, run in the background by tests/background.py -> the finished process."""
    import sys

    from background import run

    code = ("import sys, torchblur.hardware.emulator, torchblur.config; "
            "print(sorted(m for m in sys.modules if m.startswith('torchblur.identify')))")
    return run([sys.executable, "-c", code], started, timeout_s=300)


def test_the_emulator_and_the_settings_do_not_load_the_pipeline(background, request):
    done = background.get(request.module.__name__)  # import torchblur.hardware.emulator and torchblur.config in a fresh process
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_identify_package_names_load_on_use():
    import torchblur.identify as ident
    from torchblur.identify.calibration import calibrate
    from torchblur.identify.pipeline import identify

    assert ident.identify is identify and ident.calibrate is calibrate  # the function, not the calibration module
    with pytest.raises(AttributeError, match="no_such_name"):
        ident.no_such_name  # noqa: B018
