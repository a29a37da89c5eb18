"""
Identification of a control model from a plant: an excitation experiment, then a calibration.

Stable API::

    from mshoot_core import identification as ident
    plant = cards.build_model(cards.load_card('plant.yaml'), role='emulator')
    table = ident.excite(plant, scenario, ident.Excitation(seed=1))   # one row per step
    model_card = cards.load_card('model.yaml')                        # a network card
    result = ident.identify(model_card, table, validation_share=0.3)  # an Identification
    ident.write_card(model_card, result, 'out/model_identified.yaml')

The excitation (:func:`excite`) runs the plant (any model with a plant or a simulation, built
from its card) through a scenario (disturbances by name), its controls held at random levels
within their limits for a random number of control steps each (1 to 8 by default), and
returns per step the disturbances and controls held over it and the plant's states at its
start (and the last step's end). The identification (:func:`identify`) fits the model card's
free network parameters (:func:`mshoot_core.calibration.calibrate`, analytic Jacobian) to the
zone temperatures of the first part of the table and scores the rest (held out): per zone the
RMSE of a free run from the held-out part's first row and of one step ahead from the measured
zone temperatures (unmeasured states from the free run). The zones are the model's measured
zone air temperature states (``T``, ``T_<zone>``), compared through the model outputs of the
same name. Every period starts its unmeasured states at the first zone's temperature; its first
``settle_steps`` rows are not fitted (the unmeasured states settle) and not scored.

Nothing here names a building: the plant, its controls and the model come from the cards.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
import time
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core import calibration
from mshoot_core.emulation import Emulator, initial_state
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN

__all__ = ['control_limits', 'excite', 'Excitation', 'excitation_levels', 'identify',
           'Identification', 'one_step_predictions', 'write_card', 'zone_names']

logger = logging.getLogger(__name__)

#: Seconds between two progress messages of an excitation.
PROGRESS_S = 10.0


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
    levels = dict(excitation.levels or {})
    unknown = sorted(set(levels) - set(names))
    if unknown:
        raise ValueError(f'excitation levels of {unknown}, which are not controls {list(names)}')
    ranges = []
    for name, (lo, hi) in zip(names, control_bounds):
        level = levels.get(name, (lo, hi))
        if level[0] < lo or level[1] > hi:
            raise ValueError(f'excitation levels of {name!r} {level} outside its limits '
                             f'({lo:g}, {hi:g})')
        ranges.append(level)
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
    started = last = time.perf_counter()
    for k in range(steps):
        record = emulator.advance(controls[k])
        states.append(record.x_end)
        if time.perf_counter() - last > PROGRESS_S:
            last = time.perf_counter()
            logger.info('excitation: step %d of %d (%.1f of %.1f days), %.0f s', k + 1, steps,
                        (k + 1) * step_s / 86400.0, steps * step_s / 86400.0, last - started)
    logger.info('excitation: %d steps of %g s in %.1f s', steps, step_s,
                time.perf_counter() - started)
    disturbances = [c for c in scenario.columns if c in plant.input_names and c not in names]
    table = scenario[disturbances].copy()
    applied = np.vstack([controls, controls[-1:]])
    for j, name in enumerate(names):
        table[name] = applied[:, j]
    for j, name in enumerate(plant.state_names):
        table[name] = np.array(states)[:, j]
    return table


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
             name: str, settle_steps: int) -> list[calibration.Period]:
    """One calibration period per zone over the rows of ``table``."""
    missing = [c for c in (*model.input_names, *zones) if c not in table.columns]
    if missing:
        raise ValueError(f'the excitation records lack {missing}: the model card names inputs or '
                         f'zones the plant card does not (records have {list(table.columns)})')
    first = float(table[zones[0]].iloc[0])
    x0 = np.array([float(table[s].iloc[0]) if s in table.columns and s in zones else first
                   for s in model.state_names])
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

    Each step starts from the measured zone temperatures ``zones_k`` (state name -> [K] at
    rows 0..N) at its row and, for the other states, the free run's; the inputs held over it.
    """
    inputs = period.inputs[list(model.input_names)]
    _, xdf = model.simulate(inputs, period.x0)
    x = xdf.to_numpy(dtype=float)[:-1].copy()
    for zone, kelvin in zones_k.items():
        x[:, model.state_names.index(zone)] = np.asarray(kelvin, dtype=float)[:-1]
    u = inputs.to_numpy(dtype=float)[:-1]
    dt = float(inputs.index[1] - inputs.index[0])
    _, y = model.simulate_intervals(x, u, dt)
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

    """

    parameters: dict[str, float]
    result: calibration.CalibrationResult
    validation: dict[str, dict[str, float]]
    train_rows: int
    validation_rows: int
    step_s: float
    one_step: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

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
    validation = _periods(model, table.iloc[split - 1:], zones, units, 'validation',
                          settle_steps)
    build = calibration.card_builder(model_card)
    logger.info('fitting %s (%d free parameters) to %d rows, %d held out, zones %s',
                model_card.path.name, len(free), split, n - split, list(zones))
    result = calibration.calibrate(build, free, train, validation, starts=starts,
                                   max_evaluations=max_evaluations)
    fitted = build(result.parameters)
    scores, predictions = {}, {}
    for period, zone in zip(validation, zones):
        keep = slice(settle_steps, None)
        free_run = result.simulated[period.name]
        one_step = one_step_predictions(
            fitted, period, {z: table[z].iloc[split - 1:].to_numpy(float) for z in zones})
        predictions[zone] = one_step
        scores[zone] = {
            'free_run_rmse_k': _rmse(free_run[1:][keep], period.measured[1:][keep]),
            'one_step_rmse_k': _rmse(one_step[keep], period.measured[1:][keep]),
            'rows': int(period.measured[1:][keep].size)}
        logger.info('zone %s: validation RMSE free run %.3f K, one step ahead %.3f K', zone,
                    scores[zone]['free_run_rmse_k'], scores[zone]['one_step_rmse_k'])
    step_s = float(table.index[1] - table.index[0])
    return Identification(dict(result.parameters), result, scores, split, n - split, step_s,
                          predictions)


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
    import yaml
    path = pathlib.Path(path)
    document = yaml.safe_load(model_card.path.read_text(encoding='utf-8'))
    parameters = document['network']['parameters']
    for name, value in identification.parameters.items():
        if isinstance(parameters.get(name), dict):
            parameters[name]['value'] = float(value)
        else:
            parameters[name] = float(value)
    document['description'] = (f"{document.get('description', model_card.path.stem)} "
                               f'(identified)')
    header = [f'# {model_card.path.name} identified by mshoot identify{source}:',
              '# its fitted values in place of the start values (its comments explain the',
              '# model). Validation RMSE per zone on held-out data [K]:']
    header += [f'#   {zone}: free run {s["free_run_rmse_k"]:.3f}, one step ahead '
               f'{s["one_step_rmse_k"]:.3f} ({s["rows"]} steps)'
               for zone, s in identification.validation.items()]
    path.parent.mkdir(parents=True, exist_ok=True)
    body = yaml.safe_dump(document, sort_keys=False, width=99)
    path.write_text('\n'.join(header) + '\n' + body, encoding='utf-8')
    return path
