"""
Managed (lifecycle) nodes: the ROS 2 state machine, hooks that raise, and autostart.

A :class:`ManagedNode` is an :class:`rclpy.lifecycle.LifecycleNode` (services
``~/change_state``, ``~/get_state``, ... as ``ros2 lifecycle`` and lifecycle
managers expect them) whose node class fills in four plain methods:

=================  ====================================  ==================================
hook               transition                            what goes there
=================  ====================================  ==================================
``configure()``    unconfigured -> inactive              load models and FMUs, create
                                                         publishers (``create_lifecycle_
                                                         publisher``: they publish only
                                                         while active)
``activate()``     inactive -> active                    timers, subscriptions: the work
``deactivate()``   active -> inactive                    a last message (publishers still
                                                         publish here), then stop
``cleanup()``      inactive -> unconfigured              free FMUs and other resources
=================  ====================================  ==================================

A hook reports failure by raising: the exception is logged as one line (ERROR)
and kept in :attr:`ManagedNode.transition_error`. A failed ``configure`` or
``activate`` leaves the node where it was (FAILURE); a failed ``deactivate``
or ``cleanup`` goes through error processing, which releases everything and
ends unconfigured (ERROR). rclpy itself would swallow the exception silently.

Ownership: what a node creates (timers, subscriptions, publishers, services,
clients) is destroyed by the transition that undoes the state it was created
in. Created while configuring or inactive: destroyed after ``cleanup()``;
created while activating or active (also later, in a callback of the active
node, e.g. a run timer): destroyed after ``deactivate()``. Created before the
first configure (in ``__init__``, e.g. the :mod:`~mshoot_nodes.diagnostics`
publisher and its timer): kept until the node is destroyed. Hooks need not
destroy what they created.

Autostart: the parameter ``autostart`` (bool, default true, read-only) keeps a
plain ``ros2 run`` working. The node class calls :meth:`ManagedNode.autostart`
as the last line of its ``__init__``: with ``autostart`` true the node
configures and activates at once, synchronously. A configuration error then
raises from the constructor (``ros2 run`` ends with one line and exit code 2,
as for a bad parameter), and no timer is involved, so it works the same with
``use_sim_time`` before any ``/clock`` (a simulated-time timer would never fire
in the node that publishes ``/clock``). With ``autostart:=false`` the node
waits unconfigured for ``~/change_state`` (``ros2 lifecycle set /mpc configure``).

Simulated time: timers created in ``activate()`` with the default clock run on
the node's clock (simulated time with ``use_sim_time``); a node that drives
time itself uses :attr:`ManagedNode.steady_clock`.

Shutdown and destruction: the ``shutdown`` transition runs ``deactivate()``
(when active) and ``cleanup()`` (when configured). :meth:`destroy_node` runs
only ``cleanup()`` (it frees resources, e.g. closes FMUs): a destroyed node is
a stopped process, which sends no last message.
"""
from __future__ import annotations

from typing import Any, Callable

from lifecycle_msgs.msg import State as StateMsg
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.client import Client
from rclpy.clock import Clock, ClockType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.node import LifecycleNodeMixin
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer

#: Name of the autostart parameter.
AUTOSTART = 'autostart'
#: Primary states of the ROS 2 node lifecycle (labels as ``~/get_state`` reports them).
UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 'unconfigured', 'inactive', 'active', 'finalized'
#: Who owns an entity created in a given state (see the module docstring).
_OWNER = {StateMsg.PRIMARY_STATE_INACTIVE: 'configuration',
          StateMsg.TRANSITION_STATE_CONFIGURING: 'configuration',
          StateMsg.TRANSITION_STATE_DEACTIVATING: 'configuration',
          StateMsg.PRIMARY_STATE_ACTIVE: 'activation',
          StateMsg.TRANSITION_STATE_ACTIVATING: 'activation'}

RCLError = _rclpy.RCLError
ServiceHandler = Callable[[Any, Any], Any]
SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR


