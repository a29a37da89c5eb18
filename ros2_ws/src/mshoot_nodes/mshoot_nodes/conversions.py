"""
Messages <-> numpy arrays and pandas DataFrames, and ROS time <-> seconds.

The nodes stay thin by converting at their edges only: everything inside is
:mod:`mshoot_core` data (states in K as arrays, forecasts and scenarios as
DataFrames with the columns of :mod:`mshoot_core.scenario`).

Messages carry named vectors: ``*_names`` with ``*_values`` one to one, and named
series flattened name-major (series i, sample k at ``values[i * n + k]``,
:func:`flatten`); the names are the model's canonical names (states ``T``,
controls ``q``, disturbances ``Tout``, ...). Checks of what arrives are in
:mod:`mshoot_core.safety`.

Times: ROS stamps are handled as integer nanoseconds (exact comparisons of
step stamps); scenario times are float seconds since the scenario start.
"""
from __future__ import annotations

from typing import Iterable, Mapping, Sequence, TYPE_CHECKING

from builtin_interfaces.msg import Time
from mshoot_core.safety import named_series, PRICE_SERIES, Rejection
from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import Disturbances, Forecast, MpcStatus, Setpoint, ZoneState
import numpy as np
import pandas as pd
from rosgraph_msgs.msg import Clock

if TYPE_CHECKING:  # the emulator process need not import scipy (through mshoot_core.mpc)
    from mshoot_core.actuation import Schedule
    from mshoot_core.models.registry import ControlInterface
    from mshoot_core.mpc import MpcResult
    from mshoot_core.safety import Decision

#: Disturbance series a forecast carries by default (those of the R1C1 zone but the
#: ventilation, which the MPC assumes).
FORECAST_DISTURBANCES = ('Tout', 'solrad', 'occ')


# -- time ---------------------------------------------------------------------------------
def field_lengths(msg: object, fields: Iterable[str]) -> dict[str, int]:
    """Return the number of elements of array fields of a message (nothing is converted)."""
    return {field: len(getattr(msg, field)) for field in fields}


def seconds_to_ns(seconds: float) -> int:
    """Seconds -> integer nanoseconds (rounded to the nearest ns)."""
    return int(round(float(seconds) * NS_PER_S))


