"""
One registry of zone models: one vocabulary and one set of defaults everywhere.

The case command, the study, the benchmarks and the ROS nodes build their
models here, by name:

- ``'python'``: the exact R1C1 (:class:`~mshoot_core.models.r1c1.R1C1Model`);
- ``'fmu'``: the built-in R1C1 FMU as Model Exchange (integrated at the given
  relative tolerance); ``'fmu-cs'``: the same FMU as Co-Simulation;
- a path ending in ``.fmu``: an FMU with the R1C1 zone's variables (inputs
  solrad, Tout, occ, dpos, q; state heatCapacitor.T [K]; outputs T [degC], Qr
  [J]), run as Model Exchange;
- names that applications add with :func:`register` (e.g. the data-driven
  models of Setup 2, trained on data the application holds).

Defaults: :data:`CONTROL_TOLERANCE` for control models (the MPC's
sensitivities are accurate well above the integrator noise there) and
:data:`EMULATOR_TOLERANCE` for emulated buildings.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
from typing import Callable

from mshoot_core.models.base import Model
from mshoot_core.settings import fields_of, setting, SettingField, SettingsGroup

logger = logging.getLogger(__name__)

#: Relative tolerance of an FMU integrator for a control model [-].
CONTROL_TOLERANCE = 1e-6
#: Relative tolerance of an FMU integrator for an emulated building [-].
EMULATOR_TOLERANCE = 1e-10
#: The built-in models.
BUILTIN = ('python', 'fmu', 'fmu-cs')

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
    if name in BUILTIN or name.endswith('.fmu') or not name:
        raise ValueError(f'cannot register a model named {name!r}')
    _REGISTERED[name] = (factory, description)


def model_names() -> tuple[str, ...]:
    """Every model name understood (besides a path to an .fmu file)."""
    return BUILTIN + tuple(sorted(_REGISTERED))


def check_model(name: str) -> str | None:
    """Why ``name`` does not name a model, or None."""
    if name in BUILTIN or name in _REGISTERED:
        return None
    if name.endswith('.fmu'):
        return None if pathlib.Path(name).is_file() else f'FMU file {name!r} not found'
    return (f'model must be one of {list(model_names())} or a path to an .fmu file, '
            f'got {name!r}')


def build_model(name: str, tolerance: float = CONTROL_TOLERANCE) -> Model:
    """
    Build the model named ``name`` (see the module docstring).

    Parameters
    ----------
    name : str
        A name of :func:`model_names` or a path to an .fmu file.
    tolerance : float
        Relative tolerance of an FMU integrator [-].

    Raises
    ------
    ValueError
        Unknown name, missing FMU file, or FMU support missing.

    """
    problem = check_model(name)
    if problem:
        raise ValueError(problem)
    if not 0 < tolerance < 1:
        raise ValueError(f'tolerance must be in (0, 1), got {tolerance}')
    if name == 'python':
        from mshoot_core.models.r1c1 import R1C1Model
        return R1C1Model()
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
class ModelSettings(SettingsGroup):
    """Which model, and how it is integrated."""

    model: str = setting('python', "zone model: 'python' (exact R1C1), 'fmu' (the R1C1 FMU, "
                         "Model Exchange), 'fmu-cs' (Co-Simulation) or a path to an .fmu with "
                         'the R1C1 zone interface', apply='fixed')
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
