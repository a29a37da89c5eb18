"""Actuation of decided controls: held, or full-load bursts sent as values or setpoints."""
from __future__ import annotations

from mshoot_core.actuation import Actuator, Schedule
from mshoot_core.controller import Controller
from mshoot_core.models.r1c1 import KELVIN, R1C1Model
from mshoot_core.scenario import forecast_window, synthetic_scenario
from mshoot_core.settings import ActuationSettings, MpcSettings, SettingsError
import numpy as np
import pytest

STEP_NS = 3600 * 1_000_000_000
DUTIES = [0.3, 0.3, 0.3, 0.0, 0.5, 0.5, 1.0, 0.2, 0.0, 0.0, 0.1, 0.1, 0.1, 0.1]
HOUR = 3600.0


def _minutes(actuator: Actuator, controls: list[float], low: float = 0.0,
             high: float = 1.0) -> np.ndarray:
    """Return the sent value of every minute of the steps (the schedules laid out)."""
    out = []
    for u in controls:
        schedule = actuator.schedule([u])
        ends = [*schedule.offsets_s[1:], HOUR]
        for start, end, value in zip(schedule.offsets_s, ends, schedule.values[:, 0]):
            assert value in (low, high)  # a burst runs at a bound
            out += [value] * int(round((end - start) / 60.0))
    return np.array(out)


def test_bursts_run_the_planned_duty_joined_across_steps():
    settings = ActuationSettings(actuation='burst')
    on = _minutes(Actuator(settings, [(0.0, 1.0)], HOUR), DUTIES)
    assert on.size == len(DUTIES) * 60
    assert on.sum() * 60.0 == pytest.approx(sum(DUTIES) * HOUR, abs=len(DUTIES) * 60.0)
    starts = int(np.sum(np.diff(np.r_[0.0, on]) > 0))
    assert starts < np.count_nonzero(DUTIES)  # joined across steps: fewer starts than steps
    # the same duties of a control between other bounds: the same minutes at its bounds
    other = _minutes(Actuator(settings, [(-2000.0, 3000.0)], HOUR),
                     [-2000.0 + 5000.0 * d for d in DUTIES], -2000.0, 3000.0)
    np.testing.assert_array_equal(other == 3000.0, on == 1.0)
    # a minimum run time: every burst that stopped ran 2 h at least, with fewer starts
    on2 = _minutes(Actuator(ActuationSettings(actuation='burst', min_run_s=2 * HOUR),
                            [(0.0, 1.0)], HOUR), DUTIES)
    edges = np.diff(np.r_[0.0, on2, 0.0])
    stops, lengths = np.flatnonzero(edges < 0), np.flatnonzero(edges < 0) - np.flatnonzero(
        edges > 0)
    ended = lengths[stops < on2.size]
    assert ended.size >= 1 and ended.min() >= 120, lengths
    assert int(np.sum(edges > 0)) < starts


def test_minimum_run_waits_or_starts_with_the_plan():
    settings = ActuationSettings(actuation='burst', min_run_s=2 * HOUR)
    waiting = Actuator(settings, [(0.0, 1.0)], HOUR)
    assert waiting.schedule([0.3]).values.tolist() == [[0.0]]  # accumulates
    starting = Actuator(settings, [(0.0, 1.0)], HOUR)
    schedule = starting.schedule([0.3], next_controls=[0.5])  # the plan heats on: start now
    assert schedule.offsets_s.tolist() == [0.0, 2520.0]
    assert schedule.values[:, 0].tolist() == [0.0, 1.0]
    assert starting.schedule([0.0]).values.tolist() == [[1.0]]  # its minimum run
    starting.reset()
    assert starting.schedule([0.0]).values.tolist() == [[0.0]]


def test_hold_and_setpoint_sending():
    held = Actuator(ActuationSettings(), [(0.0, 1.0), (-5.0, 5.0)], HOUR).schedule([0.4, -1.0])
    assert held.held and held.values.tolist() == [[0.4, -1.0]]
    settings = ActuationSettings(actuation='burst', actuation_send='setpoint',
                                 setpoint_above_k=10.0, setpoint_below_k=3.0)
    schedule = Actuator(settings, [(0.0, 1.0)], HOUR).schedule([0.5], zone_k=293.0)
    assert schedule.offsets_s.tolist() == [0.0, 1800.0]
    assert schedule.values[:, 0].tolist() == [290.0, 303.0]
    with pytest.raises(ValueError, match='zone temperature'):
        Actuator(settings, [(0.0, 1.0)], HOUR).schedule([0.5])


def test_bad_actuation_inputs_and_settings():
    with pytest.raises(ValueError, match='expected 1 controls, got 2'):
        Actuator(ActuationSettings(), [(0.0, 1.0)], HOUR).schedule([0.1, 0.2])
    with pytest.raises(ValueError, match='lower < upper'):
        Actuator(ActuationSettings(), [(1.0, 0.0)], HOUR)
    with pytest.raises(ValueError, match='multiple of burst_resolution_s'):
        Actuator(ActuationSettings(actuation='burst', burst_resolution_s=7.0), [(0, 1)], 100.0)
    with pytest.raises(ValueError, match='increasing offsets'):
        Schedule(np.array([0.0, 0.0]), np.zeros((2, 1)))
    with pytest.raises(SettingsError, match="needs actuation 'burst'"):
        MpcSettings.from_flat(actuation_send='setpoint')
    with pytest.raises(SettingsError, match='actuation must be one of'):
        MpcSettings.from_flat(actuation='pulse')
    with pytest.raises(SettingsError, match='band_margin_k must be in'):
        MpcSettings.from_flat(band_margin_k=-0.5)


def _decide(settings: MpcSettings, steps: int = 3) -> list:
    """Return the outcomes of the first steps of an R1C1 controller on a perfect forecast."""
    scenario = synthetic_scenario(hours=12)
    controller = Controller(R1C1Model(), settings)
    outcomes = []
    for k in range(steps):
        window = forecast_window(scenario, k, controller.mpc.horizon_steps)
        now = k * STEP_NS
        assert controller.offer_state(now, [20.0 + KELVIN], now) is None
        assert controller.offer_forecast(now, HOUR, {c: window[c].to_numpy()
                                                     for c in window.columns}, now) is None
        outcomes += controller.poll(now)
    return outcomes


def test_controller_sends_bursts_of_its_decisions_and_plans_with_a_band_margin():
    base = MpcSettings.from_flat(horizon_steps=4, control_min=0.0, control_max=4000.0)
    held = _decide(base)
    assert [o.schedule.held for o in held] == [True] * 3
    np.testing.assert_array_equal(held[0].schedule.values[0], held[0].decision.controls)
    bursts = _decide(base.replace(actuation='burst'))
    sent = 0.0
    for outcome, same in zip(bursts, held):  # the same decisions, sent as bursts at the bounds
        np.testing.assert_allclose(outcome.decision.controls, same.decision.controls)
        s = outcome.schedule
        assert set(s.values[:, 0]) <= {0.0, 4000.0}
        sent += float(np.diff([*s.offsets_s, HOUR]) @ s.values[:, 0])
    asked = sum(float(o.decision.controls[0]) * HOUR for o in held)
    assert sent == pytest.approx(asked, abs=3 * 4000.0 * 60.0)  # to the burst grid
    raised = _decide(base.replace(band_margin_k=1.0), 1)[0]
    assert raised.decision.controls[0] > held[0].decision.controls[0]