def stamp_to_ns(stamp: Time) -> int:
    """Return a ``builtin_interfaces/Time`` as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (>= 0) as a ``builtin_interfaces/Time``."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def clock_msg(ns: int) -> Clock:
    """Return a ``rosgraph_msgs/Clock`` at ``ns``."""
    return Clock(clock=ns_to_stamp(ns))


def floor_to_step(ns: int, step_ns: int) -> int:
    """Return the start of the step holding ``ns`` on the grid of multiples of ``step_ns``."""
    return (int(ns) // int(step_ns)) * int(step_ns)


# -- named vectors ------------------------------------------------------------------------
def named(names: Sequence[str], values: Sequence[float]) -> dict[str, float]:
    """Return a named vector of a message (``*_names``, ``*_values``) as a dict."""
    return {str(name): float(value) for name, value in zip(names, values)}


def flatten(series: Mapping[str, Sequence[float]]) -> tuple[list[str], list[float]]:
    """Named series of one length as (names, values flattened name-major)."""
    names = [str(name) for name in series]
    if not names:
        return names, []
    return names, np.concatenate([np.asarray(series[name], dtype=float).reshape(-1)
                                  for name in names]).tolist()


def unflatten_series(names: Sequence[str], values: Sequence[float]) -> dict[str, np.ndarray]:
    """
    Split named series flattened name-major back into a dict.

    ValueError on a length that does not split evenly.
    """
    if not names:
        if len(values):
            raise ValueError(f'{len(values)} values for no names')
        return {}
    n, rest = divmod(len(values), len(names))
    if rest:
        raise ValueError(f'{len(values)} values do not split into {len(names)} series')
    x = np.asarray(values, dtype=float).reshape(len(names), n)
    return {str(name): x[i].copy() for i, name in enumerate(names)}


# -- zone state ---------------------------------------------------------------------------
def zone_state_msg(stamp_ns: int, states: Mapping[str, float],
                   outputs: Mapping[str, float] | None = None,
                   controls: Mapping[str, float] | None = None, zone: str = '') -> ZoneState:
    """
    Build the state of a building's zones at ``stamp_ns`` as named vectors.

    Parameters
    ----------
    stamp_ns : int
        Time of the measurement [ns].
    states : mapping
        The model's states by name, SI units (temperatures [K]).
    outputs : mapping, optional
        Measured outputs by name (the model's units; temperatures [degC]).
    controls : mapping, optional
        Controls applied over the last step by name (heat rates [W]).
    zone : str
        Building or zone name (``header.frame_id``).

    """
    msg = ZoneState()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    for field, values in (('state', states), ('output', outputs or {}),
                          ('control', controls or {})):
        setattr(msg, f'{field}_names', [str(name) for name in values])
        setattr(msg, f'{field}_values', [float(v) for v in values.values()])
    return msg


def zone_state_states(msg: ZoneState) -> dict[str, float]:
    """Return the states of a zone state message by name (SI units)."""
    return named(msg.state_names, msg.state_values)


# -- disturbances -------------------------------------------------------------------------
def disturbances_msg(stamp_ns: int, values: Mapping[str, float],
                     zone: str = '') -> Disturbances:
    """Measured disturbances by name (scenario units: Tout [degC], solrad [W/m2], ...)."""
    msg = Disturbances()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.names = [str(name) for name in values]
    msg.values = [float(v) for v in values.values()]
    return msg


def disturbances_to_series(msg: Disturbances) -> pd.Series:
    """Return a Disturbances message as a Series indexed by the disturbance names."""
    return pd.Series(named(msg.names, msg.values), dtype=float)


# -- forecast -----------------------------------------------------------------------------
def forecast_msg(stamp_ns: int, step_s: float, window: pd.DataFrame,
                 series: Sequence[str] = FORECAST_DISTURBANCES, zone: str = '') -> Forecast:
    """
    Build a forecast message from a window of scenario rows.

    Parameters
    ----------
    stamp_ns : int
        Start time of the first sample [ns].
    step_s : float
        Sample spacing [s].
    window : DataFrame, shape (n, ...)
        Rows with the columns ``series``, ``comfort_min``, ``comfort_max`` [degC]
        and optionally ``price`` [currency/kWh] (e.g.
        :func:`mshoot_core.scenario.forecast_window`: N+1 rows).
    series : sequence of str
        The disturbance columns to send (default: Tout, solrad, occ).
    zone : str
        ``header.frame_id``.

    """
    msg = Forecast()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.step_s = float(step_s)
    bands = ['comfort_min', 'comfort_max'] + ([PRICE_SERIES] if PRICE_SERIES in window.columns
                                              else [])
    names = [str(name) for name in series]
    # The window as one array (selecting columns in pandas costs a millisecond).
    position = {name: k for k, name in enumerate(window.columns)}
    missing = [name for name in names + bands if name not in position]
    if missing:
        raise KeyError(f'the forecast window has no column(s) {missing}')
    columns = window.to_numpy(dtype=float).T[[position[name] for name in names + bands]]
    msg.series_names = names
    msg.series_values = columns[:len(names)].reshape(-1).tolist()
    msg.comfort_min_c = columns[len(names)].tolist()
    msg.comfort_max_c = columns[len(names) + 1].tolist()
    if len(bands) > 2:
        msg.price_per_kwh = columns[len(names) + 2].tolist()
    return msg


def forecast_length(msg: Forecast) -> int:
    """Return the number of samples of a forecast (that of its comfort band)."""
    return len(msg.comfort_min_c)


def forecast_series(msg: Forecast) -> tuple[dict[str, np.ndarray], Rejection | None]:
    """
    Return the series of a forecast by name.

    Its disturbances, ``comfort_min``, ``comfort_max`` and ``price`` (when given), checked for
    their names and lengths only (:func:`mshoot_core.safety.named_series`); what
    :func:`mshoot_core.safety.check_forecast` validates.

    Returns
    -------
    (series, rejection)
        ``rejection`` when the names repeat or clash, or the flattened values do not
        hold one series of n samples per name (then ``series`` is empty).

    """
    return named_series(list(msg.series_names), msg.series_values, msg.comfort_min_c,
                        msg.comfort_max_c, msg.price_per_kwh)


def forecast_to_frame(msg: Forecast, assumed: Mapping[str, float] | None = None) -> pd.DataFrame:
    """
    Return a forecast message as a DataFrame of its series (ValueError if malformed).

    Parameters
    ----------
    msg : Forecast
        The forecast message.
    assumed : mapping, optional
        Series the message does not carry, held constant (e.g. ``{'dpos': 0.0}``).

    Returns
    -------
    DataFrame, shape (n, ...)
        One column per series (disturbances, comfort_min, comfort_max, price
        when given, then the assumed ones); index the sample start times [s]
        (ROS time).

    """
    series, rejection = forecast_series(msg)
    if rejection:
        raise ValueError(rejection.reason)
    n = forecast_length(msg)
    lengths = {name: len(values) for name, values in series.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f'forecast arrays differ in length: {lengths}')
    t0 = stamp_to_ns(msg.header.stamp) / NS_PER_S
    frame = pd.DataFrame(series, index=pd.Index(t0 + np.arange(n) * msg.step_s,
                                                name='time_s'))
    for name, value in (assumed or {}).items():
        if name not in frame.columns:
            frame[name] = float(value)
    return frame


# -- setpoint and status ------------------------------------------------------------------
def setpoint_msg(stamp_ns: int, step_s: float, controls: Mapping[str, float],
                 temperatures_c: Mapping[str, float] | None = None,
                 plan_controls: Mapping[str, Sequence[float]] | None = None,
                 plan_temperatures_c: Mapping[str, Sequence[float]] | None = None,
                 zone: str = '', released: Sequence[bool] = ()) -> Setpoint:
    """
    Build a setpoint: named controls, zone temperature setpoints and the plan behind them.

    Parameters
    ----------
    stamp_ns : int
        Start of the step [ns].
    step_s : float
        Control step [s].
    controls : mapping
        Every control by name (each in its unit).
    temperatures_c : mapping, optional
        Temperature setpoint of every zone by name [degC].
    plan_controls, plan_temperatures_c : mapping, optional
        The plan: per control (per zone temperature) its values over the
        intervals, all of one length; the keys in the order of ``controls``
        (``temperatures_c``). None: no plan.
    zone : str
        ``header.frame_id``.
    released : sequence of bool
        Per control (in the order of ``controls``): its overwrite released (empty: none).

    """
    msg = Setpoint()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.step_s = float(step_s)
    msg.control_names = [str(name) for name in controls]
    msg.control_values = [float(v) for v in controls.values()]
    temperatures_c = temperatures_c or {}
    msg.temperature_names = [str(name) for name in temperatures_c]
    msg.temperature_setpoints_c = [float(v) for v in temperatures_c.values()]
    msg.plan_controls = flatten(plan_controls)[1] if plan_controls else []
    msg.plan_temperatures_c = flatten(plan_temperatures_c)[1] if plan_temperatures_c else []
    msg.released = [bool(r) for r in released]
    return msg


def setpoint_controls(msg: Setpoint) -> dict[str, float]:
    """Return the controls of a setpoint by name."""
    return named(msg.control_names, msg.control_values)


def setpoint_plan(msg: Setpoint) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """
    Return the plan of a (checked) setpoint.

    (controls by name, predicted zone temperatures [degC] by name), each over the plan's intervals.
    """
    m = len(msg.plan_controls) // max(len(msg.control_names), 1)
    controls = np.asarray(msg.plan_controls, dtype=float).reshape(len(msg.control_names), m)
    temperatures = np.asarray(msg.plan_temperatures_c, dtype=float).reshape(
        len(msg.temperature_names), m)
    return ({n: controls[i] for i, n in enumerate(msg.control_names)},
            {n: temperatures[i] for i, n in enumerate(msg.temperature_names)})


def status_msg(stamp_ns: int, result: MpcResult | None, *, fallback: bool = False,
               message: str = '', solve_time_s: float = 0.0) -> MpcStatus:
    """Return the status of an MPC step; ``result`` None when no solve produced the setpoint."""
    msg = MpcStatus()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.fallback = bool(fallback)
    if result is None:
        msg.success = False
        msg.message = message
        msg.solve_time_s = float(solve_time_s)
        msg.objective = float('nan')
        msg.max_defect = float('nan')
        return msg
    msg.success = bool(result.success)
    msg.message = message or str(result.message)
    msg.iterations = int(result.nit)
    msg.solve_time_s = float(result.solve_time_s)
    msg.objective = float(result.fun)
    msg.max_defect = float(result.max_defect)
    return msg


def decision_setpoint_msg(stamp_ns: int, decision: Decision, step_s: float,
                          interface: ControlInterface, safe_temperature_c: float,
                          zone: str = '', schedule: Schedule | None = None,
                          control_names: Sequence[str] | None = None) -> Setpoint:
    """
    Build the setpoint of a supervisor decision.

    Every control, the predicted temperature of every zone and the plan.

    Parameters
    ----------
    stamp_ns : int
        Start of the step [ns].
    decision : Decision
        From :class:`mshoot_core.safety.SetpointSupervisor` (controls in the order of
        ``interface.control_names``, states in the model's order).
    step_s : float
        Control step [s].
    interface : ControlInterface
        The controller's controls and zone temperatures
        (:attr:`mshoot_core.controller.Controller.interface`).
    safe_temperature_c : float
        Temperature setpoint of every zone sent with a safe setpoint (which
        predicts nothing) [degC].
    zone : str
        ``header.frame_id``.
    schedule : Schedule, optional
        What is sent within the step (:class:`~mshoot_core.actuation.Actuator`): with more than
        one piece, the setpoint's schedule within the step and ``control_values`` its first
        piece's; one piece: its values held over the step.
    control_names : sequence of str, optional
        The controls' names sent (default ``interface.control_names``; e.g. the plant's:
        :attr:`mshoot_core.controller.Controller.plant_control_names`).

    """
    names, zones = interface.control_names, interface.temperature_names
    names = tuple(control_names) if control_names is not None else names
    controls = np.asarray(decision.controls, dtype=float).reshape(-1)
    if schedule is not None:
        controls = schedule.values[0]
    if decision.predicted_state is not None:
        temperatures = interface.temperatures_c(decision.predicted_state)
    else:
        temperatures = np.full(len(zones), float(safe_temperature_c))
    plan_u = np.asarray(decision.plan_controls, dtype=float).reshape(-1, len(names))
    plan_x = np.asarray(decision.plan_states, dtype=float)
    plan_t = (interface.temperatures_c(plan_x) if plan_x.size
              else np.empty((0, len(zones))))
    m = plan_u.shape[0]
    msg = setpoint_msg(
        stamp_ns, step_s, dict(zip(names, controls)), dict(zip(zones, temperatures)),
        {n: plan_u[:, i] for i, n in enumerate(names)} if m else None,
        {n: plan_t[:, j] for j, n in enumerate(zones)} if m and plan_t.shape[0] == m
        else None, zone, decision.released)
    if schedule is not None and not schedule.held:
        msg.schedule_offsets_s = [float(o) for o in schedule.offsets_s]
        msg.schedule_values = [float(v) for v in schedule.values.T.reshape(-1)]
    return msg


def decision_status_msg(stamp_ns: int, decision: Decision, result: MpcResult | None, *,
                        solve_time_s: float, rejected_states: int = 0,
                        rejected_forecasts: int = 0,
                        consecutive_fallbacks: int = 0,
                        state: Mapping[str, float] | None = None,
                        state_std: Sequence[float] | None = None) -> MpcStatus:
    """
    Return the status of a supervisor decision; never a non-finite number.

    ``result`` is the step's solve result if there is one (its numbers are
    reported even when it was not used); without one, ``objective`` and
    ``max_defect`` are -1. ``state`` is the state the step was planned from by
    name [K], ``state_std`` the standard deviation of an estimated one [K].
    """
    msg = status_msg(stamp_ns, result, fallback=decision.fallback,
                     message=decision.reason, solve_time_s=solve_time_s)
    msg.solve_time_s = _finite(solve_time_s, 0.0)
    msg.objective = _finite(msg.objective, -1.0)
    msg.max_defect = _finite(msg.max_defect, -1.0)
    msg.source = decision.source
    msg.fallback_reason = decision.code
    msg.rejected_states = _int32(rejected_states)
    msg.rejected_forecasts = _int32(rejected_forecasts)
    msg.consecutive_fallbacks = _int32(consecutive_fallbacks)
    if state is not None and all(np.isfinite(v) for v in state.values()):
        msg.state_names = [str(name) for name in state]
        msg.state_values = [float(v) for v in state.values()]
        if state_std is not None and len(state_std) == len(state):
            msg.state_std = [_finite(v, -1.0) for v in state_std]
    return msg


def _finite(value: float, default: float) -> float:
    value = float(value)
    return value if np.isfinite(value) else default


def _int32(value: int) -> int:
    return int(min(max(int(value), 0), 2 ** 31 - 1))


# -- records of a run ---------------------------------------------------------------------
def mpc_records_frame(setpoints: Iterable[Setpoint], statuses: Iterable[MpcStatus],
                      epoch_ns: int = 0) -> pd.DataFrame:
    """
    Per-step MPC records from setpoint and status messages (the first of each stamp).

    Returns
    -------
    DataFrame
        Index ``time_s`` (stamp minus ``epoch_ns`` [s]); columns
        ``<control>_setpoint`` for every control (``q_setpoint`` [W]),
        ``<zone>_predicted_c`` for every zone temperature (``T_predicted_c``
        [degC]), ``success``, ``fallback``, ``iterations``, ``solve_time_s``,
        ``objective``, ``max_defect``, ``message``, ``source``,
        ``fallback_reason``; where a status carries an estimated state (its
        ``state_std``), ``<state>_estimate`` (the state the step was planned
        from [K]) and ``<state>_std`` (its standard deviation [K], NaN where
        the status reports -1), as in the core's per-step records
        (:func:`mshoot_core.closed_loop.step_row`).

    """
    rows: dict[int, dict] = {}
    for msg in setpoints:
        row = rows.setdefault(stamp_to_ns(msg.header.stamp), {})
        if 'setpoint' not in row:
            row['setpoint'] = True
            row.update({f'{name}_setpoint': value
                        for name, value in setpoint_controls(msg).items()})
            row.update({f'{name}_predicted_c': value for name, value in
                        named(msg.temperature_names, msg.temperature_setpoints_c).items()})
    for msg in statuses:
        row = rows.setdefault(stamp_to_ns(msg.header.stamp), {})
        if 'success' not in row:
            row.update(success=bool(msg.success), fallback=bool(msg.fallback),
                       iterations=int(msg.iterations), solve_time_s=msg.solve_time_s,
                       objective=msg.objective, max_defect=msg.max_defect,
                       message=msg.message, source=msg.source,
                       fallback_reason=msg.fallback_reason)
            if len(msg.state_std) and len(msg.state_std) == len(msg.state_names) \
                    == len(msg.state_values):
                for name, value, std in zip(msg.state_names, msg.state_values, msg.state_std):
                    row[f'{name}_estimate'] = float(value)
                    row[f'{name}_std'] = float(std) if std >= 0 else np.nan
    frame = pd.DataFrame.from_dict(rows, orient='index').sort_index()
    frame = frame.drop(columns=['setpoint'], errors='ignore')
    frame.index = pd.Index((frame.index.to_numpy(dtype=np.int64) - int(epoch_ns)) / NS_PER_S,
                           name='time_s')
    return frame
