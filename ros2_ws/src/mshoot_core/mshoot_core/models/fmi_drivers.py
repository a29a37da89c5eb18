"""
ctypes bindings of the batch drivers ``fmu_src/cs_batch.c`` and ``fmu_src/me_batch.c``.

A driver runs a batch of independent intervals of one FMU instance in one C
loop, calling the FMU's own functions (taken from the library fmpy loaded for
the instance), so that a batch costs one Python call instead of dozens per
interval:

- :class:`CsBatchDriver`: per interval ``fmi2Reset``, parameters, start
  values, initialisation with the inputs at the interval's start time, one
  ``fmi2DoStep``, read;
- :class:`MeBatchDriver`: per interval the restore of an FMU state and the
  interval's start time (or a reset and initialisation at that time), an
  input event, and an explicit Dormand-Prince 5(4) integration over the
  interval, optionally with the forward sensitivities (:class:`SensitivityRequest`).

Both take optional per-interval FMU start times (``t_start``; None: every
interval at FMU time 0).

``make setup`` builds the drivers (:mod:`mshoot_core.fmu_build`); here they
are only found (:func:`mshoot_core.fmu_cache.find_driver`): a missing driver
raises :class:`~mshoot_core.fmu_cache.NotBuiltError` naming the file and the
command that builds it, it never falls back to a slower path. Also here: the
ctypes arrays and pointers the FMI calls take.
"""
from __future__ import annotations

import ctypes
import dataclasses
import logging
from typing import Any, Sequence

from fmpy.fmi2 import FMU2Model, FMU2Slave
import numpy as np

from mshoot_core.fmu_cache import find_driver

logger = logging.getLogger(__name__)

DOUBLE_P = ctypes.POINTER(ctypes.c_double)
VR_P = ctypes.POINTER(ctypes.c_uint)
SIZE_P = ctypes.POINTER(ctypes.c_size_t)


def size_array(values: Sequence[int]) -> ctypes.Array:
    """Return a ``size_t`` array of ``values`` (at least one element)."""
    return (ctypes.c_size_t * max(len(values), 1))(*values)


def real_array(values: Sequence[float]) -> ctypes.Array:
    """Return an ``fmi2Real`` (double) array of ``values``."""
    return (ctypes.c_double * len(values))(*values)


def vr_array(refs: Sequence[int]) -> ctypes.Array:
    """Return an ``fmi2ValueReference`` (unsigned int) array of ``refs``."""
    return (ctypes.c_uint * len(refs))(*refs)


def double_pointer(array: np.ndarray) -> Any:
    """Return a ``double *`` to the data of the contiguous float64 ``array`` (no copy)."""
    return array.ctypes.data_as(DOUBLE_P)


def address(array: np.ndarray | None) -> int | None:
    """
    Return the data address of a C-contiguous float64 ``array``, or None (NULL).

    For a ``const double *`` argument; the caller keeps ``array`` alive (e.g. from
    :func:`~mshoot_core.models.base.interval_start_times`).
    """
    return None if array is None else array.__array_interface__['data'][0]


def _address(array: np.ndarray) -> int:
    """
    Return the address of the data of the contiguous ``array`` (no copy).

    For an argument the driver declares as ``void *``: half the cost of a typed pointer
    (:func:`double_pointer`), and nothing to keep alive beyond ``array`` itself, which the caller
    holds for the call.
    """
    return array.ctypes.data


def _bind(fmu: FMU2Model | FMU2Slave, names: Sequence[str],
          optional: bool = False) -> list[int | None]:
    """Addresses of the FMU's functions ``names``; with ``optional``, None where not exported."""
    return [ctypes.cast(getattr(fmu.dll, name), ctypes.c_void_p)
            if not optional or hasattr(fmu.dll, name) else None for name in names]


# -- Co-Simulation -----------------------------------------------------------------------------
class CsApi(ctypes.Structure):
    """The FMI functions the Co-Simulation driver calls (``mshoot_cs_api``)."""

    _fields_ = [(name, ctypes.c_void_p) for name in (
        'reset', 'set_real', 'get_real', 'setup_experiment', 'enter_initialization',
        'exit_initialization', 'do_step')]


