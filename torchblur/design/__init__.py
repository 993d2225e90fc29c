"""Experiment design: exposure windows and the checks that they identify the phase
(``windows``), multisine excitation signals (``multisine``) and the image set's Fisher
information (``fisher``)."""
from torchblur.design.windows import (
    DesignWarning, alias_separation, check_design, dual_exposure_windows, resolve_branches, trigger_phase_for,
)

__all__ = [
    "DesignWarning", "alias_separation", "check_design", "dual_exposure_windows", "resolve_branches",
    "trigger_phase_for",
]
