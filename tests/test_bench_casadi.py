"""
The CasADi reference of bench/versus.py solves our problem (skipped without casadi).

casadi is a benchmark-only dependency (``make bench-setup``): these tests run where it is
installed and are skipped elsewhere.
"""
import pathlib
import sys

from mshoot_core.models import R1C1Model
from mshoot_core.models.multizone import MultiZoneModel
from mshoot_core.mpc import MPC
from mshoot_core.scenario import DISTURBANCE_COLUMNS, forecast_window, synthetic_scenario
from mshoot_core.units import KELVIN
import numpy as np
import pytest

ca = pytest.importorskip('casadi')
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / 'bench'))

from casadi_ref import CasadiMpc, rk4_interval, ZoneParameters  # noqa: E402


def random_intervals(rng: np.random.Generator, batch: int, zones: int) -> tuple:
    """
    Return random intervals for B rows and Z zones.

    Start temperatures [degC] (B, Z), heat rates [W] (B, Z), disturbances (B, 4), with the
    ventilation on in some rows (the max(Tout, Tve) branch).
    """
    start = rng.uniform(12.0, 30.0, (batch, zones))
    heat = rng.uniform(-2000.0, 2000.0, (batch, zones))
    disturbances = np.column_stack([rng.uniform(0.0, 700.0, batch),
                                    rng.uniform(-10.0, 30.0, batch),
                                    rng.uniform(0.0, 40.0, batch),
                                    np.where(rng.random(batch) < 0.5, 0.0,
                                             rng.uniform(0.0, 100.0, batch))])
    return start, heat, disturbances


def test_rk4_interval_matches_the_exact_r1c1():
    rng = np.random.default_rng(3)
    start, heat, disturbances = random_intervals(rng, 40, 1)
    interval = rk4_interval(ZoneParameters.from_r1c1(), 3600.0, 4)
    exact, _ = R1C1Model().simulate_intervals(start + KELVIN, np.column_stack([disturbances,
                                                                               heat]), 3600.0)
    rk4 = np.array([float(interval(start[b], heat[b], disturbances[b]))
                    for b in range(len(start))])
    assert np.max(np.abs(rk4 - (exact[:, 0] - KELVIN))) < 1e-5  # RK4 truncation ~1e-6 K
    assert np.max(np.abs(exact[:, 0] - KELVIN - start[:, 0])) > 0.5  # the intervals do move


def test_rk4_interval_matches_the_multizone_model():
    rng = np.random.default_rng(4)
    model = MultiZoneModel(7)
    start, heat, disturbances = random_intervals(rng, 10, 7)
    interval = rk4_interval(ZoneParameters.from_multizone(model), 3600.0, 4)
    exact, _ = model.simulate_intervals(start + KELVIN, np.column_stack([disturbances, heat]),
                                        3600.0)
    rk4 = np.vstack([np.asarray(interval(start[b], heat[b], disturbances[b])).reshape(-1)
                     for b in range(len(start))])
    assert np.max(np.abs(rk4 - (exact - KELVIN))) < 1e-5


def test_casadi_mpc_step_equals_ours_where_the_band_is_reachable():
    horizon = 10
    scenario = synthetic_scenario(hours=horizon + 1)
    forecast = forecast_window(scenario, 0, horizon)
    ours = MPC(R1C1Model(), horizon_steps=horizon, solver='ipopt').solve(
        [20.5 + KELVIN], 0.0, forecast)
    theirs = CasadiMpc(ZoneParameters.from_r1c1(), horizon).solve(
        np.array([20.5]), forecast[list(DISTURBANCE_COLUMNS)].to_numpy()[:horizon],
        forecast[['comfort_min']].to_numpy()[1:], forecast[['comfort_max']].to_numpy()[1:])
    assert ours.success and theirs['success'] and not ours.relaxed
    assert np.max(np.abs(ours.controls[:, 0])) > 100.0  # the band makes it heat
    assert np.max(np.abs(theirs['q'][:, 0] - ours.controls[:, 0])) < 1.0
    assert np.max(np.abs(theirs['T'][:, 0] + KELVIN - ours.states[1:, 0])) < 1e-3
    assert np.max(theirs['slack']) < 1e-6
