"""
Forward sensitivities of Model Exchange intervals of an FMU model (:mod:`.fmi`).

For Model Exchange FMUs with ``providesDirectionalDerivative``,
:meth:`ForwardSensitivities.interval_jacobians` integrates the forward
sensitivities ``Sx' = J_x Sx``, ``Su' = J_x Su + J_u`` along with the states
(the Jacobian products come from ``fmi2GetDirectionalDerivative``), so the
derivatives are as accurate as the states: in the compiled Model Exchange
driver where :meth:`~mshoot_core.models.fmi_me.ModelExchangeIntegration.me_batch_plan`
allows it, else with CVode on the augmented system :class:`_Sensitivities`.
Co-Simulation FMUs, and FMUs without directional derivatives or with event
indicators, return ``None``: the optimiser falls back to finite differences
over ``simulate_intervals``.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Sequence

from fmpy.fmi2 import FMU2Model
import numpy as np

from mshoot_core.models.base import IntervalBatch, IntervalJacobians
from mshoot_core.models.fmi_drivers import (double_pointer, DriverGaveUp, SensitivityRequest,
                                            vr_array)
from mshoot_core.models.fmi_me import HeldInputs, MAX_SOLVER_STEPS

logger = logging.getLogger(__name__)

#: Absolute tolerances of the forward sensitivities relative to the states' (see
#: ``_Sensitivities.get_nominals``); 1e-2 costs ~5 % more steps than 1.
SENSITIVITY_NOMINAL_FACTOR = 1e-2


class _Sensitivities:
    """
    The augmented ODE [x, S] for fmpy's CVode solver (callbacks on raw buffers).

    Only the columns the model needs are integrated: ``S = [Sx | Su]`` of
    shape (n, k + m), Sx the derivatives w.r.t. the k model states among the
    n FMU continuous states (positions ``state_positions``), Su those w.r.t.
    the m requested inputs; stored row-major after x. Column j obeys
    ``S_j' = J_x S_j (+ J_u e_j)``, one directional-derivative call per
    column with the FMU states (and input j) as knowns.
    """

    def __init__(self, fmu: FMU2Model, derivative_refs: Sequence[int],
                 state_refs: Sequence[int], state_positions: Sequence[int],
                 input_refs: Sequence[int], input_nominals: Sequence[float]) -> None:
        self.fmu = fmu
        self.n = len(state_refs)
        self.positions = list(state_positions)
        self.k = len(self.positions)
        self.m = len(input_refs)
        self.columns = self.k + self.m
        self.size = self.n * (1 + self.columns)
        self.y = np.zeros(self.size)
        self.input_nominals = np.asarray(input_nominals, dtype=float)
        self._unknowns = vr_array(derivative_refs)
        self._state_knowns = vr_array(state_refs)
        self._input_knowns = [vr_array([*state_refs, ref]) for ref in input_refs]
        self._seed = np.zeros(self.n + 1)
        self._column = np.zeros(self.n)
        self._x_nominal = np.ones(self.n)
        # The arrays are only ever updated in place, so their pointers stay valid.
        self._y_ptr = double_pointer(self.y)
        self._seed_ptr = double_pointer(self._seed)
        self._column_ptr = double_pointer(self._column)

    def load(self, x: np.ndarray) -> None:
        """Start from FMU states ``x`` with Sx = the unit columns, Su = 0."""
        self.y[:] = 0.0
        self.y[:self.n] = x
        self.matrix()[self.positions, np.arange(self.k)] = 1.0

    def matrix(self) -> np.ndarray:
        """View of S = [Sx | Su], shape (n, k + m)."""
        return self.y[self.n:].reshape(self.n, self.columns)

    def get_x(self, buffer: Any, size: int) -> None:
        np.ctypeslib.as_array(buffer, (size,))[:] = self.y

    def set_x(self, buffer: Any, size: int) -> None:
        self.y[:] = np.ctypeslib.as_array(buffer, (size,))
        self.fmu.setContinuousStates(self._y_ptr, self.n)

    def get_dx(self, buffer: Any, size: int) -> None:
        n, fmu = self.n, self.fmu
        dy = np.ctypeslib.as_array(buffer, (size,))
        fmu.getDerivatives(buffer, n)
        ds = dy[n:].reshape(n, self.columns)
        s = self.y[n:].reshape(n, self.columns)
        seed, column = self._seed, self._column
        for j in range(self.columns):
            seed[:n] = s[:, j]
            if j < self.k:
                knowns, n_known = self._state_knowns, n
            else:
                knowns, n_known = self._input_knowns[j - self.k], n + 1
                seed[n] = 1.0
            fmu.fmi2GetDirectionalDerivative(fmu.component, self._unknowns, n, knowns, n_known,
                                             self._seed_ptr, self._column_ptr)
            ds[:, j] = column

    def get_nominals(self, buffer: Any, size: int) -> None:
        """
        Nominals (absolute tolerance = tolerance * nominal) of [x, S].

        The FMU's nominals for x; for S_ij the change of x_i per nominal
        change of state or input j (x_nom_i / nom_j), tightened by
        :data:`SENSITIVITY_NOMINAL_FACTOR`, since a derivative is a difference
        of states and needs more absolute accuracy than the states.
        """
        self.fmu.getNominalsOfContinuousStates(double_pointer(self._x_nominal), self.n)
        nominal = np.ctypeslib.as_array(buffer, (size,))
        nominal[:self.n] = self._x_nominal
        x_nom = np.abs(self._x_nominal)
        scale = np.concatenate([x_nom[self.positions], self.input_nominals])
        nominal[self.n:] = (SENSITIVITY_NOMINAL_FACTOR * x_nom[:, None] / scale[None, :]).ravel()

    @staticmethod
    def get_z(buffer: Any, size: int) -> None:
        """No event indicators (FMUs with events get no sensitivities)."""


class _JacobianPlan:
    """
    What the interval Jacobians of one set of input columns need, found once per model.

    ``wrt`` the input columns; ``reason`` why sensitivities are unavailable (None when they
    are); ``request`` the driver's :class:`SensitivityRequest`; ``output_rows`` the model
    outputs that are FMU outputs (their partials come from the driver); ``state_outputs``
    (ny, n) the ones of the outputs that are continuous states read as outputs;
    ``all_outputs`` whether every model output is an FMU output, in order; ``positions``
    the model states among the FMU's continuous states (a slice where they are contiguous).
    """

    def __init__(self, wrt: list[int], reason: str | None) -> None:
        self.wrt = wrt
        self.reason = reason
        self.request: SensitivityRequest | None = None
        self.output_rows = np.zeros(0, dtype=np.intp)
        self.state_outputs = np.zeros((0, 0))
        self.all_outputs = False
        self.positions: slice | np.ndarray = slice(0, 0)


class _DriverBatch(IntervalBatch):
    """
    An FMU's interval batch on the compiled Model Exchange driver, with sensitivities.

    An :class:`~mshoot_core.models.base.IntervalBatch`. The first :meth:`jacobians` goes
    through :meth:`ForwardSensitivities.interval_jacobians` (the first initialisation,
    the batch's description, its bound buffers); later ones,
    while that binding holds (the same driver, instance and snapshot, no time events),
    copy the buffers into the driver's and run it: the same numbers without the checks
    and look-ups of a call. Starts or inputs that are not finite, a driver that gives up
    or fails, go through ``interval_jacobians``, which reports them as it does.
    """

    def __init__(self, model: Any, batch: int, dt_s: float, wrt_inputs: Sequence[int],
                 t_start_s: np.ndarray | None, plan: _JacobianPlan) -> None:
        super().__init__(model, batch, dt_s, wrt_inputs, t_start_s)
        self._plan = plan
        self._fmu_times = model._fmu_start_times(self.t_start_s, int(batch))
        self._t_end = (self.dt_s if self._fmu_times is None else self._fmu_times + self.dt_s)
        self._bound: Any = None
        self._snapshot: Any = None
        self._views: tuple | None = None

    def jacobians(self) -> IntervalJacobians | None:
        model, bound = self.model, self._bound
        x_start, u = self.x_start, self.u
        if bound is None or not (
                model._me_driver is bound.driver and model._snapshot is self._snapshot
                and model._fmu is not None and model._fmu.component is bound.component
                and model._next_event_time is None
                and math.isfinite(np.add.reduce(x_start, None) + np.add.reduce(u, None))):
            jac = super().jacobians()  # the whole call; then bind to its driver batch
            self._bind()
            return jac
        np.copyto(bound.starts, x_start)
        np.copyto(bound.inputs, u)
        if bound.times is not None:
            np.copyto(bound.times, self._fmu_times)
        model._plant = None  # the instance is re-initialised: a plant run ends here
        try:
            bound.run()
        except (DriverGaveUp, RuntimeError):
            self._bound = None
            return super().jacobians()  # the call handles it (CVode, or the error)
        x_end, y_end = bound.x_end.copy(), bound.y_end.copy()
        if not math.isfinite(np.add.reduce(x_end, None) + np.add.reduce(y_end, None)):
            model._check_finite(x_end, y_end, self._t_end)
        views = self._views
        if views is None:
            return model._driver_jacobians(self._plan, x_end, y_end, bound.s_end, bound.dyo)
        # _driver_jacobians where every output is an FMU output, on views taken once
        sx, su, dy_dx, dy_du_direct, positions = views
        return IntervalJacobians(x_end, y_end, sx[:, positions].copy(), su[:, positions].copy(),
                                 dy_dx @ sx, dy_dx @ su + dy_du_direct)

    def _bind(self) -> None:
        """Take the driver batch the last call ran on, if it ran on the driver."""
        model = self.model
        self._bound = None
        if not model._me_driver or model._next_event_time is not None:
            return
        key = (self.dt_s, self._plan.request.input_refs,
               None if model._snapshot is None else model._snapshot.value, 0)
        bound = model._me_bound.get((key, self.x_start.shape[0], self._fmu_times is None))
        if bound is not None and bound.driver is model._me_driver:
            self._bound, self._snapshot = bound, model._snapshot
            self._views = None
            if self._plan.all_outputs:  # the views of the bound buffers _driver_jacobians takes
                nx, n = bound.x_end.shape[1], model._n_continuous
                self._views = (bound.s_end[:, :, :nx], bound.s_end[:, :, nx:],
                               bound.dyo[:, :, :n], bound.dyo[:, :, n:], self._plan.positions)


class ForwardSensitivities:
    """
    Forward-sensitivity part of :class:`~mshoot_core.models.fmi.FmiModel` (a mixin).

    Keeps on the instance, per set of input columns, the CVode solvers of
    the augmented systems (``_sensitivity_solvers``) and the requests to the
    compiled driver (``_sensitivity_requests``).
    """

    def _sensitivity_plan(self, wrt: Sequence[int]) -> str | None:
        """Why sensitivities are unavailable, or None when they are."""
        md = self.model_description
        if not self.is_model_exchange:
            return 'Co-Simulation FMU'
        if not md.modelExchange.providesDirectionalDerivative:
            return 'no directional derivatives'
        if md.numberOfEventIndicators > 0:
            return 'the FMU has event indicators'
        if self._n_continuous == 0:
            return 'no continuous states'
        output_vars = {u.variable.name for u in md.outputs}
        states = {v.name for v in self._continuous_states}
        odd = [v.name for v in self._output_vars
               if v.name not in output_vars and v.name not in states]
        if odd:
            return f'outputs {odd} are neither FMU outputs nor states'
        return None

    def interval_batch(self, batch: int, dt_s: float, wrt_inputs: Sequence[int],
                       t_start_s: np.ndarray | None = None) -> IntervalBatch:
        """
        Return an :class:`~mshoot_core.models.base.IntervalBatch` of ``batch`` intervals.

        Bound to the compiled driver's buffers after its first evaluation where the driver
        integrates the sensitivities (:class:`_DriverBatch`); else, and for a subclass with
        its own :meth:`interval_jacobians` (a card's unit conversions), the default.
        """
        if type(self).interval_jacobians is not ForwardSensitivities.interval_jacobians:
            # a subclass that converts values (a card's units): its own interval_jacobians
            return IntervalBatch(self, batch, dt_s, wrt_inputs, t_start_s)
        plan = self._jacobian_plans.get(tuple(wrt_inputs))
        if plan is None:
            plan = self._jacobian_plan(wrt_inputs)
        if plan.reason is not None or self.me_batch_plan() is not None:
            return IntervalBatch(self, batch, dt_s, wrt_inputs, t_start_s)
        return _DriverBatch(self, batch, dt_s, wrt_inputs, t_start_s, plan)

    def _driver_jacobians(self, plan: _JacobianPlan, x_end: np.ndarray, y_end: np.ndarray,
                          s_end: np.ndarray, dyo: np.ndarray) -> IntervalJacobians:
        """
        Return the interval Jacobians of a driver batch from its end values and sensitivities.

        ``s_end`` (B, n, nx + m) and the output partials ``dyo`` (B, n_yo, n + m) are the
        driver's buffers: read here, not kept.
        """
        batch, nx, ny = x_end.shape[0], x_end.shape[1], y_end.shape[1]
        sx, su = s_end[:, :, :nx], s_end[:, :, nx:]  # (B, n, nx), (B, n, m)
        n = self._n_continuous
        if plan.all_outputs:  # every output an FMU output: its partials as they are
            dy_dx, dy_du_direct = dyo[:, :, :n], dyo[:, :, n:]
        else:  # the FMU outputs' partials, ones for states read as outputs
            dy_dx = np.empty((batch, ny, n))
            dy_dx[:] = plan.state_outputs
            dy_dx[:, plan.output_rows] = dyo[:, :, :n]
            dy_du_direct = np.zeros((batch, ny, su.shape[2]))
            dy_du_direct[:, plan.output_rows] = dyo[:, :, n:]
        return IntervalJacobians(x_end, y_end, sx[:, plan.positions].copy(),
                                 su[:, plan.positions].copy(), dy_dx @ sx,
                                 dy_dx @ su + dy_du_direct)

    def _jacobian_plan(self, wrt_inputs: Sequence[int]) -> _JacobianPlan:
        """
        Return what :meth:`interval_jacobians` needs for the inputs ``wrt_inputs``, built once.

        Raises
        ------
        ValueError
            If an index is not one of :attr:`input_names`.

        """
        key = tuple(wrt_inputs)
        wrt = [int(j) for j in key]
        bad = [j for j in wrt if not 0 <= j < len(self.input_names)]
        if bad:
            raise ValueError(f'wrt_inputs must index {list(self.input_names)}, got {wrt}')
        reason = self._sensitivity_plan(wrt)
        plan = _JacobianPlan(wrt, reason)
        if reason is None:
            plan.request = self._sensitivity_request(wrt)
            fmu_outputs = {o.variable.name for o in self.model_description.outputs}
            plan.output_rows = np.array([i for i, v in enumerate(self._output_vars)
                                         if v.name in fmu_outputs], dtype=np.intp)
            plan.state_outputs = np.zeros((len(self._output_vars), self._n_continuous))
            for i, v in enumerate(self._output_vars):
                if v.name not in fmu_outputs:  # a continuous state read as an output
                    plan.state_outputs[i, self._continuous_states.index(v)] = 1.0
            plan.all_outputs = plan.output_rows.tolist() == list(range(len(self._output_vars)))
            pos = list(self._state_positions)
            contiguous = pos == list(range(pos[0], pos[0] + len(pos))) if pos else False
            plan.positions = slice(pos[0], pos[0] + len(pos)) if contiguous else np.array(
                pos, dtype=np.intp)
        self._jacobian_plans[key] = plan
        return plan

    def _sensitivity_request(self, wrt: Sequence[int]) -> SensitivityRequest:
        """Return the inputs ``wrt`` (indices of :attr:`input_names`) with their nominals."""
        key = tuple(wrt)
        request = self._sensitivity_requests.get(key)
        if request is None:
            inputs = [self._input_vars[j] for j in wrt]
            nominals = [abs(float(v.nominal)) if v.nominal not in (None, '') and
                        float(v.nominal) != 0.0 else 1.0 for v in inputs]
            request = SensitivityRequest(tuple(v.valueReference for v in inputs),
                                         tuple(nominals), SENSITIVITY_NOMINAL_FACTOR)
            self._sensitivity_requests[key] = request
        return request

    def _sensitivity_solver(self, wrt: Sequence[int]) -> tuple[_Sensitivities, Any]:
        """Return the augmented system and its CVode solver for the inputs ``wrt`` (cached)."""
        key = tuple(wrt)
        if key not in self._sensitivity_solvers:
            from fmpy.sundials import CVodeSolver
            request = self._sensitivity_request(wrt)
            system = _Sensitivities(self._fmu, self._derivative_refs,
                                    [v.valueReference for v in self._continuous_states],
                                    self._state_positions, request.input_refs,
                                    request.input_nominals)
            system.load(self._x_full)
            solver = CVodeSolver(nx=system.size, nz=0, get_x=system.get_x, set_x=system.set_x,
                                 get_dx=system.get_dx, get_z=system.get_z,
                                 get_nominals=system.get_nominals, set_time=self._record_time,
                                 input=HeldInputs(), startTime=0.0,
                                 relativeTolerance=self.tolerance,
                                 maxNumSteps=MAX_SOLVER_STEPS)
            self._sensitivity_solvers[key] = (system, solver)
        return self._sensitivity_solvers[key]

    def _output_partials(self, wrt_refs: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """(dy/dx over all continuous states (ny, n), dy/du for ``wrt_refs`` (ny, m))."""
        fmu = self._fmu
        n = self._n_continuous
        ny = len(self._output_vars)
        outputs = {u.variable.name for u in self.model_description.outputs}
        rows = [i for i, v in enumerate(self._output_vars) if v.name in outputs]
        dy_dx = np.zeros((ny, n))
        dy_du = np.zeros((ny, len(wrt_refs)))
        for i, v in enumerate(self._output_vars):
            if v.name not in outputs:  # a continuous state read as an output
                dy_dx[i, self._continuous_states.index(v)] = 1.0
        if rows:
            refs = [self._output_vars[i].valueReference for i in rows]
            knowns = [v.valueReference for v in self._continuous_states] + list(wrt_refs)
            for j, known in enumerate(knowns):
                column = fmu.getDirectionalDerivative(refs, [known], [1.0])
                if j < n:
                    dy_dx[rows, j] = column
                else:
                    dy_du[rows, j - n] = column
        return dy_dx, dy_du

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians | None:
        """
        End values and forward-sensitivity derivatives of B intervals (ME), or None.

        Integrates ``[x, Sx, Su]`` at the model's tolerance, the Jacobian-vector
        products from ``fmi2GetDirectionalDerivative``: in the compiled
        Runge-Kutta driver when :meth:`me_batch_plan` allows it, else with
        CVode.
        Returns None (finite-difference fallback) for Co-Simulation FMUs and
        for Model Exchange FMUs without directional derivatives or with event
        indicators.

        Parameters
        ----------
        x_start : ndarray, shape (B, nx)
            Start state of each interval.
        u : ndarray, shape (B, nu)
            Inputs of each interval, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s].
        wrt_inputs : sequence of int
            Column indices of ``u`` to differentiate with respect to.
        t_start_s : ndarray, shape (B,), optional
            Start time of each interval [s] in the caller's time base (see
            :meth:`~mshoot_core.models.fmi.FmiModel.simulate_intervals`).

        Raises
        ------
        FmuValueError
            If a state or output is not finite (names it and the FMU time).

        """
        plan = self._jacobian_plans.get(tuple(wrt_inputs))
        if plan is None:
            plan = self._jacobian_plan(wrt_inputs)
        if plan.reason is not None:
            logger.debug('interval_jacobians unavailable (%s): finite differences', plan.reason)
            return None
        wrt = plan.wrt
        x_start, u, dt_s = self._check_batch(x_start, u, dt_s)
        t0 = self._fmu_start_times(t_start_s, x_start.shape[0])
        t_end = dt_s if t0 is None else t0 + dt_s  # (the end times, for messages)
        self._plant = None  # the instance is re-initialised: a plant run ends here
        batch, m = x_start.shape[0], len(wrt)
        nx, ny = len(self.state_names), len(self.output_names)
        pos = self._state_positions
        x_end = np.empty((batch, nx))
        y_end = np.empty((batch, ny))
        if self.me_batch_plan() is None:
            done = self._me_batch_in_c(x_start, u, dt_s, x_end, y_end, plan.request,
                                       t_start=t0)
            if done is not False:
                if not math.isfinite(np.add.reduce(x_end, None) + np.add.reduce(y_end, None)):
                    self._check_finite(x_end, y_end, t_end)
                return self._driver_jacobians(plan, x_end, y_end, *done)
        dx_dx0 = np.empty((batch, nx, nx))
        dx_du = np.empty((batch, nx, m))
        dy_dx0 = np.empty((batch, ny, nx))
        dy_du = np.empty((batch, ny, m))
        wrt_refs = [self._input_vars[j].valueReference for j in wrt]
        for b in range(batch):
            start = 0.0 if t0 is None else float(t0[b])
            self._start_interval(x_start[b], u[b], start)
            system, solver = self._sensitivity_solver(wrt)
            self._fmu.getContinuousStates(double_pointer(self._x_full), self._n_continuous)
            system.load(self._x_full)
            solver.reset(start)
            try:
                _, _, t = solver.step(start, start + dt_s)
            except Exception as error:  # noqa: BLE001 - CVode's RuntimeError
                self._diagnose(error, f' (interval from FMU time {start:.9g} s)')
                raise
            self._fmu.setTime(t)
            s = system.matrix()
            sx, su = s[:, :nx], s[:, nx:]  # (n, nx): d x_FMU / d x0_model; (n, m)
            x_end[b], y_end[b] = self._read()
            dy_dx, dy_du_direct = self._output_partials(wrt_refs)
            dx_dx0[b] = sx[pos]
            dx_du[b] = su[pos]
            dy_dx0[b] = dy_dx @ sx
            dy_du[b] = dy_dx @ su + dy_du_direct
        self._check_finite(x_end, y_end, t_end)
        return IntervalJacobians(x_end, y_end, dx_dx0, dx_du, dy_dx0, dy_du)
