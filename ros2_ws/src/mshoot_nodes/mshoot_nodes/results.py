"""
The outputs of a ROS run: per-step records, KPIs, plot, as the case command writes them.

A ROS run is recorded in two places: the emulator knows what it applied and
the fine trajectory (:meth:`EmulatorNode.applied_frame`, ``fine_frame``, or
``applied.csv`` and ``trajectories.csv`` from a separate process), the MPC's
setpoints and statuses are on the topics (the node's history, or the bag).
:func:`steps_frame` joins them by step and :func:`run_outputs` computes
``kpis.json`` with :func:`mshoot_core.kpis.closed_loop_kpis` (the keys of the
case command) and writes the files with :func:`mshoot_core.outputs.write_outputs`.
"""
from __future__ import annotations

import pathlib
from typing import Mapping, Sequence

from mshoot_core.closed_loop import ClosedLoopResult
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.outputs import write_outputs
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd

#: Columns of the per-step MPC records that go into steps.csv (besides every
#: ``<control>_setpoint``, ``<zone>_predicted_c`` and, with an estimated state,
#: ``<state>_estimate`` and ``<state>_std``).
MPC_COLUMNS = ('solve_time_s', 'success', 'fallback', 'iterations', 'objective',
               'max_defect', 'message')
#: The zone temperatures of a single-zone (R1C1) run: state -> column of the fine trajectory.
SINGLE_ZONE = {'T': 'y_T'}


def steps_frame(applied: pd.DataFrame, mpc_records: pd.DataFrame) -> pd.DataFrame:
    """
    One row per control step: what the emulator applied and what the MPC reported.

    Parameters
    ----------
    applied : DataFrame
        Index ``time_s``; columns the applied controls (``q`` [W]), and
        ``<state>_start``, ``<state>_end`` (``T_start``, ``T_end`` [K]) (the
        emulator's :meth:`applied_frame`).
    mpc_records : DataFrame
        Index ``time_s``; see :func:`mshoot_nodes.conversions.mpc_records_frame`.

    Returns
    -------
    DataFrame
        ``applied`` joined with the MPC columns (with an estimated state its
        ``<state>_estimate`` and ``<state>_std`` [K], as the core's steps.csv),
        plus ``<zone>_predicted`` [K]
        for every ``<zone>_predicted_c`` (``T_predicted``); steps without an
        MPC record (should not happen in lockstep) get ``success`` False and
        ``solve_time_s`` 0.

    """
    named = [c for c in mpc_records.columns
             if c.endswith(('_setpoint', '_predicted_c', '_estimate', '_std'))]
    steps = applied.drop(columns=['stamp_ns'], errors='ignore').join(
        mpc_records.reindex(columns=[*MPC_COLUMNS[:-1], *named, MPC_COLUMNS[-1]]), how='left')
    steps['mpc_record'] = steps['success'].notna()
    steps['success'] = steps['success'].astype('boolean').fillna(False).astype(bool)
    steps['fallback'] = steps['fallback'].astype('boolean').fillna(False).astype(bool)
    steps['solve_time_s'] = steps['solve_time_s'].astype(float).fillna(0.0)
    for column in named:
        if column.endswith('_predicted_c'):
            steps[column[:-2]] = steps[column].astype(float) + KELVIN
    return steps


def zone_temperature_columns(fine: pd.DataFrame,
                             zones: Mapping[str, str] | None = None) -> list[str]:
    """
    Return the columns of ``fine`` holding the zone temperatures [degC].

    Parameters
    ----------
    fine : DataFrame
        The fine trajectory; gains a column ``<zone>_c`` [degC] for every zone
        whose temperature is a state column ``x_<zone>`` [K].
    zones : mapping, optional
        Zone temperature state -> its column (an output ``y_...`` [degC] or
        the state ``x_...`` [K]), as the emulator reports it
        (:meth:`EmulatorNode.zone_temperature_columns`, ``run.json``); default
        the single R1C1 zone (``y_T``).

    """
    columns = []
    for zone, column in (zones or SINGLE_ZONE).items():
        if column.startswith('x_'):
            fine[f'{zone}_c'] = fine[column].astype(float) - KELVIN
            column = f'{zone}_c'
        columns.append(column)
    return columns


def run_kpis(steps: pd.DataFrame, fine: pd.DataFrame, step_s: float, wall_s: float,
             controls: Sequence[str] = ('q',), temperature_columns: Sequence[str] = ('y_T',),
             **extra: object) -> dict:
    """
    Return the KPIs of a ROS run.

    :func:`closed_loop_kpis` (summed over the controls and zones) plus ``extra`` and ``fallbacks``.
    """
    kpis = closed_loop_kpis(steps, fine, step_s, wall_s, list(controls),
                            list(temperature_columns))
    kpis['fallbacks'] = int(np.sum(steps['fallback'].to_numpy(dtype=bool)))
    kpis['mpc_records_missing'] = int(np.sum(~steps['mpc_record'].to_numpy(dtype=bool)))
    kpis.update(extra)
    return kpis


def run_outputs(out: pathlib.Path, applied: pd.DataFrame, fine: pd.DataFrame,
                mpc_records: pd.DataFrame, step_s: float, wall_s: float, title: str,
                controls: Sequence[str] = ('q',), zones: Mapping[str, str] | None = None,
                **extra: object) -> dict:
    """
    Write kpis.json, steps.csv, trajectories.csv and plot.png to ``out``; return the KPIs.

    ``controls`` are the applied heat rates (columns of ``applied``), ``zones``
    the zone temperatures (see :func:`zone_temperature_columns`); the plot
    shows the first zone and its control.
    """
    steps = steps_frame(applied, mpc_records)
    columns = zone_temperature_columns(fine, zones)
    kpis = run_kpis(steps, fine, step_s, wall_s, controls, columns, **extra)
    result = ClosedLoopResult(steps, fine, [], step_wall_s=[], wall_s=wall_s)
    write_outputs(pathlib.Path(out), result, kpis, title,
                  control=controls[0], temperature_column=columns[0])
    return kpis


def kpi_summary(kpis: dict) -> str:
    """Return a few lines with the KPIs an operator looks at first."""
    missing = kpis.get('mpc_records_missing', 0)
    return (f"energy {kpis['energy_kwh']:.2f} kWh (heating {kpis['heating_kwh']:.2f}, cooling "
            f"{kpis['cooling_kwh']:.2f})\n"
            f"discomfort {kpis['discomfort_kh']:.2f} Kh (hourly samples "
            f"{kpis['discomfort_kh_hourly']:.2f} Kh)\n"
            f"{kpis['steps']} steps, wall {kpis['wall_s']:.2f} s, solve total "
            f"{kpis['solve_s_total']:.2f} s (median {kpis['solve_s_median']:.4f} s, max "
            f"{kpis['solve_s_max']:.3f} s), solver failures {kpis['solver_failures']}, "
            f"fallbacks {kpis.get('fallbacks', 0)}"
            + (f'\nwarning: {missing} steps have no recorded MPC setpoint/status' if missing
               else ''))
