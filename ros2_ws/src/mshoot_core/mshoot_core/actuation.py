"""
Actuation: what a step's decided controls become within the step (settings ``actuation``).

Stable API::

    from mshoot_core.actuation import Actuator
    actuator = Actuator(settings.actuation, settings.problem.control_bounds, step_s)
    schedule = actuator.schedule(t_s, controls, next_controls, zone_k)
    schedule.offsets_s, schedule.values     # pieces from the step's start, values (n, nc)

``'hold'``: each control held over the step at its decided value (one piece).

``'burst'``: a control decided at u between its bounds (lo, hi) asks for the duty
d = (u - lo) / (hi - lo) of the step at its upper bound: d x step seconds. The request is added to
a balance (what was asked and not yet run). A running burst keeps running from the start of the
step while the balance lasts (and at least until its minimum run time is reached, unless the
plan stops asking); a stopped one starts when the balance reaches one ``burst_resolution_s``
(with a minimum run time: the run time, capped at one step, unless the plan asks in the next step
too), at the end of the step, so that it runs on into the next step as one burst. A decision of
zero duty clears the balance. Bursts start and stop on the ``burst_resolution_s`` grid.

A burst is sent as the control's bounds (``actuation_send`` 'value'), or as a temperature
setpoint for the building's own loop (``'setpoint'``): ``setpoint_above_k`` above the zone
temperature while it runs, ``setpoint_below_k`` below it otherwise [K, as the zone temperature].
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from mshoot_core.settings import ActuationSettings


@dataclasses.dataclass(frozen=True)
class Schedule:
    """
    The values sent over one step, piece by piece.

    Attributes
    ----------
    offsets_s : ndarray, shape (n,)
        Start of every piece from the step's start [s], increasing, the first 0; each piece
        lasts to the next one or to the step's end.
    values : ndarray, shape (n, nc)
        The controls of every piece (setpoints [K] with ``actuation_send`` 'setpoint').

    """

    offsets_s: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        if self.offsets_s.ndim != 1 or self.values.shape[:1] != self.offsets_s.shape or \
                self.offsets_s.size < 1 or self.offsets_s[0] != 0.0 or \
                np.any(np.diff(self.offsets_s) <= 0.0):
            raise ValueError(f'a schedule needs increasing offsets from 0 and one row of values '
                             f'each, got offsets {self.offsets_s.tolist()} and values of shape '
                             f'{self.values.shape}')

    @property
    def held(self) -> bool:
        """Return True for one piece over the whole step."""
        return self.offsets_s.size == 1


class _Burst:
    """The full-load bursts of one control (see the module)."""

    def __init__(self, min_run_s: float, step_s: float, quantum_s: float) -> None:
        self.min_run_s = float(min_run_s)
        self.step_s = float(step_s)
        self.quantum_s = float(quantum_s)
        self.balance_s = 0.0
        self.on = False
        self.run_s = 0.0

    def pieces(self, duty: float, next_duty: float) -> list[tuple[float, bool]]:
        """Return the step's (start offset [s], running) pieces for a duty in [0, 1]."""
        step, quantum = self.step_s, self.quantum_s
        self.balance_s = 0.0 if duty <= 0.0 else min(self.balance_s + duty * step, 2.0 * step)
        if self.on:
            keep = max(self.balance_s, self.min_run_s - self.run_s)
            run = min(step, quantum * math.floor(keep / quantum + 0.5))
            if duty <= 0.0 and self.run_s >= self.min_run_s:
                run = 0.0
            self.balance_s = max(0.0, self.balance_s - run)
            self.run_s += run
            if run >= step:
                return [(0.0, True)]
            self.on, self.run_s = False, 0.0
            return ([(0.0, True)] if run > 0 else []) + [(run, False)]
        threshold = quantum if next_duty > 0.0 else max(quantum, min(self.min_run_s, step))
        if self.balance_s < threshold - 1e-9:
            return [(0.0, False)]
        run = min(step, quantum * math.floor(self.balance_s / quantum + 0.5))
        self.balance_s = max(0.0, self.balance_s - run)
        self.on, self.run_s = True, run
        return ([(0.0, False)] if run < step else []) + [(step - run, True)]


