"""
The pre-heating rule for BOPTEST test cases: zone setpoints ahead of the comfort band.

The rule sends a zone temperature setpoint every control step (1 h) to each setpoint input it
is given (``targets``: overwrite input -> its zone, the band's edge it follows and the input's
range). A heating (minimum) setpoint gets the highest lower bound of the zone's comfort band
over the coming step and the ``lead`` after it, plus a ``margin``::

    setpoint(t) = max { LowerSetp[z](s) : t <= s < t + step + lead } + margin    [K]

a cooling (maximum) setpoint its mirror, the lowest upper bound minus the ``cooling margin``::

    setpoint(t) = min { UpperSetp[z](s) : t <= s < t + step + lead } - cooling margin    [K]

each clipped to the input's range. With a lead the building starts heating (cooling) for the
occupied band ``lead`` hours before it begins, and it holds that level until the band's end
(the max over the window, rather than the bound ``lead`` ahead alone, which would drop the
setpoint ``lead`` before the occupied hours end). The band is read from the test case's data
(forward-filled, at its rows in the window).

A supply temperature target (:class:`SupplyReset`) follows a heating curve instead: piecewise
linear in the outdoor temperature measured at the decision (an output of the FMU), constant
beyond its end points, shifted by the ``supply shift`` [K], then held at or above its floor and
clipped to the input's range.

:func:`rule_targets` finds the targets of a card: its ``boptest.setpoint_zones`` (heating
control -> zone), ``boptest.cooling_zones`` (cooling control -> zone) and
``boptest.supply_reset`` (the supply control, the outdoor temperature output, the curve's
points in degC, its floor), with each control's FMU input and declared range. The rule is a
decision, so it lives here, where the rule node and the core period loop reach it; its tuning
on a grid of leads, margins and shifts is an application (:mod:`mshoot_studies.boptest_rule`).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Mapping

import numpy as np

from mshoot_core.boptest.testcase import TestCase
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)


#: The band edges a zone setpoint follows: ``lower`` (a heating setpoint, pre-heating) or
#: ``upper`` (a cooling setpoint, pre-cooling).
EDGES = ('lower', 'upper')


@dataclasses.dataclass(frozen=True)
class RuleTarget:
    """
    One zone setpoint the rule writes.

    Attributes
    ----------
    zone : str
        The zone whose band it follows.
    lower_k, upper_k : float
        The input's range [K] (its declared min/max).
    edge : {'lower', 'upper'}
        The band's edge it follows: ``lower`` (``LowerSetp[zone]`` + margin, a heating
        setpoint) or ``upper`` (``UpperSetp[zone]`` - cooling margin, a cooling setpoint).

    """

    zone: str
    lower_k: float = -math.inf
    upper_k: float = math.inf
    edge: str = 'lower'

    def __post_init__(self) -> None:
        """Check the edge."""
        if self.edge not in EDGES:
            raise ValueError(f'expected a band edge in {list(EDGES)}, got {self.edge!r}')


@dataclasses.dataclass(frozen=True)
class SupplyReset:
    """
    A supply temperature the rule writes: a heating curve of the outdoor temperature.

    ``value = clip(max(interp(outdoor, curve) + shift, floor), lower, upper)`` [K]: piecewise
    linear between the points, constant beyond the first and the last.

    Attributes
    ----------
    outdoor : str
        The FMU output read at the decision: the outdoor temperature [K].
    outdoor_k, supply_k : tuple of float
        The curve's points: outdoor temperatures [K] (strictly increasing, at least two) and
        the supply temperatures there [K].
    floor_k : float
        The lowest supply temperature the curve gives after its shift [K].
    lower_k, upper_k : float
        The input's range [K] (its declared min/max).

    """

    outdoor: str
    outdoor_k: tuple[float, ...]
    supply_k: tuple[float, ...]
    floor_k: float = -math.inf
    lower_k: float = -math.inf
    upper_k: float = math.inf

    def __post_init__(self) -> None:
        """Check the curve."""
        x, y = np.asarray(self.outdoor_k, dtype=float), np.asarray(self.supply_k, dtype=float)
        if x.ndim != 1 or len(x) < 2 or x.shape != y.shape or not np.all(np.isfinite(x)) \
                or not np.all(np.isfinite(y)) or not np.all(np.diff(x) > 0):
            raise ValueError('a supply reset needs at least two finite points (outdoor, supply) '
                             f'with strictly increasing outdoor temperatures, got outdoor '
                             f'{list(self.outdoor_k)}, supply {list(self.supply_k)}')
        if math.isnan(self.floor_k):
            raise ValueError('expected a supply floor, got nan')

    def value(self, outdoor_k: float, shift_k: float = 0.0) -> float:
        """
        Return the supply temperature [K] at an outdoor temperature [K], the curve shifted [K].

        Raises
        ------
        ValueError
            For an outdoor temperature that is not finite.

        """
        if not math.isfinite(outdoor_k):
            raise ValueError(f'the supply reset needs a finite outdoor temperature '
                             f'({self.outdoor}), got {outdoor_k!r}')
        curve = float(np.interp(outdoor_k, self.outdoor_k, self.supply_k)) + shift_k
        return float(min(max(curve, self.floor_k, self.lower_k), self.upper_k))


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
    inputs = _overwrite_inputs(case, zones)
    return {name: RuleTarget(str(zone), inputs[name].lower, inputs[name].upper)
            for name, zone in zones.items()}


def _overwrite_inputs(case: TestCase, names: Any) -> dict:
    """Return the FMU's overwrite inputs (name -> its declaration); check ``names`` are some."""
    from mshoot_core.boptest.plant import BoptestPlant
    inputs = BoptestPlant(case, record=[]).inputs
    unknown = [name for name in names if name not in inputs]
    if unknown:
        raise ValueError(f'not overwrite inputs of {case.name}: {unknown}; expected some of '
                         f'{sorted(inputs)}')
    return inputs


