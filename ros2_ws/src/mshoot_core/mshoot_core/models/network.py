"""
One linear thermal network, described by data (a card's ``network`` section).

A network has *nodes* (temperatures [K], each with a heat capacity [J/K]),
*boundaries* (temperatures [K] the network does not change: the outdoor air, a
ventilation supply), *conductances* [W/K] between two nodes or a node and a
boundary, and *gains* [W] into a node. Every conductance and gain is a value
(an expression of the parameters) times an optional product of inputs
(``times``): ``occheff * 84 / 32`` times ``occ`` is a conductance that grows with
the occupancy, ``1206 / 3600 * maxVent / 100`` times ``dpos`` one that opens
with the damper, ``1`` times ``q`` a heat rate, ``qb`` times ``[d, Tout]`` a heat
pump's heat linear in its duty and the outdoor temperature. A boundary
temperature is an expression of inputs and parameters (``Tout + 273.15``,
``max(Tout, Tve) + 273.15``). Outputs are linear in the states plus products of
inputs (``integral: true``: the integral of the input terms, per interval in
the batch methods and since the start in :meth:`NetworkModel.simulate`)::

    C_i dT_i/dt = sum_j G_ij(u) (T_j - T_i) + sum_b G_ib(u) (T_b(u) - T_i) + sum Q_i(u)

With the inputs held over an interval this is ``dx/dt = A(u) x + b(u)``, solved
exactly: nodes without a neighbour node in closed form
``T_end = f/g + (T_0 - f/g) exp(-g dt / C)``, coupled nodes by the matrix
exponential (:func:`expm2` for two nodes), ``x_end = Phi x_0 + Gamma b`` with
``[[Phi, Gamma]] = expm([[A, I], [0, 0]] dt)``. Derivatives are exact: with
respect to the start state (``Phi``), to inputs entering only ``b`` (``Gamma
db``), to inputs or parameters changing ``A`` (the Frechet derivative of the
augmented exponential, :func:`expm_frechet_batch`), and the parameter
sensitivities of a whole simulation (forward recursion), for calibration.

The description (nodes, boundaries, conductances, gains, outputs, parameters and
their expressions) is parsed and checked by :mod:`mshoot_core.models.network_spec`.

Monotonicity (:attr:`Model.monotone_inputs`) is derived from the structure: with
positive capacities and node-node conductances of nonnegative constant value,
``A`` is Metzler for every input, so ``Phi = expm(A dt) >= 0`` and
``Gamma >= 0``; an input that enters only gains, alone (``times: [c]``) and
with a nonnegative value, then raises every end temperature. Such controls are
the model's monotone inputs.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd
import scipy.linalg

from mshoot_core.models.base import IntervalBatch, IntervalJacobians, Model
from mshoot_core.models.network_spec import (card_network, CARDS_DIR, Expression,
                                             NetworkError, NetworkSpec, Parameter,
                                             parse_network, Term)

__all__ = ['card_network', 'CARDS_DIR', 'expm2', 'expm_frechet_batch', 'NetworkError',
           'NetworkModel', 'NetworkSpec', 'Parameter', 'parameters_class', 'parse_network']


def parameters_class(spec: NetworkSpec, name: str, doc: str, module: str,
                     bases: tuple[type, ...] = ()) -> type:
    """
    Return a frozen dataclass of the network's parameters, defaults the spec's values.

    Built once per preset from its card (e.g. ``R1C1Parameters``): the card is the one
    place the values live. Each field may hold an array (one value per zone, for
    applications computing with them); a model takes scalars.
    """
    def check(self: Any) -> None:
        values = dataclasses.asdict(self)
        for key, value in values.items():
            if not np.all(np.isfinite(np.asarray(value, dtype=float))):
                raise ValueError(f'{name} parameter {key} must be finite, got {value!r}')
        if all(np.ndim(v) == 0 for v in values.values()):
            NetworkModel(spec, values={k: float(v) for k, v in values.items()})

    fields = [(p.name, Any, dataclasses.field(default=p.value))
              for p in spec.parameters.values()]
    cls = dataclasses.make_dataclass(name, fields, bases=bases, frozen=True,
                                     namespace={'__post_init__': check, '__doc__': doc})
    cls.__module__ = module
    return cls


# -- matrix exponentials ----------------------------------------------------------------------
def expm2(a: np.ndarray) -> np.ndarray:
    """
    Return ``expm(a)`` of a batch of 2x2 matrices with real eigenvalues, in closed form.

    ``expm(a) = exp(l2) I + D (a - l2 I)`` with the eigenvalues ``l1 >= l2``
    and ``D = (exp(l1) - exp(l2)) / (l1 - l2)`` (``exp(l1)`` when equal),
    computed without cancellation. The A of an RC network is similar to a
    symmetric matrix: its eigenvalues are real. Equal to
    :func:`scipy.linalg.expm` to round-off, without its per-matrix cost.

    Parameters
    ----------
    a : ndarray, shape (B, 2, 2)
        The matrices [-] (``A dt``).

    Returns
    -------
    ndarray, shape (B, 2, 2)

    """
    half = 0.5 * (a[:, 0, 0] - a[:, 1, 1])
    cross = a[:, 0, 1] * a[:, 1, 0]
    q = np.sqrt(np.maximum(half ** 2 + cross, 0.0))
    mean = 0.5 * (a[:, 0, 0] + a[:, 1, 1])
    low = mean - q  # l2
    gap = 2.0 * q  # l1 - l2 >= 0
    small = gap < 1e-8
    safe = np.where(small, 1.0, gap)
    divided = np.exp(mean + q) * np.where(small, 1.0 - gap / 2.0, -np.expm1(-safe) / safe)
    # a - l2 I: the diagonal q + half and q - half, each without cancellation
    plus = np.where(half >= 0, q + half, cross / np.where(q - half > 0, q - half, 1.0))
    minus = np.where(half <= 0, q - half, cross / np.where(q + half > 0, q + half, 1.0))
    out = np.empty_like(a, dtype=float)
    e_low = np.exp(low)
    out[:, 0, 0] = e_low + divided * plus
    out[:, 1, 1] = e_low + divided * minus
    out[:, 0, 1] = divided * a[:, 0, 1]
    out[:, 1, 0] = divided * a[:, 1, 0]
    return out


def expm_frechet_batch(m: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``expm(m)`` and its Frechet derivatives along ``e`` for a batch of matrices.

    Through the eigendecomposition ``m = V diag(l) V^-1`` (the augmented
    matrix of an RC network is diagonalisable: real distinct eigenvalues of a
    matrix similar to a symmetric one, and 0):
    ``L(m, e) = V ((V^-1 e V) * D) V^-1`` with the divided differences
    ``D_ij = (exp(l_i) - exp(l_j)) / (l_i - l_j)`` (``exp(l_i)`` when equal).
    Equal to :func:`scipy.linalg.expm_frechet` (to about 1e-12 relative here)
    at a fraction of its cost in a batch.

    Parameters
    ----------
    m : ndarray, shape (R, n, n)
        The matrices (diagonalisable).
    e : ndarray, shape (R, P, n, n)
        P directions per matrix.

    Returns
    -------
    expm : ndarray, shape (R, n, n)
    frechet : ndarray, shape (R, P, n, n)

    """
    lam, v = np.linalg.eig(m)
    v_inv = np.linalg.inv(v)
    li, lj = lam[:, :, None], lam[:, None, :]
    top = np.where(li.real >= lj.real, li, lj)  # exp(top) * expm1(d) / d with d <= 0
    d = np.where(li.real >= lj.real, lj - li, li - lj)
    small = np.abs(d) < 1e-8
    safe = np.where(small, 1.0, d)
    divided = np.exp(top) * np.where(small, 1.0 + d / 2.0, np.expm1(safe) / safe)
    expm = np.einsum('rij,rj,rjk->rik', v, np.exp(lam), v_inv)
    inner = np.einsum('rij,rpjk,rkl->rpil', v_inv, e, v) * divided[:, None]
    frechet = np.einsum('rij,rpjk,rkl->rpil', v, inner, v_inv)
    return expm.real, frechet.real


