"""
The description of a linear thermal network: a card's ``network`` section, parsed and checked.

:func:`parse_network` turns the section (a mapping read from YAML) into a
:class:`NetworkSpec`, reporting every problem at once (:class:`NetworkError`, each
problem with its place); :func:`card_network` reads a card file's section. The
format is documented in ``docs/models.md``; the model that solves a network is
:class:`mshoot_core.models.network.NetworkModel`.

Expressions (capacities, conductance and gain values, boundary temperatures, output
coefficients) use numbers, parameter names (and, in a boundary, input names),
``+ - * / **``, ``max``, ``min``, ``exp`` and ``sqrt``. They are parsed once and
checked node by node (:class:`Expression`): nothing else is ever evaluated. Their
derivatives (by a parameter, or an input of a boundary) are taken in forward mode;
at ``max(a, b)`` that of the argument that wins (the first on a tie).
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import math
import pathlib
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ['card_network', 'CARDS_DIR', 'Expression', 'NetworkError', 'NetworkSpec', 'OutputSpec',
           'Parameter', 'parse_network', 'Term']

#: The built-in cards (R1C1, R2C2, the two-zone building, the FMU and BOPTEST cards).
CARDS_DIR = pathlib.Path(__file__).resolve().parents[1] / 'cards'
#: Functions an expression may call.
FUNCTIONS = ('max', 'min', 'exp', 'sqrt')
#: Keys of a network section and of its entries.
SECTION_KEYS = ('inputs', 'parameters', 'nodes', 'boundaries', 'conductances', 'gains',
                'outputs')
PARAMETER_KEYS = ('value', 'min', 'max', 'free', 'unit', 'description')
NODE_KEYS = ('capacity', 'measured')
CONDUCTANCE_KEYS = ('between', 'value', 'times')
GAIN_KEYS = ('node', 'value', 'times')
OUTPUT_KEYS = ('unit', 'terms', 'offset', 'integral')
TERM_KEYS = ('state', 'value', 'times')


class NetworkError(ValueError):
    """An invalid network description: ``problems`` holds every problem, one sentence each."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        super().__init__('network: ' + '; '.join(self.problems))


# -- expressions ------------------------------------------------------------------------------
_BINARY = (ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow)


class Expression:
    """
    An arithmetic expression of named values, parsed once (see the module docstring).

    Parameters
    ----------
    text : str or number
        The expression (a number is one too).
    where : str
        Where it is written, for messages.

    Raises
    ------
    ValueError
        For a syntax error or a construct outside the language.

    """

    def __init__(self, text: Any, where: str) -> None:
        if isinstance(text, bool) or not isinstance(text, (str, int, float)):
            raise ValueError(f'{where}: expected a number or an expression, got {text!r}')
        self.text = str(text)
        try:
            tree = ast.parse(self.text.strip(), mode='eval')
        except SyntaxError:
            raise ValueError(f'{where}: {self.text!r} is not an expression') from None
        self.names: set[str] = set()
        self._check(tree.body, where)
        self.tree = tree.body
        self.code = compile(tree, f'<{where}>', 'eval')

    def _check(self, node: ast.AST, where: str) -> None:
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not \
                isinstance(node.value, bool):
            return
        if isinstance(node, ast.Name):
            if node.id in FUNCTIONS:
                raise ValueError(f'{where}: {node.id!r} is a function, call it')
            self.names.add(node.id)
            return
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            self._check(node.operand, where)
            return
        if isinstance(node, ast.BinOp) and isinstance(node.op, _BINARY):
            self._check(node.left, where)
            self._check(node.right, where)
            return
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in FUNCTIONS and not node.keywords and node.args):
            count = len(node.args)
            if (node.func.id in ('max', 'min') and count < 2) or (
                    node.func.id in ('exp', 'sqrt') and count != 1):
                raise ValueError(f'{where}: {node.func.id}() of {count} arguments in '
                                 f'{self.text!r}')
            for arg in node.args:
                self._check(arg, where)
            return
        raise ValueError(f'{where}: {self.text!r} uses {ast.unparse(node)!r}; expressions '
                         f'take numbers, names, + - * / **, and {list(FUNCTIONS)}')

    def value(self, env: Mapping[str, Any]) -> Any:
        """Evaluate with ``env`` (name -> number or array)."""
        return eval(self.code, {'__builtins__': {}, 'max': _maximum, 'min': _minimum,  # noqa: S307
                                'exp': np.exp, 'sqrt': np.sqrt}, dict(env))

    def derivative(self, env: Mapping[str, Any], wrt: str) -> Any:
        """Return d value / d ``wrt`` at ``env`` (forward mode; 0 where it does not appear)."""
        if wrt not in self.names:
            return 0.0
        return _forward(self.tree, env, wrt)[1]


