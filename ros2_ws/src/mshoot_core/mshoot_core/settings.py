"""
Settings of the controller as data: frozen, validated dataclasses described once.

Every setting of the MPC and of its supervisor is a field of one of the
groups below, with its default, a description with its unit, its range or
choices, and what a change at run time implies (:data:`APPLY`). The same
description serves the command line (:func:`add_arguments`), the ROS node's
parameter table (:data:`PARAMETERS`) and :meth:`mshoot_core.controller.Controller.update`,
which decides from it whether a change is a setter or a rebuild.

Settings are validated once, with every problem reported at once
(:class:`SettingsError` lists them all), and flat names are unique across the
groups, so a flat mapping (CLI options, node parameters) maps to one setting.

>>> s = MpcSettings.from_flat(horizon_steps=6, cost='energy')
>>> s.problem.horizon_steps, s.replace(soft_penalty=10.0).comfort.soft_penalty
(6, 10.0)
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import logging
import math
import pathlib
import re
from typing import Any, Callable, Iterable, Mapping

logger = logging.getLogger(__name__)

#: What a run-time change of a setting implies, in increasing cost:
#: 'inputs' (input gating, applied at once), 'supervisor' (the fallback chain is
#: rebuilt: the last good plan is forgotten), 'solver' (the solver is replaced,
#: warm start kept), 'comfort' (hard/soft bounds switched), 'rebuild' (the MPC is
#: rebuilt: warm start lost), 'fixed' (cannot change once running).
APPLY = ('inputs', 'supervisor', 'solver', 'comfort', 'rebuild', 'fixed')
#: The packaged settings files (:meth:`MpcSettings.from_file` by name).
SETTINGS_DIR = pathlib.Path(__file__).resolve().parent / 'mpc_settings'
#: Names of the NLP solvers (see :mod:`mshoot_core.solvers`).
SOLVER_NAMES = ('ipopt', 'slsqp', 'trust-constr')
#: BOPTEST's forecast uncertainty levels (:mod:`mshoot_core.forecast`).
UNCERTAINTY_LEVELS = ('none', 'low', 'medium', 'high')


class SettingsError(ValueError):
    """Invalid settings; ``problems`` holds one sentence per problem."""

    def __init__(self, problems: Iterable[str]) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__('; '.join(self.problems))

    def __reduce__(self) -> tuple:
        return type(self), (self.problems,)  # from a worker process: the problems, not letters


def setting(default: Any, description: str, *, low: float | None = None,
            high: float | None = None, choices: tuple[str, ...] = (), apply: str = 'rebuild',
            cli: str | None = None, also: tuple[str, ...] = (), optional: bool = False) -> Any:
    """
    Return a dataclass field described for the CLI and the node parameters.

    Parameters
    ----------
    default :
        Default value (fixes the type).
    description : str
        What it is, with its unit.
    low, high : float, optional
        Inclusive range.
    choices : tuple of str
        Allowed values of a string setting.
    apply : str
        One of :data:`APPLY`.
    cli : str, optional
        Command-line option (default ``--name-with-dashes``).
    also : tuple of str
        Other groups a change also reconfigures (from :data:`APPLY`).
    optional : bool
        A float setting that may be NaN: not set (e.g. the card's value holds).

    """
    return dataclasses.field(default=default, metadata={
        'description': description, 'low': low, 'high': high, 'choices': tuple(choices),
        'apply': apply, 'cli': cli, 'also': tuple(also), 'optional': optional})


@dataclasses.dataclass(frozen=True)
class SettingField:
    """The description of one setting (a row of :data:`PARAMETERS`)."""

    name: str
    group: str
    default: Any
    description: str
    low: float | None
    high: float | None
    choices: tuple[str, ...]
    apply: str
    cli: str | None
    also: tuple[str, ...]
    optional: bool = False

    @property
    def read_only(self) -> bool:
        """Return True when the setting cannot change once a controller runs."""
        return self.apply == 'fixed'

    @property
    def applies(self) -> set[str]:
        """Every part a change reconfigures."""
        return {self.apply, *self.also}

    def problem(self, value: Any) -> str | None:
        """Why ``value`` is not valid for this setting, or None."""
        kind = type(self.default)
        if kind is bool:
            ok = isinstance(value, bool)
        elif kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif kind is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        else:
            ok = isinstance(value, kind)
        if not ok:
            return f'{self.name} must be a {kind.__name__}, got {value!r}'
        if kind is float and self.optional and math.isnan(value):
            return None  # not set
        if kind is float and not math.isfinite(value):
            return f'{self.name} must be finite{" or NaN (not set)" if self.optional else ""}, ' \
                f'got {value!r}'
        if self.choices and value not in self.choices:
            return f'{self.name} must be one of {list(self.choices)}, got {value!r}'
        if self.low is not None and value < self.low or self.high is not None and \
                value > self.high:
            return (f'{self.name} must be in [{_g(self.low)}, {_g(self.high)}], '
                    f'got {value!r}')
        return None


def _g(bound: float | None) -> str:
    return '-inf' if bound is None else f'{bound:g}'


class SettingsGroup:
    """
    Shared behaviour of the settings groups.

    Field checks here; cross-field rules in :meth:`rules`.
    """

    def problems(self) -> list[str]:
        """Every problem of this group (empty when valid)."""
        out = []
        for f in fields_of(type(self)):
            problem = f.problem(getattr(self, f.name))
            if problem:
                out.append(problem)
        return out if out else self.rules()

    def rules(self) -> list[str]:
        """Return the cross-field problems (checked once every field is valid)."""
        return []


@dataclasses.dataclass(frozen=True)
class ProblemSettings(SettingsGroup):
    """The optimal control problem over one horizon."""

    horizon_steps: int = setting(10, 'horizon N in control steps [-]', low=1, high=1000,
                                 cli='--horizon')
    step_s: float = setting(3600.0, 'control step [s]', low=1.0, high=86400.0, apply='fixed')
    cost: str = setting('quadratic', "'quadratic': sum (q/q_nom)^2; 'energy': sum |q/q_nom|; "
                        "'output': sum over the intervals of the model output cost_output",
                        choices=('quadratic', 'energy', 'output'))
    cost_output: str = setting('cost', 'model output summed over the horizon by the cost '
                               "'output' (e.g. an interval's electricity cost) [its unit]")
    control_min: float = setting(math.nan, 'lower limit of every control, narrowing the '
                                 "model card's min (NaN: the card's) [the control's unit]",
                                 also=('supervisor',), optional=True)
    control_max: float = setting(math.nan, 'upper limit of every control, narrowing the '
                                 "model card's max (NaN: the card's) [the control's unit]",
                                 also=('supervisor',), optional=True)
    relaxation: str = setting('two-phase', "unreachable hard bounds: 'two-phase' (the hard "
                              'problem where the band is reachable, else the least violation, '
                              'then the least cost unless the solver certified the first) or '
                              "'exact-penalty' (one soft solve every time)",
                              choices=('two-phase', 'exact-penalty'))
    mode: str = setting('fast', "'fast': batched structured sensitivities; 'naive': the "
                        'original MShoot algorithm (slow, for comparison)',
                        choices=('fast', 'naive'), apply='fixed')
    blas_threads: int = setting(1, 'BLAS threads during a solve (0: the library default) [-]',
                                low=0, high=256, apply='fixed')
    state_offset: float = setting(math.nan, 'offset of the normalised states: every state '
                                  'enters the solver as (x - state_offset) / state_scale (NaN: '
                                  "from the comfort bounds) [the states' unit, e.g. K]",
                                  optional=True)
    state_scale: float = setting(math.nan, 'scale of the normalised states, with state_offset '
                                 "(NaN: from the comfort bounds), > 0 [the states' unit]",
                                 optional=True)
    #: Optimised model inputs (not a parameter: fixed by the model).
    control_names: tuple[str, ...] = ('q',)
    #: The model's controls (not a parameter: fixed by the model, from its card; see
    #: :mod:`mshoot_core.controls`): one ControlSpec per control name; empty: the R1C1
    #: convention (the heat rate q of the built-in card r1c1.yaml) for every control.
    controls: tuple[Any, ...] = ()

    @property
    def control_specs(self) -> tuple[Any, ...]:
        """Return the ControlSpec of every control (the model's, else the R1C1 convention)."""
        from mshoot_core.controls import specs_for
        return specs_for(self.controls, self.control_names)

    @property
    def control_bounds(self) -> tuple[tuple[float, float], ...]:
        """(min, max) of every control [its unit]: the card's, narrowed by the settings."""
        from mshoot_core.controls import narrowed
        return tuple(narrowed((c.min, c.max), self.control_min, self.control_max)
                     for c in self.control_specs)

    def rules(self) -> list[str]:
        out = []
        if not self.control_names or not all(isinstance(c, str) for c in self.control_names):
            return [f'control_names must be a non-empty tuple of names, got '
                    f'{self.control_names!r}']
        if math.isnan(self.state_offset) != math.isnan(self.state_scale):
            return [f'state_offset and state_scale go together (both set or both NaN), got '
                    f'{self.state_offset} and {self.state_scale}']
        if not (math.isnan(self.state_scale) or self.state_scale > 0):
            return [f'state_scale must be > 0, got {self.state_scale}']
        if not (math.isnan(self.control_min) or math.isnan(self.control_max)
                or self.control_min < self.control_max):
            return [f'control_min must be < control_max, got {self.control_min} and '
                    f'{self.control_max}']
        for spec, (low, high) in zip(self.control_specs, self.control_bounds):
            if not (math.isfinite(low) and math.isfinite(high)):
                out.append(f'control {spec.label()} needs finite limits, got [{low:g}, '
                           f'{high:g}]: give min and max in its card (or control_min, '
                           'control_max)')
            elif not low < high:
                out.append(f'control {spec.label()}: control_min/control_max '
                           f'[{self.control_min:g}, {self.control_max:g}] leave no range '
                           f"within the card's limits [{spec.min:g}, {spec.max:g}]")
        return out


@dataclasses.dataclass(frozen=True)
class ComfortSettings(SettingsGroup):
    """How the comfort band bounds the zone states."""

    comfort: str = setting('hard', "'hard': the band as bounds, relaxed where unreachable; "
                           "'soft': slack with penalty", choices=('hard', 'soft'),
                           apply='comfort')
    soft_penalty: float = setting(1e3, 'weight of the quadratic penalty on normalised slack '
                                  "(comfort 'soft') [-]", low=1e-9, high=1e12, apply='comfort')
    soft_penalty_linear: float = setting(0.0, 'weight of the linear penalty on normalised '
                                         "slack (comfort 'soft') [-]", low=0.0, high=1e12)
    band_margin_k: float = setting(0.0, "raise of the comfort band's lower edge in the plan "
                                   '(the plan sees the zone at the step ends only, the '
                                   'discomfort is counted in between too; the upper edge is '
                                   'kept, at least at the raised lower one) [K]', low=0.0,
                                   high=20.0, apply='inputs')
    forecast_error_inputs: str = setting(
        '', "model inputs whose forecasts carry BOPTEST's errors, 'input=temperature' or "
        "'input=solar' items separated by commas (the AR(1) error models of "
        'mshoot_core.forecast)', apply='inputs')
    forecast_uncertainty: str = setting(
        'none', "the error level of those inputs' forecasts the plan allows for (BOPTEST's "
        "parameters of the level); 'none': no forecast margin", choices=UNCERTAINTY_LEVELS,
        apply='inputs')
    forecast_margin_std: float = setting(
        1.0, 'the comfort band narrowed on each side (after band_margin_k, at most to its '
        'middle) by this many standard deviations of the zone temperature that the forecast '
        'errors cause along the plan (the errors propagated through the model: '
        'mshoot_core.forecast_margin) [-]',
        low=0.0, high=10.0, apply='inputs')

    @property
    def soft(self) -> bool:
        return self.comfort == 'soft'

    @property
    def error_kinds(self) -> dict[str, str]:
        """Return ``forecast_error_inputs`` as model input -> error kind."""
        return {name.strip(): kind.strip() for name, _, kind in (
            item.partition('=') for item in self.forecast_error_inputs.split(',')
            if item.strip())}

    def rules(self) -> list[str]:
        items = [i for i in self.forecast_error_inputs.split(',') if i.strip()]
        kinds = self.error_kinds
        if len(kinds) != len(items) or not all(
                name.isidentifier() and kind in ('temperature', 'solar')
                for name, kind in kinds.items()):
            return ["forecast_error_inputs must be distinct 'input=temperature' or "
                    f"'input=solar' items separated by commas, got "
                    f'{self.forecast_error_inputs!r}']
        if self.forecast_uncertainty != 'none' and not kinds:
            return [f'forecast_uncertainty {self.forecast_uncertainty!r} needs '
                    'forecast_error_inputs (which inputs carry the errors)']
        return []


@dataclasses.dataclass(frozen=True)
class SolverSettings(SettingsGroup):
    """The NLP solver."""

    solver: str = setting('slsqp', 'NLP solver', choices=SOLVER_NAMES, apply='solver')
    solver_max_iter: int = setting(200, 'iteration limit of the solver [-]', low=1,
                                   high=1_000_000, apply='solver')
    solver_tol: float = setting(0.0, "solver tolerance (0 = the solver's default) [-]",
                                low=0.0, high=1.0, apply='solver')
    #: Further keyword arguments of the solver class (e.g. IPOPT ``options``); not a
    #: parameter.
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`mshoot_core.solvers.make_solver`."""
        out: dict[str, Any] = {'max_iter': self.solver_max_iter, **self.extra}
        if self.solver_tol > 0:
            out['tol'] = self.solver_tol
        return out

    def rules(self) -> list[str]:
        from mshoot_core.solvers import make_solver
        try:
            make_solver(self.solver, **self.options())
        except (TypeError, ValueError) as exc:
            return [f'solver {self.solver!r} cannot be used: {exc}']
        return []


@dataclasses.dataclass(frozen=True)
class SupervisorSettings(SettingsGroup):
    """The fallback chain and the time budget."""

    time_budget_s: float = setting(0.0, 'wall time allowed per solve: the solver stops there '
                                   'and the step gets a fallback setpoint (0 = no budget) [s]',
                                   low=0.0, high=86400.0, apply='inputs')
    on_failure: str = setting('plan', "when the solver does not converge: 'plan' applies its "
                              "best plan if it is sane, 'fallback' the fallback chain",
                              choices=('plan', 'fallback'), apply='inputs')
    safe_value: float = setting(math.nan, 'safe value of every control, applied when no '
                                'good plan is left and the control is not released, '
                                "overriding the card's safe (NaN: the card's, else 0 "
                                "clipped into the limits) [the control's unit]",
                                apply='supervisor', optional=True)
    release: str = setting('auto', "last link of the fallback chain: 'auto' releases the "
                           'overwrites of controls whose card has an overwrite switch '
                           "(activate), so the building's own controller acts, and applies "
                           "the safe values otherwise; 'release' releases every control (a "
                           "control model without switches of a plant with them); 'never' "
                           'always applies the safe values', choices=('auto', 'release', 'never'),
                           apply='supervisor')
    safe_temperature_c: float = setting(21.0, 'zone temperature setpoint sent with the safe '
                                        'values (for the HVAC loop) [degC]', low=-50.0,
                                        high=80.0, apply='inputs')
    max_plan_age_steps: int = setting(4, 'a failed step falls back on the last good plan '
                                      'while it is at most this many steps old, then on the '
                                      'safe setpoint [-]', low=0, high=10_000,
                                      apply='supervisor')
    max_fallback_share: float = setting(0.5, "largest share of a run's steps that may be "
                                        'fallbacks: a run with more ends with a WARNING '
                                        'summary and a non-zero exit code (1 = never) [-]',
                                        low=0.0, high=1.0, apply='inputs')


@dataclasses.dataclass(frozen=True)
class InputSettings(SettingsGroup):
    """When inputs are fresh enough, and how long a due step waits for them."""

    input_wait_s: float = setting(5.0, 'wall time a due step waits for a missing or stale '
                                  'zone state or forecast before its fallback [s]',
                                  low=0.001, high=86400.0, apply='inputs')
    input_deadline_s: float = setting(1800.0, 'controller-clock time a due step waits for a '
                                      'missing or stale input before its fallback (0 = only '
                                      'input_wait_s) [s]', low=0.0, high=86400.0,
                                      apply='inputs')
    max_state_age_s: float = setting(0.0, 'oldest zone state accepted for a step, before the '
                                     'step start [s]', low=0.0, high=86400.0, apply='inputs')
    max_forecast_age_s: float = setting(0.0, 'oldest forecast accepted for a step (shifted '
                                        'to the step) [s]', low=0.0, high=7 * 86400.0,
                                        apply='inputs')
    max_future_s: float = setting(3600.0, 'inputs stamped further ahead of the clock are '
                                  'rejected (data and clock are not ordered: allow a step) '
                                  '[s]', low=0.0, high=86400.0, apply='inputs')


def _pairs(text: str) -> dict[str, str]:
    """Return comma-separated 'a=b' items as a dict (a later item with the same a wins)."""
    return {a.strip(): b.strip() for a, _, b in (
        item.partition('=') for item in text.split(',') if item.strip())}


def _distinct_pairs(text: str, right: Callable[[str], bool] = str.isidentifier) -> bool:
    """
    Return whether comma-separated items are 'name=value' pairs with distinct left names.

    Each left side a name; each right side one ``right`` accepts (default: a name too).
    """
    pairs = _pairs(text)
    return len(pairs) == len([i for i in text.split(',') if i.strip()]) and all(
        a.isidentifier() and right(b) for a, b in pairs.items())


def _is_number(text: str) -> bool:
    """Return whether a text is a finite number."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


#: How the decided controls of a step reach the building (setting ``actuation``).
ACTUATIONS = ('hold', 'burst')
#: What is sent (setting ``actuation_send``).
ACTUATION_SENDS = ('value', 'setpoint')


@dataclasses.dataclass(frozen=True)
class ActuationSettings(SettingsGroup):
    """How a step's decided controls reach the building within the step."""

    actuation: str = setting('hold', "'hold': each control held over the step at its decided "
                             "value; 'burst': a control is run at its upper bound for the "
                             'share of the step its value asks for (its duty between its '
                             'bounds), at its lower bound otherwise: full-load bursts joined '
                             'across steps, in a schedule within the step',
                             choices=ACTUATIONS, apply='inputs')
    min_run_s: float = setting(0.0, "actuation 'burst': shortest burst once started, unless "
                               'the plan stops heating (0 = none) [s]', low=0.0, high=86400.0,
                               apply='inputs')
    burst_resolution_s: float = setting(60.0, "actuation 'burst': bursts start and stop on "
                                        "this grid, e.g. the plant's sampling [s]", low=1.0,
                                        high=86400.0, apply='inputs')
    actuation_send: str = setting('value', "actuation 'burst': 'value' sends the control's "
                                  "bounds; 'setpoint' sends a temperature setpoint above the "
                                  'zone temperature while a burst runs and below it otherwise '
                                  "(for the building's own loop)", choices=ACTUATION_SENDS,
                                  apply='inputs')
    setpoint_above_k: float = setting(10.0, "actuation_send 'setpoint': the setpoint while a "
                                      'burst runs, above the zone temperature [K]', low=0.0,
                                      high=100.0, apply='inputs')
    setpoint_below_k: float = setting(3.0, "actuation_send 'setpoint': the setpoint otherwise, "
                                      'below the zone temperature [K]', low=0.0, high=100.0,
                                      apply='inputs')

    plant_controls: str = setting('', "the plant's control (its card's) each model control is "
                                  "sent as, comma-separated 'control=plant_control' (e.g. a "
                                  "duty sent in bursts as the heat pump's modulation; '' = the "
                                  'same names)', apply='fixed')
    band_setpoints: str = setting(
        '', "plant controls (their cards') sent every step at an edge of a comfort band moved "
        "inward by band_setpoint_margin_k, not planned: comma-separated 'plant_control=max:zone' "
        "(the zone's band's upper edge less the margin, e.g. its maximum (cooling) setpoint) or "
        "'plant_control=min:zone' (the lower edge plus the margin); 'max' or 'min' alone: the "
        'band comfort_max, comfort_min. The tightest edge over the step from the forecast, '
        "clipped to the plant control's range; released with the overwrites by the last "
        "fallback, and when no forecast covers the step ('' = none) [the band's unit, degC]",
        apply='fixed')
    band_setpoint_margin_k: float = setting(
        0.0, 'band_setpoints moved inward from their band edge by this much, at most to the '
        "band's middle [K]", low=0.0, high=20.0, apply='inputs')
    cooling_mode_margin_k: float = setting(
        math.nan, 'band_setpoints moved inward by this much instead of band_setpoint_margin_k '
        'in cooling mode: a step whose plan heats nowhere, neither in the step nor in a later '
        "interval (no capped setpoint of setpoint_caps at its zone's planned temperature); "
        'NaN: band_setpoint_margin_k always; else 0-20 [K]', optional=True, apply='inputs')
    setpoint_caps: str = setting(
        '', "model controls that are a zone's heating setpoint for the building's own loop: "
        "comma-separated 'control=zone_state'. Each is sent no higher than the plan's "
        "temperature of its zone at the step's end (or the zone's band's lower edge there, "
        'raised by band_margin_k, where the plan falls short of it) and no lower than that '
        "raised lower edge at the step's start; every planned interval likewise. A high-gain "
        "loop asked for more than the plan's temperature heats on past it; capped, it stops "
        'where the plan does, still goes for the band where the plan expects to miss it, and '
        "holds the band as the building's own loop would. A safe or released step is not "
        "capped ('' = none) [the band's unit, degC]", apply='fixed')

    supply_floors: str = setting(
        '', 'model controls that are the supply temperature of the loops the capped setpoints '
        '(setpoint_caps) heat through, with the least supply temperature those loops need to '
        "deliver the plan's heat: comma-separated 'control=floor'. In a step where a capped "
        "setpoint heats (it is sent at the plan's temperature of its zone at the step's end, "
        'or above it, within 0.05 K: the loop holds or raises the zone), each is sent at least '
        'at its floor; otherwise as planned, e.g. at its lower limit where the model prices its '
        "gas and no capacity falling with it; every planned interval likewise ('' = none) "
        "[the control's unit, degC]", apply='fixed')

    @property
    def supply_floor_items(self) -> dict[str, float]:
        """Return ``supply_floors`` as model control -> floor (:meth:`rules` checks them)."""
        return {control: float(floor) for control, floor in _pairs(self.supply_floors).items()}

    @property
    def cap_items(self) -> dict[str, str]:
        """Return ``setpoint_caps`` as model control -> zone state."""
        return _pairs(self.setpoint_caps)

    @property
    def plant_names(self) -> dict[str, str]:
        """Return ``plant_controls`` as model control -> plant control."""
        return _pairs(self.plant_controls)

    @property
    def band_items(self) -> tuple[tuple[str, str, str], ...]:
        """
        Return ``band_setpoints`` as (plant control, edge, zone) items.

        The edge 'min' or 'max'; the zone '' for the band ``comfort_min``, ``comfort_max``
        (also for an item that does not parse: :meth:`rules` reports it).
        """
        out = []
        for item in (i.strip() for i in self.band_setpoints.split(',') if i.strip()):
            control, _, source = (part.strip() for part in item.partition('='))
            edge, colon, zone = (part.strip() for part in source.partition(':'))
            out.append((control, edge, zone if colon and zone else ('?' if colon else '')))
        return tuple(out)

    def rules(self) -> list[str]:
        names = self.plant_names
        if not _distinct_pairs(self.plant_controls):
            return ["plant_controls must be distinct 'control=plant_control' items separated "
                    f'by commas, got {self.plant_controls!r}']
        items = [i for i in self.band_setpoints.split(',') if i.strip()]
        bands = self.band_items
        if len({c for c, _, _ in bands}) != len(items) or not all(
                control.isidentifier() and edge in ('min', 'max') and re.fullmatch(r'\w*', zone)
                for control, edge, zone in bands):
            return ["band_setpoints must be distinct 'plant_control=max:zone' or "
                    "'plant_control=min:zone' items separated by commas (':zone' may be left "
                    f'out), got {self.band_setpoints!r}']
        both = sorted({c for c, _, _ in bands} & set(names.values()))
        if both:
            return [f'band_setpoints: {both} are also sent as model controls (plant_controls '
                    f'{self.plant_controls!r})']
        if not _distinct_pairs(self.setpoint_caps):
            return ["setpoint_caps must be distinct 'control=zone_state' items separated by "
                    f'commas, got {self.setpoint_caps!r}']
        if not (math.isnan(self.cooling_mode_margin_k)
                or 0.0 <= self.cooling_mode_margin_k <= 20.0):
            return ['cooling_mode_margin_k must be NaN or within [0, 20] K, got '
                    f'{self.cooling_mode_margin_k!r}']
        floors = _pairs(self.supply_floors)
        if not _distinct_pairs(self.supply_floors, _is_number):
            return ["supply_floors must be distinct 'control=floor' items (a model control, a "
                    f'number) separated by commas, got {self.supply_floors!r}']
        if floors and not self.cap_items:
            return ['supply_floors needs setpoint_caps (a supply floor holds while a capped '
                    'setpoint heats)']
        both = sorted(set(floors) & set(self.cap_items))
        if both:
            return [f'supply_floors: {both} are also capped setpoints (setpoint_caps)']
        if self.cap_items and self.actuation != 'hold':
            return [f"setpoint_caps needs actuation 'hold' (a capped setpoint is held over the "
                    f'step), got actuation {self.actuation!r}']
        if self.actuation_send == 'setpoint' and self.actuation != 'burst':
            return ["actuation_send 'setpoint' needs actuation 'burst', got actuation "
                    f'{self.actuation!r}']
        return []


#: Ways of getting the state a step is planned from (setting ``estimation``).
ESTIMATION_MODES = ('auto', 'off', 'ekf')


@dataclasses.dataclass(frozen=True)
class EstimationSettings(SettingsGroup):
    """How the state a step is planned from comes from the measurements."""

    estimation: str = setting('auto', "'auto': estimate the states when not all are measured "
                              "(an extended Kalman filter on the model), 'ekf': always filter, "
                              "'off': every state must be measured and is taken as it is",
                              choices=ESTIMATION_MODES, apply='fixed')
    measured_states: str = setting('', "the states a sensor measures, comma-separated ('' = "
                                   'those the model declares, else all of them)', apply='fixed')
    measurement_noise_k: float = setting(0.1, 'standard deviation of a measured state, e.g. '
                                         'the air temperature sensor [K]', low=1e-6, high=100.0,
                                         apply='inputs')
    process_noise_k: float = setting(0.05, 'standard deviation of the model error of every '
                                     'state over one control step [K]', low=0.0, high=100.0,
                                     apply='inputs')
    initial_std_k: float = setting(3.0, 'standard deviation of the first estimate of an '
                                   'unmeasured state [K]', low=1e-6, high=1000.0,
                                   apply='inputs')
    measured_inputs: str = setting('', 'model inputs measured over each step, taken by the '
                                   'state estimate instead of the decided controls and the '
                                   "forecast: comma-separated 'input=output' (the step mean of "
                                   "a measured output, in the input's unit) or, for a control, "
                                   "'control=output/model_output' (the control at which the "
                                   "model's output equals the measured one: e.g. a heat pump's "
                                   'duty from its measured heat; not capped above); empty: '
                                   'none', apply='fixed')
    comfort_margin_std: float = setting(0.0, 'with an estimated state: the comfort band is '
                                        'narrowed, on each side, by this many standard '
                                        'deviations of the predicted zone temperature at each '
                                        "step of the horizon (the estimate's covariance "
                                        'propagated by the model) [-]',
                                        low=0.0, high=10.0, apply='inputs')

    @property
    def measured(self) -> tuple[str, ...]:
        """Return the measured states named by ``measured_states`` (empty: the model's)."""
        return tuple(n.strip() for n in self.measured_states.split(',') if n.strip())

    @property
    def input_measurements(self) -> dict[str, tuple[str, str]]:
        """
        Return ``measured_inputs`` as input -> (measured output, model output or '').

        The model output is set for a control measured through its effect.
        """
        out = {}
        for item in (i.strip() for i in self.measured_inputs.split(',') if i.strip()):
            name, _, source = (part.strip() for part in item.partition('='))
            output, _, model_output = (part.strip() for part in source.partition('/'))
            out[name] = (output, model_output)
        return out

    def rules(self) -> list[str]:
        names = self.measured
        bad = [n for n in names if not n.isidentifier()]
        if bad or len(set(names)) != len(names):
            return [f'measured_states must be distinct state names separated by commas, got '
                    f'{self.measured_states!r}']
        items = [i.strip() for i in self.measured_inputs.split(',') if i.strip()]
        pairs = self.input_measurements
        if len(pairs) != len(items) or not all(
                name.isidentifier() and output and (not model or model.isidentifier())
                and '/' not in model and '=' not in output
                for name, (output, model) in pairs.items()):
            return ["measured_inputs must be distinct 'input=output' or "
                    "'control=output/model_output' items separated by commas, got "
                    f'{self.measured_inputs!r}']
        return []


@dataclasses.dataclass(frozen=True)
class ForecastErrorSettings(SettingsGroup):
    """
    The forecasts' emulated errors, as BOPTEST's forecast uncertainty scenario has them.

    Not a group of :class:`MpcSettings`: the forecaster's (:mod:`mshoot_core.forecast`).
    Validated on construction.

    Raises
    ------
    SettingsError
        With every problem at once.

    """

    temperature_uncertainty: str = setting(
        'none', "error level of the outdoor temperature forecast (BOPTEST's "
        "temperature_uncertainty: AR(1) Gaussian errors; 'none': exact)",
        choices=UNCERTAINTY_LEVELS, apply='fixed')
    solar_uncertainty: str = setting(
        'none', "error level of the global horizontal irradiance forecast (BOPTEST's "
        "solar_uncertainty: AR(1) Laplace errors; 'none': exact)",
        choices=UNCERTAINTY_LEVELS, apply='fixed')
    seed: int = setting(0, 'seed of the forecast errors: a draw at time t [s] is seeded with '
                        'seed + t, as BOPTEST does [-]', low=0, high=2 ** 31 - 1, apply='fixed')

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise SettingsError(problems)


#: The groups of :class:`MpcSettings`, by attribute name.
GROUPS: dict[str, type] = {'problem': ProblemSettings, 'comfort': ComfortSettings,
                           'solver': SolverSettings, 'supervisor': SupervisorSettings,
                           'inputs': InputSettings, 'estimation': EstimationSettings,
                           'actuation': ActuationSettings}


@functools.cache  # (a group's fields never change; every validation asks for them)
def fields_of(group: type) -> tuple[SettingField, ...]:
    """Return the described settings of one group (fields without a description are left out)."""
    out = []
    for f in dataclasses.fields(group):
        if 'description' not in f.metadata:
            continue
        name = next((g for g, cls in GROUPS.items() if cls is group), group.__name__)
        m = f.metadata
        out.append(SettingField(f.name, name, f.default, m['description'], m['low'],
                                m['high'], m['choices'], m['apply'], m['cli'], m['also'],
                                m.get('optional', False)))
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class MpcSettings:
    """
    Every setting of the controller; validated on construction.

    Raises
    ------
    SettingsError
        With every problem of every group.

    """

    problem: ProblemSettings = dataclasses.field(default_factory=ProblemSettings)
    comfort: ComfortSettings = dataclasses.field(default_factory=ComfortSettings)
    solver: SolverSettings = dataclasses.field(default_factory=SolverSettings)
    supervisor: SupervisorSettings = dataclasses.field(default_factory=SupervisorSettings)
    inputs: InputSettings = dataclasses.field(default_factory=InputSettings)
    estimation: EstimationSettings = dataclasses.field(default_factory=EstimationSettings)
    actuation: ActuationSettings = dataclasses.field(default_factory=ActuationSettings)

    def __post_init__(self) -> None:
        problems = []
        for name, cls in GROUPS.items():
            group = getattr(self, name)
            if not isinstance(group, cls):
                problems.append(f'{name} must be {cls.__name__}, got {type(group).__name__}')
            else:
                problems += group.problems()
        if not problems:
            for spec, (low, high), safe, released in zip(
                    self.problem.control_specs, self.problem.control_bounds, self.safe_values,
                    self.released):
                if not (released or low <= safe <= high):  # (released: clipped, not applied)
                    given = ('safe_value' if not math.isnan(self.supervisor.safe_value)
                             else "the card's safe")
                    problems.append(f'{given} of {spec.label()} must be within its limits '
                                    f'[{low:g}, {high:g}], got {safe:g}')
        if problems:
            raise SettingsError(problems)

    @property
    def safe_values(self) -> tuple[float, ...]:
        """
        Return the safe value of every control [its unit].

        ``safe_value`` if set, else the card's ``safe``, else 0 clipped into the limits.
        """
        from mshoot_core.controls import safe_values
        return safe_values(self.problem.control_specs, self.problem.control_bounds,
                           self.supervisor.safe_value)

    @property
    def released(self) -> tuple[bool, ...]:
        """Return, per control, whether the last fallback releases it (setting ``release``)."""
        mode = self.supervisor.release
        return tuple(mode == 'release' or (mode == 'auto' and spec.releasable)
                     for spec in self.problem.control_specs)

    @classmethod
    def from_flat(cls, values: Mapping[str, Any] | None = None, /, **more: Any) -> MpcSettings:
        """
        Build settings from flat names; unknown names are problems too.

        The flat names are those of :data:`PARAMETERS`, plus ``control_names``,
        ``controls`` (the model's ControlSpecs) and ``solver_extra``; the deprecated names of
        :data:`DEPRECATED` are taken with a warning.
        """
        return cls().replace(values, **more)

    @classmethod
    def from_file(cls, path: str | pathlib.Path, /, **more: Any) -> MpcSettings:
        """
        Build settings from a YAML file of flat names (see :meth:`from_flat`), ``more`` over it.

        ``path`` is a file, or the name of a packaged settings file (:data:`SETTINGS_DIR`,
        e.g. ``'boptest_house'``).

        Raises
        ------
        ValueError
            For a missing file, one that is not a mapping, or bad settings (every problem).

        """
        import yaml
        file = pathlib.Path(path)
        if not file.is_file():
            packaged = SETTINGS_DIR / f'{path}.yaml'
            if not packaged.is_file():
                names = sorted(p.stem for p in SETTINGS_DIR.glob('*.yaml'))
                raise ValueError(f'no settings file {str(path)!r}: expected a YAML file or one '
                                 f'of the packaged {names}')
            file = packaged
        document = yaml.safe_load(file.read_text())
        if not isinstance(document, dict):
            raise ValueError(f'{file}: expected a mapping of flat setting names, got '
                             f'{type(document).__name__}')
        try:
            return cls.from_flat({**document, **more})
        except SettingsError as exc:
            raise SettingsError([f'{file}: {problem}' for problem in exc.problems]) from None

    def replace(self, values: Mapping[str, Any] | None = None, /, **more: Any) -> MpcSettings:
        """Return a copy with flat-named settings changed, validated (every problem at once)."""
        changes = {**(values or {}), **more}
        by_group: dict[str, dict[str, Any]] = {name: {} for name in GROUPS}
        unknown = []
        for key, value in changes.items():
            if key in DEPRECATED:
                logger.warning("setting %s is deprecated: use %s (in the control's unit)",
                               key, DEPRECATED[key])
                key = DEPRECATED[key]
            if key in ('control_names', 'controls'):
                by_group['problem'][key] = tuple(value)
            elif key == 'solver_extra':
                by_group['solver']['extra'] = dict(value)
            elif key in BY_NAME:
                by_group[BY_NAME[key].group][key] = _coerce(BY_NAME[key], value)
            else:
                unknown.append(key)
        problems = [f'unknown setting(s) {sorted(unknown)}; valid: {sorted(BY_NAME)}'
                    ] if unknown else []
        try:
            settings = MpcSettings(**{name: dataclasses.replace(getattr(self, name), **kw)
                                      for name, kw in by_group.items()})
        except SettingsError as exc:
            problems += exc.problems
        if problems:
            raise SettingsError(problems)
        return settings

    def flat(self) -> dict[str, Any]:
        """Flat name -> value of every described setting."""
        return {f.name: getattr(getattr(self, f.group), f.name) for f in PARAMETERS}

    def changed(self, other: MpcSettings) -> set[str]:
        """Flat names whose value differs in ``other`` (plus 'control_names', 'solver_extra')."""
        a, b = self.flat(), other.flat()
        out = {name for name in a if not _same(a[name], b[name])}
        if (self.problem.control_names != other.problem.control_names
                or self.problem.controls != other.problem.controls):
            out.add('control_names')
        if dict(self.solver.extra) != dict(other.solver.extra):
            out.add('solver_extra')
        return out

    def fixed_changes(self, other: MpcSettings) -> list[str]:
        """
        Return the changed names in ``other`` that cannot change once running.

        Those are the settings described as fixed (``step_s``, ``mode``,
        ``blas_threads``) and the controls, sorted.
        """
        return sorted(n for n in self.changed(other)
                      if n == 'control_names' or (n in BY_NAME and BY_NAME[n].read_only))


def _same(a: Any, b: Any) -> bool:
    """Return True when two setting values are equal (NaN equals NaN: both not set)."""
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a)
                      and math.isnan(b))


