"""
Setup 2 of the reference case: data-driven OU44 zone models trained on R1C1 responses.

The R1C1 zone is simulated over the measured OU44 disturbances of
2018-04-04 08:00 to 2018-04-13 21:00, excited by a +-2000 W sinusoidal heat
rate; a :class:`~mshoot_core.models.sklearn_model.SklearnModel` learns its
hourly temperature change over the first part (to 9 April) and is validated
by a free run over the rest (SPEC section 3, "Setup 2"). The generic pieces
(the model, the excitation data, the scores) are in
:mod:`mshoot_core.models.sklearn_model`; this module holds the case's dates
and its report.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
from typing import Any

from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.models.sklearn_model import (evaluate, make_excitation_data, make_zone_model,
                                              SklearnModel)
from mshoot_core.scenario import load_ou44
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd

logger = logging.getLogger(__name__)

#: Training and validation periods of Setup 2 (the data start at 2018-04-04 08:00).
SETUP2_START = '2018-04-04 08:00'
SETUP2_SPLIT = '2018-04-09 00:00'
SETUP2_END = '2018-04-13 21:00'


@dataclasses.dataclass(frozen=True)
class TrainingReport:
    """
    How a data-driven zone model did on its validation data.

    Attributes
    ----------
    estimator : str
        Estimator name or class.
    ventilation : str
        ``'measured'`` (dpos as measured) or ``'off'`` (dpos = 0).
    n_train, n_validation : int
        Training pairs and validation samples.
    rmse_free_run_k : float
        RMSE [K] of a free-run simulation over the validation period from the
        true initial state (no re-initialisation).
    max_abs_free_run_k : float
        Largest free-run error [K].
    rmse_one_step_k : float
        RMSE [K] of one-step predictions from the true state.
    rmse_train_free_run_k : float
        Free-run RMSE [K] over the training period.
    fit_time_s : float
        Wall-clock training time [s].
    validation : DataFrame, shape (n_validation, 3)
        ``T_true``, ``T_free_run``, ``T_one_step`` [degC] indexed by time [s].

    """

    estimator: str
    ventilation: str
    n_train: int
    n_validation: int
    rmse_free_run_k: float
    max_abs_free_run_k: float
    rmse_one_step_k: float
    rmse_train_free_run_k: float
    fit_time_s: float
    validation: pd.DataFrame = dataclasses.field(repr=False)


def train_setup2(ou44_csv: str | pathlib.Path, estimator: str | Any = 'svr', seed: int = 0,
                 *, ventilation: str = 'measured', step_s: float = 3600.0,
                 period_h: float = 10.0, amplitude_w: float = 2000.0,
                 use_state: bool = True) -> tuple[SklearnModel, TrainingReport]:
    """
    Train a data-driven OU44 zone model on R1C1 responses (SPEC Setup 2) and validate it.

    The R1C1 model is simulated over 2018-04-04 08:00 to 2018-04-13 21:00 on
    the measured disturbances (hourly means), from the measured initial
    temperature, excited by a sinusoidal q of ``amplitude_w``; the first part
    (to 9 April 00:00) trains the model, the rest (9-13 April) validates it
    with a free-run simulation from the R1C1 state at the split and with
    one-step predictions.

    Parameters
    ----------
    ou44_csv : path-like
        The OU44 ``measurements.csv``.
    estimator : str or object
        A name of :data:`ESTIMATOR_FACTORIES` or a regressor.
    seed : int
        Seed of a named estimator.
    ventilation : {'measured', 'off'}
        ``'measured'`` excites the R1C1 model with the measured damper
        position (the default: training and validation temperatures then
        stay in one 20-27 degC range); ``'off'`` sets dpos = 0 as in the MPC
        case, where the unventilated zone drifts to 34 degC in the validation
        days, beyond the training range.
    step_s : float
        Learning step [s] (a divisor of the MPC's 3600 s control step).
    period_h, amplitude_w : float
        The excitation sinusoid [h], [W].
    use_state : bool
        Learn the increment from the current temperature too.

    Returns
    -------
    (SklearnModel, TrainingReport)

    """
    if ventilation not in ('measured', 'off'):
        raise ValueError(f"ventilation must be 'measured' or 'off', got {ventilation!r}")
    scenario = load_ou44(ou44_csv, start=SETUP2_START, end=SETUP2_END, step_s=3600.0)
    split_s = (pd.Timestamp(SETUP2_SPLIT) - pd.Timestamp(SETUP2_START)).total_seconds()
    x0 = (float(scenario['T_measured'].iloc[0]) + KELVIN,)
    fixed = {'dpos': 0.0} if ventilation == 'off' else None
    data = make_excitation_data(R1C1Model(), scenario, amplitude_w=amplitude_w,
                                period_h=period_h, step_s=step_s, x0=x0, fixed_inputs=fixed)
    train = data.between(-np.inf, split_s)
    validation = data.between(split_s, np.inf)
    name = estimator if isinstance(estimator, str) else type(estimator).__name__
    model = make_zone_model(estimator, step_s=step_s, use_state=use_state, seed=seed)
    model.fit(train.states, train.inputs)
    rmse_free, max_free, rmse_one, table = evaluate(model, validation)
    rmse_train, _, _, _ = evaluate(model, train)
    report = TrainingReport(
        estimator=name, ventilation=ventilation, n_train=model.n_training_pairs_,
        n_validation=len(validation.states), rmse_free_run_k=rmse_free,
        max_abs_free_run_k=max_free, rmse_one_step_k=rmse_one,
        rmse_train_free_run_k=rmse_train, fit_time_s=model.fit_time_s_,
        validation=(table - KELVIN).rename(columns={'true': 'T_true', 'free_run': 'T_free_run',
                                                    'one_step': 'T_one_step'}))
    logger.info('Setup 2 %s (ventilation %s): validation RMSE free run %.3f K, one step %.4f K',
                name, ventilation, rmse_free, rmse_one)
    return model, report
