"""Reading a config: the built-in defaults, then a YAML file (``--config FILE``), then dotted
overrides (``plant.num=[1,2]``), merged with OmegaConf into the frozen dataclasses of
:mod:`torchblur.config.schema`; unknown keys raise :class:`ConfigError` naming the key. The
file's safety: its size and list lengths bounded, a YAML bomb or recursive alias refused, no
interpolation in an untrusted (recorded) file, its ``schema``/``schema_version`` checked.
:func:`load_config` then validates (:mod:`torchblur.config.checks`) and checks the run's size
(:mod:`torchblur.config.budget`) before any work starts.
"""
from __future__ import annotations

import io
import os
import re
from dataclasses import asdict, field, fields, is_dataclass

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchblur.config.budget import check_limits
from torchblur.config.checks import validate
from torchblur.config.schema import IdentifyConfig
from torchblur.errors import ConfigError, check_schema_version, excerpt, key_excerpt
from torchblur.files import read_bounded

__all__ = ["load_config", "load_dataclass", "config_to_yaml", "CONFIG_SCHEMA", "MAX_CONFIG_BYTES", "MAX_LIST_ENTRIES"]


def _from_dict(cls, data: dict, prefix: str = ""):
    kwargs = {}
    names = {f.name: f for f in fields(cls)}
    for k, v in data.items():
        if k not in names:
            raise ConfigError(f"{key_excerpt(prefix + str(k))}: unknown config key (known: {', '.join(prefix + n for n in names)})")
        default = names[k].default_factory() if names[k].default_factory is not field().default_factory else None  # type: ignore[misc]
        if is_dataclass(default):
            if not isinstance(v, dict):
                raise ConfigError(f"{prefix}{k}: expected a section (mapping), got {excerpt(v)}")
            kwargs[k] = _from_dict(type(default), v, prefix + k + ".")
        elif names[k].type in ("int", "Optional[int]") and isinstance(v, float) and v.is_integer() and abs(v) < 2**53:
            kwargs[k] = int(v)  # 1e3 written for an integer key: the integer it is
        else:
            kwargs[k] = v
    return cls(**kwargs)