def _maximum(*args: Any) -> Any:
    out = args[0]
    for arg in args[1:]:
        out = np.maximum(out, arg)
    return out


def _minimum(*args: Any) -> Any:
    out = args[0]
    for arg in args[1:]:
        out = np.minimum(out, arg)
    return out


def _forward(node: ast.AST, env: Mapping[str, Any], wrt: str) -> tuple[Any, Any]:
    """Return (value, d value / d wrt) of a checked expression tree."""
    if isinstance(node, ast.Constant):
        return float(node.value), 0.0
    if isinstance(node, ast.Name):
        return env[node.id], (1.0 if node.id == wrt else 0.0)
    if isinstance(node, ast.UnaryOp):
        v, d = _forward(node.operand, env, wrt)
        return (-v, -d) if isinstance(node.op, ast.USub) else (v, d)
    if isinstance(node, ast.BinOp):
        a, da = _forward(node.left, env, wrt)
        b, db = _forward(node.right, env, wrt)
        op = node.op
        if isinstance(op, ast.Add):
            return a + b, da + db
        if isinstance(op, ast.Sub):
            return a - b, da - db
        if isinstance(op, ast.Mult):
            return a * b, da * b + a * db
        if isinstance(op, ast.Div):
            return a / b, da / b - a * db / b ** 2
        power = a ** b
        d = b * a ** (b - 1.0) * da
        if np.any(db != 0.0):
            d = d + power * np.log(a) * db
        return power, d
    name = node.func.id  # a checked call
    pairs = [_forward(arg, env, wrt) for arg in node.args]
    if name == 'exp':
        v = np.exp(pairs[0][0])
        return v, v * pairs[0][1]
    if name == 'sqrt':
        v = np.sqrt(pairs[0][0])
        return v, 0.5 * pairs[0][1] / v
    value, deriv = pairs[0]
    for v, d in pairs[1:]:  # the derivative of the argument that wins (the first on a tie)
        keep = value >= v if name == 'max' else value <= v
        value, deriv = np.where(keep, value, v), np.where(keep, deriv, d)
    return value, deriv


# -- the description --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Parameter:
    """
    A named parameter of a network.

    Attributes
    ----------
    name : str
    value : float
        Its value [its unit].
    min, max : float or None
        Bounds of a fit.
    free : bool
        Whether a calibration fits it (then both bounds are given).
    unit : str
    description : str

    """

    name: str
    value: float
    min: float | None = None  # noqa: A003 (the card's key)
    max: float | None = None  # noqa: A003 (the card's key)
    free: bool = False
    unit: str = ''
    description: str = ''


@dataclasses.dataclass(frozen=True)
class Term:
    """A value (expression of the parameters) times a product of inputs (column indices)."""

    value: Expression
    times: tuple[int, ...]
    node: int = -1        # gains: the node heated; conductances: one end
    other: int = -1       # conductances: the other node (-1: a boundary)
    boundary: int = -1    # conductances: the boundary (-1: a node)
    state: int = -1       # output terms: the state multiplied (-1: an input term)


@dataclasses.dataclass(frozen=True)
class OutputSpec:
    """An output: terms, an offset (expression of the parameters) and whether integrated."""

    name: str
    unit: str
    terms: tuple[Term, ...]
    offset: Expression
    integral: bool


