"""The Jazzy `main()` idiom and parameter declaration, shared by every metampc node.

:func:`run_node` adds to the idiom of ros2/demos (init, spin, shutdown) what a user of
`ros2 run` expects: a bad argument or parameter is one error line and exit status 2, not a
traceback, and Ctrl-C is exit status 0 even when it lands while a callback is publishing.
:class:`LiveParameters` takes changes of the live parameters while the node runs, checked by
the node's own parse function, as at start-up.
"""
from array import array
import concurrent.futures
import difflib
import faulthandler
import math
import signal
import sys
import threading
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
import rclpy
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from metampc_common.params import current_names, ParameterError, ParamSpec, Value
from metampc_common.stop_signals import StopSignals

SHUTDOWN_POLL_S = 0.5    # s: longest a node takes to notice a shutdown that woke nobody
# s: longest a node may take to stop once its spin has ended; then SIGALRM ends it. Seen: a
# recorder stopped after a fast session hung for good in rclpy's destroy_publisher, deaf to
# every later signal, its lifeline's included (an orphan).
STOP_DEADLINE_S = 20
CALLBACK_WAIT_S = 10.0   # s: longest the stop waits for callbacks running in other threads
RACE_RETRIES = 3         # spins in a row that may meet an entity destroyed under them


# Parameters a node takes besides its table: rclpy's own, and QoS overrides of its endpoints.
ROS_PARAMETERS = ('use_sim_time', 'start_type_description_service')
QOS_OVERRIDES = 'qos_overrides.'


def undeclared(given: Sequence[str], table: Mapping[str, ParamSpec]) -> Optional[str]:
    """None, or the error line for the first name in `given` that the node does not declare,
    with the nearest declared name."""
    for name in given:
        if name in table or name in ROS_PARAMETERS or name.startswith(QOS_OVERRIDES):
            continue
        near = difflib.get_close_matches(name, list(table), n=1)
        hint = f'; did you mean {near[0]}?' if near else ''
        return f'unknown parameter {name}{hint} (the node\'s page in docs/ lists them)'
    return None


def declare_parameters(node: Node, table: Mapping[str, ParamSpec]) -> Dict[str, Value]:
    """Declare every parameter of `table` and return their values by name.

    Those not marked live are read-only: rclpy itself refuses a change (``Trying to set a
    read-only parameter: NAME.``); a live one is checked by :class:`LiveParameters`.

    A parameter given under its former name (``ParamSpec.formerly``) is declared under
    today's with that value, and a warning line names today's.

    Raises:
        ParameterError: a parameter given on the command line (or in a parameter file) that
            the node does not declare: ROS would ignore it, and a misspelt name would silently
            run the default; or one given under both its former name and today's.
    """
    # rclpy keeps the parameters given to the node (-p, --params-file) in this attribute; it
    # has no public accessor for those not declared (test_nodes_start pins the behaviour).
    given = dict(getattr(node, '_parameter_overrides', {}))
    current = current_names(given, table)
    error = undeclared(list(current), table)
    if error:
        raise ParameterError(error)
    for name, spec in table.items():
        # Given under its former name: rclpy holds the value under that name.
        value = current[name].value if name in current and name not in given else spec.default
        # dynamic_typing: the node's parse function accepts integers for doubles and names
        # bad types itself, with one clear line.
        node.declare_parameter(name, value, ParameterDescriptor(
            description=spec.description, read_only=not spec.live, dynamic_typing=True))
    return {name: node.get_parameter(name).value for name in table}