CS_FUNCTIONS = ('fmi2Reset', 'fmi2SetReal', 'fmi2GetReal', 'fmi2SetupExperiment',
                'fmi2EnterInitializationMode', 'fmi2ExitInitializationMode', 'fmi2DoStep')


class CsBatchDriver:
    """
    The batched Co-Simulation driver bound to one FMU's functions.

    Parameters
    ----------
    fmu : FMU2Slave
        The fmpy instance whose library provides the FMI functions.
    label : str
        Name of the FMU in error messages.

    Raises
    ------
    NotBuiltError
        If the driver is not built (``make setup``).

    """

    def __init__(self, fmu: FMU2Slave, label: str) -> None:
        self.path = find_driver('cs')
        self.label = label
        library = ctypes.CDLL(str(self.path))
        self._batch = library.mshoot_cs_batch
        self._batch.restype = ctypes.c_long
        size, real, ptr = ctypes.c_size_t, ctypes.c_double, ctypes.c_void_p
        self._batch.argtypes = [ptr, ptr, size, real, ctypes.c_int, real,
                                size, ptr, ptr, size, ptr, ptr, size, ptr, ptr,
                                size, ptr, ptr, size, ptr, ptr, ptr]
        self._library = library
        self._api = CsApi(*_bind(fmu, CS_FUNCTIONS))
        self._api_address = ctypes.addressof(self._api)  # the structure lives with self

    def run(self, component: Any, dt_s: float, tolerance: float | None,
            par_refs: ctypes.Array, par_values: ctypes.Array, start_refs: ctypes.Array,
            starts: np.ndarray, input_refs: ctypes.Array, inputs: np.ndarray,
            state_refs: ctypes.Array, x_end: np.ndarray, output_refs: ctypes.Array,
            y_end: np.ndarray, t_start: np.ndarray | None = None) -> None:
        """
        Run B intervals of ``dt_s`` [s]; fill ``x_end`` (B, nx) and ``y_end`` (B, ny).

        ``starts`` (B, len(start_refs)) are the start values of the states set
        before initialisation, ``inputs`` (B, len(input_refs)) the inputs
        held over each interval, ``t_start`` (B,) the FMU start times [s]
        (None: 0); all float64 and C-contiguous.

        Raises
        ------
        RuntimeError
            If an FMI call fails (the message names the call and the interval).

        """
        code = self._batch(
            self._api_address, component, x_end.shape[0], dt_s,
            tolerance is not None, tolerance or 0.0,
            len(par_refs), par_refs, par_values,
            len(start_refs), start_refs, _address(starts),
            len(input_refs), input_refs, _address(inputs),
            len(state_refs), state_refs, _address(x_end),
            len(output_refs), output_refs, _address(y_end), address(t_start))
        if code:
            raise RuntimeError(f'{self.label}: FMI call {code % 16 - 1} of interval '
                               f'{code // 16} failed in the batched driver '
                               f'(0 reset, 1 parameters, 2 start states, 3 setup, 4 enter '
                               f'init, 5 inputs, 6 exit init, 7 doStep, 8/9 read)')


# -- Model Exchange ----------------------------------------------------------------------------
class MeApi(ctypes.Structure):
    """The FMI functions the Model Exchange driver calls (``mshoot_me_api``)."""

    _fields_ = [(name, ctypes.c_void_p) for name in (
        'reset', 'set_real', 'get_real', 'setup_experiment', 'enter_initialization',
        'exit_initialization', 'set_fmu_state', 'enter_event_mode', 'new_discrete_states',
        'enter_continuous_time_mode', 'completed_integrator_step', 'set_time',
        'set_continuous_states', 'get_derivatives', 'get_continuous_states', 'get_nominals',
        'get_directional_derivative')]


ME_FUNCTIONS = ('fmi2Reset', 'fmi2SetReal', 'fmi2GetReal', 'fmi2SetupExperiment',
                'fmi2EnterInitializationMode', 'fmi2ExitInitializationMode', 'fmi2SetFMUstate',
                'fmi2EnterEventMode', 'fmi2NewDiscreteStates', 'fmi2EnterContinuousTimeMode',
                'fmi2CompletedIntegratorStep', 'fmi2SetTime', 'fmi2SetContinuousStates',
                'fmi2GetDerivatives', 'fmi2GetContinuousStates',
                'fmi2GetNominalsOfContinuousStates', 'fmi2GetDirectionalDerivative')


