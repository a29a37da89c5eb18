"""
The R1C1 zone of the OU44 reference case: the thermal network of the card ``cards/r1c1.yaml``.

    C dT/dt = (Tout + 273.15 - T)/R + shgc*solrad + occheff*occ*M(T) + qv + q
    C = tmass*1.2*1005*Vi,  R = RExt/(3*Vi^(2/3)),  M(T) = 84*(325.15 - T)/32
    qv = (1206/3600)*(maxVent*dpos/100)*(max(Tout, Tve) + 273.15 - T)

The equations, the parameters (values, bounds, which a calibration frees) and the
outputs live in the card; :class:`R1C1Model` is that card's
:class:`~mshoot_core.models.network.NetworkModel` (exact per-interval solution,
analytic Jacobians and parameter sensitivities) with the parameters of an
:class:`R1C1Parameters`, whose defaults are the card's values.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from mshoot_core.models.network import (card_network, CARDS_DIR, NetworkModel,
                                        parameters_class)
from mshoot_core.units import KELVIN  # noqa: F401 (re-exported)

#: The card of the R1C1 zone.
CARD = CARDS_DIR / 'r1c1.yaml'
#: Metabolic heat per occupant [W] at 293.15 K, falling linearly to 0 W at 325.15 K (the
#: card's occupant conductance; for references written outside the network, e.g. CasADi's).
OCC_HEAT_W = 84.0
OCC_HEAT_ZERO_K = 325.15
OCC_HEAT_SPAN_K = 32.0
#: Volumetric heat capacity of air [J/(m3 K)] over 3600 s/h, as in the original model.
AIR_HEAT_PER_M3H = 1206.0 / 3600.0
#: Heat capacity of the zone air per m3 and per unit of tmass [J/(m3 K)].
AIR_CAPACITY_J_M3K = 1.2 * 1005.0

_SPEC = card_network(CARD)
_CAPACITY = _SPEC.nodes['T'][0]
_CONDUCTANCE = _SPEC.conductances[0].value  # T to the outdoor air


class _Quantities:
    """Derived quantities of the R1C1 parameters (the card's expressions, per zone too)."""

    @property
    def capacity_j_k(self) -> float | np.ndarray:
        """Heat capacity C [J/K]."""
        return _CAPACITY.value(dataclasses.asdict(self))

    @property
    def resistance_k_w(self) -> float | np.ndarray:
        """Thermal resistance R to the outdoors [K/W]."""
        return 1.0 / _CONDUCTANCE.value(dataclasses.asdict(self))


#: Parameters of the R1C1 zone (a frozen dataclass; defaults: the card's, the calibrated
#: OU44 classroom): tmass, shgc, occheff, RExt, Tve, Vi, maxVent.
R1C1Parameters = parameters_class(
    _SPEC, 'R1C1Parameters', 'Parameters of the R1C1 zone (defaults: the card, the calibrated '
    'OU44 classroom).', __name__, bases=(_Quantities,))


class R1C1Model(NetworkModel):
    """
    The R1C1 zone: the network of :data:`CARD` with the given parameters.

    Inputs: ``solrad`` [W/m2], ``Tout`` [degC], ``occ`` [persons], ``dpos``
    [%], ``q`` [W]. State: ``T`` [K]. Outputs: ``T`` [degC], ``Qr`` = integral
    of q [J] since the start of the simulation (per interval in the batch methods).
    Monotone in ``q`` (derived from the network's structure).
    """

    input_names = tuple(_SPEC.inputs)
    state_names = tuple(_SPEC.nodes)
    output_names = tuple(_SPEC.outputs)

    def __init__(self, parameters: R1C1Parameters | None = None) -> None:
        values = None if parameters is None else {
            k: float(v) for k, v in dataclasses.asdict(parameters).items()}
        super().__init__(_SPEC, values=values)
