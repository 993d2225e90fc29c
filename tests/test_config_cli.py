"""identify's configuration and command line: defaults, overrides, errors that name the key."""
import sys
from pathlib import Path

import numpy as np
import pytest

from torchblur.config import IdentifyConfig, load_config
from torchblur.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_defaults_and_overrides():
    cfg = load_config(None, ["sweep.n=5", "plant.num=[1,2]", "plant.den=[1,3,2]", "camera.jitter_s=1e-6"])
    assert cfg.sweep.n == 5 and cfg.plant.num == [1, 2] and cfg.camera.jitter_s == 1e-6
    f = cfg.frequencies_hz()
    assert f[0] == pytest.approx(1.0) and f[-1] == pytest.approx(1000.0) and len(f) == 5
    assert load_config(None, ["sweep.freq_hz=[300,10,50]"]).frequencies_hz() == [10.0, 50.0, 300.0]
    assert isinstance(load_config(), IdentifyConfig)


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("identify_*.yaml")), ids=lambda p: p.name)
def test_shipped_configs_load(path):
    load_config(str(path))


BAD = [
    (["sweep.nn=3"], "sweep.nn"),
    (["foo=1"], "foo"),
    (["sweep.f_min_hz=-1"], "sweep.f_min_hz"),
    (["sweep.freq_hz=[10,-5]"], "sweep.freq_hz[1]"),
    (["sweep.exposures=[0.5,2.0]"], "sweep.exposures"),
    (["plant.den=[1,-1]"], "plant.den"),
    (["plant.num=[1,2,3]", "plant.den=[1,1]"], "plant.num"),
    (["plant.num=[]"], "plant.num"),
    (["camera.bit_depth=abc"], "camera.bit_depth"),
    (["camera.peak_fraction=1.5"], "camera.peak_fraction"),
    (["fit.optimizer=newton"], "fit.optimizer"),
    (["excitation.target_px=0"], "excitation.target_px"),
    (["sweep.images_per_point=0"], "sweep.images_per_point"),
    (["rig.kind=bench"], "rig.kind"),
    (["report.figures=perhaps"], "report.figures"),
    (["sweep"], "sweep"),
]


@pytest.mark.parametrize("overrides,key", BAD, ids=[b[1] for b in BAD])
def test_bad_config_names_the_key(overrides, key):
    with pytest.raises(ConfigError) as info:
        load_config(None, overrides)
    assert str(info.value).startswith(key)


def BACKGROUND_JOB(tmp_path, started):
    """The two command lines below, each in a fresh process, run in the background by tests/background.py
    -> ``{name: (tmp_path, finished process)}``."""
    from background import run

    cli = [sys.executable, "-m", "torchblur.cli", "identify"]
    return {"bad": (tmp_path, run([*cli, "--out", str(tmp_path / "o"), "sweep.f_min_hz=-3"], started)),
            "missing": (tmp_path, run([*cli, "--config", str(tmp_path / "nope.yaml"), "--out", str(tmp_path)], started))}


def test_cli_bad_config_is_one_clear_line_without_traceback(background, request):
    tmp_path, out = background.get(request.module.__name__)["bad"]  # identify --out TMP/o sweep.f_min_hz=-3
    assert out.returncode == 2
    assert "sweep.f_min_hz" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "o").exists()  # nothing started


def test_cli_missing_config_file(background, request):
    tmp_path, out = background.get(request.module.__name__)["missing"]  # identify --config TMP/nope.yaml --out TMP
    assert out.returncode == 2 and "--config" in out.stderr and "Traceback" not in out.stderr


def _declared_keys():
    """``[(dotted key, rule)]`` of every key whose check the schema declares (config.key)."""
    from dataclasses import fields, is_dataclass

    def walk(obj, prefix):
        for f in fields(obj):
            value = getattr(obj, f.name)
            if is_dataclass(value):
                yield from walk(value, f"{prefix}{f.name}.")
            elif "check" in f.metadata:
                yield f"{prefix}{f.name}", f.metadata["check"]

    return list(walk(IdentifyConfig(), ""))


