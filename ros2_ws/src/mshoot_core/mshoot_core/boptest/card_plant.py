"""
A card of kind ``boptest`` as the emulator's plant: the test case's FMU in the card's terms.

:class:`CardPlant` is what :func:`mshoot_core.models.card.build_model` makes of a card of kind
``boptest``: the test case's FMU (Co-Simulation or Model Exchange, at the card's ``tolerance``)
as one persistent :class:`~mshoot_core.boptest.plant.BoptestPlant` with the plant interface the
emulator drives (``plant_start``, ``plant_step``). ``plant_start`` runs the warm-up under the
building's own control (``warmup_days`` of the card) up to the scenario's first time; every
``plant_step`` applies the controls as overwrites (the card's canonical units converted to the
FMU's; a control with ``activate`` overwrites, one without leaves the building's own controller
in charge: the baseline) and advances in steps of <= 60 s, recording BOPTEST's outputs
(:meth:`CardPlant.boptest_records`) for the KPIs.

FMU time = scenario time - ``time_origin_s`` (the card's ``time_origin``, e.g. 1 January of
:data:`~mshoot_core.boptest.period_scenario.YEAR`, against the scenario's start; see
:func:`~mshoot_core.models.card.time_origin_seconds`).
"""
from __future__ import annotations

import logging
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core.boptest.plant import BoptestPlant, MAX_SAMPLE_S, ME_TOLERANCE
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.period_loop import run_steps

logger = logging.getLogger(__name__)


def card_overwrites(controls: Sequence[Any], values: Sequence[float],
                    released: Sequence[bool] = ()) -> dict[str, float | None]:
    """
    Return a plant's overwrites of card controls: FMU input -> value in the FMU's unit.

    The one conversion of controls to overwrites (:class:`CardPlant`, the supervised
    controller's pieces, the identification's excitation).

    Parameters
    ----------
    controls : sequence of CardVariable
        The card's controls (their ``variable`` is the overwrite input ``X_u``).
    values : sequence of float
        One value per control [canonical unit].
    released : sequence of bool
        Per control (or empty: none), whether its overwrite is released: its value is None,
        the building's own controller acts (:meth:`BoptestPlant.advance`).

    Raises
    ------
    ValueError
        For a number of values or flags other than the controls', or a non-finite value.

    """
    numbers = np.asarray(values, dtype=float).reshape(-1)
    flags = tuple(bool(r) for r in released) or (False,) * len(controls)
    if numbers.size != len(controls) or len(flags) != len(controls) \
            or not np.all(np.isfinite(numbers)):
        raise ValueError(f'expected {len(controls)} finite values and release flags of the '
                         f'controls {[v.variable for v in controls]}, got {list(values)} and '
                         f'{list(released)}')
    return {v.variable: None if free else v.to_model(value)
            for v, value, free in zip(controls, numbers, flags)}


def card_values(plant: BoptestPlant, variables: Sequence[Any]) -> list[float]:
    """
    Return card variables read from a plant now [canonical unit] (states, outputs).

    Parameters
    ----------
    plant : BoptestPlant
        A running plant.
    variables : sequence of CardVariable
        The card's variables.

    """
    now = plant.read([v.variable for v in variables])
    return [v.from_model(now[v.variable]) for v in variables]


def record_means(plant: BoptestPlant, variables: Sequence[Any], t0_s: float,
                 t1_s: float) -> Iterator[float]:
    """
    Yield the mean of each card variable over a plant's records in (t0, t1] [canonical unit].

    The step means of a card's outputs, as the emulator publishes them (``mean_<output>``) and
    the supervisory controller measures them.

    Parameters
    ----------
    plant : BoptestPlant
        The plant (recording the variables' FMU outputs).
    variables : sequence of CardVariable
        The card's variables.
    t0_s, t1_s : float
        The interval [s, FMU time].

    """
    table = plant.records(t0_s, t1_s)
    window = table[(table['time'] > t0_s) & (table['time'] <= t1_s + 1e-6)]
    for v in variables:
        yield v.from_model(float(window[v.variable].mean()))