def _card_input(card: Any, entry: str, control: Any) -> str:
    """Return the FMU input of a card's control named by ``boptest.<entry>``; check it."""
    variable = card.controls.get(control) if isinstance(control, str) else None
    if variable is None or variable.activate is None:
        raise ValueError(f'model card {card.path}: boptest.{entry} names {control!r}: expected '
                         f'a control with an overwrite switch (activate), one of '
                         f'{sorted(card.controls)}')
    return variable.variable


def supply_reset(card: Any) -> dict[str, SupplyReset]:
    """
    Return the supply reset of a card's ``boptest.supply_reset`` (FMU input -> it), or {}.

    The entry: ``control`` (a control with an overwrite switch, unit K), ``outdoor`` (an output
    of the card, unit K: the outdoor temperature measured at the decision), ``points`` (pairs
    ``[outdoor, supply]`` in degC, outdoor strictly increasing) and ``floor`` (optional, degC:
    the lowest supply after the curve's shift). The reset's range is left open:
    :func:`rule_targets` gives it the input's declared range.

    Raises
    ------
    ValueError
        For an entry that is not a mapping with these keys, or bad values.

    """
    entry = (card.boptest or {}).get('supply_reset')
    if entry is None:
        return {}
    keys = {'control', 'outdoor', 'points', 'floor'}
    where = f'model card {card.path}: boptest.supply_reset'
    if not isinstance(entry, Mapping) or not {'control', 'outdoor', 'points'} <= set(entry) \
            or not set(entry) <= keys:
        raise ValueError(f'{where}: expected a mapping with control, outdoor, points and '
                         f'optionally floor, got {entry!r}')
    name = _card_input(card, 'supply_reset', entry['control'])
    output = card.outputs.get(entry['outdoor']) if isinstance(entry['outdoor'], str) else None
    if output is None:
        raise ValueError(f'{where}: outdoor {entry["outdoor"]!r}: expected an output of the '
                         f'card (the outdoor temperature), one of {sorted(card.outputs)}')
    for label, unit in (('control', card.controls[entry['control']].unit),
                        ('outdoor', output.unit)):
        if unit != 'K':
            raise ValueError(f'{where}: the {label} must be in K, got {unit!r}')
    points = entry['points']
    try:
        pairs = [(float(a), float(b)) for a, b in points]
        floor = float(entry['floor']) + KELVIN if 'floor' in entry else -math.inf
        return {name: SupplyReset(output.variable, tuple(a + KELVIN for a, _ in pairs),
                                  tuple(b + KELVIN for _, b in pairs), floor)}
    except (TypeError, ValueError) as error:
        raise ValueError(f'{where}: points must be at least two pairs [outdoor, supply] in '
                         f'degC, outdoor strictly increasing, and floor a number; got points '
                         f'{points!r}, floor {entry.get("floor")!r} ({error})') from error


def rule_targets(card: Any, case: TestCase) -> dict[str, RuleTarget | SupplyReset]:
    """
    Return the rule's targets of a card: FMU input -> :class:`RuleTarget` or the supply reset.

    Parameters
    ----------
    card : ModelCard
        A card of kind ``boptest`` whose ``boptest.setpoint_zones`` maps heating setpoint
        controls to zones, and optionally ``boptest.cooling_zones`` cooling setpoint controls
        to zones and ``boptest.supply_reset`` a supply temperature (:func:`supply_reset`).
    case : TestCase
        The test case (the declared ranges of its FMU's inputs [K]).

    Raises
    ------
    ValueError
        When the card names no setpoint zone, a control without an overwrite switch, an input
        twice, or a bad supply reset.

    """
    section = card.boptest or {}
    zones = dict(section.get('setpoint_zones') or {})
    if not zones:
        raise ValueError(f'model card {card.path}: the rule needs boptest.setpoint_zones '
                         '(setpoint control -> zone of its comfort band)')
    cooling = section.get('cooling_zones') or {}
    if not isinstance(cooling, Mapping):
        raise ValueError(f'model card {card.path}: boptest.cooling_zones: expected a mapping '
                         f'(cooling setpoint control -> zone), got {cooling!r}')
    twice = sorted(set(zones) & set(cooling))
    if twice:
        raise ValueError(f'model card {card.path}: {twice} in both boptest.setpoint_zones and '
                         'boptest.cooling_zones')
    edges = {}
    for entry, edge, mapping in (('setpoint_zones', 'lower', zones),
                                 ('cooling_zones', 'upper', cooling)):
        edges.update({_card_input(card, entry, control): (str(zone), edge)
                      for control, zone in mapping.items()})
    reset = supply_reset(card)
    if set(reset) & set(edges):
        raise ValueError(f'model card {card.path}: boptest.supply_reset names a zone setpoint')
    inputs = _overwrite_inputs(case, [*edges, *reset])
    targets: dict[str, RuleTarget | SupplyReset] = {
        name: RuleTarget(zone, inputs[name].lower, inputs[name].upper, edge)
        for name, (zone, edge) in edges.items()}
    targets.update({name: dataclasses.replace(r, lower_k=inputs[name].lower,
                                              upper_k=inputs[name].upper)
                    for name, r in reset.items()})
    return targets


