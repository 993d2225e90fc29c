"""The settings of ``torchblur identify`` (layer 8: it imports the physics, estimators and the
DM's physics below it, nothing of the rigs, the hardware, the pipeline or the command line):

- :mod:`~torchblur.config.schema`: the frozen dataclasses, one per section, and their defaults;
- :mod:`~torchblur.config.load`: defaults, YAML file and overrides merged, and the file's safety;
- :mod:`~torchblur.config.checks`: every key's value and the rules between keys;
- :mod:`~torchblur.config.budget`: what a run takes (frames, memory, disk, bench time, a DM
  run's plan) and the limits it is refused beyond;
- :mod:`~torchblur.config.keys`: every key with its unit (``torchblur config``);
- :mod:`~torchblur.config.camera_urls`: what an SDK camera's ``rig.frames`` URL names.

The bench emulator imports these settings without loading the pipeline.
"""
from torchblur.config import budget, camera_urls, checks, keys, load, schema
from torchblur.config.budget import *  # noqa: F401,F403 (each module's __all__)
from torchblur.config.camera_urls import *  # noqa: F401,F403
from torchblur.config.checks import *  # noqa: F401,F403
from torchblur.config.keys import *  # noqa: F401,F403
from torchblur.config.load import *  # noqa: F401,F403
from torchblur.config.schema import *  # noqa: F401,F403

__all__ = [*schema.__all__, *load.__all__, *checks.__all__, *budget.__all__, *keys.__all__, *camera_urls.__all__]