class CardPlant:
    """
    A card's BOPTEST test case as a persistent plant (module docstring).

    Parameters
    ----------
    card : ModelCard
        A card of kind ``boptest`` (:func:`mshoot_core.models.card.load_card`).
    instance_name : str
        For messages.

    Attributes
    ----------
    input_names, control_names, state_names, output_names : tuple of str
        The card's canonical names (inputs = controls: the building reads its own weather).
    comfort_states : tuple of str
        The zone temperature states (``T``, ``T_<zone>``).
    control_limits : tuple of (float, float)
        The card's control limits [canonical units] (+-inf where it gives none).
    time_origin_s : float
        Scenario time of FMU time 0 [s], set by the emulator from the card's ``time_origin``.
    warmup_s : float
        Warm-up before the first step under the building's own control [s].

    """

    def __init__(self, card: Any, instance_name: str = 'mshoot-emulator') -> None:
        spec = dict(card.boptest or {})
        self.card = card
        self.case = TestCase.load(spec.get('test_case_dir'))
        self.warmup_s = float(spec.get('warmup_days', 7.0)) * 86400.0
        #: Step of the warm-up's history and of the published output means [s] (0: none).
        self.history_step_s = float(spec.get('history_step_s', 0.0))
        #: The warm-up's history (:meth:`plant_start` with ``history_step_s``): times [s,
        #: scenario], states at those times and step means of the outputs over the interval
        #: ending there (NaN at the first time) [canonical units].
        self.history: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.control_names = tuple(card.control_names)
        self.input_names = self.control_names
        self.state_names = tuple(card.state_names)
        self.output_names = tuple(card.output_names)
        #: Output names whose step means the emulator publishes (``mean_<name>``).
        self.step_mean_outputs = self.output_names if self.history_step_s > 0 else ()
        self.comfort_states = tuple(n for n in self.state_names if n == 'T' or n.startswith('T_'))
        self.control_limits = card.control_bounds((-np.inf, np.inf))
        self.time_origin_s = 0.0
        self.instance_name = instance_name
        # every output recorded, as BOPTEST stores them (the card's and kpis.json's among them)
        self.plant = BoptestPlant(self.case, tolerance=card.tolerance or ME_TOLERANCE)
        self._controls = [card.controls[n] for n in self.control_names]
        self._switches: dict[str, int] = {}  # switch -> on (1) / released (0)
        self._states = list(card.states.values())
        self._outputs = list(card.outputs.values())

    # -- conversions ---------------------------------------------------------------------------
    def overwrites(self, u: Sequence[float]) -> dict[str, float | None]:
        """
        Return the FMU overwrites of controls ``u`` [canonical units] (:func:`card_overwrites`).

        Controls without ``activate`` in the card, or released, are not overwritten (None): the
        building's own control.
        """
        released = [v.activate is None or not self._switches.get(v.activate, 1)
                    for v in self._controls]
        return card_overwrites(self._controls, u, released)

    def plant_switches(self, values: Mapping[str, bool]) -> None:
        """Set overwrite switches (the card's ``activate``): 0 releases the overwrite."""
        switches = {v.activate for v in self._controls if v.activate is not None}
        unknown = [name for name in values if name not in switches]
        if unknown:
            raise ValueError(f'{unknown} are not overwrite switches of the card: '
                             f'{sorted(switches)}')
        self._switches.update({name: int(bool(on)) for name, on in values.items()})

    @property
    def switch_state(self) -> dict[str, int]:
        """Return the overwrite switches of the card's controls as applied (1: on)."""
        return {v.activate: self._switches.get(v.activate, 1) for v in self._controls
                if v.activate is not None}

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        values = card_values(self.plant, [*self._states, *self._outputs])
        return np.array(values[:len(self._states)]), np.array(values[len(self._states):])

    # -- the plant -----------------------------------------------------------------------------
    @property
    def plant_time_s(self) -> float | None:
        """Return the plant's time in the caller's (scenario) time base [s], or None."""
        t = self.plant.time_s
        return None if t is None else t + self.time_origin_s

    def fmu_time(self, t_s: float) -> float:
        """Return the FMU time [s from 1 January] of a scenario time [s]."""
        return float(t_s) - self.time_origin_s

    def plant_start(self, x0: Sequence[float], t_s: float,
                    u: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """
        Start the FMU ``warmup_s`` before ``t_s`` and warm it up under its own control.

        ``x0`` is not used (the FMU starts from its built-in state: hence the warm-up); ``u``
        is checked and applied from the first step on.

        Returns
        -------
        (x, y) : the states and outputs at ``t_s`` [canonical units].

        """
        self.overwrites(u)
        start = self.fmu_time(t_s)
        if self.plant.running:
            self.plant.close()
        self.plant.start(start - self.warmup_s)
        if self.history_step_s > 0:
            self.history = self._warm_up_recorded(start - self.warmup_s, start)
        else:
            self.plant.advance(start)
        logger.info('%s warmed up under its own control from %g s to %g s (FMU time)',
                    self.case.name, start - self.warmup_s, start)
        return self._read()

    def _warm_up_recorded(self, t0_s: float, t1_s: float) -> tuple[np.ndarray, ...]:
        """Warm up from t0 to t1 (FMU time) in history steps; return the history."""
        step = self.history_step_s
        n = int(round((t1_s - t0_s) / step))
        if n < 0 or abs(t0_s + n * step - t1_s) > 1e-6:
            raise ValueError(f'the warm-up ({(t1_s - t0_s) / 86400:g} d) must be a whole '
                             f'number of history steps ({step:g} s)')
        times, states = [t0_s], [self._read()[0]]
        means = [np.full(len(self._outputs), np.nan)]

        def own_control(a: float, b: float, decided: None) -> None:
            self.plant.advance(b)
            means.append(self._step_means(a, b))
            states.append(self._read()[0])
            times.append(b)

        run_steps(t0_s, t0_s + n * step, step, own_control, label=f'{self.case.name} warm-up')
        return (np.asarray(times) + self.time_origin_s, np.array(states), np.array(means))

    def _step_means(self, t0_s: float, t1_s: float) -> np.ndarray:
        """Means of the outputs over the records in (t0, t1] (FMU time) [canonical units]."""
        return np.array(list(record_means(self.plant, self._outputs, t0_s, t1_s)))

    def step_means(self, t0_s: float, t1_s: float) -> dict[str, float]:
        """Return the means of the outputs over (t0, t1] (scenario time) by output name."""
        values = self._step_means(self.fmu_time(t0_s), self.fmu_time(t1_s))
        return dict(zip(self.output_names, map(float, values)))

    def plant_step(self, u: Sequence[float], dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Apply controls ``u`` [canonical units] over ``dt_s`` [s]; return states and outputs."""
        if not self.plant.running:
            raise RuntimeError('the BOPTEST plant is not running: plant_start first')
        self.plant.advance(self.plant.time_s + float(dt_s), self.overwrites(u),
                           sample_s=min(MAX_SAMPLE_S, float(dt_s)))
        return self._read()

    def boptest_records(self) -> pd.DataFrame:
        """Return the plant's record table (:meth:`BoptestPlant.records`, FMU time)."""
        return self.plant.records()

    def close(self) -> None:
        """Free the FMU instance (the records stay)."""
        self.plant.close()

    def __repr__(self) -> str:
        """Return a short description."""
        return (f'CardPlant({self.case.name}, controls {list(self.control_names)}, '
                f'warm-up {self.warmup_s / 86400:g} d)')
