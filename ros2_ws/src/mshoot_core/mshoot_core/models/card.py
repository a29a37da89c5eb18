"""
Model cards: a zone model described once (YAML) for every application.

A card names the model (an FMU, or a built-in model) and maps its variables
onto the *canonical* names the applications speak: the MPC's controls, the
disturbances filled from the scenario or forecast series of the same name,
the states the MPC shoots over, and the measured outputs::

    fmu: zone.fmu              # relative to the card (or `builtin: r1c1` / `r1c1-fmu`)
    fmi_type: auto             # auto | model-exchange | co-simulation
    tolerance: 1.0e-6          # optional: default that of the role
    time_origin: scenario      # wall-clock time of FMU t = 0: `scenario` or ISO 8601
    monotone: true             # optional: states nondecreasing in their starts and the controls
    parameters: {shgc: 4.6}    # set before every initialisation
    controls:
      q: {variable: q, unit: W, min: -2000, max: 2000, safe: 0}
    disturbances:
      Tout: {variable: Tout, unit: degC}
      solrad: {variable: solrad, unit: W/m2}
      occ: {variable: occ}
    states:
      T: {variable: cair.T, unit: K}
      # Tw: {variable: wall.T, unit: K, measured: false}  # estimated by the controller
    outputs:
      T: {variable: T, unit: degC}

:func:`load_card` checks the YAML against the JSON Schema shipped with the
package (:data:`SCHEMA_PATH`), then against the model itself (variable names
by causality, units, parameters, the FMI type), and reports every problem at
once in one :class:`CardError` naming the card, with the model's valid names
(causality and unit) for every bad name. :func:`build_model` makes the
:class:`~mshoot_core.models.base.Model` the applications use:
an :class:`~mshoot_core.models.fmi.FmiModel` with the name mapping, the
parameters, the overwrite switches held at 1 and, where a unit differs from
the canonical one, the conversion at its boundary
(:class:`CardFmiModel`); or a thermal network with its exact solution
(:class:`~mshoot_core.models.network.NetworkModel`): the card's own ``network``
section, or ``builtin: r1c1`` / ``r2c2``, the networks of the built-in cards of those
names (see ``docs/models.md``).

A state no sensor measures says ``measured: false``: the model's
``measured_states`` leave it out and a controller estimates it
(:mod:`mshoot_core.estimation`).

``monotone: true`` is a claim about the model's physics that only its author can make:
the end states of every interval are nondecreasing in its start states and in every
control, as the temperatures of a thermal RC network are in their start values and in
the heat rates (not in a ventilation rate, say). The model's ``monotone_inputs`` are
then the controls, and the MPC tests the band's feasibility before it solves
(:meth:`~mshoot_core.shooting.ShootingProblem.infeasible_band`); ``false`` withdraws a
built-in model's own claim; absent, the model's own (none for an FMU).

Canonical units (what the applications see): states in SI (temperatures in
K, power W, energy J); inputs and outputs in the scenario's conventions
(temperatures degC, power W, energy J, solar irradiance W/m2, ``dpos`` in %,
``occ`` in persons). Known units: :data:`UNITS`; a unit outside the table is
taken as it is (no conversion), unless the canonical name needs a quantity
(``T``, ``Tout``, ``q``, ... in :data:`NAME_QUANTITY`). Built-in cards:
:data:`CARDS_DIR` (:func:`builtin_card`).

A control's ``min``, ``max`` (actuator limits) and ``safe`` (the value applied when no
plan is left) are written in the entry's ``unit`` (e.g. ``unit: K, min: 278.15``), converted
to the canonical unit at the boundary, and checked against the min/max the FMU declares for
the variable. An entry's unit may differ from the FMU's declared unit of the same quantity
(``unit: degC`` on a variable in K): the card's numbers are then in its unit, the model
speaks the FMU's. See ``docs/controls.md`` and :mod:`mshoot_core.controls`.
"""
from __future__ import annotations

import dataclasses
import datetime
import difflib
import inspect
import json
import logging
import math
import pathlib
from typing import Any, Mapping, Sequence

import jsonschema
import numpy as np
import pandas as pd
import yaml

from mshoot_core import fmu_binary
from mshoot_core.controls import ControlSpec
from mshoot_core.fmu_binary import Library
from mshoot_core.fmu_cache import extract_fmu
from mshoot_core.models import network_spec
from mshoot_core.models.base import IntervalJacobians, Model
from mshoot_core.models.defaults import (CONTROL_TOLERANCE, EMULATOR_TOLERANCE,
                                         FINITE_DIFFERENCE_TOLERANCE, is_card_path)
from mshoot_core.models.fmi import FmiModel, read_cached_description, read_fmu_description
from mshoot_core.models.fmu_variables import fmu_variables, ModelVariable

__all__ = ['builtin_card', 'build_model', 'CardError', 'CardFmiModel', 'CardVariable',
           'CARDS_DIR', 'conversion', 'describe', 'is_card_path', 'load_card', 'ModelCard',
           'SCHEMA_PATH', 'schema', 'schema_problems', 'time_origin_seconds', 'UNITS',
           'write_parameters']

logger = logging.getLogger(__name__)

#: The JSON Schema of a card, shipped with the package.
SCHEMA_PATH = pathlib.Path(__file__).resolve().parents[1] / 'schema' / 'model_card.schema.json'
#: The built-in cards: ``r1c1.yaml`` and ``r2c2.yaml`` (thermal networks), ``r1c1_fmu.yaml``
#: (built-in FMU, Model Exchange), ``r1c1_fmu_cs.yaml`` (Co-Simulation), ...
CARDS_DIR = network_spec.CARDS_DIR
#: The built-in model sources of ``builtin:``.
BUILTIN_SOURCES = ('r1c1', 'r1c1-fmu', 'r2c2', 'setpoint-zone-fmu')
#: The built-in FMUs of ``builtin:`` -> their name in :data:`mshoot_core.fmu_cache.MODELS`.
BUILTIN_FMUS = {'r1c1-fmu': 'r1c1', 'setpoint-zone-fmu': 'setpoint_zone'}
#: The keys naming a card's model: exactly one of them.
SOURCES = ('fmu', 'builtin', 'boptest', 'network')
#: The built-in networks of ``builtin:`` (the cards of the same name): name -> label.
PYTHON_SOURCES = {'r1c1': 'the R1C1 network', 'r2c2': 'the R2C2 network'}
#: Card ``fmi_type`` -> FMI interface name (``auto`` resolves to one of them).
FMI_TYPES = {'model-exchange': 'ModelExchange', 'co-simulation': 'CoSimulation'}
#: Roles a card's model is built for.
ROLES = ('control', 'emulator')
#: The variable sections of a card, in order.
SECTIONS = ('controls', 'disturbances', 'states', 'outputs')
#: Longest list of valid names quoted in one problem.
MAX_LISTED = 40


@dataclasses.dataclass(frozen=True)
class Unit:
    """A unit as an affine map to its SI base: ``si = scale * value + offset``."""

    quantity: str
    scale: float
    offset: float = 0.0


#: The known unit spellings ('' and '1': dimensionless).
UNITS: dict[str, Unit] = {
    'K': Unit('temperature', 1.0), 'degC': Unit('temperature', 1.0, 273.15),
    'W': Unit('power', 1.0), 'kW': Unit('power', 1e3),
    'J': Unit('energy', 1.0), 'Wh': Unit('energy', 3600.0), 'kWh': Unit('energy', 3.6e6),
    'W/m2': Unit('irradiance', 1.0),
    '%': Unit('ratio', 0.01), '1': Unit('ratio', 1.0), '': Unit('ratio', 1.0),
}
#: Canonical unit of each quantity for inputs and outputs (the scenario's conventions)...
IO_UNITS = {'temperature': 'degC', 'power': 'W', 'energy': 'J', 'irradiance': 'W/m2'}
#: ... and for states (SI).
STATE_UNITS = {'temperature': 'K', 'power': 'W', 'energy': 'J', 'irradiance': 'W/m2'}
#: Canonical names with a fixed quantity (the scenario's series and the R1C1's variables).
NAME_QUANTITY = {'T': 'temperature', 'Tout': 'temperature', 'solrad': 'irradiance',
                 'q': 'power', 'Qr': 'energy', 'occ': 'ratio', 'dpos': 'ratio'}
#: Canonical names of dimensionless series with a fixed unit.
NAME_UNIT = {'occ': '1', 'dpos': '%'}