# -- products of inputs -----------------------------------------------------------------------
def _finite_at(expr: Expression, env: Mapping[str, Any]) -> bool:
    try:
        return bool(np.all(np.isfinite(expr.value(env))))
    except ArithmeticError:
        return False


class _Products:
    """The input products of a list of terms, evaluated for a batch of inputs at once."""

    def __init__(self, times: Sequence[tuple[int, ...]]) -> None:
        self.count = len(times)
        self.single = np.array([k for k, t in enumerate(times) if len(t) == 1], dtype=int)
        self.single_col = np.array([t[0] for t in times if len(t) == 1], dtype=int)
        self.multi = [(k, list(t)) for k, t in enumerate(times) if len(t) > 1]
        self.times = [tuple(t) for t in times]

    def of(self, u: np.ndarray) -> np.ndarray:
        """Return the products, shape (B, terms)."""
        if self.single.size == self.count:  # every term one input: a gather
            return u[:, self.single_col]
        out = np.ones((u.shape[0], self.count))
        if self.single.size:
            out[:, self.single] = u[:, self.single_col]
        for k, cols in self.multi:
            out[:, k] = np.prod(u[:, cols], axis=1)
        return out

    def derivative(self, u: np.ndarray, col: int) -> np.ndarray:
        """Return d products / d u[:, col], shape (B, terms)."""
        out = np.zeros((u.shape[0], self.count))
        for k, t in enumerate(self.times):
            for position, c in enumerate(t):
                if c == col:
                    rest = [x for i, x in enumerate(t) if i != position]
                    out[:, k] += np.prod(u[:, rest], axis=1) if rest else 1.0
        return out

    def involves(self, col: int) -> bool:
        return any(col in t for t in self.times)


class _Incidence:
    """
    Sums of K terms into ``size`` bins per row: ``values (B, K) -> (B, size)``.

    A dense matrix product for small networks; for large ones a sum of a few gathers where
    every bin receives few terms (independent zones: three or so each), else a sparse
    product. The gathers add each bin's terms in the sparse product's order (by term, from
    zero), so both give the same values.
    """

    #: Most terms into one bin summed by gathers (one gather per term of the fullest bin).
    GATHERS = 8

    def __init__(self, index: tuple[Sequence[int], Sequence[int]], weights: Sequence[float],
                 terms: int, size: int) -> None:
        rows, cols = (np.asarray(i, dtype=int) for i in index)
        values = np.asarray(weights, dtype=float)
        self.size = size
        self.empty = terms == 0
        self.gathers: list[tuple[np.ndarray, np.ndarray]] = []
        if terms * size <= 4096:
            self.matrix = np.zeros((terms, size))
            np.add.at(self.matrix, (rows, cols), values)
            return
        import scipy.sparse  # (only where a network is large)
        self.matrix = scipy.sparse.csr_matrix((values, (rows, cols)), shape=(terms, size))
        by_bin = self.matrix.tocsc()  # duplicates summed, each bin's terms in term order
        by_bin.sort_indices()
        counts = np.diff(by_bin.indptr)
        if self.empty or counts.max() > self.GATHERS:
            return
        for k in range(counts.max()):  # the k-th term of every bin, weight 0 where none
            has = counts > k
            term = np.zeros(size, dtype=int)
            weight = np.zeros(size)
            term[has] = by_bin.indices[by_bin.indptr[:-1][has] + k]
            weight[has] = by_bin.data[by_bin.indptr[:-1][has] + k]
            self.gathers.append((term, weight))

    def __call__(self, values: np.ndarray) -> np.ndarray:
        if self.empty:
            return np.zeros((values.shape[0], self.size))
        if self.gathers:
            term, weight = self.gathers[0]
            out = values[:, term] * weight
            for term, weight in self.gathers[1:]:
                out += values[:, term] * weight
            return out
        return np.asarray(values @ self.matrix)


def _scatter_vector(index: Sequence[int], values: Sequence[float], size: int) -> np.ndarray:
    out = np.zeros(size)
    np.add.at(out, np.asarray(index, dtype=int), np.asarray(values, dtype=float))
    return out


