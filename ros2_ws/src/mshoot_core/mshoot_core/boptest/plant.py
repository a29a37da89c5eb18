"""
The BOPTEST test case's FMU as a plant: one persistent instance stepped for a whole run.

Stable API (other modules build on it)::

    from mshoot_core.boptest.plant import BoptestPlant, RECORDED, heat_pump_starts
    with BoptestPlant(case) as plant:             # case: TestCase (default TestCase.load())
        plant.start(warmup_start_s)               # instantiate + initialise at FMU time [s]
        plant.advance(start_s)                    # baseline control (no overwrite)
        plant.advance(start_s + 3600, {'oveTSet_u': 294.15})   # overwrite over the hour
        plant.time_s, plant.outputs               # now, and the outputs now (dict)
        table = plant.records()                   # DataFrame: 'time' [s] + RECORDED + overwrites
    heat_pump_starts(table, start_s, end_s)       # -> (count, per day)

FMU time is seconds from 1 January (the clock of the test case's data). :meth:`advance` steps
``fmi2DoStep`` every ``sample_s`` (default 60 s, at most 60 s: BOPTEST's KPIs need a fine grid)
and records :data:`RECORDED` (the KPI outputs, the weather the building sees, the heat pump and
the baseline setpoints) plus the overwrite values applied (NaN where the building's own control
held) after every step; the row of the start time is recorded by :meth:`start`.

Overwrites follow BOPTEST's ``/advance``: a dict of ``X_u`` input -> value applied (held) over the
advance, each with its ``X_activate`` Boolean set true; every overwrite input *not* in the dict
(or given as None) is released to the building's own controller (``X_activate`` false). Unknown
names and values outside the input's declared [min, max] raise :class:`ValueError`.

The FMU allows one instance per process (``canBeInstantiatedOnlyOncePerProcess``): starting a
plant while another one of this process holds an instance raises :class:`RuntimeError`; close it
first (:meth:`BoptestPlant.close`, or use the plant as a context manager).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core import fmu_cache
from mshoot_core.boptest.testcase import load_shim, TestCase

logger = logging.getLogger(__name__)

#: Outputs recorded at every step (those the KPIs, the figures and the identification read).
RECORDED = ('reaTZon_y', 'reaPHeaPum_y', 'reaPFan_y', 'reaPPumEmi_y', 'reaCO2RooAir_y',
            'weaSta_reaWeaTDryBul_y', 'weaSta_reaWeaHGloHor_y', 'reaHeaPumY_y', 'reaCOP_y',
            'reaQFloHea_y', 'reaQHeaPumCon_y', 'reaTSetHea_y', 'reaTSetCoo_y', 'reaTSet_y',
            'reaTSup_y', 'reaTRet_y', 'reaPum_y', 'reaFan_y')
#: Largest step between two recorded samples [s].
MAX_SAMPLE_S = 60.0
#: Modulation above which the heat pump counts as on [-] (:func:`heat_pump_starts`).
ON_THRESHOLD = 0.01
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
        The value input (``oveTSet_u``).
    activate : str
        Its Boolean switch (``oveTSet_activate``).
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


class BoptestPlant:
    """
    The test case's FMU, one persistent ``fmpy.fmi2.FMU2Slave`` instance (see the module).

    Parameters
    ----------
    case : TestCase, optional
        The test case; default :meth:`TestCase.load`.
    record : sequence of str, optional
        Outputs recorded at every step; default :data:`RECORDED`.

    Attributes
    ----------
    inputs : dict of str to OverwriteInput
        The overwrite inputs by value name (``oveTSet_u``, ``oveHeaPumY_u``, ``ovePum_u``,
        ``oveFan_u``).
    outputs_available : list of str
        Every output of the FMU.

    """

    def __init__(self, case: TestCase | None = None,
                 record: Sequence[str] | None = None) -> None:
        import fmpy  # noqa: F401 (imported where used)
        self.case = case if case is not None else TestCase.load()
        load_shim(self.case.directory)
        self._unzipped = fmu_cache.extract_fmu(self.case.fmu_path)
        self.model_description = fmpy.read_model_description(
            str(self._unzipped), validate=False)
        variables = {v.name: v for v in self.model_description.modelVariables}
        self._refs = {name: v.valueReference for name, v in variables.items()}
        self.outputs_available = [v.name for v in self.model_description.modelVariables
                                  if v.causality == 'output']
        self.inputs: dict[str, OverwriteInput] = {}
        for v in self.model_description.modelVariables:
            if v.causality != 'input' or not v.name.endswith('_u'):
                continue
            activate = v.name[:-2] + '_activate'
            if activate not in variables:
                continue
            self.inputs[v.name] = OverwriteInput(
                v.name, activate, v.unit or '',
                float(v.min) if v.min is not None else -math.inf,
                float(v.max) if v.max is not None else math.inf, v.description or '')
        self.recorded = tuple(record) if record is not None else RECORDED
        unknown = [n for n in self.recorded if n not in self.outputs_available]
        if unknown:
            raise ValueError(f'not outputs of {self.case.name}: {unknown}; outputs: '
                             f'{self.outputs_available}')
        self._record_refs = [self._refs[n] for n in self.recorded]
        self._fmu = None
        self._time_s: float | None = None
        self._applied: dict[str, float] = {}
        self._rows: list[list[float]] = []
        self._last: list[float] = []

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """Whether this plant holds an FMU instance."""
        return self._fmu is not None

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
        from fmpy.fmi2 import FMU2Slave
        if not (math.isfinite(t0_s) and t0_s >= 0):
            raise ValueError(f'expected a start time >= 0 s, got {t0_s!r}')
        with _instance_lock:
            if _instance_owner:
                which = 'this plant' if _instance_owner[0] is self else 'another BoptestPlant'
                raise RuntimeError(f'{which} of this process holds the instance of '
                                   f'{self.case.name} (one instance per process): close it first')
            md = self.model_description
            fmu = FMU2Slave(guid=md.guid, unzipDirectory=str(self._unzipped),
                            modelIdentifier=md.coSimulation.modelIdentifier,
                            instanceName='boptest')
            fmu.instantiate()
            _instance_owner.append(self)
        self._fmu = fmu
        try:
            fmu.setupExperiment(startTime=float(t0_s))
            fmu.enterInitializationMode()
            fmu.exitInitializationMode()
        except BaseException:
            self.close()
            raise
        self._time_s = float(t0_s)
        self._applied = {}
        self._rows = []
        self._record()
        logger.debug('%s started at t = %g s', self.case.name, t0_s)
        return self.outputs

    def close(self) -> None:
        """Terminate and free the instance (idempotent); the records stay."""
        fmu, self._fmu = self._fmu, None
        if fmu is None:
            return
        try:
            try:
                fmu.terminate()
            finally:
                fmu.freeInstance()
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
        fmu = self._fmu
        for name, spec in self.inputs.items():
            if name in active:
                fmu.setReal([self._refs[name]], [active[name]])
                fmu.setBoolean([self._refs[spec.activate]], [True])
            else:
                fmu.setBoolean([self._refs[spec.activate]], [False])
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
        if self._fmu is None:
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
            self._fmu.doStep(currentCommunicationPoint=self._time_s,
                             communicationStepSize=t_next - self._time_s)
            self._time_s = t_next
            self._record()
        return self.outputs

    def _record(self) -> None:
        values = self._fmu.getReal(self._record_refs)
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
        if self._fmu is None:
            raise RuntimeError('the plant is not running: call start() first')
        unknown = [n for n in names if n not in self._refs]
        if unknown:
            raise ValueError(f'unknown variables of {self.case.name}: {unknown}')
        return dict(zip(names, self._fmu.getReal([self._refs[n] for n in names])))

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


def heat_pump_starts(records: pd.DataFrame, start_s: float | None = None,
                     end_s: float | None = None, threshold: float = ON_THRESHOLD,
                     column: str = 'reaHeaPumY_y') -> tuple[int, float]:
    """
    Count the heat pump's starts: off -> on transitions of its modulation.

    A start is a sample above ``threshold`` whose previous sample is at or below it; only
    starts at sample times in (start_s, end_s] count.

    Parameters
    ----------
    records : pd.DataFrame
        A record table (:meth:`BoptestPlant.records`) with ``time`` [s] and ``column``.
    start_s, end_s : float, optional
        The window [s]; default the table's span.
    threshold : float
        Modulation above which the heat pump is on [-].
    column : str
        The modulation column.

    Returns
    -------
    tuple of (int, float)
        The number of starts and the starts per day of the window.

    Raises
    ------
    ValueError
        For missing columns or an empty window.

    """
    for name in ('time', column):
        if name not in records.columns:
            raise ValueError(f'the record table lacks the column {name!r}')
    times = records['time'].to_numpy(dtype=float)
    on = records[column].to_numpy(dtype=float) > threshold
    t0 = times[0] if start_s is None else float(start_s)
    t1 = times[-1] if end_s is None else float(end_s)
    if not t1 > t0:
        raise ValueError(f'empty window [{t0:g}, {t1:g}] s')
    rising = np.zeros_like(on)
    rising[1:] = on[1:] & ~on[:-1]
    inside = (times > t0 + _EPS_S) & (times <= t1 + _EPS_S)
    count = int(np.count_nonzero(rising & inside))
    return count, count / ((t1 - t0) / 86400.0)
