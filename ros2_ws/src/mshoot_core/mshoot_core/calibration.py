"""
Calibration: fit named parameters of a zone model to measured data by least squares.

A :class:`Period` is a stretch of measurements: the model's inputs held over
each row, the start state (from the measured output at the first row) and the
measured output. :func:`calibrate` simulates every training period freely
(no state correction) from its start state, minimises the residuals
(simulated - measured) / ``noise`` over the free parameters within their
bounds (:func:`scipy.optimize.least_squares`, from one or several starts),
with optional Gaussian priors as extra residuals, then reports per period the
RMSE and MAE [K], the parameters with approximate confidence intervals from
the Jacobian at the optimum (covariance ``s^2 (J^T J)^-1``), and warnings for
parameters at a bound or strongly correlated.

The model is rebuilt for every parameter vector by a ``build(parameters)``
callable: :func:`r1c1_builder` for the Python R1C1, :func:`r2c2_builder` for the
Python R2C2 (analytic Jacobian too), :func:`model_builder` for
any Python model built from a parameters dataclass, :func:`card_builder` for
the model of a card and :func:`fmi_builder` for any FMU model (an FMU's
parameters are set before every initialisation), :func:`registry_builder`
for a model name of the registry. :func:`ou44_periods` makes the periods of the OU44 reference
calibration from the measurements.

The Jacobian of the residuals with respect to the parameters is analytic
where the model has parameter sensitivities (``parameter_sensitivities``,
e.g. the exact R1C1's forward sensitivities), else forward finite
differences: one batched simulation of all perturbed parameter vectors when
the builder can batch them (``simulate_batch``), one simulation per parameter
otherwise. :func:`cross_validate` scores a fit setup on held-out blocks of a
training period (the rest of the period fitted), without a validation period.

Learned (scikit-learn) zone models are fitted by :func:`fit_learned` on the
same periods and scored the same way: the regressor learns the temperature
increment over one row from the measured temperature and the inputs held
over the row, on the training rows only, then every period is simulated
freely from its first measured temperature. A :class:`LearnedResult`
describes the regressor (and, for a linear one, its coefficients in
physical units and the equivalent R1C1: :func:`r1c1_equivalent`); it has no
confidence intervals.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import pathlib
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd
import scipy.optimize
import scipy.stats

from mshoot_core.models.base import Model
from mshoot_core.scenario import OU44_COLUMNS, read_ou44
from mshoot_core.units import json_ready

__all__ = ['calibrate', 'CalibrationResult', 'card_builder', 'cross_validate', 'fmi_builder',
           'NetworkBuilder',
           'fit_learned', 'FreeParameter', 'JACOBIANS', 'LearnedResult',
           'LEARNED_UNCERTAINTY', 'LOSSES', 'metrics', 'model_builder', 'ModelBuilder',
           'OU44_FIXED', 'OU44_FREE', 'OU44_MAX_HEAT_W', 'OU44_STUDY_BOUNDS', 'OU44_STUDY_FREE',
           'OU44_TRAIN', 'OU44_VALIDATION', 'ou44_periods', 'Period', 'r1c1_builder',
           'r1c1_equivalent',
           'r2c2_builder', 'registry_builder', 'simulate_period']
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: |correlation| above which two parameters are reported as strongly correlated.
CORRELATION_WARNING = 0.95
#: Distance to a bound, as a fraction of the bounds' span, reported as 'at a bound'.
BOUND_WARNING = 1e-3
#: Seconds between two progress messages of a fit.
PROGRESS_S = 5.0
#: Robust losses of :func:`scipy.optimize.least_squares` ('linear': plain least squares).
LOSSES = ('linear', 'soft_l1', 'huber', 'cauchy', 'arctan')
#: Jacobian methods: 'auto' (analytic where the model has it, else 'fd'), 'analytic', 'fd'
#: (forward differences, batched where the builder can), and scipy's own '2-point'/'3-point'.
JACOBIANS = ('auto', 'analytic', 'fd', '2-point', '3-point')
#: Relative step of the forward differences (scaled by max(|value|, 1e-3 * bounds' span)).
FD_STEP = 1.5e-8

#: Radiator power at a fully open valve (vpos = 100 %) [W] of the OU44 classroom.
OU44_MAX_HEAT_W = 2689.0
#: The OU44 reference calibration's training and validation periods (local time, inclusive).
OU44_TRAIN = ('2018-04-04 08:00', '2018-04-09 08:00')
OU44_VALIDATION = ('2018-04-09 08:00', '2018-04-13 08:00')
#: Fixed parameters of the OU44 R1C1 calibration.
OU44_FIXED = {'Tve': 21.0, 'Vi': 486.5, 'maxVent': 4800.0}


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """
    One parameter to fit.

    Attributes
    ----------
    name : str
        Parameter name, as the model builder knows it.
    initial : float
        Start value of the fit (the first start).
    lower, upper : float
        Bounds (lower < upper, initial within them).
    prior_mean, prior_sd : float or None
        Optional Gaussian prior: adds ``(value - prior_mean) / prior_sd`` to
        the residuals (both or neither).

    """

    name: str
    initial: float
    lower: float
    upper: float
    prior_mean: float | None = None
    prior_sd: float | None = None

    def __post_init__(self) -> None:
        values = (self.initial, self.lower, self.upper)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise ValueError(f'parameter {self.name}: initial, lower and upper must be finite '
                             f'numbers, got {values}')
        if not self.lower < self.upper:
            raise ValueError(f'parameter {self.name}: lower {self.lower:g} must be below upper '
                             f'{self.upper:g}')
        if not self.lower <= self.initial <= self.upper:
            raise ValueError(f'parameter {self.name}: initial {self.initial:g} outside '
                             f'[{self.lower:g}, {self.upper:g}]')
        if (self.prior_mean is None) != (self.prior_sd is None):
            raise ValueError(f'parameter {self.name}: a prior needs both prior_mean and '
                             'prior_sd')
        if self.prior_sd is not None and not self.prior_sd > 0:
            raise ValueError(f'parameter {self.name}: prior_sd must be > 0, got '
                             f'{self.prior_sd}')


@dataclasses.dataclass(frozen=True)
class Period:
    """
    A stretch of measurements, simulated freely from its first row.

    Attributes
    ----------
    name : str
        Label (e.g. 'train', 'validation').
    inputs : DataFrame
        Model inputs indexed by time [s], held over each row (the last row
        only ends the previous interval).
    x0 : ndarray
        Start state of the model [its state units].
    measured : ndarray
        Measured output at every row [output unit, degC for T].
    output : str
        Name of the model output compared with ``measured``.
    timestamps : DatetimeIndex or None
        Wall-clock time of the rows, for the figure.
    weights : ndarray or None
        Weight of each row's residual in the fit (>= 0; row 0, the start
        state, is never fitted); None: all 1. The reported RMSE and MAE are
        unweighted.

    """

    name: str
    inputs: pd.DataFrame
    x0: np.ndarray
    measured: np.ndarray
    output: str = 'T'
    timestamps: pd.DatetimeIndex | None = None
    weights: np.ndarray | None = None

    def __post_init__(self) -> None:
        measured = np.asarray(self.measured, dtype=float).reshape(-1)
        if measured.size != len(self.inputs) or measured.size < 2:
            raise ValueError(f'period {self.name}: {measured.size} measured values for '
                             f'{len(self.inputs)} rows of inputs (need at least two)')
        if not np.all(np.isfinite(measured)):
            raise ValueError(f'period {self.name}: the measured {self.output} has gaps')
        object.__setattr__(self, 'measured', measured)
        object.__setattr__(self, 'x0', np.asarray(self.x0, dtype=float).reshape(-1))
        if self.weights is not None:
            weights = np.asarray(self.weights, dtype=float).reshape(-1)
            if weights.size != measured.size or not np.all(np.isfinite(weights)) \
                    or np.any(weights < 0) or not np.any(weights[1:] > 0):
                raise ValueError(f'period {self.name}: weights must be {measured.size} finite '
                                 'values >= 0, some of rows 1.. positive')
            object.__setattr__(self, 'weights', weights)

    @property
    def root_weights(self) -> np.ndarray:
        """Square roots of the weights of rows 1..N (the residuals' factors)."""
        if self.weights is None:
            return np.ones(self.measured.size - 1)
        return np.sqrt(self.weights[1:])


@dataclasses.dataclass
class CalibrationResult:
    """
    What :func:`calibrate` found.

    Attributes
    ----------
    parameters : dict of str -> float
        Fitted values of the free parameters.
    std : dict of str -> float
        Approximate standard deviations (nan if the Jacobian is singular).
    ci95 : dict of str -> (float, float)
        Approximate 95 % confidence intervals, clipped to the bounds (not
        meaningful for a parameter at a bound: see the warnings).
    correlation : ndarray
        Correlation matrix of the free parameters (their order).
    metrics : dict of str -> dict
        Period name -> {'rmse_k', 'mae_k', 'rows'} at the fitted parameters.
    warnings : list of str
        Parameters at a bound, strongly correlated ones, an unidentifiable fit.
    cost : float
        Half the sum of squared residuals at the optimum.
    evaluations : int
        Model simulations of all periods run by the fit (a batched
        simulation of B parameter vectors counts B).
    jacobians : int
        Jacobian evaluations of the fit.
    jac : str
        How the Jacobian was computed ('analytic', 'fd', 'fd-batched',
        '2-point', '3-point').
    loss : str
        The fit criterion (:data:`LOSSES`).
    starts : list of dict
        Per start: initial values, final values, cost.
    success : bool
        Whether the best start converged.
    message : str
        The optimiser's message for the best start.
    wall_s : float
        Wall time of the fit [s].
    simulated : dict of str -> ndarray
        Period name -> simulated output at every row, fitted parameters.

    """

    parameters: dict[str, float]
    std: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    correlation: np.ndarray
    metrics: dict[str, dict[str, float]]
    warnings: list[str]
    cost: float
    evaluations: int
    jacobians: int
    jac: str
    loss: str
    starts: list[dict[str, Any]]
    success: bool
    message: str
    wall_s: float
    simulated: dict[str, np.ndarray]

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON-ready summary (no simulated series)."""
        names = list(self.parameters)
        return {'parameters': dict(self.parameters), 'std': dict(self.std),
                'ci95': {k: list(v) for k, v in self.ci95.items()},
                'correlation': {a: {b: float(self.correlation[i, j])
                                    for j, b in enumerate(names)}
                                for i, a in enumerate(names)},
                'metrics': self.metrics, 'warnings': list(self.warnings),
                'cost': self.cost, 'evaluations': self.evaluations, 'jacobians': self.jacobians,
                'jac': self.jac, 'loss': self.loss, 'starts': self.starts,
                'success': self.success, 'message': self.message, 'wall_s': self.wall_s}


Builder = Callable[[Mapping[str, float]], Model]


def simulate_period(model: Model, period: Period) -> np.ndarray:
    """
    Simulate ``period`` freely from its start state; return the output at every row.

    Parameters
    ----------
    model : Model
        The model (its inputs are taken from ``period.inputs`` by name).
    period : Period
        The period.

    Returns
    -------
    ndarray, shape (rows,)
        The simulated ``period.output`` [its unit].

    """
    udf = period.inputs[list(model.input_names)]
    ydf, _ = model.simulate(udf, period.x0)
    return ydf[period.output].to_numpy(dtype=float)


def metrics(simulated: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """
    Return the RMSE and MAE [K] of ``simulated`` against ``measured`` over rows 1..N.

    Row 0 is the start state (taken from the measurement) and is left out.
    """
    error = np.asarray(simulated, dtype=float)[1:] - np.asarray(measured, dtype=float)[1:]
    return {'rmse_k': float(np.sqrt(np.mean(error ** 2))),
            'mae_k': float(np.mean(np.abs(error))), 'rows': int(error.size)}


class ModelBuilder:
    """
    Builder of a Python model from its parameters dataclass, for :func:`calibrate`.

    ``build(parameters)`` returns ``model_cls(parameters_cls(**fixed,
    **parameters))``. When ``model_cls`` has ``simulate_parameter_batch``
    (a model whose parameters may be arrays, one value per parameter
    vector, returning its outputs of shape (rows, outputs, B)),
    :meth:`simulate_batch` simulates many parameter vectors in one call: the
    batched finite differences of :func:`calibrate`.

    Parameters
    ----------
    model_cls : type
        The model class, constructed from one parameters object.
    parameters_cls : type
        Its parameters dataclass.
    fixed : mapping, optional
        Fields held fixed (the others keep their defaults unless fitted).
    label : str, optional
        The model's name in messages (default: the class name).

    Raises
    ------
    ValueError
        For a name that is not a field of ``parameters_cls``.

    """

    def __init__(self, model_cls: type, parameters_cls: type,
                 fixed: Mapping[str, float] | None = None, label: str | None = None) -> None:
        if not dataclasses.is_dataclass(parameters_cls):
            raise TypeError(f'parameters_cls must be a dataclass, got {parameters_cls!r}')
        self.model_cls = model_cls
        self.parameters_cls = parameters_cls
        self.label = label or model_cls.__name__
        self.names = frozenset(f.name for f in dataclasses.fields(parameters_cls))
        self.fixed = dict(fixed or {})
        self._check(self.fixed)

    def _check(self, parameters: Mapping[str, Any]) -> None:
        unknown = sorted(set(parameters) - self.names)
        if unknown:
            raise ValueError(f'unknown {self.label} parameters {unknown}; '
                             f'expected names from {sorted(self.names)}')

    def __call__(self, parameters: Mapping[str, float]) -> Model:
        """Return the model with ``parameters`` (name -> value) over the fixed ones."""
        self._check(parameters)
        return self.model_cls(self.parameters_cls(
            **{**self.fixed, **{k: float(v) for k, v in parameters.items()}}))

    @property
    def can_batch(self) -> bool:
        """Whether :meth:`simulate_batch` runs all parameter vectors in one simulation."""
        return hasattr(self.model_cls, 'simulate_parameter_batch')

    def simulate_batch(self, parameter_sets: Sequence[Mapping[str, float]],
                       period: Period) -> np.ndarray:
        """
        Simulate ``period`` for every parameter vector; return the output (B, rows).

        One batched simulation when :attr:`can_batch`: the model's
        ``simulate_parameter_batch(udf, x0)`` returns its outputs (rows,
        outputs, B) for parameters that are arrays of B values; else one
        simulation per vector.
        """
        keys = {tuple(sorted(values)) for values in parameter_sets}
        if not self.can_batch or len(keys) != 1:
            return np.array([simulate_period(self(values), period) for values in parameter_sets])
        for values in parameter_sets:
            self._check(values)
        columns = {name: np.array([float(values[name]) for values in parameter_sets])
                   for name in keys.pop()}
        model = self.model_cls(self.parameters_cls(**{**self.fixed, **columns}))
        udf = period.inputs[list(model.input_names)]
        outputs = model.simulate_parameter_batch(udf, period.x0)
        return outputs[:, list(model.output_names).index(period.output), :].T


def model_builder(model_cls: type, parameters_cls: type,
                  fixed: Mapping[str, float] | None = None,
                  label: str | None = None) -> ModelBuilder:
    """
    Return a builder of ``model_cls(parameters_cls(...))`` (see :class:`ModelBuilder`).

    For any Python model constructed from a parameters dataclass; the
    Jacobian of a fit is analytic when the model has
    ``parameter_sensitivities(udf, x0, names)``.
    """
    return ModelBuilder(model_cls, parameters_cls, fixed, label)


def r1c1_builder(fixed: Mapping[str, float] | None = None) -> ModelBuilder:
    """
    Return a builder of the Python R1C1 with ``fixed`` parameters and the free ones given.

    Parameters
    ----------
    fixed : mapping, optional
        Fields of :class:`~mshoot_core.models.r1c1.R1C1Parameters` held fixed
        (the others default to the published values unless fitted).

    """
    from mshoot_core.models.r1c1 import R1C1Model, R1C1Parameters
    return ModelBuilder(R1C1Model, R1C1Parameters, fixed, label='R1C1')


def r2c2_builder(fixed: Mapping[str, float] | None = None) -> ModelBuilder:
    """
    Return a builder of the Python R2C2 with ``fixed`` parameters and the free ones given.

    The Jacobian of a fit is analytic (the R2C2's exact
    ``parameter_sensitivities``); only the air temperature ``T`` is compared,
    the envelope ``Tw`` starts where the period's ``x0`` says.

    Parameters
    ----------
    fixed : mapping, optional
        Fields of :class:`~mshoot_core.models.r2c2.R2C2Parameters` held fixed
        (the others keep their defaults unless fitted).

    """
    from mshoot_core.models.r2c2 import R2C2Model, R2C2Parameters
    return ModelBuilder(R2C2Model, R2C2Parameters, fixed, label='R2C2')


def fmi_builder(model: Any, fixed: Mapping[str, float] | None = None) -> Builder:
    """
    Return a builder of an FMU model (:class:`~mshoot_core.models.fmi.FmiModel`).

    The model is built once (its instance and drivers); ``build(parameters)``
    replaces its parameters (``fixed`` overlaid by the given ones), which
    :class:`FmiModel` validates and sets after every reset, before
    initialisation. The Jacobian of a fit is then a finite difference, one
    simulation per parameter.

    Parameters
    ----------
    model : FmiModel
        The model, with any parameters of its own.
    fixed : mapping, optional
        Parameters held fixed over the model's own.

    Raises
    ------
    TypeError
        If ``model`` cannot set parameters.

    """
    if not hasattr(model, '_set_parameters_plan'):
        raise TypeError(f'{type(model).__name__} has no settable parameters; use '
                        'model_builder for a Python model')
    base = {**dict(getattr(model, 'parameters', {}) or {}), **dict(fixed or {})}
    inputs = dict(model.fixed_inputs)

    def build(parameters: Mapping[str, float]) -> Model:
        values = {**base, **{k: float(v) for k, v in parameters.items()}}
        model._set_parameters_plan(values, inputs)  # names checked, set at every initialisation
        return model

    return build


def card_builder(card: Any, tolerance: float | None = None,
                 fixed: Mapping[str, float] | None = None) -> Builder:
    """
    Return a builder of a model card's model with the given parameters.

    For an FMU the model is built once and its parameters replaced before
    each simulation (:func:`fmi_builder`); a thermal network is rebuilt
    (:class:`NetworkBuilder`, analytic Jacobian).

    Parameters
    ----------
    card : ModelCard or path
        The card (see :mod:`mshoot_core.models.card`); its ``parameters`` are
        fixed.
    tolerance : float, optional
        Integrator tolerance when the card sets none (default: the control
        role's).
    fixed : mapping, optional
        Parameters held fixed over the card's.

    """
    from mshoot_core.models import card as cards
    if not isinstance(card, cards.ModelCard):
        card = cards.load_card(card)
    if card.network is not None:
        return NetworkBuilder(card, fixed)
    model = cards.build_model(card, role='control', tolerance=tolerance)
    return fmi_builder(model, fixed)


class NetworkBuilder:
    """
    Builder of a thermal network card's model with given parameters, for :func:`calibrate`.

    ``build(parameters)`` is the card's model with the card's parameters, ``fixed`` and
    ``parameters`` over the network's values; the Jacobian of a fit is analytic (the
    network's ``parameter_sensitivities``).

    Parameters
    ----------
    card : ModelCard
        A card with a network (its own section or ``builtin: r1c1`` / ``r2c2``).
    fixed : mapping, optional
        Parameters held fixed over the card's.

    Raises
    ------
    ValueError
        For a name that is not a parameter of the network.

    """

    def __init__(self, card: Any, fixed: Mapping[str, float] | None = None) -> None:
        self.card = card
        self.names = tuple(card.network.parameters)
        self.fixed = {**card.parameters, **dict(fixed or {})}
        self._check(self.fixed)

    def _check(self, parameters: Mapping[str, Any]) -> None:
        unknown = sorted(set(parameters) - set(self.names))
        if unknown:
            raise ValueError(f'unknown network parameters {unknown}; expected names from '
                             f'{list(self.names)}')

    def __call__(self, parameters: Mapping[str, float]) -> Model:
        """Return the model with ``parameters`` (name -> value) over the fixed ones."""
        from mshoot_core.models import card as cards
        self._check(parameters)
        values = {**self.fixed, **{k: float(v) for k, v in parameters.items()}}
        return cards.build_model(dataclasses.replace(self.card, parameters=values))


def registry_builder(name: str, fixed: Mapping[str, float] | None = None,
                     tolerance: float | None = None) -> Builder:
    """
    Return a builder of a model of the registry (:mod:`mshoot_core.models.registry`) by name.

    Parameters
    ----------
    name : str
        'python' (the exact R1C1, analytic Jacobian), 'r2c2' (the exact
        R2C2, analytic Jacobian), 'fmu' or 'fmu-cs' (the
        built-in R1C1 FMU), a path to an .fmu file with the R1C1's variables,
        or a model card (.yaml).
    fixed : mapping, optional
        Parameters held fixed (the model's defaults otherwise).
    tolerance : float, optional
        Integrator tolerance of an FMU (default: the control role's).

    Raises
    ------
    ValueError
        For a name whose models are built without settable parameters (the
        multi-zone model, registered data-driven models) or an unknown name.

    """
    from mshoot_core.models import registry
    if name == 'python':
        return r1c1_builder(fixed)
    if name == 'r2c2':
        return r2c2_builder(fixed)
    if registry.is_card_path(name):
        return card_builder(name, tolerance, fixed)
    if name in ('fmu', 'fmu-cs') or str(name).endswith('.fmu'):
        return fmi_builder(registry.build_model(
            name, registry.CONTROL_TOLERANCE if tolerance is None else tolerance), fixed)
    problem = registry.check_model(name)
    raise ValueError(problem or f'model {name!r} is built without settable parameters; '
                     'calibrate a model card or a Python model (model_builder) instead')


class _Problem:
    """The residuals of a fit and their Jacobian over scaled parameters theta = value / scale."""

    def __init__(self, build: Builder, free: Sequence[FreeParameter], periods: Sequence[Period],
                 noise: float, fd_step: float = FD_STEP) -> None:
        self.build = build
        self.free = list(free)
        self.names = [p.name for p in self.free]
        self.periods = list(periods)
        self.noise = noise
        self.fd_step = fd_step
        self.scale = np.array([max(abs(p.initial), abs(p.lower), abs(p.upper)) or 1.0
                               for p in self.free])
        self.lower = np.array([p.lower for p in self.free])
        self.upper = np.array([p.upper for p in self.free])
        self.evaluations = 0
        self.jacobians = 0
        self.started = time.monotonic()
        self.last_report = self.started
        self.best = math.inf
        self._last: tuple[np.ndarray, list[np.ndarray]] | None = None

    def values(self, theta: np.ndarray) -> dict[str, float]:
        return {p.name: float(v) for p, v in zip(self.free, np.asarray(theta) * self.scale)}

    def simulate(self, values: Mapping[str, float]) -> list[np.ndarray]:
        model = self.build(values)
        self.evaluations += 1
        return [simulate_period(model, period) for period in self.periods]

    @property
    def size(self) -> int:
        return sum(len(p.measured) - 1 for p in self.periods) + len(self.priors)

    def _residuals_of(self, values: Mapping[str, float],
                      outputs: Sequence[np.ndarray]) -> np.ndarray:
        parts = [p.root_weights * (y[1:] - p.measured[1:]) / self.noise
                 for y, p in zip(outputs, self.periods)]
        parts.append(np.array([(values[p.name] - p.prior_mean) / p.prior_sd
                               for p in self.priors]))
        return np.concatenate(parts)

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        values = self.values(theta)
        try:
            outputs = self.simulate(values)
        except (ValueError, ArithmeticError) as error:
            logger.debug('simulation failed at %s: %s', values, error)
            self._last = None
            return np.full(self.size, 1e6)
        self._last = (np.array(theta, dtype=float), outputs)
        r = self._residuals_of(values, outputs)
        cost = 0.5 * float(r @ r)
        self.best = min(self.best, cost)
        self._progress()
        return r

    def _progress(self) -> None:
        now = time.monotonic()
        if now - self.last_report >= PROGRESS_S:
            self.last_report = now
            logger.info('calibration: %d simulations, %d Jacobians, %.1f s, best cost %.6g',
                        self.evaluations, self.jacobians, now - self.started, self.best)

    # -- the Jacobian d r / d theta -----------------------------------------------------------
    def analytic_available(self) -> bool:
        """Whether the model has parameter sensitivities for every period's output."""
        model = self.build({p.name: p.initial for p in self.free})
        return hasattr(model, 'parameter_sensitivities') and all(
            p.output in model.output_names for p in self.periods)

    def _data_rows(self, dy: Sequence[np.ndarray]) -> np.ndarray:
        """Rows of the data residuals from d output / d value (rows, n) per period."""
        return np.vstack([(p.root_weights / self.noise)[:, None] * d[1:]
                          for d, p in zip(dy, self.periods)])

    def _prior_rows(self) -> np.ndarray:
        rows = np.zeros((len(self.priors), len(self.free)))
        for i, prior in enumerate(self.priors):
            rows[i, self.names.index(prior.name)] = 1.0 / prior.prior_sd
        return rows

    def jacobian_analytic(self, theta: np.ndarray) -> np.ndarray:
        values = self.values(theta)
        model = self.build(values)
        self.evaluations += 1
        self.jacobians += 1
        dy = []
        for period in self.periods:
            udf = period.inputs[list(model.input_names)]
            _, sens = model.parameter_sensitivities(udf, period.x0, self.names)
            dy.append(sens[:, list(model.output_names).index(period.output), :])
        self._progress()
        return np.vstack([self._data_rows(dy), self._prior_rows()]) * self.scale[None, :]

    def fd_steps(self, theta: np.ndarray) -> np.ndarray:
        """Forward steps in values, turned backward where the upper bound is near."""
        values = np.asarray(theta) * self.scale
        step = self.fd_step * np.maximum(np.abs(values), 1e-3 * (self.upper - self.lower))
        return np.where(values + step > self.upper, -step, step)

    def jacobian_fd(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, dtype=float)
        base = self.values(theta)
        steps = self.fd_steps(theta)
        perturbed = [{**base, name: base[name] + h} for name, h in zip(self.names, steps)]
        self.jacobians += 1
        batch = getattr(self.build, 'simulate_batch', None)
        if batch is not None and getattr(self.build, 'can_batch', False):
            # one batched simulation per period of the base and all perturbed vectors
            outputs = [batch([base, *perturbed], period) for period in self.periods]
            self.evaluations += len(perturbed) + 1
            y0 = [y[0] for y in outputs]
            columns = [[y[j + 1] for y in outputs] for j in range(len(perturbed))]
        else:
            if self._last is not None and np.array_equal(self._last[0], theta):
                y0 = self._last[1]
            else:
                y0 = self.simulate(base)
            columns = [self.simulate(values) for values in perturbed]
        dy = [np.column_stack([(columns[j][i] - y0[i]) / steps[j] for j in range(len(steps))])
              for i in range(len(self.periods))]
        self._progress()
        return np.vstack([self._data_rows(dy), self._prior_rows()]) * self.scale[None, :]

    @property
    def priors(self) -> list[FreeParameter]:
        return [p for p in self.free if p.prior_sd is not None]


def _start_points(free: Sequence[FreeParameter], starts: int,
                  seed: int) -> list[np.ndarray]:
    """Return the first start (the initial values) and ``starts - 1`` uniform draws in bounds."""
    rng = np.random.default_rng(seed)
    points = [np.array([p.initial for p in free])]
    lower = np.array([p.lower for p in free])
    upper = np.array([p.upper for p in free])
    for _ in range(starts - 1):
        points.append(lower + (upper - lower) * rng.uniform(0.05, 0.95, size=len(free)))
    return points


def calibrate(build: Builder, free: Sequence[FreeParameter], train: Sequence[Period],
              validation: Sequence[Period] = (), starts: int = 1, seed: int = 0,
              noise: float = 1.0, xtol: float = 1e-10, max_evaluations: int | None = None,
              jac: str = 'auto', loss: str = 'linear', f_scale: float = 1.0,
              fd_step: float = FD_STEP) -> CalibrationResult:
    """
    Fit the ``free`` parameters to the ``train`` periods; score every period.

    Parameters
    ----------
    build : callable
        ``build(parameters) -> Model`` for a mapping name -> value of the
        free parameters (:func:`r1c1_builder`, :func:`model_builder`,
        :func:`card_builder`).
    free : sequence of FreeParameter
        The parameters to fit, their start values, bounds and priors.
    train : sequence of Period
        The periods fitted (their ``weights`` weight the residuals).
    validation : sequence of Period
        Periods only scored.
    starts : int
        Number of starts: the initial values, then uniform draws within the
        bounds (seeded by ``seed``); the best fit wins.
    seed : int
        Seed of the random starts.
    noise : float
        Measurement noise standard deviation [K]: the data residuals are
        divided by it (matters only next to priors or a robust loss).
    xtol, max_evaluations : float, int
        Stopping rules of :func:`scipy.optimize.least_squares` (``xtol``,
        ``max_nfev`` per start).
    jac : str
        The Jacobian (:data:`JACOBIANS`): 'auto' is 'analytic' when the
        model has ``parameter_sensitivities`` for the periods' output, else
        'fd' (forward differences of relative step ``fd_step``, one batched
        simulation when the builder can batch parameter vectors);
        '2-point'/'3-point' let scipy difference the residuals.
    loss, f_scale : str, float
        Fit criterion of :func:`scipy.optimize.least_squares`: 'linear'
        (least squares) or a robust loss (:data:`LOSSES`) whose residuals
        beyond ``f_scale`` (in units of ``noise``) weigh less.
    fd_step : float
        Relative step of the finite differences.

    Returns
    -------
    CalibrationResult
        The confidence intervals come from the plain least-squares
        covariance at the optimum (also for a robust loss: approximate).

    Raises
    ------
    ValueError
        For no free parameters, duplicate names, no training period, a bad
        number of starts, noise, Jacobian method, loss or step, or
        ``jac='analytic'`` for a model without parameter sensitivities.

    """
    free = list(free)
    if not free:
        raise ValueError('calibrate needs at least one free parameter')
    names = [p.name for p in free]
    if len(set(names)) != len(names):
        raise ValueError(f'duplicate free parameters in {names}')
    if not train:
        raise ValueError('calibrate needs at least one training period')
    if isinstance(starts, bool) or not isinstance(starts, int) or starts < 1:
        raise ValueError(f'starts must be an integer >= 1, got {starts!r}')
    for label, value in (('noise', noise), ('f_scale', f_scale), ('fd_step', fd_step)):
        if isinstance(value, bool) or not (isinstance(value, (int, float))
                                           and math.isfinite(value) and value > 0):
            raise ValueError(f'{label} must be a positive number, got {value!r}')
    if jac not in JACOBIANS:
        raise ValueError(f'jac must be one of {list(JACOBIANS)}, got {jac!r}')
    if loss not in LOSSES:
        raise ValueError(f'loss must be one of {list(LOSSES)}, got {loss!r}')
    t0 = time.perf_counter()
    problem = _Problem(build, free, train, float(noise), float(fd_step))
    analytic = problem.analytic_available()
    if jac == 'analytic' and not analytic:
        raise ValueError('jac=analytic: the model has no parameter_sensitivities for the '
                         f'output {train[0].output!r}; use jac=fd')
    method = 'analytic' if jac == 'auto' and analytic else ('fd' if jac == 'auto' else jac)
    jacobian = {'analytic': problem.jacobian_analytic, 'fd': problem.jacobian_fd}.get(method,
                                                                                      method)
    if method == 'fd' and getattr(build, 'can_batch', False):
        method = 'fd-batched'
    lower = problem.lower / problem.scale
    upper = problem.upper / problem.scale
    best, records = None, []
    for k, start in enumerate(_start_points(free, starts, seed)):
        theta0 = np.clip(start / problem.scale, lower, upper)
        fit = scipy.optimize.least_squares(problem.residuals, theta0, jac=jacobian,
                                           bounds=(lower, upper), method='trf', x_scale='jac',
                                           xtol=xtol, ftol=1e-12, gtol=1e-12,
                                           max_nfev=max_evaluations, loss=loss,
                                           f_scale=float(f_scale))
        records.append({'initial': problem.values(theta0), 'final': problem.values(fit.x),
                        'cost': float(fit.cost), 'success': bool(fit.success)})
        logger.info('calibration start %d/%d: cost %.6g (%s)', k + 1, starts, fit.cost,
                    fit.message)
        if best is None or fit.cost < best.cost:
            best = fit
    values = problem.values(best.x)
    for p in free:  # undo the round-off of the scaling at a bound
        span = p.upper - p.lower
        values[p.name] = min(max(values[p.name], p.lower), p.upper)
        for bound in (p.lower, p.upper):
            if abs(values[p.name] - bound) <= 1e-12 * span:
                values[p.name] = bound
    # the plain residuals and their Jacobian at the optimum (scipy's are loss-modified)
    theta = np.array([values[name] for name in names]) / problem.scale
    final_jac = (problem.jacobian_analytic if analytic else problem.jacobian_fd)(theta)
    std, ci95, correlation, warnings = _uncertainty(problem.residuals(theta), final_jac,
                                                    problem, free, values)
    model = build(values)
    simulated, scores = {}, {}
    for period in [*train, *validation]:
        simulated[period.name] = simulate_period(model, period)
        scores[period.name] = metrics(simulated[period.name], period.measured)
    wall_s = time.perf_counter() - t0
    logger.info('calibration done in %.2f s, %d simulations, %d Jacobians (%s): %s', wall_s,
                problem.evaluations, problem.jacobians, method,
                ', '.join(f'{k} = {v:.6g}' for k, v in values.items()))
    return CalibrationResult(values, std, ci95, correlation, scores, warnings, float(best.cost),
                             problem.evaluations, problem.jacobians, method, loss, records,
                             bool(best.success), str(best.message), wall_s, simulated)


def cross_validate(build: Builder, free: Sequence[FreeParameter], period: Period,
                   folds: int = 5, **options: Any) -> dict[str, Any]:
    """
    Score a fit setup on held-out blocks of one training period.

    Rows 1..N are cut into ``folds`` consecutive blocks. For each block the
    parameters are fitted to the other rows (the block's weights set to 0;
    the whole period is still simulated freely from its first row, the
    inputs being measured), and the block's rows are scored. No validation
    period is involved: this chooses between fit setups (bounds, priors,
    losses, weights) on the training data alone.

    Parameters
    ----------
    build, free
        As for :func:`calibrate`.
    period : Period
        The training period.
    folds : int
        Number of blocks (2 or more; each at least two rows).
    **options
        Passed to :func:`calibrate` (starts, jac, loss, f_scale, noise ...).

    Returns
    -------
    dict
        ``rmse_k`` (over all held-out rows), ``mae_k`` and ``folds``: per
        block its first and last row, ``rmse_k`` and fitted ``parameters``.

    Raises
    ------
    ValueError
        For a bad number of folds.

    """
    rows = len(period.measured) - 1
    if isinstance(folds, bool) or not isinstance(folds, int) or not 2 <= folds <= rows // 2:
        raise ValueError(f'folds must be an integer from 2 to {rows // 2}, got {folds!r}')
    base = np.ones(rows + 1) if period.weights is None else period.weights
    errors, out = [], []
    for block in np.array_split(np.arange(1, rows + 1), folds):
        weights = base.copy()
        weights[block] = 0.0
        fitted = calibrate(build, free, [dataclasses.replace(period, weights=weights)],
                           **options)
        simulated = simulate_period(build(fitted.parameters), period)
        error = simulated[block] - period.measured[block]
        errors.append(error)
        out.append({'rows': [int(block[0]), int(block[-1])],
                    'rmse_k': float(np.sqrt(np.mean(error ** 2))),
                    'parameters': fitted.parameters})
    error = np.concatenate(errors)
    return {'rmse_k': float(np.sqrt(np.mean(error ** 2))),
            'mae_k': float(np.mean(np.abs(error))), 'folds': out}


def _uncertainty(residuals: np.ndarray, jac_theta: np.ndarray, problem: _Problem,
                 free: Sequence[FreeParameter], values: Mapping[str, float]
                 ) -> tuple[dict, dict, np.ndarray, list[str]]:
    """Covariance s^2 (J^T J)^-1 at the optimum; confidence intervals; warnings."""
    n = len(free)
    m = residuals.size
    jac = np.asarray(jac_theta, dtype=float) / problem.scale[None, :]  # d r / d value
    dof = max(m - n, 1)
    s2 = float(residuals @ residuals) / dof
    warnings = []
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
        if not np.all(np.isfinite(cov)):
            raise np.linalg.LinAlgError('non-finite covariance')
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.nan)
        warnings.append('the Jacobian at the optimum is singular: parameters not identifiable '
                        'from these data')
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid='ignore', divide='ignore'):
        correlation = cov / np.outer(sd, sd)
    quantile = float(scipy.stats.t.ppf(0.975, dof))
    std = {p.name: float(s) for p, s in zip(free, sd)}
    ci95 = {p.name: (max(values[p.name] - quantile * s, p.lower),
                     min(values[p.name] + quantile * s, p.upper)) for p, s in zip(free, sd)}
    for p in free:
        margin = BOUND_WARNING * (p.upper - p.lower)
        if values[p.name] <= p.lower + margin:
            warnings.append(f'{p.name} = {values[p.name]:.6g} is at its lower bound {p.lower:g}')
        elif values[p.name] >= p.upper - margin:
            warnings.append(f'{p.name} = {values[p.name]:.6g} is at its upper bound {p.upper:g}')
    for i in range(n):
        for j in range(i + 1, n):
            if abs(correlation[i, j]) > CORRELATION_WARNING:
                warnings.append(f'{free[i].name} and {free[j].name} are strongly correlated '
                                f'(correlation {correlation[i, j]:+.3f})')
    for text in warnings:
        logger.warning('calibration: %s', text)
    return std, ci95, correlation, warnings


# -- learned models ---------------------------------------------------------------------------
#: What the report of a learned model says of its uncertainty.
LEARNED_UNCERTAINTY = ('none: a learned model is a fitted regressor, not parameters with a '
                       'likelihood; no confidence intervals are computed')


@dataclasses.dataclass
class LearnedResult:
    """
    What :func:`fit_learned` found: a regressor fitted to data, scored as :func:`calibrate` scores.

    The "parameters" of a learned model are its fitted regressor: its kind,
    hyperparameters and training rows, and for a linear regressor the
    coefficients of the temperature increment in physical units. There are
    no confidence intervals (:data:`LEARNED_UNCERTAINTY`).

    Attributes
    ----------
    estimator : str
        Name of the built-in estimator
        (:data:`~mshoot_core.models.sklearn_model.ESTIMATOR_FACTORIES`) or
        the regressor's class name.
    regressor : str
        The regressor's class name.
    hyperparameters : dict
        The regressor's ``get_params()`` (JSON-ready; other values as their repr).
    training_rows : int
        Training pairs (T_k, u_k) -> T_{k+1} - T_k over all training periods.
    step_s : float
        Learning step [s]: the data's row length.
    use_state : bool
        Whether the temperature is a feature of the increment.
    features : list of str
        Features of the increment, in order (``T`` [K] first if used).
    coefficients : dict of str -> float or None
        For a linear regressor: the temperature increment over one step per
        unit of each feature [K per step per feature unit: 1 for ``T`` and
        ``Tout``, per W/m2, person, % and W] and ``intercept`` [K per step];
        None otherwise.
    physical : dict of str -> float or None
        R1C1-equivalent quantities of a linear model whose features include
        ``T`` and ``q`` (see :func:`r1c1_equivalent`); None otherwise.
    metrics : dict of str -> dict
        Period name -> {'rmse_k', 'mae_k', 'rows'} (:func:`metrics`).
    warnings : list of str
        The regressor's own warnings while fitting (e.g. no convergence),
        scored inputs or free runs outside the training range (extrapolation),
        a free run that failed.
    fit_s : float
        Wall time of the regressor's fit [s].
    wall_s : float
        Wall time of the fit and the scoring [s].
    simulated : dict of str -> ndarray
        Period name -> simulated output at every row.
    model : SklearnModel
        The fitted model (:func:`~mshoot_core.models.sklearn_model.make_zone_model`).

    """

    estimator: str
    regressor: str
    hyperparameters: dict[str, Any]
    training_rows: int
    step_s: float
    use_state: bool
    features: list[str]
    coefficients: dict[str, float] | None
    physical: dict[str, float] | None
    metrics: dict[str, dict[str, float]]
    warnings: list[str]
    fit_s: float
    wall_s: float
    simulated: dict[str, np.ndarray]
    model: Any = dataclasses.field(repr=False)

    @property
    def parameters(self) -> dict[str, Any]:
        """Return the learned model's description: what stands for its parameters."""
        return {'estimator': self.estimator, 'regressor': self.regressor,
                'hyperparameters': dict(self.hyperparameters),
                'training_rows': self.training_rows, 'step_s': self.step_s,
                'use_state': self.use_state, 'features': list(self.features),
                'coefficients': None if self.coefficients is None else dict(self.coefficients),
                'physical': None if self.physical is None else dict(self.physical)}

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON-ready summary (no simulated series, no model)."""
        return {'parameters': self.parameters, 'uncertainty': LEARNED_UNCERTAINTY,
                'metrics': self.metrics, 'warnings': list(self.warnings),
                'fit_s': self.fit_s, 'wall_s': self.wall_s}


def r1c1_equivalent(coefficients: Mapping[str, float],
                    step_s: float) -> dict[str, float] | None:
    """
    Return the R1C1 quantities equivalent to an affine temperature increment.

    The exact discretisation of the R1C1 over a step dt with constant
    conductance g is ``T+ - T = (a - 1) T + (1 - a)(Tout + K + (shgc solrad
    + q + ...) / g)``, ``a = exp(-g dt / C)``: so ``c_T = a - 1``, ``c_q =
    (1 - a) / g``, and from the coefficients ``g = -c_T / c_q``, ``tau =
    -dt / ln(1 + c_T)``, ``C = tau g``, each gain per W of ``q``. With
    occupants or ventilation varying, g varies in the physics and these are
    averages over the training data.

    Parameters
    ----------
    coefficients : mapping
        Increment per unit of each feature [K per step per unit] with at
        least ``T`` and ``q`` (as :attr:`LearnedResult.coefficients`).
    step_s : float
        The step [s].

    Returns
    -------
    dict or None
        ``time_constant_h`` [h], ``conductance_w_k`` (to the outdoors and
        the ventilation, [W/K]), ``capacity_mj_k`` [MJ/K], ``outdoor_gain``
        (``c_Tout / -c_T``: 1 for an R1C1), and for the inputs present
        ``shgc_m2`` [m2], ``occupant_heat_w`` [W per person],
        ``ventilation_w_pct`` [W per % of damper]; None when the
        coefficients describe no stable R1C1 (``-1 < c_T < 0``, ``c_q > 0``).

    """
    c_t, c_q = coefficients.get('T'), coefficients.get('q')
    if c_t is None or c_q is None or not (-1.0 < c_t < 0.0 and c_q > 0.0):
        return None
    conductance = -c_t / c_q
    time_constant_s = -step_s / math.log1p(c_t)
    physical = {'time_constant_h': time_constant_s / 3600.0, 'conductance_w_k': conductance,
                'capacity_mj_k': time_constant_s * conductance / 1e6}
    if 'Tout' in coefficients:
        physical['outdoor_gain'] = coefficients['Tout'] / -c_t
    for name, label in (('solrad', 'shgc_m2'), ('occ', 'occupant_heat_w'),
                        ('dpos', 'ventilation_w_pct')):
        if name in coefficients:
            physical[label] = coefficients[name] / c_q
    return physical


def fit_learned(estimator: str | Any, train: Sequence[Period], validation: Sequence[Period] = (),
                *, use_state: bool = True, seed: int = 0) -> LearnedResult:
    """
    Fit a learned zone model to the ``train`` periods; score every period as :func:`calibrate`.

    The model is :func:`~mshoot_core.models.sklearn_model.make_zone_model`
    (the R1C1's inputs, state ``T`` [K], output ``T`` [degC]) with a
    learning step of the data's row length. The regressor learns the
    temperature increment over one row from the measured temperature
    (``use_state``) and the inputs held over the row, on the training rows
    only. Every period is then scored like a physical calibration: simulated
    freely from its start state (:func:`simulate_period`; no correction by
    the measurements) and compared over rows 1..N (:func:`metrics`).

    Parameters
    ----------
    estimator : str or object
        A built-in estimator's name
        (:data:`~mshoot_core.models.sklearn_model.ESTIMATOR_FACTORIES`:
        'linear', 'ridge', 'knn', 'random_forest', 'mlp', 'svr') or an
        unfitted regressor with ``fit`` and ``predict``.
    train : sequence of Period
        The periods learned from: output ``T`` [degC], one state (``x0`` the
        first row's temperature [K]), rows of one length. Row weights are
        not used.
    validation : sequence of Period
        Periods only scored (their rows a multiple of the training rows' length).
    use_state : bool
        Learn the increment from the temperature too (else from the inputs only).
    seed : int
        Seed of a named estimator that uses one (random forest, MLP).

    Returns
    -------
    LearnedResult
        The regressor's description, the scores per period, warnings.

    Raises
    ------
    ValueError
        For no training period, a period whose output is not ``T`` or whose
        start state is not one temperature, rows of unequal length, an
        unknown estimator name, or a validation period whose rows are not a
        multiple of the learning step.
    TypeError
        For an estimator without ``fit``/``predict``.

    """
    import warnings as python_warnings

    from mshoot_core.models.sklearn_model import make_zone_model

    train, validation = list(train), list(validation)
    if not train:
        raise ValueError('fit_learned needs at least one training period')
    for period in [*train, *validation]:
        if period.output != 'T' or period.x0.size != 1:
            raise ValueError(f'period {period.name}: a learned zone model needs the output '
                             f"'T' and one start temperature, got output {period.output!r} and "
                             f'{period.x0.size} start states')
    steps = np.concatenate([np.diff(np.asarray(p.inputs.index, dtype=float)) for p in train])
    step_s = float(steps[0])
    if not np.allclose(steps, step_s, rtol=1e-9, atol=1e-6):
        raise ValueError('fit_learned: the training rows must have one length (the learning '
                         f'step), got {steps.min():g} s to {steps.max():g} s')
    started = time.perf_counter()
    model = make_zone_model(estimator, step_s=step_s, use_state=use_state, seed=seed)
    name = estimator if isinstance(estimator, str) else type(estimator).__name__
    states = [pd.DataFrame({'T': p.measured + KELVIN}, index=p.inputs.index) for p in train]
    with python_warnings.catch_warnings(record=True) as caught:
        python_warnings.simplefilter('always')
        model.fit(states, [p.inputs for p in train])
    first_lines = [(str(w.message).strip() or type(w.message).__name__).splitlines()[0]
                   for w in caught]
    warnings = list(dict.fromkeys(f'{name} fit: {line}' for line in first_lines))
    simulated, scores = {}, {}
    for period in [*train, *validation]:
        try:
            simulated[period.name] = simulate_period(model, period)
        except FloatingPointError as error:
            simulated[period.name] = np.full(period.measured.size, np.nan)
            warnings.append(f'period {period.name}: the free run failed ({error})')
        scores[period.name] = metrics(simulated[period.name], period.measured)
    warnings += _extrapolation(model, train, validation, simulated)
    for text in warnings:
        logger.warning('learned model: %s', text)
    coefficients = physical = None
    affine = model.affine_increments()
    if affine is not None:
        coefficients = {f: float(v) for f, v in affine[0].loc['T'].items()}
        coefficients['intercept'] = float(affine[1]['T'])
        physical = r1c1_equivalent(coefficients, step_s)
    regressor = model.estimator
    params = regressor.get_params() if hasattr(regressor, 'get_params') else {}
    wall_s = time.perf_counter() - started
    logger.info('learned model %s: %d training rows, fit %.3f s, %s', name,
                model.n_training_pairs_, model.fit_time_s_,
                ', '.join(f'RMSE {k} {v["rmse_k"]:.4f} K' for k, v in scores.items()))
    return LearnedResult(name, type(regressor).__name__,
                         {k: json_ready(v) for k, v in params.items()},
                         int(model.n_training_pairs_), step_s, bool(use_state),
                         list(model.feature_names), coefficients, physical, scores, warnings,
                         float(model.fit_time_s_), wall_s, simulated, model)


def _extrapolation(model: Any, train: Sequence[Period], validation: Sequence[Period],
                   simulated: Mapping[str, np.ndarray]) -> list[str]:
    """Warn of scored inputs and free runs outside the training range (extrapolation)."""
    inputs = pd.concat([p.inputs.iloc[:-1] for p in train])
    low, high = inputs.min(), inputs.max()
    measured = np.concatenate([p.measured for p in train])
    texts = []
    for period in validation:
        held = period.inputs.iloc[:-1][list(model.input_names)]
        outside = {name: int(((held[name] < low[name]) | (held[name] > high[name])).sum())
                   for name in model.input_names}
        for name, count in outside.items():
            if count:
                texts.append(f'period {period.name}: {name} outside its training range '
                             f'[{low[name]:.4g}, {high[name]:.4g}] in {count} of {len(held)} '
                             'rows (extrapolation)')
    for period in [*train, *validation]:
        run = simulated[period.name]
        count = int(np.sum((run < measured.min()) | (run > measured.max())))
        if count:
            texts.append(f'period {period.name}: the free run leaves the training '
                         f'temperature range [{measured.min():.2f}, {measured.max():.2f}] degC '
                         f'in {count} of {run.size} rows (extrapolation)')
    return texts


# -- the OU44 reference calibration -----------------------------------------------------------
#: Free parameters of the OU44 calibration: start values (the published ones) and wide bounds.
OU44_FREE = (FreeParameter('tmass', 50.0, 1.0, 250.0),
             FreeParameter('shgc', 4.608961327935981, 0.0, 20.0),
             FreeParameter('occheff', 2.0836995296486704, 0.0, 10.0),
             FreeParameter('RExt', 4.0, 0.1, 40.0))
#: Bounds of the reference study's own estimation (the original MShoot's
#: examples/bs2019/case1/case1_est.py: tmass 1-50, shgc 0-10, occheff 0.5-3, RExt 0.5-4):
#: prior knowledge of the study, not fitted to these data. The published parameters are the
#: bounded least-squares optimum of the study's setup (hourly means, a 20 degC start) within
#: them, tmass and RExt on their upper bounds.
OU44_STUDY_BOUNDS = {'tmass': (1.0, 50.0), 'shgc': (0.0, 10.0), 'occheff': (0.5, 3.0),
                     'RExt': (0.5, 4.0)}
#: :data:`OU44_FREE` within :data:`OU44_STUDY_BOUNDS`.
OU44_STUDY_FREE = tuple(FreeParameter(p.name, min(max(p.initial, OU44_STUDY_BOUNDS[p.name][0]),
                                                  OU44_STUDY_BOUNDS[p.name][1]),
                                      *OU44_STUDY_BOUNDS[p.name]) for p in OU44_FREE)


def ou44_periods(path: str | pathlib.Path, train: tuple[str, str] = OU44_TRAIN,
                 validation: tuple[str, str] = OU44_VALIDATION,
                 max_heat_w: float = OU44_MAX_HEAT_W) -> list[Period]:
    """
    Read the OU44 measurements into the training and validation periods.

    The 30-minute rows as they are (inputs held over each row), inputs
    ``solrad``, ``Tout``, ``occ``, ``dpos`` and ``q = max_heat_w * vpos / 100``;
    the start state is the measured temperature at the first row of each
    period, the measured output ``T`` [degC].

    Parameters
    ----------
    path : path-like
        The ``measurements.csv`` file (columns datetime, T, solrad, Tout, occ,
        dpos, vpos).
    train, validation : (str, str)
        Inclusive time ranges (local time).
    max_heat_w : float
        Radiator power at a fully open valve [W].

    Returns
    -------
    list of Period
        ``[train, validation]``, named 'train' and 'validation'.

    Raises
    ------
    FileNotFoundError, ValueError
        If the file is missing, lacks columns, or a range is not covered
        without gaps.

    """
    columns = (*OU44_COLUMNS, 'vpos')
    raw = read_ou44(path, columns)
    periods = []
    for name, (start, end) in (('train', train), ('validation', validation)):
        t0, t1 = pd.Timestamp(start), pd.Timestamp(end)
        if not t0 < t1:
            raise ValueError(f'{name} period: start {t0} must be before end {t1}')
        if t0 < raw.index[0] or t1 > raw.index[-1]:
            raise ValueError(f'{path} covers {raw.index[0]} to {raw.index[-1]}, not the '
                             f'{name} period {t0} to {t1}')
        sel = raw.loc[t0:t1, list(columns[1:])].astype(float)
        if sel.isna().any().any():
            raise ValueError(f'{path}: gaps in the data of the {name} period {t0} to {t1}')
        seconds = (sel.index - t0).total_seconds().to_numpy()
        inputs = pd.DataFrame({'solrad': sel['solrad'].to_numpy(),
                               'Tout': sel['Tout'].to_numpy(), 'occ': sel['occ'].to_numpy(),
                               'dpos': sel['dpos'].to_numpy(),
                               'q': max_heat_w * sel['vpos'].to_numpy() / 100.0},
                              index=pd.Index(seconds, name='time_s'))
        measured = sel['T'].to_numpy()
        periods.append(Period(name, inputs, np.array([measured[0] + KELVIN]), measured,
                              timestamps=sel.index))
    return periods