@dataclasses.dataclass(frozen=True)
class PreheatRule:
    """
    The pre-heating (and pre-cooling, supply reset) rule (module docstring).

    Parameters
    ----------
    case : TestCase
        The test case (its band).
    targets : dict of str to RuleTarget or SupplyReset
        FMU input -> its zone, edge and range, or its supply reset.
    lead_h : float
        How far beyond the coming step the band is looked at [h], >= 0.
    margin_k : float
        Added to the band's lower bound (heating setpoints) [K], >= 0.
    step_s : float
        The control step [s] (the setpoint is held over it).
    cooling_margin_k : float
        Taken from the band's upper bound (cooling setpoints) [K], >= 0.
    supply_shift_k : float
        Added to the supply reset's curve [K] (before its floor).

    """

    case: TestCase
    targets: Mapping[str, RuleTarget | SupplyReset]
    lead_h: float = 0.0
    margin_k: float = 0.0
    step_s: float = 3600.0
    cooling_margin_k: float = 0.0
    supply_shift_k: float = 0.0

    def __post_init__(self) -> None:
        """Check the parameters."""
        for name in ('lead_h', 'margin_k', 'cooling_margin_k', 'supply_shift_k'):
            value = getattr(self, name)
            low = -math.inf if name == 'supply_shift_k' else 0.0
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= low):
                raise ValueError(f'expected {name} {"finite" if low < 0 else ">= 0"}, got '
                                 f'{value!r}')
        if not self.step_s > 0:
            raise ValueError(f'expected a positive step_s, got {self.step_s!r}')
        unknown = [t.zone for t in self.targets.values()
                   if isinstance(t, RuleTarget) and t.zone not in self.case.zones]
        if unknown:
            raise ValueError(f'unknown zones {unknown}: expected zones of {self.case.name} '
                             f'{self.case.zones}')

    def setpoint(self, t_s: float, zone: str, lower_k: float = -math.inf,
                 upper_k: float = math.inf, edge: str = 'lower') -> float:
        """
        Return a zone's setpoint [K] over the control step starting at ``t_s`` [s].

        The band's ``edge`` is looked up at ``t_s`` and at every data row time in the window
        ``(t_s, t_s + step + lead)``: the highest lower bound plus the margin, or the lowest
        upper bound minus the cooling margin; the result is clipped to [lower_k, upper_k].
        """
        if edge not in EDGES:
            raise ValueError(f'expected a band edge in {list(EDGES)}, got {edge!r}')
        column = self.case.band_columns(zone)[EDGES.index(edge)]
        end = t_s + self.step_s + self.lead_h * 3600.0
        index = self.case.row_times(column)
        rows = index[(index > t_s) & (index < end)]
        band = self.case.lookup(column, np.concatenate([[t_s], rows]))
        value = (float(np.max(band)) + self.margin_k if edge == 'lower'
                 else float(np.min(band)) - self.cooling_margin_k)
        return float(min(max(value, lower_k), upper_k))

    def __call__(self, t_s: float, outputs: Mapping[str, float] | None = None
                 ) -> dict[str, float]:
        """
        Return the overwrites over the step from ``t_s`` (a step policy of run_period).

        Raises
        ------
        ValueError
            When a supply reset's outdoor temperature is not among the ``outputs``.

        """
        overwrites = {}
        for name, target in self.targets.items():
            if isinstance(target, SupplyReset):
                if outputs is None or target.outdoor not in outputs:
                    have = 'none' if outputs is None else f'{len(outputs)} others'
                    raise ValueError(f'the supply reset of {name} reads the outdoor '
                                     f'temperature {target.outdoor}: not among the plant '
                                     f'outputs ({have}; record it)')
                overwrites[name] = target.value(float(outputs[target.outdoor]),
                                                self.supply_shift_k)
            else:
                overwrites[name] = self.setpoint(t_s, target.zone, target.lower_k,
                                                 target.upper_k, target.edge)
        return overwrites