class Actuator:
    """
    Turn each step's decided controls into the schedule sent within the step (see the module).

    Parameters
    ----------
    settings : ActuationSettings
    bounds : sequence of (float, float)
        (lower, upper) bound of every control, in the order of the decided controls.
    step_s : float
        Control step [s].

    Raises
    ------
    ValueError
        For bounds that are not finite with lower < upper, or a step that is not a multiple of
        ``burst_resolution_s`` with actuation 'burst'.

    """

    def __init__(self, settings: ActuationSettings, bounds: Sequence[tuple[float, float]],
                 step_s: float) -> None:
        self.settings = settings
        self.bounds = np.asarray(bounds, dtype=float).reshape(-1, 2)
        finite = np.all(np.isfinite(self.bounds))
        if not (finite and np.all(self.bounds[:, 0] < self.bounds[:, 1])):
            raise ValueError(f'control bounds must be finite with lower < upper, got '
                             f'{self.bounds.tolist()}')
        self.step_s = float(step_s)
        quantum = settings.burst_resolution_s
        if settings.actuation == 'burst' and abs(self.step_s / quantum
                                                 - round(self.step_s / quantum)) > 1e-9:
            raise ValueError(f'the control step ({self.step_s:g} s) must be a multiple of '
                             f'burst_resolution_s ({quantum:g} s)')
        self.reset()

    def reset(self) -> None:
        """Forget the bursts in progress (e.g. after a safe setpoint)."""
        s = self.settings
        self._bursts = [_Burst(s.min_run_s, self.step_s, s.burst_resolution_s)
                        for _ in range(self.bounds.shape[0])]

    def duties(self, controls: Sequence[float]) -> np.ndarray:
        """Return the duty in [0, 1] of every control: its share of the way between its bounds."""
        u = np.asarray(controls, dtype=float).reshape(-1)
        if u.shape != (self.bounds.shape[0],):
            raise ValueError(f'expected {self.bounds.shape[0]} controls, got {u.shape[0]}')
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        return np.clip(np.where(np.isfinite(u), (u - lo) / (hi - lo), 0.0), 0.0, 1.0)

    def schedule(self, controls: Sequence[float], next_controls: Sequence[float] | None = None,
                 zone_k: float | None = None) -> Schedule:
        """
        Return the schedule of one step (call once per step, in order).

        Parameters
        ----------
        controls : sequence of float
            The step's decided controls.
        next_controls : sequence of float, optional
            The plan's controls of the next step (None: none planned): a stopped burst with a
            minimum run time starts at the end of this step when the plan asks in both.
        zone_k : float, optional
            The zone temperature at the step's start [K] (``actuation_send`` 'setpoint').

        Raises
        ------
        ValueError
            For a wrong number of controls, or no finite zone temperature with 'setpoint'.

        """
        s = self.settings
        u = np.asarray(controls, dtype=float).reshape(-1)
        if s.actuation == 'hold':
            self.duties(u)  # (checks the count)
            return Schedule(np.zeros(1), u[None, :].copy())
        duty = self.duties(u)
        following = (self.duties(next_controls) if next_controls is not None
                     else np.zeros_like(duty))
        if s.actuation_send == 'setpoint' and not (zone_k is not None and math.isfinite(zone_k)):
            raise ValueError(f"actuation_send 'setpoint' needs the zone temperature, got "
                             f'{zone_k!r}')
        per_control = [b.pieces(float(d), float(f))
                       for b, d, f in zip(self._bursts, duty, following)]
        offsets = np.array(sorted({o for pieces in per_control for o, _ in pieces}))
        running = np.zeros((offsets.size, duty.size), dtype=bool)
        for i, pieces in enumerate(per_control):
            for o, on in pieces:
                running[offsets >= o, i] = on
        if s.actuation_send == 'setpoint':
            values = np.where(running, zone_k + s.setpoint_above_k, zone_k - s.setpoint_below_k)
        else:
            values = np.where(running, self.bounds[:, 1][None, :], self.bounds[:, 0][None, :])
        return Schedule(offsets.astype(float), values.astype(float))