@dataclasses.dataclass(frozen=True)
class NetworkSpec:
    """
    A parsed and checked network section (made by :func:`parse_network`).

    Attributes
    ----------
    inputs : dict of str -> str
        Input name -> unit, in the model's input order.
    parameters : dict of str -> Parameter
    nodes : dict of str -> (Expression, bool)
        Node name -> (capacity [J/K], measured).
    boundaries : dict of str -> Expression
        Boundary name -> temperature [K] (inputs and parameters).
    conductances, gains : tuple of Term
    outputs : dict of str -> OutputSpec

    """

    inputs: dict[str, str]
    parameters: dict[str, Parameter]
    nodes: dict[str, tuple[Expression, bool]]
    boundaries: dict[str, Expression]
    conductances: tuple[Term, ...]
    gains: tuple[Term, ...]
    outputs: dict[str, OutputSpec]

    @property
    def free_parameters(self) -> tuple[Parameter, ...]:
        """Return the parameters a calibration fits."""
        return tuple(p for p in self.parameters.values() if p.free)

    def with_values(self, values: Mapping[str, float]) -> NetworkSpec:
        """
        Return the spec with parameter values replaced.

        Raises
        ------
        ValueError
            For a name that is not a parameter.

        """
        unknown = sorted(set(values) - set(self.parameters))
        if unknown:
            raise ValueError(f'unknown network parameters {unknown}; expected names from '
                             f'{list(self.parameters)}')
        parameters = {name: dataclasses.replace(p, value=values[name]) if name in values
                      else p for name, p in self.parameters.items()}
        return dataclasses.replace(self, parameters=parameters)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(
        value)


def _numeric(value: Any) -> Any:
    """Return ``value`` as a float where it is a number written as text (YAML reads 5.0e6 so)."""
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return value
        return number if math.isfinite(number) else value
    return value


def _unknown_keys(entry: Mapping, allowed: Sequence[str], where: str,
                  problems: list[str]) -> None:
    extra = sorted(set(entry) - set(allowed))
    if extra:
        problems.append(f'{where}: unknown keys {extra}; allowed: {list(allowed)}')


def _parameters(raw: Any, problems: list[str]) -> dict[str, Parameter]:
    if not isinstance(raw, Mapping):
        problems.append(f'parameters: expected a mapping of name -> value or entry, got {raw!r}')
        return {}
    out = {}
    for name, entry in raw.items():
        where = f'parameters.{name}'
        entry = _numeric(entry)
        if _number(entry):
            out[name] = Parameter(name, float(entry))
            continue
        if not isinstance(entry, Mapping):
            problems.append(f'{where}: expected a number or a mapping with value, min, max, '
                            f'free, got {entry!r}')
            continue
        _unknown_keys(entry, PARAMETER_KEYS, where, problems)
        value, low, high = (_numeric(entry.get(key)) for key in ('value', 'min', 'max'))
        free = entry.get('free', False)
        mine = []
        if not _number(value):
            mine.append(f'{where}.value: expected a finite number, got {value!r}')
        for key, bound in (('min', low), ('max', high)):
            if bound is not None and not _number(bound):
                mine.append(f'{where}.{key}: expected a finite number, got {bound!r}')
        if not isinstance(free, bool):
            mine.append(f'{where}.free: expected true or false, got {free!r}')
        elif free and (low is None or high is None):
            mine.append(f'{where}: a free parameter needs min and max')
        if not mine and low is not None and high is not None and not low <= value <= high:
            mine.append(f'{where}: value {value} must lie within [min {low}, max {high}]')
        problems += mine
        if not mine:
            out[name] = Parameter(name, float(value), None if low is None else float(low),
                                  None if high is None else float(high), bool(free),
                                  str(entry.get('unit', '')), str(entry.get('description', '')))
    return out


def _expression(text: Any, where: str, allowed: set[str], problems: list[str],
                what: str = 'parameters') -> Expression | None:
    try:
        expr = Expression(text, where)
    except ValueError as exc:
        problems.append(str(exc))
        return None
    unknown = sorted(expr.names - allowed)
    if unknown:
        problems.append(f'{where}: {expr.text!r} names {unknown}, which are not {what}; '
                        f'{what}: {sorted(allowed) or "none"}')
        return None
    return expr


