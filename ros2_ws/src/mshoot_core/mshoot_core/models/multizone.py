"""
A building of Z R1C1 zones: the scale test case of the optimiser, as one thermal network.

Every zone follows the R1C1 network of the card ``cards/r1c1.yaml`` with its own size,
solar aperture and occupancy share, under the shared outdoor conditions, and has its
own heater/cooler ``q_i``. The zones are thermally independent (no conductance between
them), so the network solves every node in closed form at once and the per-interval
Jacobian is diagonal: :meth:`~mshoot_core.models.network.NetworkModel.jacobian_sparsity`
says so, and finite differences perturb all zones at once. The two-zone building of the
registry (``r1c1x2``) is also written out as the card ``cards/r1c1x2.yaml``.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mshoot_core.models.network import NetworkModel
from mshoot_core.models.r1c1 import R1C1Parameters
from mshoot_core.units import KELVIN


def multizone_network(n_zones: int, seed: int = 0,
                      base: R1C1Parameters | None = None) -> dict[str, Any]:
    """
    Return the network section of Z independent R1C1 zones (the mapping a card holds).

    Parameters
    ----------
    n_zones : int
        Number of zones Z.
    seed : int
        Seed of the zone-to-zone variation: volume x U(0.7, 1.3), solar
        aperture x U(0.5, 1.5), occupancy share x U(0.5, 1.5).
    base : R1C1Parameters, optional
        Parameters of the reference zone (default: the OU44 classroom).

    """
    if int(n_zones) != n_zones or n_zones < 1:
        raise ValueError(f'n_zones must be a positive integer, got {n_zones}')
    n_zones = int(n_zones)
    rng = np.random.default_rng(seed)
    base = base or R1C1Parameters()
    volume = base.Vi * rng.uniform(0.7, 1.3, n_zones)
    solar = rng.uniform(0.5, 1.5, n_zones)
    occupancy = rng.uniform(0.5, 1.5, n_zones)
    shared = {k: float(v) for k, v in dataclasses.asdict(base).items() if k != 'Vi'}
    parameters: dict[str, Any] = dict(shared)
    nodes, conductances, gains, outputs = {}, [], [], {}
    for i in range(n_zones):
        parameters.update({f'Vi_{i}': float(volume[i]), f'solar_{i}': float(solar[i]),
                           f'occupancy_{i}': float(occupancy[i])})
        nodes[f'T_{i}'] = {'capacity': f'tmass * 1.2 * 1005 * Vi_{i}'}
        conductances += [
            {'between': [f'T_{i}', 'outdoor'], 'value': f'3 * Vi_{i} ** (2 / 3) / RExt'},
            {'between': [f'T_{i}', 'occupants'], 'value': f'occheff * occupancy_{i} * 84 / 32',
             'times': ['occ']},
            {'between': [f'T_{i}', 'supply'], 'value': '1206 / 3600 * maxVent / 100',
             'times': ['dpos']}]
        gains += [{'node': f'T_{i}', 'value': f'shgc * solar_{i}', 'times': ['solrad']},
                  {'node': f'T_{i}', 'value': 1, 'times': [f'q_{i}']}]
        outputs[f'Tc_{i}'] = {'unit': 'degC', 'terms': [{'state': f'T_{i}'}],
                              'offset': -KELVIN}
    return {'inputs': {'solrad': 'W/m2', 'Tout': 'degC', 'occ': '1', 'dpos': '%',
                       **{f'q_{i}': 'W' for i in range(n_zones)}},
            'parameters': parameters, 'nodes': nodes,
            'boundaries': {'outdoor': 'Tout + 273.15', 'occupants': 325.15,
                           'supply': 'max(Tout, Tve) + 273.15'},
            'conductances': conductances, 'gains': gains, 'outputs': outputs}


class MultiZoneModel(NetworkModel):
    """
    Z independent R1C1 zones in one network (see :func:`multizone_network`).

    Inputs ``solrad``, ``Tout``, ``occ``, ``dpos`` (shared) and ``q_0`` ...
    ``q_{Z-1}`` [W]; states ``T_0`` ... [K]; outputs ``Tc_0`` ... [degC].
    The controls (:attr:`control_names`) are the heat rates ``q_i``; every state
    is a zone temperature bounded by the comfort band (:attr:`comfort_states`;
    see :func:`mshoot_core.models.registry.control_interface`).

    Attributes
    ----------
    n_zones : int
    zone_parameters : R1C1Parameters
        The zones' R1C1 parameters, ``Vi`` an array of Z volumes [m3].
    solar_share, occupancy_share : ndarray, shape (Z,)
        Each zone's share of the reference solar aperture and occupancy.

    """

    def __init__(self, n_zones: int, seed: int = 0,
                 base: R1C1Parameters | None = None) -> None:
        section = multizone_network(n_zones, seed, base)
        self.n_zones = int(n_zones)
        values = section['parameters']
        zones = range(self.n_zones)
        self.solar_share = np.array([values[f'solar_{i}'] for i in zones])
        self.occupancy_share = np.array([values[f'occupancy_{i}'] for i in zones])
        self.zone_parameters = R1C1Parameters(**{
            **dataclasses.asdict(base or R1C1Parameters()),
            'Vi': np.array([values[f'Vi_{i}'] for i in zones])})
        controls = tuple(f'q_{i}' for i in zones)
        super().__init__(section, control_names=controls,
                         comfort_states=tuple(f'T_{i}' for i in zones))


def multizone_mpc_options(model: MultiZoneModel, solver: str = 'ipopt') -> dict:
    """
    MPC keyword arguments for a :class:`MultiZoneModel`.

    One heater per zone (-2000..2000 W), every zone bounded by the comfort
    band, and for IPOPT the large-problem configuration: a single
    exact-penalty solve where the band is out of reach, Mehrotra's
    predictor-corrector (the problem is a convex QP: the zones are affine in
    state and heat rate, the cost is quadratic), and the linear-algebra
    settings of :data:`mshoot_core.solvers.IPOPT_LARGE_PROBLEM_OPTIONS`.
    """
    options = {'control_names': model.control_names,
               'control_min': -2000.0, 'control_max': 2000.0,
               'state_bounds': {name: ('comfort_min', 'comfort_max', KELVIN)
                                for name in model.comfort_states},
               'solver': solver}
    if solver == 'ipopt':
        from mshoot_core.solvers import IPOPT_LARGE_PROBLEM_OPTIONS
        options.update(relaxation='exact-penalty',
                       solver_extra={'options': {'mehrotra_algorithm': 'yes',
                                                 **IPOPT_LARGE_PROBLEM_OPTIONS}})
    return options