def _with(cfg, key, value):
    """``cfg`` with the dotted ``key`` set to ``value`` (frozen sections replaced)."""
    from dataclasses import replace

    head, _, rest = key.partition(".")
    return replace(cfg, **{head: _with(getattr(cfg, head), rest, value) if rest else value})


def test_every_declared_check_refuses_a_wrong_value_naming_its_key():
    from torchblur.config import validate

    base = IdentifyConfig()  # spots and a mirror enabled, so that their sections are checked too
    for key, value in (("spots.rows", 2), ("spots.cols", 2), ("dm.n_across", 4), ("excitation.target_px", 2.0)):
        base = _with(base, key, value)
    validate(base)
    declared = _declared_keys()
    assert len(declared) > 80 and {"camera.frame_rate_hz", "fit.loss", "report.figures", "seed", "dm.registration.shift_x"} <= {k for k, _ in declared}
    for key, rule in declared:
        with pytest.raises(ConfigError) as info:
            validate(_with(base, key, "" if rule.get("text") else "abc"))  # a string is a text key's type: an empty one is not
        want = ("one of" if "choice" in rule else "true or false" if rule.get("flag") else
                rule.get("what", "a non-empty string") if rule.get("text") else rule["what"] if "items" in rule else "a number")
        assert str(info.value).startswith(f"{key}: expected {want}"), str(info.value)
        if rule.get("integer"):
            with pytest.raises(ConfigError, match=rf"^{key}: expected an integer, got 2\.5$"):
                validate(_with(base, key, 2.5))


def test_one_scalar_check_for_arguments_and_config_keys():
    from torchblur.errors import InputTypeError, ParameterError, check_real_scalar

    assert check_real_scalar(3, "x", integer=True, low=0, high=3) == 3.0
    for value, exc, message in (("abc", InputTypeError, "x: expected a number, got 'abc'"),
                                (True, InputTypeError, "x: expected a number, got True"),
                                (float("inf"), ParameterError, "x: expected a finite number, got inf"),
                                (-1, ParameterError, "x: expected a value >= 0, got -1")):
        with pytest.raises(exc) as plain:
            check_real_scalar(value, "x", nonnegative=True)
        with pytest.raises(ConfigError) as config:
            check_real_scalar(value, "x", nonnegative=True, error=ConfigError)
        assert type(plain.value) is exc and str(plain.value) == str(config.value) == message


def test_one_integer_check_for_arguments_and_recording_fields():
    # errors.check_int serves arguments and a recording manifest's integer fields alike (its
    # error raised there): the same message naming the field, the value quoted and bounded.
    from torchblur.errors import EXCERPT_CHARS, InputTypeError, ParameterError, check_int
    from torchblur.hardware.manifest import _Bad

    assert check_int(np.int64(3), "page", low=0, high=3) == 3 and type(check_int(np.int64(3), "page")) is int
    for value, exc, message in ((1.0, InputTypeError, "page: expected an integer, got float 1.0"),
                                ("7", InputTypeError, "page: expected an integer, got str '7'"),
                                (True, InputTypeError, "page: expected an integer, got bool True"),
                                (4, ParameterError, "page: expected an integer in [0, 3], got 4"),
                                (-1, ParameterError, "page: expected an integer in [0, 3], got -1")):
        with pytest.raises(exc) as plain:
            check_int(value, "page", low=0, high=3)
        with pytest.raises(_Bad) as manifest:
            check_int(value, "page", low=0, high=3, error=_Bad)
        assert type(plain.value) is exc and str(plain.value) == str(manifest.value) == message
    with pytest.raises(InputTypeError) as info:
        check_int("\x1b" * 10_000, "page")
    assert len(str(info.value)) < EXCERPT_CHARS + 60 and "\x1b" not in str(info.value)