# -- the model --------------------------------------------------------------------------------
class NetworkModel(Model):
    """
    A linear thermal network with its exact per-interval solution (see the module).

    Inputs as the spec's ``inputs`` (their order); states the nodes [K]; outputs as the
    spec's ``outputs``.

    Parameters
    ----------
    spec : NetworkSpec or mapping
        The network (a mapping is parsed with :func:`parse_network`).
    values : mapping, optional
        Parameter values over the spec's (name -> value).
    control_names : sequence of str, optional
        The inputs a controller sets (default: none declared, the convention of
        :func:`~mshoot_core.models.registry.control_interface` applies).
    comfort_states : sequence of str, optional
        The zone temperatures the comfort band bounds (default: none declared).
    measured_states : sequence of str, optional
        The nodes a sensor measures (default: those the spec marks measured).

    Raises
    ------
    NetworkError
        For an invalid spec.
    ValueError
        For an unknown parameter, a capacity that is not positive, a conductance or a
        gain that is not finite, or unknown control, comfort or measured names.

    """

    def __init__(self, spec: NetworkSpec | Mapping, values: Mapping[str, float] | None = None,
                 control_names: Sequence[str] | None = None,
                 comfort_states: Sequence[str] | None = None,
                 measured_states: Sequence[str] | None = None) -> None:
        if not isinstance(spec, NetworkSpec):
            spec = parse_network(spec)
        if values:
            spec = spec.with_values(values)
        self.spec = spec
        self.input_names = tuple(spec.inputs)
        self.state_names = tuple(spec.nodes)
        self.output_names = tuple(spec.outputs)
        for label, names, pool in (('control_names', control_names, self.input_names),
                                   ('comfort_states', comfort_states, self.state_names),
                                   ('measured_states', measured_states, self.state_names)):
            if names is not None and (not set(names) <= set(pool)
                                      or len(set(names)) != len(tuple(names))):
                raise ValueError(f'{label} must be distinct names of {list(pool)}, got '
                                 f'{list(names)}')
        if control_names is not None:
            self.control_names = tuple(control_names)
        if comfort_states is not None:
            self.comfort_states = tuple(comfort_states)
        self.measured_states = (tuple(measured_states) if measured_states is not None else
                                tuple(n for n, (_, m) in spec.nodes.items() if m))
        if not self.measured_states:
            raise ValueError('a network needs at least one measured state')
        self._setup()

    # -- constants of the parameters ---------------------------------------------------------
    @property
    def parameters(self) -> dict[str, float]:
        """Return the parameter values (name -> value)."""
        return {name: p.value for name, p in self.spec.parameters.items()}

    def _constants(self, exprs: Sequence[Expression], names: Sequence[str]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Return values (K,) and d value / d parameter (K, P) of parameter expressions."""
        env = self._penv
        try:
            values = np.array([float(e.value(env)) for e in exprs], dtype=float)
            derivs = np.zeros((len(exprs), len(names)))
            for k, e in enumerate(exprs):
                for j, name in enumerate(names):
                    if name in e.names:
                        derivs[k, j] = float(e.derivative(env, name))
        except ArithmeticError as exc:  # 1 / R with R = 0, an overflow
            bad = [e.text for e in exprs if not _finite_at(e, env)]
            raise ValueError(f'network expressions {bad} are not finite at the parameters '
                             f'{env} ({exc})') from None
        return values, derivs

    def _tables(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """
        Return the constants of the network and their derivatives by the parameters ``names``.

        Capacities ``cap`` (n,), conductance values ``g`` (K,), gain values ``h`` (L,) and
        the outputs' ``cy`` (ny, n), ``offset`` (ny,) and ``w`` (ny, terms); ``d<name>``
        the derivatives, one more axis of len(names).
        """
        spec = self.spec
        out: dict[str, np.ndarray] = {}
        out['cap'], out['dcap'] = self._constants([c for c, _ in spec.nodes.values()], names)
        out['g'], out['dg'] = self._constants([t.value for t in spec.conductances], names)
        out['h'], out['dh'] = self._constants([t.value for t in spec.gains], names)
        outputs = list(spec.outputs.values())
        ny, n, count = len(outputs), len(spec.nodes), len(names)
        cy, dcy = np.zeros((ny, n)), np.zeros((ny, n, count))
        offset, doffset = np.zeros(ny), np.zeros((ny, count))
        rows = []
        for i, o in enumerate(outputs):
            state_terms = [t for t in o.terms if t.state >= 0]
            value, deriv = self._constants([t.value for t in state_terms], names)
            for t, v, d in zip(state_terms, value, deriv):
                cy[i, t.state] += v
                dcy[i, t.state] += d
            rows += [(i, t.value) for t in o.terms if t.state < 0]
            if not o.integral:
                value, deriv = self._constants([o.offset], names)
                offset[i], doffset[i] = value[0], deriv[0]
        value, deriv = self._constants([expr for _, expr in rows], names)
        w, dw = np.zeros((ny, len(rows))), np.zeros((ny, len(rows), count))
        for k, (i, _) in enumerate(rows):
            w[i, k], dw[i, k] = value[k], deriv[k]
        out.update(cy=cy, dcy=dcy, offset=offset, doffset=doffset, w=w, dw=dw)
        return out

    def _setup(self) -> None:
        spec = self.spec
        self._pnames = list(spec.parameters)
        self._penv = self.parameters
        n = len(spec.nodes)
        tables = self._tables([])
        self.capacity = tables['cap']
        if not np.all(self.capacity > 0):
            raise ValueError(f'network capacities must be > 0 [J/K], got '
                             f'{dict(zip(spec.nodes, self.capacity))}')
        cond, gains = spec.conductances, spec.gains
        self._g, self._h = tables['g'], tables['h']
        for label, values in (('conductance', self._g), ('gain', self._h)):
            if not np.all(np.isfinite(values)):
                raise ValueError(f'network {label} values must be finite, got {values}')
        if np.any(self._g < 0):
            raise ValueError(f'network conductance values must be >= 0 [W/K], got '
                             f'{dict(zip((t.value.text for t in cond), self._g))}')
        self._g_prod = _Products([t.times for t in cond])
        self._h_prod = _Products([t.times for t in gains])
        self._g_node = np.array([t.node for t in cond], dtype=int)
        self._g_other = np.array([t.other for t in cond], dtype=int)
        self._g_bnd = np.array([t.boundary for t in cond], dtype=int)
        self._to_node = self._g_other >= 0
        self._h_node = np.array([t.node for t in gains], dtype=int)
        self._boundaries = list(spec.boundaries.values())
        self._input_cols = {name: i for i, name in enumerate(self.input_names)}
        self._varying_boundaries = [k for k, e in enumerate(self._boundaries)
                                    if e.names & set(self.input_names)]
        self._fixed_boundaries = np.array([
            np.nan if k in self._varying_boundaries else float(e.value(self._penv))
            for k, e in enumerate(self._boundaries)])
        self._bnd_cols = {name: i for i, name in enumerate(self.input_names)
                          if any(name in e.names for e in self._boundaries)}
        # sums of terms into nodes: loss (diagonal or full), boundary forcing, gains
        count, to_b = len(cond), np.flatnonzero(self._g_other < 0)
        a_i = self._g_node
        b_i = np.where(self._g_other >= 0, self._g_other, self._g_node)
        coupled = self._g_other >= 0
        self._loss_diag = _Incidence((np.arange(count), a_i), np.ones(count), count, n)
        terms = np.arange(count)
        self._loss_full = _Incidence(
            (np.concatenate([terms, terms[coupled], terms[coupled], terms[coupled]]),
             np.concatenate([a_i * n + a_i, b_i[coupled] * n + b_i[coupled],
                             a_i[coupled] * n + b_i[coupled], b_i[coupled] * n + a_i[coupled]])),
            np.concatenate([np.ones(count), np.ones(3 * int(coupled.sum()))
                            * np.repeat([1.0, -1.0, -1.0], int(coupled.sum()))]), count, n * n)
        self._to_b = to_b
        self._to_b_bnd = self._g_bnd[to_b]
        self._forcing_b = _Incidence((np.arange(to_b.size), a_i[to_b]), np.ones(to_b.size),
                                     to_b.size, n)
        self._forcing_h = _Incidence((np.arange(len(gains)), self._h_node),
                                     np.ones(len(gains)), len(gains), n)
        # the structure: which nodes are coupled, which inputs change A
        self.coupled = bool(np.any(self._to_node))
        self._modulated = any(t.times for t in cond)
        self._a_inputs = {c for t in cond for c in t.times}
        self._b_inputs = ({c for t in gains for c in t.times} | self._a_inputs
                          | {self._input_cols[name] for e in self._boundaries
                             for name in e.names if name in self._input_cols})
        # inputs entering only gains, alone (a heat rate): dF/du is a constant [W per unit]
        self._gain_only: dict[int, np.ndarray] = {}
        self._gains_of: dict[int, list[tuple[Term, float]]] = {}
        for t, h in zip(gains, self._h):
            for col in set(t.times):
                self._gains_of.setdefault(col, []).append((t, h))
        for col in self._b_inputs:
            uses = self._gains_of.get(col, [])
            if (col in self._a_inputs or self.input_names[col] in self._bnd_cols
                    or not all(t.times == (col,) for t, _ in uses)):
                continue
            self._gain_only[col] = _scatter_vector([t.node for t, _ in uses],
                                                   [h for _, h in uses], n)
        # every node reaches a boundary through a constant positive conductance: A is Hurwitz
        reach = set()
        for t, g in zip(cond, self._g):
            if t.other < 0 and not t.times and g > 0:
                reach.add(t.node)
        links = [(t.node, t.other) for t, g in zip(cond, self._g)
                 if t.other >= 0 and not t.times and g > 0]
        grown = True
        while grown:  # (through the constant links between nodes)
            grown = False
            for a, b in links:
                if (a in reach) != (b in reach):
                    reach |= {a, b}
                    grown = True
        self._hurwitz = len(reach) == n
        self._components = self._find_components()
        self._cy, self._y_offset, self._y_w = tables['cy'], tables['offset'], tables['w']
        # outputs of at most one state each (a zone temperature): a gather, not a product
        # with a mostly zero matrix (the same values: one term of weight w, the rest 0)
        self._cy_pick = None
        if np.all(np.count_nonzero(self._cy, axis=1) <= 1):
            picked = np.argmax(self._cy != 0, axis=1)
            self._cy_pick = (picked, self._cy[np.arange(self._cy.shape[0]), picked])
        outputs = list(spec.outputs.values())
        self._y_integral = np.array([o.integral for o in outputs], dtype=bool)
        self._y_prod = _Products([t.times for o in outputs for t in o.terms if t.state < 0])
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self.monotone_inputs = self._monotone_inputs()

    def _find_components(self) -> np.ndarray:
        label = np.arange(len(self.spec.nodes))
        changed = True
        while changed:
            changed = False
            for a, b in zip(self._g_node[self._to_node], self._g_other[self._to_node]):
                low = min(label[a], label[b])
                if label[a] != low or label[b] != low:
                    label[label == label[a]] = low
                    label[label == label[b]] = low
                    changed = True
        return label

    def _output_scale(self, dt: Any) -> Any:
        """Return the factor of the input terms: dt for integrals, 1 otherwise (B or 1, ny)."""
        if not self._y_integral.any():
            return 1.0
        return np.where(self._y_integral, np.reshape(dt, (-1, 1)), 1.0)

    def _monotone_inputs(self) -> tuple[str, ...]:
        """Return the controls the structure makes the model monotone in (module docstring)."""
        to_node = [(t, g) for t, g in zip(self.spec.conductances, self._g) if t.other >= 0]
        if any(t.times or g < 0 for t, g in to_node):
            return ()
        controls = getattr(self, 'control_names', None)
        if controls is None:
            controls = ('q',) if 'q' in self.input_names else ()
        out = []
        for name in controls:
            col = self._input_cols[name]
            uses = self._gains_of.get(col, [])
            if (uses and col not in self._a_inputs
                    and not any(name in e.names for e in self._boundaries)
                    and all(t.times == (col,) and h >= 0 for t, h in uses)):
                out.append(name)
        return tuple(out)

    # -- the linear system of a batch of intervals ------------------------------------------
    def _environment(self, u: np.ndarray) -> dict[str, Any]:
        """Return the names of the boundary expressions: parameters and input columns."""
        return {**self._penv, **{name: u[:, i] for name, i in self._bnd_cols.items()}}

    def _boundary_temperatures(self, u: np.ndarray) -> np.ndarray:
        out = np.empty((u.shape[0], len(self._boundaries)))
        out[:] = self._fixed_boundaries
        if self._varying_boundaries:
            env = self._environment(u)
            for k in self._varying_boundaries:
                out[:, k] = self._boundaries[k].value(env)
        return out

    def _boundary_derivatives(self, u: np.ndarray, wrt: str) -> np.ndarray | None:
        """Return d boundary temperatures / d ``wrt`` (B, NB), or None where none depends."""
        if not any(wrt in e.names for e in self._boundaries):
            return None
        env = self._environment(u)
        out = np.zeros((u.shape[0], len(self._boundaries)))
        for k, expr in enumerate(self._boundaries):
            out[:, k] = expr.derivative(env, wrt)
        return out

    def _coefficients(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return conductances g (B, K) [W/K], boundary temperatures (B, NB) [K], gains (B, L)."""
        return (self._g * self._g_prod.of(u), self._boundary_temperatures(u),
                self._h * self._h_prod.of(u))

    def _assemble(self, g: np.ndarray, tb: np.ndarray, h: np.ndarray, full: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the loss L and the forcing F of ``C dx/dt = -L x + F``.

        L is (B, n) (its diagonal) unless ``full``, then (B, n, n); F is (B, n) [W].
        """
        n = len(self.state_names)
        forcing = self._forcing_h(h) + self._forcing_b(g[:, self._to_b] * tb[:, self._to_b_bnd])
        if not full:
            return self._loss_diag(g), forcing
        return self._loss_full(g).reshape(g.shape[0], n, n), forcing

    def system(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return ``A`` (B, n, n) [1/s] and ``b`` (B, n) [K/s] with dx/dt = A x + b for inputs u.

        ``u`` has shape (B, nu), columns in :attr:`input_names` order.
        """
        loss, forcing = self._assemble(*self._coefficients(u), full=True)
        return -loss / self.capacity[None, :, None], forcing / self.capacity

    def _direction(self, u: np.ndarray, dg: np.ndarray, dh: np.ndarray,
                   dtb: np.ndarray | None, full: bool) -> tuple[np.ndarray, np.ndarray]:
        """Return dL and dF along changes dg, dh, dtb of conductances, gains and boundaries."""
        tb = self._boundary_temperatures(u)
        dloss, dforcing = self._assemble(dg, tb, dh, full)
        if dtb is not None:
            g = self._g * self._g_prod.of(u)
            dforcing = dforcing + self._forcing_b(g[:, self._to_b] * dtb[:, self._to_b_bnd])
        return dloss, dforcing

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """
        Return dx/dt [K/s] at states ``x`` (B, nx) and inputs ``u`` (B, nu): ``A(u) x + b(u)``.

        For references outside the exact solution (an ODE integrator in a test).
        """
        u = np.atleast_2d(np.asarray(u, dtype=float))
        x = np.asarray(x, dtype=float).reshape(u.shape[0], len(self.state_names))
        a, b = self.system(u)
        return np.einsum('bij,bj->bi', a, x) + b

    def _input_derivative(self, u: np.ndarray, col: int, full: bool
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Return dL/du_col and dF/du_col (shapes of :meth:`_assemble`)."""
        return self._direction(u, self._g * self._g_prod.derivative(u, col),
                               self._h * self._h_prod.derivative(u, col),
                               self._boundary_derivatives(u, self.input_names[col]), full)

    def _parameter_derivative(self, u: np.ndarray, name: str, dg: np.ndarray, dh: np.ndarray,
                              full: bool) -> tuple[np.ndarray, np.ndarray]:
        """Return dL/dp and dF/dp at inputs ``u`` (capacities aside) from dg, dh of ``name``."""
        return self._direction(u, dg * self._g_prod.of(u), dh * self._h_prod.of(u),
                               self._boundary_derivatives(u, name), full)

    # -- the exact solution of an interval --------------------------------------------------
    def _decoupled(self, x0: np.ndarray, loss: np.ndarray, forcing: np.ndarray,
                   dt: Any) -> tuple[np.ndarray, np.ndarray]:
        """End states and the decay of nodes without neighbours (all arrays (B, n))."""
        positive = loss > 0
        g = np.where(positive, loss, 1.0)
        decay = np.exp(-g * dt / self.capacity)
        t_inf = forcing / g
        x_end = np.where(positive, t_inf + (x0 - t_inf) * decay,
                         x0 + forcing * dt / self.capacity)
        return x_end, np.where(positive, decay, 1.0)

    def _transition(self, a: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Return ``Phi`` and ``Gamma`` (B, n, n) of ``A`` (B, n, n) over ``dt``."""
        n = a.shape[1]
        if not self._modulated:
            hit = self._cache.get(dt)
            if hit is None:
                m = np.zeros((2 * n, 2 * n))
                m[:n, :n], m[:n, n:] = a[0] * dt, np.eye(n) * dt
                e = scipy.linalg.expm(m)
                hit = (e[:n, :n].copy(), e[:n, n:].copy())
                if len(self._cache) < 64:
                    self._cache[dt] = hit
            return (np.broadcast_to(hit[0], a.shape), np.broadcast_to(hit[1], a.shape))
        if n == 2 and self._hurwitz:
            phi = expm2(a * dt)
            return phi, np.linalg.solve(a, phi - np.eye(2))
        m = np.zeros((a.shape[0], 2 * n, 2 * n))
        m[:, :n, :n], m[:, :n, n:] = a * dt, np.eye(n) * dt
        e = scipy.linalg.expm(m)
        return e[:, :n, :n], e[:, :n, n:]

    def _outputs(self, x: np.ndarray, u: np.ndarray, dt: Any) -> np.ndarray:
        """Return the outputs (B, ny) at ``x`` after inputs ``u`` held over ``dt``."""
        y = self._through_outputs(x) + self._y_offset
        if self._y_w.size:
            y = y + (self._y_prod.of(u) @ self._y_w.T) * self._output_scale(dt)
        return y

    def _through_outputs(self, states: np.ndarray) -> np.ndarray:
        """Return ``Cy`` times the states' axis 1 of (B, n) or (B, n, m): (B, ny[, m])."""
        if self._cy_pick is None:
            return states @ self._cy.T if states.ndim == 2 else self._cy @ states
        picked, weights = self._cy_pick
        return states[:, picked] * weights.reshape((-1,) + (1,) * (states.ndim - 2))

    def _end_states(self, x0: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        if not self.coupled:
            loss, forcing = self._assemble(*self._coefficients(u), full=False)
            return self._decoupled(x0, loss, forcing, dt)[0]
        a, b = self.system(u)
        phi, gamma = self._transition(a, dt)
        return np.einsum('bij,bj->bi', phi, x0) + np.einsum('bij,bj->bi', gamma, b)

    # -- the Model interface ----------------------------------------------------------------
    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        t, u, x0_arr = self.check_inputs(udf, x0)
        states = self._trajectory(t, u, x0_arr)
        xdf = pd.DataFrame(states, index=udf.index, columns=list(self.state_names))
        ydf = pd.DataFrame(self._output_rows(t, u, states), index=udf.index,
                           columns=list(self.output_names))
        return ydf, xdf

    def _trajectory(self, t: np.ndarray, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
        dt = np.diff(t)
        n = len(self.state_names)
        states = np.empty((t.size, n))
        states[0] = x0
        if not self.coupled:
            loss, forcing = self._assemble(*self._coefficients(u[:-1]), full=False)
            positive = loss > 0
            g = np.where(positive, loss, 1.0)
            decay = np.exp(-g * dt[:, None] / self.capacity)
            t_inf = forcing / g
            rise = forcing * dt[:, None] / self.capacity
            for k in range(dt.size):
                states[k + 1] = np.where(positive[k], t_inf[k] + (states[k] - t_inf[k])
                                         * decay[k], states[k] + rise[k])
            return states
        a, b = self.system(u[:-1])
        if np.allclose(dt, dt[0], rtol=1e-12, atol=0.0):
            phi, gamma = self._transition(a, float(dt[0]))
        else:
            pairs = [self._transition(a[k:k + 1], float(dt[k])) for k in range(dt.size)]
            phi = np.concatenate([p[0] for p in pairs])
            gamma = np.concatenate([p[1] for p in pairs])
        forced = np.einsum('bij,bj->bi', gamma, b)
        for k in range(dt.size):
            states[k + 1] = phi[k] @ states[k] + forced[k]
        return states

    def _output_rows(self, t: np.ndarray, u: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Return the outputs at every row: after the interval ending there (row 0: no inputs)."""
        dt = np.diff(t)
        y = np.empty((t.size, len(self.output_names)))
        y[1:] = self._outputs(states[1:], u[:-1], dt)
        y[:1] = self._outputs(states[:1], np.zeros((1, u.shape[1])), 0.0)
        y[1:, self._y_integral] = np.cumsum(y[1:, self._y_integral], axis=0)
        return y

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Exact end values of B intervals (``t_start_s`` ignored: time-invariant)."""
        x_start, u = self._check_batch(x_start, u)
        x_end = self._end_states(x_start, u, float(dt_s))
        return x_end, self._outputs(x_end, u, float(dt_s))

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians:
        """Exact end values and derivatives (``t_start_s`` ignored: time-invariant)."""
        x_start, u = self._check_batch(x_start, u)
        dt = float(dt_s)
        wrt = self._input_columns(wrt_inputs)
        if not self.coupled:  # the closed form: a fresh batch, evaluated once
            batch = _ClosedFormBatch(self, x_start.shape[0], dt, wrt)
            batch.x_start[:], batch.u[:] = x_start, u
            return batch.jacobians()
        batch, n = x_start.shape
        dx_du = np.zeros((batch, n, len(wrt)))
        a, b = self.system(u)
        phi, gamma = self._transition(a, dt)
        x_end = np.einsum('bij,bj->bi', phi, x_start) + np.einsum('bij,bj->bi', gamma, b)
        dx_dx0 = np.array(phi)
        for j, col in enumerate(wrt):
            if col not in self._b_inputs:
                continue
            vector = self._gain_only.get(col)
            if vector is not None:  # a heat rate: Gamma db
                dx_du[:, :, j] = np.einsum('bij,j->bi', gamma, vector / self.capacity)
                continue
            dloss, dforcing = self._input_derivative(u, col, full=True)
            db = dforcing / self.capacity
            if col not in self._a_inputs:
                dx_du[:, :, j] = np.einsum('bij,bj->bi', gamma, db)
            else:
                da = -dloss / self.capacity[None, :, None]
                dx_du[:, :, j] = self._frechet_step(a, b, da, db, x_start, dt)
        return IntervalJacobians(x_end, self._outputs(x_end, u, dt), dx_dx0, dx_du,
                                 *self._output_jacobians(u, dt, wrt, dx_dx0, dx_du))

    def interval_batch(self, batch: int, dt_s: float, wrt_inputs: Sequence[int],
                       t_start_s: np.ndarray | None = None) -> IntervalBatch:
        """
        Return a batch of ``batch`` intervals (``t_start_s`` ignored: time-invariant).

        Where no conductance joins two nodes, a :class:`_ClosedFormBatch`: its derivative
        arrays allocated once, only their nonzero entries rewritten at each evaluation. A
        subclass with its own :meth:`interval_jacobians` gets the batch that calls it.
        """
        if self.coupled or type(self).interval_jacobians is not NetworkModel.interval_jacobians:
            return IntervalBatch(self, batch, dt_s, wrt_inputs)
        return _ClosedFormBatch(self, batch, dt_s, self._input_columns(wrt_inputs))

    def _input_columns(self, wrt_inputs: Sequence[int]) -> list[int]:
        """Return the columns ``wrt_inputs`` as ints, checked against the inputs."""
        wrt = [int(c) for c in wrt_inputs]
        for col in wrt:
            if not 0 <= col < len(self.input_names):
                raise ValueError(f'input column {col} out of range [0, {len(self.input_names)})')
        return wrt

    def _output_jacobians(self, u: np.ndarray, dt: float, wrt: Sequence[int],
                          dx_dx0: np.ndarray, dx_du: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Return d y_end / d x_start (B, ny, nx) and d y_end / d u (B, ny, len(wrt))."""
        dy_dx0 = self._through_outputs(dx_dx0)
        dy_du = self._through_outputs(dx_du)
        if self._y_w.size:
            scale = self._output_scale(dt)
            for j, col in enumerate(wrt):
                if self._y_prod.involves(col):
                    dy_du[:, :, j] += (self._y_prod.derivative(u, col) @ self._y_w.T) * scale
        return dy_dx0, dy_du

    def _decoupled_derivative(self, x0: np.ndarray, forcing: np.ndarray, g: np.ndarray,
                              decay: np.ndarray, positive: np.ndarray, dloss: np.ndarray,
                              dforcing: np.ndarray, dcap: Any, dt: Any) -> np.ndarray:
        """Return the closed-form end state's derivative along (dL, dF, dC) (arrays (B, n))."""
        cap = self.capacity
        t_inf = forcing / g
        dt_inf = (dforcing * g - forcing * dloss) / g ** 2
        ddecay = -(decay * dt) * (dloss * cap - g * dcap) / cap ** 2
        moving = dt_inf * (1.0 - decay) + (x0 - t_inf) * ddecay
        # a node without any conductance integrates: x0 + F dt / C
        still = dforcing * dt / cap - forcing * dt * dcap / cap ** 2
        return np.where(positive, moving, still)

    @staticmethod
    def _frechet_step(a: np.ndarray, b: np.ndarray, da: np.ndarray, db: np.ndarray,
                      x0: np.ndarray, dt: float) -> np.ndarray:
        """Return d x_end along (dA, db): the Frechet derivative of the augmented exponential."""
        batch, n = b.shape
        m = np.zeros((batch, n + 1, n + 1))
        m[:, :n, :n], m[:, :n, n] = a, b
        dm = np.zeros((batch, 1, n + 1, n + 1))
        dm[:, 0, :n, :n], dm[:, 0, :n, n] = da, db
        _, de = expm_frechet_batch(m * dt, dm * dt)
        return np.einsum('bij,bj->bi', de[:, 0, :n, :n], x0) + de[:, 0, :n, n]

    def jacobian_sparsity(self, wrt_inputs: Sequence[int]) -> np.ndarray | None:
        """Return the block structure of independent parts (None for one coupled part)."""
        labels = self._components
        if np.unique(labels).size == 1:
            return None
        n = len(self.state_names)
        same = labels[:, None] == labels[None, :]
        touches = np.zeros((n, len(wrt_inputs)), bool)
        for j, col in enumerate(wrt_inputs):
            col = int(col)
            name = self.input_names[col]
            hit = np.zeros(n, bool)
            for t in self.spec.conductances:
                if col in t.times or (t.boundary >= 0
                                      and name in self._boundaries[t.boundary].names):
                    hit[labels == labels[t.node]] = True
            for t in self.spec.gains:
                if col in t.times:
                    hit[labels == labels[t.node]] = True
            touches[:, j] = hit
        uses = self._cy != 0
        state_part = (uses.astype(int) @ same.astype(int)) > 0
        input_part = (uses.astype(int) @ touches.astype(int)) > 0
        for j, col in enumerate(wrt_inputs):
            for k, t in enumerate(self._y_prod.times):
                if int(col) in t:
                    input_part[:, j] |= self._y_w[:, k] != 0
        top = np.hstack([same, touches])
        return np.vstack([top, np.hstack([state_part, input_part])])

    # -- calibration ------------------------------------------------------------------------
    def parameter_sensitivities(self, udf: pd.DataFrame, x0: Sequence[float],
                                names: Sequence[str]) -> tuple[pd.DataFrame, np.ndarray]:
        """
        Simulate as :meth:`simulate` and return the exact output derivatives w.r.t. parameters.

        Forward sensitivities of the exact per-interval solution, ``dx_0/dp = 0`` (the
        start state is given): for nodes without neighbours, with ``a = exp(-g dt / C)``
        and ``T_inf = f / g``,
        ``dT_{k+1}/dp = dT_inf/dp (1 - a) + (T_k - T_inf) da/dp + a dT_k/dp``; for
        coupled nodes ``dx_{k+1}/dp = dE_k [x_k; 1] + Phi_k dx_k/dp`` with ``dE_k`` the
        Frechet derivative of ``expm([[A, b], [0, 0]] dt)`` along ``dp``.

        Parameters
        ----------
        udf : DataFrame
            Inputs as for :meth:`simulate`.
        x0 : sequence of float, length nx
            Start state [K].
        names : sequence of str
            Parameter names.

        Returns
        -------
        ydf : DataFrame
            The outputs of :meth:`simulate`.
        dy_dp : ndarray, shape (T, ny, len(names))
            d output / d parameter at every row [output unit per parameter unit].

        Raises
        ------
        ValueError
            For an unknown name.

        """
        names = list(names)
        unknown = [name for name in names if name not in self._pnames]
        if unknown:
            raise ValueError(f'unknown network parameters {unknown}; expected names from '
                             f'{self._pnames}')
        t, u, x0_arr = self.check_inputs(udf, x0)
        states = self._trajectory(t, u, x0_arr)
        ydf = pd.DataFrame(self._output_rows(t, u, states), index=udf.index,
                           columns=list(self.output_names))
        d = self._tables(names)
        dt = np.diff(t)
        ui = u[:-1]
        rows, n, count = dt.size, len(self.state_names), len(names)
        sens = np.zeros((t.size, n, count))
        if not self.coupled:
            loss, forcing = self._assemble(*self._coefficients(ui), full=False)
            positive = loss > 0
            g = np.where(positive, loss, 1.0)
            decay = np.exp(-g * dt[:, None] / self.capacity)
            steps = np.empty((rows, n, count))
            for k, name in enumerate(names):
                dloss, dforcing = self._parameter_derivative(ui, name, d['dg'][:, k],
                                                             d['dh'][:, k], full=False)
                steps[:, :, k] = self._decoupled_derivative(
                    states[:-1], forcing, g, decay, positive, dloss, dforcing,
                    d['dcap'][:, k], dt[:, None])
            for k in range(rows):
                sens[k + 1] = steps[k] + decay[k][:, None] * sens[k]
        else:
            a, b = self.system(ui)
            m = np.zeros((rows, n + 1, n + 1))
            m[:, :n, :n], m[:, :n, n] = a, b
            m *= dt[:, None, None]
            dm = np.zeros((rows, count, n + 1, n + 1))
            cap = self.capacity
            for k, name in enumerate(names):
                dloss, dforcing = self._parameter_derivative(ui, name, d['dg'][:, k],
                                                             d['dh'][:, k], full=True)
                dcap = d['dcap'][:, k]
                dm[:, k, :n, :n] = (-dloss / cap[None, :, None]
                                    - a * (dcap / cap)[None, :, None])
                dm[:, k, :n, n] = dforcing / cap - b * (dcap / cap)[None, :]
            dm *= dt[:, None, None, None]
            exp, frechet = expm_frechet_batch(m, dm)
            phi = exp[:, :n, :n]
            augmented = np.column_stack([states[:-1], np.ones(rows)])
            for k in range(rows):
                sens[k + 1] = (np.einsum('jab,b->aj', frechet[k, :, :n, :], augmented[k])
                               + phi[k] @ sens[k])
        # y = Cy x + offset + W products(u) (integrals: cumulated W products(u) dt)
        dy_dp = (np.einsum('yj,tjk->tyk', self._cy, sens)
                 + np.einsum('tj,yjk->tyk', states, d['dcy']) + d['doffset'][None])
        if self._y_w.size:
            dw = d['dw']
            per_row = np.zeros((t.size, len(self.output_names), count))
            per_row[1:] = np.einsum('tk,ykp->typ', self._y_prod.of(ui), dw)
            per_row[:1] = np.einsum('tk,ykp->typ', self._y_prod.of(np.zeros((1, u.shape[1]))),
                                    dw)
            integral = self._y_integral
            per_row[1:, integral] = np.cumsum(per_row[1:, integral] * dt[:, None, None], axis=0)
            per_row[0, integral] = 0.0
            dy_dp += per_row
        return ydf, dy_dp

    def __repr__(self) -> str:
        return (f'NetworkModel(nodes={list(self.state_names)}, inputs={list(self.input_names)}, '
                f'outputs={list(self.output_names)})')


class _ClosedFormBatch(IntervalBatch):
    """
    B intervals of a :class:`NetworkModel` without node-node conductances, evaluated again.

    Every node then follows its own closed form, so d x_end / d x_start is diagonal and a
    heat rate moves only the nodes it heats. The derivative arrays (B, n, n) and
    (B, n, len(wrt_inputs)) are allocated once, zero but for those entries, which each
    :meth:`jacobians` writes by index arrays (no loop over nodes); the columns of other
    inputs (a boundary temperature, a modulated conductance) are written whole. The
    arrays it returns are read-only and the batch's own, valid until its next call;
    where the outputs are the states (an offset aside) and no output term involves a
    differentiated input, the outputs' derivatives are the same arrays.
    """

    def __init__(self, model: NetworkModel, batch: int, dt_s: float,
                 wrt_inputs: Sequence[int]) -> None:
        super().__init__(model, batch, dt_s, wrt_inputs)
        n, wrt = len(model.state_names), self.wrt_inputs
        self._nodes = np.arange(n)
        rows, cols, weights = [], [], []  # the nonzero entries of the heat rates' columns
        for j, col in enumerate(wrt):
            vector = model._gain_only.get(col)
            if vector is not None:
                heated = np.flatnonzero(vector)
                rows.append(heated)
                cols.append(np.full(heated.size, j))
                weights.append(vector[heated])
        self._rows = np.concatenate(rows) if rows else np.zeros(0, int)
        self._cols = np.concatenate(cols) if cols else np.zeros(0, int)
        self._weights = np.concatenate(weights) if weights else np.zeros(0)
        self._capacity = model.capacity[self._rows]
        self._others = [(j, col) for j, col in enumerate(wrt)
                        if col in model._b_inputs and col not in model._gain_only]
        self._dx_dx0 = np.zeros((int(batch), n, n))
        self._dx_du = np.zeros((int(batch), n, len(wrt)))
        self._dx_dx0.flags.writeable = self._dx_du.flags.writeable = False
        self._same_outputs = (model._cy.shape == (n, n)
                              and np.array_equal(model._cy, np.eye(n))
                              and not any(model._y_prod.involves(c) for c in wrt))

    def jacobians(self) -> IntervalJacobians:
        model, dt = self.model, self.dt_s
        x_start, u = model._check_batch(self.x_start, self.u)
        loss, forcing = model._assemble(*model._coefficients(u), full=False)
        x_end, decay = model._decoupled(x_start, loss, forcing, dt)
        positive = loss > 0
        g = np.where(positive, loss, 1.0)
        dx_dx0, dx_du, rows = self._dx_dx0, self._dx_du, self._rows
        dx_dx0.flags.writeable = dx_du.flags.writeable = True
        try:
            dx_dx0[:, self._nodes, self._nodes] = decay
            if rows.size:  # a heat rate: dT_end/dq = (1 - a) / g, or dt / C without loss
                dx_du[:, rows, self._cols] = np.where(
                    positive[:, rows], (1.0 - decay[:, rows]) / g[:, rows] * self._weights,
                    self._weights * dt / self._capacity)
            for j, col in self._others:
                dloss, dforcing = model._input_derivative(u, col, full=False)
                dx_du[:, :, j] = model._decoupled_derivative(
                    x_start, forcing, g, decay, positive, dloss, dforcing, 0.0, dt)
        finally:
            dx_dx0.flags.writeable = dx_du.flags.writeable = False
        y_end = model._outputs(x_end, u, dt)
        if self._same_outputs:
            return IntervalJacobians(x_end, y_end, dx_dx0, dx_du, dx_dx0, dx_du)
        return IntervalJacobians(x_end, y_end, dx_dx0, dx_du,
                                 *model._output_jacobians(u, dt, self.wrt_inputs, dx_dx0, dx_du))