class LiveParameters:
    """Changes of a node's live parameters, checked as at start-up, then handed to the node.

    A ``ros2 param set`` (or ``load``, or any client of the parameter services) proposes new
    values; they are merged into the current values of the node's table and given to the same
    parse function as at start-up (e.g. ``controller_params.parse_params``), then to the node's
    own `check` of what only the running node knows (e.g. the plant's bounds). A failure
    refuses the change with ``SetParametersResult(successful=False, reason=<the error line>)``
    (the line a bad value gives at start-up, after ``invalid parameter: ``); the node goes on
    with its values. Once rclpy has set the values (and published them on
    ``/parameter_events``) the new typed config goes to `apply`, in the thread that set them.
    A change that parses to the config in use is accepted and not applied again.

    rclpy serves a node's parameter services in its default callback group, one request at a
    time, and calls the on-set and post-set callbacks of a request in turn, so the config
    checked in the one is the one applied in the other.
    """

    def __init__(self, node: Node, table: Mapping[str, ParamSpec], values: Mapping[str, Value],
                 config: Any, parse: Callable[[Mapping[str, Value]], Any],
                 apply: Callable[[Any, Dict[str, Value]], None],
                 check: Optional[Callable[[Any], str]] = None):
        """Args:
            node: the node whose parameters these are (declared by :func:`declare_parameters`).
            table: its declaration table.
            values: the values it started with (what declare_parameters returned).
            config: what `parse` made of them.
            parse: raw values -> typed config; raises ParameterError with the reason.
            apply: takes the accepted config and the changed values {name: value} (arrays as
                lists).
            check: the running node's further check of a parsed config: '' or the reason.
        """
        self.values: Dict[str, Value] = dict(values)
        self.config = config
        self._table = table
        self._parse, self._apply, self._check = parse, apply, check
        self._pending: Optional[Tuple[Dict[str, Value], Any]] = None
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._on_post_set)

    def propose(self, changes: Mapping[str, Value]) -> Tuple[Any, str]:
        """(the config of the current values with `changes`, '') or (None, why not)."""
        try:
            config = self._parse({**self.values, **changes})
        except ParameterError as err:
            return None, str(err)
        reason = self._check(config) if self._check is not None else ''
        return (None, reason) if reason else (config, '')

    def _on_set(self, parameters: List[Parameter]) -> SetParametersResult:
        self._pending = None
        changes = {p.name: list(p.value) if isinstance(p.value, array) else p.value
                   for p in parameters if p.name in self._table}
        if not changes:     # rclpy's own (use_sim_time): not ours to judge
            return SetParametersResult(successful=True)
        config, reason = self.propose(changes)
        if config is None:
            return SetParametersResult(successful=False, reason=reason)
        self._pending = (changes, config)
        return SetParametersResult(successful=True)

    def _on_post_set(self, parameters: List[Parameter]) -> None:
        pending, self._pending = self._pending, None
        if pending is None:
            return
        changes, config = pending
        self.values.update(changes)
        if config != self.config:
            self.config = config
            self._apply(config, changes)


class EventCounts:
    """A node's event counters (logged when it stops), each with a throttled warning.

    Attributes:
        counts: {name: count}, in the order given; nodes also increment it directly.
    """

    def __init__(self, node: Node, names: Sequence[str], warn_period_s: float = 1.0):
        self.counts: Dict[str, int] = dict.fromkeys(names, 0)
        self._node = node
        self._period = warn_period_s
        self._last_warn: Dict[str, float] = {}

    def warn(self, counter: str, text: str) -> None:
        """Count an event and warn about it, at most once per warn period for each kind."""
        self.counts[counter] += 1
        now = time.monotonic()
        if now - self._last_warn.get(counter, -math.inf) >= self._period:
            self._last_warn[counter] = now
            self._node.get_logger().warning(f'{text} ({self.counts[counter]} {counter} so far)')

    def summary(self) -> str:
        """'n1 name1, n2 name2, ...' for the stop line."""
        return ', '.join(f'{n} {name}' for name, n in self.counts.items())


def loop_executor() -> Executor:
    """The executor of the nodes on a control loop's critical path (plant, controller).

    rclpy's EventsExecutor (``rclpy.experimental``) dispatches from an event queue filled by
    the middleware's callbacks instead of rebuilding and scanning a wait set in Python on every
    wake-up. Measured with ``scripts/bench_lockstep.py`` on the 2-core machine, alternating:
    the experiment's lockstep tracking ran at 835-1410 steps/s with it against 440-680 with
    the SingleThreadedExecutor (docs/speed.md). Not for the recorder: its raw
    subscriptions end the spin with "SystemError: null argument to internal routine" (rclpy
    Jazzy), so it and the other nodes keep the SingleThreadedExecutor.
    """
    from rclpy.experimental import EventsExecutor
    return EventsExecutor()


def error_line(name: str, message: str) -> None:
    """Write one error line to stderr in rcutils' default console format.

    Not through rcutils: with a node half built (a ParameterError from its constructor), rcl's
    rosout handler publishes the line through that node's rosout writer; one of 14 plants started
    at once hung there after the line reached stderr (faulthandler: main thread in
    logger.error). A start-up error needs the console only.
    """
    print(f'[ERROR] [{time.time():.9f}] [{name}]: {message}', file=sys.stderr, flush=True)


def _stop_executor(ex: Executor, node: Optional[Node]) -> None:
    """Stop `ex` once its callbacks still running have ended (up to CALLBACK_WAIT_S).

    Called after the spin has ended. A node's long work (the learner's job, run inside a
    service callback) is stopped first: ``node.stop_work()`` where it has one. Then, in this
    order, because rclpy Jazzy's ``Executor.shutdown`` neither waits for callbacks (it tests
    ``_is_shutdown`` right after setting it) nor stops a MultiThreadedExecutor's pool, and
    destroys the guard condition that every callback's task triggers:
    - the callbacks in flight are waited for (one that ended after ``destroy_node`` failed on
      its destroyed service, seen in the learner's test beside a second suite);
    - the pool's queued callbacks are dropped and the ones its threads have taken waited for
      (one that started after ``shutdown`` failed on the destroyed guard condition, "The
      following exception was never retrieved: cannot use Destroyable because destruction
      was requested", seen in the learner's test);
    - then the executor is shut down;
    - and the tasks it made and never ran are cancelled, which closes their coroutines (rclpy
      makes a task's coroutine when an entity is ready, and a spin that ended before running
      it left "RuntimeWarning: coroutine ... was never awaited" on the learner's Ctrl-C after
      service calls by hand).
    """
    stop_work = getattr(node, 'stop_work', None)
    if stop_work is not None:
        stop_work()
    tracker = getattr(ex, '_work_tracker', None)    # Executor's; the EventsExecutor has none
    finished = tracker is None or tracker.wait(CALLBACK_WAIT_S)
    pool = getattr(ex, '_executor', None)           # MultiThreadedExecutor's
    if isinstance(pool, concurrent.futures.ThreadPoolExecutor):
        pool.shutdown(wait=finished, cancel_futures=True)
    ex.shutdown()
    for task, *_ in getattr(ex, '_tasks', ()):     # Executor's; the EventsExecutor has none
        if not task.done():
            task.cancel()


