"""
Data-driven zone models: any scikit-learn regressor behind the :class:`Model` interface.

A :class:`SklearnModel` learns the **per-step change of its states** over a
fixed learning step ``step_s`` [s],

    x_{k+1} = x_k + dx(x_k, u_k)        (``use_state=True``)
    x_{k+1} = x_k + dx(u_k)             (``use_state=False``)

with the inputs ``u_k`` held constant over the step, so a simulation
integrates the learned increments to a state trajectory. Any object with
``fit(X, y)`` and ``predict(X)`` serves as the regressor; features and
targets are standardised inside the model (so SVR, k-NN and MLP see unit
scales), and single-output regressors such as SVR are fitted once per target
automatically.

Outputs come in two kinds, both evaluated with one convention: the output at
a time t is a function of the state at t and of the input held over the step
that *ended* at t (at the first time, the first step's input):

- **learned outputs** ``y = h(x, u)``: a second regressor, fitted on output
  trajectories given to :meth:`SklearnModel.fit`;
- **analytic outputs** (:class:`AnalyticOutput`): fixed functions of the
  named states and inputs, e.g. the zone temperature in degC
  (:func:`state_output`), or integrals over the learned steps, e.g. the heat
  delivered ``Qr`` = integral of q dt [J] (:func:`input_integral`), which
  start at 0 at the start of a simulation and of every batch interval.

States are what the multiple-shooting optimiser constrains; outputs are what
its cost sees. :func:`make_excitation_data` makes training trajectories
from a physical emulator excited by a sinusoidal heat input, and
:func:`evaluate` scores a model's free-run and one-step predictions on them.
(The reference case's "Setup 2" training lives with the applications, in
``mshoot_studies.setup2``.)
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd
from sklearn.base import clone
from sklearn.ensemble import RandomForestRegressor
from sklearn.exceptions import NotFittedError
from sklearn.linear_model import LinearRegression, Ridge
from sklearn.neighbors import KNeighborsRegressor
from sklearn.neural_network import MLPRegressor
from sklearn.svm import SVR
from sklearn.utils import get_tags

from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: Relative tolerance when checking that a time span is a whole number of learning steps.
STEP_TOLERANCE = 1e-9

#: Regressor factories of the built-in estimators: name -> f(seed) -> unfitted regressor.
#: Hyperparameters act on standardised features and targets (see :class:`SklearnModel`).
ESTIMATOR_FACTORIES: dict[str, Callable[[int], Any]] = {
    'linear': lambda seed: LinearRegression(),
    'ridge': lambda seed: Ridge(alpha=1e-3),
    'knn': lambda seed: KNeighborsRegressor(n_neighbors=4, weights='distance'),
    'random_forest': lambda seed: RandomForestRegressor(
        n_estimators=60, min_samples_leaf=1, random_state=seed, n_jobs=1),
    'mlp': lambda seed: MLPRegressor(
        hidden_layer_sizes=(16,), activation='tanh', solver='lbfgs', alpha=1e-3,
        max_iter=5000, tol=1e-9, random_state=seed),
    # Chosen on a holdout inside the Setup 2 training days (train on the first 70 %, free-run
    # the last 30 %) from C in {1, 10, 100, 1000}, epsilon in {0.003, 0.01, 0.05}, gamma in
    # {0.005, 0.02, 0.1, 'scale'}: a wide kernel (small gamma) keeps the nearly affine physics
    # and extrapolates gently; a tight epsilon tube resolves the small hourly increments.
    'svr': lambda seed: SVR(kernel='rbf', C=1000.0, epsilon=0.003, gamma=0.005),
}


def make_estimator(name: str, seed: int = 0) -> Any:
    """
    Return a fresh unfitted regressor of the built-in kind ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`ESTIMATOR_FACTORIES`: ``'linear'``, ``'ridge'``,
        ``'knn'``, ``'random_forest'``, ``'mlp'`` or ``'svr'``.
    seed : int
        Random seed of the estimators that use one (random forest, MLP).

    Raises
    ------
    ValueError
        If ``name`` is not a known estimator.

    """
    try:
        factory = ESTIMATOR_FACTORIES[name]
    except KeyError:
        raise ValueError(f'unknown estimator {name!r}; expected one of '
                         f'{sorted(ESTIMATOR_FACTORIES)}') from None
    return factory(seed)


# -- analytic outputs -------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class AnalyticOutput:
    """
    An output given by a fixed function instead of a regressor.

    Attributes
    ----------
    name : str
        Output name.
    function : callable
        ``function(states, inputs) -> ndarray (B,)`` where ``states`` and
        ``inputs`` map each state / input name to an array of shape (B,).
    integrate : bool
        If False the output is ``function`` of the state at the output time
        and the input of the step that ended then. If True the output is the
        integral of ``function`` over time [unit * s], accumulated over the
        learned steps (rectangle rule on each step's start state and input;
        exact for functions of the inputs only) from 0 at the start.

    """

    name: str
    function: Callable[[Mapping[str, np.ndarray], Mapping[str, np.ndarray]], np.ndarray]
    integrate: bool = False


@dataclasses.dataclass(frozen=True)
class _AffineOfState:
    """Picklable ``scale * states[state] + offset``."""

    state: str
    scale: float
    offset: float

    def __call__(self, states: Mapping[str, np.ndarray],
                 inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        return self.scale * states[self.state] + self.offset


@dataclasses.dataclass(frozen=True)
class _InputValue:
    """Picklable ``inputs[name]``."""

    input_name: str

    def __call__(self, states: Mapping[str, np.ndarray],
                 inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        return inputs[self.input_name]


def state_output(name: str, state: str, scale: float = 1.0, offset: float = 0.0) -> AnalyticOutput:
    """
    Output ``scale * state + offset``.

    E.g. ``state_output('T', 'T', offset=-273.15)``: the zone temperature [degC].
    """
    return AnalyticOutput(name, _AffineOfState(state, float(scale), float(offset)))


def input_integral(name: str, input_name: str) -> AnalyticOutput:
    """
    Output the integral of an input over time [input unit * s].

    E.g. ``input_integral('Qr', 'q')``: the heat delivered [J].
    """
    return AnalyticOutput(name, _InputValue(input_name), integrate=True)


# -- the model --------------------------------------------------------------------------------
@dataclasses.dataclass
class _Standardiser:
    """Column means and scales (1 where a column is constant)."""

    mean: np.ndarray
    scale: np.ndarray
    constant: np.ndarray

    @classmethod
    def from_data(cls, values: np.ndarray) -> '_Standardiser':
        mean = values.mean(axis=0)
        std = values.std(axis=0)
        constant = ~(std > 1e-12 * np.maximum(1.0, np.abs(mean)))
        return cls(mean, np.where(constant, 1.0, std), constant)


class _Regressor:
    """
    One regressor group (the state increments or the learned outputs).

    Fits one estimator on all targets when it supports several (scikit-learn
    ``multi_output`` tag), otherwise one clone per target.
    """

    def __init__(self, template: Any, n_targets: int, per_target: bool | None) -> None:
        if per_target is None:
            per_target = n_targets > 1 and not _supports_multi_output(template)
        self.per_target = per_target
        self.n_targets = n_targets
        count = n_targets if per_target else 1
        self.estimators = [clone(template, safe=False) for _ in range(count)]

    def fit(self, features: np.ndarray, targets: np.ndarray) -> None:
        if self.per_target:
            for j, estimator in enumerate(self.estimators):
                estimator.fit(features, targets[:, j])
        elif self.n_targets == 1:
            self.estimators[0].fit(features, targets[:, 0])
        else:
            self.estimators[0].fit(features, targets)

    def predict(self, features: np.ndarray) -> np.ndarray:
        batch = features.shape[0]
        if self.per_target:
            columns = [np.asarray(e.predict(features), dtype=float).reshape(batch)
                       for e in self.estimators]
            return np.column_stack(columns)
        return np.asarray(self.estimators[0].predict(features),
                          dtype=float).reshape(batch, self.n_targets)


def _supports_multi_output(estimator: Any) -> bool:
    """Tell whether scikit-learn tags say ``estimator`` fits 2-D targets (False if unknown)."""
    if not hasattr(estimator, '__sklearn_tags__'):
        return False
    try:
        return bool(get_tags(estimator).target_tags.multi_output)
    except Exception:  # noqa: B902 - third-party tags may be broken; fall back to per target
        return False


class SklearnModel(Model):
    """
    A zone model whose state increments (and optional outputs) are learned regressions.

    Parameters
    ----------
    estimator : object
        Unfitted regressor with ``fit(X, y)`` and ``predict(X)``, cloned
        (``sklearn.base.clone``, deep copy for non-scikit-learn objects) for
        every target group; e.g. ``make_estimator('svr')``.
    state_names : sequence of str
        States, in the order of ``x0`` and of state arrays (e.g. ``('T',)`` [K]).
    input_names : sequence of str
        Inputs, the column order of ``u`` arrays (e.g. R1C1's five inputs).
    step_s : float
        Learning step [s]: the increment is learned over this step and every
        simulated interval must be a whole number of steps.
    use_state : bool
        If True the increment is learned from the current state and the
        inputs; if False from the inputs only.
    analytic_outputs : sequence of AnalyticOutput
        Outputs given by fixed functions (first in :attr:`output_names`).
    learned_output_names : sequence of str
        Outputs learned by regression of y on (x, u) from the output
        trajectories given to :meth:`fit` (after the analytic outputs).
    output_estimator : object, optional
        Regressor of the learned outputs; default: a clone of ``estimator``.
    per_target : bool, optional
        Fit one estimator per target column. Default: only if the estimator
        does not declare multi-output support (SVR, third-party objects).
    standardise : bool
        Standardise features and targets with the training means and standard
        deviations (the estimators' hyperparameters then act on unit scales).

    Raises
    ------
    TypeError
        If an estimator lacks ``fit``/``predict``.
    ValueError
        On empty or duplicate names, a non-positive step, or analytic outputs
        that refer to unknown states or inputs.

    """

    def __init__(self, estimator: Any, state_names: Sequence[str], input_names: Sequence[str],
                 *, step_s: float = 3600.0, use_state: bool = True,
                 analytic_outputs: Sequence[AnalyticOutput] = (),
                 learned_output_names: Sequence[str] = (), output_estimator: Any = None,
                 per_target: bool | None = None, standardise: bool = True) -> None:
        for role, candidate in (('estimator', estimator), ('output_estimator', output_estimator)):
            if candidate is None and role == 'output_estimator':
                continue
            if not (callable(getattr(candidate, 'fit', None))
                    and callable(getattr(candidate, 'predict', None))):
                raise TypeError(f'{role} must have fit(X, y) and predict(X) methods, got '
                                f'{type(candidate).__name__}')
        self.state_names = _names('state_names', state_names, allow_empty=False)
        self.input_names = _names('input_names', input_names, allow_empty=False)
        analytic_outputs = tuple(analytic_outputs)
        for output in analytic_outputs:
            if not isinstance(output, AnalyticOutput):
                raise TypeError(f'analytic_outputs must hold AnalyticOutput, got '
                                f'{type(output).__name__}')
        self.learned_output_names = _names('learned_output_names', learned_output_names,
                                           allow_empty=True)
        self.output_names = _names('output names', [o.name for o in analytic_outputs]
                                   + list(self.learned_output_names), allow_empty=True)
        self.analytic_outputs = analytic_outputs
        step_s = float(step_s)
        if not np.isfinite(step_s) or step_s <= 0:
            raise ValueError(f'step_s must be a positive number of seconds, got {step_s}')
        self.step_s = step_s
        self.use_state = bool(use_state)
        self.standardise = bool(standardise)
        self.estimator = estimator
        self.output_estimator = output_estimator
        self.per_target = per_target
        self._check_analytic_outputs()
        self._state_regressor: _Regressor | None = None
        self._output_regressor: _Regressor | None = None
        self._feature_scaler: _Standardiser | None = None
        self._increment_scaler: _Standardiser | None = None
        self._output_feature_scaler: _Standardiser | None = None
        self._output_scaler: _Standardiser | None = None
        #: Number of (x_k, u_k) -> dx_k pairs of the last fit.
        self.n_training_pairs_ = 0
        #: Wall-clock time of the last fit [s].
        self.fit_time_s_ = float('nan')

    def __repr__(self) -> str:
        return (f'{type(self).__name__}({type(self.estimator).__name__}, states='
                f'{list(self.state_names)}, inputs={list(self.input_names)}, outputs='
                f'{list(self.output_names)}, step_s={self.step_s:g}, use_state={self.use_state}'
                f', fitted={self.is_fitted})')

    # -- configuration helpers -------------------------------------------------------------
    def _check_analytic_outputs(self) -> None:
        """Evaluate every analytic output once on zeros to catch unknown names now."""
        states = dict(zip(self.state_names, np.zeros((len(self.state_names), 1))))
        inputs = dict(zip(self.input_names, np.zeros((len(self.input_names), 1))))
        for output in self.analytic_outputs:
            try:
                value = np.asarray(output.function(states, inputs), dtype=float)
            except KeyError as err:
                raise ValueError(f'analytic output {output.name!r} refers to unknown name '
                                 f'{err}; states {list(self.state_names)}, inputs '
                                 f'{list(self.input_names)}') from None
            if value.size != 1:
                raise ValueError(f'analytic output {output.name!r} must return one value per '
                                 f'batch row, got shape {value.shape} for one row')

    @property
    def feature_names(self) -> tuple[str, ...]:
        """Features of the state-increment regressor, in column order."""
        return (self.state_names if self.use_state else ()) + self.input_names

    @property
    def is_fitted(self) -> bool:
        """Return True once :meth:`fit` has succeeded."""
        return self._state_regressor is not None

    def _require_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError(f'{type(self).__name__} is not trained yet: call fit() first')

    # -- training --------------------------------------------------------------------------
    def fit(self, states: pd.DataFrame | Sequence[pd.DataFrame],
            inputs: pd.DataFrame | Sequence[pd.DataFrame],
            outputs: pd.DataFrame | Sequence[pd.DataFrame] | None = None) -> 'SklearnModel':
        """
        Learn the state increments (and learned outputs) from trajectories.

        Each trajectory is sampled every ``step_s``; consecutive rows k, k+1
        give one training pair ``(x_k, u_k) -> x_{k+1} - x_k`` with ``u_k``
        the input held over [t_k, t_{k+1}); learned outputs are fitted as
        ``(x_{k+1}, u_k) -> y_{k+1}``. Several trajectories (e.g. separate
        experiments) may be given as lists; no pair spans two of them.

        Parameters
        ----------
        states : DataFrame, shape (T, >= nx), or list of them
            States indexed by time [s], one column per name in
            :attr:`state_names` (extra columns are ignored).
        inputs : DataFrame, shape (T, >= nu), or list of them
            Inputs on the same index, one column per name in :attr:`input_names`.
        outputs : DataFrame, shape (T, >= ny_learned), or list of them, optional
            Required when the model has learned outputs.

        Returns
        -------
        SklearnModel
            ``self``, trained.

        Raises
        ------
        ValueError
            On missing columns, non-finite values, mismatched indices, a time
            step other than ``step_s``, or fewer than two training pairs.

        """
        states_list = _as_list(states, 'states')
        inputs_list = _as_list(inputs, 'inputs')
        if len(states_list) != len(inputs_list):
            raise ValueError(f'got {len(states_list)} state trajectories but '
                             f'{len(inputs_list)} input trajectories')
        if self.learned_output_names:
            if outputs is None:
                raise ValueError(f'the model learns outputs {list(self.learned_output_names)}:'
                                 ' fit() needs output trajectories')
            outputs_list: list[pd.DataFrame | None] = list(_as_list(outputs, 'outputs'))
            if len(outputs_list) != len(states_list):
                raise ValueError(f'got {len(states_list)} state trajectories but '
                                 f'{len(outputs_list)} output trajectories')
        else:
            outputs_list = [None] * len(states_list)
        x_now, u_now, x_next, y_next = [], [], [], []
        for i, (sdf, idf, odf) in enumerate(zip(states_list, inputs_list, outputs_list)):
            x = self._frame_values(sdf, self.state_names, f'states[{i}]')
            u = self._frame_values(idf, self.input_names, f'inputs[{i}]')
            self._check_time_index(sdf, idf, f'trajectory {i}')
            x_now.append(x[:-1])
            u_now.append(u[:-1])
            x_next.append(x[1:])
            if odf is not None:
                if not np.array_equal(np.asarray(odf.index, dtype=float),
                                      np.asarray(sdf.index, dtype=float)):
                    raise ValueError(f'outputs[{i}] must have the index of states[{i}]')
                y_next.append(self._frame_values(odf, self.learned_output_names,
                                                 f'outputs[{i}]')[1:])
        x_now_arr, u_now_arr = np.vstack(x_now), np.vstack(u_now)
        x_next_arr = np.vstack(x_next)
        n_pairs = x_now_arr.shape[0]
        if n_pairs < 2:
            raise ValueError(f'need at least 2 training pairs (3 samples), got {n_pairs}')
        tic = time.perf_counter()
        features = self._features(x_now_arr, u_now_arr)
        increments = x_next_arr - x_now_arr
        feature_scaler = self._scaler(features, self.feature_names, 'feature')
        increment_scaler = self._scaler(increments, self.state_names, 'increment')
        regressor = _Regressor(self.estimator, len(self.state_names), self.per_target)
        regressor.fit(self._scale(features, feature_scaler),
                      self._scale(increments, increment_scaler))
        output_regressor = output_feature_scaler = output_scaler = None
        if self.learned_output_names:
            output_features = np.hstack([x_next_arr, u_now_arr])
            learned = np.vstack(y_next)
            output_feature_scaler = self._scaler(
                output_features, self.state_names + self.input_names, 'output feature')
            output_scaler = self._scaler(learned, self.learned_output_names, 'output')
            output_regressor = _Regressor(
                self.estimator if self.output_estimator is None else self.output_estimator,
                len(self.learned_output_names), self.per_target)
            output_regressor.fit(self._scale(output_features, output_feature_scaler),
                                 self._scale(learned, output_scaler))
        # Commit only after every regressor trained: a failed fit leaves the model as it was.
        self._feature_scaler, self._increment_scaler = feature_scaler, increment_scaler
        self._output_feature_scaler, self._output_scaler = output_feature_scaler, output_scaler
        self._state_regressor = regressor
        self._output_regressor = output_regressor
        self.fit_time_s_ = time.perf_counter() - tic
        self.n_training_pairs_ = n_pairs
        logger.info('trained %s on %d pairs (step %g s) in %.3f s', type(self.estimator).__name__,
                    n_pairs, self.step_s, self.fit_time_s_)
        return self

    def _frame_values(self, frame: pd.DataFrame, names: Sequence[str], label: str) -> np.ndarray:
        if not isinstance(frame, pd.DataFrame):
            raise TypeError(f'{label} must be a pandas DataFrame, got {type(frame).__name__}')
        missing = [n for n in names if n not in frame.columns]
        if missing:
            raise ValueError(f'{label} lacks columns {missing}; expected {list(names)}, got '
                             f'{list(frame.columns)}')
        values = frame[list(names)].to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            counts = {n: int(c) for n, c in zip(names, bad.sum(axis=0)) if c}
            raise ValueError(f'{label} holds non-finite values (count per column: {counts})')
        return values

    def _check_time_index(self, states: pd.DataFrame, inputs: pd.DataFrame, label: str) -> None:
        t = np.asarray(states.index, dtype=float)
        if not np.array_equal(t, np.asarray(inputs.index, dtype=float)):
            raise ValueError(f'{label}: states and inputs must share one time index [s]')
        if t.size < 2:
            raise ValueError(f'{label}: need at least 2 samples, got {t.size}')
        steps = np.diff(t)
        if not np.allclose(steps, self.step_s, rtol=STEP_TOLERANCE, atol=1e-6):
            raise ValueError(f'{label}: samples must be step_s = {self.step_s:g} s apart, got '
                             f'steps from {steps.min():g} s to {steps.max():g} s')

    def _features(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.hstack([x, u]) if self.use_state else u

    def _scaler(self, values: np.ndarray, names: Sequence[str], role: str) -> _Standardiser:
        scaler = _Standardiser.from_data(values)
        if not self.standardise:
            scaler = _Standardiser(np.zeros_like(scaler.mean), np.ones_like(scaler.scale),
                                   scaler.constant)
        for name, value, constant in zip(names, scaler.mean, scaler.constant):
            if constant:
                logger.warning('%s %r is constant (%g) in the training data: the model cannot '
                               'learn its effect, other values extrapolate', role, name, value)
        return scaler

    @staticmethod
    def _scale(values: np.ndarray, scaler: _Standardiser) -> np.ndarray:
        return (values - scaler.mean) / scaler.scale

    # -- prediction ------------------------------------------------------------------------
    def predict_increments(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """
        One learned step: the state increments for B (state, input) pairs.

        Parameters
        ----------
        x : ndarray, shape (B, nx)
            States at the step start.
        u : ndarray, shape (B, nu)
            Inputs held over the step, columns in :attr:`input_names` order.

        Returns
        -------
        ndarray, shape (B, nx)
            Predicted ``x_{k+1} - x_k`` over ``step_s``.

        """
        self._require_fitted()
        x, u = self._check_batch(x, u)
        return self._increments(x, u)

    def affine_increments(self) -> tuple[pd.DataFrame, pd.Series] | None:
        """
        Return the learned increment as an affine function of the features, if it is one.

        For a linear regressor (one with ``coef_`` and ``intercept_``, e.g.
        ``LinearRegression`` or ``Ridge``) the standardisation is undone:
        ``dx = coefficients @ features + intercept`` over one learning step.

        Returns
        -------
        (DataFrame, Series) or None
            ``coefficients`` of shape (nx, n_features), indexed by
            :attr:`state_names`, columns :attr:`feature_names` [state unit
            per step per feature unit], and ``intercept`` (nx,) [state unit
            per step]; None for a regressor without linear coefficients.

        Raises
        ------
        NotFittedError
            If the model is not trained.

        """
        self._require_fitted()
        estimators = self._state_regressor.estimators
        if not all(hasattr(e, 'coef_') and hasattr(e, 'intercept_') for e in estimators):
            return None
        n_features = len(self.feature_names)
        weights = np.vstack([np.asarray(e.coef_, dtype=float).reshape(-1, n_features)
                             for e in estimators])
        offsets = np.concatenate([np.asarray(e.intercept_, dtype=float).reshape(-1)
                                  for e in estimators])
        if weights.shape != (len(self.state_names), n_features):
            return None
        x_scale, y_scale = self._feature_scaler, self._increment_scaler
        coefficients = y_scale.scale[:, None] * weights / x_scale.scale[None, :]
        intercept = y_scale.mean + y_scale.scale * (offsets - weights
                                                    @ (x_scale.mean / x_scale.scale))
        return (pd.DataFrame(coefficients, index=list(self.state_names),
                             columns=list(self.feature_names)),
                pd.Series(intercept, index=list(self.state_names)))

    def _increments(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        features = self._scale(self._features(x, u), self._feature_scaler)
        scaled = self._state_regressor.predict(features)
        increments = scaled * self._increment_scaler.scale + self._increment_scaler.mean
        if not np.all(np.isfinite(increments)):
            raise FloatingPointError(f'{type(self.estimator).__name__} predicted non-finite '
                                     'state increments')
        return increments

    def _instant_outputs(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Evaluate the outputs from the state (B, nx) and the input of the step just ended."""
        y = np.zeros((x.shape[0], len(self.output_names)))
        states = dict(zip(self.state_names, x.T))
        inputs = dict(zip(self.input_names, u.T))
        for j, output in enumerate(self.analytic_outputs):
            if not output.integrate:
                y[:, j] = output.function(states, inputs)
        if self._output_regressor is not None:
            features = self._scale(np.hstack([x, u]), self._output_feature_scaler)
            learned = (self._output_regressor.predict(features) * self._output_scaler.scale
                       + self._output_scaler.mean)
            y[:, len(self.analytic_outputs):] = learned
        return y

    def _integrands(self, x: np.ndarray, u: np.ndarray) -> np.ndarray | None:
        """Rates of the integrated outputs (B, ny) over one step, or None if there are none."""
        if not any(o.integrate for o in self.analytic_outputs):
            return None
        rates = np.zeros((x.shape[0], len(self.output_names)))
        states = dict(zip(self.state_names, x.T))
        inputs = dict(zip(self.input_names, u.T))
        for j, output in enumerate(self.analytic_outputs):
            if output.integrate:
                rates[:, j] = output.function(states, inputs)
        return rates

    def _advance(self, x: np.ndarray, u: np.ndarray,
                 n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """
        Integrate ``n_steps`` learned steps from x (B, nx) under constant u (B, nu).

        Returns the end states (B, nx) and the integrals of the integrated
        outputs over the interval (B, ny; zero in the other columns).
        """
        integrals = np.zeros((x.shape[0], len(self.output_names)))
        for _ in range(n_steps):
            rates = self._integrands(x, u)
            if rates is not None:
                integrals += rates * self.step_s
            x = x + self._increments(x, u)
        return x, integrals

    def n_steps(self, dt_s: float) -> int:
        """
        Return the number of learned steps in an interval of ``dt_s`` [s].

        Raises
        ------
        ValueError
            If ``dt_s`` is not a positive whole multiple of :attr:`step_s`.

        """
        ratio = float(dt_s) / self.step_s
        n = int(round(ratio))
        if not np.isfinite(ratio) or n < 1 or abs(ratio - n) > STEP_TOLERANCE * max(1.0, ratio):
            raise ValueError(f'interval length must be a positive multiple of the learning step '
                             f'step_s = {self.step_s:g} s, got {dt_s!r} s')
        return n

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """
        Simulate B independent intervals, one ``predict`` per learned step for the batch.

        Parameters
        ----------
        x_start : ndarray, shape (B, nx)
            Start state of each interval.
        u : ndarray, shape (B, nu)
            Inputs of each interval, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s], a whole multiple of :attr:`step_s`.
        t_start_s : ndarray, shape (B,), optional
            Ignored: the learned dynamics do not depend on time.

        Returns
        -------
        x_end : ndarray, shape (B, nx)
            States at the interval ends.
        y_end : ndarray, shape (B, ny)
            Outputs at the interval ends; integrated outputs count from 0 at
            each interval's start.

        Raises
        ------
        ValueError
            On wrong shapes, non-finite values, or ``dt_s`` not a multiple of ``step_s``.
        NotFittedError
            If the model is not trained (a ValueError subclass).

        """
        self._require_fitted()
        n = self.n_steps(dt_s)
        x_start, u = self._check_batch(x_start, u)
        x_end, integrals = self._advance(x_start, u, n)
        return x_end, self._instant_outputs(x_end, u) + integrals

    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        """
        Simulate from ``x0`` over the index of ``udf`` (every step a multiple of ``step_s``).

        Parameters
        ----------
        udf : DataFrame, shape (T, >= nu)
            Inputs indexed by time [s]; row i is held over [t_i, t_{i+1}).
        x0 : sequence of float, length nx
            Initial state.

        Returns
        -------
        ydf : DataFrame, shape (T, ny)
            Outputs; integrated outputs count from 0 at ``udf.index[0]``.
        xdf : DataFrame, shape (T, nx)
            States; the first row equals ``x0``. Row k+1 is exactly what
            :meth:`simulate_intervals` gives from row k.

        Raises
        ------
        ValueError
            On missing input columns, non-finite values, or a time step that
            is not a multiple of ``step_s``.
        NotFittedError
            If the model is not trained.

        """
        self._require_fitted()
        t, u, x0_arr = self.check_inputs(udf, x0)
        steps = [self.n_steps(dt) for dt in np.diff(t)]
        x = np.empty((t.size, len(self.state_names)))
        integrals = np.zeros((t.size, len(self.output_names)))
        x[0] = x0_arr
        for k, n in enumerate(steps):
            x_end, interval_integrals = self._advance(x[k:k + 1], u[k:k + 1], n)
            x[k + 1] = x_end[0]
            integrals[k + 1] = integrals[k] + interval_integrals[0]
        u_ended = np.vstack([u[:1], u[:-1]])  # input of the step that ended at each time
        y = self._instant_outputs(x, u_ended) + integrals
        xdf = pd.DataFrame(x, index=udf.index.copy(), columns=list(self.state_names))
        ydf = pd.DataFrame(y, index=udf.index.copy(), columns=list(self.output_names))
        return ydf, xdf

    def one_step_predictions(self, states: pd.DataFrame, inputs: pd.DataFrame) -> pd.DataFrame:
        """
        One-step-ahead state predictions along a trajectory.

        Parameters
        ----------
        states : DataFrame, shape (T, >= nx)
            Reference states every ``step_s`` [s].
        inputs : DataFrame, shape (T, >= nu)
            Inputs on the same index.

        Returns
        -------
        DataFrame, shape (T, nx)
            Row k+1 = ``states`` row k + predicted increment; row 0 = ``states`` row 0.

        """
        self._require_fitted()
        x = self._frame_values(states, self.state_names, 'states')
        u = self._frame_values(inputs, self.input_names, 'inputs')
        self._check_time_index(states, inputs, 'one_step_predictions')
        predicted = x.copy()
        predicted[1:] = x[:-1] + self._increments(x[:-1], u[:-1])
        return pd.DataFrame(predicted, index=states.index.copy(), columns=list(self.state_names))


def _names(label: str, names: Sequence[str], allow_empty: bool) -> tuple[str, ...]:
    if isinstance(names, str):
        raise TypeError(f'{label} must be a sequence of names, got the string {names!r}')
    result = tuple(names)
    if not allow_empty and not result:
        raise ValueError(f'{label} must not be empty')
    for name in result:
        if not isinstance(name, str) or not name:
            raise ValueError(f'{label} must be non-empty strings, got {name!r}')
    if len(set(result)) != len(result):
        raise ValueError(f'{label} must be unique, got {list(result)}')
    return result


def _as_list(frames: pd.DataFrame | Sequence[pd.DataFrame], label: str) -> list[pd.DataFrame]:
    if isinstance(frames, pd.DataFrame):
        return [frames]
    if isinstance(frames, (list, tuple)) and frames:
        return list(frames)
    raise TypeError(f'{label} must be a DataFrame or a non-empty list of DataFrames, got '
                    f'{type(frames).__name__}')


def make_zone_model(estimator: Any | str, step_s: float = 3600.0, use_state: bool = True,
                    seed: int = 0, **kwargs: Any) -> SklearnModel:
    """
    Make a data-driven stand-in for :class:`R1C1Model`: same inputs, state and outputs.

    State ``T`` [K] learned; outputs ``T`` [degC] = state - 273.15 and
    ``Qr`` [J] = integral of q dt, both analytic.

    Parameters
    ----------
    estimator : object or str
        A regressor, or a name of :data:`ESTIMATOR_FACTORIES`.
    step_s : float
        Learning step [s].
    use_state : bool
        Learn the increment from the current state too.
    seed : int
        Seed of a named estimator.
    **kwargs
        Further :class:`SklearnModel` keywords.

    """
    if isinstance(estimator, str):
        estimator = make_estimator(estimator, seed)
    return SklearnModel(estimator, R1C1Model.state_names, R1C1Model.input_names, step_s=step_s,
                        use_state=use_state,
                        analytic_outputs=(state_output('T', 'T', offset=-KELVIN),
                                          input_integral('Qr', 'q')), **kwargs)


# -- training data ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Trajectories:
    """
    Simulated trajectories on one time grid.

    Attributes
    ----------
    inputs : DataFrame, shape (T, nu)
        Inputs indexed by time [s]; row k held over [t_k, t_{k+1}).
    states : DataFrame, shape (T, nx)
        States on the same index.
    outputs : DataFrame, shape (T, ny)
        Outputs on the same index.

    """

    inputs: pd.DataFrame
    states: pd.DataFrame
    outputs: pd.DataFrame

    def between(self, start_s: float, end_s: float) -> 'Trajectories':
        """Return the rows with ``start_s <= t <= end_s`` [s]."""
        keep = (self.inputs.index >= start_s) & (self.inputs.index <= end_s)
        return Trajectories(self.inputs.loc[keep].copy(), self.states.loc[keep].copy(),
                            self.outputs.loc[keep].copy())


def make_excitation_data(emulator_model: Model, disturbances_df: pd.DataFrame,
                         amplitude_w: float = 2000.0, period_h: float = 10.0,
                         step_s: float = 3600.0, *, x0: Sequence[float] = (293.15,),
                         control_name: str = 'q', phase_rad: float = 0.0,
                         fixed_inputs: Mapping[str, float] | None = None) -> Trajectories:
    """
    Responses of a physical model to a sinusoidal control on given disturbances.

    The control is ``amplitude_w * sin(2 pi (t - t0) / period + phase)``
    sampled at the start of every step and held over it (SPEC Setup 2:
    +-2000 W); the disturbances are held from their last sample (zero-order
    hold onto the ``step_s`` grid).

    Parameters
    ----------
    emulator_model : Model
        The physical model to excite (e.g. :class:`R1C1Model`).
    disturbances_df : DataFrame, shape (T, >= nu - 1)
        Indexed by time [s]; one column per input of ``emulator_model``
        except ``control_name`` (extra columns are ignored).
    amplitude_w : float
        Amplitude of the control [W].
    period_h : float
        Period of the sinusoid [h]. The default 10 h is incommensurate with
        the daily cycle of the disturbances, so q is not collinear with them.
    step_s : float
        Grid step [s] of the returned trajectories.
    x0 : sequence of float
        Initial state (default 293.15 K, for one-state zones such as R1C1).
    control_name : str
        The excited input.
    phase_rad : float
        Phase of the sinusoid [rad].
    fixed_inputs : mapping of str to float, optional
        Inputs replaced by constants, e.g. ``{'dpos': 0.0}`` (ventilation off).

    Returns
    -------
    Trajectories
        Inputs, states and outputs of the emulator every ``step_s`` from the
        first to the last disturbance time.

    Raises
    ------
    ValueError
        On missing or non-finite disturbances, or non-positive steps/periods.

    """
    if control_name not in emulator_model.input_names:
        raise ValueError(f'control {control_name!r} is not an input of the model; inputs '
                         f'{list(emulator_model.input_names)}')
    for label, value in (('step_s', step_s), ('period_h', period_h)):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f'{label} must be positive, got {value}')
    fixed = dict(fixed_inputs or {})
    unknown = [n for n in fixed if n not in emulator_model.input_names]
    if unknown or control_name in fixed:
        raise ValueError(f'fixed_inputs must name disturbance inputs of the model, got '
                         f'{list(fixed)}; inputs {list(emulator_model.input_names)}')
    columns = [n for n in emulator_model.input_names if n != control_name and n not in fixed]
    missing = [n for n in columns if n not in disturbances_df.columns]
    if missing:
        raise ValueError(f'disturbances_df lacks columns {missing}; expected {columns}, got '
                         f'{list(disturbances_df.columns)}')
    t_data = np.asarray(disturbances_df.index, dtype=float)
    if t_data.size < 2 or np.any(np.diff(t_data) <= 0):
        raise ValueError('disturbances_df index must be at least two increasing times [s]')
    values = disturbances_df[columns].to_numpy(dtype=float)
    if not np.all(np.isfinite(values)):
        raise ValueError('disturbances_df holds non-finite values')
    t = np.arange(t_data[0], t_data[-1] + 1e-9 * step_s, step_s)
    rows = np.searchsorted(t_data, t, side='right') - 1
    udf = pd.DataFrame(index=pd.Index(t, name='time_s'))
    for name in emulator_model.input_names:
        if name == control_name:
            udf[name] = amplitude_w * np.sin(2.0 * np.pi * (t - t[0]) / (period_h * 3600.0)
                                             + phase_rad)
        elif name in fixed:
            udf[name] = float(fixed[name])
        else:
            udf[name] = values[rows, columns.index(name)]
    ydf, xdf = emulator_model.simulate(udf, x0)
    return Trajectories(udf, xdf, ydf)


# -- validation ------------------------------------------------------------------------------
def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def evaluate(model: SklearnModel, data: Trajectories) -> tuple[float, float, float, pd.DataFrame]:
    """
    Free-run and one-step errors of ``model`` on ``data`` for its first state.

    Returns
    -------
    (rmse_free_run, max_abs_free_run, rmse_one_step, table)
        Errors in the state's unit (K for zone temperatures); ``table`` has
        columns ``true``, ``free_run``, ``one_step`` indexed by time [s].

    """
    state = model.state_names[0]
    _, xdf = model.simulate(data.inputs, data.states.iloc[0].to_numpy())
    one_step = model.one_step_predictions(data.states, data.inputs)
    true = data.states[state].to_numpy()
    free = xdf[state].to_numpy()
    table = pd.DataFrame({'true': true, 'free_run': free, 'one_step': one_step[state].to_numpy()},
                         index=data.states.index.copy())
    # Row 0 is the given initial state in both predictions: score the predicted rows only.
    return (_rmse(free[1:], true[1:]), float(np.max(np.abs(free - true))),
            _rmse(table['one_step'].to_numpy()[1:], true[1:]), table)
