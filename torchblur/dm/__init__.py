"""Deformable mirrors read by a Shack-Hartmann sensor (issue 17).

``mirror`` (the actuators, their influence functions and dynamics), ``shack_hartmann`` (the
subapertures, their spots and the geometry matrix G), ``plans`` (which actuators move together
in each pattern), ``rig`` (the simulated DM rig) and ``pipeline`` (the DM identification run).
Not imported by ``import torchblur``: import the submodules where they are used.

The public entry of a lab's own mirror (docs/dm_rig.md): :func:`identify_dm` (``cfg``, a DM
config, and ``rig``, an object that fulfils :class:`DMRig`), and for frames recorded with the
lab's own software :func:`read_dm_recording` / :func:`write_dm_recording` (docs/outside_recordings.md,
"Deformable mirrors"); ``torchblur fit FOLDER`` fits such a folder. These names are loaded on
first use (``import torchblur.dm`` stays light).

Conventions (shared by every module here): N actuators ``j = 0..N-1`` in row-major order of the
actuator grid, positions ``actuator_xy [N, 2]`` in actuator pitches with 0 at the pupil centre
(x to the right, y down, like image columns and rows); M valid subapertures, slopes ordered
``[x of all M, y of all M]`` (2M) in px of spot displacement on the sensor camera; a plan is a
pattern matrix ``patterns [P, N]``: in pattern p actuator j is commanded
``amplitude * patterns[p, j] * sin(omega t)``.
"""
import importlib as _importlib

#: the public names and the modules they live in (loaded on first use)
_PUBLIC = {"identify_dm": "torchblur.dm.pipeline", "DMResult": "torchblur.dm.pipeline", "DMRig": "torchblur.dm.contract",
           "check_dm_rig": "torchblur.dm.contract", "read_dm_recording": "torchblur.dm.outside",
           "write_dm_recording": "torchblur.dm.outside", "export_dm_recording": "torchblur.dm.outside",
           "identify_dm_recording": "torchblur.dm.outside"}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(_importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'torchblur.dm' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