class MeProblem(ctypes.Structure):
    """What is common to the intervals of a Model Exchange batch (``mshoot_me_problem``)."""

    _fields_ = [('snapshot', ctypes.c_void_p), ('needs_completed_step', ctypes.c_int),
                ('tolerance', ctypes.c_double), ('dt', ctypes.c_double),
                ('max_steps', ctypes.c_size_t), ('n', ctypes.c_size_t),
                ('cstate_vr', VR_P), ('derivative_vr', VR_P),
                ('nx', ctypes.c_size_t), ('x_pos', SIZE_P),
                ('x_vr', VR_P), ('ny', ctypes.c_size_t), ('y_vr', VR_P),
                ('n_in', ctypes.c_size_t), ('in_vr', VR_P),
                ('n_par', ctypes.c_size_t), ('par_vr', VR_P), ('par_val', DOUBLE_P),
                ('n_start', ctypes.c_size_t), ('start_vr', VR_P),
                ('start_idx', SIZE_P),
                ('n_su', ctypes.c_size_t), ('su_vr', VR_P), ('su_nominal', DOUBLE_P),
                ('sensitivity_factor', ctypes.c_double), ('sensitivities', ctypes.c_int),
                ('n_yo', ctypes.c_size_t), ('yo_vr', VR_P), ('chain', ctypes.c_size_t)]


@dataclasses.dataclass(frozen=True)
class SensitivityRequest:
    """
    Forward sensitivities the Model Exchange driver integrates along with the states.

    The columns are the model states', then those of the inputs ``input_refs``;
    the absolute tolerance of S_ij is ``nominal_factor * x_nom_i / nom_j``.

    Attributes
    ----------
    input_refs : tuple of int
        Value references of the inputs to differentiate with respect to.
    input_nominals : tuple of float
        Their nominal values (same units as the inputs).
    nominal_factor : float
        Tightening of the sensitivities' absolute tolerances relative to the states'.

    """

    input_refs: tuple[int, ...]
    input_nominals: tuple[float, ...]
    nominal_factor: float


#: Negative return codes of the Model Exchange driver that send the batch to CVode.
ME_GAVE_UP = {-1: 'a time event inside the interval', -2: 'a step event',
              -3: 'more than {max_steps} steps in one interval (stiff?)',
              -4: 'a step size underflow', -5: 'out of memory',
              -7: 'an FMI function it needs is not exported'}
#: Return code of the Model Exchange driver when the FMU requests termination.
ME_TERMINATE = -6
#: Stages of the FMI calls in the Model Exchange driver's error codes (16 * interval + stage + 1).
ME_STAGES = ('restore/reset', 'parameters', 'start values', 'setup', 'enter init', 'inputs',
             'exit init', 'event iteration', 'continuous-time mode', 'states',
             'derivatives', 'directional derivatives', 'completed step', 'read')


class DriverGaveUp(Exception):
    """
    The Model Exchange driver met what it does not do (an event, stiffness).

    Attributes
    ----------
    reason : str
        What it met.
    interval : int
        Index of the interval in the batch.

    """

    def __init__(self, reason: str, interval: int) -> None:
        super().__init__(f'interval {interval}: {reason}')
        self.reason = reason
        self.interval = interval


