"""
A BOPTEST test case's FMU as a plant: one persistent instance stepped for a whole run.

Stable API (other modules build on it)::

    from mshoot_core.boptest.plant import BoptestPlant, run_period, run_span
    with BoptestPlant(case) as plant:             # case: TestCase
        plant.start(warmup_start_s)               # instantiate + initialise at FMU time [s]
        plant.advance(start_s)                    # baseline control (no overwrite)
        plant.advance(start_s + 3600, {'<X>_u': value})   # overwrite X over the hour
        plant.time_s, plant.outputs               # now, and the outputs now (dict)
        table = plant.records()                   # DataFrame: 'time' [s] + recorded + overwrites
    run = run_period(case, 'peak_heat_day', controller=None)   # baseline; PeriodRun
    run = run_period(case, 'peak_heat_day', lambda t_s, outputs: {'<X>_u': value})
    run = run_span(case, warmup_start_s, start_s, end_s, policy)  # any span of the year

The FMU is Co-Simulation or Model Exchange (Co-Simulation when it has both), run by one
:class:`~mshoot_core.models.fmi.FmiModel` as its plant (:mod:`mshoot_core.models.fmi_plant`:
``fmi2DoStep``, or CVode with the FMU's events and no stop time). Co-Simulation FMUs keep their
own integrator tolerance (BOPTEST gives them none); Model Exchange is integrated at
``tolerance`` (default :data:`ME_TOLERANCE`).

FMU time is seconds from 1 January (the clock of the test case's data). :meth:`advance` steps
every ``sample_s`` (default 60 s, at most 60 s: BOPTEST's KPIs need a fine grid) and records
the outputs :attr:`BoptestPlant.recorded` (default: every output of the FMU, as BOPTEST stores
them; or those a caller names, e.g. :func:`recorded_outputs` of a card and ``kpis.json``) plus
the overwrite values applied (NaN where the building's own control held) after every step; the
row of the start time is recorded by :meth:`start`.

Overwrites follow BOPTEST's ``/advance``: a dict of ``X_u`` input -> value applied (held) over the
advance, each with its ``X_activate`` Boolean set true; every overwrite input *not* in the dict
(or given as None) is released to the building's own controller (``X_activate`` false). Unknown
names and values outside the input's declared [min, max] raise :class:`ValueError`.

BOPTEST's FMUs allow one instance per process (``canBeInstantiatedOnlyOncePerProcess``):
starting a plant while another one of this process holds an instance raises
:class:`RuntimeError`; close it first (:meth:`BoptestPlant.close`, or use the plant as a
context manager).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core import fmu_cache
from mshoot_core.boptest.testcase import shim_libraries, TestCase
from mshoot_core.models.fmu_variables import fmu_variables
from mshoot_core.period_loop import LoopRun, run_steps, step_count

logger = logging.getLogger(__name__)

#: Largest step between two recorded samples [s].
MAX_SAMPLE_S = 60.0
#: Relative tolerance of the Model Exchange integration (CVode) [-].
ME_TOLERANCE = 1e-6
#: Time tolerance [s].
_EPS_S = 1e-6

_instance_lock = threading.Lock()
_instance_owner: list[BoptestPlant] = []


@dataclasses.dataclass(frozen=True)
class OverwriteInput:
    """
    One BOPTEST overwrite input pair.

    Attributes
    ----------
    name : str
        The value input (``X_u``).
    activate : str
        Its Boolean switch (``X_activate``).
    unit : str
        Declared unit ('' if none).
    lower, upper : float
        Declared range [min, max] (-inf/inf if none).
    description : str
        The FMU's description.

    """

    name: str
    activate: str
    unit: str
    lower: float
    upper: float
    description: str


def recorded_outputs(case: TestCase, variables: Iterable[str] = ()) -> list[str]:
    """
    Return what a run must record: the outputs ``kpis.json`` names, then ``variables``.

    Parameters
    ----------
    case : TestCase
        The test case.
    variables : iterable of str
        More FMU outputs (e.g. the variables a card maps).

    """
    return list(dict.fromkeys([*case.kpi_output_names, *variables]))


class BoptestPlant:
    """
    A test case's FMU as one persistent plant instance (see the module).

    Parameters
    ----------
    case : TestCase, optional
        The test case; default :meth:`TestCase.load`.
    record : sequence of str, optional
        Outputs recorded at every step; default every output of the FMU.
    tolerance : float
        Relative tolerance of a Model Exchange integration [-].

    Attributes
    ----------
    inputs : dict of str to OverwriteInput
        The overwrite inputs by value name (``X_u``).
    outputs_available : list of str
        Every output of the FMU.
    interface : str
        'CoSimulation' or 'ModelExchange'.
    model_description : fmpy ModelDescription
        The FMU's, shared with every reader of it in the process
        (:func:`~mshoot_core.models.fmi.read_cached_description`): read only.

    """

    def __init__(self, case: TestCase | None = None, record: Sequence[str] | None = None,
                 tolerance: float = ME_TOLERANCE) -> None:
        from mshoot_core.models.fmi import read_cached_description
        self.case = case if case is not None else TestCase.load()
        self.tolerance = float(tolerance)
        self._unzipped = fmu_cache.extract_fmu(self.case.fmu_path)
        self.model_description = read_cached_description(
            self._unzipped, self.case.fmu_path.name, validate=False)
        md = self.model_description
        self.interface = 'CoSimulation' if md.coSimulation is not None else 'ModelExchange'
        variables = fmu_variables(md)
        names = {v.name for v in variables}
        descriptions = {v.name: v.description or '' for v in md.modelVariables}
        self.outputs_available = [v.name for v in variables if v.causality == 'output']
        self.inputs: dict[str, OverwriteInput] = {}
        for v in variables:
            if v.causality != 'input' or not v.name.endswith('_u'):
                continue
            activate = v.name[:-2] + '_activate'
            if activate not in names:
                continue
            self.inputs[v.name] = OverwriteInput(
                v.name, activate, v.unit, -math.inf if v.min is None else v.min,
                math.inf if v.max is None else v.max, descriptions[v.name])
        self.recorded = (tuple(record) if record is not None
                         else tuple(self.outputs_available))
        unknown = [n for n in self.recorded if n not in self.outputs_available]
        if unknown:
            raise ValueError(f'not outputs of {self.case.name}: {unknown}; outputs: '
                             f'{self.outputs_available}')
        self._model: Any = None
        self._time_s: float | None = None
        self._applied: dict[str, float] = {}
        self._switches: dict[str, float | bool] = {}
        self._rows: list[list[float]] = []
        self._last: list[float] = []

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """Whether this plant holds an FMU instance."""
        return self._model is not None

    @property
    def time_s(self) -> float | None:
        """FMU time now [s from 1 January], None before :meth:`start`."""
        return self._time_s

    def start(self, t0_s: float) -> dict[str, float]:
        """
        Instantiate and initialise the FMU at ``t0_s``; record the first row.

        Parameters
        ----------
        t0_s : float
            Start time [s from 1 January], >= 0.

        Returns
        -------
        dict of str to float
            The recorded outputs at ``t0_s``.

        Raises
        ------
        RuntimeError
            If this or another plant of this process holds an instance.
        ValueError
            For a negative or non-finite time.

        """
        from mshoot_core.models.fmi import FmiModel
        if not (math.isfinite(t0_s) and t0_s >= 0):
            raise ValueError(f'expected a start time >= 0 s, got {t0_s!r}')
        with _instance_lock:
            if _instance_owner:
                which = 'this plant' if _instance_owner[0] is self else 'another BoptestPlant'
                raise RuntimeError(f'{which} of this process holds the instance of '
                                   f'{self.case.name} (one instance per process): close it first')
            model = FmiModel(self.case.fmu_path, inputs=[], states=[],
                             outputs=list(self.recorded),
                             tolerance=self.tolerance, fmi_type=self.interface,
                             instance_name='boptest', validate=False,
                             libraries=shim_libraries(self.case.directory), own_tolerance=True)
            _instance_owner.append(self)
        self._model = model
        try:
            _, values = model.plant_start([], float(t0_s), [])
        except BaseException:
            self.close()
            raise
        self._time_s = float(t0_s)
        self._applied = {}
        self._switches = {}
        self._rows = []
        self._record(values)
        logger.debug('%s started at t = %g s (%s)', self.case.name, t0_s, self.interface)
        return self.outputs

    def close(self) -> None:
        """Terminate and free the instance (idempotent); the records stay."""
        model, self._model = self._model, None
        if model is None:
            return
        try:
            try:
                model.fmu.terminate()
            finally:
                model.close()
        finally:
            with _instance_lock:
                if self in _instance_owner:
                    _instance_owner.remove(self)

    def __enter__(self) -> BoptestPlant:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover (best effort)
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass

    # -- overwrites ----------------------------------------------------------------------------
    def check_overwrites(self, overwrites: Mapping[str, float | None] | None
                         ) -> dict[str, float]:
        """
        Validate overwrites; return the active ones as name -> float.

        Raises
        ------
        ValueError
            For an unknown name, a non-finite value or one outside the declared range.
        TypeError
            For a non-mapping.

        """
        if overwrites is None:
            return {}
        if not isinstance(overwrites, Mapping):
            raise TypeError(f'overwrites must be a mapping name -> value, got '
                            f'{type(overwrites).__name__}')
        active = {}
        for name, value in overwrites.items():
            if name not in self.inputs:
                raise ValueError(f'unknown overwrite input {name!r}: expected one of '
                                 f'{sorted(self.inputs)} (the *_activate switches are set '
                                 'automatically)')
            if value is None:
                continue
            spec = self.inputs[name]
            number = float(value)
            if not math.isfinite(number) or number < spec.lower or number > spec.upper:
                raise ValueError(f'{name} = {value!r} outside its range [{spec.lower:g}, '
                                 f'{spec.upper:g}] {spec.unit}'.rstrip())
            active[name] = number
        return active

    def _apply(self, active: dict[str, float]) -> None:
        """Set the overwrites and switches that change (each change an event in ME)."""
        wanted: dict[str, float | bool] = {}
        for name, spec in self.inputs.items():
            if name in active:
                wanted[name] = active[name]
            wanted[spec.activate] = name in active
        changed = {k: v for k, v in wanted.items() if self._switches.get(k) != v}
        if changed:
            self._model.plant_set(changed)
            self._switches.update(changed)
        self._applied = active

    # -- stepping ------------------------------------------------------------------------------
    def advance(self, to_s: float, overwrites: Mapping[str, float | None] | None = None,
                sample_s: float = MAX_SAMPLE_S) -> dict[str, float]:
        """
        Advance the plant to ``to_s``, overwrites held, recording every ``sample_s``.

        Parameters
        ----------
        to_s : float
            End time [s from 1 January], >= :attr:`time_s`.
        overwrites : dict of str to float or None, optional
            ``X_u`` input -> value (see the module); None or {}: the building's own control.
        sample_s : float
            Step of ``fmi2DoStep`` and of the records [s], in (0, 60]; the last step is
            shorter when the span is not a multiple.

        Returns
        -------
        dict of str to float
            The recorded outputs at ``to_s``.

        Raises
        ------
        RuntimeError
            Before :meth:`start` or after :meth:`close`.
        ValueError
            For bad overwrites, a time in the past or a bad sample step.

        """
        if self._model is None:
            raise RuntimeError('the plant is not running: call start() first')
        if not (math.isfinite(sample_s) and 0 < sample_s <= MAX_SAMPLE_S):
            raise ValueError(f'expected 0 < sample_s <= {MAX_SAMPLE_S:g} s, got {sample_s!r}')
        if not math.isfinite(to_s) or to_s < self._time_s - _EPS_S:
            raise ValueError(f'cannot advance to {to_s!r} s: the plant is at {self._time_s:g} s')
        self._apply(self.check_overwrites(overwrites))
        t_begin = self._time_s
        steps = max(0, math.ceil((to_s - t_begin) / sample_s - 1e-9))
        for k in range(steps):
            t_next = min(t_begin + (k + 1) * sample_s, to_s)
            _, values = self._model.plant_step([], t_next - self._time_s)
            self._time_s = t_next
            self._record(values)
        return self.outputs

    def _record(self, values: np.ndarray) -> None:
        values = [float(v) for v in values]
        self._last = values
        applied = [self._applied.get(name, math.nan) for name in self.inputs]
        self._rows.append([self._time_s, *values, *applied])

    @property
    def outputs(self) -> dict[str, float]:
        """Return the recorded outputs at :attr:`time_s` (name -> value)."""
        return dict(zip(self.recorded, self._last))

    def read(self, names: Sequence[str]) -> dict[str, float]:
        """
        Read any Real variables of the FMU now.

        Raises
        ------
        ValueError
            For an unknown name.
        RuntimeError
            When not running.

        """
        if self._model is None:
            raise RuntimeError('the plant is not running: call start() first')
        return self._model.plant_get(list(names))

    def drop_records(self) -> None:
        """Forget the rows recorded so far (a long run kept in pieces); the plant runs on."""
        self._rows = []

    def records(self, start_s: float | None = None, end_s: float | None = None) -> pd.DataFrame:
        """
        Return the record table.

        Parameters
        ----------
        start_s, end_s : float, optional
            Keep rows with start_s <= time <= end_s [s].

        Returns
        -------
        pd.DataFrame
            Columns ``time`` [s from 1 January], the recorded outputs (FMU units: K, W, ppm,
            W/m2, -) and the overwrite inputs applied over the step ending at the row (NaN where
            the building's own control held; NaN at the start row); a RangeIndex.

        """
        columns = ['time', *self.recorded, *self.inputs]
        table = pd.DataFrame(np.asarray(self._rows, dtype=float).reshape(-1, len(columns)),
                             columns=columns)
        keep = np.ones(len(table), dtype=bool)
        if start_s is not None:
            keep &= table['time'].to_numpy() >= start_s - _EPS_S
        if end_s is not None:
            keep &= table['time'].to_numpy() <= end_s + _EPS_S
        return table[keep].reset_index(drop=True)


#: A step policy of :func:`run_period`: (time [s], outputs now) -> the overwrites over the next
#: control step (None: the building's own control), or the step's pieces
#: ``[(end time [s], overwrites), ...]`` in order, the last ending at the step's end.
StepPolicy = Callable[[float, Mapping[str, float]], Any]


@dataclasses.dataclass
class PeriodRun(LoopRun):
    """
    One run of :func:`run_span` (or :func:`run_period`): a :class:`LoopRun` with the records.

    Attributes
    ----------
    records : pd.DataFrame
        The whole record table, warm-up included (:meth:`BoptestPlant.records`).
    warmup_start_s, start_s, end_s : float
        The period [s from 1 January].
    step_wall_s : list of float
        The controller's wall time at each control step of the test period [s] (keyword).
    wall_s : float
        Wall time of the whole run, warm-up included [s] (keyword).

    """

    records: pd.DataFrame
    warmup_start_s: float
    start_s: float
    end_s: float


def run_period(case: TestCase, period: str, controller: StepPolicy | None = None,
               warmup_days: float = 7.0, length_days: float = 14.0,
               control_step_s: float | None = None,
               sample_s: float = MAX_SAMPLE_S,
               record: Sequence[str] | None = None) -> PeriodRun:
    """
    Run a test period in this process: warm-up under the building's own control, then the test.

    :func:`run_span` over the period's times (:meth:`TestCase.test_period`).

    Parameters
    ----------
    case : TestCase
        The test case.
    period : str
        A test period (:meth:`TestCase.test_period`).
    controller, control_step_s, sample_s, record
        As :func:`run_span`.
    warmup_days, length_days : float
        Warm-up and test period lengths [days] (BOPTEST: 7 and 14).

    Returns
    -------
    PeriodRun

    """
    warmup_start, start, end = case.test_period(period, warmup_days, length_days)
    return run_span(case, warmup_start, start, end, controller, control_step_s, sample_s,
                    record, label=period)


def run_span(case: TestCase, warmup_start_s: float, start_s: float, end_s: float,
             controller: StepPolicy | None = None, control_step_s: float | None = None,
             sample_s: float = MAX_SAMPLE_S, record: Sequence[str] | None = None,
             label: str = '') -> PeriodRun:
    """
    Run the plant from ``warmup_start_s``: its own control up to ``start_s``, then controlled.

    The one period loop of every controller on a test case's FMU: the baseline (None), a
    rule, the MPC (:class:`~mshoot_core.boptest.supervision.SupervisedPlant`), the
    identification's excitation (:func:`mshoot_core.identification.excite_test_case`). A
    controller with an ``observe(plant)`` method observes the plant at the start and at the end
    of every control step, the warm-up's included (then the warm-up runs in control steps from
    its start); every control step from ``start_s`` to ``end_s`` it is called for the step's
    overwrites. The steps go through the one period loop
    (:func:`mshoot_core.period_loop.run_steps`: its progress lines and wall times).

    Parameters
    ----------
    case : TestCase
        The test case.
    warmup_start_s, start_s, end_s : float
        Plant start, first controlled step, end [s from 1 January], in this order.
    controller : callable, optional
        ``controller(t_s, outputs)`` called at every control step from ``start_s``: the
        overwrites held over the step, or the step's pieces (see :data:`StepPolicy`); None:
        the baseline (no overwrite).
    control_step_s : float, optional
        Control step [s]; default the test case's (3600 s).
    sample_s : float
        Record step [s], <= 60.
    record : sequence of str, optional
        The outputs recorded (:class:`BoptestPlant`; default every output).
    label : str
        Names the run in the progress lines.

    Returns
    -------
    PeriodRun

    Raises
    ------
    ValueError
        For a bad control step or times, or pieces that do not end at the step's end in order.

    """
    warmup_start, start, end = float(warmup_start_s), float(start_s), float(end_s)
    step = case.control_step_s if control_step_s is None else float(control_step_s)
    if not step > 0:
        raise ValueError(f'expected a positive control step, got {control_step_s!r}')
    if not 0.0 <= warmup_start <= start < end:
        raise ValueError(f'expected 0 <= warm-up start <= start < end, got {warmup_start:g}, '
                         f'{start:g}, {end:g} s')
    observe = getattr(controller, 'observe', None)
    name = label or case.name
    began = time.perf_counter()
    with BoptestPlant(case, record=record) as plant:

        def look(t_s: float) -> None:
            observe(plant)

        def own_control(t_s: float, t_next: float, decided: None) -> None:
            plant.advance(t_next, sample_s=sample_s)

        def overwrite(t_s: float, t_next: float, decided: Any) -> None:
            for piece_end, overwrites in _pieces(decided, t_s, t_next):
                plant.advance(piece_end, overwrites, sample_s=sample_s)

        plant.start(warmup_start)
        if observe is None:  # the warm-up in one go
            plant.advance(start, sample_s=sample_s)
        else:  # the warm-up observed step by step
            run_steps(warmup_start, start, step, own_control, observe=look,
                      label=f'{name} warm-up')
        loop = run_steps(start, end, step, overwrite, observe=look if observe else None,
                         decide=lambda t_s: controller(t_s, plant.outputs) if controller
                         else None, label=name)
        if observe is not None:  # the plant at the end of the last step
            observe(plant)
        records = plant.records()
    wall = time.perf_counter() - began
    logger.info('%s on %s: %d steps of %g s in %.1f s', name, case.name,
                step_count(start, end, step), step, wall)
    return PeriodRun(records, warmup_start, start, end, step_wall_s=loop.step_wall_s,
                     wall_s=wall)


def _pieces(decided: Any, t_s: float, t_next: float) -> list[tuple[float, Any]]:
    """Return a controller's answer as pieces (end time [s], overwrites) up to ``t_next``."""
    if decided is None or isinstance(decided, Mapping):
        return [(t_next, decided)]
    pieces = [(float(e), o) for e, o in decided]
    ends = [t_s] + [e for e, _ in pieces]
    if not pieces or any(b <= a for a, b in zip(ends, ends[1:])) or \
            abs(pieces[-1][0] - t_next) > _EPS_S:
        raise ValueError(f'the pieces of the step at {t_s:g} s must end in order at '
                         f'{t_next:g} s, got ends {ends[1:]}')
    return pieces