def _coerce(f: SettingField, value: Any) -> Any:
    """Ints given for float settings become floats (a CLI or YAML habit)."""
    if type(f.default) is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


#: Every described setting, in group order: the node parameter table and the CLI options.
PARAMETERS: tuple[SettingField, ...] = tuple(f for cls in GROUPS.values() for f in fields_of(cls))
#: Flat name -> description.
BY_NAME: dict[str, SettingField] = {f.name: f for f in PARAMETERS}
#: Deprecated flat names -> their settings (taken by :meth:`MpcSettings.replace` with a
#: warning): the names of the heat-rate-only era.
DEPRECATED: dict[str, str] = {'heat_rate_min_w': 'control_min', 'heat_rate_max_w': 'control_max',
                              'safe_heat_rate_w': 'safe_value'}
assert len(BY_NAME) == len(PARAMETERS), 'flat setting names must be unique'


# -- the command line ---------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser, names: Iterable[str | SettingField],
                  defaults: Mapping[str, Any] | None = None) -> None:
    """
    Add the settings ``names`` as options of ``parser`` (help from their descriptions).

    A name is that of an MPC setting (:data:`BY_NAME`), or a :class:`SettingField` of another
    group (e.g. ``fields_of(ForecastErrorSettings)``). Options are parsed as strings of the
    setting's type; validation is left to :meth:`MpcSettings.replace` (or the group's
    constructor), so every problem is reported at once.
    """
    for name in names:
        f = name if isinstance(name, SettingField) else BY_NAME[name]
        name = f.name
        default = (defaults or {}).get(name, f.default)
        option = f.cli or '--' + name.replace('_', '-')
        kind = type(f.default)
        extra: dict[str, Any] = {}
        if f.choices:
            extra['choices'] = f.choices
        help_text = f'{f.description} (default {default!r})'
        parser.add_argument(option, dest=name, type=_parse_bool if kind is bool else kind,
                            default=default, help=help_text.replace('%', '%%'),
                            metavar=None if f.choices else option.lstrip('-').upper(), **extra)


def option_wording(problem: str, fields: Iterable[SettingField] = ()) -> str:
    """
    Word a settings problem in command-line terms.

    ``horizon_steps must ...`` becomes ``--horizon must ...`` (the described settings, plus
    ``fields``).
    """
    for f in (*PARAMETERS, *fields):
        if problem.startswith(f.name + ' '):
            return (f.cli or '--' + f.name.replace('_', '-')) + problem[len(f.name):]
    return problem


def _parse_bool(text: str) -> bool:
    if text.lower() in ('1', 'true', 'yes', 'on'):
        return True
    if text.lower() in ('0', 'false', 'no', 'off'):
        return False
    raise argparse.ArgumentTypeError(f'expected true or false, got {text!r}')


def from_arguments(args: argparse.Namespace, names: Iterable[str],
                   base: MpcSettings | None = None) -> MpcSettings:
    """Build settings from parsed options (see :func:`add_arguments`)."""
    return (base or MpcSettings()).replace({name: getattr(args, name) for name in names})