class ManagedNode(LifecycleNode):
    """
    A lifecycle node with hooks that raise, owned entities and autostart.

    Parameters
    ----------
    node_name : str
        The node's name.
    autostart : bool
        Default of the ``autostart`` parameter (an override wins).
    **kwargs
        Passed to :class:`rclpy.lifecycle.LifecycleNode` (context,
        parameter_overrides, ...).

    Attributes
    ----------
    transition_error : Exception or None
        Why the last transition failed (None after a successful one).
    steady_clock : Clock
        A STEADY_TIME clock for timers that must run on wall time (the node that
        publishes ``/clock``; watchdogs).
    diagnostics : DiagnosticsPublisher or None
        When set (see :mod:`mshoot_nodes.diagnostics`), it is published at once
        after every transition.

    """

    def __init__(self, node_name: str, *, autostart: bool = True, **kwargs: Any) -> None:
        # Before Node.__init__: it creates publishers through our create_* overrides.
        self._owned: dict[str, list[Any]] = {'configuration': [], 'activation': []}
        self._configured = False
        self.transition_error: Exception | None = None
        self.diagnostics: Any = None
        self._reporting_state = ''
        self._autostarting = False
        super().__init__(node_name, **kwargs)
        self.steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        self.declare_parameter(AUTOSTART, bool(autostart), ParameterDescriptor(
            description='configure and activate at start-up (false: stay unconfigured until '
                        'a lifecycle transition is requested on ~/change_state)',
            read_only=True))
        service = getattr(self, '_service_change_state', None)
        if service is not None:
            service.callback = self._guarded_change_state(service.callback)

    def _guarded_change_state(self, handler: ServiceHandler) -> ServiceHandler:
        """
        Answer a transition the current state does not have with success=False.

        rclpy 7.1.6 raises RCLError out of the service callback instead, which ends
        the executor's spin: one bad request from a lifecycle manager would stop
        the node.
        """
        def change_state(request: Any, response: Any) -> Any:
            try:
                return handler(request, response)
            except RCLError as exc:
                transition = request.transition.label or request.transition.id
                self.get_logger().warning(f'transition {transition!r} refused in state '
                                          f'{self.lifecycle_state}: {exc}')
                response.success = False
                return response
        return change_state

    # -- the hooks (the node class fills them in) ----------------------------------------
    def configure(self) -> None:
        """Load what the node needs (models, FMUs), create its publishers; raise on error."""

    def activate(self) -> None:
        """Start working: timers, subscriptions; raise on error."""

    def deactivate(self) -> None:
        """Stop working (publishers still publish here: a last message); raise on error."""

    def cleanup(self) -> None:
        """Free what ``configure`` loaded (FMUs); raise on error."""

    # -- state ---------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        """Label of the current state: 'unconfigured', 'inactive', 'active', ... ."""
        return self._reporting_state or self._state_machine.current_state[1]

    @property
    def is_active(self) -> bool:
        """Return True in the active state."""
        if self._reporting_state:
            return self._reporting_state == ACTIVE
        return self._state_machine.current_state[0] == StateMsg.PRIMARY_STATE_ACTIVE

    @property
    def is_configured(self) -> bool:
        """Return True after a successful configure and until cleanup."""
        return self._configured

    def autostart(self) -> None:
        """
        Configure and activate now if the ``autostart`` parameter is true.

        Call it as the last line of the node class's ``__init__``.

        Raises
        ------
        Exception
            The error of the failed transition (the node is destroyed first).

        """
        if not self.get_parameter(AUTOSTART).value:
            self.get_logger().info('autostart is false: unconfigured, waiting for '
                                   f'{self.get_fully_qualified_name()}/change_state')
            return
        self._autostarting = True  # a failure raises from here: the caller reports it
        try:
            results = [self.trigger_configure()]
            if results[0] == SUCCESS:
                results.append(self.trigger_activate())
        finally:
            self._autostarting = False
        for result in results:
            if result != SUCCESS:
                error = self.transition_error or RuntimeError(
                    f'{self.get_name()}: autostart failed in state {self.lifecycle_state}')
                self.destroy_node()
                raise error

    # -- rclpy's transition callbacks -----------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        if not self._run('configure', self.configure):
            self._release('configuration')
            return FAILURE
        self._configured = True
        return self._done(LifecycleNodeMixin.on_configure(self, state), 'configured')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        LifecycleNodeMixin.on_activate(self, state)  # enables the lifecycle publishers
        if not self._run('activate', self.activate):
            LifecycleNodeMixin.on_deactivate(self, state)
            self._release('activation')
            return FAILURE
        return self._done(SUCCESS, 'active')

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ok = self._run('deactivate', self.deactivate)
        LifecycleNodeMixin.on_deactivate(self, state)  # disables the lifecycle publishers
        self._release('activation')
        return self._done(SUCCESS, 'inactive') if ok else ERROR

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        ok = self._run('cleanup', self.cleanup)
        self._release('configuration')
        self._configured = False
        return self._done(LifecycleNodeMixin.on_cleanup(self, state), 'unconfigured') \
            if ok else ERROR

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if state.state_id == StateMsg.PRIMARY_STATE_ACTIVE:
            self._run('deactivate', self.deactivate)
            LifecycleNodeMixin.on_deactivate(self, state)
            self._release('activation')
        self._release_configuration()
        return self._done(SUCCESS, 'finalized')

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error(f'error processing after a failed transition from '
                                f'{state.label}: releasing everything (now unconfigured)')
        LifecycleNodeMixin.on_deactivate(self, state)
        self._release('activation')
        self._release_configuration()
        return SUCCESS

    # -- entity ownership -----------------------------------------------------------------
    def _own(self, entity: Any) -> Any:
        machine = getattr(self, '_state_machine', None)
        owner = _OWNER.get(machine.current_state[0]) if machine is not None else None
        if owner is not None:
            self._owned[owner].append(entity)
        return entity

    def create_timer(self, *args: Any, **kwargs: Any) -> Timer:
        return self._own(super().create_timer(*args, **kwargs))

    def create_subscription(self, *args: Any, **kwargs: Any) -> Subscription:
        return self._own(super().create_subscription(*args, **kwargs))

    def create_publisher(self, *args: Any, **kwargs: Any) -> Publisher:
        return self._own(super().create_publisher(*args, **kwargs))

    def create_lifecycle_publisher(self, *args: Any, **kwargs: Any) -> LifecyclePublisher:
        return self._own(super().create_lifecycle_publisher(*args, **kwargs))

    def create_service(self, *args: Any, **kwargs: Any) -> Service:
        return self._own(super().create_service(*args, **kwargs))

    def create_client(self, *args: Any, **kwargs: Any) -> Client:
        return self._own(super().create_client(*args, **kwargs))

    def _release(self, owner: str) -> None:
        """Destroy what ``owner`` ('configuration', 'activation') created, newest first."""
        entities, self._owned[owner] = self._owned[owner], []
        for entity in reversed(entities):
            if isinstance(entity, Timer):
                self.destroy_timer(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            elif isinstance(entity, LifecyclePublisher):
                self.destroy_lifecycle_publisher(entity)
            elif isinstance(entity, Publisher):
                self.destroy_publisher(entity)
            elif isinstance(entity, Service):
                self.destroy_service(entity)
            elif isinstance(entity, Client):
                self.destroy_client(entity)

    def _release_configuration(self) -> None:
        if self._configured:
            self._run('cleanup', self.cleanup)
            self._configured = False
        self._release('configuration')

    # -- helpers --------------------------------------------------------------------------
    def _run(self, name: str, hook: Callable[[], None]) -> bool:
        """Run a hook; log and keep its exception. True when it succeeded."""
        try:
            hook()
        except Exception as exc:  # noqa: BLE001 - a failed transition, reported, not a crash
            self.transition_error = exc
            if self._autostarting:
                return False
            self.get_logger().error(f'{name} failed: {exc}' if isinstance(
                exc, (ValueError, FileNotFoundError)) else
                f'{name} failed: {type(exc).__name__}: {exc}')
            return False
        self.transition_error = None
        return True

    def _done(self, result: TransitionCallbackReturn, state: str) -> TransitionCallbackReturn:
        if result == SUCCESS:
            self.get_logger().debug(f'now {state}')
            if self.diagnostics is not None:
                # The state machine still says 'configuring' etc.: report the state reached.
                self._reporting_state = state
                try:
                    self.diagnostics.publish()
                finally:
                    self._reporting_state = ''
        return result

    def destroy_node(self) -> None:
        """
        Free what the configuration holds, then destroy the node.

        Freeing is ``cleanup()``, with no ``deactivate()``.
        """
        if getattr(self, '_owned', None) is not None and hasattr(self, '_state_machine'):
            if self.is_active:
                LifecycleNodeMixin.on_deactivate(self, LifecycleState(
                    label=ACTIVE, state_id=StateMsg.PRIMARY_STATE_ACTIVE))
            self._release('activation')
            self._release_configuration()
        super().destroy_node()
        release_state_machine(self)


def release_state_machine(node: Any) -> None:
    """
    Destroy a lifecycle node's state machine after ``Node.destroy_node``.

    rclpy's LifecycleNode leaves it to the garbage collector, and until then the
    rcl node stays alive (its ``/rosout`` publisher too): a node of the same name
    created next warns 'Publisher already registered'.
    """
    machine = getattr(node, '_state_machine', None)
    if machine is not None:
        machine.destroy_when_not_in_use()