class CardError(ValueError):
    """
    An invalid model card: ``problems`` holds every problem, ``path`` the card.

    The message is one line: the card's path and the problems joined by '; '.
    """

    def __init__(self, path: str | pathlib.Path, problems: Sequence[str]) -> None:
        self.path = pathlib.Path(path)
        self.problems = list(problems)
        super().__init__(f'model card {self.path}: ' + '; '.join(self.problems))


@dataclasses.dataclass(frozen=True)
class CardVariable:
    """
    One mapped variable of a card.

    Attributes
    ----------
    variable : str
        Name of the model variable (the FMU's; default the canonical name).
    unit : str
        Unit of the model variable: the card's, else the FMU's declared unit.
    min, max : float or None
        Actuator limits of a control, in the canonical unit (the card writes them in its
        unit).
    safe : float or None
        Safe value of a control, in the canonical unit (the card writes it in its unit).
    activate : str or None
        FMU input held at 1 whenever this control is applied (overwrite pairs).
    start : float or None
        Initial value of a state in the canonical unit, where an application
        needs one (default: the FMU's start value).
    canonical_unit : str
        Unit the applications see (set by :func:`load_card`).
    causality : str
        Causality of the model variable (``input``, ``output``, ``local``,
        ``state``, ...; set by :func:`load_card`).
    model_start : float or None
        The model's own start value of the variable, in the canonical unit.
    measured : bool
        For a state: whether a sensor measures it (default true); the
        controller estimates the others.
    computed : bool
        For a state of a Model Exchange FMU: a variable computed from its
        continuous states, read by a plant and never written.

    """

    variable: str
    unit: str = ''
    min: float | None = None  # noqa: A003 (the card's key)
    max: float | None = None  # noqa: A003 (the card's key)
    activate: str | None = None
    start: float | None = None
    canonical_unit: str = ''
    safe: float | None = None
    causality: str = ''
    model_start: float | None = None
    measured: bool = True
    computed: bool = False

    def conversion(self) -> tuple[float, float]:
        """``(scale, offset)`` with model value = scale * canonical value + offset."""
        return conversion(self.canonical_unit, self.unit)

    def to_model(self, value: float) -> float:
        """Return a canonical value in the model's (FMU's) unit."""
        scale, offset = self.conversion()
        return scale * float(value) + offset

    def from_model(self, value: float) -> float:
        """Return a model's (FMU's) value in the canonical unit."""
        scale, offset = self.conversion()
        return (float(value) - offset) / scale


