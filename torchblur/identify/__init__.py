"""The identification pipeline: the runner, its plans, the verdict, the outputs and the report
(each module's place: docs/architecture.md; its settings: :mod:`torchblur.config`; the
``torchblur`` command: :mod:`torchblur.cli`).

The package is itself callable: ``torchblur.identify(cfg, rig)`` is
``torchblur.identify.identify(cfg, rig)``. Its names load on first use.
"""
import importlib as _importlib
import sys as _sys
import types as _types

__all__ = [
    "Calibration", "DMResult", "IdentificationResult", "build_rig", "build_simulated_rig", "calibrate", "calibrate_latency",
    "check_resume_config", "export_dm_recording", "fit_model", "identify", "identify_dm_recording", "plant_of", "read_dm_recording",
    "write_dm_recording",
]


def __getattr__(name: str):
    if name in __all__:
        value = getattr(_importlib.import_module("torchblur.identify.run"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchblur.identify' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


class _CallableModule(_types.ModuleType):
    """``torchblur.identify`` is both this package and the function it is named after."""

    def __call__(self, *args, **kwargs):
        return self.identify(*args, **kwargs)


_sys.modules[__name__].__class__ = _CallableModule