def load_config(path: str | None = None, overrides: list[str] | None = None, *, trusted: bool = True,
                force: bool = False) -> IdentifyConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides; validated, and the run's
    size checked against :data:`LIMITS` (:func:`estimate_run`) unless ``force``.

    ``trusted=False`` for a file from a recording: no interpolation (``${...}``) is allowed
    in it, so nothing outside the recording (an environment variable) is read.

    Raises:
        ConfigError: naming the key, for unknown keys, unparsable values, invalid values, or
            a run beyond the limits (with the estimate).
    """
    cfg = load_dataclass(IdentifyConfig, path, overrides, trusted=trusted)
    validate(cfg)
    if not force:
        check_limits(cfg)
    return cfg


MAX_CONFIG_BYTES = 1 << 20
MAX_LIST_ENTRIES = 1000


def _load_file(path: str, *, trusted: bool):
    """The OmegaConf of a YAML file: at most :data:`MAX_CONFIG_BYTES`, aliases expanded to
    at most OmegaConf's node limit (a YAML bomb or a recursive alias is refused), and, when
    not ``trusted``, no interpolation anywhere.

    Raises:
        ConfigError: naming the file.
    """
    if not os.path.lexists(path):
        raise ConfigError(f"--config: file not found: {path}")
    data = read_bounded(path, MAX_CONFIG_BYTES, f"--config {path}", error=ConfigError)  # the opening rule (torchblur.files)
    try:
        file_cfg = OmegaConf.load(io.StringIO(data.decode("utf-8")))
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise ConfigError(f"--config {path}: not a usable YAML file ({str(exc).splitlines()[0][:120]})") from None
    if not OmegaConf.is_dict(file_cfg):
        raise ConfigError(f"--config {path}: expected a mapping of sections, got a {type(file_cfg).__name__}")
    _check_config_schema(file_cfg, path)
    if not trusted:
        _refuse_interpolation(OmegaConf.to_container(file_cfg, resolve=False), path)
    return file_cfg


def _refuse_interpolation(value, path: str, key: str = "") -> None:
    if isinstance(value, str) and "${" in value:
        raise ConfigError(f"{key or 'config'}: an interpolation ({excerpt(value[:60])}) in the recorded {path}; a recording's "
                          f"config is read literally, refused")
    if isinstance(value, dict):
        for k, v in value.items():
            _refuse_interpolation(v, path, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _refuse_interpolation(v, path, f"{key}[{i}]")


def _check_sizes(value, key: str = "") -> None:
    """Every list at most :data:`MAX_LIST_ENTRIES` long, nesting at most 8 deep."""
    if key.count(".") + key.count("[") > 8:
        raise ConfigError(f"{key}: nested more than 8 levels deep")
    if isinstance(value, list):
        if len(value) > MAX_LIST_ENTRIES:
            raise ConfigError(f"{key}: {len(value)} entries, more than {MAX_LIST_ENTRIES}")
        for i, v in enumerate(value):
            _check_sizes(v, f"{key}[{i}]")
    elif isinstance(value, dict):
        for k, v in value.items():
            _check_sizes(v, f"{key}.{k}" if key else str(k))


def load_dataclass(cls, path: str | None = None, overrides: list[str] | None = None, *, ignore_file_sections=(),
                   trusted: bool = True):
    """Defaults of the frozen dataclass ``cls``, then the YAML file (its top-level sections in
    ``ignore_file_sections`` skipped; ``trusted=False``: no interpolation in it), then
    ``key=value`` overrides; not validated.

    Raises:
        ConfigError: naming the key, for unknown keys and unparsable values.
    """
    merged = OmegaConf.create(asdict(cls()))
    OmegaConf.set_struct(merged, True)
    try:
        if path is not None:
            file_cfg = _load_file(path, trusted=trusted)
            for k in ignore_file_sections:
                if k in file_cfg:
                    file_cfg.pop(k)
            merged = OmegaConf.merge(merged, file_cfg)
        for item in overrides or ():
            if "=" not in item:
                raise ConfigError(f"{item}: expected key=value")
            try:
                merged = OmegaConf.merge(merged, OmegaConf.from_dotlist([item]))
            except (yaml.YAMLError, RecursionError) as exc:
                raise ConfigError(f"{item.partition('=')[0]}: the value cannot be read ({str(exc).splitlines()[0][:100]})") from None
        data = OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or getattr(exc, "key", None) or "config"
        raise ConfigError(f"{key_excerpt(key)}: {_clip_quotes(str(exc).splitlines()[0])}") from None
    except (RecursionError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"config: cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:100]})") from None
    _check_sizes(data)
    return _from_dict(cls, data)


def _clip_quotes(text: str) -> str:
    """A third-party message about untrusted content with every quoted part cut to an excerpt."""
    return re.sub(r"'([^']*)'", lambda m: excerpt(m.group(1)), text)[:300]


#: the ``schema`` and ``schema_version`` a run's config.yaml starts with (:func:`config_to_yaml`);
#: versions read. A file without them (a config written by hand, or a run's config.yaml from before
#: they were written) reads as version 1.
CONFIG_SCHEMA = ("torchblur.config", (1,))


def config_to_yaml(cfg: IdentifyConfig) -> str:
    """The YAML of every key of ``cfg`` (a run's config.yaml), headed by ``schema`` and
    ``schema_version`` (:data:`CONFIG_SCHEMA`); :func:`load_config` reads it back."""
    head = f"schema: {CONFIG_SCHEMA[0]}\nschema_version: {CONFIG_SCHEMA[1][-1]}\n"
    return head + OmegaConf.to_yaml(OmegaConf.create(asdict(cfg)))


def _check_config_schema(file_cfg, path: str) -> None:
    """Take ``schema`` / ``schema_version`` out of the loaded file ``file_cfg`` (in place); a
    file without them is version 1. ConfigError naming the key for another schema or a version
    this torchblur does not read (a newer one: say so)."""
    if "schema" not in file_cfg and "schema_version" not in file_cfg:
        return
    name, version = file_cfg.pop("schema", None), file_cfg.pop("schema_version", None)
    if name != CONFIG_SCHEMA[0]:
        raise ConfigError(f"schema: expected {CONFIG_SCHEMA[0]!r} in {path}, got {excerpt(name)}")
    check_schema_version(version, CONFIG_SCHEMA[1], f"{path}: ", error=ConfigError)
