"""
Defaults every model-building module shares (no imports of the models themselves).

:mod:`mshoot_core.models.registry` and :mod:`mshoot_core.models.card` both read these; kept
apart so that neither imports the other at module level.
"""
from __future__ import annotations

#: Relative tolerance of an FMU integrator for a control model [-].
CONTROL_TOLERANCE = 1e-6
#: Relative tolerance of an FMU integrator for an emulated building [-].
EMULATOR_TOLERANCE = 1e-10
#: Relative tolerance of a control FMU whose sensitivities are finite differences (no
#: directional derivatives) [-]: the differences are as accurate as the integration.
FINITE_DIFFERENCE_TOLERANCE = 1e-10


def is_card_path(name: str) -> bool:
    """Whether ``name`` is a path to a model card (ends in .yaml or .yml)."""
    return str(name).lower().endswith(('.yaml', '.yml'))
