"""Data-driven zone models: training, batch/sequential agreement, errors."""
import logging

from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.models.sklearn_model import (AnalyticOutput, ESTIMATOR_FACTORIES,
                                              evaluate, input_integral, make_estimator,
                                              make_excitation_data, make_zone_model,
                                              SklearnModel, state_output)
from mshoot_core.scenario import synthetic_scenario
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd
import pytest
from sklearn.exceptions import NotFittedError
from sklearn.linear_model import LinearRegression
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import PolynomialFeatures

TRAIN_DAYS = 5
#: Free-run validation RMSE bounds [K] on the synthetic R1C1 data (about 2-7x what each gets).
#: Linear and ridge miss R1C1's occupancy x temperature and ventilation x temperature
#: products; k-NN and random forests cannot extrapolate between training samples.
FREE_RUN_BOUND_K = {'linear': 0.4, 'ridge': 0.4, 'knn': 0.75, 'random_forest': 0.6,
                    'mlp': 0.1, 'svr': 0.05}


def _disturbances(occupied: bool = True, ventilated: bool = True) -> pd.DataFrame:
    """Eight synthetic days, with the ventilation open 40 % from 07:00 to 18:00."""
    scenario = synthetic_scenario(hours=24 * 8 + 1, seed=3)
    hour = (scenario.index.to_numpy() / 3600.0) % 24.0
    scenario['dpos'] = np.where((hour >= 7) & (hour < 18) & ventilated, 40.0, 0.0)
    if not occupied:
        scenario['occ'] = 0.0
    return scenario


def _split(data):
    split_s = TRAIN_DAYS * 86400.0
    return data.between(-np.inf, split_s), data.between(split_s, np.inf)


@pytest.fixture(scope='module')
def r1c1_data():
    """(training, validation) trajectories of R1C1 under the +-2000 W sinusoid."""
    return _split(make_excitation_data(R1C1Model(), _disturbances(), x0=(294.15,)))


@pytest.fixture(scope='module')
def svr_model(r1c1_data):
    train, _ = r1c1_data
    return make_zone_model('svr').fit(train.states, train.inputs)


class LeastSquares:
    """A third-party regressor: only fit/predict, no scikit-learn base, 1-D targets only."""

    def fit(self, X, y):
        y = np.asarray(y, dtype=float)
        if y.ndim != 1:
            raise ValueError('LeastSquares fits one target at a time')
        design = np.column_stack([X, np.ones(len(X))])
        self.coef_, *_ = np.linalg.lstsq(design, y, rcond=None)
        return self

    def predict(self, X):
        return np.column_stack([X, np.ones(len(X))]) @ self.coef_


class CountingRegressor(LinearRegression):
    """LinearRegression that counts its predict calls."""

    def predict(self, X):
        CountingRegressor.calls.append(np.asarray(X).shape)
        return super().predict(X)


# -- every built-in estimator --------------------------------------------------------------------
@pytest.mark.parametrize('name', sorted(ESTIMATOR_FACTORIES))
def test_estimator_trains_and_validates(name, r1c1_data):
    train, validation = r1c1_data
    model = make_zone_model(name, seed=0).fit(train.states, train.inputs)
    rmse_free, max_free, rmse_one, table = evaluate(model, validation)
    ydf, xdf = model.simulate(validation.inputs, validation.states.iloc[0].to_numpy())
    assert np.all(np.isfinite(ydf.to_numpy())) and np.all(np.isfinite(xdf.to_numpy()))
    assert list(ydf.columns) == ['T', 'Qr'] and list(xdf.columns) == ['T']
    np.testing.assert_allclose(ydf['T'].to_numpy(), xdf['T'].to_numpy() - KELVIN)
    true = validation.states['T'].to_numpy()
    persistence = np.sqrt(np.mean((true[1:] - true[0]) ** 2))
    assert rmse_free < FREE_RUN_BOUND_K[name], (name, rmse_free)
    assert rmse_free < 0.8 * persistence, (name, rmse_free, persistence)
    assert rmse_one < rmse_free + 1e-12 and max_free >= rmse_free
    assert table.shape == (len(validation.states), 3)


def test_linear_exact_when_r1c1_is_affine():
    """Without occupants and ventilation the R1C1 per-step change is affine in T and inputs."""
    train, validation = _split(make_excitation_data(
        R1C1Model(), _disturbances(occupied=False, ventilated=False), x0=(294.15,)))
    for name, bound in (('linear', 1e-8), ('ridge', 1e-3)):
        model = make_zone_model(name).fit(train.states, train.inputs)
        rmse_free, max_free, _, _ = evaluate(model, validation)
        assert max_free < bound, (name, max_free)


