"""
Messages <-> numpy arrays and pandas DataFrames, and ROS time <-> seconds.

The nodes stay thin by converting at their edges only: everything inside is
:mod:`mshoot_core` data (states in K as arrays, forecasts and scenarios as
DataFrames with the columns of :mod:`mshoot_core.scenario`).

Times: ROS stamps are handled as integer nanoseconds (exact comparisons of
step stamps); scenario times are float seconds since the scenario start.
"""
from __future__ import annotations

from typing import Iterable, Sequence, TYPE_CHECKING

from builtin_interfaces.msg import Time
from mshoot_core.models.r1c1 import KELVIN
from mshoot_msgs.msg import Disturbances, Forecast, MpcStatus, Setpoint, ZoneState
import numpy as np
import pandas as pd
from rosgraph_msgs.msg import Clock

if TYPE_CHECKING:  # the emulator process need not import scipy (through mshoot_core.mpc)
    from mshoot_core.mpc import MpcResult
    from mshoot_core.safety import Decision

NS_PER_S = 1_000_000_000
#: Forecast columns in the message, as scenario columns.
FORECAST_FIELDS = {'Tout': 'outdoor_temperature_c', 'solrad': 'solar_radiation_w_m2',
                   'occ': 'occupancy', 'comfort_min': 'comfort_min_c',
                   'comfort_max': 'comfort_max_c'}


# -- time ---------------------------------------------------------------------------------
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


# -- zone state ---------------------------------------------------------------------------
def zone_state_msg(stamp_ns: int, temperature_k: float, heat_rate_w: float,
                   zone: str = '') -> ZoneState:
    """
    Return the zone state at ``stamp_ns``: temperature from the model state [K] to [degC].

    Parameters
    ----------
    stamp_ns : int
        Time of the measurement [ns].
    temperature_k : float
        Zone temperature [K] (the R1C1 state).
    heat_rate_w : float
        Heat rate applied over the last step [W].
    zone : str
        Zone name (``header.frame_id``).

    """
    msg = ZoneState()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.temperature_c = float(temperature_k) - KELVIN
    msg.heat_rate_w = float(heat_rate_w)
    return msg


def zone_state_to_x(msg: ZoneState) -> np.ndarray:
    """Return the model state of a zone state message: ``[T]`` [K], shape (1,)."""
    return np.array([msg.temperature_c + KELVIN])


# -- disturbances -------------------------------------------------------------------------
def disturbances_msg(stamp_ns: int, row: pd.Series, zone: str = '') -> Disturbances:
    """Measured disturbances of a scenario row (columns Tout, solrad, occ)."""
    msg = Disturbances()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.outdoor_temperature_c = float(row['Tout'])
    msg.solar_radiation_w_m2 = float(row['solrad'])
    msg.occupancy = float(row['occ'])
    return msg


def disturbances_to_series(msg: Disturbances) -> pd.Series:
    """Return a Disturbances message as a Series with the scenario columns Tout, solrad, occ."""
    return pd.Series({'Tout': msg.outdoor_temperature_c, 'solrad': msg.solar_radiation_w_m2,
                      'occ': msg.occupancy})


# -- forecast -----------------------------------------------------------------------------
def forecast_msg(stamp_ns: int, step_s: float, window: pd.DataFrame,
                 zone: str = '') -> Forecast:
    """
    Return a forecast message from a window of scenario rows.

    Parameters
    ----------
    stamp_ns : int
        Start time of the first sample [ns].
    step_s : float
        Sample spacing [s].
    window : DataFrame, shape (n, >= 5)
        Rows of the columns Tout, solrad, occ, comfort_min, comfort_max (e.g.
        :func:`mshoot_core.closed_loop.forecast_window`: N+1 rows).
    zone : str
        Zone name (``header.frame_id``).

    """
    msg = Forecast()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.step_s = float(step_s)
    for column, field in FORECAST_FIELDS.items():
        setattr(msg, field, window[column].to_numpy(dtype=float).tolist())
    return msg


def forecast_length(msg: Forecast) -> int:
    """Return the number of samples of a forecast; ValueError if its arrays differ in length."""
    lengths = {field: len(getattr(msg, field)) for field in FORECAST_FIELDS.values()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f'forecast arrays differ in length: {lengths}')
    return next(iter(lengths.values()))


def forecast_series(msg: Forecast) -> dict[str, Sequence[float]]:
    """
    Return the arrays of a forecast by scenario column, unchecked.

    The columns are Tout, solrad, occ, comfort_min and comfort_max; unchecked: what
    :func:`mshoot_core.safety.check_forecast` validates.
    """
    return {column: getattr(msg, field) for column, field in FORECAST_FIELDS.items()}


