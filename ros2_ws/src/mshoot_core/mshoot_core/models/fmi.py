"""
Any FMI 2.0 FMU (Model Exchange or Co-Simulation) as a :class:`Model`, through fmpy.

The FMU is extracted once into the cache (keyed by the file's sha256, see
:func:`mshoot_core.fmu_cache.extract_fmu`), its modelDescription read and one
instance created once, in the constructor; every simulation resets that instance
(``fmi2Reset``), sets the parameters and the start states, initialises, and
then feeds the inputs held constant over each interval:

- Co-Simulation: one ``fmi2DoStep`` per interval (the FMU's own solver; the
  R1C1 FMU's step is the exact solution); batches of independent intervals
  (:meth:`FmiModel.simulate_intervals`) run in the compiled Co-Simulation
  driver (:mod:`~mshoot_core.models.fmi_drivers`), the same FMI calls in one
  C loop;
- Model Exchange: fmpy's CVode, or for batches the compiled Runge-Kutta
  driver, with events handled (:mod:`~mshoot_core.models.fmi_me`).

Time: every time the model is given (``udf.index`` of :meth:`FmiModel.simulate`,
the interval start times ``t_start_s``, the plant's start time) is in the
caller's time base; the FMU sees ``t - time_origin_s``. Interval k of a batch
starts at its own FMU time: Model Exchange sets the time (and the states)
after restoring its FMU-state snapshot or initialises there; Co-Simulation
re-initialises at that time from the mapped states (``fmi2SetupExperiment``
start time). Limits: a Co-Simulation FMU's states other than the mapped ones
start each interval from their start values (FMI 2.0 lets an importer set a
Co-Simulation FMU's states only before initialisation; an FMU state is opaque),
and a Model Exchange FMU restored from its snapshot must accept a new time
(``fmi2SetTime``) followed by an event iteration at that time. Intervals
without start times start at FMU time 0 (time-invariant models).

The emulated building uses the same instance as a plant
(:class:`~mshoot_core.models.fmi_plant.FmuPlant`): stepped forward for the
whole run, never re-initialised. Non-finite states or outputs raise
:class:`~mshoot_core.models.fmi_values.FmuValueError` (variable and FMU time).
FMI 3.0 FMUs are refused with a plain ValueError (not supported yet).

Derivatives: for Model Exchange FMUs with ``providesDirectionalDerivative``,
:meth:`FmiModel.interval_jacobians` integrates the forward sensitivities along
with the states (:mod:`~mshoot_core.models.fmi_sensitivities`); Co-Simulation
FMUs return ``None`` there and the optimiser falls back to finite differences
over :meth:`simulate_intervals`.

The drivers and the built-in R1C1 FMU are built by ``make setup`` and found in
the FMU cache (:mod:`mshoot_core.fmu_cache`); a missing build is a
:class:`~mshoot_core.fmu_cache.NotBuiltError` naming the command that builds
it.

Variable names (this module): ``inputs``, ``states`` and ``outputs`` are
either sequences of FMU variable names, or mappings ``{model name: FMU
variable name}`` when the model-side names must differ (the R1C1 FMU's state
is ``heatCapacitor.T`` in K and its output ``T`` in degC;
:func:`r1c1_fmi_model` maps the state to ``'T'`` so the model matches
:class:`~mshoot_core.models.r1c1.R1C1Model`). States are set through their
start values before initialisation (so they need ``initial="exact"`` or
``"approx"`` in Co-Simulation) and, in Model Exchange, also written into the
continuous-state vector after it.
"""
from __future__ import annotations

import ctypes
import dataclasses
import logging
import math
import os
import pathlib
import pickle
import sys
import tempfile
from typing import Any, Mapping, Sequence, Union

import fmpy
from fmpy.fmi2 import (fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE,
                       fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, FMU2Model, FMU2Slave)
from fmpy.model_description import ValidationError
import numpy as np
import pandas as pd

from mshoot_core.fmu_binary import binary_file, check_binary, isolated, Library
from mshoot_core.fmu_cache import extract_fmu, find_fmu, STAGING_PREFIX
from mshoot_core.models.base import interval_start_times, Model
from mshoot_core.models.fmi_drivers import (CsBatchDriver, MeBatchDriver, MeProblem,
                                            real_array, vr_array)
from mshoot_core.models.fmi_me import (MAX_SOLVER_STEPS, ME_MAX_STEPS,
                                       ModelExchangeIntegration)
from mshoot_core.models.fmi_plant import FmuPlant
from mshoot_core.models.fmi_sensitivities import (ForwardSensitivities,
                                                  SENSITIVITY_NOMINAL_FACTOR)
from mshoot_core.models.fmi_values import FmuValueError, NonFiniteChecks
from mshoot_core.models.r1c1 import R1C1Model

__all__ = ['DESCRIPTION_PICKLE', 'FMI_TYPES', 'FmiModel', 'FmuValueError', 'MAX_SOLVER_STEPS',
           'ME_MAX_STEPS', 'R1C1_VARIABLES', 'r1c1_fmi_model', 'read_cached_description',
           'read_fmu_description', 'SENSITIVITY_NOMINAL_FACTOR', 'summarise',
           'VALIDATED_MARKER', 'VariableNames']

logger = logging.getLogger(__name__)

#: The FMI types an FMU may be used as.
FMI_TYPES = ('ModelExchange', 'CoSimulation')
#: Names as a sequence (model name = FMU name) or a mapping model name -> FMU name.
VariableNames = Union[Sequence[str], Mapping[str, str]]
#: Longest list of valid names quoted in an error message.
_MAX_LISTED = 60
#: Problems of a long list (fmpy's schema validation) quoted in a one-line message.
SHOWN_PROBLEMS = 3

_FMU_LOG_LEVELS = {0: logging.DEBUG, 1: logging.WARNING, 2: logging.WARNING, 3: logging.ERROR,
                   4: logging.CRITICAL}


