"""
The variables of an FMU as its model description declares them (name, causality, unit, range).

One reading of an fmpy model description for every user: what a card may map to
(:mod:`mshoot_core.models.card`, ``mshoot card``) and a BOPTEST plant's overwrite inputs and
outputs (:class:`~mshoot_core.boptest.plant.BoptestPlant`). A variable's unit, min and max are
its own, else its declared type's.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any


@dataclasses.dataclass(frozen=True)
class ModelVariable:
    """What a card may map to: one variable of the model, as the card check lists it."""

    name: str
    causality: str
    type: str = 'Real'  # noqa: A003 (the FMI attribute)
    unit: str = ''
    start: float | None = None
    variability: str = ''
    initial: str = ''
    min: float | None = None  # noqa: A003 (the FMI attribute)
    max: float | None = None  # noqa: A003 (the FMI attribute)

    def label(self) -> str:
        """``name (causality, unit)``."""
        return f"{self.name} ({self.causality}{', ' + self.unit if self.unit else ''})"


def finite_float(value: Any) -> float | None:
    """Return ``value`` as a finite float, or None (missing, not a number, infinite)."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def fmu_variables(md: Any) -> list[ModelVariable]:
    """Every scalar variable of an fmpy model description, as :class:`ModelVariable`."""
    out = []
    continuous = {d.variable.derivative.name for d in getattr(md, 'derivatives', [])
                  if d.variable.derivative is not None}
    for v in md.modelVariables:
        declared = v.declaredType
        unit = v.unit or (declared.unit if declared is not None else None) or ''
        causality = v.causality or 'local'
        low = v.min if v.min is not None else getattr(declared, 'min', None)
        high = v.max if v.max is not None else getattr(declared, 'max', None)
        out.append(ModelVariable(v.name, causality, v.type, unit, finite_float(v.start),
                                 v.variability or '', v.initial or '', finite_float(low),
                                 finite_float(high)))
        if v.name in continuous:
            out[-1] = dataclasses.replace(out[-1], causality=f'{causality}, state')
    return out
