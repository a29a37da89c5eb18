r"""
A plant under its own local loop next to an MPC run of it: discomfort and heat delivered.

    python -m mshoot_studies.local_loop --plant PLANT.yaml --scenario DATA.csv --hours 72 \
        --mpc out/setpoint_zone_mpc --meter Qheat_total

runs the plant of a card with its overwrite switches released (a card's ``activate``
inputs left at 0: the building's own controller, e.g. a local loop on its fixed setpoint) over
the scenario's first ``--hours`` control steps, and prints its discomfort [K h] (the
comfort band of the scenario, 60 s samples) and the heat delivered [kWh] (the increase of the
plant's energy meter, the output ``--meter`` [J]) next to those of an MPC run's
``trajectories.csv`` (``--mpc``: the output folder of ``bringup`` or ``mshoot case``).
Writes ``local_loop.csv`` (the local loop's trajectory), ``comparison.json`` and, with
``--mpc``, ``comparison.png`` (both runs' zone temperature and heat) to ``--out``.
The KPIs of the runs count the controls as heat rates; here heat comes from the plant's
meter, whatever the control's quantity (a setpoint).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import pathlib
from typing import Any, Sequence

from mshoot_core.emulation import Emulator, initial_state
from mshoot_core.kpis import discomfort_kh
from mshoot_core.scenario import reference_scenario
import numpy as np
import pandas as pd

from mshoot_studies.cli import verb_parser

logger = logging.getLogger(__name__)

#: Initial zone temperature of the runs [degC] (the setpoint zone's overlay).
INITIAL_C = 21.0


def released(card: Any) -> Any:
    """Return the card without its overwrite switches: every ``activate`` input stays 0."""
    controls = {name: dataclasses.replace(v, activate=None) for name, v in card.controls.items()}
    return dataclasses.replace(card, controls=controls)


def run_local_loop(card: Any, scenario: pd.DataFrame, hours: int,
                   initial_c: float = INITIAL_C) -> pd.DataFrame:
    """
    Run a plant card's model under its own control; return its 60 s trajectory.

    Columns as a run's ``trajectories.csv``: ``x_<state>``, ``y_<output>``, the band.
    """
    from mshoot_core.identification import control_limits
    from mshoot_core.models import card as cards
    own = released(card)
    model = cards.build_model(own, role='emulator')
    try:
        limits = control_limits(own, (-np.inf, np.inf))
        held = [lo if np.isfinite(lo) else 0.0 for lo, _ in limits]  # ignored: released
        emulator = Emulator(model, scenario, initial_state(model.state_names, initial_c),
                            control_names=own.control_names, control_bounds=limits)
        fines = [emulator.advance(held).fine for _ in range(hours)]
    finally:
        if hasattr(model, 'close'):
            model.close()
    return pd.concat([f.iloc[:-1] for f in fines[:-1]] + [fines[-1]])


def heat_kpis(trajectory: pd.DataFrame, meter: str, zone: str = 'y_T') -> dict[str, float]:
    """
    Return discomfort [K h] and heat delivered [kWh] of a 60 s trajectory.

    Raises
    ------
    ValueError
        Without the meter or zone column.

    """
    missing = [c for c in (meter, zone) if c not in trajectory.columns]
    if missing:
        raise ValueError(f'the trajectory has no columns {missing}; it has '
                         f'{list(trajectory.columns)}')
    heat_j = float(trajectory[meter].iloc[-1] - trajectory[meter].iloc[0])
    return {**discomfort_kh(trajectory, zone), 'heat_kwh': heat_j / 3.6e6}


def figure(path: pathlib.Path, local: pd.DataFrame, mpc: pd.DataFrame,
           rows: dict[str, dict[str, float]]) -> None:
    """Draw the zone temperature and the heat delivered of both runs, with the band."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    hours = local.index.to_numpy(dtype=float) / 3600.0
    top.fill_between(hours, local['comfort_min'], local['comfort_max'], color='0.9',
                     label='comfort band')
    for frame, name, style in ((local, 'local loop', 'C3-'), (mpc, 'mpc', 'C0-')):
        label = (f"{name}: {rows[name]['discomfort_kh']:.2f} K h, "
                 f"{rows[name]['heat_kwh']:.1f} kWh")
        t = frame.index.to_numpy(dtype=float) / 3600.0
        top.plot(t, frame['y_T'], style, lw=1.0, label=label)
        bottom.plot(t, frame['y_Qheat'] / 1000.0, style, lw=0.8, label=name)
    top.set_ylabel('zone temperature [degC]')
    top.legend(loc='upper right', fontsize=8)
    bottom.set_ylabel('heat delivered [kW]')
    bottom.set_xlabel('time [h]')
    bottom.legend(loc='upper right', fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line (see the module docstring).

    Fills ``parser``, or a new parser when None. Its errors are one line
    (``<prog>: error: ...``) and exit 2 (:func:`~mshoot_studies.cli.verb_parser`).
    """
    parser = verb_parser(parser, 'mshoot_studies.local_loop', __doc__)
    parser.add_argument('--plant', type=pathlib.Path, required=True, metavar='CARD',
                        help='model card of the plant (with overwrite switches)')
    parser.add_argument('--scenario', required=True,
                        help="the scenario: 'synthetic', or a data CSV with a band")
    parser.add_argument('--hours', type=int, default=72,
                        help='hours simulated, one control step each (default 72)')
    parser.add_argument('--mpc', type=pathlib.Path, default=None,
                        help='output folder of an MPC run (its trajectories.csv) to compare '
                             '(default: none, the local loop alone)')
    parser.add_argument('--meter', default='Qheat_total',
                        help='output of the plant metering the heat delivered [J] (default '
                             'Qheat_total)')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/local_loop'),
                        help='output folder (default out/local_loop)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the comparison; 0, or 2 on bad input."""
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    args = build_parser().parse_args(argv)
    from mshoot_core.models import card as cards
    try:
        card = cards.load_card(args.plant)
        scenario = reference_scenario(args.scenario, None, args.hours)
        trajectory = run_local_loop(card, scenario, args.hours)
        rows = {'local loop': heat_kpis(trajectory, f'y_{args.meter}')}
        if args.mpc is not None:
            mpc = pd.read_csv(args.mpc / 'trajectories.csv', index_col='time_s')
            rows['mpc'] = heat_kpis(mpc, f'y_{args.meter}')
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', exc)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    trajectory.to_csv(args.out / 'local_loop.csv', index_label='time_s')
    if args.mpc is not None:
        figure(args.out / 'comparison.png', trajectory, mpc, rows)
    (args.out / 'comparison.json').write_text(json.dumps(rows, indent=2) + '\n')
    for name, row in rows.items():
        logger.info('%-10s discomfort %6.2f K h, heat delivered %7.2f kWh', name,
                    row['discomfort_kh'], row['heat_kwh'])
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
