"""
Safety rules of the supervisory loop: input validation and the fallback chains.

A supervisory controller that stops publishing, or publishes NaN, is worse
than none. This module holds the decisions; the ROS nodes only convert
messages to the plain values used here and act on the verdicts.

- Validation (:func:`check_zone_state`, :func:`check_disturbances`,
  :func:`check_forecast`, :func:`check_setpoint`, :class:`StampGate`): a
  malformed or untimely input gets a :class:`Rejection` (a kind from
  :data:`REJECTION_KINDS` and one clear sentence) and is counted by a
  :class:`RejectionCounter`; nothing rejected reaches the optimiser or the
  building. Inputs are named vectors (names and values, or named series
  flattened name-major, :func:`unflatten`): the names must be distinct and,
  where the receiver knows its model, known to it (:func:`check_names`).
- The MPC fallback chain (:class:`SetpointSupervisor`): a fresh optimum when
  the solve succeeded and its plan is sane; else the next interval of the last
  good plan while it is at most ``max_plan_age_steps`` old; else the configured
  safe setpoint.
- The emulator's hold policy (:class:`SetpointHold`): the setpoint of the
  step; else the last one held for ``hold_s``; else the safe default.
- :class:`InputWait`: how long a due control step waits for missing inputs
  before it gets a fallback.

Times: stamps are integer nanoseconds (exact step arithmetic on message
stamps), plan times are seconds as in :mod:`mshoot_core.mpc`.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
from typing import Any, Mapping, Sequence

import numpy as np

from mshoot_core.units import NS_PER_S

logger = logging.getLogger(__name__)

#: Why an input was rejected.
REJECTION_KINDS = ('non_finite', 'out_of_range', 'length', 'band', 'step', 'stamp', 'grid',
                   'future', 'stale', 'backwards', 'names')
#: Why a setpoint is a fallback (codes of :attr:`Decision.code`).
FALLBACK_CODES = ('solve_failed', 'budget', 'not_converged', 'invalid_plan', 'inputs_missing',
                  'deactivated')
#: Where a published setpoint comes from: 'released' is the last link for a plant with
#: overwrite switches (the overwrites released: the building's own controller acts).
SOURCES = ('optimum', 'plan', 'safe', 'released')
#: Forecast series, in the column names of :mod:`mshoot_core.scenario` (those a forecast of
#: the R1C1 zone needs).
FORECAST_SERIES = ('Tout', 'solrad', 'occ', 'comfort_min', 'comfort_max')
#: The comfort band series of a forecast [degC].
COMFORT_SERIES = ('comfort_min', 'comfort_max')
#: Name of the energy price series of a forecast [currency/kWh].
PRICE_SERIES = 'price'


def zone_band_series(zone: str) -> tuple[str, str]:
    """
    Return the series of one zone's own comfort band [degC]: (lower, upper).

    ``comfort_min_<zone>`` and ``comfort_max_<zone>``: a forecast of several zones' bands
    carries them beside :data:`COMFORT_SERIES` (the first zone's band).
    """
    lower, upper = COMFORT_SERIES
    return f'{lower}_{zone}', f'{upper}_{zone}'


@dataclasses.dataclass(frozen=True)
class Rejection:
    """
    Why an input was refused.

    Attributes
    ----------
    kind : str
        One of :data:`REJECTION_KINDS`.
    reason : str
        One sentence naming the bad value and what was expected.

    """

    kind: str
    reason: str


@dataclasses.dataclass(frozen=True)
class Limits:
    """
    Plausible ranges of the inputs (inclusive); values outside are rejected.

    Attributes
    ----------
    zone_temperature_c : (float, float)
        Zone air temperature [degC].
    outdoor_temperature_c : (float, float)
        Outdoor air temperature [degC].
    solar_radiation_w_m2 : (float, float)
        Global solar radiation [W/m2].
    occupancy : (float, float)
        Occupants [persons].
    comfort_c : (float, float)
        Comfort band bounds [degC].
    damper_percent : (float, float)
        Ventilation damper position ``dpos`` [%].
    price_per_kwh : (float, float)
        Energy price [currency/kWh] (negative prices happen).
    control_abs : float
        Largest plausible magnitude of any control, in its unit (beyond the actuator
        limits a setpoint is clipped; beyond this it is rejected).
    max_samples : int
        Longest forecast or plan accepted [-].
    max_names : int
        Most names in a named vector (states, outputs, controls, series) [-].
    max_values : int
        Most values in an array field whose length the receiver's model does not bound
        (zone temperature plans, output histories) [-].
    output_abs : float
        Largest plausible |measured output| (the model's units: [degC], [J], ...); zone
        temperature outputs are held to ``zone_temperature_c``.

    Series of other names (a model's own disturbances) are only required to be
    finite.

    """

    zone_temperature_c: tuple[float, float] = (-50.0, 80.0)
    outdoor_temperature_c: tuple[float, float] = (-90.0, 70.0)
    solar_radiation_w_m2: tuple[float, float] = (0.0, 2000.0)
    occupancy: tuple[float, float] = (0.0, 10_000.0)
    comfort_c: tuple[float, float] = (-50.0, 80.0)
    damper_percent: tuple[float, float] = (0.0, 100.0)
    price_per_kwh: tuple[float, float] = (-1e4, 1e4)
    control_abs: float = 1e7
    max_samples: int = 10_000
    max_names: int = 1000
    max_values: int = 100_000
    output_abs: float = 1e12

    @property
    def forecast_ranges(self) -> dict[str, tuple[float, float]]:
        """Range of every known forecast or disturbance series (name -> (low, high))."""
        return {'Tout': self.outdoor_temperature_c, 'solrad': self.solar_radiation_w_m2,
                'occ': self.occupancy, 'dpos': self.damper_percent,
                'comfort_min': self.comfort_c, 'comfort_max': self.comfort_c,
                PRICE_SERIES: self.price_per_kwh}


#: The default limits.
LIMITS = Limits()


# -- value checks -------------------------------------------------------------------------
def check_value(name: str, value: Any, low: float = -math.inf,
                high: float = math.inf) -> Rejection | None:
    """Check a finite scalar within [low, high]; return the rejection, else None."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        return Rejection('non_finite', f'{name} must be a number, got {value!r}')
    if not math.isfinite(x):
        return Rejection('non_finite', f'{name} = {x} is not finite')
    if not low <= x <= high:
        return Rejection('out_of_range', f'{name} = {x:g} is outside [{low:g}, {high:g}]')
    return None


def check_series(name: str, values: Sequence[float], low: float = -math.inf,
                 high: float = math.inf) -> Rejection | None:
    """Finite values within [low, high], else the rejection naming the first bad sample."""
    x = np.asarray(values, dtype=float).reshape(-1)
    if x.size and math.isfinite(np.add.reduce(x)) and low <= np.minimum.reduce(x) \
            and np.maximum.reduce(x) <= high:
        return None  # (all finite and within: the usual case, in three reductions)
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        return Rejection('non_finite', f'{name}[{bad[0]}] = {x[bad[0]]} is not finite '
                         f'({bad.size} of {x.size} samples)')
    bad = np.flatnonzero((x < low) | (x > high))
    if bad.size:
        return Rejection('out_of_range', f'{name}[{bad[0]}] = {x[bad[0]]:g} is outside '
                         f'[{low:g}, {high:g}] ({bad.size} of {x.size} samples)')
    return None


def check_stamp_fields(sec: int, nanosec: int) -> Rejection | None:
    """Check a time stamp given as (seconds, nanoseconds): nanoseconds must be below 1e9."""
    if not 0 <= int(nanosec) < NS_PER_S:
        return Rejection('stamp', f'stamp nanosec = {nanosec} is outside [0, 999999999]')
    if int(sec) < 0:
        return Rejection('stamp', f'stamp sec = {sec} is before 1970')
    return None


def check_on_grid(stamp_ns: int, step_ns: int, origin_ns: int = 0) -> Rejection | None:
    """
    Check that a stamp lies on the step grid of its stream: ``origin_ns + k * step_ns``.

    States, forecasts and setpoints are stamped with the start of the step they are for; a
    stamp between two step starts is not one of them (kind 'grid').
    """
    offset = (int(stamp_ns) - int(origin_ns)) % int(step_ns)
    if offset:
        return Rejection('grid', f'stamp {_s(stamp_ns)} is {offset / NS_PER_S:g} s past the '
                         f'start of its step on the {step_ns / NS_PER_S:g} s grid: expected a '
                         'step start')
    return None


def check_lengths(message: str, lengths: Mapping[str, int],
                  caps: Mapping[str, int]) -> Rejection | None:
    """
    Check the array fields of a message against their caps, before any of them is converted.

    Parameters
    ----------
    message : str
        What the message is (for the sentence), e.g. 'zone state'.
    lengths : mapping
        Field -> number of elements as received (``len()`` of the deserialised field).
    caps : mapping
        Field -> most elements the receiver takes (from its model's dimensions:
        :func:`zone_state_caps`, :func:`forecast_caps`, :func:`setpoint_caps`); a field
        without a cap is not limited here.

    """
    for field, cap in caps.items():
        n = int(lengths.get(field, 0))
        if n > cap:
            return Rejection('length', f'{message} {field} has {n} elements, at most {cap} '
                             "expected (the receiver's model dimensions)")
    return None


def zone_state_caps(n_states: int, n_controls: int, limits: Limits = LIMITS) -> dict[str, int]:
    """Return the caps of the array fields of a zone state for a model of this size."""
    return {'state_names': n_states, 'state_values': n_states,
            'output_names': limits.max_names, 'output_values': limits.max_names,
            'control_names': n_controls, 'control_values': n_controls,
            'history_offsets_s': limits.max_samples,
            'history_state_values': n_states * limits.max_samples,
            'history_output_names': limits.max_names,
            'history_output_values': limits.max_values}


def forecast_caps(n_series: int, limits: Limits = LIMITS) -> dict[str, int]:
    """Return the caps of a forecast's array fields for ``n_series`` known disturbance names."""
    return {'series_names': n_series, 'series_values': n_series * limits.max_samples,
            'comfort_min_c': limits.max_samples, 'comfort_max_c': limits.max_samples,
            'price_per_kwh': limits.max_samples}


def setpoint_caps(n_controls: int, limits: Limits = LIMITS) -> dict[str, int]:
    """Return the caps of a setpoint's array fields for a model with ``n_controls`` controls."""
    return {'control_names': n_controls, 'control_values': n_controls,
            'temperature_names': limits.max_names,
            'temperature_setpoints_c': limits.max_names,
            'plan_controls': n_controls * limits.max_samples,
            'plan_temperatures_c': limits.max_values,
            'schedule_offsets_s': limits.max_samples,
            'schedule_values': n_controls * limits.max_samples,
            'released': n_controls}


def check_names(field: str, names: Sequence[str], *, expected: Sequence[str] | None = None,
                allowed: Sequence[str] | None = None,
                limits: Limits = LIMITS) -> Rejection | None:
    """
    Check the names of a named vector.

    Distinct non-empty strings, and either exactly ``expected`` (in any order) or a subset of
    ``allowed``.

    Parameters
    ----------
    field : str
        What the names name (for the message), e.g. 'state_names'.
    names : sequence of str
        The names to check.
    expected : sequence of str, optional
        The names that must all be there, and no others.
    allowed : sequence of str, optional
        The names that may be there.
    limits : Limits
        Plausible ranges (``max_names``: at most that many names).

    """
    if len(names) > limits.max_names:  # (before the names are copied)
        return Rejection('length', f'{field} has {len(names)} names, at most '
                         f'{limits.max_names} expected')
    names = list(names)
    if not all(isinstance(n, str) and n for n in names):
        return Rejection('names', f'{field} must be non-empty names, got {names}')
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        return Rejection('names', f'{field} repeats {duplicates}')
    if expected is not None:
        missing = [n for n in expected if n not in names]
        unknown = [n for n in names if n not in expected]
        if missing or unknown:
            what = '; '.join(part for part in (
                f'lacks {missing}' if missing else '', f'has unknown {unknown}' if unknown
                else '') if part)
            return Rejection('names', f'{field} {what}: expected {list(expected)}')
    if allowed is not None:
        unknown = [n for n in names if n not in allowed]
        if unknown:
            return Rejection('names', f'{field} has unknown {unknown}: known are '
                             f'{list(allowed)}')
    return None


def check_named(field: str, names: Sequence[str], values: Sequence[float],
                low: float = -math.inf, high: float = math.inf, *,
                expected: Sequence[str] | None = None, allowed: Sequence[str] | None = None,
                ranges: Mapping[str, tuple[float, float]] | None = None,
                limits: Limits = LIMITS) -> Rejection | None:
    """
    Check a named vector: one value per name, each finite within its range.

    One value per name (:func:`check_names`), each finite within [low, high] (or its own range in
    ``ranges``).
    """
    if len(values) != len(names):
        return Rejection('length', f'{field}: {len(names)} names but {len(values)} values')
    rejection = check_names(field, names, expected=expected, allowed=allowed, limits=limits)
    if rejection:
        return rejection
    for name, value in zip(names, values):
        lo, hi = (ranges or {}).get(name, (low, high))
        rejection = check_value(f'{field} {name}', value, lo, hi)
        if rejection:
            return rejection
    return None


def reorder(names: Sequence[str], values: Sequence[float], order: Sequence[str]) -> np.ndarray:
    """
    Return the values of a checked named vector in the order ``order``.

    Every name of ``order`` must be in ``names``.
    """
    index = {name: k for k, name in enumerate(names)}
    x = np.asarray(values, dtype=float).reshape(-1)
    return np.array([x[index[name]] for name in order], dtype=float)


def unflatten(field: str, names: Sequence[str], values: Sequence[float], samples: int,
              limits: Limits = LIMITS) -> tuple[dict[str, np.ndarray], Rejection | None]:
    """
    Split named series flattened name-major into a dict, or return the rejection.

    Series i, sample k at ``values[i * samples + k]``; rejected: names not distinct, a length that
    does not match.

    Returns
    -------
    (series, rejection)
        ``series`` is empty when ``rejection`` is not None.

    """
    rejection = check_names(field, names, limits=limits)
    if rejection:
        return {}, rejection
    if len(values) != len(names) * samples:
        return {}, Rejection('length', f'{field}: {len(names)} series of {samples} samples need '
                             f'{len(names) * samples} values, got {len(values)}')
    x = np.asarray(values, dtype=float).reshape(len(names), samples) if names else np.empty(
        (0, samples))
    return {name: x[i].copy() for i, name in enumerate(names)}, None


def named_series(series_names: Sequence[str], series_values: Sequence[float],
                 comfort_min_c: Sequence[float], comfort_max_c: Sequence[float],
                 price_per_kwh: Sequence[float] = (),
                 limits: Limits = LIMITS) -> tuple[dict[str, np.ndarray], Rejection | None]:
    """
    Return the series of a forecast by name from its message form.

    Disturbance series flattened name-major with n = ``len(comfort_min_c)`` samples each, the
    comfort band and the price (none when empty); what :func:`check_forecast` then validates.

    Returns
    -------
    (series, rejection)
        ``rejection`` when the names repeat, clash with the comfort band or the price, or
        the flattened values do not hold n samples per name (then ``series`` is empty).

    """
    series, rejection = unflatten('forecast series_names', series_names, series_values,
                                  len(comfort_min_c), limits)
    if rejection:
        return {}, rejection
    clash = [name for name in (*COMFORT_SERIES, PRICE_SERIES) if name in series]
    if clash:
        return {}, Rejection('names', f'forecast series_names {clash} clash with the '
                             'dedicated comfort and price fields')
    series['comfort_min'] = np.asarray(comfort_min_c, dtype=float)
    series['comfort_max'] = np.asarray(comfort_max_c, dtype=float)
    if len(price_per_kwh):
        series[PRICE_SERIES] = np.asarray(price_per_kwh, dtype=float)
    return series, None


def check_zone_state(state_names: Sequence[str], state_values: Sequence[float],
                     output_names: Sequence[str] = (), output_values: Sequence[float] = (),
                     control_names: Sequence[str] = (), control_values: Sequence[float] = (),
                     *, expected_states: Sequence[str] | None = None,
                     allowed_controls: Sequence[str] | None = None,
                     control_ranges: Mapping[str, tuple[float, float]] | None = None,
                     limits: Limits = LIMITS) -> Rejection | None:
    """
    Check a measured state of a building's zones: named states, outputs and applied controls.

    Parameters
    ----------
    state_names, state_values : sequences
        The model's states by name, in SI units (temperatures [K]); finite
        (their plausible ranges are the controller's, see
        :meth:`mshoot_core.controller.Controller.offer_state`).
    output_names, output_values : sequences
        Measured outputs by name (the model's units); finite, within
        ``limits.output_abs``.
    control_names, control_values : sequences
        The controls applied over the last step by name (heat rates [W]);
        finite, within ``limits.control_abs`` (or each within its
        ``control_ranges``); empty before the first step.
    expected_states : sequence of str, optional
        The receiver's model states: exactly these names (any order).
    allowed_controls : sequence of str, optional
        The receiver's controls: the applied ones must be among them.
    control_ranges : mapping, optional
        Control name -> plausible (low, high) applied value [W] (see
        :func:`applied_control_ranges`).
    limits : Limits
        Plausible ranges.

    """
    return (check_named('state', state_names, state_values, expected=expected_states,
                        limits=limits)
            or check_named('output', output_names, output_values, -limits.output_abs,
                           limits.output_abs, limits=limits)
            or check_named('control', control_names, control_values,
                           -limits.control_abs, limits.control_abs,
                           allowed=allowed_controls, ranges=control_ranges, limits=limits))


def applied_control_ranges(control_names: Sequence[str],
                           control_bounds: Sequence[tuple[float, float]]
                           ) -> dict[str, tuple[float, float]]:
    """
    Return the plausible range of every applied control: its bounds widened by their span.

    A building whose actuator limits differ somewhat from the control model's is not refused;
    an applied heat rate a thousand times the model's limits is.
    """
    ranges = {}
    for name, (low, high) in zip(control_names, control_bounds):
        span = max(float(high) - float(low), abs(float(low)), abs(float(high)))
        ranges[name] = (float(low) - span, float(high) + span)
    return ranges


def check_history(state_names: Sequence[str], offsets_s: Sequence[float],
                  state_values: Sequence[float], output_names: Sequence[str] = (),
                  output_values: Sequence[float] = (),
                  limits: Limits = LIMITS) -> Rejection | None:
    """
    Check the history before the first step that a zone state may carry (a warm-up).

    Parameters
    ----------
    state_names : sequence of str
        The states of the message (the history's states are in their order).
    offsets_s : sequence of float
        m times [s from the stamp]: finite, increasing, <= 0.
    state_values : sequence of float
        The states at those times, flattened name-major (m values per state); finite.
    output_names, output_values : sequences
        Output means over the interval ending at each time, flattened name-major (m values
        per output); finite within ``limits.output_abs``, NaN allowed at the first time only.
    limits : Limits
        Plausible ranges.

    """
    m = len(offsets_s)
    if len(state_values) != m * len(state_names) or len(output_values) != m * len(output_names):
        return Rejection('length', f'history: {m} times need {m * len(state_names)} state and '
                         f'{m * len(output_names)} output values, got {len(state_values)} and '
                         f'{len(output_values)}')
    if not m:
        return None
    rejection = check_names('history_output_names', output_names, limits=limits)
    if rejection:
        return rejection
    offsets = np.asarray(offsets_s, dtype=float)
    rejection = (check_series('history_offsets_s', offsets, -math.inf, 0.0)
                 or check_series('history_state_values', state_values))
    if rejection:
        return rejection
    if m > 1 and not np.all(np.diff(offsets) > 0):
        return Rejection('out_of_range', 'history_offsets_s must increase')
    outputs = np.asarray(output_values, dtype=float).reshape(len(output_names), m)
    first = outputs[:, :1]
    return check_series('history_output_values', np.where(np.isnan(first), 0.0, first),
                        -limits.output_abs, limits.output_abs) or check_series(
        'history_output_values', outputs[:, 1:], -limits.output_abs, limits.output_abs)


def check_disturbances(names: Sequence[str], values: Sequence[float],
                       limits: Limits = LIMITS) -> Rejection | None:
    """
    Check measured disturbances by name.

    Tout [degC], solrad [W/m2], occ [persons], dpos [%] within their plausible ranges; other names
    finite.
    """
    return check_named('disturbance', names, values, ranges=limits.forecast_ranges,
                       limits=limits)


def check_forecast(step_s: float, series: Mapping[str, Sequence[float]],
                   expected_step_s: float | None = None, limits: Limits = LIMITS, *,
                   required: Sequence[str] = FORECAST_SERIES,
                   known: Sequence[str] | None = None) -> Rejection | None:
    """
    Check a forecast of the disturbances, the comfort band and the energy price.

    Parameters
    ----------
    step_s : float
        Sample spacing [s].
    series : mapping
        Name -> samples: the disturbances (Tout [degC], solrad [W/m2], occ
        [persons], dpos [%] or any other model input), ``comfort_min``,
        ``comfort_max`` [degC] and, optionally, ``price`` [currency/kWh]. All of
        one length, finite, the known ones within :attr:`Limits.forecast_ranges`.
    expected_step_s : float, optional
        The control step the forecast must be sampled at [s].
    limits : Limits
        Plausible ranges.
    required : sequence of str
        Series that must be there (default :data:`FORECAST_SERIES`; a
        controller asks for its model's disturbances and the comfort band).
    known : sequence of str, optional
        Every series name the receiver understands (besides ``required``);
        another name is rejected (kind 'names'). None: any name.

    """
    rejection = check_value('step_s', step_s, 1e-9, math.inf)
    if rejection:
        return Rejection(rejection.kind if rejection.kind == 'non_finite' else 'step',
                         rejection.reason)
    if expected_step_s is not None and abs(float(step_s) - expected_step_s) > 1e-6:
        return Rejection('step', f'step_s = {float(step_s):g} s differs from the control step '
                         f'{expected_step_s:g} s')
    missing = [name for name in required if name not in series]
    if missing:
        return Rejection('length', f'forecast lacks the series {missing}')
    rejection = check_names('forecast series', list(series), allowed=None if known is None
                            else [*required, *known], limits=limits)
    if rejection:
        return rejection
    lengths = {name: len(values) for name, values in series.items()}
    if len(set(lengths.values())) != 1:
        return Rejection('length', f'forecast arrays differ in length: {lengths}')
    n = next(iter(lengths.values()))
    if not 1 <= n <= limits.max_samples:
        return Rejection('length', f'forecast has {n} samples, expected 1 to '
                         f'{limits.max_samples}')
    ranges = limits.forecast_ranges
    for name, values in series.items():
        rejection = check_series(name, values, *ranges.get(name, (-math.inf, math.inf)))
        if rejection:
            return rejection
    if all(name in series for name in COMFORT_SERIES):
        low = np.asarray(series['comfort_min'], dtype=float)
        high = np.asarray(series['comfort_max'], dtype=float)
        bad = np.flatnonzero(low > high)
        if bad.size:
            k = bad[0]
            return Rejection('band', f'comfort band inverted at sample {k}: comfort_min '
                             f'{low[k]:g} > comfort_max {high[k]:g} degC ({bad.size} samples)')
    return None


def check_setpoint(step_s: float, control_names: Sequence[str],
                   control_values: Sequence[float], temperature_names: Sequence[str] = (),
                   temperatures_c: Sequence[float] = (), plan_controls: Sequence[float] = (),
                   plan_temperatures_c: Sequence[float] = (), *,
                   expected_step_s: float | None = None,
                   expected_controls: Sequence[str] | None = None,
                   schedule_offsets_s: Sequence[float] = (),
                   schedule_values: Sequence[float] = (), schedules: bool = True,
                   released: Sequence[bool] = (),
                   limits: Limits = LIMITS) -> Rejection | None:
    """
    Check a supervisory setpoint: named controls, zone temperature setpoints, the plan.

    Parameters
    ----------
    step_s : float
        Control step [s].
    control_names, control_values : sequences
        Every control by name (in its unit): at least one; finite within
        ``limits.control_abs`` (beyond the actuator limits but within this
        they are not rejected here: the building clips them, with a warning).
    temperature_names, temperatures_c : sequences
        Temperature setpoints of the zones' local loops by name [degC].
    plan_controls, plan_temperatures_c : sequences
        The plan over m intervals, flattened name-major (control i over
        interval k at ``plan_controls[i * m + k]``; the same for the
        temperatures): ``m * len(control_names)`` and
        ``m * len(temperature_names)`` values.
    expected_step_s : float, optional
        The receiver's control step [s].
    expected_controls : sequence of str, optional
        The receiver's controls: exactly these names (any order).
    schedule_offsets_s, schedule_values : sequences
        An optional schedule within the step (:func:`check_schedule`).
    schedules : bool
        Whether the receiver takes a schedule within the step (else a setpoint with one is
        rejected).
    released : sequence of bool
        Per control, whether its overwrite is released (empty: none).
    limits : Limits
        Plausible ranges.

    """
    rejection = check_value('step_s', step_s, 1e-9, math.inf)
    if rejection:
        return rejection
    if expected_step_s is not None and abs(float(step_s) - expected_step_s) > 1e-6:
        return Rejection('step', f'step_s = {float(step_s):g} s differs from the control step '
                         f'{expected_step_s:g} s')
    if not len(control_names):
        return Rejection('names', 'the setpoint names no control')
    rejection = (check_named('control', control_names, control_values,
                             -limits.control_abs, limits.control_abs,
                             expected=expected_controls, limits=limits)
                 or check_named('temperature setpoint', temperature_names, temperatures_c,
                                *limits.zone_temperature_c, limits=limits))
    if rejection:
        return rejection
    nc, nz = len(control_names), len(temperature_names)
    if len(released) not in (0, nc):
        return Rejection('length', f'released has {len(released)} flags for {nc} controls '
                         '(one per control, or none)')
    m, rest = divmod(len(plan_controls), nc)
    if rest or len(plan_temperatures_c) != m * nz:
        return Rejection('length', f'plan arrays do not match {nc} controls and {nz} '
                         f'temperatures over the same intervals: plan_controls '
                         f'{len(plan_controls)}, plan_temperatures_c '
                         f'{len(plan_temperatures_c)} values')
    if m > limits.max_samples:
        return Rejection('length', f'plan has {m} intervals, at most '
                         f'{limits.max_samples} expected')
    return (check_series('plan_controls', plan_controls, -limits.control_abs,
                         limits.control_abs)
            or check_series('plan_temperatures_c', plan_temperatures_c,
                            *limits.zone_temperature_c)
            or (check_schedule(schedule_offsets_s, schedule_values, nc, float(step_s),
                               schedules, limits)
                if len(schedule_offsets_s) or len(schedule_values) else None))


def check_schedule(offsets_s: Sequence[float], values: Sequence[float], n_controls: int,
                   step_s: float, allowed: bool = True,
                   limits: Limits = LIMITS) -> Rejection | None:
    """
    Check a schedule within a step: n pieces, every control's value over each.

    Parameters
    ----------
    offsets_s : sequence of float
        Start of every piece [s from the step start]: the first 0, increasing, within the step.
    values : sequence of float
        n values per control, flattened name-major [W]; finite within
        ``limits.control_abs``.
    n_controls : int
        Controls of the setpoint.
    step_s : float
        Control step [s].
    allowed : bool
        Whether the receiver takes schedules at all.
    limits : Limits
        Plausible ranges.

    """
    n = len(offsets_s)
    if not allowed:
        return Rejection('length', 'a schedule within the step needs lockstep mode, got '
                         f'{n} offsets')
    if n == 0 or len(values) != n * n_controls:
        return Rejection('length', f'a schedule within the step needs n offsets and n values '
                         f'per control ({n_controls}), got {n} offsets and {len(values)} values')
    offsets = np.asarray(offsets_s, dtype=float)
    rejection = (check_series('schedule_offsets_s', offsets, 0.0, step_s)
                 or check_series('schedule_values', values, -limits.control_abs,
                                 limits.control_abs))
    if rejection:
        return rejection
    if offsets[0] != 0.0 or (n > 1 and not np.all(np.diff(offsets) > 0)) \
            or offsets[-1] >= step_s:
        return Rejection('out_of_range', f'schedule_offsets_s must start at 0 and increase '
                         f'within the {step_s:g} s step, got {offsets.tolist()[:10]}')
    return None


# -- time stamps --------------------------------------------------------------------------
class StampGate:
    """
    Refuses stamps that go backwards, lie in the future or are too old to be used.

    One gate per input stream. The rules, in order, for a stamp ``t`` when the
    receiver's clock reads ``now`` (0: no clock yet, e.g. simulated time before
    the first /clock; then only the grid and the order are checked):

    0. with a grid (``origin_ns`` given), ``t`` not a step start
       ``origin_ns + k * step_ns``: 'grid' (:func:`check_on_grid`);
    1. ``t`` equal to the newest accepted stamp: accepted (a repeat, e.g. a
       heartbeat or a re-delivered latched message);
    2. ``t`` before the newest accepted stamp: 'backwards';
    3. ``t > now + max_future_ns``: 'future';
    4. ``t`` before the start of the current step minus ``max_age_ns``: 'stale'.

    :meth:`check` moves nothing: a message is checked whole (every field and its stamp)
    before :meth:`accept` records its stamp.

    Parameters
    ----------
    step_ns : int
        Control step [ns] (the grid of "the current step").
    max_age_ns : int
        Oldest usable stamp before the current step's start [ns].
    max_future_ns : int
        Largest lead over the clock [ns] (data and clock topics are not
        ordered, so a stamp one step ahead is normal in simulated time).
    origin_ns : int, optional
        A step start [ns]: stamps must lie on the grid ``origin_ns + k * step_ns``
        (None: any stamp).

    """

    def __init__(self, step_ns: int, max_age_ns: int = 0, max_future_ns: int = 0,
                 origin_ns: int | None = None) -> None:
        if step_ns <= 0 or max_age_ns < 0 or max_future_ns < 0:
            raise ValueError(f'step_ns must be > 0 and the tolerances >= 0, got {step_ns}, '
                             f'{max_age_ns}, {max_future_ns}')
        self.step_ns = int(step_ns)
        self.max_age_ns = int(max_age_ns)
        self.max_future_ns = int(max_future_ns)
        self.origin_ns = None if origin_ns is None else int(origin_ns)
        self.latest_ns: int | None = None

    def check(self, stamp_ns: int, now_ns: int) -> Rejection | None:
        """Return the rejection of a stamp, None if acceptable (see the class docstring)."""
        stamp_ns, now_ns = int(stamp_ns), int(now_ns)
        if self.origin_ns is not None:
            rejection = check_on_grid(stamp_ns, self.step_ns, self.origin_ns)
            if rejection:
                return rejection
        if self.latest_ns is not None:
            if stamp_ns == self.latest_ns:
                return None
            if stamp_ns < self.latest_ns:
                return Rejection('backwards', f'stamp {_s(stamp_ns)} is before the previous one '
                                 f'{_s(self.latest_ns)}: time went backwards')
        if now_ns > 0:
            if stamp_ns > now_ns + self.max_future_ns:
                return Rejection('future', f'stamp {_s(stamp_ns)} is '
                                 f'{(stamp_ns - now_ns) / NS_PER_S:g} s ahead of the clock '
                                 f'{_s(now_ns)} (at most {self.max_future_ns / NS_PER_S:g} s)')
            oldest = (now_ns // self.step_ns) * self.step_ns - self.max_age_ns
            if stamp_ns < oldest:
                return Rejection('stale', f'stamp {_s(stamp_ns)} is '
                                 f'{(now_ns - stamp_ns) / NS_PER_S:g} s old: older than '
                                 f'{_s(oldest)}, the oldest usable now')
        return None

    def accept(self, stamp_ns: int, now_ns: int) -> None:
        """
        Remember an accepted stamp, only once a clock runs.

        A stamp that could not be checked against the clock must not lock out the ones that follow.
        """
        if int(now_ns) > 0:
            self.latest_ns = max(int(stamp_ns), self.latest_ns or 0)

    def reset(self) -> None:
        """Forget the newest stamp (after the clock jumped back: a restarted simulation)."""
        self.latest_ns = None


def _s(ns: int) -> str:
    return f'{ns / NS_PER_S:.3f} s'


class RejectionCounter:
    """
    Counts rejections per input stream and kind.

    Attributes
    ----------
    counts : Counter
        (stream, kind) -> number of rejections.

    """

    def __init__(self) -> None:
        self.counts: collections.Counter[tuple[str, str]] = collections.Counter()

    def add(self, stream: str, rejection: Rejection) -> int:
        """Count one rejection; return the stream's total so far."""
        self.counts[(stream, rejection.kind)] += 1
        return self.total(stream)

    def total(self, stream: str | None = None) -> int:
        """Rejections of ``stream`` (all streams when None)."""
        return sum(n for (s, _), n in self.counts.items() if stream is None or s == stream)

    def by_kind(self, stream: str | None = None) -> dict[str, int]:
        """Kind -> rejections of ``stream`` (all streams when None)."""
        out: dict[str, int] = {}
        for (s, kind), n in sorted(self.counts.items()):
            if stream is None or s == stream:
                out[kind] = out.get(kind, 0) + n
        return out


# -- the MPC fallback chain ---------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Decision:
    """
    The setpoint of one control step and where it comes from.

    Attributes
    ----------
    t_s : float
        Start of the step [s].
    controls : ndarray, shape (nc,)
        Controls to apply over the step (finite, within the bounds).
    predicted_state : ndarray, shape (nx,), or None
        Predicted state at the end of the step (None for the safe setpoint).
    plan_controls : ndarray, shape (m, nc)
        The plan from this step on (empty for the safe setpoint).
    plan_states : ndarray, shape (m, nx)
        Predicted states at the end of every planned interval.
    source : str
        'optimum' (this step's solve), 'plan' (the last good plan's interval
        for this step), 'safe' (the safe values) or 'released' (the overwrites of
        ``released`` controls released, the safe values of the others).
    fallback : bool
        True unless ``source`` is 'optimum'.
    code : str
        '' or one of :data:`FALLBACK_CODES`: why the solve result was not used.
    reason : str
        '' or one sentence saying why, and what was used instead.
    released : tuple of bool
        Per control: whether its overwrite is released (the building's own controller
        acts; ``controls`` then holds its safe value, applied by a plant without a switch);
        empty when none is.

    """

    t_s: float
    controls: np.ndarray
    predicted_state: np.ndarray | None
    plan_controls: np.ndarray
    plan_states: np.ndarray
    source: str
    fallback: bool
    code: str = ''
    reason: str = ''
    released: tuple[bool, ...] = ()


@dataclasses.dataclass
class _GoodPlan:
    t_s: float
    controls: np.ndarray  # (N, nc)
    states: np.ndarray    # (N, nx): end of every interval


class SetpointSupervisor:
    """
    The MPC's fallback chain: the optimum, else the last good plan, else the last link.

    The last link releases the overwrites of the ``released`` controls (the building's own
    controller takes over; source 'released') and applies the safe values of the others
    (source 'safe' when none is released).

    Parameters
    ----------
    control_bounds : sequence of (float, float)
        Actuator limits of every control (physical units).
    step_s : float
        Control step [s].
    safe_controls : sequence of float
        The safe values (clipped to the bounds).
    max_plan_age_steps : int
        How many steps after it was computed a good plan may still be used
        (0: never fall back on a plan, go to the safe setpoint at once).
    state_range : (sequence, sequence), optional
        Plausible (lower, upper) state values (physical units); a plan whose
        predicted states leave them is not used.
    bound_tolerance : float
        Relative slack on the control bounds before a plan is refused (a
        solver's bound satisfaction is only up to its tolerance; within it the
        controls are clipped).
    released : sequence of bool, optional
        Per control: the last link releases its overwrite (a plant with an overwrite
        switch) instead of applying its safe value (default: none).

    """

    def __init__(self, control_bounds: Sequence[tuple[float, float]], step_s: float,
                 safe_controls: Sequence[float], *, max_plan_age_steps: int = 4,
                 state_range: tuple[Sequence[float], Sequence[float]] | None = None,
                 bound_tolerance: float = 1e-6,
                 released: Sequence[bool] | None = None) -> None:
        bounds = np.asarray(control_bounds, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(bounds)) or np.any(bounds[:, 0] > bounds[:, 1]):
            raise ValueError(f'control_bounds must be finite (min, max) pairs, got '
                             f'{bounds.tolist()}')
        safe = np.asarray(safe_controls, dtype=float).reshape(-1)
        if safe.size != bounds.shape[0] or not np.all(np.isfinite(safe)):
            raise ValueError(f'safe_controls must be {bounds.shape[0]} finite values, got '
                             f'{safe.tolist()}')
        if not step_s > 0:
            raise ValueError(f'step_s must be > 0, got {step_s}')
        if max_plan_age_steps < 0:
            raise ValueError(f'max_plan_age_steps must be >= 0, got {max_plan_age_steps}')
        self.bounds = bounds
        self.step_s = float(step_s)
        self.safe_controls = np.clip(safe, bounds[:, 0], bounds[:, 1])
        released = tuple(bool(r) for r in (released or ()))
        if released and len(released) != bounds.shape[0]:
            raise ValueError(f'released must have one flag per control ({bounds.shape[0]}), '
                             f'got {list(released)}')
        #: Per control: released by the last link (empty: none).
        self.released = released if any(released) else ()
        self.max_plan_age_steps = int(max_plan_age_steps)
        self.state_range = (None if state_range is None else
                            (np.asarray(state_range[0], dtype=float),
                             np.asarray(state_range[1], dtype=float)))
        self.bound_tolerance = float(bound_tolerance)
        self._limits: tuple | None = None  # (_control_limits)
        self._plan: _GoodPlan | None = None
        #: Consecutive steps without a fresh optimum.
        self.consecutive_fallbacks = 0
        #: Decisions by source since the start.
        self.sources: collections.Counter[str] = collections.Counter()
        self._at_last_link = False

    @property
    def n_controls(self) -> int:
        return self.bounds.shape[0]

    def reset(self) -> None:
        """Forget the last good plan (e.g. after the clock jumped back)."""
        self._plan = None
        self.consecutive_fallbacks = 0

    def plan_problem(self, controls: Any, states: Any) -> str | None:
        """
        Return why a plan cannot be applied, or None.

        The reasons: non-finite, outside the bounds or the state range, wrong shape.
        """
        try:
            u = np.asarray(controls, dtype=float)
            x = np.asarray(states, dtype=float)
        except (TypeError, ValueError) as exc:
            return f'the plan is not numeric ({exc})'
        if u.ndim != 2 or u.shape[1] != self.n_controls or u.shape[0] < 1:
            return f'the plan has shape {u.shape}, expected (N >= 1, {self.n_controls})'
        if x.ndim != 2 or x.shape[0] != u.shape[0]:
            return f'the predicted states have shape {x.shape} for {u.shape[0]} intervals'
        if not np.isfinite(u).all():
            return 'the plan holds non-finite controls'
        if not np.isfinite(x).all():
            return 'the predicted states are not finite'
        lowest, highest = self._control_limits()
        if (u < lowest).any() or (u > highest).any():
            return (f'the plan leaves the control bounds {self.bounds.tolist()} '
                    f'(range {u.min():g} to {u.max():g})')
        if self.state_range is not None:
            low, high = self.state_range
            if (x < low).any() or (x > high).any():
                return (f'the predicted states leave the plausible range [{low.tolist()}, '
                        f'{high.tolist()}] (range {x.min():g} to {x.max():g})')
        return None

    def _control_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the lowest and highest controls a plan may hold: the bounds and a tolerance.

        ``bound_tolerance`` of the larger of the bound's magnitude and the range, plus 1e-9;
        computed again when the bounds or the tolerance changed.
        """
        key = (self.bounds.tobytes(), self.bounds.shape, self.bound_tolerance)
        cached = self._limits
        if cached is None or cached[0] != key:
            span = self.bounds[:, 1] - self.bounds[:, 0]
            slack = (self.bound_tolerance * np.maximum(np.abs(self.bounds).max(axis=1), span)
                     + 1e-9)
            cached = self._limits = (key, (self.bounds[:, 0] - slack, self.bounds[:, 1] + slack))
        return cached[1]

    def review(self, t_s: float, result: Any, *, accept_unconverged: bool = True) -> Decision:
        """
        Return the setpoint of the step at ``t_s`` given its solve result.

        Parameters
        ----------
        t_s : float
            Start of the step [s].
        result : MpcResult-like
            ``success``, ``message``, ``controls`` (N, nc) and ``states``
            (N+1, nx: x0 first).
        accept_unconverged : bool
            Use the best plan of a solver that did not converge (the offline
            loop does) if it is sane; else fall back.

        """
        try:
            controls = np.asarray(result.controls, dtype=float)
            states = np.asarray(result.states, dtype=float)[1:]
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            return self.fallback(t_s, 'invalid_plan', f'the solve returned no usable plan '
                                 f'({exc})')
        problem = self.plan_problem(controls, states)
        if problem:
            return self.fallback(t_s, 'invalid_plan', problem)
        if not bool(result.success) and not accept_unconverged:
            return self.fallback(t_s, 'not_converged',
                                 f'solver did not converge: {result.message}')
        controls = np.clip(controls, self.bounds[:, 0], self.bounds[:, 1])
        self._plan = _GoodPlan(float(t_s), controls.copy(), states.copy())
        self.consecutive_fallbacks = 0
        self._at_last_link = False
        self.sources['optimum'] += 1
        return Decision(float(t_s), controls[0].copy(), states[0].copy(), controls.copy(),
                        states.copy(), 'optimum', False)

    def fallback(self, t_s: float, code: str, reason: str) -> Decision:
        """
        Return the fallback of the step at ``t_s``: the last good plan's interval, else safe.

        Parameters
        ----------
        t_s : float
            Start of the step [s].
        code : str
            One of :data:`FALLBACK_CODES`.
        reason : str
            Why the step's own solve cannot be used.

        """
        if code not in FALLBACK_CODES:
            raise ValueError(f'code must be one of {list(FALLBACK_CODES)}, got {code!r}')
        self.consecutive_fallbacks += 1
        plan = self._plan
        if plan is not None:
            age = int(round((float(t_s) - plan.t_s) / self.step_s))
            if 1 <= age <= self.max_plan_age_steps and age < plan.controls.shape[0]:
                self.sources['plan'] += 1
                return Decision(float(t_s), plan.controls[age].copy(), plan.states[age].copy(),
                                plan.controls[age:].copy(), plan.states[age:].copy(), 'plan',
                                True, code, f'{reason}; fallback: interval {age} of the plan '
                                f'made {age} step(s) ago')
            why = (f'the last good plan is {age} steps old (at most {self.max_plan_age_steps})'
                   if age >= 1 else 'no earlier plan')
        else:
            why = 'no good plan yet'
        return self.safe(t_s, code, f'{reason}; fallback: {self.last_link} ({why})')

    @property
    def last_link(self) -> str:
        """Say what the last link of the chain applies (for reasons and logs)."""
        if not self.released:
            return f'the safe values {self.safe_controls.tolist()}'
        kept = [f'{v:g}' for v, r in zip(self.safe_controls, self.released) if not r]
        return ("the overwrites released (the building's own controller acts)"
                + (f', the safe values {kept} for the other controls' if kept else ''))

    def safe(self, t_s: float, code: str, reason: str) -> Decision:
        """
        Return the last link of the chain, with ``reason`` as given.

        The overwrites of the released controls released (source 'released'), the safe values
        of the others; without released controls the safe values (source 'safe').
        """
        source = 'released' if self.released else 'safe'
        self.sources[source] += 1
        if not self._at_last_link:  # logged once per run of last-link steps
            logger.log(logging.WARNING if self.released else logging.INFO,
                       'step at %.0f s: %s (%s)', t_s, self.last_link, code)
            self._at_last_link = True
        nx = self._plan.states.shape[1] if self._plan is not None else 0
        return Decision(float(t_s), self.safe_controls.copy(), None,
                        np.empty((0, self.n_controls)), np.empty((0, nx)), source, True, code,
                        reason, self.released)


# -- waiting for inputs -------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class InputWait:
    """
    How long a due control step waits for a missing or stale input.

    The wait is measured from the moment the controller found the step due
    (a controller started in the middle of a step waits too), on two clocks:

    Attributes
    ----------
    wait_s : float
        Wall time [s] after which the step gets a fallback (in lockstep
        simulated time stands still while the controller waits).
    deadline_s : float
        Time on the controller's own clock [s] (simulated time running freely,
        or real time) after which the step gets a fallback; 0 disables it.

    """

    wait_s: float = 5.0
    deadline_s: float = 1800.0

    def overdue(self, waited_wall_s: float, waited_clock_s: float) -> bool:
        """Return True when the step should stop waiting and fall back."""
        return waited_wall_s >= self.wait_s or (
            self.deadline_s > 0 and waited_clock_s >= self.deadline_s)


# -- the emulator's hold policy -----------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class HoldDecision:
    """
    Controls the building applies over a step.

    Attributes
    ----------
    controls : ndarray, shape (nc,)
    source : str
        'setpoint' (stamped for this step), 'held' (an earlier one, within
        the hold time) or 'safe' (the safe default).
    age_s : float
        Age of the setpoint used at the step start [s] (0 for 'setpoint',
        NaN for 'safe').
    reason : str
        '' for 'setpoint', else one sentence.
    released : tuple of bool
        Per control, its overwrite released (empty: none).

    """

    controls: np.ndarray
    source: str
    age_s: float
    reason: str = ''
    released: tuple[bool, ...] = ()


class SetpointHold:
    """
    What a building applies when the supervisory setpoint of a step is missing.

    Parameters
    ----------
    safe_controls : sequence of float
        The safe default controls.
    hold_s : float
        How long after its step's start a setpoint may still be applied [s].
    released : sequence of bool, optional
        Per control: the safe default releases its overwrite (a plant with its switch) rather
        than applying its safe value (default: none).

    """

    def __init__(self, safe_controls: Sequence[float], hold_s: float,
                 released: Sequence[bool] = ()) -> None:
        self.safe_controls = np.asarray(safe_controls, dtype=float).reshape(-1)
        if not np.all(np.isfinite(self.safe_controls)):
            raise ValueError(f'safe_controls must be finite, got {self.safe_controls}')
        if not hold_s >= 0:
            raise ValueError(f'hold_s must be >= 0, got {hold_s}')
        self.hold_s = float(hold_s)
        self.released = tuple(bool(r) for r in released) if any(released) else ()
        self._latest: tuple[float, np.ndarray, tuple[bool, ...]] | None = None

    @property
    def latest_t_s(self) -> float | None:
        """Step start of the newest setpoint [s] (None before the first)."""
        return None if self._latest is None else self._latest[0]

    def offer(self, t_s: float, controls: Sequence[float], released: Sequence[bool] = ()) -> None:
        """
        Offer a validated setpoint for the step starting at ``t_s`` (older ones are ignored).

        ``released``: per control, its overwrite released (empty: none).
        """
        u = np.asarray(controls, dtype=float).reshape(-1)
        if u.shape != self.safe_controls.shape or not np.all(np.isfinite(u)):
            raise ValueError(f'controls must be {self.safe_controls.size} finite values, '
                             f'got {u}')
        if self._latest is None or float(t_s) >= self._latest[0]:
            self._latest = (float(t_s), u.copy(), tuple(bool(r) for r in released))

    def controls_for(self, t_s: float) -> HoldDecision:
        """Return the controls of the step starting at ``t_s``."""
        if self._latest is not None:
            stamp, u, released = self._latest
            age = float(t_s) - stamp
            if abs(age) < 1e-6:
                return HoldDecision(u.copy(), 'setpoint', 0.0, released=released)
            if 0 < age <= self.hold_s + 1e-6:
                return HoldDecision(u.copy(), 'held', age,
                                    f'no setpoint for this step: holding the one from {age:g} s '
                                    f'earlier ({u.tolist()}; hold {self.hold_s:g} s)', released)
            why = (f'the last one is {age:g} s old (hold {self.hold_s:g} s)' if age > 0
                   else 'the last one is for a later step')
        else:
            why = 'none received yet'
        what = ("releasing the overwrites (the building's own controller acts)" if self.released
                else f'applying the safe default {self.safe_controls.tolist()}')
        return HoldDecision(self.safe_controls.copy(), 'safe', math.nan,
                            f'no setpoint for this step and {why}: {what}', self.released)