def me_problem(*, snapshot: int | None, needs_completed_step: bool, tolerance: float,
               dt_s: float, max_steps: int, n: int, cstate_refs: Sequence[int],
               derivative_refs: Sequence[int], state_positions: Sequence[int],
               state_refs: Sequence[int], output_refs: Sequence[int],
               input_refs: Sequence[int], par_refs: Sequence[int],
               par_values: Sequence[float], start_refs: Sequence[int],
               start_index: Sequence[int], fmu_output_refs: Sequence[int],
               sensitivities: SensitivityRequest | None,
               chain: int = 0) -> tuple[MeProblem, list]:
    """
    Describe a Model Exchange batch for the driver.

    Returns the structure and the arrays it points to: keep both alive while
    the structure is used. ``fmu_output_refs`` are the model outputs that are
    FMU outputs (their partials are evaluated with sensitivities). ``chain`` C > 0:
    interval b >= C starts from the end states of interval b - C (C trajectories of
    consecutive intervals, interleaved), not from its own start states.
    """
    keep: list[Any] = []

    def refs(values: Sequence[int]) -> Any:
        array = vr_array(list(values) or [0])
        keep.append(array)
        return ctypes.cast(array, VR_P)

    def sizes(values: Sequence[int]) -> Any:
        array = size_array(values)
        keep.append(array)
        return ctypes.cast(array, SIZE_P)

    def reals(values: Sequence[float]) -> Any:
        array = real_array(list(values) or [0.0])
        keep.append(array)
        return ctypes.cast(array, DOUBLE_P)

    su_refs = sensitivities.input_refs if sensitivities is not None else ()
    su_nominals = sensitivities.input_nominals if sensitivities is not None else ()
    factor = sensitivities.nominal_factor if sensitivities is not None else 0.0  # unused
    problem = MeProblem(
        snapshot=snapshot, needs_completed_step=int(bool(needs_completed_step)),
        tolerance=tolerance, dt=dt_s, max_steps=max_steps, n=n,
        cstate_vr=refs(cstate_refs), derivative_vr=refs(derivative_refs),
        nx=len(state_refs), x_pos=sizes(state_positions), x_vr=refs(state_refs),
        ny=len(output_refs), y_vr=refs(output_refs),
        n_in=len(input_refs), in_vr=refs(input_refs),
        n_par=len(par_refs), par_vr=refs(par_refs), par_val=reals(par_values),
        n_start=len(start_refs), start_vr=refs(start_refs), start_idx=sizes(start_index),
        n_su=len(su_refs), su_vr=refs(su_refs), su_nominal=reals(su_nominals),
        sensitivity_factor=factor, sensitivities=int(sensitivities is not None),
        n_yo=len(fmu_output_refs), yo_vr=refs(fmu_output_refs), chain=int(chain))
    return problem, keep


class MeBatchDriver:
    """
    The batched Model Exchange driver bound to one FMU's functions.

    Functions an FMU may not export (optional capabilities) stay NULL; the
    driver only calls them where the model description says they exist.

    Parameters
    ----------
    fmu : FMU2Model
        The fmpy instance whose library provides the FMI functions.
    label : str
        Name of the FMU in error messages.

    Raises
    ------
    NotBuiltError
        If the driver is not built (``make setup``).

    """

    def __init__(self, fmu: FMU2Model, label: str) -> None:
        self.path = find_driver('me')
        self.label = label
        library = ctypes.CDLL(str(self.path))
        self._batch = library.mshoot_me_batch
        self._batch.restype = ctypes.c_long
        ptr = ctypes.c_void_p
        self._batch.argtypes = [ptr, ptr, ptr, ctypes.c_size_t, ptr, ptr, ptr, ptr,
                                ptr, ptr, ptr, ptr]
        self._library = library
        self._api = MeApi(*_bind(fmu, ME_FUNCTIONS, optional=True))
        self._api_address = ctypes.addressof(self._api)  # the structure lives with self
        self._stats = (ctypes.c_long * 4)()  # steps, rejected, evaluations, interval

    def run(self, component: Any, problem: MeProblem, starts: np.ndarray, inputs: np.ndarray,
            x_end: np.ndarray, y_end: np.ndarray, s_end: np.ndarray,
            dyo: np.ndarray, t_start: np.ndarray | None = None) -> None:
        """
        Integrate B intervals from ``starts`` (B, nx) with ``inputs`` (B, nu).

        Interval b starts at FMU time ``t_start[b]`` [s] (None: every one at 0).

        Fills ``x_end`` (B, nx), ``y_end`` (B, ny) and, with sensitivities,
        ``s_end`` (B, n, nx + m) and the output partials ``dyo``
        (B, n_yo, n + m); all float64 and C-contiguous.

        Raises
        ------
        DriverGaveUp
            For an interval the driver does not do (an event, too many steps).
        RuntimeError
            If an FMI call fails or the FMU requests termination.

        """
        batch = starts.shape[0]
        code = self._batch(
            self._api_address, component, ctypes.addressof(problem), batch,
            _address(starts), _address(inputs), _address(x_end), _address(y_end),
            _address(s_end), _address(dyo), self._stats, address(t_start))
        self.check(code, problem, batch)

    def check(self, code: int, problem: MeProblem, batch: int) -> None:
        """
        Raise for the return ``code`` of a batch of ``batch`` intervals (log its statistics).

        Raises
        ------
        DriverGaveUp
            For an interval the driver does not do (an event, too many steps).
        RuntimeError
            If an FMI call fails or the FMU requests termination.

        """
        stats = self._stats
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug('ME batch of %d: %d steps, %d rejected, %d evaluations', batch,
                         stats[0], stats[1], stats[2])
        if not code:
            return
        if code == ME_TERMINATE:
            raise RuntimeError(f'{self.label} requested termination in interval '
                               f'{stats[3]} of a Model Exchange batch')
        if code < 0:
            raise DriverGaveUp(ME_GAVE_UP.get(code, f'code {code}').format(
                max_steps=problem.max_steps), stats[3])
        raise RuntimeError(f'{self.label}: FMI call ({ME_STAGES[code % 16 - 1]}) '
                           f'of interval {code // 16} failed in the batched Model Exchange '
                           f'driver')

    def bind(self, component: Any, problem: tuple[MeProblem, list], batch: int, nx: int,
             nu: int, ny: int, times: bool) -> 'BoundMeBatch':
        """Return a batch of ``batch`` intervals of ``problem`` bound to buffers of its own."""
        return BoundMeBatch(self, component, problem, batch, nx, nu, ny, times)