def test_pipeline_with_interactions_is_nearly_exact(r1c1_data):
    """Degree-2 features hold the occupancy and ventilation products of R1C1."""
    train, validation = r1c1_data
    estimator = make_pipeline(PolynomialFeatures(2), LinearRegression())
    model = make_zone_model(estimator).fit(train.states, train.inputs)
    assert evaluate(model, validation)[1] < 1e-3


def test_use_state_false_trains(r1c1_data):
    train, validation = r1c1_data
    model = make_zone_model('ridge', use_state=False).fit(train.states, train.inputs)
    assert model.feature_names == R1C1Model.input_names
    assert np.isfinite(evaluate(model, validation)[0])


# -- batch path and sequential simulation agree ------------------------------------------------
@pytest.mark.parametrize('n_steps', [1, 3])
def test_batch_equals_successive_simulate(svr_model, r1c1_data, n_steps):
    _, validation = r1c1_data
    rng = np.random.default_rng(7)
    batch = 20
    rows = rng.integers(0, len(validation.inputs) - 1, size=batch)
    u = validation.inputs.to_numpy()[rows]
    u[:, 4] = rng.uniform(-2000.0, 2000.0, size=batch)
    x_start = rng.uniform(292.0, 298.0, size=(batch, 1))
    dt_s = n_steps * svr_model.step_s
    x_end, y_end = svr_model.simulate_intervals(x_start, u, dt_s)
    assert x_end.shape == (batch, 1) and y_end.shape == (batch, 2)
    for b in range(batch):
        udf = pd.DataFrame(np.vstack([u[b], u[b]]), index=[0.0, dt_s],
                           columns=list(svr_model.input_names))
        ydf, xdf = svr_model.simulate(udf, x_start[b])
        np.testing.assert_allclose(xdf.to_numpy()[-1], x_end[b], rtol=0, atol=1e-10)
        np.testing.assert_allclose(ydf.to_numpy()[-1], y_end[b], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(y_end[:, 1], u[:, 4] * dt_s)  # Qr = q dt over the interval
    np.testing.assert_allclose(y_end[:, 0], x_end[:, 0] - KELVIN)


def test_simulate_chains_single_intervals(svr_model, r1c1_data):
    _, validation = r1c1_data
    udf = validation.inputs.iloc[:25]
    ydf, xdf = svr_model.simulate(udf, [295.0])
    x = np.array([[295.0]])
    u = udf.to_numpy()
    for k in range(len(udf) - 1):
        x, y = svr_model.simulate_intervals(x, u[k:k + 1], svr_model.step_s)
        np.testing.assert_allclose(xdf.to_numpy()[k + 1], x[0], rtol=0, atol=1e-10)
        np.testing.assert_allclose(ydf['T'].iloc[k + 1], y[0, 0], rtol=0, atol=1e-10)
    qr = np.concatenate([[0.0], np.cumsum(u[:-1, 4] * np.diff(udf.index.to_numpy()))])
    np.testing.assert_allclose(ydf['Qr'].to_numpy(), qr)
    assert xdf['T'].iloc[0] == 295.0


def test_one_predict_call_per_substep_for_the_whole_batch(r1c1_data):
    train, _ = r1c1_data
    model = make_zone_model(CountingRegressor()).fit(train.states, train.inputs)
    CountingRegressor.calls = []
    u = np.tile(train.inputs.to_numpy()[:1], (20, 1))
    model.simulate_intervals(np.full((20, 1), 294.0), u, 3 * model.step_s)
    assert CountingRegressor.calls == [(20, 6)] * 3


def test_substeps_match_a_fine_grid(r1c1_data):
    """A 900 s model simulated on hourly rows equals it on 900 s rows with held inputs."""
    train, validation = r1c1_data
    fine = make_excitation_data(R1C1Model(), _disturbances(), step_s=900.0, x0=(294.15,))
    model = make_zone_model('ridge', step_s=900.0).fit(*_fit_args(fine.between(0, 4e5)))
    hourly = validation.inputs.iloc[:12]
    index_fine = np.arange(hourly.index[0], hourly.index[-1] + 1.0, 900.0)
    held = hourly.reindex(index_fine, method='ffill')
    _, x_hourly = model.simulate(hourly, [295.0])
    _, x_fine = model.simulate(held, [295.0])
    np.testing.assert_allclose(x_hourly['T'].to_numpy(),
                               x_fine['T'].loc[hourly.index].to_numpy(), rtol=0, atol=1e-10)


def _fit_args(data):
    return data.states, data.inputs


# -- general models: several states, learned outputs, third-party estimators -------------------
def _two_state_data(n=300, seed=0):
    """Simulate a linear two-state system with one learned output y = 2 x1 - x2 + 0.5 u."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.9, 0.05], [0.1, 0.8]])
    b = np.array([[0.3], [0.1]])
    u = rng.uniform(-1.0, 1.0, size=(n, 1))
    x = np.zeros((n, 2))
    for k in range(n - 1):
        x[k + 1] = a @ x[k] + b @ u[k]
    y = 2.0 * x[1:, 0] - x[1:, 1] + 0.5 * u[:-1, 0]
    index = np.arange(n) * 600.0
    states = pd.DataFrame(x, index=index, columns=['x1', 'x2'])
    inputs = pd.DataFrame(u, index=index, columns=['u'])
    outputs = pd.DataFrame({'y': np.concatenate([[0.0], y])}, index=index)
    return states, inputs, outputs


@pytest.mark.parametrize('estimator', [LeastSquares(), LinearRegression()])
def test_multi_state_learned_and_analytic_outputs(estimator):
    states, inputs, outputs = _two_state_data()
    model = SklearnModel(estimator, ['x1', 'x2'], ['u'], step_s=600.0,
                         analytic_outputs=[state_output('x1_scaled', 'x1', scale=10.0),
                                           input_integral('u_integral', 'u')],
                         learned_output_names=['y'])
    assert model.output_names == ('x1_scaled', 'u_integral', 'y')
    model.fit(states, inputs, outputs)
    assert model._state_regressor.per_target == isinstance(estimator, LeastSquares)
    ydf, xdf = model.simulate(inputs.iloc[:50], states.iloc[0].to_numpy())
    np.testing.assert_allclose(xdf.to_numpy(), states.iloc[:50].to_numpy(), atol=1e-9)
    np.testing.assert_allclose(ydf['y'].to_numpy()[1:], outputs['y'].to_numpy()[1:50],
                               atol=1e-9)
    np.testing.assert_allclose(ydf['x1_scaled'].to_numpy(), 10.0 * xdf['x1'].to_numpy())
    np.testing.assert_allclose(ydf['u_integral'].to_numpy()[-1],
                               600.0 * inputs['u'].to_numpy()[:49].sum())
    x_end, y_end = model.simulate_intervals(states.to_numpy()[:5], inputs.to_numpy()[:5], 600.0)
    np.testing.assert_allclose(x_end, states.to_numpy()[1:6], atol=1e-9)
    np.testing.assert_allclose(y_end[:, 2], outputs['y'].to_numpy()[1:6], atol=1e-9)


def test_failed_fit_leaves_the_model_unchanged():
    states, inputs, _ = _two_state_data()
    model = SklearnModel(LeastSquares(), ['x1', 'x2'], ['u'], step_s=600.0, per_target=False)
    with pytest.raises(ValueError, match='one target at a time'):
        model.fit(states, inputs)
    assert not model.is_fitted
    model.per_target = True
    model.fit(states, inputs)
    x_end, _ = model.simulate_intervals(states.to_numpy()[:3], inputs.to_numpy()[:3], 600.0)
    model.per_target = False
    with pytest.raises(ValueError, match='one target at a time'):
        model.fit(states, inputs)
    np.testing.assert_array_equal(
        model.simulate_intervals(states.to_numpy()[:3], inputs.to_numpy()[:3], 600.0)[0], x_end)


def test_fit_accepts_several_trajectories():
    first, second = _two_state_data(seed=1), _two_state_data(seed=2)
    second_states = second[0].set_axis(second[0].index + 1e6)  # a gap: no pair across it
    second_inputs = second[1].set_axis(second[1].index + 1e6)
    model = SklearnModel(LinearRegression(), ['x1', 'x2'], ['u'], step_s=600.0)
    model.fit([first[0], second_states], [first[1], second_inputs])
    assert model.n_training_pairs_ == 2 * (len(first[0]) - 1)


def test_third_party_estimator_on_r1c1(r1c1_data):
    train, validation = r1c1_data
    model = make_zone_model(LeastSquares()).fit(train.states, train.inputs)
    reference = make_zone_model('linear').fit(train.states, train.inputs)
    assert evaluate(model, validation)[0] == pytest.approx(evaluate(reference, validation)[0],
                                                           rel=1e-6)


# -- training data --------------------------------------------------------------------------------
def test_excitation_data_is_the_r1c1_response():
    disturbances = _disturbances()
    data = make_excitation_data(R1C1Model(), disturbances, amplitude_w=2000.0, period_h=10.0,
                                x0=(294.15,), fixed_inputs={'dpos': 0.0})
    q = data.inputs['q'].to_numpy()
    assert np.max(np.abs(q)) <= 2000.0 and np.max(q) > 1900.0 and np.min(q) < -1900.0
    np.testing.assert_allclose(q[:11], 2000.0 * np.sin(2 * np.pi * np.arange(11) / 10.0),
                               atol=1e-9)
    assert np.all(data.inputs['dpos'] == 0.0)
    np.testing.assert_array_equal(data.inputs['Tout'].to_numpy(),
                                  disturbances['Tout'].to_numpy())
    ydf, xdf = R1C1Model().simulate(data.inputs, [294.15])
    pd.testing.assert_frame_equal(xdf, data.states)
    pd.testing.assert_frame_equal(ydf, data.outputs)


# -- bad inputs -------------------------------------------------------------------------------
def test_untrained_model_raises():
    model = make_zone_model('svr')
    udf = _disturbances().iloc[:3].assign(q=0.0)
    with pytest.raises(NotFittedError, match='not trained'):
        model.simulate(udf, [294.0])
    with pytest.raises(ValueError, match='not trained'):
        model.simulate_intervals(np.array([[294.0]]), np.zeros((1, 5)), 3600.0)


def test_bad_simulation_inputs_raise(svr_model):
    udf = _disturbances().iloc[:4].assign(q=100.0)
    with pytest.raises(ValueError, match=r"lacks input columns \['q'\]"):
        svr_model.simulate(udf.drop(columns='q'), [294.0])
    with pytest.raises(ValueError, match='non-finite'):
        svr_model.simulate(udf.assign(Tout=np.nan), [294.0])
    with pytest.raises(ValueError, match='x0 must have 1'):
        svr_model.simulate(udf, [294.0, 1.0])
    with pytest.raises(ValueError, match='multiple of the learning step'):
        svr_model.simulate(udf.set_axis([0.0, 3600.0, 5400.0, 9000.0]), [294.0])
    with pytest.raises(ValueError, match='multiple of the learning step'):
        svr_model.simulate_intervals(np.array([[294.0]]), np.zeros((1, 5)), 1800.0)
    with pytest.raises(ValueError, match=r'shape \(2, 5\)'):
        svr_model.simulate_intervals(np.full((2, 1), 294.0), np.zeros((2, 4)), 3600.0)
    with pytest.raises(ValueError, match='finite'):
        svr_model.simulate_intervals(np.array([[np.nan]]), np.zeros((1, 5)), 3600.0)


def test_bad_training_data_raise(r1c1_data):
    train, _ = r1c1_data
    model = make_zone_model('linear')
    with pytest.raises(ValueError, match=r"lacks columns \['occ'\]"):
        model.fit(train.states, train.inputs.drop(columns='occ'))
    nan_states = train.states.copy()
    nan_states.iloc[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"non-finite values \(count per column: \{'T': 1\}"):
        model.fit(nan_states, train.inputs)
    with pytest.raises(ValueError, match='step_s = 1800 s apart'):
        make_zone_model('linear', step_s=1800.0).fit(train.states, train.inputs)
    with pytest.raises(ValueError, match='share one time index'):
        model.fit(train.states, train.inputs.iloc[1:])
    with pytest.raises(ValueError, match='at least 2 training pairs'):
        model.fit(train.states.iloc[:2], train.inputs.iloc[:2])
    learned = SklearnModel(LinearRegression(), ['T'], ['q'], learned_output_names=['P'])
    with pytest.raises(ValueError, match='needs output trajectories'):
        learned.fit(train.states, train.inputs)
    assert not model.is_fitted


def test_bad_configuration_raises(caplog):
    with pytest.raises(ValueError, match="unknown estimator 'svm'"):
        make_estimator('svm')
    with pytest.raises(TypeError, match='fit.*predict'):
        SklearnModel(object(), ['T'], ['q'])
    with pytest.raises(ValueError, match="refers to unknown name 'Tz'"):
        SklearnModel(LinearRegression(), ['T'], ['q'],
                     analytic_outputs=[state_output('T_c', 'Tz', offset=-KELVIN)])
    with pytest.raises(ValueError, match='unique'):
        SklearnModel(LinearRegression(), ['T'], ['q'],
                     analytic_outputs=[AnalyticOutput('y', lambda x, u: u['q'])],
                     learned_output_names=['y'])
    with pytest.raises(ValueError, match='step_s must be a positive'):
        SklearnModel(LinearRegression(), ['T'], ['q'], step_s=0.0)
    with pytest.raises(ValueError, match="lacks columns \\['solrad'"):
        make_excitation_data(R1C1Model(), _disturbances().drop(columns='solrad'))
    states, inputs, _ = _two_state_data()
    with caplog.at_level(logging.WARNING):
        SklearnModel(LinearRegression(), ['x1', 'x2'], ['u', 'c'], step_s=600.0).fit(
            states, inputs.assign(c=1.0))
    assert "'c' is constant" in caplog.text
