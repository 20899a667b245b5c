"""What every playseg node shares: declared+validated parameters, the run loop, autostart."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription

from playseg_core.errors import PlaysegError
from playseg_ros.launch import NODE_NAME

RCLError = _rclpy.RCLError

STOP_DELIVERY_TIMEOUT_S = 10.0
"""At a stop, how long a node waits at most for its subscribers to acknowledge what it published last
(below `playseg up`'s default shutdown_timeout_s, so the launcher does not kill it first)."""

SEQUENCE_NUMBER_UNSUPPORTED = 2**64 - 1
"""rmw's value of a message info's sequence number when the middleware does not report it."""


def take_queued(sub: Subscription) -> int:
    """Run the subscription's callback on each message its reader holds already (delivered, so
    acknowledged to the publisher, but not yet handed over by the executor); a node that stops takes
    them instead of dropping them with its subscription. Returns how many."""
    with_info = sub._callback_type is Subscription.CallbackType.WithMessageInfo  # as rclpy's executor
    count = 0
    while True:
        with sub.handle:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
        if taken is None:
            return count
        if with_info:
            sub.callback(*taken)
        else:
            sub.callback(taken[0])
        count += 1


def wait_delivered(node: Node, publishers: Iterable[Publisher | None], timeout_s: float) -> None:
    """Wait until every subscriber acknowledged what the publishers sent (reliable messages not yet
    acknowledged die with the process), at most ``timeout_s``; a warning names a topic that missed it."""
    for publisher in publishers:
        if publisher is not None and not publisher.wait_for_all_acked(Duration(seconds=timeout_s)):
            node.get_logger().warning(
                f"{publisher.topic_name}: not every subscriber acknowledged within {timeout_s} s"
            )


class StartGaps:
    """Warns once per topic when the first message a node receives on it is not the first its publisher
    sent: a gap at the start (the node subscribed after the stream began, e.g. a bag_player that did not
    wait for it). The publisher's sequence number says so, for any message type."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.seen: set[str] = set()

    def check(self, topic: str, info: Mapping[str, Any]) -> None:
        if topic in self.seen:
            return
        self.seen.add(topic)
        number = info.get("publication_sequence_number")
        if number is None or number == SEQUENCE_NUMBER_UNSUPPORTED or number <= 1:
            return
        self.node.get_logger().warning(
            f"{topic}: gap at the start: the first message received is its publisher's message {number}, "
            f"the {number - 1} before it were published before this node subscribed (a publisher that does "
            "not wait for its subscribers: wait_for_subscribers, or `playseg up`, which sets it)"
        )


class ReleasingLifecycleNode(LifecycleNode):
    """A lifecycle node whose cleanup, shutdown and error processing all undo configure and activate by
    one `release` (safe to call again), so a failed or errored node can be configured afresh."""

    def release(self) -> None:
        raise NotImplementedError

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()  # error processing ends in unconfigured: configure must be able to start afresh
        return TransitionCallbackReturn.SUCCESS


def declare(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare a parameter with a description and return its value.

    A float parameter also accepts an integer (`rate_hz: 10` in a YAML file); any other value of the
    wrong type is a ValueError naming the node, the parameter and the expected type.
    """
    if isinstance(default, float):
        descriptor = ParameterDescriptor(description=description, dynamic_typing=True)
        value = node.declare_parameter(name, default, descriptor).value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PlaysegError(f"{node.get_name()}: parameter {name!r} must be a number, got {value!r}")
        return float(value)
    try:
        return node.declare_parameter(name, default, ParameterDescriptor(description=description)).value
    except InvalidParameterTypeException as exc:
        raise PlaysegError(f"{node.get_name()}: invalid parameter: {exc}") from exc


def require(condition: bool, node: Node, message: str) -> None:
    """Parameter validation: raise ValueError naming the node and the problem.

    It also marks the node (``bad_parameter``): a lifecycle node checks its parameters in configure,
    where rclpy swallows the exception, and `run_node` must still tell a bad parameter (exit 2, the
    node's one logged line) from a configure that failed otherwise (exit 1)."""
    if not condition:
        node.bad_parameter = message  # type: ignore[attr-defined]
        raise PlaysegError(f"{node.get_name()}: invalid parameter: {message}")


def ros_arguments_error(argv: list[str]) -> str | None:
    """Why rcl would refuse ``argv``'s node-name remap (``--ros-args -r __node:=NAME``), or None.

    rcl refuses it inside `rclpy.init` with two log lines of its own and an RCLError traceback; checked
    here first, it is one line naming the argument."""
    inside, previous = False, ""
    for arg in argv:
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and previous in ("-r", "--remap"):
            target, _, value = arg.partition(":=")
            name = target.rsplit(":", 1)[-1]  # "talker:__node:=x" remaps the node named talker
            if name in ("__node", "__name") and not NODE_NAME.fullmatch(value):
                return (
                    f"invalid node name {value!r} in '-r {arg}': a ROS node name is letters, digits and '_'"
                )
        previous = arg if inside else ""
    return None


def run_node(make_node: Callable[[], Node], args: list[str] | None = None, threads: int = 1) -> int:
    """Init rclpy, build the node, autostart lifecycle nodes, spin until Ctrl-C, clean up.

    A LifecycleNode with parameter ``autostart`` true (the default) configures and activates itself;
    with ``autostart:=false`` an external manager drives its transitions. SIGINT/SIGTERM end the spin;
    lifecycle nodes are then deactivated and cleaned up so their files are closed.

    Exit code: 0; 2 for a bad parameter; 1 when configure fails, when a shutdown transition fails (a
    recorder that could not finish its bag) or when the node sets a non-zero ``exit_code`` attribute (a
    node that cannot go on, e.g. a bag player that could not play its whole bag), which also ends the
    spin.
    """
    # Our own SIGINT/SIGTERM handling: the context stays valid while the node shuts down, so lifecycle
    # transitions (which close files) can still run.
    argv = sys.argv if args is None else args
    problem = ros_arguments_error(argv)
    if problem is None:
        try:
            rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        except RCLError as exc:  # another argument rcl cannot parse (it logged its own lines already)
            problem = f"invalid ROS arguments: {str(exc).split(', at ')[0]}"
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    # Installed explicitly: a process started in the background by a shell inherits SIGINT ignored.
    # The first signal only asks the spin loop to stop, so no callback is cut off half-way (a message the
    # executor already took would be lost); a second one interrupts at once.
    stop = threading.Event()

    def request_stop(signum: int, frame: object) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    node = None
    executor = None
    code = 0
    try:
        node = make_node()
        autostart = isinstance(node, LifecycleNode) and declare(
            node, "autostart", True, "configure and activate on start-up"
        )
        _warn_unknown_parameters(node)
        if isinstance(node, LifecycleNode):
            if autostart:
                if node.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                    if getattr(node, "bad_parameter", None):
                        return 2  # the node logged the parameter and the problem, in one line
                    node.get_logger().error("configure failed")
                    return 1
                node.trigger_activate()
        # One thread runs each callback to completion inside spin_once: nothing is in flight at a stop.
        executor = SingleThreadedExecutor() if threads == 1 else MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        # Short waits, so a stop request (or a node giving up) is seen promptly.
        while rclpy.ok() and not stop.is_set() and not _exit_code(node):
            executor.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    finally:
        if executor is not None:
            _stop_executor(executor)
        if node is not None:
            if not _shut_down(node):
                code = code or 1
            code = code or _exit_code(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _warn_unknown_parameters(node: Node) -> None:
    """A parameter given to the node (a parameter file, `-p`) that it does not declare is a misspelling
    rclpy ignores without a word: say so. Every node declares its parameters when it is built."""
    given = getattr(node, "_parameter_overrides", {})  # rclpy's, for this node only
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if unknown:
        node.get_logger().warning(f"parameters this node does not have, ignored: {', '.join(unknown)}")


def _stop_executor(executor: SingleThreadedExecutor | MultiThreadedExecutor) -> None:
    """Let callbacks still running in worker threads (a recorder's write) finish before cleanup."""
    try:
        executor.shutdown()
    except KeyboardInterrupt:  # a second Ctrl-C: clean up at once
        pass


def _exit_code(node: Node) -> int:
    """The exit code a node asked for by setting ``exit_code`` (0 when it did not)."""
    return int(getattr(node, "exit_code", 0) or 0)


def _lifecycle_state(node: LifecycleNode) -> str:
    return node._state_machine.current_state[1]  # rclpy exposes no public getter


def _shut_down(node: Node) -> bool:
    """Run the lifecycle transitions down to unconfigured so that files are flushed and closed.

    False when a transition did not succeed: rclpy turns an exception in a transition callback into
    ERROR without a word, so the failure is logged here and becomes the exit code (a recorder whose bag
    could not be finished must not exit 0).
    """
    if not isinstance(node, LifecycleNode):
        if hasattr(node, "close"):
            node.close()
        return True
    ok = True
    for state, name, trigger in (
        ("active", "deactivate", node.trigger_deactivate),
        ("inactive", "cleanup", node.trigger_cleanup),
    ):
        if _lifecycle_state(node) != state:
            continue
        result = trigger()
        if result != TransitionCallbackReturn.SUCCESS:
            node.get_logger().error(f"{name} at shutdown failed ({result.to_label()}): exiting with code 1")
            ok = False
    return ok