def _log_fmu_message(component: Any, instance_name: bytes, status: int, category: bytes,
                     message: bytes) -> None:
    """Route an FMU's log message to this module's logger."""
    name = instance_name.decode('utf-8', 'replace') if instance_name else '?'
    text = message.decode('utf-8', 'replace') if message else ''
    logger.log(_FMU_LOG_LEVELS.get(status, logging.ERROR), '[%s] %s', name, text)


def _make_callbacks() -> fmi2CallbackFunctions:
    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(_log_fmu_message)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(fmpy.calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(fmpy.free)
    try:  # a native proxy formats printf-style messages before they reach Python
        from fmpy.logging import addLoggerProxy
        addLoggerProxy(ctypes.byref(callbacks))
    except Exception as error:  # noqa: BLE001 - messages stay unformatted, nothing else
        logger.debug('fmpy logger proxy unavailable: %s', error)
    return callbacks


#: One callbacks struct for every instance; module-level so it outlives them.
_CALLBACKS = _make_callbacks()


def _name_map(kind: str, spec: VariableNames) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Split ``spec`` into (model names, FMU variable names), validating its shape."""
    if isinstance(spec, (str, bytes)):
        raise TypeError(f'{kind} must be a sequence of names or a mapping model name -> FMU '
                        f'variable name, got the string {spec!r}')
    if isinstance(spec, Mapping):
        model_names, fmu_names = tuple(spec.keys()), tuple(spec.values())
    else:
        model_names = fmu_names = tuple(spec)
    for name in (*model_names, *fmu_names):
        if not isinstance(name, str) or not name:
            raise TypeError(f'{kind} names must be non-empty strings, got {name!r}')
    for names, side in ((model_names, 'model'), (fmu_names, 'FMU')):
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f'{kind} repeat the {side} names {duplicates}')
    return model_names, fmu_names


def _listed(names: Sequence[str]) -> str:
    names = list(names)
    if len(names) > _MAX_LISTED:
        return f'{names[:_MAX_LISTED]} (and {len(names) - _MAX_LISTED} more)'
    return str(names)


#: A file in an FMU's cache folder (:func:`mshoot_core.fmu_cache.extract_fmu`) once its
#: modelDescription passed fmpy's schema validation. The folder is keyed by the FMU file's
#: hash: later models of the same file read it without validating it again (loading the XML
#: schema costs some 12 ms of every command).
VALIDATED_MARKER = '.mshoot-validated'

#: The modelDescription of a validated FMU of the cache, as fmpy read it (a pickle; per fmpy
#: and Python version): later models of the file load it instead of parsing the XML (lxml's
#: import and the parse, some 6 ms of every command with an FMU).
DESCRIPTION_PICKLE = '.mshoot-description-fmpy{fmpy}-py{python}.pickle'

#: The modelDescriptions :func:`read_cached_description` returned in this process: by the
#: resolved folder and its modelDescription.xml's mtime [ns] and size, the description and
#: whether it was validated. A large FMU's pickle takes seconds to load (the BOPTEST office's
#: 26 642 variables, 11 MB) and a run reads it several times (the card's check, the plant,
#: the controller's card).
_DESCRIPTIONS: dict[tuple[str, int, int], tuple[Any, bool]] = {}


def read_cached_description(folder: pathlib.Path, label: str, validate: bool = True) -> Any:
    """
    :func:`read_fmu_description` of an FMU in the cache: validated once, then marked.

    Validated (when ``validate``) unless the folder holds :data:`VALIDATED_MARKER`, which a
    validated read leaves there (where the cache can be written), with the description read
    (:data:`DESCRIPTION_PICKLE`): a marked folder's description is loaded from it, when it
    is there and loads; else read from the XML again. Without ``validate`` (a card's
    ``validate: false``) the pickle is used whether or not the folder is marked. The cache is
    trusted as for the FMU's own binaries, which it holds and which are loaded and run.

    Read once per process: a later call for the same folder returns the very same object
    (``_DESCRIPTIONS``), unless the folder's modelDescription.xml changed (its mtime or
    size; a changed FMU file is extracted into another folder anyway, the cache's folders
    being keyed by the file's hash) or a validated description is asked for and the one read
    was not. The description is shared: callers read it and never change it.
    """
    folder = pathlib.Path(folder)
    try:
        stat = (folder / 'modelDescription.xml').stat()
        key: tuple[str, int, int] | None = (str(folder.resolve()), stat.st_mtime_ns,
                                            stat.st_size)
    except OSError:  # no description: read_fmu_description says what is wrong
        key = None
    known = _DESCRIPTIONS.get(key) if key is not None else None
    if known is not None and (known[1] or not validate):
        return known[0]
    md, validated = _read_cached_description(folder, label, validate)
    if key is not None and not folder.name.startswith(STAGING_PREFIX):
        # (a folder being extracted is renamed next: its key would never be asked for)
        _DESCRIPTIONS[key] = (md, validated)
    return md


def _read_cached_description(folder: pathlib.Path, label: str,
                             validate: bool) -> tuple[Any, bool]:
    """:func:`read_cached_description` without the memo: (description, whether validated)."""
    marker = folder / VALIDATED_MARKER
    cached = folder / DESCRIPTION_PICKLE.format(
        fmpy=fmpy.__version__, python=f'{sys.version_info[0]}.{sys.version_info[1]}')
    validated = marker.is_file()
    if validated or not validate:
        try:
            with open(cached, 'rb') as stream:
                return pickle.load(stream), validated
        except FileNotFoundError:
            pass
        except Exception as error:  # noqa: BLE001 - a damaged pickle: read the XML again
            logger.debug('cached modelDescription of %s not loaded (%s: %s)', label,
                         type(error).__name__, error)
    md = read_fmu_description(folder, label, validate=validate and not validated)
    try:
        if validate and not validated:
            marker.touch()
        _write_whole(cached, pickle.dumps(md, protocol=pickle.HIGHEST_PROTOCOL))
    except (OSError, pickle.PicklingError, TypeError, AttributeError) as error:
        # a read-only cache (validated every time) or a description that does not pickle
        logger.debug('modelDescription of %s not cached (%s: %s)', label,
                     type(error).__name__, error)
    return md, validated or validate


def _write_whole(path: pathlib.Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` whole or not at all (a file beside it, renamed)."""
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f'{path.name}.',
                                     delete=False) as out:
        try:
            out.write(payload)
        except BaseException:
            os.unlink(out.name)
            raise
    try:
        os.replace(out.name, path)
    except BaseException:
        os.unlink(out.name)
        raise