class BoundMeBatch:
    """
    A Model Exchange batch of one size bound to buffers of its own: the driver's arguments once.

    The per-call cost of :meth:`MeBatchDriver.run` is mostly its arguments (the
    addresses of the arrays, a ctypes conversion each): here the caller copies
    the starts, inputs and start times into :attr:`starts`, :attr:`inputs` and
    :attr:`times`, :meth:`run` calls the driver with arguments prepared once, and
    the results are in :attr:`x_end`, :attr:`y_end`, :attr:`s_end` and :attr:`dyo`
    until the next run (shapes as :meth:`MeBatchDriver.run`'s).

    Parameters
    ----------
    driver : MeBatchDriver
    component : the FMU instance's component
    problem : (MeProblem, list)
        The batch's description and the arrays it points to (kept alive here).
    batch, nx, nu, ny : int
        Intervals, model states, inputs, outputs.
    times : bool
        Whether the intervals have start times (:attr:`times`, else all at FMU time 0).

    """

    def __init__(self, driver: MeBatchDriver, component: Any, problem: tuple[MeProblem, list],
                 batch: int, nx: int, nu: int, ny: int, times: bool) -> None:
        description = problem[0]
        self.driver = driver
        self.component = component
        self.problem = problem
        self.batch = batch
        self.starts = np.zeros((batch, nx))
        self.inputs = np.zeros((batch, nu))
        self.times = np.zeros(batch) if times else None
        self.x_end = np.zeros((batch, nx))
        self.y_end = np.zeros((batch, ny))
        n, m = description.n, description.n_su
        if description.sensitivities:
            self.s_end = np.zeros((batch, n, nx + m))
            self.dyo = np.zeros((batch, description.n_yo, n + m))
        else:
            self.s_end = self.dyo = np.zeros(1)
        self._call = driver._batch
        self._arguments = (driver._api_address, component, ctypes.addressof(description),
                           batch, _address(self.starts), _address(self.inputs),
                           _address(self.x_end), _address(self.y_end), _address(self.s_end),
                           _address(self.dyo), driver._stats,
                           None if self.times is None else _address(self.times))

    def run(self) -> None:
        """
        Integrate the batch from the buffers' starts, inputs and times.

        Raises
        ------
        DriverGaveUp, RuntimeError
            As :meth:`MeBatchDriver.run`.

        """
        code = self._call(*self._arguments)
        if code or logger.isEnabledFor(logging.DEBUG):
            self.driver.check(code, self.problem[0], self.batch)