def run_node(make_node: Callable[[], Node], name: str, args: Optional[Sequence[str]] = None,
             executor: Optional[Callable[[], Executor]] = None) -> int:
    """Init rclpy, build the node, spin it until Ctrl-C or shutdown; return the exit code.

    Ctrl-C or SIGTERM (:mod:`.stop_signals`, main thread): noted and the executor woken; the
    spin ends after the callback in progress, then the executor stops, the node is destroyed
    (its stop line logged) and only then is the context shut down, so nothing publishes into a
    dead context. A second signal shuts the context down at once. A signal that arrives while
    the node is being built ends it as soon as it is built (one before rclpy.init: at once).
    Called from another thread, rclpy's own handlers (which shut the context down at once)
    stand in. Stopping (executor, node, context) that takes over STOP_DEADLINE_S ends the
    process by SIGALRM (exit status -14), so a node never outlives its stop for good. The spin
    loop's bounded wait (SHUTDOWN_POLL_S) also sees a shutdown that came from elsewhere.

    A node that hangs can be asked where: SIGUSR1 (``kill -USR1 PID``) prints the stack of
    every thread to stderr (faulthandler) and the node goes on.

    Args:
        make_node: builds the node (may raise ParameterError).
        name: logger name for the error lines.
        executor: factory of the executor to spin in (default: a SingleThreadedExecutor).
    """
    stop = None
    if threading.current_thread() is threading.main_thread():
        stop = StopSignals()
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        rclpy.init(args=args, signal_handler_options=(
            SignalHandlerOptions.ALL if stop is None else SignalHandlerOptions.NO))
    except _rclpy.RCLError as err:  # e.g. `-p x0:=[1, 0.5]`: YAML lists must be of one type
        # rcl has logged a generic line already; add what it could not parse.
        why = str(err).split(', at ')[0].replace('failed to initialize rcl: ', '')
        error_line(name, f'invalid arguments: {why}')
        return 2
    if stop is not None and stop.requested:     # before rclpy.init: nothing to build
        rclpy.try_shutdown()
        return 0
    node = ex = None
    try:
        node = make_node()
        ex = SingleThreadedExecutor() if executor is None else executor()
        ex.add_node(node)
        if stop is not None:
            stop.wake_on_signal(ex)
        # Not ex.spin(): a bounded wait also sees a context shut down by a second signal, which
        # wakes nobody.
        raced = 0
        while ex.context.ok() and not (stop is not None and stop.requested):
            try:
                ex.spin_once(timeout_sec=SHUTDOWN_POLL_S)
                raced = 0
            except InvalidHandle:
                # An entity that a callback in another thread destroyed (the learner's y
                # subscription when buffering stops) while this thread built its wait set:
                # rclpy Jazzy lets that race through (the learner ended with a traceback in a
                # CI run beside a second suite). The next wait set is built without it; the
                # same error again and again is no race.
                raced += 1
                if raced > RACE_RETRIES:
                    raise
    except ParameterError as err:
        error_line(name, f'invalid parameter: {err}')
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # A second signal (or rclpy's handler, off the main thread) shuts the context down
        # while the executor may be taking a message or a callback publishing (or the node is
        # still being built); those then fail (RCLError, or pybind11's RuntimeError in
        # take_message): a shutdown, not a crash.
        if rclpy.ok():
            raise
    finally:
        if stop is not None:
            stop.close()
            # The kernel's default action, not a Python handler: it ends a process whose main
            # thread is stuck in C holding the GIL as well.
            signal.signal(signal.SIGALRM, signal.SIG_DFL)
            signal.alarm(STOP_DEADLINE_S)
        # The executor first: an EventsExecutor (loop_executor) that still holds the node
        # keeps its /rosout writer alive past destroy_node, and a line logged after it (the
        # plant's and the controller's stop lines) would go to that writer.
        if ex is not None:
            _stop_executor(ex, node)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        if stop is not None:
            signal.alarm(0)
    return 0
