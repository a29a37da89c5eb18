"""
Identification of a control model from a plant: an excitation experiment, then a calibration.

Stable API::

    from mshoot_core import identification as ident
    plant = cards.build_model(cards.load_card('plant.yaml'), role='emulator')
    table = ident.excite(plant, scenario, ident.Excitation(seed=1))   # one row per step
    # or a BOPTEST test case and its card (boptest.excitation: days, levels, hold times):
    experiment = ident.TestCaseExperiment.from_card(card, case.control_step_s)
    records = ident.excite_test_case(case, card, experiment)         # outside the test periods
    table = ident.step_table(records, case, card, model_card, experiment)
    model_card = cards.load_card('model.yaml')                        # a network card
    result = ident.identify(model_card, table, validation_share=0.3)  # an Identification
    ident.score(model_card, table, other_values)                     # the same rows, side by side
    ident.write_card(model_card, result, 'out/model_identified.yaml')

The excitation (:func:`excite`) runs the plant (any model with a plant or a simulation, built
from its card) through a scenario (disturbances by name), its controls held at random levels
within their limits for a random number of control steps each (1 to 8 by default), and returns
per step the disturbances and controls held over it and the plant's states at its start (and
the last step's end). A BOPTEST test case (:func:`excite_test_case`) runs under its own weather
from ``first_day``, after ``lead_days`` under the building's own control, never inside a test
period or its warm-up; :func:`step_table` makes the same table from its records (each model
input the step mean of the card's output or control of its name, or of the series of the model
card's ``testcase_forecast`` section: where the controller's forecast takes it from).
The identification (:func:`identify`) fits the model card's free network parameters
(:func:`mshoot_core.calibration.calibrate`, analytic Jacobian) to the zone temperatures of the
first part of the table and scores the rest (held out): per zone the RMSE of a free run from
the held-out part's first row and of one step ahead (from the state the controller's Kalman
filter estimates from the measured zone temperatures). The zones are the model's measured zone
air temperature states (``T``, ``T_<zone>``), compared through the model outputs of the same
name. The fitted period starts its unmeasured states at the first zone's temperature, its first
``settle_steps`` rows not fitted (the unmeasured states settle); the held-out period starts
them where the model's free run over the fitted rows ends, its first ``settle_steps`` rows not
scored.

Nothing here names a building: the plant, its controls and the model come from the cards.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core import calibration
from mshoot_core.emulation import Emulator, initial_state
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.period_loop import run_steps

__all__ = ['check_outside_test_periods', 'control_limits', 'excite', 'excite_test_case',
           'Excitation', 'excitation_levels', 'identify', 'Identification',
           'one_step_predictions', 'overlapping_test_periods', 'score', 'step_table',
           'TestCaseExperiment', 'write_card', 'zone_names']

logger = logging.getLogger(__name__)

#: Seconds per day.
DAY_S = 86400.0


@dataclasses.dataclass(frozen=True)
class Excitation:
    """
    How the plant is excited.

    Attributes
    ----------
    seed : int
        Seed of the random levels and hold times.
    hold_steps : (int, int)
        Fewest and most control steps a level is held (inclusive).
    levels : mapping str -> (float, float), optional
        Range of the random levels per control [its canonical unit]; default: the limits.
    start_temperature_c : float
        Start temperature of the plant's states [degC].

    """

    seed: int = 0
    hold_steps: tuple[int, int] = (1, 8)
    levels: Mapping[str, tuple[float, float]] | None = None
    start_temperature_c: float = 21.0

    def __post_init__(self) -> None:
        low, high = self.hold_steps
        if not (isinstance(low, int) and isinstance(high, int) and 1 <= low <= high):
            raise ValueError(f'hold_steps must be two integers 1 <= min <= max, got '
                             f'{self.hold_steps}')
        for name, (lo, hi) in (self.levels or {}).items():
            if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
                raise ValueError(f'levels of {name!r}: expected finite (min, max) with min <= '
                                 f'max, got ({lo}, {hi})')


def control_limits(card: Any, default: tuple[float, float] | None = None
                   ) -> tuple[tuple[float, float], ...]:
    """
    Return the (min, max) of every control of a card [canonical unit].

    Parameters
    ----------
    card : ModelCard
        The card (its limits are in the controls' canonical units, as every card's today).
    default : (float, float), optional
        Limits where the card has none; None: both limits are required.

    Raises
    ------
    ValueError
        For a control without both limits and no default.

    """
    bounds = card.control_bounds((np.nan, np.nan) if default is None else default)
    for name, (low, high) in zip(card.controls, bounds):
        if not (np.isfinite(low) and np.isfinite(high)) and default is None:
            raise ValueError(f'{card.path}: control {name!r} needs min and max (the '
                             'excitation draws its levels between them)')
    return tuple(bounds)


def excitation_levels(steps: int, bounds: Sequence[tuple[float, float]],
                      excitation: Excitation) -> np.ndarray:
    """
    Return random control levels, each held for a random number of steps.

    Parameters
    ----------
    steps : int
        Control steps.
    bounds : sequence of (float, float)
        Range of each control's levels.
    excitation : Excitation
        Seed and hold times.

    Returns
    -------
    ndarray, shape (steps, len(bounds))

    """
    rng = np.random.default_rng(excitation.seed)
    low, high = excitation.hold_steps
    out = np.empty((steps, len(bounds)))
    for j, (lo, hi) in enumerate(bounds):
        k = 0
        while k < steps:
            hold = int(rng.integers(low, high + 1))
            out[k:k + hold, j] = rng.uniform(lo, hi)
            k += hold
    return out


def excite(plant: Model, scenario: pd.DataFrame, excitation: Excitation = Excitation(), *,
           control_names: Sequence[str] | None = None,
           control_bounds: Sequence[tuple[float, float]] | None = None,
           step_s: float | None = None) -> pd.DataFrame:
    """
    Run the plant through ``scenario`` under random control levels (see the module).

    Parameters
    ----------
    plant : Model
        The plant (e.g. ``cards.build_model(card, role='emulator')``).
    scenario : DataFrame
        Disturbances and comfort band (:mod:`mshoot_core.scenario`), rows ``step_s`` apart.
    excitation : Excitation
        Seed, hold times and levels.
    control_names, control_bounds : optional
        The plant's controls and their limits (default: the card's, ``plant.control_names``
        and ``plant.control_bounds``).
    step_s : float, optional
        Control step [s] (default: the scenario's row spacing).

    Returns
    -------
    DataFrame
        Index: time [s] of every step's start and of the last step's end; columns: the
        scenario's disturbances and the controls held over the step from that row (the last
        row repeats the one before), and the plant's states at that time [its units].

    Raises
    ------
    ValueError
        For a scenario of fewer than two rows, levels of an unknown control, or levels outside
        the limits.

    """
    names = tuple(control_names or getattr(plant, 'control_names', ()) or ())
    if not names:
        raise ValueError('the plant names no controls: give control_names')
    if control_bounds is None:
        control_bounds = getattr(plant, 'control_bounds', None)
    if control_bounds is None or len(control_bounds) != len(names):
        raise ValueError(f'need (min, max) limits for the controls {list(names)}, got '
                         f'{control_bounds!r}')
    ranges = _level_ranges(names, control_bounds, excitation)
    if len(scenario) < 2:
        raise ValueError(f'the scenario needs at least two rows, got {len(scenario)}')
    if step_s is None:
        step_s = float(scenario.index[1] - scenario.index[0])
    steps = len(scenario) - 1
    controls = excitation_levels(steps, ranges, excitation)
    x0 = initial_state(plant.state_names, excitation.start_temperature_c)
    emulator = Emulator(plant, scenario, x0, control_names=names, control_bounds=control_bounds,
                        step_s=step_s)
    emulator.start_plant(controls[0])  # a plant: its own start state (as far as it sets it)
    states = [emulator.x.copy()]

    def apply(t_s: float, end_s: float, level: np.ndarray) -> None:
        states.append(emulator.advance(level).x_end)

    start = emulator.t_s
    loop = run_steps(start, start + steps * step_s, step_s, apply,
                     decide=lambda t_s: controls[len(states) - 1], label='excitation')
    logger.info('excitation: %d steps of %g s in %.1f s', steps, step_s, loop.wall_s)
    disturbances = [c for c in scenario.columns if c in plant.input_names and c not in names]
    table = scenario[disturbances].copy()
    applied = np.vstack([controls, controls[-1:]])
    for j, name in enumerate(names):
        table[name] = applied[:, j]
    for j, name in enumerate(plant.state_names):
        table[name] = np.array(states)[:, j]
    return table


@dataclasses.dataclass(frozen=True)
class TestCaseExperiment:
    """
    An excitation experiment on a BOPTEST test case (a card's ``boptest.excitation``).

    Attributes
    ----------
    first_day : float
        First excited day [days from 1 January].
    days : float
        Length of the excitation [days].
    lead_days : float
        Days run before it under the building's own control [days].
    step_s : float
        Step of the records and of the control model [s]; each level is held whole steps.
    excitation : Excitation
        Seed, hold times and level ranges of the card's controls [canonical units].
    sample_s : float
        Step of the plant's records [s] (at most 60 s).

    """

    __test__ = False  # not a pytest test class

    first_day: float
    days: float
    lead_days: float = 3.0
    step_s: float = 3600.0
    excitation: Excitation = Excitation()
    sample_s: float = 60.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.first_day - self.lead_days and self.lead_days >= 0.0
                and self.days > 0.0 and self.first_day + self.days <= 365.0):
            raise ValueError(f'excitation days: expected 0 <= first_day - lead_days, days > 0 '
                             f'and first_day + days <= 365, got first_day {self.first_day:g}, '
                             f'days {self.days:g}, lead_days {self.lead_days:g}')
        if not 0.0 < self.sample_s <= 60.0 or not self.step_s >= self.sample_s:
            raise ValueError(f'expected 0 < sample_s <= 60 s and step_s >= sample_s, got '
                             f'{self.sample_s:g} and {self.step_s:g}')
        if self.steps < 4:
            raise ValueError(f'{self.days:g} days are fewer than 4 steps of {self.step_s:g} s')

    @property
    def steps(self) -> int:
        """Return the steps of the excitation."""
        return int(round(self.days * DAY_S / self.step_s))

    @property
    def start_s(self) -> float:
        """Start of the excitation [s from 1 January]."""
        return self.first_day * DAY_S

    @property
    def end_s(self) -> float:
        """End of the excitation [s from 1 January]."""
        return self.start_s + self.steps * self.step_s

    @classmethod
    def from_card(cls, card: Any, step_s: float, **changes: Any) -> TestCaseExperiment:
        """
        Return the experiment of a BOPTEST card's ``boptest.excitation`` section.

        Parameters
        ----------
        card : ModelCard
            A card of kind ``boptest``.
        step_s : float
            Step where the section names none (the test case's control step) [s].
        **changes
            Fields replaced (e.g. ``days`` for a shortened run, ``seed``).

        Raises
        ------
        ValueError
            For a card without the section or bad values.

        """
        spec = dict((card.boptest or {}).get('excitation') or {})
        if not spec:
            raise ValueError(f'{card.path}: no boptest.excitation section (first_day, days, '
                             'levels, ...): mshoot identify --testcase needs one')
        missing = [k for k in ('first_day', 'days') if k not in spec and k not in changes]
        if missing:
            raise ValueError(f'{card.path}: boptest.excitation lacks {missing}')
        excitation = Excitation(
            seed=int(changes.pop('seed', spec.get('seed', 0))),
            hold_steps=tuple(int(v) for v in spec.get('hold_steps', (1, 8))),
            levels={str(k): (float(v[0]), float(v[1]))
                    for k, v in (spec.get('levels') or {}).items()} or None)
        fields = {'first_day': spec.get('first_day'), 'days': spec.get('days'),
                  'lead_days': spec.get('lead_days', 3.0),
                  'step_s': spec.get('step_s', step_s), **changes}
        return cls(**{k: float(v) for k, v in fields.items()}, excitation=excitation)


def overlapping_test_periods(case: Any, experiment: TestCaseExperiment,
                             warmup_days: float) -> list[str]:
    """
    Return the test periods (with their warm-ups) the experiment overlaps, lead days included.

    Parameters
    ----------
    case : TestCase
        The test case (its ``days.json``).
    experiment : TestCaseExperiment
        The experiment.
    warmup_days : float
        The warm-up before each test period [days] (the card's ``boptest.warmup_days``).

    """
    lo = experiment.start_s - experiment.lead_days * DAY_S
    out = []
    for name in sorted(case.days):
        _, start, end = case.test_period(name, 0.0)
        warmup_start = max(0.0, start - warmup_days * DAY_S)
        if lo < end and experiment.end_s > warmup_start:
            out.append(f'{name} [{warmup_start / DAY_S:g}, {end / DAY_S:g}) days')
    return out


def check_outside_test_periods(case: Any, card: Any, experiment: TestCaseExperiment) -> None:
    """
    Refuse an experiment that overlaps a test period or its warm-up (the card's).

    Raises
    ------
    ValueError
        Naming the periods overlapped.

    """
    overlaps = overlapping_test_periods(case, experiment,
                                        (card.boptest or {}).get('warmup_days', 7.0))
    if overlaps:
        raise ValueError(f'the excitation (days {experiment.first_day - experiment.lead_days:g}'
                         f' to {experiment.end_s / DAY_S:g}, lead days included) overlaps test '
                         f'periods with their warm-ups: {", ".join(overlaps)}')


def _level_ranges(names: Sequence[str], bounds: Sequence[tuple[float, float]],
                  excitation: Excitation) -> list[tuple[float, float]]:
    """Return each control's range of levels: the excitation's, within the limits."""
    levels = dict(excitation.levels or {})
    unknown = sorted(set(levels) - set(names))
    if unknown:
        raise ValueError(f'excitation levels of {unknown}, which are not controls {list(names)}')
    ranges = []
    for name, (lo, hi) in zip(names, bounds):
        level = levels.get(name, (lo, hi))
        if level[0] < lo or level[1] > hi:
            raise ValueError(f'excitation levels of {name!r} {level} outside its limits '
                             f'({lo:g}, {hi:g})')
        ranges.append(level)
    return ranges


def excite_test_case(case: Any, card: Any, experiment: TestCaseExperiment) -> pd.DataFrame:
    """
    Run a BOPTEST test case's plant under the experiment, outside every test period.

    The plant starts ``lead_days`` before ``first_day`` under the building's own control, then
    every control of the card is overwritten with random levels (:func:`excitation_levels`, in
    the card's canonical units, converted to the FMU's), each held whole steps.

    Parameters
    ----------
    case : TestCase
        The test case.
    card : ModelCard
        Its card (kind ``boptest``): the controls excited, the states and outputs recorded.
    experiment : TestCaseExperiment
        The experiment.

    Returns
    -------
    DataFrame
        The plant's records from the excitation's start to its end (``time`` [s], the card's
        variables in FMU units, the overwrites applied), every ``sample_s``.

    Raises
    ------
    ValueError
        If the days overlap a test period or its warm-up, or the levels are outside the limits.

    """
    from mshoot_core.boptest.card_plant import card_overwrites
    from mshoot_core.boptest.plant import run_span
    check_outside_test_periods(case, card, experiment)
    names = card.control_names
    ranges = _level_ranges(names, control_limits(card), experiment.excitation)
    levels = excitation_levels(experiment.steps, ranges, experiment.excitation)
    specs = [card.controls[n] for n in names]
    recorded = list(dict.fromkeys(v.variable for v in (*card.states.values(),
                                                       *card.outputs.values())))
    start, end = experiment.start_s, experiment.end_s

    def excitation(t_s: float, outputs: Any) -> dict[str, float | None]:
        return card_overwrites(specs, levels[int(round((t_s - start) / experiment.step_s))])

    run = run_span(case, start - experiment.lead_days * DAY_S, start, end, excitation,
                   experiment.step_s, experiment.sample_s, recorded, label='excitation')
    times = run.records['time'].to_numpy()
    keep = (times >= start - 1e-6) & (times <= end + 1e-6)
    return run.records[keep].reset_index(drop=True)


def step_table(records: pd.DataFrame, case: Any, card: Any, model_card: Any,
               experiment: TestCaseExperiment) -> pd.DataFrame:
    """
    Return a test case's records as :func:`identify` reads them: one row per step.

    Parameters
    ----------
    records : DataFrame
        :func:`excite_test_case`'s records.
    case : TestCase
        The test case (its data columns).
    card : ModelCard
        Its card: the variables of the outputs, controls and states.
    model_card : ModelCard
        The network card identified: its inputs (units from its ``network.inputs``), where
        those that are no output or control of ``card`` come from in the test case (its
        ``testcase_forecast`` series, :class:`~mshoot_core.boptest.forecasts.ForecastSpec`:
        each at the records' times, exact) and its zones.
    experiment : TestCaseExperiment
        The experiment (its start and step).

    Returns
    -------
    DataFrame
        Index: every step's start [s]; columns: each model input's mean over the step (a
        row of the records ends the sample before it) in the model's unit, and each zone's
        temperature at the step's start [K] (the card's state of the same name). Steps not
        fully recorded are dropped.

    Raises
    ------
    ValueError
        For a model input that is no card output or control and no series of the model
        card's ``testcase_forecast``, or a zone that is no state of the card.

    """
    from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
    from mshoot_core.models.card import conversion
    times = records['time'].to_numpy(dtype=float)
    section = getattr(model_card, 'testcase_forecast', None)
    forecasts = (TestCaseForecasts(case, ForecastSpec.from_section(
        section, f'{model_card.path}: testcase_forecast')) if section else None)
    series: dict[str, np.ndarray] = {}
    for name, unit in model_card.network.inputs.items():
        if name in card.outputs or name in card.controls:
            variable = card.outputs.get(name) or card.controls[name]
            scale, offset = conversion(unit, variable.unit)
            series[name] = (records[variable.variable].to_numpy(dtype=float) - offset) / scale
        elif forecasts is not None and name in forecasts.spec.series:
            series[name] = forecasts.series_at(name, times, experiment.sample_s)
        else:
            raise ValueError(f'the model input {name!r} is no output or control of '
                             f'{card.path.name} ({list(card.outputs)}, {list(card.controls)}) '
                             f'and no series of the testcase_forecast section of '
                             f'{model_card.path.name}')
    step_of = np.floor((times - experiment.start_s - 1e-6) / experiment.step_s).astype(int)
    frame = pd.DataFrame(series).assign(step=step_of).iloc[1:]
    grouped = frame.groupby('step')
    table = grouped.mean()
    counts = grouped.size()
    table = table[counts >= counts.max()]
    table.index = experiment.start_s + table.index.to_numpy(dtype=float) * experiment.step_s
    from mshoot_core.models import card as cards
    for zone in zone_names(cards.build_model(model_card)):
        if zone not in card.states:
            raise ValueError(f'the model zone {zone!r} is no state of {card.path.name} '
                             f'({list(card.states)})')
        variable = card.states[zone]
        scale, offset = conversion('K', variable.unit)
        kelvin = (records[variable.variable].to_numpy(dtype=float) - offset) / scale
        table[zone] = pd.Series(kelvin, index=times).reindex(table.index).to_numpy()
    return table.dropna()


def zone_names(model: Model) -> tuple[str, ...]:
    """
    Return the zones the identification compares: measured zone air temperature states.

    Raises
    ------
    ValueError
        When the model has none, or no output of the same name.

    """
    measured = tuple(getattr(model, 'measured_states', None) or model.state_names)
    zones = tuple(getattr(model, 'comfort_states', None) or
                  [n for n in model.state_names if n == 'T' or n.startswith('T_')])
    zones = tuple(z for z in zones if z in measured)
    if not zones:
        raise ValueError(f'the model has no measured zone temperature state (T or T_<zone>) '
                         f'among its states {list(model.state_names)}')
    missing = [z for z in zones if z not in model.output_names]
    if missing:
        raise ValueError(f'the model needs an output per zone, of the same name, to compare '
                         f'with the plant: {missing} are not outputs {list(model.output_names)}')
    return zones


def _in_unit(unit: str, kelvin: np.ndarray) -> np.ndarray:
    """Return plant temperatures [K] in the unit of a zone output (degC or K)."""
    return kelvin - KELVIN if unit == 'degC' else kelvin


def _periods(model: Model, table: pd.DataFrame, zones: Sequence[str], units: Mapping[str, str],
             name: str, settle_steps: int,
             unmeasured: np.ndarray | None = None) -> list[calibration.Period]:
    """
    One calibration period per zone over the rows of ``table``.

    The zones start at their measured temperatures, the other states at ``unmeasured`` (a
    full state vector [K] whose zone entries are ignored), else at the first zone's.
    """
    missing = [c for c in (*model.input_names, *zones) if c not in table.columns]
    if missing:
        raise ValueError(f'the excitation records lack {missing}: the model card names inputs or '
                         f'zones the plant card does not (records have {list(table.columns)})')
    first = float(table[zones[0]].iloc[0])
    x0 = np.array([float(table[s].iloc[0]) if s in zones
                   else (first if unmeasured is None else float(unmeasured[k]))
                   for k, s in enumerate(model.state_names)])
    weights = np.ones(len(table))
    weights[:min(settle_steps + 1, len(table) - 1)] = 0.0
    return [calibration.Period(name if len(zones) == 1 else f'{name}_{zone}',
                               table[list(model.input_names)], x0,
                               _in_unit(units[zone], table[zone].to_numpy(float)),
                               output=zone, weights=weights)
            for zone in zones]


def one_step_predictions(model: Model, period: calibration.Period,
                         zones_k: Mapping[str, np.ndarray]) -> np.ndarray:
    """
    Return the model's one-step-ahead prediction of ``period.output`` at rows 1..N.

    As a controller predicts: at every row the state is estimated from the measured zone
    temperatures ``zones_k`` (state name -> [K] at rows 0..N) by the controller's Kalman filter
    (:class:`~mshoot_core.estimation.StateEstimator` with the default
    :class:`~mshoot_core.settings.EstimationSettings`, first guess ``period.x0``), then the
    model runs one step with the inputs held over it.
    """
    from mshoot_core.estimation import StateEstimator
    from mshoot_core.settings import EstimationSettings
    inputs = period.inputs[list(model.input_names)]
    u = inputs.to_numpy(dtype=float)
    times = inputs.index.to_numpy(dtype=float)
    dt = float(times[1] - times[0])
    estimator = StateEstimator.from_settings(model, EstimationSettings(), dt,
                                             initial_state=period.x0)
    x_hat = np.empty((len(times) - 1, len(model.state_names)))
    for k in range(len(times) - 1):
        measured = {zone: float(kelvin[k]) for zone, kelvin in zones_k.items()}
        x_hat[k] = estimator.update(times[k], measured, None if k == 0 else u[k - 1]).x
    _, y = model.simulate_intervals(x_hat, u[:-1], dt)
    return y[:, model.output_names.index(period.output)]


@dataclasses.dataclass
class Identification:
    """
    An identified control model.

    Attributes
    ----------
    parameters : dict of str -> float
        The fitted free parameters.
    result : CalibrationResult
        The fit (metrics per period, confidence intervals, warnings).
    validation : dict of str -> dict
        Per zone: ``free_run_rmse_k``, ``one_step_rmse_k`` on the held-out rows, ``rows``.
    train_rows, validation_rows : int
        Rows of the table fitted and held out (the held-out period starts at the last row
        fitted).
    step_s : float
        The table's step [s].
    one_step : dict of str -> ndarray
        Per zone the one-step-ahead predictions of the held-out rows 1.. [output unit].
    free_run : dict of str -> ndarray
        Per zone the free run over the held-out rows 0.. [output unit].

    """

    parameters: dict[str, float]
    result: calibration.CalibrationResult
    validation: dict[str, dict[str, float]]
    train_rows: int
    validation_rows: int
    step_s: float
    one_step: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    free_run: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON-ready report."""
        return {'parameters': dict(self.parameters), 'validation': self.validation,
                'train_rows': self.train_rows, 'validation_rows': self.validation_rows,
                'step_s': self.step_s, 'fit': self.result.to_dict()}


def identify(model_card: Any, table: pd.DataFrame, validation_share: float = 0.3,
             settle_steps: int = 12, starts: int = 1,
             max_evaluations: int | None = None) -> Identification:
    """
    Fit a network card's free parameters to an excitation table and score held-out rows.

    Parameters
    ----------
    model_card : ModelCard
        A card with a ``network`` section (its free parameters, bounds and start values).
    table : DataFrame
        The excitation's records (:func:`excite`): the model's inputs and the zone states [K].
    validation_share : float
        Share of the rows held out at the end (0 < share < 1).
    settle_steps : int
        Rows at each period's start that are neither fitted nor scored.
    starts, max_evaluations : int
        See :func:`~mshoot_core.calibration.calibrate`.

    Raises
    ------
    ValueError
        For a card without a network or free parameters, a bad share, or too few rows.

    """
    from mshoot_core.models import card as cards
    if getattr(model_card, 'network', None) is None:
        raise ValueError(f'the model card {getattr(model_card, "path", model_card)} has no '
                         'network section: mshoot identify calibrates a thermal network card '
                         '(e.g. cards/r2c2.yaml)')
    free = [calibration.FreeParameter(p.name, p.value, p.min, p.max)
            for p in model_card.network.free_parameters]
    if not free:
        raise ValueError(f'the model card {model_card.path} has no free parameters '
                         '(free: true, with min and max)')
    if not 0.0 < validation_share < 1.0:
        raise ValueError(f'validation_share must be in (0, 1), got {validation_share}')
    n = len(table)
    split = int(round(n * (1.0 - validation_share)))
    if split < settle_steps + 3 or n - split < settle_steps + 3:
        raise ValueError(f'{n} rows are too few to fit and hold out {validation_share:.0%} with '
                         f'{settle_steps} settling rows each: run a longer excitation')
    model = cards.build_model(model_card)
    zones = zone_names(model)
    units = {zone: model_card.network.outputs[zone].unit for zone in zones}
    train = _periods(model, table.iloc[:split], zones, units, 'train', settle_steps)
    build = calibration.card_builder(model_card)
    logger.info('fitting %s (%d free parameters) to %d rows, %d held out, zones %s',
                model_card.path.name, len(free), split, n - split, list(zones))
    result = calibration.calibrate(build, free, train, starts=starts,
                                   max_evaluations=max_evaluations)
    scores, free_run, one_step = _held_out(build(result.parameters), train[0], table, split,
                                           zones, units, settle_steps)
    step_s = float(table.index[1] - table.index[0])
    return Identification(dict(result.parameters), result, scores, split, n - split, step_s,
                          one_step, free_run)


def score(model_card: Any, table: pd.DataFrame, parameters: Mapping[str, float],
          validation_share: float = 0.3, settle_steps: int = 12) -> dict[str, dict[str, float]]:
    """
    Score given parameter values of a network card on the rows :func:`identify` holds out.

    For a side-by-side comparison of an identification with other values of the same
    parameters (e.g. a packaged card's): the same held-out rows, the unmeasured states started
    alike (from a free run of these values over the rows fitted).

    Parameters
    ----------
    model_card : ModelCard
        A card with a ``network`` section.
    table : DataFrame
        The excitation's records (as for :func:`identify`).
    parameters : mapping of str -> float
        Values of the card's parameters (the others keep the card's).
    validation_share, settle_steps :
        As for :func:`identify`.

    Returns
    -------
    dict of str -> dict
        Per zone ``free_run_rmse_k``, ``one_step_rmse_k``, ``rows``.

    """
    unknown = sorted(set(parameters) - set(model_card.network.parameters))
    if unknown:
        raise ValueError(f'{unknown} are not parameters of {model_card.path.name} '
                         f'{sorted(model_card.network.parameters)}')
    from mshoot_core.models import card as cards
    model = cards.build_model(model_card)
    zones = zone_names(model)
    units = {zone: model_card.network.outputs[zone].unit for zone in zones}
    split = int(round(len(table) * (1.0 - validation_share)))
    train = _periods(model, table.iloc[:split], zones, units, 'train', settle_steps)
    fitted = calibration.card_builder(model_card)(dict(parameters))
    return _held_out(fitted, train[0], table, split, zones, units, settle_steps)[0]


def _held_out(fitted: Model, train: calibration.Period, table: pd.DataFrame, split: int,
              zones: Sequence[str], units: Mapping[str, str], settle_steps: int
              ) -> tuple[dict[str, dict[str, float]], dict[str, np.ndarray],
                         dict[str, np.ndarray]]:
    """
    Score a model on the held-out rows (from row ``split - 1``), per zone.

    The zones start measured, the unmeasured states where the model's free run over the rows
    fitted (``train``) ends. Returns the scores (``free_run_rmse_k``, ``one_step_rmse_k``,
    ``rows``), the free runs and the one-step-ahead predictions per zone [output unit].
    """
    _, xdf = fitted.simulate(train.inputs[list(fitted.input_names)], train.x0)
    validation = _periods(fitted, table.iloc[split - 1:], zones, units, 'validation',
                          settle_steps, xdf.to_numpy(dtype=float)[-1])
    measured_k = {z: table[z].iloc[split - 1:].to_numpy(float) for z in zones}
    scores, free_runs, predictions = {}, {}, {}
    keep = slice(settle_steps, None)
    for period, zone in zip(validation, zones):
        free_run = calibration.simulate_period(fitted, period)
        one_step = one_step_predictions(fitted, period, measured_k)
        free_runs[zone], predictions[zone] = free_run, one_step
        scores[zone] = {
            'free_run_rmse_k': _rmse(free_run[1:][keep], period.measured[1:][keep]),
            'one_step_rmse_k': _rmse(one_step[keep], period.measured[1:][keep]),
            'rows': int(period.measured[1:][keep].size)}
        logger.info('zone %s: validation RMSE free run %.3f K, one step ahead %.3f K', zone,
                    scores[zone]['free_run_rmse_k'], scores[zone]['one_step_rmse_k'])
    return scores, free_runs, predictions


def _rmse(simulated: np.ndarray, measured: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(simulated) - np.asarray(measured)) ** 2)))


def write_card(model_card: Any, identification: Identification,
               path: str | pathlib.Path, source: str = '') -> pathlib.Path:
    """
    Write the model card with the identified parameter values (structure and bounds kept).

    Parameters
    ----------
    model_card : ModelCard
        The card calibrated.
    identification : Identification
        Its identification.
    path : path
        The card written.
    source : str
        What it was identified from, for the header comment.

    """
    from mshoot_core.models.card import write_parameters
    name = model_card.path.name
    header = [f'{name} identified by mshoot identify{source}:',
              'its fitted values in place of the start values (the comments of the card it',
              'copies explain the model). Validation RMSE per zone on held-out data [K]:']
    header += [f'  {zone}: free run {s["free_run_rmse_k"]:.3f}, one step ahead '
               f'{s["one_step_rmse_k"]:.3f} ({s["rows"]} steps)'
               for zone, s in identification.validation.items()]
    description = f'{model_card.description or model_card.path.stem} (identified)'
    return write_parameters(model_card.path, identification.parameters, path, header,
                            description)
