"""
Model Exchange integration of an :class:`~mshoot_core.models.fmi.FmiModel`.

Two integrators, the same FMI calls around them:

- fmpy's CVode (BDF, dense Newton) with the relative ``tolerance`` and
  absolute tolerances ``tolerance * nominal``; each input switch is an event
  (event mode, new discrete states, solver re-start), and the FMU's state,
  step and time events are handled;
- for batches of independent intervals of FMUs without event indicators, the
  compiled driver (:class:`~mshoot_core.models.fmi_drivers.MeBatchDriver`):
  the same FMI calls per interval, integrated by an explicit Dormand-Prince
  5(4) method at the same tolerances in one C loop over the batch
  (:meth:`ModelExchangeIntegration.me_batch_plan` says when it applies). An
  interval with a time or step event, or needing more than
  :data:`ME_MAX_STEPS` steps (a stiff FMU), sends the model back to CVode for
  good, with a logged warning: a numerical limit of the method, not a missing
  build (a missing driver is an error).

FMUs that support FMU states start each interval by restoring a snapshot
taken after the first initialisation (at FMU time 0) instead of
re-initialising; an interval starting at another FMU time then sets that time
(``fmi2SetTime``) and iterates the events there, so schedules and time events
inside the FMU see the interval's own time.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from mshoot_core.models.fmi_drivers import (double_pointer, DriverGaveUp, me_problem,
                                            MeBatchDriver, MeProblem, SensitivityRequest)
from mshoot_core.models.fmi_values import FmuValueError

logger = logging.getLogger(__name__)

#: CVode's limit on internal steps per call (one call per interval or event).
MAX_SOLVER_STEPS = 100_000
#: Attempted Runge-Kutta steps per interval of the batched Model Exchange driver before it
#: gives up (a stiff FMU) and the model falls back to CVode.
ME_MAX_STEPS = 20_000


class HeldInputs:
    """The ``input`` object fmpy's CVode solver expects; inputs are set per interval."""

    def apply(self, time: float, continuous: bool = True, discrete: bool = True,
              after_event: bool = False) -> None:
        """Do nothing: the inputs are already set on the FMU for the interval."""