def forecast_to_frame(msg: Forecast, dpos: float = 0.0) -> pd.DataFrame:
    """
    Return a forecast message as a DataFrame with the scenario columns.

    Parameters
    ----------
    msg : Forecast
        The forecast (all arrays of one length n).
    dpos : float
        Ventilation damper position [%] assumed over the horizon (the message
        carries no ventilation forecast; 0: ventilation off).

    Returns
    -------
    DataFrame, shape (n, 6)
        Columns solrad, Tout, occ, dpos, comfort_min, comfort_max; index the
        sample start times [s] (ROS time).

    """
    n = forecast_length(msg)
    t0 = stamp_to_ns(msg.header.stamp) / NS_PER_S
    frame = pd.DataFrame({column: np.asarray(getattr(msg, field), dtype=float)
                          for column, field in FORECAST_FIELDS.items()},
                         index=pd.Index(t0 + np.arange(n) * msg.step_s, name='time_s'))
    frame['dpos'] = float(dpos)
    return frame[['solrad', 'Tout', 'occ', 'dpos', 'comfort_min', 'comfort_max']]


# -- setpoint and status ------------------------------------------------------------------
def setpoint_msg(stamp_ns: int, result: MpcResult, step_s: float, zone: str = '') -> Setpoint:
    """
    Return the setpoint of a solved MPC step.

    The first control, its predicted end temperature and the plan (first control ``q``, first state
    ``T`` in K).
    """
    msg = Setpoint()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    controls = np.asarray(result.controls, dtype=float)[:, 0]
    temperatures_c = np.asarray(result.states, dtype=float)[1:, 0] - KELVIN
    msg.heat_rate_w = float(controls[0])
    msg.temperature_setpoint_c = float(temperatures_c[0])
    msg.step_s = float(step_s)
    msg.plan_heat_rate_w = controls.tolist()
    msg.plan_temperature_c = temperatures_c.tolist()
    return msg


def fallback_setpoint_msg(stamp_ns: int, heat_rate_w: float, temperature_c: float,
                          step_s: float, plan_heat_rate_w: Sequence[float] = (),
                          plan_temperature_c: Sequence[float] = (),
                          zone: str = '') -> Setpoint:
    """Return a setpoint that is not a fresh optimum (e.g. the previous plan's next interval)."""
    msg = Setpoint()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = zone
    msg.heat_rate_w = float(heat_rate_w)
    msg.temperature_setpoint_c = float(temperature_c)
    msg.step_s = float(step_s)
    msg.plan_heat_rate_w = [float(v) for v in plan_heat_rate_w]
    msg.plan_temperature_c = [float(v) for v in plan_temperature_c]
    return msg


def setpoint_to_controls(msg: Setpoint) -> np.ndarray:
    """Return the controls of a setpoint: ``[q]`` [W], shape (1,)."""
    return np.array([msg.heat_rate_w])


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
                          safe_temperature_c: float, zone: str = '') -> Setpoint:
    """
    Return the setpoint of a supervisor decision (first control ``q``, first state ``T`` [K]).

    Parameters
    ----------
    stamp_ns : int
        Start of the step [ns].
    decision : Decision
        From :class:`mshoot_core.safety.SetpointSupervisor`.
    step_s : float
        Control step [s].
    safe_temperature_c : float
        Temperature setpoint sent with a safe setpoint (which predicts nothing) [degC].
    zone : str
        ``header.frame_id``.

    """
    temperature_c = (float(decision.predicted_state[0]) - KELVIN
                     if decision.predicted_state is not None else float(safe_temperature_c))
    return fallback_setpoint_msg(stamp_ns, float(decision.controls[0]), temperature_c, step_s,
                                 np.asarray(decision.plan_controls, dtype=float)[:, 0],
                                 np.asarray(decision.plan_states, dtype=float)[:, 0] - KELVIN
                                 if len(decision.plan_states) else (), zone)


def decision_status_msg(stamp_ns: int, decision: Decision, result: MpcResult | None, *,
                        solve_time_s: float, rejected_states: int = 0,
                        rejected_forecasts: int = 0,
                        consecutive_fallbacks: int = 0) -> MpcStatus:
    """
    Return the status of a supervisor decision; never a non-finite number.

    ``result`` is the step's solve result if there is one (its numbers are
    reported even when it was not used); without one, ``objective`` and
    ``max_defect`` are -1.
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
        ``q_setpoint`` [W], ``T_predicted_c`` [degC], ``success``, ``fallback``,
        ``iterations``, ``solve_time_s``, ``objective``, ``max_defect``,
        ``message``, ``source``, ``fallback_reason``.

    """
    rows: dict[int, dict] = {}
    for msg in setpoints:
        stamp = stamp_to_ns(msg.header.stamp)
        rows.setdefault(stamp, {}).setdefault('q_setpoint', msg.heat_rate_w)
        rows[stamp].setdefault('T_predicted_c', msg.temperature_setpoint_c)
    for msg in statuses:
        row = rows.setdefault(stamp_to_ns(msg.header.stamp), {})
        if 'success' not in row:
            row.update(success=bool(msg.success), fallback=bool(msg.fallback),
                       iterations=int(msg.iterations), solve_time_s=msg.solve_time_s,
                       objective=msg.objective, max_defect=msg.max_defect,
                       message=msg.message, source=msg.source,
                       fallback_reason=msg.fallback_reason)
    frame = pd.DataFrame.from_dict(rows, orient='index').sort_index()
    frame.index = pd.Index((frame.index.to_numpy(dtype=np.int64) - int(epoch_ns)) / NS_PER_S,
                           name='time_s')
    return frame
