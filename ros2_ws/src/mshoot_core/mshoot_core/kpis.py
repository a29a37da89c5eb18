"""Key performance indicators of a closed-loop run: energy, discomfort, computation time."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

JOULES_PER_KWH = 3.6e6


def band_distances(temperature: np.ndarray, lower: np.ndarray,
                   upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return how far each temperature is below and above its band [K] (0 inside).

    The one definition of a band violation: the discomfort of a closed-loop run
    (:func:`discomfort_kh`) and BOPTEST's ``tdis``
    (:func:`mshoot_core.boptest.kpi_calculator.zone_discomfort`).

    Parameters
    ----------
    temperature : ndarray
        Temperatures [degC or K, as the band].
    lower, upper : ndarray
        The band's edges (broadcast against ``temperature``).

    """
    t = np.asarray(temperature, dtype=float)
    return (np.maximum(np.asarray(lower, dtype=float) - t, 0.0),
            np.maximum(t - np.asarray(upper, dtype=float), 0.0))


def comfort_violation(temperature_c: np.ndarray, comfort_min: np.ndarray,
                      comfort_max: np.ndarray) -> np.ndarray:
    """Distance [K] of each temperature outside its band [comfort_min, comfort_max] (0 inside)."""
    below, above = band_distances(temperature_c, comfort_min, comfort_max)
    return below + above


def hours_integral(times_s: np.ndarray, values: np.ndarray) -> float:
    """
    Return the trapezoidal integral of samples over time in hours (a violation [K] -> K h).

    The one integral of every discomfort KPI (:func:`discomfort_kh`, BOPTEST's ``tdis`` and
    ``idis``).

    Parameters
    ----------
    times_s : ndarray
        Sample times [s], increasing.
    values : ndarray
        The samples (e.g. [K] or [ppm]).

    """
    t = np.asarray(times_s, dtype=float)
    v = np.asarray(values, dtype=float)
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)) / 3600.0)


def energy_kwh(heat_rate_w: np.ndarray, step_s: float) -> dict[str, float]:
    """
    Energy of a piecewise-constant heat rate: total sum |q| dt, heating and cooling apart.

    Parameters
    ----------
    heat_rate_w : ndarray
        Heat rate of each step [W], heating > 0, cooling < 0.
    step_s : float
        Step length [s].

    Returns
    -------
    dict with 'energy_kwh', 'heating_kwh', 'cooling_kwh' [kWh] (all >= 0).

    """
    q = np.asarray(heat_rate_w, dtype=float)
    return {'energy_kwh': float(np.sum(np.abs(q)) * step_s / JOULES_PER_KWH),
            'heating_kwh': float(np.sum(np.clip(q, 0, None)) * step_s / JOULES_PER_KWH),
            'cooling_kwh': float(-np.sum(np.clip(q, None, 0)) * step_s / JOULES_PER_KWH)}


def discomfort_kh(fine: pd.DataFrame, temperature_column: str = 'y_T',
                  sample_every_s: float = 3600.0) -> dict[str, float]:
    """
    Thermal discomfort [K h] of a trajectory on a fine grid.

    Parameters
    ----------
    fine : DataFrame
        Indexed by time [s] (fine grid, e.g. 60 s) with the zone temperature
        [degC] and the columns ``comfort_min``, ``comfort_max`` [degC].
    temperature_column : str
        Column of the zone temperature.
    sample_every_s : float
        Spacing of the samples of the original's hourly-sum KPI [s].

    Returns
    -------
    dict with 'discomfort_kh' (trapezoidal integral of the violation over the
    fine grid, BOPTEST-style) and 'discomfort_kh_hourly' (sum over the samples
    at multiples of ``sample_every_s``, each weighted by that spacing, as the
    original reported it).

    """
    t = np.asarray(fine.index, dtype=float)
    dist = comfort_violation(fine[temperature_column].to_numpy(), fine['comfort_min'].to_numpy(),
                             fine['comfort_max'].to_numpy())
    integral = hours_integral(t, dist)
    on_grid = np.isclose(np.mod(t - t[0], sample_every_s), 0.0, atol=1e-6)
    hourly = float(np.sum(dist[on_grid]) * sample_every_s / 3600.0)
    return {'discomfort_kh': integral, 'discomfort_kh_hourly': hourly}


def closed_loop_kpis(steps: pd.DataFrame, fine: pd.DataFrame, step_s: float,
                     wall_s: float, control: str | Sequence[str] = 'q',
                     temperature_column: str | Sequence[str] = 'y_T') -> dict[str, float]:
    """
    All KPIs of a closed-loop run (the keys of ``kpis.json``).

    Parameters
    ----------
    steps : DataFrame
        Per-step records with the applied control and ``solve_time_s``, ``success`` (and
        ``released``, the controls whose overwrite was released: counted as
        ``released_steps``).
    fine : DataFrame
        The fine-grid trajectory (see :func:`discomfort_kh`).
    step_s : float
        Control step [s].
    wall_s : float
        Wall time of the whole run [s].
    control : str or sequence of str
        Column(s) of the applied heat rates [W]; with several (one per zone)
        the energies are summed.
    temperature_column : str or sequence of str
        Column(s) of the zone temperatures [degC] in ``fine``; with several the
        discomfort of every zone is summed.

    """
    controls = [control] if isinstance(control, str) else list(control)
    columns = ([temperature_column] if isinstance(temperature_column, str)
               else list(temperature_column))
    kpis: dict = {}
    for name in controls:
        for key, value in energy_kwh(steps[name].to_numpy(), step_s).items():
            kpis[key] = kpis.get(key, 0.0) + value
    for column in columns:
        for key, value in discomfort_kh(fine, column, step_s).items():
            kpis[key] = kpis.get(key, 0.0) + value
    solve = steps['solve_time_s'].to_numpy(dtype=float)
    kpis.update(steps=int(len(steps)), wall_s=float(wall_s),
                solve_s_total=float(solve.sum()), solve_s_median=float(np.median(solve)),
                solve_s_max=float(solve.max()),
                solve_per_control_step=float(solve.sum() / (len(steps) * step_s)),
                solver_failures=int((~steps['success'].astype(bool)).sum()))
    if 'released' in steps:  # steps on which the plant's overwrites were released
        kpis['released_steps'] = int((steps['released'].fillna('').astype(str) != '').sum())
    return kpis


#: Exit code of a command whose run ended but was not controlled: more of its steps fell back
#: than ``max_fallback_share`` (:func:`fallback_problem`).
FALLBACK_EXIT = 3


def fallback_problem(fallbacks: int, steps: int, max_share: float) -> str | None:
    """
    Say why a run controlled too little: more of its steps were fallbacks than ``max_share``.

    The decision behind :data:`FALLBACK_EXIT` of ``mshoot case`` and the demo's bring-up.

    Parameters
    ----------
    fallbacks, steps : int
        Steps whose setpoint was a fallback, and all steps of the run.
    max_share : float
        Largest share of fallback steps of a run that controlled [-] (the
        ``max_fallback_share`` setting); 1 accepts every run.

    Returns
    -------
    str or None
        One sentence (the count, the share and the limit), or None for a run within it (or
        without steps).

    """
    if steps <= 0:
        return None
    share = fallbacks / steps
    if share <= max_share:
        return None
    every = 'every step' if fallbacks == steps else f'{fallbacks} of {steps} steps'
    return (f'{every} fell back ({share:.0%}, more than max_fallback_share {max_share:.0%}): '
            'the MPC did not control this run')
