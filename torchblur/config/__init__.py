"""The settings of ``torchblur identify`` (layer 8, docs/architecture.md: nothing of the rigs, the
hardware, the pipeline or the command line, so the bench emulator imports them without loading
the pipeline): :mod:`~torchblur.config.schema` (the frozen dataclasses), :mod:`~torchblur.config.load`
(defaults, YAML and overrides merged, the file's safety), :mod:`~torchblur.config.checks` (every
key's value and the rules between keys), :mod:`~torchblur.config.budget` (what a run takes and
its limits), :mod:`~torchblur.config.keys` (every key with its unit) and
:mod:`~torchblur.config.camera_urls` (an SDK camera's ``rig.frames`` URL).
"""
from torchblur.config import budget, camera_urls, checks, keys, load, schema
from torchblur.config.budget import *  # noqa: F401,F403 (each module's __all__)
from torchblur.config.camera_urls import *  # noqa: F401,F403
from torchblur.config.checks import *  # noqa: F401,F403
from torchblur.config.keys import *  # noqa: F401,F403
from torchblur.config.load import *  # noqa: F401,F403
from torchblur.config.schema import *  # noqa: F401,F403

__all__ = [*schema.__all__, *load.__all__, *checks.__all__, *budget.__all__, *keys.__all__, *camera_urls.__all__]
