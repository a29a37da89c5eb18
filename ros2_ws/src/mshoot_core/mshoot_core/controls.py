"""
The controls of a model: unit, limits, safe value and overwrite switch, from its card.

A model card's control may be any quantity (a heat rate in W, a zone setpoint in degC, a
modulation 0-1, ...). What the controller needs to know of each is a :class:`ControlSpec`,
in the control's canonical unit (what the MPC, the setpoints and the records speak):

- ``min``/``max``: the actuator limits (card keys ``min``/``max``, written in the card's
  unit and converted at the boundary); settings only narrow them (``control_min``,
  ``control_max``: :mod:`mshoot_core.settings`);
- ``safe``: the value applied when no plan is left (card key ``safe``; setting
  ``safe_value`` overrides it);
- ``switch``: the control's overwrite switch (card key ``activate``, e.g. BOPTEST's
  ``X_activate``): the last link of the fallback chain may *release* the control
  (the switch set to 0), so the building's own controller acts.

A model built from a card declares its controls as ``model.control_specs``
(:func:`mshoot_core.models.card.build_model`). A model that declares none follows the R1C1
convention: every control has the limits and safe value of the heat rate ``q`` of the
built-in card ``r1c1.yaml`` (:func:`convention`).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
from typing import Any, Sequence

import yaml

__all__ = ['ControlSpec', 'convention', 'model_controls', 'narrowed', 'safe_values',
           'specs_for']


@dataclasses.dataclass(frozen=True)
class ControlSpec:
    """
    One control as the controller sees it (canonical unit).

    Attributes
    ----------
    name : str
        Canonical name (the model input).
    unit : str
        Canonical unit ('' for a dimensionless control).
    min, max : float
        Actuator limits [unit]; NaN where the card gives none.
    safe : float
        Safe value [unit]; NaN where the card gives none.
    switch : str
        Its overwrite switch, the plant's input held at 1 while the control is applied (the
        card's ``activate``; '' for none).

    """

    name: str
    unit: str = ''
    min: float = math.nan  # noqa: A003 (the card's key)
    max: float = math.nan  # noqa: A003 (the card's key)
    safe: float = math.nan
    switch: str = ''

    @property
    def releasable(self) -> bool:
        """Return True when the plant can release the control (it has an overwrite switch)."""
        return bool(self.switch)

    def label(self) -> str:
        """``name [unit]``."""
        return f'{self.name} [{self.unit or "1"}]'


#: The built-in card whose heat rate ``q`` is the R1C1 convention.
CONVENTION_CARD = pathlib.Path(__file__).resolve().parent / 'cards' / 'r1c1.yaml'


@functools.cache
def convention() -> ControlSpec:
    """
    Return the R1C1 convention: the heat rate ``q`` of the built-in card ``r1c1.yaml``.

    Read from the card's YAML (its unit, W, is the canonical one: nothing to convert).
    """
    entry = yaml.safe_load(CONVENTION_CARD.read_text(encoding='utf-8'))['controls']['q']
    return ControlSpec('q', entry['unit'], *(float(entry.get(key, math.nan))
                                             for key in ('min', 'max', 'safe')))


def specs_for(declared: Sequence[ControlSpec], names: Sequence[str]) -> tuple[ControlSpec, ...]:
    """Return the spec of each control of ``names``: the declared one, else the R1C1 convention."""
    by_name = {spec.name: spec for spec in declared}
    return tuple(by_name[n] if n in by_name else dataclasses.replace(convention(), name=n)
                 for n in names)


def model_controls(model: Any, names: Sequence[str]) -> tuple[ControlSpec, ...]:
    """
    Return the specs of the controls ``names`` of ``model``.

    The model's ``control_specs`` where it declares them, else the R1C1 convention
    (:func:`convention`) under each name.
    """
    return specs_for(getattr(model, 'control_specs', None) or (), names)


def narrowed(limit: tuple[float, float], low: float, high: float) -> tuple[float, float]:
    """
    Return the limits ``limit`` narrowed by the overrides ``low``, ``high`` (NaN: none).

    An override only narrows: a NaN limit takes the override; a finite one the tighter.
    """
    lo, hi = (float(v) for v in limit)
    if not math.isnan(low):
        lo = low if math.isnan(lo) else max(lo, low)
    if not math.isnan(high):
        hi = high if math.isnan(hi) else min(hi, high)
    return lo, hi


def safe_values(specs: Sequence[ControlSpec], bounds: Sequence[tuple[float, float]],
                override: float = math.nan) -> tuple[float, ...]:
    """
    Return the safe value of every control [its unit].

    ``override`` (a setting) if not NaN, else the card's ``safe``, else 0 clipped into
    ``bounds`` (the control's limits).
    """
    out = []
    for spec, (low, high) in zip(specs, bounds):
        if not math.isnan(override):
            out.append(float(override))
        elif not math.isnan(spec.safe):
            out.append(float(spec.safe))
        else:
            out.append(float(min(max(0.0, low), high)))
    return tuple(out)
