"""
One registry of zone models: one vocabulary and one set of defaults everywhere.

The case command, the study, the benchmarks and the ROS nodes build their
models here, by name:

- ``'python'``: the exact R1C1, the thermal network of the built-in card ``r1c1.yaml``
  (:class:`~mshoot_core.models.network.NetworkModel`);
- ``'r2c2'``: the exact two-node R2C2, the network of the card ``r2c2.yaml`` (air
  ``T`` and envelope ``Tw`` [K], the R1C1's inputs; only ``T`` measured);
- ``'fmu'``: the built-in R1C1 FMU as Model Exchange (integrated at the given
  relative tolerance); ``'fmu-cs'``: the same FMU as Co-Simulation;
- a path ending in ``.fmu``: an FMU with the R1C1 zone's variables (inputs
  solrad, Tout, occ, dpos, q; state heatCapacitor.T [K]; outputs T [degC], Qr
  [J]), run as Model Exchange;
- a path ending in ``.yaml`` or ``.yml``: a model card
  (:mod:`mshoot_core.models.card`): any FMU with its names mapped, or a
  built-in model; the card's tolerance, if it sets one, wins over the
  ``tolerance`` given here;
- ``'r1c1x2'``: two independent R1C1 zones, the network of the card ``r1c1x2.yaml``
  (:func:`~mshoot_core.models.multizone.multizone_network` of 2 zones, seed 0): controls
  ``q_0``, ``q_1`` [W], states ``T_0``, ``T_1`` [K] (the multi-zone case over ROS);
- names that applications add with :func:`register` (e.g. the data-driven
  models of Setup 2, trained on data the application holds).

Defaults: :data:`CONTROL_TOLERANCE` for control models (the MPC's
sensitivities are accurate well above the integrator noise there) and
:data:`EMULATOR_TOLERANCE` for emulated buildings.

How a model is controlled (:func:`control_interface`): its controls (the MPC's
decision variables, the setpoint's named values) and its zone temperatures
(the states bounded by the comfort band, the temperature setpoints of the
building's local loops). A model declares them with the attributes
``control_names`` and ``comfort_states``; without them the R1C1 convention
applies (control ``q``, zone temperature ``T`` [K]). Every zone temperature is
bounded by the forecast's band (``comfort_min``, ``comfort_max`` [degC]) unless
the model's ``comfort_bands`` gives it a band of its own (``{state: (lower,
upper)}`` series, e.g. a card with several zones' bands:
:func:`~mshoot_core.models.card.comfort_bands`).
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import pathlib
from typing import Callable

import numpy as np

from mshoot_core.models.base import Model
from mshoot_core.models.defaults import (CONTROL_TOLERANCE, EMULATOR_TOLERANCE,  # noqa: F401
                                         is_card_path)
from mshoot_core.safety import COMFORT_SERIES
from mshoot_core.settings import fields_of, setting, SettingField, SettingsGroup
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: The built-in single-zone models.
BUILTIN = ('python', 'fmu', 'fmu-cs', 'r2c2')
#: The built-in multi-zone models: name -> number of independent R1C1 zones.
MULTIZONE = {'r1c1x2': 2}
#: The built-in models described by a built-in card (a thermal network): name -> card.
CARD_MODELS = {'python': 'r1c1', 'r2c2': 'r2c2', 'r1c1x2': 'r1c1x2'}

#: Factories added by applications: name -> (factory(tolerance) -> Model, description).
_REGISTERED: dict[str, tuple[Callable[[float], Model], str]] = {}


def register(name: str, factory: Callable[[float], Model], description: str) -> None:
    """
    Add a model name (e.g. a trained data-driven model) to the vocabulary.

    Parameters
    ----------
    name : str
        The name; must not shadow a built-in one or end in '.fmu'.
    factory : callable
        ``factory(tolerance) -> Model``.
    description : str
        One line for help texts.

    """
    if (name in BUILTIN or name in MULTIZONE or name.endswith('.fmu') or is_card_path(name)
            or not name):
        raise ValueError(f'cannot register a model named {name!r}')
    _REGISTERED[name] = (factory, description)


def model_names() -> tuple[str, ...]:
    """Every model name understood (besides a path to an .fmu file or a model card)."""
    return BUILTIN + tuple(MULTIZONE) + tuple(sorted(_REGISTERED))


@functools.lru_cache(maxsize=16)
def _card_problem(path: str, version: tuple[int, int] | None) -> str | None:
    """Check a card once per file version (nodes validate all parameters at each declaration)."""
    from mshoot_core.models.card import CardError, load_card
    try:
        load_card(path)
    except CardError as exc:
        return str(exc)
    return None


def card_controls(name: str) -> tuple:
    """
    Return the controls of the card ``name`` (ControlSpecs), or () for another model name.

    For checking settings against a card's limits before its model is built (an invalid card:
    (), its problems are :func:`check_model`'s).
    """
    if not is_card_path(name) or check_model(name) is not None:
        return ()
    stat = pathlib.Path(name).expanduser().stat()
    return _card_controls(name, (stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=16)
def _card_controls(path: str, version: tuple[int, int]) -> tuple:
    from mshoot_core.models.card import load_card
    return load_card(path).control_specs()


def check_model(name: str) -> str | None:
    """
    Say why ``name`` does not name a model, or return None.

    A model card is loaded and checked against its model: every problem of the card in one line.
    """
    if name in BUILTIN or name in MULTIZONE or name in _REGISTERED:
        return None
    if name.endswith('.fmu'):
        return None if pathlib.Path(name).is_file() else f'FMU file {name!r} not found'
    if is_card_path(name):
        path = pathlib.Path(name).expanduser()
        try:
            stat = path.stat()
        except OSError:
            return _card_problem(name, None)
        return _card_problem(name, (stat.st_mtime_ns, stat.st_size))
    return (f'model must be one of {list(model_names())}, a path to an .fmu file or a model '
            f'card (.yaml), got {name!r}')


def build_model(name: str, tolerance: float = CONTROL_TOLERANCE,
                role: str = 'control') -> Model:
    """
    Build the model named ``name`` (see the module docstring).

    Parameters
    ----------
    name : str
        A name of :func:`model_names`, a path to an .fmu file or to a model card.
    tolerance : float
        Relative tolerance of an FMU integrator [-] (a card's own tolerance wins).
    role : {'control', 'emulator'}
        What a model card's model is built for (its FMU instance's name).

    Raises
    ------
    ValueError
        Unknown name, missing FMU file, FMU support missing, or an invalid
        model card (:class:`~mshoot_core.models.card.CardError`, every problem).

    """
    if not 0 < tolerance < 1:
        raise ValueError(f'tolerance must be in (0, 1), got {tolerance}')
    if is_card_path(name):
        from mshoot_core.models import card
        return card.build_model(card.load_card(name), role, tolerance=tolerance)
    problem = check_model(name)
    if problem:
        raise ValueError(problem)
    if name == 'python':
        from mshoot_core.models.r1c1 import R1C1Model
        return R1C1Model()
    if name == 'r2c2':
        from mshoot_core.models.r2c2 import R2C2Model
        return R2C2Model()
    if name in MULTIZONE:  # the network of its card (no card check: a built-in, tested)
        from mshoot_core.models.network import card_network, CARDS_DIR, NetworkModel
        spec = card_network(CARDS_DIR / f'{CARD_MODELS[name]}.yaml')
        return NetworkModel(spec, control_names=tuple(f'q_{i}' for i in range(MULTIZONE[name])),
                            comfort_states=tuple(spec.nodes))
    if name in _REGISTERED:
        return _REGISTERED[name][0](tolerance)
    try:
        from mshoot_core.models.fmi import r1c1_fmi_model
    except ImportError as exc:
        raise ValueError(f'model {name!r} needs FMU support in mshoot_core ({exc})') from exc
    fmi_type = 'CoSimulation' if name == 'fmu-cs' else 'ModelExchange'
    return r1c1_fmi_model(fmi_type=fmi_type, tolerance=tolerance,
                          fmu_path=None if name in BUILTIN else pathlib.Path(name))


@dataclasses.dataclass(frozen=True)
class ControlInterface:
    """
    How a model is controlled: what the MPC optimises and the comfort band bounds.

    Attributes
    ----------
    control_names : tuple of str
        The model inputs the controller sets (its decision variables, the named
        controls of a setpoint), in the model's input order.
    state_names : tuple of str
        The model's states (their order in state vectors).
    state_bounds : dict
        ``{state: ('comfort_min', 'comfort_max', offset)}`` for every zone
        temperature state (in the model's state order): bounded by the comfort
        band [degC] plus ``offset`` (273.15 for states in K), or by its own band's
        series (the model's ``comfort_bands``); the form of
        :class:`mshoot_core.mpc.MPC`'s ``state_bounds``.

    """

    control_names: tuple[str, ...]
    state_names: tuple[str, ...]
    state_bounds: dict[str, tuple[str, str, float]]

    @property
    def temperature_names(self) -> tuple[str, ...]:
        """Return the zone temperature states (those bounded by the comfort band)."""
        return tuple(self.state_bounds)

    def temperatures_c(self, x: np.ndarray) -> np.ndarray:
        """
        Return the zone temperatures [degC] of states ``x``.

        ``x`` has shape (..., nx), the result (..., nz) in the order of :attr:`temperature_names`.
        """
        x = np.asarray(x, dtype=float)
        columns = [self.state_names.index(s) for s in self.state_bounds]
        offsets = np.array([spec[2] for spec in self.state_bounds.values()])
        return x[..., columns] - offsets


def control_interface(model: Model) -> ControlInterface:
    """
    Return the controls and zone temperatures of ``model`` (see the module docstring).

    Raises
    ------
    ValueError
        If the declared names are not inputs / states of the model, or a model
        declares no controls and has no input ``q``.

    """
    inputs, states = tuple(model.input_names), tuple(model.state_names)
    controls = getattr(model, 'control_names', None)
    if controls is None:
        if 'q' not in inputs:
            raise ValueError(f'{type(model).__name__} declares no control_names and has no '
                             f"input 'q' (inputs {list(inputs)})")
        controls = ('q',)
    controls = tuple(controls)
    unknown = [c for c in controls if c not in inputs]
    if not controls or unknown or len(set(controls)) != len(controls):
        raise ValueError(f'control_names must be distinct inputs of the model {list(inputs)}, '
                         f'got {list(controls)}')
    comfort = getattr(model, 'comfort_states', None)
    if comfort is None:
        comfort = ('T',) if 'T' in states else ()
    unknown = [s for s in comfort if s not in states]
    if unknown:
        raise ValueError(f'comfort_states {unknown} are not states of the model {list(states)}')
    bands = dict(getattr(model, 'comfort_bands', None) or {})
    unknown = [s for s in bands if s not in comfort]
    if unknown:
        raise ValueError(f'comfort_bands {unknown} are not comfort states {list(comfort)}')
    return ControlInterface(tuple(c for c in inputs if c in controls), states,
                            {s: (*bands.get(s, COMFORT_SERIES), KELVIN) for s in states
                             if s in comfort})


@dataclasses.dataclass(frozen=True)
class ModelSettings(SettingsGroup):
    """Which model, and how it is integrated."""

    model: str = setting('python', "zone model: 'python' (exact R1C1), 'fmu' (the R1C1 FMU, "
                         "Model Exchange), 'fmu-cs' (Co-Simulation), 'r2c2' (exact air + "
                         "envelope R2C2, only the air measured), 'r1c1x2' (two R1C1 "
                         'zones, controls q_0, q_1), a path to an .fmu with the R1C1 zone '
                         'interface, or a path to a model card (.yaml)', apply='fixed')
    fmu_tolerance: float = setting(CONTROL_TOLERANCE, 'relative tolerance of the FMU '
                                   'integrator [-]', low=1e-14, high=1e-2, apply='fixed',
                                   cli='--tolerance')

    def rules(self) -> list[str]:
        problem = check_model(self.model)
        return [problem] if problem else []

    def build(self) -> Model:
        """Build the model (see :func:`build_model`)."""
        return build_model(self.model, self.fmu_tolerance)


#: The model settings as described rows (node parameters, CLI options).
MODEL_PARAMETERS: tuple[SettingField, ...] = fields_of(ModelSettings)
