"""
An R2C2 zone, the network of the card ``cards/r2c2.yaml``: an air node and an envelope node.

Its heat balances [W]::

    Cair  dT/dt  = (Tw - T)/Raw + (Tout + 273.15 - T)/Rwin + (1 - fsun)*shgc*solrad
                   + occheff*84*occ + qv + q
    Cwall dTw/dt = (T - Tw)/Raw + (Tout + 273.15 - Tw)/Rwa + fsun*shgc*solrad
    qv = (1206/3600)*(maxVent*dpos/100)*(max(Tout, Tve) + 273.15 - T)

The air node ``T`` [K] is what a room sensor measures; the envelope node ``Tw`` [K]
(walls, slab, furniture) is not measured in a real building, so the model declares
``measured_states = ('T',)`` and a controller estimates ``Tw``
(:mod:`mshoot_core.estimation`). It takes the inputs of the R1C1 zone (``solrad``,
``Tout``, ``occ``, ``dpos``, ``q``), so it runs on the same scenarios and forecasts.
The equations and parameters live in the card; :class:`R2C2Model` is its
:class:`~mshoot_core.models.network.NetworkModel` (the matrix exponential in closed
form, :func:`~mshoot_core.models.network.expm2`, exact Jacobians and parameter
sensitivities).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

from mshoot_core.models.network import (card_network, CARDS_DIR, NetworkModel,
                                        parameters_class)

#: The card of the R2C2 zone.
CARD = CARDS_DIR / 'r2c2.yaml'
_SPEC = card_network(CARD)

#: Parameters of the R2C2 zone (a frozen dataclass; defaults: the card's, a classroom of the
#: OU44 building's size): Cair, Cwall [J/K], Raw, Rwa, Rwin [K/W], shgc [m2], fsun, occheff
#: [-], Tve [degC], maxVent [m3/h].
R2C2Parameters = parameters_class(
    _SPEC, 'R2C2Parameters', 'Parameters of the R2C2 zone (defaults: the card).', __name__)


class R2C2Model(NetworkModel):
    """
    The R2C2 zone: the network of :data:`CARD` with the given parameters.

    Inputs: ``solrad`` [W/m2], ``Tout`` [degC], ``occ`` [persons], ``dpos`` [%], ``q`` [W].
    States: ``T`` (air) and ``Tw`` (envelope) [K]. Outputs: ``T`` [degC] and ``Qr`` [J]
    (integral of q since the start of the simulation; per interval in
    :meth:`simulate_intervals`).

    Parameters
    ----------
    parameters : R2C2Parameters, optional
        Default: the card's values.
    measured_states : sequence of str
        The states a sensor measures (default: the air node only); a
        controller estimates the others.

    """

    input_names = tuple(_SPEC.inputs)
    state_names = tuple(_SPEC.nodes)
    output_names = tuple(_SPEC.outputs)

    def __init__(self, parameters: R2C2Parameters | None = None,
                 measured_states: Sequence[str] = ('T',)) -> None:
        values = None if parameters is None else {
            k: float(v) for k, v in dataclasses.asdict(parameters).items()}
        measured = tuple(measured_states)
        if not measured or not set(measured) <= set(_SPEC.nodes) or len(set(measured)) != len(
                measured):
            raise ValueError(f'measured_states must be distinct states of the R2C2 '
                             f'{list(_SPEC.nodes)}, got {list(measured)}')
        super().__init__(_SPEC, values=values, control_names=('q',), comfort_states=('T',),
                         measured_states=measured)