@dataclasses.dataclass(frozen=True)
class ModelCard:
    """
    A validated model card (see the module docstring; made by :func:`load_card`).

    Attributes
    ----------
    path : pathlib.Path
        The card file.
    fmu : pathlib.Path or None
        The FMU (absolute; for ``builtin: r1c1-fmu`` the built-in FMU).
    builtin : str or None
        One of :data:`BUILTIN_SOURCES`, or None for a card naming an FMU.
    fmi_type : str
        As written: 'auto', 'model-exchange' or 'co-simulation'.
    interface : str or None
        The FMI interface used ('ModelExchange' or 'CoSimulation'; None for
        a thermal network).
    tolerance : float or None
        Relative integrator tolerance, or None for the role's default.
    time_origin : str
        'scenario' or an ISO 8601 date-time.
    monotone : bool or None
        Whether the model is monotone in its start states and its controls (None: the
        card says nothing, the model's own claim holds).
    parameters : dict
        Variable name -> value, set before every initialisation.
    controls, disturbances, states, outputs : dict of str -> CardVariable
        Canonical name -> mapped variable, in the card's order.
    description : str
        Free text.
    boptest : dict or None
        For a card of kind ``boptest``: ``test_case_dir`` (absolute), ``warmup_days``,
        ``history_step_s``, ``power_signs`` (a KPI power output -> -1: reported with the wrong
        sign), ``setpoint_zones`` (setpoint control -> zone), ``cooling_zones`` (cooling
        setpoint control -> zone), ``supply_reset`` (as the card writes it, or None),
        ``excitation`` (the identification's experiment as the card writes it, or None) and
        ``control``
        (the MPC's ``card`` and ``settings`` as absolute paths, or None).
    network : NetworkSpec or None
        For a thermal network (a card's ``network`` section, or ``builtin: r1c1`` /
        ``r2c2``: the built-in card's): the parsed network
        (:class:`~mshoot_core.models.network_spec.NetworkSpec`).
    validate : bool
        Whether fmpy validates the FMU's modelDescription against the FMI schema (the card
        check and every model built alike; ``validate: false`` relaxes it).
    preload : tuple of Library
        Libraries loaded before the FMU's binary (paths, names, stand-in sources; see
        :mod:`mshoot_core.fmu_binary`).
    testcase_forecast : dict or None
        The card's ``testcase_forecast`` section as written: where its forecast comes from in
        a BOPTEST test case folder (:mod:`mshoot_core.boptest.forecasts`).

    """

    path: pathlib.Path
    fmu: pathlib.Path | None
    builtin: str | None
    fmi_type: str
    interface: str | None
    tolerance: float | None
    time_origin: str
    parameters: dict[str, Any]
    controls: dict[str, CardVariable]
    disturbances: dict[str, CardVariable]
    states: dict[str, CardVariable]
    outputs: dict[str, CardVariable]
    description: str = ''
    boptest: dict[str, Any] | None = None
    monotone: bool | None = None
    network: Any = None
    validate: bool = True
    preload: tuple[Library, ...] = ()
    testcase_forecast: dict[str, Any] | None = None

    @property
    def source(self) -> str:
        """'fmu' (an FMU file named by the card), 'builtin', 'network' or 'boptest'."""
        if self.boptest is not None:
            return 'boptest'
        if self.builtin is not None:
            return 'builtin'
        return 'network' if self.network is not None else 'fmu'

    @property
    def control_names(self) -> tuple[str, ...]:
        return tuple(self.controls)

    @property
    def disturbance_names(self) -> tuple[str, ...]:
        return tuple(self.disturbances)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Return the controls, then the disturbances (the input order of the FMU models)."""
        return tuple(self.controls) + tuple(self.disturbances)

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(self.states)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(self.outputs)

    @property
    def measured_states(self) -> tuple[str, ...]:
        """Return the states a sensor measures (those without ``measured: false``)."""
        return tuple(name for name, v in self.states.items() if v.measured)

    def control_bounds(self, default: tuple[float, float]) -> tuple[tuple[float, float], ...]:
        """(min, max) of every control [canonical unit], ``default`` where the card has none."""
        return tuple((default[0] if v.min is None else v.min,
                      default[1] if v.max is None else v.max) for v in self.controls.values())

    def control_specs(self) -> tuple[ControlSpec, ...]:
        """Return every control as :class:`~mshoot_core.controls.ControlSpec` (canonical unit)."""
        def number(value: float | None) -> float:
            return math.nan if value is None else float(value)
        return tuple(ControlSpec(name, v.canonical_unit, number(v.min), number(v.max),
                                 number(v.safe), v.activate or '')
                     for name, v in self.controls.items())

    def initial_state(self, zone_temperature_k: float) -> np.ndarray:
        """
        Return a start state [canonical units].

        ``T`` from ``zone_temperature_k`` [K], the other states from the card's ``start``, else the
        model's start value.

        Raises
        ------
        ValueError
            If a state other than T has neither.

        """
        values, missing = [], []
        for name, v in self.states.items():
            if name == 'T':
                values.append(float(zone_temperature_k))
            elif v.start is not None:
                values.append(v.start)
            elif v.model_start is not None:
                values.append(v.model_start)
            else:
                values.append(math.nan)
                missing.append(name)
        if missing:
            raise ValueError(f'model card {self.path}: states {missing} need a start value '
                             f'(key start) to begin a run')
        return np.array(values)


# -- units ------------------------------------------------------------------------------------
def _same_unit(a: str, b: str) -> bool:
    return a == b or {a, b} <= {'', '1'}


def conversion(canonical_unit: str, model_unit: str) -> tuple[float, float]:
    """
    ``(scale, offset)`` with model value = scale * canonical value + offset.

    Raises
    ------
    ValueError
        If the units are not of one quantity of :data:`UNITS` (and not equal).

    """
    if _same_unit(canonical_unit, model_unit):
        return 1.0, 0.0
    a, b = UNITS.get(canonical_unit), UNITS.get(model_unit)
    if a is None or b is None or a.quantity != b.quantity:
        raise ValueError(f'unit {model_unit!r} does not convert to {canonical_unit!r}')
    return a.scale / b.scale, (a.offset - b.offset) / b.scale


def canonical_unit(section: str, name: str, unit: str) -> tuple[str, str | None]:
    """
    Return the canonical unit of ``name`` in ``section`` and the problem, if any.

    The canonical unit of ``name`` in ``section`` whose model unit is ``unit``, and the problem
    when it cannot convert (None if it can).
    """
    known = UNITS.get(unit)
    need = NAME_QUANTITY.get(name)
    if need is not None and (known is None or known.quantity != need):
        want = (NAME_UNIT.get(name) or (STATE_UNITS if section == 'states'
                                        else IO_UNITS)[need])
        return want, (f'{section}.{name}: unit {unit!r} does not convert to the canonical '
                      f'{want!r} of {name!r} (known units: {_known_units()})')
    if known is None:
        return unit, None  # a quantity mshoot does not know: passed through as it is
    if name in NAME_UNIT:
        return NAME_UNIT[name], None
    if known.quantity == 'ratio':
        return unit, None
    return (STATE_UNITS if section == 'states' else IO_UNITS)[known.quantity], None


def _known_units() -> str:
    return ', '.join(repr(u) for u in UNITS)


# -- the model's variables --------------------------------------------------------------------
@dataclasses.dataclass
class _Catalogue:
    """The variables of a model by what a card can map them to."""

    label: str
    inputs: list[ModelVariable]
    states: list[ModelVariable]
    outputs: list[ModelVariable]
    switches: list[ModelVariable]  # inputs of any type (activate targets)
    parameters: list[ModelVariable]
    state_kind: str
    python: bool = False


def _fmu_catalogue(label: str, md: Any, interface: str) -> _Catalogue:
    variables = fmu_variables(md)
    by_name = {v.name: v for v in variables}
    real = [v for v in variables if v.type == 'Real']
    inputs = [v for v in real if v.causality == 'input']
    if interface == 'ModelExchange':
        states = [by_name[d.variable.derivative.name] for d in md.derivatives
                  if d.variable.derivative is not None]
        state_kind = 'continuous states'
    else:
        states = [v for v in real if v.causality.split(',')[0] not in
                  ('parameter', 'input', 'calculatedParameter')
                  and v.initial in ('exact', 'approx')]
        state_kind = 'Real variables with a settable start value'
    outputs = [v for v in real if v.causality.split(',')[0] not in
               ('parameter', 'calculatedParameter', 'input')]
    switches = [v for v in variables if v.causality == 'input']
    parameters = [v for v in variables if v.causality != 'input'
                  and v.variability != 'constant'
                  and (v.causality == 'parameter' or v.initial in ('exact', 'approx'))]
    return _Catalogue(label, inputs, states, outputs, switches, parameters, state_kind)


def _network_catalogue(label: str, spec: Any) -> _Catalogue:
    """Return the variables of a thermal network (a :class:`~.network_spec.NetworkSpec`)."""
    inputs = [ModelVariable(name, 'input', unit=unit) for name, unit in spec.inputs.items()]
    parameters = [ModelVariable(name, 'parameter', start=p.value, unit=p.unit)
                  for name, p in spec.parameters.items()]
    states = [ModelVariable(name, 'state', unit='K') for name in spec.nodes]
    outputs = [ModelVariable(name, 'output', unit=o.unit) for name, o in spec.outputs.items()]
    return _Catalogue(label, inputs, states, outputs, [], parameters, f'nodes of {label}',
                      python=True)


def _network_spec(path: pathlib.Path, document: dict, problems: list[str]) -> Any:
    """
    Return the card's thermal network (its own section or a built-in card's), or None.

    Problems of the section are appended, each prefixed with where it is.
    """
    builtin = document.get('builtin')
    if 'network' in document:
        section, where = document['network'], 'network'
    elif builtin in PYTHON_SOURCES:
        section, where = _read_yaml(builtin_card(builtin)).get('network'), f'builtin {builtin}'
    else:
        return None
    try:
        return network_spec.parse_network(section)
    except network_spec.NetworkError as exc:
        problems += [f'{where}: {problem}' for problem in exc.problems]
    return None


def _listing(variables: Sequence[ModelVariable], wanted: str = '') -> str:
    """Return the valid names with causality and unit (close matches of ``wanted`` first)."""
    names = [v.name for v in variables]
    if not names:
        return 'none'
    close = difflib.get_close_matches(wanted, names, n=3, cutoff=0.5) if wanted else []
    ordered = close + [n for n in names if n not in close]
    by_name = {v.name: v for v in variables}
    shown = ', '.join(by_name[n].label() for n in ordered[:MAX_LISTED])
    more = len(ordered) - MAX_LISTED
    return shown + (f' (and {more} more: mshoot card variables FMU lists them all)'
                    if more > 0 else '')


# -- loading ----------------------------------------------------------------------------------
def _yaml_loader() -> type:
    class Loader(yaml.SafeLoader):
        """SafeLoader that refuses a key given twice in one mapping."""

    def construct_mapping(loader: Any, node: Any, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f'key {key!r} is given twice', key_node.start_mark)
            seen.add(key)
        return yaml.SafeLoader.construct_mapping(loader, node, deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping)
    return Loader


def _read_yaml(path: pathlib.Path) -> Any:
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise CardError(path, ['file not found']) from None
    except OSError as exc:
        raise CardError(path, [f'cannot read the file: {exc}']) from None
    try:
        return yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise CardError(path, [' '.join(f'not valid YAML: {exc}'.split())]) from None


def schema() -> dict:
    """Return the JSON Schema of a card (:data:`SCHEMA_PATH`)."""
    return json.loads(SCHEMA_PATH.read_text(encoding='utf-8'))


def _where(path: Sequence[Any]) -> str:
    return '.'.join(str(p) for p in path) if path else 'card'


def schema_problems(document: Any) -> list[str]:
    """Every way ``document`` (a parsed card) breaks the JSON Schema, one sentence each."""
    spec = schema()
    validator = jsonschema.Draft202012Validator(spec)
    problems = []
    for error in sorted(validator.iter_errors(document), key=lambda e: list(map(str, e.path))):
        where = _where(list(error.path))
        kind = error.validator
        if kind == 'oneOf' and not error.path:
            given = [key for key in SOURCES if isinstance(document, dict) and key in document]
            both = len(given) > 1
            problems.append(f"give {'only ' if both else ''}one of 'fmu' (path of an FMU, "
                            f"relative to the card), 'builtin' (one of "
                            f"{list(BUILTIN_SOURCES)}), 'boptest' (a BOPTEST test case) or "
                            f"'network' (a thermal network)"
                            + (f', not several (got {given})' if both else ''))
        elif kind == 'additionalProperties':
            allowed = sorted(error.schema.get('properties', {}))
            extra = sorted(set(error.instance) - set(allowed))
            problems.append(f'{where}: unknown key{"s" if len(extra) > 1 else ""} '
                            f'{", ".join(map(repr, extra))}; allowed: {", ".join(allowed)}')
        elif kind == 'required':
            missing = error.message.split("'")[1] if "'" in error.message else error.message
            problems.append(f'{where}: missing required key {missing!r}' if error.path
                            else f'missing required key {missing!r}')
        elif kind == 'pattern' and error.schema is spec['$defs']['name']:
            problems.append(f'{where}: name {error.instance!r} must be an identifier (letters, '
                            'digits and _, not starting with a digit)')
        elif kind == 'type':
            expected = error.validator_value
            expected = ' or '.join(expected) if isinstance(expected, list) else expected
            problems.append(f'{where}: expected {expected}, got {error.instance!r}')
        elif kind == 'enum':
            problems.append(f'{where} must be one of {error.validator_value}, got '
                            f'{error.instance!r}')
        elif kind == 'minProperties':
            problems.append(f'{where}: needs at least one entry')
        else:
            problems.append(f'{where}: {error.message}')
    return problems


#: The keys of a variable entry, by section (as in the schema).
ENTRY_KEYS = {'controls': ('variable', 'unit', 'min', 'max', 'safe', 'activate'),
              'disturbances': ('variable', 'unit'),
              'states': ('variable', 'unit', 'start', 'measured', 'computed'),
              'outputs': ('variable', 'unit')}


def _variable_section(document: dict, section: str,
                      schema_problems: Sequence[str]) -> dict[str, dict]:
    """
    Return the entries of a section to check against the model.

    Without the keys the schema refused (unknown keys, wrong types: reported already).
    """
    raw = document.get(section)
    if not isinstance(raw, dict):
        return {}
    out = {}
    for name, spec in raw.items():
        if not isinstance(spec, dict):
            continue
        out[name] = {key: value for key, value in spec.items() if key in ENTRY_KEYS[section]
                     and not any(p.startswith(f'{section}.{name}.{key}:')
                                 for p in schema_problems)}
    return out


def load_card(path: str | pathlib.Path) -> ModelCard:
    """
    Read and validate a model card (YAML), against the schema and against its model.

    Parameters
    ----------
    path : path
        The card file.

    Returns
    -------
    ModelCard

    Raises
    ------
    CardError
        With every problem at once: schema violations (unknown or missing keys,
        wrong types), a missing or unreadable FMU, an FMI type the FMU lacks,
        variable names the model does not have in that role (each with the
        model's valid names, causality and unit), units that do not convert,
        bad parameters, a bad time origin.

    """
    path = pathlib.Path(path).expanduser()
    document = _read_yaml(path)
    if document is None:
        raise CardError(path, ['the file is empty'])
    if isinstance(document, dict) and isinstance(document.get('time_origin'),
                                                 (datetime.date, datetime.datetime)):
        # YAML reads an unquoted date-time as one
        document['time_origin'] = document['time_origin'].isoformat()
    problems = schema_problems(document)
    if not isinstance(document, dict):
        raise CardError(path, problems or ['a card must be a mapping of keys'])
    sections = {section: _variable_section(document, section, problems)
                for section in SECTIONS}
    time_origin = document.get('time_origin', 'scenario')
    if isinstance(time_origin, str):
        problem = _time_origin_problem(time_origin)
        if problem:
            problems.append(problem)
    fmi_type = document.get('fmi_type', 'auto')
    tolerance = document.get('tolerance')
    validate = document.get('validate', True) is not False
    preload = _preload(path, document.get('preload'), problems)
    parameters = document.get('parameters') or {}
    if not isinstance(parameters, dict):
        parameters = {}
    boptest = None
    if isinstance(document.get('boptest'), dict):
        if preload:
            problems.append("preload: a BOPTEST test case's FMU takes its stand-ins from the "
                            "test case folder's shim/ (one C file and a version script)")
        boptest, fmu_name = _boptest_spec(path, document['boptest'], problems)
        if fmu_name is not None:
            document = {**document, 'fmu': fmu_name}
    network = _network_spec(path, document, problems)
    catalogue, fmu, interface = _catalogue(path, document, fmi_type, problems, network,
                                           validate)
    if catalogue is not None and boptest is not None:
        # a BOPTEST plant's states are measured: its outputs
        catalogue = dataclasses.replace(
            catalogue, states=list(catalogue.outputs),
            state_kind='outputs (the states of a BOPTEST plant are measured)')
    variables = {}
    if catalogue is not None:
        variables = _check_variables(catalogue, sections, problems)
        problems += _parameter_problems(catalogue, parameters)
    if problems:
        raise CardError(path, problems)
    card = ModelCard(
        path=path, fmu=fmu, builtin=document.get('builtin'), fmi_type=fmi_type,
        interface=interface, tolerance=None if tolerance is None else float(tolerance),
        time_origin=time_origin, parameters=dict(parameters),
        description=document.get('description', ''), boptest=boptest,
        monotone=document.get('monotone'), network=network, validate=validate,
        preload=preload, testcase_forecast=document.get('testcase_forecast'), **variables)
    try:
        comfort_bands(card)
    except ValueError as error:
        raise CardError(path, [str(error)]) from None
    return card


def _preload(path: pathlib.Path, entries: Any, problems: list[str]) -> tuple[Library, ...]:
    """Resolve a card's ``preload`` list (paths and sources relative to the card)."""
    if not isinstance(entries, list):
        return ()  # absent, or the schema reported it
    out = []
    for k, entry in enumerate(entries):
        where = f'preload.{k}'
        if isinstance(entry, str) and entry:
            if '/' not in entry:  # a name the dynamic linker finds
                out.append(Library(path=entry))
                continue
            file = (path.parent / pathlib.Path(entry).expanduser()).resolve()
            if not file.is_file():
                problems.append(f'{where}: library not found: {file} (the path is relative to '
                                "the card's folder)")
                continue
            out.append(Library(path=str(file)))
        elif isinstance(entry, dict) and isinstance(entry.get('source'), str):
            folder = (path.parent / pathlib.Path(entry['source']).expanduser()).resolve()
            soname = entry.get('soname')
            if not folder.is_dir():
                problems.append(f'{where}.source: folder not found: {folder} (the path is '
                                "relative to the card's folder)")
                continue
            out.append(Library(source=folder,
                               soname=soname if isinstance(soname, str) else None))
    return tuple(out)


def _boptest_spec(path: pathlib.Path, spec: dict,
                  problems: list[str]) -> tuple[dict[str, Any] | None, str | None]:
    """Resolve a card's ``boptest`` entry: (spec with the absolute folder, its FMU) or Nones."""
    from mshoot_core.boptest.testcase import default_directory, find_fmu
    folder = spec.get('test_case')
    try:
        directory = ((path.parent / pathlib.Path(folder).expanduser()).resolve()
                     if isinstance(folder, str) else default_directory())
    except FileNotFoundError as error:  # no folder given and $MSHOOT_BOPTEST_DIR unset
        problems.append(f'boptest.test_case: {error}')
        return None, None
    try:
        fmu = find_fmu(directory)
    except FileNotFoundError:
        problems.append(f'boptest.test_case: no BOPTEST test case (wrapped.fmu or '
                        f'models/wrapped.fmu) in {directory}'
                        + ('' if isinstance(folder, str) else
                           ' (the default folder; set $MSHOOT_BOPTEST_DIR or test_case)'))
        return None, None
    warmup = spec.get('warmup_days', 7.0)
    if isinstance(warmup, bool) or not isinstance(warmup, (int, float)) or warmup < 0:
        return None, None  # the schema reported it
    history = spec.get('history_step_s', 0.0)
    if isinstance(history, bool) or not isinstance(history, (int, float)) or history < 0:
        return None, None  # the schema reported it
    zones = spec.get('setpoint_zones') or {}
    signs = spec.get('power_signs') or {}
    cooling = spec.get('cooling_zones') or {}
    return {'test_case_dir': str(directory), 'warmup_days': float(warmup),
            'power_signs': {str(k): float(v) for k, v in signs.items()}
            if isinstance(signs, dict) else {},
            'history_step_s': float(history),
            'setpoint_zones': {str(k): str(v) for k, v in zones.items()}
            if isinstance(zones, dict) else {},
            'cooling_zones': {str(k): str(v) for k, v in cooling.items()}
            if isinstance(cooling, dict) else {},
            'supply_reset': dict(spec['supply_reset'])
            if isinstance(spec.get('supply_reset'), dict) else None,
            'excitation': dict(spec['excitation']) if isinstance(spec.get('excitation'), dict)
            else None,
            'control': _boptest_control(path, spec.get('control'), problems)}, str(fmu)


def _boptest_control(path: pathlib.Path, entry: Any,
                     problems: list[str]) -> dict[str, str] | None:
    """
    Resolve ``boptest.control``: its ``card`` and ``settings`` as absolute file paths.

    Each is a file relative to the card's folder, or else the name of a packaged one (a
    built-in card, :func:`builtin_card`; packaged settings,
    :data:`mshoot_core.settings.SETTINGS_DIR`). Problems are appended; None without the entry.
    """
    from mshoot_core.settings import SETTINGS_DIR
    if not isinstance(entry, dict):
        return None  # none, or the schema reported it
    packaged = {'card': CARDS_DIR, 'settings': SETTINGS_DIR}
    out = {}
    for key, value in entry.items():
        if key not in packaged or not isinstance(value, str) or not value:
            continue  # the schema reported it
        local = (path.parent / pathlib.Path(value).expanduser()).resolve()
        named = packaged[key] / f'{value}.yaml'
        if local.is_file():
            out[key] = str(local)
        elif '/' not in value and named.is_file():
            out[key] = str(named)
        else:
            names = sorted(p.stem for p in packaged[key].glob('*.yaml'))
            problems.append(f'boptest.control.{key}: {value!r} is neither a file relative to '
                            f"the card's folder ({local}) nor a packaged {key} {names}")
    return out


def _time_origin_problem(value: str) -> str | None:
    if value == 'scenario':
        return None
    try:
        datetime.datetime.fromisoformat(value)
    except ValueError:
        return (f"time_origin must be 'scenario' or an ISO 8601 date-time (e.g. "
                f"'2018-04-05T00:00:00'), got {value!r}")
    return None


def _catalogue(path: pathlib.Path, document: dict, fmi_type: Any, problems: list[str],
               network: Any = None, validate: bool = True
               ) -> tuple[_Catalogue | None, pathlib.Path | None, str | None]:
    """Return the model's variables, its FMU (absolute) and the FMI interface used."""
    builtin, fmu_name = document.get('builtin'), document.get('fmu')
    own = 'network' in document
    if network is not None and fmu_name is None and (builtin is not None) != own:
        label = PYTHON_SOURCES.get(builtin, f'the network of {path.name}')
        if 'fmi_type' in document and fmi_type != 'auto':
            problems.append(f'fmi_type: {label} is not an FMU; leave fmi_type out')
        return _network_catalogue(label, network), None, None
    if ((builtin is None) == (fmu_name is None) or 'network' in document
            or builtin in PYTHON_SOURCES or fmi_type not in ('auto', *FMI_TYPES)):
        return None, None, None
    if builtin in BUILTIN_FMUS:
        from mshoot_core.fmu_cache import find_fmu
        try:
            fmu = find_fmu(BUILTIN_FMUS[builtin])
        except FileNotFoundError as exc:
            problems.append(f'builtin: {exc}')
            return None, None, None
    elif isinstance(fmu_name, str):
        fmu = (path.parent / pathlib.Path(fmu_name).expanduser()).resolve()
        if not fmu.exists():
            problems.append(f"fmu: file not found: {fmu} (the path is relative to the card's "
                            f'folder {path.parent.resolve()})')
            return None, None, None
    else:
        return None, None, None
    try:
        md = _description(fmu, validate)
    except ValueError as exc:  # not a zip, not readable, FMI 3.0, breaks the schema: labelled
        problems.append(f'fmu: {" ".join(str(exc).split())}')
        return None, None, None
    except Exception as exc:  # noqa: BLE001 - any unreadable FMU is a problem of the card
        problems.append(f'fmu: cannot read the model description of {fmu}: '
                        f'{" ".join(str(exc).split())}')
        return None, None, None
    if md.fmiVersion != '2.0':  # (an FMI 3.0 FMU is refused as one when it is read)
        problems.append(f'fmu: {fmu.name} is an FMI {md.fmiVersion} FMU: only FMI 2.0 FMUs are '
                        'supported')
        return None, None, None
    available = [name for name, kind in (('ModelExchange', md.modelExchange),
                                         ('CoSimulation', md.coSimulation)) if kind]
    if fmi_type == 'auto':
        interface = 'ModelExchange' if 'ModelExchange' in available else available[0]
    else:
        interface = FMI_TYPES[fmi_type]
        if interface not in available:
            problems.append(f'fmi_type: {fmu.name} offers {available} only, got {fmi_type!r}')
            return None, fmu, None
    label = f"{fmu.name} ({'Model Exchange' if interface == 'ModelExchange' else 'Co-Simulation'})"
    return _fmu_catalogue(label, md, interface), fmu, interface


def _description(fmu: pathlib.Path, validate: bool) -> Any:
    """
    Return an FMU's modelDescription as every model of it reads it (one validation policy).

    An FMU file is extracted into the cache and read as :class:`FmiModel` reads it
    (validated once per file, then kept); an FMU folder is read in place.
    """
    if fmu.is_dir():
        return read_fmu_description(fmu, fmu.name, validate)
    return read_cached_description(extract_fmu(fmu), fmu.name, validate)


def _check_variables(catalogue: _Catalogue, sections: dict[str, dict[str, dict]],
                     problems: list[str]) -> dict[str, dict[str, CardVariable]]:
    """Resolve the card's variables against the model; problems appended."""
    kinds = {'controls': (catalogue.inputs, 'a Real input'),
             'disturbances': (catalogue.inputs, 'a Real input'),
             'states': (catalogue.states, f'one of the {catalogue.state_kind}'),
             'outputs': (catalogue.outputs, 'a Real variable (not a parameter or input)')}
    out: dict[str, dict[str, CardVariable]] = {}
    both = sorted(set(sections['controls']) & set(sections['disturbances']))
    if both:
        problems.append(f'{both} are both controls and disturbances')
    for section in SECTIONS:
        resolved: dict[str, CardVariable] = {}
        for name, spec in sections[section].items():
            where = f'{section}.{name}'
            choices, what = kinds[section]
            mine: list[str] = []
            if section == 'states' and spec.get('computed', False):
                # a state a Model Exchange plant reads from a variable its continuous states
                # determine (FmiModel.derived_states): only a plant can use such a card
                if catalogue.state_kind != 'continuous states':
                    mine.append(f'{where}.computed: for a state of a Model Exchange FMU; the '
                                f'states of {catalogue.label} are {catalogue.state_kind}')
                choices, what = kinds['outputs']
            by_name = {v.name: v for v in choices}
            variable = spec.get('variable', name)
            found = by_name.get(variable)
            if found is None:
                mine.append(f'{where}: {variable!r} is not {what} of {catalogue.label}; '
                            f'valid: {_listing(choices, variable)}')
            elif catalogue.python and variable != name:
                mine.append(f'{where}: {catalogue.label} keeps its own names: use {variable!r} '
                            'as the canonical name too')
            unit = card_unit = spec.get('unit')
            if found is not None and unit is None:
                unit = card_unit = found.unit
            elif found is not None and found.unit and not _same_unit(unit, found.unit) and (
                    catalogue.python or found.unit in UNITS):
                if _convertible(unit, found.unit) and not catalogue.python:
                    unit = found.unit  # the card's numbers in its unit, the model in the FMU's
                else:
                    mine.append(f'{where}: unit {unit!r} differs from the unit {found.unit!r} '
                                f'{catalogue.label} declares for {variable!r}')
            canonical, problem = canonical_unit(section, name, unit or '')
            if problem and not mine:  # a unit the model contradicts is one problem
                mine.append(problem)
            elif problem:
                pass
            elif catalogue.python and not _same_unit(canonical, unit or ''):
                mine.append(f'{where}: {catalogue.label} has no unit conversion')
            if section == 'controls' and not mine and found is not None:
                mine += _limit_problems(where, spec, card_unit or '', found, catalogue.label)
            problems += mine
            if mine or found is None:
                continue
            scale, offset = conversion(canonical, unit)
            model_start = (None if found.start is None else (found.start - offset) / scale)
            low, high, safe = (_in_unit(spec.get(key), card_unit or '', canonical)
                               for key in ('min', 'max', 'safe'))
            resolved[name] = CardVariable(
                variable=variable, unit=unit, min=low, max=high, safe=safe,
                activate=spec.get('activate'), start=spec.get('start'),
                canonical_unit=canonical, causality=found.causality, model_start=model_start,
                measured=bool(spec.get('measured', True)),
                computed=bool(spec.get('computed', False)))
        out[section] = resolved
    _check_unique(out, problems)
    _check_switches(catalogue, sections, problems)
    if catalogue.python:
        mapped = {spec.get('variable', name) for s in ('controls', 'disturbances')
                  for name, spec in sections[s].items()}
        missing = [v.name for v in catalogue.inputs if v.name not in mapped]
        if missing:
            problems.append(f'{catalogue.label} needs every input mapped: missing {missing} (as '
                            'controls or disturbances)')
    return out


def _convertible(a: str | None, b: str) -> bool:
    """Return True when units ``a`` and ``b`` are known units of one quantity."""
    ua, ub = UNITS.get(a or ''), UNITS.get(b)
    return ua is not None and ub is not None and ua.quantity == ub.quantity


def _in_unit(value: float | None, unit: str, target: str) -> float | None:
    """Return ``value`` [unit] in ``target`` (None stays None)."""
    if value is None:
        return None
    scale, offset = conversion(unit, target) if _convertible(unit, target) else (1.0, 0.0)
    return scale * float(value) + offset


def _limit_problems(where: str, spec: Mapping[str, Any], unit: str, found: ModelVariable,
                    label: str) -> list[str]:
    """
    Check a control's min, max and safe (in the card's ``unit``) against each other and the FMU.

    The FMU's declared min/max of the variable (in its unit) bound the card's limits.
    """
    low, high, safe = spec.get('min'), spec.get('max'), spec.get('safe')
    shown = f' {unit}' if unit else ''
    if low is not None and high is not None and not low <= high:
        return [f'{where}: min {low} must be <= max {high}']
    out = []
    if safe is not None and not ((low is None or low <= safe) and (high is None or safe <= high)):
        out.append(f'{where}: safe {safe}{shown} must be within [min, max] = '
                   f'[{_bound(low, "-inf")}, {_bound(high, "inf")}]{shown}')
    model_unit = found.unit if _convertible(unit, found.unit) else unit
    for key, value, fmu_value, outside in (('min', low, found.min, lambda a, b: a < b),
                                           ('max', high, found.max, lambda a, b: a > b)):
        if value is None or fmu_value is None:
            continue
        in_model = _in_unit(value, unit, model_unit)
        if outside(in_model, fmu_value) and not math.isclose(in_model, fmu_value,
                                                             rel_tol=1e-9, abs_tol=1e-9):
            converted = f' (= {in_model:g} {model_unit})' if model_unit != unit else ''
            out.append(f'{where}: {key} {value:g}{shown}{converted} is outside the '
                       f'{"min" if key == "min" else "max"} {fmu_value:g} {model_unit} '
                       f'{label} declares for {found.name!r} (a limit written in another '
                       'unit than the entry unit?)')
    return out


def _check_unique(out: dict[str, dict[str, CardVariable]], problems: list[str]) -> None:
    inputs = [(f'{s}.{n}', v.variable) for s in ('controls', 'disturbances')
              for n, v in out[s].items()]
    for section, entries in (('inputs', inputs),
                             *((s, [(f'{s}.{n}', v.variable) for n, v in out[s].items()])
                               for s in ('states', 'outputs'))):
        seen: dict[str, str] = {}
        for where, variable in entries:
            if variable in seen:
                problems.append(f'{where}: {variable!r} is already mapped by {seen[variable]}')
            else:
                seen[variable] = where


def _check_switches(catalogue: _Catalogue, sections: dict[str, dict[str, dict]],
                    problems: list[str]) -> None:
    mapped = {spec.get('variable', name) for s in ('controls', 'disturbances')
              for name, spec in sections[s].items()}
    switches = {s.name for s in catalogue.switches}
    seen: dict[str, str] = {}
    for name, spec in sections['controls'].items():
        switch = spec.get('activate')
        if switch is None:
            continue
        where = f'controls.{name}.activate'
        if catalogue.python:
            problems.append(f'{where}: {catalogue.label} has no overwrite switches')
        elif switch not in switches:
            problems.append(f'{where}: {switch!r} is not an input of {catalogue.label}; '
                            f'valid: {_listing(catalogue.switches, switch)}')
        elif switch in mapped:
            problems.append(f'{where}: {switch!r} is mapped as a control or disturbance')
        elif switch in seen:
            problems.append(f'{where}: {switch!r} already activates {seen[switch]}')
        else:
            seen[switch] = name


def _parameter_problems(catalogue: _Catalogue, parameters: Mapping[str, Any]) -> list[str]:
    by_name = {v.name: v for v in catalogue.parameters}
    problems = []
    for name, value in parameters.items():
        var = by_name.get(name)
        if var is None:
            problems.append(f'parameters.{name}: not a settable parameter of {catalogue.label};'
                            f' valid: {_listing(catalogue.parameters, name)}')
            continue
        kind = {'Enumeration': 'Integer'}.get(var.type, var.type)
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = {'Real': number and math.isfinite(float(value)) if number else False,
              'Integer': isinstance(value, int) and not isinstance(value, bool),
              'Boolean': isinstance(value, bool), 'String': isinstance(value, str)}.get(kind)
        if not ok:
            problems.append(f'parameters.{name}: expected a {kind} value for {var.label()}, '
                            f'got {value!r}')
    return problems


# -- writing ----------------------------------------------------------------------------------
def write_parameters(source: str | pathlib.Path, values: Mapping[str, float],
                     target: str | pathlib.Path, header: Sequence[str] = (),
                     description: str | None = None) -> pathlib.Path:
    """
    Write a copy of the card ``source`` with the parameter ``values``; the card it is loads.

    A thermal network card's values replace those of its ``network.parameters`` (an entry's
    ``value``; its ``min``, ``max`` and ``free`` kept); another card's go to its
    ``parameters`` (set before every initialisation). The rest of the card is kept as it is,
    but a relative ``fmu`` path, made absolute for the copy's folder. The copy is written
    from the parsed YAML: the comments of ``source`` are not kept; ``header`` (lines of text)
    heads the copy as comments.

    Parameters
    ----------
    source : path
        The card copied (not written).
    values : mapping of str -> float
        Parameter name -> value (in the parameter's unit).
    target : path
        The copy written (its folder created).
    header : sequence of str
        Comment lines, without their ``#``.
    description : str, optional
        The copy's ``description`` (default: that of ``source``).

    Returns
    -------
    pathlib.Path
        ``target``.

    Raises
    ------
    ValueError
        For a name that is not a parameter of a network card.
    CardError
        If ``source`` cannot be read, or the copy does not load.

    """
    source, target = pathlib.Path(source), pathlib.Path(target)
    document = _read_yaml(source)
    if not isinstance(document, dict):
        raise CardError(source, [f'expected a mapping, got {document!r}'])
    if isinstance(document.get('network'), dict):
        parameters = document['network'].setdefault('parameters', {})
        unknown = sorted(set(values) - set(parameters))
        if unknown:
            raise ValueError(f'{source}: unknown network parameters {unknown}; expected names '
                             f'from {list(parameters)}')
    else:
        parameters = document.setdefault('parameters', {})
    for name, value in values.items():
        if isinstance(parameters.get(name), dict):
            parameters[name]['value'] = float(value)
        else:
            parameters[name] = float(value)
    if description is not None:
        document['description'] = description
    if isinstance(document.get('fmu'), str):  # as load_card reads it, for the copy's folder
        document['fmu'] = str((source.parent / pathlib.Path(document['fmu']).expanduser())
                              .resolve())
    target.parent.mkdir(parents=True, exist_ok=True)
    comments = ''.join(f'# {line}\n' if line else '#\n' for line in header)
    target.write_text(comments + yaml.safe_dump(document, sort_keys=False, width=99),
                      encoding='utf-8')
    load_card(target)
    return target


# -- building the model -----------------------------------------------------------------------
def builtin_card(name: str) -> pathlib.Path:
    """
    Path of a built-in card: 'r1c1', 'r1c1_fmu', 'r1c1_fmu_cs' or 'r2c2'.

    Raises
    ------
    ValueError
        For another name.

    """
    path = CARDS_DIR / f'{name}.yaml'
    if not path.is_file():
        names = sorted(p.stem for p in CARDS_DIR.glob('*.yaml'))
        raise ValueError(f'no built-in card {name!r}; built-in cards: {names}')
    return path


def time_origin_seconds(card: ModelCard, scenario_start: str | datetime.datetime | None) -> float:
    """
    Seconds from the scenario's first row to FMU time 0 (the model's ``time_origin_s``).

    FMU time = scenario time [s] - this value: 0 for ``time_origin: scenario``.

    Parameters
    ----------
    card : ModelCard
        The card (its ``time_origin``).
    scenario_start : str or datetime or None
        The scenario's first row (``scenario.attrs['start']``, ISO 8601).

    Raises
    ------
    ValueError
        If the card gives a date-time and the scenario's start is unknown, or
        one is time-zone aware and the other not.

    """
    if card.time_origin == 'scenario':
        return 0.0
    if scenario_start is None:
        raise ValueError(f'model card {card.path}: time_origin {card.time_origin} needs the '
                         "scenario's start date-time")
    origin = datetime.datetime.fromisoformat(card.time_origin)
    start = (scenario_start if isinstance(scenario_start, datetime.datetime)
             else datetime.datetime.fromisoformat(str(scenario_start)))
    if (origin.tzinfo is None) != (start.tzinfo is None):
        raise ValueError(f'model card {card.path}: time_origin {card.time_origin} and the '
                         f'scenario start {start.isoformat()} must both have a time zone or '
                         'neither')
    return (origin - start).total_seconds()


def role_tolerance(role: str) -> float:
    """Return a role's default integrator tolerance (see :mod:`mshoot_core.models.registry`)."""
    if role not in ROLES:
        raise ValueError(f'role must be one of {list(ROLES)}, got {role!r}')
    return CONTROL_TOLERANCE if role == 'control' else EMULATOR_TOLERANCE


def build_model(card: ModelCard | str | pathlib.Path, role: str = 'control',
                time_origin_s: float = 0.0, tolerance: float | None = None) -> Model:
    """
    Build the model a card describes, speaking its canonical names and units.

    Parameters
    ----------
    card : ModelCard or path
        A card (paths are loaded with :func:`load_card`).
    role : {'control', 'emulator'}
        What the model is for: sets the default tolerance (control
        :data:`~mshoot_core.models.registry.CONTROL_TOLERANCE`, emulator
        :data:`~mshoot_core.models.registry.EMULATOR_TOLERANCE`) and the FMU
        instance's name.
    time_origin_s : float
        Caller time [s] of FMU time 0 (see :func:`time_origin_seconds`).
    tolerance : float, optional
        Tolerance when the card sets none (default: that of the role).

    Returns
    -------
    Model
        An :class:`~mshoot_core.models.fmi.FmiModel` (a :class:`CardFmiModel`
        where a unit converts) with inputs ``controls + disturbances``, or a
        :class:`~mshoot_core.models.network.NetworkModel` with the network's inputs.

    Raises
    ------
    CardError
        For a card path that does not load.
    ValueError
        For a bad role or tolerance, or a time origin this FmiModel cannot use.

    """
    if not isinstance(card, ModelCard):
        card = load_card(card)
    default = role_tolerance(role)
    tol = card.tolerance if card.tolerance is not None else (
        default if tolerance is None else tolerance)
    if isinstance(tol, bool) or not 0.0 < float(tol) < 1.0:
        raise ValueError(f'tolerance must be in (0, 1), got {tol!r}')
    if card.boptest is not None:
        from mshoot_core.boptest.card_plant import CardPlant
        if role != 'emulator':
            raise ValueError(f'model card {card.path}: a BOPTEST test case is an emulator '
                             f'(a plant), not a {role} model')
        model = CardPlant(card, instance_name=f'mshoot-{role}')
        model.time_origin_s = float(time_origin_s)
        model.control_specs = card.control_specs()
        return model
    if card.network is not None:
        from mshoot_core.models.network import NetworkModel
        model = NetworkModel(card.network, values=card.parameters,
                             control_names=card.control_names,
                             comfort_states=_comfort_states(card),
                             measured_states=card.measured_states)
        model.control_specs = card.control_specs()
        model.comfort_bands = comfort_bands(card)
        return _claim_monotone(model, card)
    options: dict[str, Any] = {}
    if 'time_origin_s' in inspect.signature(FmiModel).parameters:
        options['time_origin_s'] = float(time_origin_s)
    elif time_origin_s:
        raise ValueError(f'model card {card.path}: time_origin {card.time_origin} needs '
                         'absolute FMU time, which this FmiModel does not support yet')
    conversions = _Conversions.of(card)
    cls, extra = (FmiModel, {}) if conversions.identity else (CardFmiModel,
                                                              {'conversions': conversions})
    fixed = {v.activate: 1 for v in card.controls.values() if v.activate is not None}
    # (a plant releases them: FmuPlant.plant_switches)
    computed = tuple(n for n, v in card.states.items() if v.computed)
    if computed:  # a plant only (FmiModel.derived_states)
        options['computed_states'] = computed
    model = cls(card.fmu,
                inputs={n: v.variable for s in ('controls', 'disturbances')
                        for n, v in getattr(card, s).items()},
                states={n: v.variable for n, v in card.states.items()},
                outputs={n: v.variable for n, v in card.outputs.items()},
                parameters=card.parameters, tolerance=float(tol), fmi_type=card.interface,
                instance_name=f'mshoot-{role}', fixed_inputs=fixed, validate=card.validate,
                libraries=card.preload, **extra, **options)
    if role == 'control':
        finite_difference_tolerance(model, card)
    # What controllers and nodes read (registry.control_interface): the card's controls, and
    # its zone air temperatures (T, T_<zone>) as the states the comfort band bounds.
    model.control_names = tuple(card.control_names)
    model.control_specs = card.control_specs()  # units, limits, safe values, switches
    model.comfort_states = _comfort_states(card)
    model.comfort_bands = comfort_bands(card)  # a zone's own band, when the card has several
    model.measured_states = card.measured_states  # the others are estimated
    logger.debug('built %r from %s for the %s', model, card.path, role)
    return _claim_monotone(model, card)


def _comfort_states(card: ModelCard) -> tuple[str, ...]:
    """Return the card's zone air temperatures (``T``, ``T_<zone>``): bounded by the band."""
    return tuple(n for n in card.state_names if n == 'T' or n.startswith('T_'))


def comfort_bands(card: ModelCard) -> dict[str, tuple[str, str]]:
    """
    Return each zone temperature's own comfort band series: ``{T_<zone>: (lower, upper)}``.

    A card whose ``testcase_forecast`` names the bands of several zones bounds each zone air
    temperature ``T_<zone>`` by its zone's band (``comfort_min_<zone>``, ``comfort_max_<zone>``:
    :func:`~mshoot_core.safety.zone_band_series`, the series its forecast carries); with one
    band or none, every zone temperature is bounded by the one band (an empty map).

    Raises
    ------
    ValueError
        With several bands, for a zone temperature whose zone has none (the zones named).

    """
    from mshoot_core.safety import zone_band_series
    section = card.testcase_forecast if isinstance(card.testcase_forecast, Mapping) else {}
    bands = section.get('bands')
    zones = [str(z) for z in bands] if isinstance(bands, Mapping) else []
    if len(zones) < 2:
        return {}
    states = _comfort_states(card)
    missing = [s for s in states if s[len('T_'):] not in zones]
    if missing:
        raise ValueError(f'testcase_forecast.bands: the zone temperatures {missing} have no '
                         f'band of their own (T_<zone> for a zone of {zones})')
    return {s: zone_band_series(s[len('T_'):]) for s in states}


def finite_difference_tolerance(model: FmiModel, card: ModelCard) -> str | None:
    """
    Keep the finite differences of a control FMU without sensitivities accurate; say which.

    A Model Exchange FMU without forward sensitivities (no directional derivatives, event
    indicators, ...) gives the MPC finite differences of its integrated states, which are only
    as good as the integrator: at the control default (1e-6) many solves fail. Its tolerance
    is tightened to :data:`~mshoot_core.models.defaults.FINITE_DIFFERENCE_TOLERANCE` (logged)
    unless the card sets one; a card's looser tolerance is kept with a warning.

    Returns
    -------
    str or None
        What was done (the message logged), or None for a model with sensitivities (or a
        Co-Simulation FMU, whose tolerance is its own solver's).

    """
    if not getattr(model, 'is_model_exchange', False):
        return None
    reason = model._sensitivity_plan(())
    if reason is None or model.tolerance <= FINITE_DIFFERENCE_TOLERANCE:
        return None
    if card.tolerance is not None:
        message = (f'control model {card.path}: finite-difference sensitivities ({reason}) at '
                   f"the card's integrator tolerance {model.tolerance:g}: the differences may "
                   f'be too coarse for the solver (tolerance <= '
                   f'{FINITE_DIFFERENCE_TOLERANCE:g} keeps them accurate)')
        logger.warning('%s', message)
        return message
    message = (f'control model {card.path}: finite-difference sensitivities ({reason}): '
               f'integrator tolerance {FINITE_DIFFERENCE_TOLERANCE:g} instead of '
               f'{model.tolerance:g}, so that the differences stay accurate')
    logger.info('%s', message)
    model.tolerance = FINITE_DIFFERENCE_TOLERANCE
    return message


def check_binary(card: ModelCard) -> tuple[str, ...]:
    """
    Load the binary of a card's FMU once in a child process, as a run will load it.

    With the card's ``preload`` libraries (a ``boptest`` card: its test case's ``shim/``);
    cached per binary (:func:`mshoot_core.fmu_binary.check_binary`).

    Returns
    -------
    tuple of str
        The libraries preloaded for it (none for a Python model).

    Raises
    ------
    CardError
        One problem: the binary lacks a library (named, with how to provide it), is
        damaged (it killed the child with a signal) or does not load.

    """
    try:
        if card.boptest is not None:
            from mshoot_core.boptest.testcase import load_shim
            return load_shim(card.boptest['test_case_dir'])
        if card.fmu is None:
            return ()
        folder = card.fmu if card.fmu.is_dir() else extract_fmu(card.fmu)
        md = _description(card.fmu, card.validate)
        interface = md.modelExchange if card.interface == 'ModelExchange' else md.coSimulation
        return fmu_binary.check_binary(folder, interface.modelIdentifier, card.preload,
                                       label=card.fmu.name)
    except (ValueError, FileNotFoundError) as exc:
        raise CardError(card.path, [f'fmu: {exc}']) from None


def _claim_monotone(model: Model, card: ModelCard) -> Model:
    """Set ``model.monotone_inputs`` as the card's ``monotone`` says (absent: as it is)."""
    if card.monotone is not None:
        model.monotone_inputs = tuple(card.control_names) if card.monotone else ()
    return model


# -- unit conversion at the boundary ----------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Conversions:
    """Affine maps canonical -> model units: model = scale * canonical + offset."""

    u_scale: np.ndarray
    u_offset: np.ndarray
    x_scale: np.ndarray
    x_offset: np.ndarray
    y_scale: np.ndarray
    y_offset: np.ndarray

    @classmethod
    def of(cls, card: ModelCard) -> _Conversions:
        def pairs(variables: Sequence[CardVariable]) -> tuple[np.ndarray, np.ndarray]:
            values = np.array([v.conversion() for v in variables], dtype=float).reshape(-1, 2)
            return values[:, 0].copy(), values[:, 1].copy()

        inputs = [*card.controls.values(), *card.disturbances.values()]
        return cls(*pairs(inputs), *pairs(list(card.states.values())),
                   *pairs(list(card.outputs.values())))

    @property
    def identity(self) -> bool:
        return all(np.all(s == 1.0) and np.all(o == 0.0) for s, o in (
            (self.u_scale, self.u_offset), (self.x_scale, self.x_offset),
            (self.y_scale, self.y_offset)))


class CardFmiModel(FmiModel):
    """
    An :class:`~mshoot_core.models.fmi.FmiModel` whose units differ from the canonical ones.

    Values are converted at the boundary of every public method (inputs and states in, states and
    outputs out, derivatives scaled), so the applications see canonical units while the FMU sees
    its own.

    Parameters
    ----------
    conversions : _Conversions
        The affine maps (from :func:`build_model`).
    *args, **kwargs
        Those of :class:`~mshoot_core.models.fmi.FmiModel`.

    """

    def __init__(self, *args: Any, conversions: _Conversions, **kwargs: Any) -> None:
        self.conversions = conversions
        super().__init__(*args, **kwargs)

    # canonical -> model
    def _u_in(self, u: np.ndarray) -> np.ndarray:
        c = self.conversions
        return np.asarray(u, dtype=float) * c.u_scale + c.u_offset

    def _x_in(self, x: np.ndarray) -> np.ndarray:
        c = self.conversions
        return np.asarray(x, dtype=float) * c.x_scale + c.x_offset

    # model -> canonical
    def _x_out(self, x: np.ndarray) -> np.ndarray:
        c = self.conversions
        return (np.asarray(x, dtype=float) - c.x_offset) / c.x_scale

    def _y_out(self, y: np.ndarray) -> np.ndarray:
        c = self.conversions
        return (np.asarray(y, dtype=float) - c.y_offset) / c.y_scale

    def _frames_in(self, udf: pd.DataFrame,
                   x0: Sequence[float]) -> tuple[pd.DataFrame, np.ndarray]:
        _, u, x0_arr = self.check_inputs(udf, x0)
        converted = pd.DataFrame(self._u_in(u), index=udf.index, columns=list(self.input_names))
        return converted, self._x_in(x0_arr)

    def _frames_out(self, ydf: pd.DataFrame, xdf: pd.DataFrame,
                    x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        ydf = pd.DataFrame(self._y_out(ydf.to_numpy()), index=ydf.index, columns=ydf.columns)
        xdf = pd.DataFrame(self._x_out(xdf.to_numpy()), index=xdf.index, columns=xdf.columns)
        xdf.iloc[0] = np.asarray(x0, dtype=float).reshape(-1)
        return ydf, xdf

    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        """:meth:`FmiModel.simulate` in canonical units."""
        converted, x0_model = self._frames_in(udf, x0)
        ydf, xdf = super().simulate(converted, x0_model)
        return self._frames_out(ydf, xdf, x0)

    def simulate_fresh(self, udf: pd.DataFrame,
                       x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        """:meth:`FmiModel.simulate_fresh` in canonical units."""
        converted, x0_model = self._frames_in(udf, x0)
        ydf, xdf = super().simulate_fresh(converted, x0_model)
        return self._frames_out(ydf, xdf, x0)

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           *args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`FmiModel.simulate_intervals` in canonical units."""
        x_start, u = Model._check_batch(self, x_start, u)
        x_end, y_end = super().simulate_intervals(self._x_in(x_start), self._u_in(u), dt_s,
                                                  *args, **kwargs)
        return self._x_out(x_end), self._y_out(y_end)

    def plant_start(self, x0: Sequence[float], t_s: float,
                    u: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`FmiModel.plant_start` in canonical units."""
        x, y = super().plant_start(self._x_in(x0), t_s, self._u_in(u))
        return self._x_out(x), self._y_out(y)

    def plant_step(self, u: Sequence[float], dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`FmiModel.plant_step` in canonical units."""
        x, y = super().plant_step(self._u_in(u), dt_s)
        return self._x_out(x), self._y_out(y)

    def plant_read(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`FmiModel.plant_read` in canonical units."""
        x, y = super().plant_read()
        return self._x_out(x), self._y_out(y)

    def plant_restore(self, saved: bytes) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`FmiModel.plant_restore` in canonical units."""
        x, y = super().plant_restore(saved)
        return self._x_out(x), self._y_out(y)

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int], *args: Any,
                           **kwargs: Any) -> IntervalJacobians | None:
        """:meth:`FmiModel.interval_jacobians` in canonical units (derivatives scaled)."""
        x_start, u = Model._check_batch(self, x_start, u)
        jac = super().interval_jacobians(self._x_in(x_start), self._u_in(u), dt_s, wrt_inputs,
                                         *args, **kwargs)
        if jac is None:
            return None
        c = self.conversions
        su = c.u_scale[[int(j) for j in wrt_inputs]]
        sx_row, sy_row = (1.0 / c.x_scale)[None, :, None], (1.0 / c.y_scale)[None, :, None]
        return IntervalJacobians(
            self._x_out(jac.x_end), self._y_out(jac.y_end),
            jac.dx_dx0 * sx_row * c.x_scale[None, None, :], jac.dx_du * sx_row * su[None, None],
            jac.dy_dx0 * sy_row * c.x_scale[None, None, :], jac.dy_du * sy_row * su[None, None])


# -- what a card maps (the card check) --------------------------------------------------------
def describe(card: ModelCard) -> list[dict[str, str]]:
    """
    Describe the mapping of a card: one row per mapped variable.

    Columns: section, canonical name, model variable, causality, model unit, canonical unit and the
    conversion (``model = a * canonical + b``).
    """
    rows = []
    for section in SECTIONS:
        for name, v in getattr(card, section).items():
            scale, offset = v.conversion()
            if scale == 1.0 and offset == 0.0:
                how = '-'
            else:
                how = f'{v.unit or "1"} = {scale:g} * {v.canonical_unit or "1"}' + (
                    f' {"+" if offset >= 0 else "-"} {abs(offset):g}' if offset else '')
            extra = []
            if v.min is not None or v.max is not None:
                extra.append(f'[{_bound(v.min, "-inf")}, {_bound(v.max, "inf")}]')
            if v.safe is not None:
                extra.append(f'safe {v.safe:g}')
            if v.activate:
                extra.append(f'{v.activate} := 1 (released by the fallback)')
            if v.start is not None:
                extra.append(f'start {v.start:g}')
            if v.computed:
                extra.append('computed: read by a plant, never written')
            rows.append({'section': section[:-1] if section != 'disturbances' else 'disturbance',
                         'name': name, 'variable': v.variable, 'causality': v.causality,
                         'unit': v.unit or '1', 'canonical': v.canonical_unit or '1',
                         'conversion': how, 'notes': '; '.join(extra)})
    return rows


def _bound(value: float | None, default: str) -> str:
    return default if value is None else f'{value:g}'