def summarise(problems: Sequence[str], shown: int = SHOWN_PROBLEMS) -> str:
    """
    Return a long list of problems as one short line: the count and the first ``shown``.

    ``'3 problems: a; b; c'``, or ``'151 problems, the first 3: a; b; c (and 148 more)'``.
    """
    items = [' '.join(str(p).split()) for p in problems]
    count = f'{len(items)} problem{"s" if len(items) != 1 else ""}'
    if len(items) <= shown:
        return f'{count}: ' + '; '.join(items)
    return (f'{count}, the first {shown}: ' + '; '.join(items[:shown])
            + f' (and {len(items) - shown} more)')


def read_fmu_description(folder: str | pathlib.Path, label: str, validate: bool = True) -> Any:
    """
    Read the modelDescription of an extracted FMU; refuse what FmiModel cannot run.

    Parameters
    ----------
    folder : path
        The extracted FMU.
    label : str
        The FMU's name in messages (its file).
    validate : bool
        Validate the XML against the FMI schema (fmpy's ``validate``).

    Raises
    ------
    ValueError
        If the modelDescription is missing or unreadable, or the FMU is an
        FMI 3.0 FMU (not supported yet).

    """
    invalid = None
    try:
        try:
            md = fmpy.read_model_description(str(folder), validate=validate)
        except ValidationError as error:  # an FMI 3.0 FMU is refused as one, valid or not
            invalid = error
            md = fmpy.read_model_description(str(folder), validate=False)
    except Exception as error:  # noqa: BLE001 - fmpy raises plain Exceptions, lxml, KeyError
        raise ValueError(f'{label} is not a readable FMU: its modelDescription.xml '
                         f'could not be read ({type(error).__name__}: '
                         f'{" ".join(str(error).split())})') from error
    version = str(md.fmiVersion)
    if version.startswith('3'):
        raise ValueError(f'{label}: FMI 3.0 FMUs are not supported yet (fmiVersion '
                         f'{version!r}); export the model as an FMI 2.0 FMU (Model Exchange or '
                         'Co-Simulation)')
    if invalid is not None:
        raise ValueError(f'{label}: its modelDescription.xml breaks the FMI schema '
                         f"({summarise(invalid.problems)}); a card relaxes fmpy's schema "
                         f'validation with `validate: false`') from invalid
    return md


