"""
The pre-heating rule for BOPTEST test cases: a zone setpoint ahead of the comfort band.

The rule sends a zone temperature setpoint every control step (1 h) to each setpoint input it
is given (``targets``: overwrite input -> its zone and the input's range): the highest lower
bound of the zone's comfort band over the coming step and the ``lead`` after it, plus a
``margin``::

    setpoint(t) = max { LowerSetp[z](s) : t <= s < t + step + lead } + margin    [K]

clipped to the input's range. With a lead the building starts heating for the occupied band
``lead`` hours before it begins, and it holds that level until the band's end (the max over
the window, rather than the bound ``lead`` ahead alone, which would drop the setpoint ``lead``
before the occupied hours end). The band is read from the test case's data (forward-filled, at
its rows in the window).

:func:`rule_targets` finds the targets of a card: its ``boptest.setpoint_zones`` (control ->
zone) with each control's FMU input and declared range. The rule is a decision, so it lives
here, where the rule node and the core period loop reach it; its tuning on a grid of leads and
margins is an application (:mod:`mshoot_studies.boptest_rule`).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Mapping

import numpy as np

from mshoot_core.boptest.testcase import TestCase

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RuleTarget:
    """
    One setpoint the rule writes.

    Attributes
    ----------
    zone : str
        The zone whose band it follows (``LowerSetp[zone]``).
    lower_k, upper_k : float
        The input's range [K] (its declared min/max).

    """

    zone: str
    lower_k: float = -math.inf
    upper_k: float = math.inf


def setpoint_targets(case: TestCase, zones: Mapping[str, str]) -> dict[str, RuleTarget]:
    """
    Return the rule's targets: FMU setpoint input -> its zone and its declared range [K].

    Parameters
    ----------
    case : TestCase
        The test case (its FMU's overwrite inputs).
    zones : dict of str to str
        Overwrite input (``X_u``) -> the zone of its band.

    Raises
    ------
    ValueError
        For an input that is not an overwrite input of the FMU.

    """
    from mshoot_core.boptest.plant import BoptestPlant
    inputs = BoptestPlant(case, record=[]).inputs
    unknown = [name for name in zones if name not in inputs]
    if unknown:
        raise ValueError(f'not overwrite inputs of {case.name}: {unknown}; expected some of '
                         f'{sorted(inputs)}')
    return {name: RuleTarget(str(zone), inputs[name].lower, inputs[name].upper)
            for name, zone in zones.items()}


def rule_targets(card: Any, case: TestCase) -> dict[str, RuleTarget]:
    """
    Return the rule's targets of a card: FMU input -> :class:`RuleTarget`.

    Parameters
    ----------
    card : ModelCard
        A card of kind ``boptest`` whose ``boptest.setpoint_zones`` maps setpoint controls to
        zones.
    case : TestCase
        The test case (the declared ranges of its FMU's inputs [K]).

    Raises
    ------
    ValueError
        When the card names no setpoint zone, or a control without an overwrite switch.

    """
    zones = dict((card.boptest or {}).get('setpoint_zones') or {})
    if not zones:
        raise ValueError(f'model card {card.path}: the rule needs boptest.setpoint_zones '
                         '(setpoint control -> zone of its comfort band)')
    inputs = {}
    for control, zone in zones.items():
        variable = card.controls.get(control)
        if variable is None or variable.activate is None:
            raise ValueError(f'model card {card.path}: boptest.setpoint_zones names '
                             f'{control!r}: expected a control with an overwrite switch '
                             f'(activate), one of {sorted(card.controls)}')
        inputs[variable.variable] = zone
    return setpoint_targets(case, inputs)


@dataclasses.dataclass(frozen=True)
class PreheatRule:
    """
    The pre-heating rule (module docstring).

    Parameters
    ----------
    case : TestCase
        The test case (its band).
    targets : dict of str to RuleTarget
        FMU setpoint input -> its zone and range.
    lead_h : float
        How far beyond the coming step the band is looked at [h], >= 0.
    margin_k : float
        Added to the band's lower bound [K], >= 0.
    step_s : float
        The control step [s] (the setpoint is held over it).

    """

    case: TestCase
    targets: Mapping[str, RuleTarget]
    lead_h: float = 0.0
    margin_k: float = 0.0
    step_s: float = 3600.0

    def __post_init__(self) -> None:
        """Check the parameters."""
        for name in ('lead_h', 'margin_k'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f'expected {name} >= 0, got {value!r}')
        if not self.step_s > 0:
            raise ValueError(f'expected a positive step_s, got {self.step_s!r}')
        unknown = [t.zone for t in self.targets.values() if t.zone not in self.case.zones]
        if unknown:
            raise ValueError(f'unknown zones {unknown}: expected zones of {self.case.name} '
                             f'{self.case.zones}')

    def setpoint(self, t_s: float, zone: str, lower_k: float = -math.inf,
                 upper_k: float = math.inf) -> float:
        """
        Return a zone's setpoint [K] over the control step starting at ``t_s`` [s].

        The band is looked up at ``t_s`` and at every data row time in the window
        ``(t_s, t_s + step + lead)``; the result is clipped to [lower_k, upper_k].
        """
        column = self.case.band_columns(zone)[0]
        end = t_s + self.step_s + self.lead_h * 3600.0
        index = self.case.row_times(column)
        rows = index[(index > t_s) & (index < end)]
        times = np.concatenate([[t_s], rows])
        lower = float(np.max(self.case.lookup(column, times)))
        return float(min(max(lower + self.margin_k, lower_k), upper_k))

    def __call__(self, t_s: float, outputs: Mapping[str, float] | None = None
                 ) -> dict[str, float]:
        """Return the overwrites over the step from ``t_s`` (a step policy of run_period)."""
        return {name: self.setpoint(t_s, t.zone, t.lower_k, t.upper_k)
                for name, t in self.targets.items()}