class ModelExchangeIntegration:
    """
    Model Exchange part of :class:`~mshoot_core.models.fmi.FmiModel` (a mixin).

    Works on the model's FMU instance and configuration; keeps on the
    instance the CVode solver (``_solver``), the FMU-state snapshot
    (``_snapshot``, ``_snapshot_event_time``), the next time event
    (``_next_event_time``), the compiled driver (``_me_driver``: None until
    first needed, False once disabled) and its batch descriptions
    (``_me_problems``).
    """

    # -- CVode and events ---------------------------------------------------------------------
    def _event_iteration(self) -> None:
        """Iterate fmi2NewDiscreteStates to convergence (event mode); note time events."""
        fmu = self._fmu
        needed = True
        while needed:
            (needed, terminate, _, _, time_defined, next_time) = fmu.newDiscreteStates()
            if terminate:
                raise RuntimeError(f'{self.fmu_path.name} requested termination at an event')
        self._next_event_time = next_time if time_defined else None

    def _write_states(self, x0: np.ndarray) -> None:
        """Write the model states into the FMU's continuous-state vector."""
        n = self._n_continuous
        if n == 0 or not self._state_positions:
            return
        fmu = self._fmu
        fmu.getContinuousStates(double_pointer(self._x_full), n)
        self._x_full[self._state_positions] = np.asarray(x0)[self._written_states]
        fmu.setContinuousStates(double_pointer(self._x_full), n)

    def _ensure_solver(self, t0: float) -> None:
        """
        (Re)start the CVode solver at ``t0`` from the FMU's current states.

        Before the first CVode integration the solver is not created here but when
        :meth:`_integrate` first needs it, at the last start time given: created there
        from the same states (nothing changes them in between), it starts as a re-start
        here would. A model whose intervals all go to the compiled driver never loads
        CVode.
        """
        if self._solver is None:
            self._solver_start = t0
        else:
            self._solver.reset(t0)

    def _cvode(self) -> Any:
        """Return the CVode solver, created at the pending start time if it is not yet."""
        if self._solver is None:
            from fmpy.sundials import CVodeSolver
            fmu = self._fmu
            self._solver = CVodeSolver(
                nx=self._n_continuous, nz=self.model_description.numberOfEventIndicators,
                get_x=fmu.getContinuousStates, set_x=fmu.setContinuousStates,
                get_dx=self._derivatives_checked, get_z=fmu.getEventIndicators,
                get_nominals=fmu.getNominalsOfContinuousStates, set_time=self._record_time,
                input=HeldInputs(), startTime=self._solver_start,
                relativeTolerance=self.tolerance, maxNumSteps=MAX_SOLVER_STEPS)
        return self._solver

    def _enter_continuous_time(self, t0: float, x0: np.ndarray) -> None:
        """After initialisation: settle the events, enter continuous time, write ``x0``."""
        self._event_iteration()
        self._fmu.enterContinuousTimeMode()
        self._write_states(x0)
        self._ensure_solver(t0)

    def _input_event(self, t: float, u: np.ndarray) -> None:
        """Apply new inputs at ``t`` as an event, and re-start the solver."""
        fmu = self._fmu
        fmu.enterEventMode()
        self._set_inputs(u)
        self._event_iteration()
        fmu.enterContinuousTimeMode()
        self._ensure_solver(t)

    def _integrate(self, t: float, t_end: float) -> None:
        """Integrate from ``t`` to ``t_end`` with CVode, handling the FMU's events."""
        fmu = self._fmu
        solver = self._cvode()
        needs_step_call = bool(self._interface.needsCompletedIntegratorStep)
        eps = 1e-12 * max(1.0, abs(t_end))
        while t_end - t > eps:
            t_next = t_end
            event_time = self._next_event_time
            if event_time is not None and t + eps < event_time < t_end - eps:
                t_next = event_time
            state_event, _, t = solver.step(t, t_next)
            fmu.setTime(t)
            step_event = False
            if needs_step_call:
                step_event, terminate = fmu.completedIntegratorStep()
                if terminate:
                    raise RuntimeError(f'{self.fmu_path.name} requested termination at t={t}')
            time_event = event_time is not None and abs(t - event_time) <= eps
            if state_event or step_event or time_event:
                fmu.enterEventMode()
                self._event_iteration()
                fmu.enterContinuousTimeMode()
                solver.reset(t)

    def _restore_snapshot(self, x0: np.ndarray, u: np.ndarray, t0: float = 0.0) -> None:
        """
        Bring the instance to FMU time ``t0`` with ``x0`` and ``u`` through its snapshot.

        The first call initialises at time 0 and takes the snapshot; later
        ones restore it (no re-initialisation), write the states and apply the
        inputs as an event. A start time other than 0 is set before that
        event, whose iteration updates the FMU's time-dependent discrete
        states (schedules) and its next time event.
        """
        fmu = self._fmu
        if self._snapshot is None:
            self._initialize(0.0, x0, u)
            self._snapshot = fmu.getFMUstate()
            self._snapshot_event_time = self._next_event_time
            if t0 != 0.0:
                fmu.setTime(t0)
                self._input_event(t0, u)
            return
        fmu.setFMUstate(self._snapshot)
        self._next_event_time = self._snapshot_event_time
        if t0 != 0.0:
            fmu.setTime(t0)
        self._write_states(x0)
        self._input_event(t0, u)

    # -- the compiled batch ---------------------------------------------------------------
    def me_batch_plan(self) -> str | None:
        """
        Why Model Exchange intervals cannot go to the compiled driver, or None if they can.

        The driver integrates with an explicit Runge-Kutta method and handles
        no events, so it applies to Model Exchange FMUs without event
        indicators (time events and step events are detected per interval and
        send the batch back to CVode). Everything else goes through fmpy's
        CVode, exactly as before.
        """
        if not self.is_model_exchange:
            return 'Co-Simulation FMU'
        if self.model_description.numberOfEventIndicators > 0:
            return 'the FMU has event indicators'
        if self._n_continuous == 0:
            return 'no continuous states'
        if self._me_driver is False:
            return 'the compiled driver was disabled'
        if not self.can_snapshot and any(kind != 'Real' for kind in self._parameter_groups):
            return 'non-Real parameters on an FMU without FMU states'
        return None

    def _me_problem(self, dt_s: float, sensitivities: SensitivityRequest | None,
                    chain: int = 0) -> tuple[MeProblem, list]:
        """Return the driver's description of a batch, and the arrays it points to (keep both)."""
        par_refs, par_values = self._parameter_groups.get('Real', ([], []))
        fmu_outputs = {o.variable.name for o in self.model_description.outputs}
        return me_problem(
            snapshot=self._snapshot.value if self._snapshot is not None else None,
            needs_completed_step=bool(self._interface.needsCompletedIntegratorStep),
            tolerance=self.tolerance, dt_s=dt_s, max_steps=ME_MAX_STEPS,
            n=self._n_continuous,
            cstate_refs=[v.valueReference for v in self._continuous_states],
            derivative_refs=self._derivative_refs, state_positions=self._state_positions,
            state_refs=[v.valueReference for v in self._state_vars],
            output_refs=[v.valueReference for v in self._output_vars],
            input_refs=[v.valueReference for v in self._input_vars],
            par_refs=par_refs, par_values=par_values,
            start_refs=[self._state_vars[i].valueReference for i in self._start_state_index],
            start_index=self._start_state_index,
            fmu_output_refs=[v.valueReference for v in self._output_vars
                             if v.name in fmu_outputs],
            sensitivities=sensitivities, chain=chain)

    def _me_batch_in_c(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                       x_end: np.ndarray, y_end: np.ndarray,
                       sensitivities: SensitivityRequest | None = None,
                       t_start: np.ndarray | None = None, chain: int = 0
                       ) -> tuple[np.ndarray, np.ndarray] | bool:
        """
        Run a Model Exchange batch in the compiled driver; False where it does not apply.

        Each interval makes the FMI calls of :meth:`_start_interval`, then
        integrates with Dormand-Prince 5(4) at :attr:`tolerance` (absolute
        tolerances ``tolerance * nominal``, as CVode here) and reads as
        :meth:`_read`. With ``sensitivities`` (m input columns) the forward
        sensitivities are integrated along, as in
        :class:`~mshoot_core.models.fmi_sensitivities._Sensitivities`, and
        the result is ``(S, output partials)``: S of shape (B, n, nx + m) over
        the FMU's n continuous states, the partials of the FMU outputs among
        the model outputs w.r.t. (continuous states, those inputs), shape
        (B, n_yo, n + m). A batch the driver gives up on (a time or step
        event, too many steps) is logged, the driver disabled for this
        instance, and False returned: the caller then uses CVode; unless the
        FMU computed non-finite values there (an
        :class:`~mshoot_core.models.fmi_values.FmuValueError`, found by
        integrating that interval with CVode), which is raised and leaves
        the driver on. Interval b starts at FMU time ``t_start[b]`` (None:
        every interval at 0). With ``chain`` C > 0 the intervals are C trajectories
        of consecutive intervals, interleaved: interval b >= C starts from the end
        states of interval b - C (its row of ``x_start`` is not read). The batch runs on
        buffers bound once per batch size
        (:class:`~mshoot_core.models.fmi_drivers.BoundMeBatch`): the returned ``S``
        and partials are those buffers, valid until the next batch.

        Raises
        ------
        NotBuiltError
            If the driver is not built (``make setup``).

        """
        if self._me_driver is False:
            return False
        if self._me_driver is None:
            self._me_driver = MeBatchDriver(self.fmu, self.fmu_path.name)
        if (self._snapshot is None if self.can_snapshot else not self._initialized_once):
            # first initialisation through fmpy
            self._start_interval(x_start[0], u[0], 0.0 if t_start is None else t_start[0])
        if self._next_event_time is not None:
            logger.debug('%s: time events, Model Exchange batches use CVode', self.fmu_path.name)
            return False
        # a model's requests differ by their inputs only (their nominals follow)
        key = (dt_s, None if sensitivities is None else sensitivities.input_refs,
               None if self._snapshot is None else self._snapshot.value, chain)
        if key not in self._me_problems:  # built once per interval length and request
            if len(self._me_problems) >= 16:
                self._me_problems.clear()
            self._me_problems[key] = self._me_problem(dt_s, sensitivities, chain)
        entry = self._me_problems[key]
        bound_key = (key, x_start.shape[0], t_start is None)
        bound = self._me_bound.get(bound_key)
        if bound is None or bound.problem is not entry or bound.driver is not self._me_driver \
                or bound.component is not self._fmu.component:
            if len(self._me_bound) >= 16:
                self._me_bound.clear()
            bound = self._me_driver.bind(self._fmu.component, entry, x_start.shape[0],
                                         x_start.shape[1], u.shape[1], y_end.shape[1],
                                         t_start is not None)
            self._me_bound[bound_key] = bound
        np.copyto(bound.starts, x_start)
        np.copyto(bound.inputs, u)
        if t_start is not None:
            np.copyto(bound.times, t_start)
        try:
            bound.run()
        except DriverGaveUp as gave_up:
            if not chain:  # (a chained interval's start is not its row of x_start)
                self._non_finite_interval(x_start, u, dt_s, t_start, gave_up)
            logger.warning('%s: the batched Model Exchange driver stopped at interval %d (%s); '
                           'this model integrates with CVode from now on', self.fmu_path.name,
                           gave_up.interval, gave_up.reason)
            self._me_driver = False
            return False
        np.copyto(x_end, bound.x_end)
        np.copyto(y_end, bound.y_end)
        return (bound.s_end, bound.dyo) if sensitivities is not None else True

    def _non_finite_interval(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                             t_start: np.ndarray | None, gave_up: DriverGaveUp) -> None:
        """
        Integrate the interval the driver gave up on with CVode.

        Raise its FmuValueError if the FMU computes non-finite values there, else return (any other
        failure is left to the CVode run of the whole batch).
        """
        b = gave_up.interval
        if not 0 <= b < x_start.shape[0]:
            return
        t0 = 0.0 if t_start is None else float(t_start[b])
        try:
            self._start_interval(x_start[b], u[b], t0)
            self._advance_checked(t0, t0 + dt_s)
            self._check_finite(*self._read(), t0 + dt_s)
        except FmuValueError as error:
            raise error from gave_up
        except Exception:  # noqa: BLE001 - not a non-finite value: the batch goes to CVode
            return