def _times(raw: Any, inputs: Sequence[str] | dict[str, int], where: str, problems: list[str]
           ) -> tuple[int, ...] | None:
    if raw is None:
        return ()
    names = [raw] if isinstance(raw, str) else raw
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        problems.append(f'{where}.times: expected an input name or a list of them, got {raw!r}')
        return None
    index = inputs if isinstance(inputs, dict) else {n: i for i, n in enumerate(inputs)}
    unknown = [n for n in names if n not in index]
    if unknown:
        problems.append(f'{where}.times: {unknown} are not inputs {list(index)}')
        return None
    return tuple(index[n] for n in names)


def _entries(raw: Any, section: str, problems: list[str]) -> list[Mapping]:
    if raw is None:
        return []
    if not isinstance(raw, list) or not all(isinstance(e, Mapping) for e in raw):
        problems.append(f'{section}: expected a list of mappings, got {raw!r}')
        return []
    return raw


def _terms(section: Mapping, key: str, keys: Sequence[str], names: set[str],
           columns: dict[str, int], problems: list[str]) -> Any:
    """Yield (where, entry, value, times) of every entry of a list of terms (None: a problem)."""
    for k, entry in enumerate(_entries(section.get(key), key, problems)):
        where = f'{key}[{k}]'
        _unknown_keys(entry, keys, where, problems)
        yield (where, entry, _expression(entry.get('value'), f'{where}.value', names, problems),
               _times(entry.get('times'), columns, where, problems))


def parse_network(section: Any) -> NetworkSpec:
    """
    Parse and check a network section (the YAML mapping; see the module docstring).

    Raises
    ------
    NetworkError
        With every problem at once.

    """
    problems: list[str] = []
    if not isinstance(section, Mapping):
        raise NetworkError([f'expected a mapping with keys {list(SECTION_KEYS)}, got '
                            f'{section!r}'])
    _unknown_keys(section, SECTION_KEYS, 'network', problems)
    for key in ('inputs', 'nodes', 'outputs'):
        if key not in section:
            problems.append(f'missing required key {key!r}')
    raw_inputs = section.get('inputs') or {}
    if not isinstance(raw_inputs, Mapping) or not all(
            isinstance(u, str) for u in raw_inputs.values()):
        problems.append(f'inputs: expected a mapping of input name -> unit, got {raw_inputs!r}')
        raw_inputs = {}
    inputs = {str(k): str(v) for k, v in raw_inputs.items()}
    parameters = _parameters(section.get('parameters') or {}, problems)
    clash = sorted(set(parameters) & set(inputs))
    if clash:
        problems.append(f'{clash} are both parameters and inputs')
    names = set(parameters)
    nodes: dict[str, tuple[Expression, bool]] = {}
    raw_nodes = section.get('nodes') or {}
    if not isinstance(raw_nodes, Mapping) or not raw_nodes:
        problems.append(f'nodes: expected a mapping of node name -> {{capacity: ...}}, got '
                        f'{raw_nodes!r}')
        raw_nodes = {}
    for name, entry in raw_nodes.items():
        where = f'nodes.{name}'
        if not isinstance(entry, Mapping) or 'capacity' not in entry:
            problems.append(f'{where}: expected a mapping with a capacity [J/K], got {entry!r}')
            continue
        _unknown_keys(entry, NODE_KEYS, where, problems)
        capacity = _expression(entry['capacity'], f'{where}.capacity', names, problems)
        measured = entry.get('measured', True)
        if not isinstance(measured, bool):
            problems.append(f'{where}.measured: expected true or false, got {measured!r}')
        if capacity is not None:
            nodes[str(name)] = (capacity, bool(measured))
    boundaries: dict[str, Expression] = {}
    raw_boundaries = section.get('boundaries') or {}
    if not isinstance(raw_boundaries, Mapping):
        problems.append(f'boundaries: expected a mapping of name -> temperature [K], got '
                        f'{raw_boundaries!r}')
        raw_boundaries = {}
    for name, text in raw_boundaries.items():
        if name in raw_nodes:
            problems.append(f'boundaries.{name}: {name!r} is a node too')
        expr = _expression(text, f'boundaries.{name}', names | set(inputs), problems,
                           'parameters or inputs')
        if expr is not None:
            boundaries[str(name)] = expr
    node_names = [str(name) for name in raw_nodes]
    columns = {name: i for i, name in enumerate(inputs)}
    boundary_names = [str(name) for name in raw_boundaries]
    node_index = {name: i for i, name in enumerate(node_names)}
    boundary_index = {name: i for i, name in enumerate(boundary_names)}
    conductances = []
    for where, entry, value, times in _terms(section, 'conductances', CONDUCTANCE_KEYS, names,
                                             columns, problems):
        between = entry.get('between')
        if (not isinstance(between, list) or len(between) != 2
                or not all(isinstance(b, str) for b in between)):
            problems.append(f'{where}.between: expected [node, node or boundary], got '
                            f'{between!r}')
            continue
        a, b = between
        if a not in node_index and b in node_index:
            a, b = b, a
        if a not in node_index or (b not in node_index and b not in boundary_index) or a == b:
            problems.append(f'{where}.between: {between} must name a node and another node or '
                            f'a boundary; nodes {node_names}, boundaries {boundary_names}')
            continue
        if value is not None and times is not None:
            conductances.append(Term(value, times, node=node_index[a],
                                     other=node_index.get(b, -1),
                                     boundary=boundary_index.get(b, -1)))
    gains = []
    for where, entry, value, times in _terms(section, 'gains', GAIN_KEYS, names, columns,
                                             problems):
        node = entry.get('node')
        if not isinstance(node, str) or node not in node_index:
            problems.append(f'{where}.node: {node!r} is not a node {node_names}')
        elif value is not None and times is not None:
            gains.append(Term(value, times, node=node_index[node]))
    outputs = _outputs(section.get('outputs') or {}, node_names, columns, names, problems)
    if problems:
        raise NetworkError(problems)
    return NetworkSpec(inputs, parameters, nodes, boundaries, tuple(conductances),
                       tuple(gains), outputs)