class FmiModel(FmuPlant, ModelExchangeIntegration, ForwardSensitivities, NonFiniteChecks,
               Model):
    """
    An FMI 2.0 FMU behind the :class:`Model` interface (fmpy).

    Parameters
    ----------
    fmu_path : path
        The ``.fmu`` file (extracted once into the FMU cache, keyed by its
        sha256, and reused by every model of the same file) or an already
        extracted FMU directory.
    inputs, states, outputs : sequence of str or mapping str -> str
        FMU variable names, or ``{model name: FMU variable name}``. Inputs
        must be Real variables with causality ``input``; states Real
        variables (in Model Exchange: continuous states of the FMU; in
        Co-Simulation: with a settable start value); outputs any Real
        variables. The model names become :attr:`input_names`,
        :attr:`state_names` and :attr:`output_names`, in the given order.
    parameters : mapping str -> value, optional
        Values set after every reset, before initialisation (parameters and
        other variables with a settable start value).
    fixed_inputs : mapping str -> value, optional
        FMU inputs that are not model inputs, held at a constant value: set
        with the parameters after every reset, before initialisation, and never
        changed (e.g. the ``*_activate`` switch of an overwrite pair, held at
        1 so the FMU uses the overwritten signal).
    tolerance : float
        Relative tolerance of the Model Exchange integrator (CVode); passed to
        ``fmi2SetupExperiment`` for Co-Simulation FMUs too.
    fmi_type : {'ModelExchange', 'CoSimulation'} or None
        Interface to use; None picks Co-Simulation when the FMU has it (as
        fmpy does), else Model Exchange.
    instance_name : str
        Name of the FMU instance (appears in its log messages).
    time_origin_s : float
        Time of FMU t = 0 in the caller's time base [s]: the FMU sees
        ``t - time_origin_s`` (default 0: the caller's time is FMU time).
    monotone_inputs : sequence of str
        Model inputs in which the FMU is a monotone system
        (:attr:`~mshoot_core.models.base.Model.monotone_inputs`): a claim about
        its physics that only its author can make (default: none).
    validate : bool
        Validate the modelDescription against the FMI schema (fmpy's ``validate``; a card's
        ``validate: false`` relaxes it).
    libraries : sequence of Library
        Libraries to preload before the FMU's binary (a card's ``preload``); the binary is
        loaded in a child process first (:func:`mshoot_core.fmu_binary.check_binary`).
    own_tolerance : bool
        Co-Simulation: give ``fmi2SetupExperiment`` no tolerance, so the FMU's own integrator
        keeps its own (as BOPTEST runs its test cases); ``tolerance`` then only serves Model
        Exchange.
    computed_states : sequence of str
        Model Exchange: states (model names) mapped to variables computed from the FMU's
        continuous states rather than to continuous states (a zone temperature of an FMU whose
        air state is its energy; a card's ``computed: true``): read, never written, so the
        model can be a plant (:meth:`plant_start`, :meth:`plant_step`) but cannot simulate
        from given states (:attr:`derived_states`).

    Raises
    ------
    FileNotFoundError
        If ``fmu_path`` does not exist.
    NotBuiltError
        (a FileNotFoundError) If the compiled batch driver this model's
        batches use is not built: ``make setup`` builds it.
    ValueError
        For unknown variable names (the message lists the valid ones), an
        FMI type the FMU lacks, a bad tolerance or time origin, a file that is
        not an FMU, an FMI 3.0 FMU, or monotone inputs that are not inputs; a binary that
        does not load (:class:`~mshoot_core.fmu_binary.FmuBinaryError`).

    Notes
    -----
    Use as a context manager or call :meth:`close` to free the instance and
    the extracted files. The instance is not thread-safe. Its ``model_description`` (fmpy's)
    is shared with every model of the same FMU file in the process
    (:func:`read_cached_description`): read it, never change it.

    This class holds the instance, the configuration and the Co-Simulation
    stepping; the Model Exchange integration comes from
    :class:`~mshoot_core.models.fmi_me.ModelExchangeIntegration` and the
    forward sensitivities (:meth:`interval_jacobians`) from
    :class:`~mshoot_core.models.fmi_sensitivities.ForwardSensitivities`.

    """

    def __init__(self, fmu_path: str | pathlib.Path, inputs: VariableNames,
                 states: VariableNames, outputs: VariableNames,
                 parameters: Mapping[str, Any] | None = None, tolerance: float = 1e-8,
                 fmi_type: str | None = None, instance_name: str = 'mshoot',
                 fixed_inputs: Mapping[str, Any] | None = None,
                 time_origin_s: float = 0.0, monotone_inputs: Sequence[str] = (),
                 validate: bool = True, libraries: Sequence[Library] = (),
                 own_tolerance: bool = False,
                 computed_states: Sequence[str] = ()) -> None:
        self._fmu: FMU2Model | FMU2Slave | None = None
        self._unzip_dir: pathlib.Path | None = None
        self._snapshot: Any = None
        self._plant: Any = None
        self._fmu_time: float | None = None
        self._non_finite_seen: tuple | None = None
        self._solver: Any = None
        self._solver_start = 0.0  # (re)start time of CVode, while not created
        self._sensitivity_solvers: dict[tuple[int, ...], tuple[Any, Any]] = {}
        self._sensitivity_requests: dict[tuple[int, ...], Any] = {}
        self._jacobian_plans: dict[tuple, Any] = {}  # (fmi_sensitivities)
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) \
                or not 0.0 < float(tolerance) < 1.0:
            raise ValueError(f'tolerance must be a float in (0, 1), got {tolerance!r}')
        if fmi_type not in (None, *FMI_TYPES):
            raise ValueError(f'fmi_type must be one of {[None, *FMI_TYPES]}, got {fmi_type!r}')
        if isinstance(time_origin_s, bool) or not isinstance(time_origin_s, (int, float)) \
                or not math.isfinite(float(time_origin_s)):
            raise ValueError(f'time_origin_s must be a finite time [s], got {time_origin_s!r}')
        path = pathlib.Path(fmu_path)
        if not path.exists():
            raise FileNotFoundError(f'FMU not found: {path}')
        self.fmu_path = path
        self.tolerance = float(tolerance)
        self.own_tolerance = bool(own_tolerance)
        #: Time of FMU t = 0 in the caller's time base [s].
        self.time_origin_s = float(time_origin_s)
        try:
            described: list[Any] = []  # read while checking a new extraction: not again
            if path.is_dir():
                self._unzip_dir = path
                described.append(read_fmu_description(path, path.name, validate))
            else:
                self._unzip_dir = extract_fmu(path, check=lambda folder: described.append(
                    read_cached_description(folder, path.name, validate)))
            self.model_description = (described[0] if described else read_cached_description(
                self._unzip_dir, path.name, validate))
            self.libraries = tuple(libraries)
            self._computed_states = tuple(computed_states)
            self._configure(inputs, states, outputs, dict(parameters or {}), fmi_type,
                            dict(fixed_inputs or {}))
            monotone = tuple(monotone_inputs)
            unknown = [name for name in monotone if name not in self.input_names]
            if unknown:
                raise ValueError(f'monotone_inputs must be inputs of the model '
                                 f'{list(self.input_names)}, got {unknown}')
            self.monotone_inputs = monotone
            self._instantiate(instance_name)
        except BaseException:
            self.close()
            raise

    # -- configuration ------------------------------------------------------------------
    def _configure(self, inputs: VariableNames, states: VariableNames, outputs: VariableNames,
                   parameters: dict[str, Any], fmi_type: str | None,
                   fixed_inputs: dict[str, Any] | None = None) -> None:
        md = self.model_description
        if md.fmiVersion != '2.0':
            raise ValueError(f'{self.fmu_path.name}: expected an FMI 2.0 FMU, '
                             f'got fmiVersion={md.fmiVersion!r}')
        available = [name for name, kind in (('ModelExchange', md.modelExchange),
                                             ('CoSimulation', md.coSimulation)) if kind]
        if fmi_type is None:
            fmi_type = 'CoSimulation' if 'CoSimulation' in available else 'ModelExchange'
        if fmi_type not in available:
            raise ValueError(f'{self.fmu_path.name} supports {available}, got '
                             f'fmi_type={fmi_type!r}')
        self.fmi_type = fmi_type
        self.is_model_exchange = fmi_type == 'ModelExchange'
        self._interface = md.modelExchange if self.is_model_exchange else md.coSimulation
        self._variables = {v.name: v for v in md.modelVariables}
        self._continuous_states = [d.variable.derivative for d in md.derivatives]
        self._derivative_refs = [d.variable.valueReference for d in md.derivatives]
        reals = [v for v in md.modelVariables if v.type == 'Real']

        self.input_names, self._input_vars = self._resolve(
            'inputs', inputs, [v.name for v in reals if v.causality == 'input'])
        if self.is_model_exchange:  # continuous states, or declared variables computed from them
            state_choices = [v.name for v in self._continuous_states]
            if self._computed_states:
                state_choices += [v.name for v in reals if v not in self._continuous_states
                                  and v.causality not in ('parameter', 'input',
                                                          'calculatedParameter')]
        else:
            state_choices = [v.name for v in reals
                             if v.causality not in ('parameter', 'input', 'calculatedParameter')
                             and v.initial in ('exact', 'approx')]
        self.state_names, self._state_vars = self._resolve('states', states, state_choices)
        computed = {n for n, v in zip(self.state_names, self._state_vars)
                    if self.is_model_exchange and v not in self._continuous_states}
        if computed != set(self._computed_states):
            raise ValueError(f'{self.fmu_path.name}: computed_states must name the states '
                             f'mapped to variables that are not continuous states, expected '
                             f'{sorted(computed)}, got {list(self._computed_states)}')
        self.output_names, self._output_vars = self._resolve(
            'outputs', outputs, [v.name for v in reals if v.causality not in
                                 ('parameter', 'calculatedParameter', 'input')])

        self._input_refs = vr_array([v.valueReference for v in self._input_vars])
        self._state_refs = vr_array([v.valueReference for v in self._state_vars])
        self._output_refs = vr_array([v.valueReference for v in self._output_vars])
        self._state_buffer = (ctypes.c_double * len(self._state_vars))()
        self._output_buffer = (ctypes.c_double * len(self._output_vars))()
        # States whose start value can be set before initialisation.
        self._start_state_index = [i for i, v in enumerate(self._state_vars)
                                   if v.initial in ('exact', 'approx')]
        self._start_state_refs = vr_array(
            [self._state_vars[i].valueReference for i in self._start_state_index])
        self._n_continuous = md.numberOfContinuousStates if self.is_model_exchange else 0
        # In Model Exchange a mapped state is a continuous state of the FMU (written at a
        # start), or a variable computed from them (a zone temperature of an FMU whose air
        # state is an energy): only read, so only a plant (plant_start/plant_step) can use it.
        self._written_states = [i for i, v in enumerate(self._state_vars)
                                if v in self._continuous_states] \
            if self.is_model_exchange else []
        self._state_positions = [self._continuous_states.index(self._state_vars[i])
                                 for i in self._written_states]
        #: States read from variables computed by the FMU, not its continuous states.
        self.derived_states = tuple(name for i, name in enumerate(self.state_names)
                                    if self.is_model_exchange and i not in self._written_states)
        self._x_full = np.zeros(self._n_continuous)
        self._set_parameters_plan(parameters, fixed_inputs or {})

    def _resolve(self, kind: str, spec: VariableNames,
                 choices: Sequence[str]) -> tuple[tuple[str, ...], list[Any]]:
        model_names, fmu_names = _name_map(kind, spec)
        unknown = [name for name in fmu_names if name not in choices]
        if unknown:
            what = {'states': ('continuous states' if self.is_model_exchange
                               else 'Real variables with a settable start value'),
                    'inputs': 'Real inputs', 'outputs': 'Real variables'}[kind]
            raise ValueError(f'{self.fmu_path.name} ({self.fmi_type}): invalid {kind} '
                             f'{unknown}; expected {what} from {_listed(choices)}, '
                             f'got {list(fmu_names)}')
        return model_names, [self._variables[name] for name in fmu_names]

    def _set_parameters_plan(self, parameters: dict[str, Any],
                             fixed_inputs: dict[str, Any]) -> None:
        """
        Validate ``parameters`` and ``fixed_inputs``; group them by FMI type.

        One set call each; both are set after every reset, before initialisation.
        """
        settable = [v.name for v in self.model_description.modelVariables
                    if v.causality != 'input' and v.variability != 'constant'
                    and (v.causality == 'parameter' or v.initial in ('exact', 'approx'))]
        unknown = [name for name in parameters if name not in settable]
        if unknown:
            raise ValueError(f'{self.fmu_path.name}: invalid parameters {unknown}; expected '
                             f'names from {_listed(settable)}, got {list(parameters)}')
        mapped = {v.name for v in self._input_vars}
        free_inputs = [v.name for v in self.model_description.modelVariables
                       if v.causality == 'input' and v.name not in mapped]
        unknown = [name for name in fixed_inputs if name not in free_inputs]
        if unknown:
            raise ValueError(f'{self.fmu_path.name}: invalid fixed_inputs {unknown}; expected '
                             f'inputs not mapped as model inputs, from {_listed(free_inputs)}')
        groups: dict[str, tuple[list[int], list[Any]]] = {}
        for name, value in {**parameters, **fixed_inputs}.items():
            var = self._variables[name]
            kind = {'Enumeration': 'Integer'}.get(var.type, var.type)
            if kind == 'Real':
                if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
                        or not math.isfinite(float(value)):
                    raise ValueError(f'parameter {name} must be a finite number, got {value!r}')
                value = float(value)
            elif kind == 'Integer':
                value = int(value)
            elif kind == 'Boolean':
                value = bool(value)
            elif kind == 'String':
                value = str(value)
            else:
                raise ValueError(f'parameter {name} has the unsupported type {var.type}')
            refs, values = groups.setdefault(kind, ([], []))
            refs.append(var.valueReference)
            values.append(value)
        self.parameters = dict(parameters)
        self.fixed_inputs = dict(fixed_inputs)
        self._parameter_groups = groups

    def _instantiate(self, instance_name: str) -> None:
        md = self.model_description
        cls = FMU2Model if self.is_model_exchange else FMU2Slave
        # a damaged binary or a missing library: a clear error, not a signal in this process
        check_binary(self._unzip_dir, self._interface.modelIdentifier, self.libraries,
                     label=self.fmu_path.name)
        binary = binary_file(self._unzip_dir, self._interface.modelIdentifier)
        try:
            with isolated(binary) as path:  # its own BLAS, not one loaded before it
                fmu = cls(guid=md.guid, unzipDirectory=str(self._unzip_dir),
                          modelIdentifier=self._interface.modelIdentifier,
                          instanceName=instance_name, libraryPath=str(path))
            fmu.instantiate(callbacks=_CALLBACKS)
        except Exception as error:  # noqa: BLE001 - fmpy: OSError, plain Exception
            raise ValueError(f'{self.fmu_path.name} ({self.fmi_type}) cannot be instantiated '
                             f'on this platform: {error}') from error
        self._fmu = fmu
        self._initialized_once = False
        self._cs_driver = None
        self._me_driver = None
        self._me_problems: dict[tuple, tuple[MeProblem, list]] = {}
        self._me_bound: dict[tuple, Any] = {}  # BoundMeBatch by problem and size
        self._bind_drivers()
        logger.debug('instantiated %s as %s', self.fmu_path.name, self.fmi_type)

    def _bind_drivers(self) -> None:
        """
        Find and bind the compiled driver this model's batches will use, if any.

        Done at construction, so that a missing build stops the model here
        (a :class:`~mshoot_core.fmu_cache.NotBuiltError` naming the command
        that builds it) rather than at its first batch.
        """
        if self.is_model_exchange:
            if self.me_batch_plan() is None:
                self._me_driver = MeBatchDriver(self._fmu, self.fmu_path.name)
        elif all(kind == 'Real' for kind in self._parameter_groups):
            self._cs_driver = CsBatchDriver(self._fmu, self.fmu_path.name)

    # -- lifecycle --------------------------------------------------------------------------
    def close(self) -> None:
        """Free the FMU instance, the solvers and the extracted files (idempotent)."""
        fmu = getattr(self, '_fmu', None)
        self._solver = None
        self._sensitivity_solvers = {}
        self._me_problems = {}
        self._me_bound = {}
        self._cs_driver = self._me_driver = None  # bound to the instance's library
        self._plant = None
        if fmu is not None:
            self._fmu = None
            try:
                if self._snapshot is not None:
                    fmu.freeFMUstate(self._snapshot)
                fmu.freeInstance()
            except Exception as error:  # noqa: BLE001 - freeing must not raise
                logger.warning('freeing the FMU instance failed: %s', error)
        self._snapshot = None
        self._unzip_dir = None  # the extracted files stay in the cache for the next model

    def __enter__(self) -> 'FmiModel':
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __repr__(self) -> str:
        return (f'FmiModel({self.fmu_path.name!r}, {self.fmi_type}, inputs={self.input_names}, '
                f'states={self.state_names}, outputs={self.output_names})')

    @property
    def fmu(self) -> FMU2Model | FMU2Slave:
        """Return the fmpy instance (raises if closed)."""
        if self._fmu is None:
            raise RuntimeError('the FmiModel is closed')
        return self._fmu

    @property
    def can_snapshot(self) -> bool:
        """Whether the FMU supports fmi2Get/SetFMUstate for this interface."""
        return bool(self._interface.canGetAndSetFMUstate)

    # -- low-level helpers ----------------------------------------------------------------
    def _set_inputs(self, u: np.ndarray) -> None:
        n = len(self._input_vars)
        if n:
            fmu = self._fmu
            fmu.fmi2SetReal(fmu.component, self._input_refs, n, real_array(u))

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        """Read the FMU's current (states, outputs)."""
        fmu = self._fmu
        nx, ny = len(self._state_vars), len(self._output_vars)
        if nx:
            fmu.fmi2GetReal(fmu.component, self._state_refs, nx, self._state_buffer)
        if ny:
            fmu.fmi2GetReal(fmu.component, self._output_refs, ny, self._output_buffer)
        return np.array(self._state_buffer), np.array(self._output_buffer)

    def _initialize(self, t0: float, x0: np.ndarray, u0: np.ndarray) -> None:
        """Reset, set parameters, start states and inputs, initialise at ``t0``."""
        fmu = self.fmu
        if self._initialized_once:
            fmu.reset()
        self._initialized_once = True
        for kind, (refs, values) in self._parameter_groups.items():
            getattr(fmu, f'set{kind}')(refs, values)
        if self._start_state_index:
            fmu.fmi2SetReal(fmu.component, self._start_state_refs, len(self._start_state_index),
                            real_array(x0[self._start_state_index]))
        own = self.own_tolerance and not self.is_model_exchange
        fmu.setupExperiment(tolerance=None if own else self.tolerance, startTime=t0)
        fmu.enterInitializationMode()
        self._set_inputs(u0)
        fmu.exitInitializationMode()
        if self.is_model_exchange:
            self._enter_continuous_time(t0, x0)

    def _switch_inputs(self, t: float, u: np.ndarray) -> None:
        """Apply new inputs at ``t``: for ME an event (and a solver re-start)."""
        if self.is_model_exchange:
            self._input_event(t, u)
        else:
            self._set_inputs(u)

    def _advance(self, t: float, t_end: float) -> None:
        """Advance the FMU from ``t`` to ``t_end`` with the inputs already set."""
        if self.is_model_exchange:
            self._integrate(t, t_end)
        else:
            self._fmu.doStep(t, t_end - t)

    def _advance_checked(self, t: float, t_end: float) -> None:
        """:meth:`_advance`; an integrator failure on non-finite values is an FmuValueError."""
        self._non_finite_seen = None
        try:
            self._advance(t, t_end)
        except FmuValueError:
            raise
        except Exception as error:  # CVode's RuntimeError, fmpy's FMICallException
            self._diagnose(error, f' (step from FMU time {t:.9g} s)')
            raise

    def _start_interval(self, x0: np.ndarray, u: np.ndarray, t0: float = 0.0) -> None:
        """
        Bring the instance to FMU time ``t0`` with states ``x0`` and inputs ``u``.

        Model Exchange FMUs that support FMU states restore a snapshot taken
        after the first initialisation (no re-initialisation) and set the
        time; others are reset and initialised at ``t0``.
        """
        if self.is_model_exchange and self.can_snapshot:
            self._restore_snapshot(x0, u, t0)
        else:
            self._initialize(t0, x0, u)

    def _fmu_start_times(self, t_start_s: np.ndarray | None, batch: int) -> np.ndarray | None:
        """
        Return the FMU start times of a batch's intervals, or None.

        The caller's times minus the origin; None means every interval at FMU time 0.
        """
        times = interval_start_times(t_start_s, batch)
        if times is None or not self.time_origin_s:
            return times
        return times - self.time_origin_s

    def _check_batch(self, x_start: np.ndarray, u: np.ndarray,
                     dt_s: float) -> tuple[np.ndarray, np.ndarray, float]:
        if self.derived_states:
            raise ValueError(f'{self.fmu_path.name}: states {list(self.derived_states)} are not '
                             'continuous states of the FMU but variables computed from them: '
                             'the FMU can be a plant (an emulator), not a control model started '
                             'from given states; identify a control model from it instead '
                             '(mshoot identify)')
        x_start, u = super()._check_batch(x_start, u)
        dt_s = float(dt_s)
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f'dt_s must be a positive number of seconds, got {dt_s}')
        return x_start, u, dt_s

    # -- the Model interface ----------------------------------------------------------------
    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        """
        Simulate from ``x0`` over the index of ``udf`` (inputs held per interval).

        Outputs at ``t_{k+1}`` are those at the end of interval k (evaluated
        with interval k's inputs), as in :meth:`simulate_intervals`; outputs
        at ``t_0`` use the first row's inputs.

        Parameters
        ----------
        udf : DataFrame, shape (T, nu)
            Inputs indexed by time [s], columns :attr:`input_names`.
        x0 : sequence of float, length nx
            Initial state, in the FMU's units.

        Returns
        -------
        ydf : DataFrame, shape (T, ny)
        xdf : DataFrame, shape (T, nx)
            ``xdf.iloc[0]`` equals ``x0``.

        """
        t, u, x0_arr = self.check_inputs(udf, x0)
        self._plant = None  # the instance is re-initialised: a plant run ends here
        if self.time_origin_s:
            t = t - self.time_origin_s
        states = np.empty((t.size, len(self.state_names)))
        outputs = np.empty((t.size, len(self.output_names)))
        self._initialize(t[0], x0_arr, u[0])
        states[0] = x0_arr
        outputs[0] = self._read()[1]
        self._check_finite(states[0], outputs[0], t[0])
        for k in range(t.size - 1):
            if k > 0:
                self._switch_inputs(t[k], u[k])
            self._advance_checked(t[k], t[k + 1])
            states[k + 1], outputs[k + 1] = self._read()
            self._check_finite(states[k + 1], outputs[k + 1], t[k + 1])
        ydf = pd.DataFrame(outputs, index=udf.index, columns=list(self.output_names))
        xdf = pd.DataFrame(states, index=udf.index, columns=list(self.state_names))
        return ydf, xdf

    def simulate_fresh(self, udf: pd.DataFrame,
                       x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        """
        Simulate as the ancestor did: ``fmpy.simulate_fmu`` from the file, every time.

        Extracts, instantiates and frees the FMU for this one simulation (the
        per-simulation cost the ``naive`` optimiser mode reproduces); inputs
        are a table with every switch time twice, so fmpy holds them constant.
        Same results as :meth:`simulate` up to the integrator tolerance.
        """
        t, u, x0_arr = self.check_inputs(udf, x0)
        names = [v.name for v in self._input_vars]
        rows = [(t[0], *u[0])]
        for k in range(1, t.size):
            rows += [(t[k], *u[k - 1]), (t[k], *u[k])]
        table = np.array(rows, dtype=[('time', float)] + [(n, float) for n in names])
        start = {**self.parameters, **self.fixed_inputs}
        start.update({self._state_vars[i].name: float(x0_arr[i])
                      for i in self._start_state_index})
        outputs = [v.name for v in self._state_vars] + [v.name for v in self._output_vars]
        fmu_t = t - self.time_origin_s
        result = fmpy.simulate_fmu(
            str(self.fmu_path), fmi_type=self.fmi_type, start_time=fmu_t[0],
            stop_time=fmu_t[-1],
            start_values=start, input=table, output=list(dict.fromkeys(outputs)),
            relative_tolerance=self.tolerance, output_interval=float(np.min(np.diff(t))))
        times = result['time']
        pick = [int(np.argmin(np.abs(times - tk))) for tk in fmu_t]
        xdf = pd.DataFrame({m: result[v.name][pick] for m, v in
                            zip(self.state_names, self._state_vars)}, index=udf.index)
        ydf = pd.DataFrame({m: result[v.name][pick] for m, v in
                            zip(self.output_names, self._output_vars)}, index=udf.index)
        xdf.iloc[0] = x0_arr
        return ydf, xdf

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """
        Simulate B independent intervals of ``dt_s`` [s] on the one instance.

        Parameters
        ----------
        x_start : ndarray, shape (B, nx)
            Start state of each interval.
        u : ndarray, shape (B, nu)
            Inputs of each interval, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s].
        t_start_s : ndarray, shape (B,), optional
            Start time of each interval [s], caller's time base: interval b
            runs from FMU time ``t_start_s[b] - time_origin_s``. None: every
            interval starts at FMU time 0.

        Returns
        -------
        x_end : ndarray, shape (B, nx)
        y_end : ndarray, shape (B, ny)

        Raises
        ------
        FmuValueError
            If a state or output is not finite (names it and the FMU time).

        """
        x_start, u, dt_s = self._check_batch(x_start, u, dt_s)
        t0 = self._fmu_start_times(t_start_s, x_start.shape[0])
        self._plant = None  # the instance is re-initialised: a plant run ends here
        x_end = np.empty(x_start.shape)
        y_end = np.empty((x_start.shape[0], len(self.output_names)))
        if not (self._batch_in_c(x_start, u, dt_s, x_end, y_end, t0) or (
                self.me_batch_plan() is None
                and self._me_batch_in_c(x_start, u, dt_s, x_end, y_end, t_start=t0))):
            for b in range(x_start.shape[0]):
                start = 0.0 if t0 is None else float(t0[b])
                self._start_interval(x_start[b], u[b], start)
                self._advance_checked(start, start + dt_s)
                x_end[b], y_end[b] = self._read()
        if not math.isfinite(np.add.reduce(x_end, None) + np.add.reduce(y_end, None)):
            self._check_finite(x_end, y_end, dt_s if t0 is None else t0 + dt_s)
        return x_end, y_end

    def simulate_chains(self, x0: np.ndarray, u: np.ndarray, dt_s: float,
                        t_start_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Simulate C trajectories of N consecutive intervals (see :meth:`Model.simulate_chains`).

        In one batch of the compiled Model Exchange driver where it applies (each interval
        as in :meth:`simulate_intervals`, its start states the end states of the previous
        interval of its trajectory, handed on inside the driver); else, or if the batch
        fails or gives non-finite values, as N batches of :meth:`simulate_intervals`
        (which report the failure as they would).
        """
        x0 = np.atleast_2d(np.asarray(x0, dtype=float))
        u = np.asarray(u, dtype=float)
        n, chains = u.shape[0], x0.shape[0]
        # (a subclass with its own simulate_intervals, a card's unit conversions: its batches)
        if n > 1 and u.ndim == 3 and u.shape[1] == chains and self.me_batch_plan() is None \
                and type(self).simulate_intervals is FmiModel.simulate_intervals:
            # rows >= chains of the starts are not read: the driver chains the end states
            x_start, inputs, dt_s = self._check_batch(np.concatenate([x0] * n),  # (np.tile)
                                                      u.reshape(n * chains, -1), dt_s)
            times = None if t_start_s is None else np.asarray(t_start_s, dtype=float)
            t0 = self._fmu_start_times(None if times is None else times.reshape(-1),
                                       n * chains)
            self._plant = None  # the instance is re-initialised: a plant run ends here
            x_end = np.empty(x_start.shape)
            y_end = np.empty((n * chains, len(self.output_names)))
            try:
                done = self._me_batch_in_c(x_start, inputs, dt_s, x_end, y_end, t_start=t0,
                                           chain=chains)
            except RuntimeError:  # an FMI call failed: the batches below say where
                done = False
            if done is not False and math.isfinite(np.add.reduce(x_end, None)
                                                   + np.add.reduce(y_end, None)):
                return x_end.reshape(n, chains, -1), y_end.reshape(n, chains, -1)
        return super().simulate_chains(x0, u, dt_s, t_start_s)

    def _batch_in_c(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                    x_end: np.ndarray, y_end: np.ndarray,
                    t_start: np.ndarray | None = None) -> bool:
        """
        Run a Co-Simulation batch in the compiled driver; False where it does not apply.

        Applies to Co-Simulation FMUs whose parameters are all Real, after the
        first initialisation through fmpy; each interval makes the same FMI
        calls as :meth:`_initialize` + ``doStep`` + :meth:`_read`, at its FMU
        start time ``t_start[b]`` (None: 0).

        Raises
        ------
        NotBuiltError
            If the driver is not built (``make setup``).

        """
        if self.is_model_exchange or not self._initialized_once or any(
                kind != 'Real' for kind in self._parameter_groups):
            return False
        if self._cs_driver is False:  # disabled (the tests compare with the fmpy calls)
            return False
        fmu = self.fmu
        if self._cs_driver is None:
            self._cs_driver = CsBatchDriver(fmu, self.fmu_path.name)
        par_refs, par_values = self._parameter_groups.get('Real', ([], []))
        self._cs_driver.run(
            fmu.component, dt_s, self.tolerance, vr_array(par_refs),
            real_array(par_values), self._start_state_refs,
            np.ascontiguousarray(x_start[:, self._start_state_index]), self._input_refs,
            np.ascontiguousarray(u), self._state_refs, x_end, self._output_refs, y_end,
            t_start=t_start)
        return True


#: Variable mapping of the R1C1 FMU onto the names of :class:`R1C1Model`.
R1C1_VARIABLES: dict[str, Any] = {
    'inputs': ('solrad', 'Tout', 'occ', 'dpos', 'q'),
    'states': {'T': 'heatCapacitor.T'},
    'outputs': ('T', 'Qr'),
}


def r1c1_fmi_model(parameters: Any = None, fmi_type: str | None = 'CoSimulation',
                   tolerance: float = 1e-8,
                   fmu_path: str | pathlib.Path | None = None) -> FmiModel:
    """
    Return the R1C1 zone as an :class:`FmiModel` with the names of ``R1C1Model``.

    Inputs ``solrad, Tout, occ, dpos, q``; state ``T`` [K] (the FMU's
    ``heatCapacitor.T``); outputs ``T`` [degC] and ``Qr`` [J].

    Parameters
    ----------
    parameters : R1C1Parameters or mapping, optional
        Zone parameters (default: the calibrated OU44 values, the FMU's defaults).
    fmi_type : {'CoSimulation', 'ModelExchange'} or None
        Co-Simulation (default) steps with the exact solution; Model Exchange
        integrates with CVode and offers :meth:`FmiModel.interval_jacobians`.
    tolerance : float
        Relative integrator tolerance (Model Exchange).
    fmu_path : path, optional
        An R1C1 FMU; default the built-in one, built by ``make setup`` and
        found in the FMU cache (:func:`mshoot_core.fmu_cache.find_fmu`).

    Raises
    ------
    NotBuiltError
        Without ``fmu_path``, if the built-in FMU is not built (the message
        names the command that builds it).

    """
    if parameters is None:
        values: dict[str, Any] = {}
    elif dataclasses.is_dataclass(parameters):
        values = dataclasses.asdict(parameters)
    else:
        values = dict(parameters)
    builtin = fmu_path is None
    if builtin:
        fmu_path = find_fmu('r1c1')
    # the built-in FMU is the RC network of R1C1Model: monotone as that network's structure
    # says, in T and q (another file of the same names makes no such claim)
    return FmiModel(fmu_path, parameters=values, tolerance=tolerance, fmi_type=fmi_type,
                    monotone_inputs=R1C1Model().monotone_inputs if builtin else (),
                    **R1C1_VARIABLES)
