"""
Parameter declaration and validation helpers shared by the nodes.

Every node declares its parameters from a table of :class:`ParamSpec`: the
default, a description, an optional numeric range, the allowed string
choices and whether it is read-only. Ranges and read-only flags are enforced
by rclpy itself (descriptors); choices and cross-parameter rules are checked
in the node's on-set callback, which only validates (no side effects) and
returns a reason that says what was expected and what was given.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Iterable, Sequence

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter


class ParameterRejected(InvalidParameterValueException):
    """
    Start-up values rejected by a node's checks.

    ``reason`` says why (in one sentence, without rclpy's list of every value given).
    """

    def __init__(self, names: str, given: Any, reason: str) -> None:
        super().__init__(names, given, reason)
        self.reason = reason


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """
    One declared parameter.

    Attributes
    ----------
    name : str
        Parameter name.
    default : bool, int, float, str or list of str
        Default value (fixes the type).
    description : str
        What the parameter is, with its unit.
    low, high : float, optional
        Inclusive numeric range (enforced by rclpy).
    choices : tuple of str, optional
        Allowed values of a string parameter (checked in the on-set callback).
    read_only : bool
        Set only at start-up (overrides, YAML), never at run time.

    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        """Return the rclpy descriptor of this parameter."""
        constraints = ''
        if self.choices:
            constraints = 'one of: ' + ', '.join(repr(c) for c in self.choices)
        descriptor = ParameterDescriptor(description=self.description, read_only=self.read_only,
                                         additional_constraints=constraints)
        if self.low is not None or self.high is not None:
            if isinstance(self.default, bool):
                raise TypeError(f'{self.name}: a bool parameter cannot have a range')
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(self.low if self.low is not None else -2 ** 62),
                    to_value=int(self.high if self.high is not None else 2 ** 62), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low if self.low is not None else -1e300),
                    to_value=float(self.high if self.high is not None else 1e300), step=0.0)]
        return descriptor

    @classmethod
    def from_setting(cls, field: Any, default: Any = None) -> ParamSpec:
        """
        Return the parameter of a described core setting.

        The setting is a :class:`mshoot_core.settings.SettingField`: same name, default,
        description, range and choices; read-only when fixed once running.
        """
        return cls(field.name, field.default if default is None else default,
                   field.description, low=field.low, high=field.high, choices=field.choices,
                   read_only=field.read_only)


Check = Callable[[dict[str, Any]], str | None]


def declare(node: Node, specs: Sequence[ParamSpec], checks: Iterable[Check] = ()) -> None:
    """
    Register the validating on-set callback, then declare ``specs`` on ``node``.

    Parameters
    ----------
    node : Node
        The node.
    specs : sequence of ParamSpec
        Its parameters.
    checks : iterable of callables
        Cross-parameter rules: ``check(values) -> reason or None`` on the
        merged current + proposed values (only the declared ones).

    Raises
    ------
    ParameterRejected
        (an rclpy ``InvalidParameterValueException``) If an override (``-p``,
        YAML) is rejected; its ``reason`` says why.
    ValueError
        If an override names a parameter the node does not have (a typo in a
        YAML file would otherwise be ignored silently); the message lists the
        valid names.

    """
    by_name = {spec.name: spec for spec in specs}
    checks = list(checks)

    def on_set(params: list[Parameter]) -> SetParametersResult:
        proposed = {p.name: p.value for p in params if p.name in by_name}
        if not proposed:
            return SetParametersResult(successful=True)
        for name, value in proposed.items():
            spec = by_name[name]
            if spec.choices and value not in spec.choices:
                return SetParametersResult(
                    successful=False,
                    reason=f'{name} must be one of {list(spec.choices)}, got {value!r}')
        # Start-up overrides of parameters not declared yet count too (they were judged
        # as a whole before the first declaration).
        values = {name: spec.default for name, spec in by_name.items()}
        values.update(startup)
        values.update({name: node.get_parameter(name).value for name in by_name
                       if node.has_parameter(name)})
        values.update(proposed)
        for check in checks:
            reason = check(values)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    overrides = getattr(node, '_parameter_overrides', {})
    startup = {name: overrides[name].value for name in by_name if name in overrides}
    node.add_on_set_parameters_callback(on_set)
    try:
        if startup:  # every start-up value at once: the reason names the real conflict
            result = on_set([Parameter(name, value=value) for name, value in startup.items()])
            if not result.successful:
                raise ParameterRejected(', '.join(sorted(startup)),
                                        [startup[n] for n in sorted(startup)], result.reason)
        for spec in specs:
            node.declare_parameter(spec.name, spec.default, spec.descriptor())
        unknown = sorted(name for name in getattr(node, '_parameter_overrides', {})
                         if not node.has_parameter(name)
                         and not name.startswith('qos_overrides.'))
        if unknown:
            raise ValueError(f'unknown parameter(s) {unknown} for node {node.get_name()!r}; '
                             f'valid: {sorted(spec.name for spec in specs)} (and use_sim_time)')
    except Exception:
        Node.destroy_node(node)  # the base class: the node's own attributes do not exist yet
        machine = getattr(node, '_state_machine', None)
        if machine is not None:  # a lifecycle node: its state machine holds the rcl node
            machine.destroy_when_not_in_use()
        raise


def values(node: Node, specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """Return the current values of ``specs`` on ``node`` (string arrays as lists)."""
    out = {}
    for spec in specs:
        value = node.get_parameter(spec.name).value
        out[spec.name] = list(value) if isinstance(value, (list, tuple)) else value
    return out


def ordered(low: str, high: str, strict: bool = True) -> Check:
    """Return a rule: parameter ``low`` < ``high`` (or <= when not strict)."""
    def check(values: dict[str, Any]) -> str | None:
        if low in values and high in values:
            bad = values[low] >= values[high] if strict else values[low] > values[high]
            if bad:
                relation = '<' if strict else '<='
                return (f'{low} must be {relation} {high}, got {low} = {values[low]} and '
                        f'{high} = {values[high]}')
        return None
    return check