def _outputs(raw: Any, node_names: list[str], inputs: dict[str, int], names: set[str],
             problems: list[str]) -> dict[str, OutputSpec]:
    if not isinstance(raw, Mapping) or not raw:
        problems.append(f'outputs: expected a mapping of output name -> {{unit, terms, offset, '
                        f'integral}}, got {raw!r}')
        return {}
    outputs = {}
    for name, entry in raw.items():
        where = f'outputs.{name}'
        if not isinstance(entry, Mapping):
            problems.append(f'{where}: expected a mapping, got {entry!r}')
            continue
        _unknown_keys(entry, OUTPUT_KEYS, where, problems)
        integral = entry.get('integral', False)
        if not isinstance(integral, bool):
            problems.append(f'{where}.integral: expected true or false, got {integral!r}')
            continue
        terms = []
        for k, term in enumerate(_entries(entry.get('terms'), f'{where}.terms', problems)):
            here = f'{where}.terms[{k}]'
            _unknown_keys(term, TERM_KEYS, here, problems)
            value = _expression(term.get('value', 1), f'{here}.value', names, problems)
            state = term.get('state')
            if state is not None:
                if state not in node_names:
                    problems.append(f'{here}.state: {state!r} is not a node {node_names}')
                    continue
                if 'times' in term or integral:
                    problems.append(f'{here}: a state term takes no times and no integral')
                    continue
                if value is not None:
                    terms.append(Term(value, (), state=node_names.index(state)))
                continue
            times = _times(term.get('times'), inputs, here, problems)
            if value is not None and times is not None:
                terms.append(Term(value, times))
        offset = _expression(entry.get('offset', 0), f'{where}.offset', names, problems)
        if offset is not None:
            outputs[str(name)] = OutputSpec(str(name), str(entry.get('unit', '')), tuple(terms),
                                            offset, bool(integral))
    return outputs


@functools.lru_cache(maxsize=32)
def card_network(path: str | pathlib.Path) -> NetworkSpec:
    """
    Return the network section of a card file, parsed (once per path).

    Raises
    ------
    NetworkError
        For an invalid section (or none).

    """
    import yaml
    document = yaml.safe_load(pathlib.Path(path).read_text(encoding='utf-8'))
    if not isinstance(document, dict) or 'network' not in document:
        raise NetworkError([f'{path} has no network section'])
    return parse_network(document['network'])
