"""The separate-process bring-up: four processes over DDS on this host complete a 24 h run."""
import json
import pathlib
import subprocess
import sys

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.models.fmi import r1c1_fmi_model
from mshoot_core.models.r1c1 import KELVIN, R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import synthetic_scenario
import numpy as np
import pandas as pd
import pytest

from mshoot_nodes import contract
from mshoot_nodes.bags import read_bag
from mshoot_nodes.processes import executable, wait_for_recorder

HOURS = 24


@pytest.mark.ros
def test_separate_processes_complete_a_24_h_run(tmp_path):
    out = tmp_path / 'processes'
    command = executable('bringup_processes', 'processes')
    assert pathlib.Path(command[0]).name == 'bringup_processes', \
        'the console script is not installed (make setup)'
    done = subprocess.run(command + ['--hours', str(HOURS), '--out', str(out),
                                     '--timeout', '120'],
                          capture_output=True, text=True, timeout=180)
    logs = '\n'.join(f'--- {p.name}\n{p.read_text()[-2000:]}'
                     for p in sorted((out / 'logs').glob('*.log')))
    assert done.returncode == 0, f'{done.stdout}\n{done.stderr}\n{logs}'
    kpis = json.loads((out / 'kpis.json').read_text())
    assert kpis['steps'] == HOURS and kpis['solver_failures'] == 0
    assert kpis['transport'] == 'ros2 processes'
    steps = pd.read_csv(out / 'steps.csv', index_col='time_s')
    bad = steps[~steps['success'].astype(bool) | steps['fallback'].astype(bool)]
    assert bad.empty, f'steps without a successful solve:\n{bad.to_string()}\n{logs}'

    core = run_closed_loop(MPC(R1C1Model(), horizon_steps=10),
                           Emulator(r1c1_fmi_model(fmi_type='ModelExchange', tolerance=1e-10),
                                    synthetic_scenario(hours=HOURS + 1), [20.0 + KELVIN]),
                           steps=HOURS, log_every=0)
    # Lockstep across processes reproduces the core-only loop too.
    assert np.max(np.abs(steps['T_end'].to_numpy() - core.steps['T_end'].to_numpy())) < 1e-9

    counts = read_bag(out / 'bag').counts
    assert counts[contract.SETPOINT] >= HOURS and counts[contract.ZONE_STATE] >= HOURS + 1
    assert (out / 'plot.png').stat().st_size > 0


def test_bringup_waits_for_the_recorder_to_match_the_publishers(tmp_path):
    """The emulator starts only after the recorder's ``matched`` lines; else a clear reason."""
    log = tmp_path / 'recorder.log'
    recorder = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)'])
    try:
        log.write_text(contract.RECORDER_MATCHED.format(topic=contract.FORECAST)
                       + ' 1 publisher(s)\n')
        problem = wait_for_recorder(log, recorder, timeout_s=0.3)
        assert problem and contract.SETPOINT in problem and contract.STATUS in problem
        assert contract.FORECAST not in problem.split('within')[0]
        with log.open('a') as f:
            for topic in (contract.SETPOINT, contract.STATUS):
                f.write(contract.RECORDER_MATCHED.format(topic=topic) + ' 2 publisher(s)\n')
        assert wait_for_recorder(log, recorder, timeout_s=0.3) is None
    finally:
        recorder.kill()
        recorder.wait()
    log.write_text('')
    problem = wait_for_recorder(log, recorder, timeout_s=5.0)
    assert problem and 'exited' in problem
