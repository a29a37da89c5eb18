"""
The one period loop: observe, decide, apply, control step after control step.

Every run of a controller on a plant in core goes through :func:`run_steps`:
:func:`mshoot_core.closed_loop.run_closed_loop` (a :class:`~mshoot_core.controller.Controller`
against an :class:`~mshoot_core.emulation.Emulator`: a model stepped through a scenario whose
disturbances are its inputs) and :func:`mshoot_core.boptest.plant.run_span` (any step policy on
a BOPTEST test case's :class:`~mshoot_core.boptest.plant.BoptestPlant`, its warm-up included:
the baseline, a rule, the supervised controller, the identification's excitation) are thin
callers, and so are the open-loop runs: a plant card's excitation
(:func:`mshoot_core.identification.excite`), the recorded warm-up of a card's BOPTEST plant
(:class:`~mshoot_core.boptest.card_plant.CardPlant` with ``history_step_s``) and the weather
read from a test case's FMU (:func:`mshoot_core.boptest.weather.derive_weather`). The loop
owns the step schedule (steps of ``step_s`` from ``start_s``, the last one ending at
``end_s``), the order of a step (observe the plant, decide, apply the decision up to the step's
end), the wall time of every decision, a wall-time budget, and the progress lines; the callers
own what is observed, decided and recorded.

Stable API::

    from mshoot_core.period_loop import LoopRun, run_steps
    loop = run_steps(start_s, end_s, step_s, apply, decide=decide, observe=observe)
    loop.step_wall_s, loop.wall_s

What stays apart, and why (each difference is one of the plant or of the decider, not of the
loop, so a common plant protocol would only rename it):

- The step: an :class:`~mshoot_core.emulation.Emulator` steps one scenario row at a time, the
  model's inputs being the controls (clipped to the card's limits, with release flags) and the
  row's disturbances; a :class:`~mshoot_core.boptest.plant.BoptestPlant` goes to an end time
  under overwrites of FMU inputs (checked against the FMU's declared ranges), piece by piece
  within a step, and reads its own weather.
- The records: the emulator records states and outputs on a fine grid in the card's canonical
  units, and the closed loop adds the controller's per-step record
  (:func:`~mshoot_core.closed_loop.step_row`) and plan; a BOPTEST plant records the FMU's
  outputs and the overwrites every <= 60 s in the FMU's units, what BOPTEST's KPIs are
  computed from. Their results (:class:`~mshoot_core.closed_loop.ClosedLoopResult`,
  :class:`~mshoot_core.boptest.plant.PeriodRun`) are both a :class:`LoopRun` with those tables.
- The decider: the closed loop's is a :class:`~mshoot_core.controller.Controller` (offered the
  state and the scenario's forecast by nanosecond stamps, polled once per step; a
  non-finite plant value ends the run with its records); a test case's is any step policy
  (``policy(t_s, outputs)``: none, a rule, an excitation, or the supervised controller, the only
  one that observes), and the BOPTEST plant alone has a warm-up under its own control.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any, Callable

logger = logging.getLogger(__name__)

#: Wall time between two progress lines of a run [s].
PROGRESS_S = 10.0

#: ``observe(t_s)``: offer the controller what the plant shows at the step's start [s].
Observe = Callable[[float], None]
#: ``decide(t_s)``: the decision of the step starting at ``t_s`` [s].
Decide = Callable[[float], Any]
#: ``apply(t_s, end_s, decision)``: take the plant from ``t_s`` to ``end_s`` [s] under the
#: decision (None without ``decide``: the plant's own control).
Apply = Callable[[float, float, Any], None]


@dataclasses.dataclass(kw_only=True)
class LoopRun:
    """
    The wall times of a run of :func:`run_steps` (the base of every period loop's result).

    Attributes
    ----------
    step_wall_s : list of float
        Wall time of each step's decision [s] (empty without a decision).
    wall_s : float
        Wall time of the whole run [s].

    """

    step_wall_s: list[float]
    wall_s: float


def step_count(start_s: float, end_s: float, step_s: float) -> int:
    """Return the number of control steps of ``step_s`` [s] from ``start_s`` to ``end_s`` [s]."""
    return max(0, math.ceil((float(end_s) - float(start_s)) / float(step_s) - 1e-9))


def run_steps(start_s: float, end_s: float, step_s: float, apply: Apply, *,
              decide: Decide | None = None, observe: Observe | None = None,
              budget_s: float | None = None, label: str = 'run',
              progress_s: float = PROGRESS_S) -> LoopRun:
    """
    Run control steps from ``start_s`` to ``end_s``: observe, decide, apply (see the module).

    Step ``k`` starts at ``start_s + k * step_s`` and ends ``step_s`` later, the last one at
    ``end_s``. At each step: ``observe(t_s)``, then ``decide(t_s)`` (timed), then
    ``apply(t_s, end, decision)``.

    Parameters
    ----------
    start_s, end_s : float
        The run's start and end [s], ``start_s <= end_s``.
    step_s : float
        Control step [s], > 0.
    apply : callable
        ``apply(t_s, end_s, decision)``: the plant taken to the step's end.
    decide : callable, optional
        ``decide(t_s) -> decision``; default none (``apply`` gets None: the plant's own control).
    observe : callable, optional
        ``observe(t_s)`` before the decision.
    budget_s : float, optional
        Wall-time budget [s]: no step after the first is started once it is spent.
    label : str
        Names the run in the log lines.
    progress_s : float
        Wall time between two progress lines [s].

    Returns
    -------
    LoopRun
        The wall times (the steps done: ``len(step_wall_s)`` with a decision).

    Raises
    ------
    ValueError
        For a step that is not positive or an end before the start.

    """
    start, end, step = float(start_s), float(end_s), float(step_s)
    if not step > 0:
        raise ValueError(f'expected a positive control step, got {step_s!r}')
    if not start <= end:
        raise ValueError(f'expected start <= end, got {start:g} and {end:g} s')
    total = step_count(start, end, step)
    walls: list[float] = []
    began = last = time.perf_counter()
    done = 0
    for k in range(total):
        if k and budget_s is not None and time.perf_counter() - began > budget_s:
            logger.info('%s: budget of %.0f s spent after %d/%d steps', label, budget_s, k,
                        total)
            break
        t, t_next = start + k * step, min(start + (k + 1) * step, end)
        if observe is not None:
            observe(t)
        decision = None
        if decide is not None:
            tic = time.perf_counter()
            decision = decide(t)
            walls.append(time.perf_counter() - tic)
        apply(t, t_next, decision)
        done = k + 1
        if time.perf_counter() - last > progress_s:
            last = time.perf_counter()
            logger.info('%s: step %d of %d, %.0f s', label, done, total, last - began)
    wall = time.perf_counter() - began
    logger.debug('%s: %d steps of %g s in %.1f s', label, done, step, wall)
    return LoopRun(step_wall_s=walls, wall_s=wall)
