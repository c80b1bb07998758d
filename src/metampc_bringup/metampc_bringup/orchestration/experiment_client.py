"""The orchestrator's window on the graph: service calls, the plant's samples, event markers.

An :class:`ExperimentClient` is an rclpy node (spun in a thread, :class:`SpunNode`) that calls
the run's services (the plant's ``reset``; the learner's ``meta_train``, ``adapt``,
``set_buffering``; each controller's ``set_active``), turning every failure (no answer in time,
the server gone, success=false) into an :class:`ExperimentError` that says what failed; follows
``y``, ``plant_info`` and ``progress`` so the orchestrator can wait on events; and publishes the
experiment events (:mod:`metampc_bringup.experiment_events`) on their latched topic, which the
recorder stores with the run for the reports.
"""
import logging
import os
import subprocess
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

from metampc_bringup.experiment_events import EVENTS_TOPIC, ExperimentEvent
from metampc_bringup.orchestration.spun_node import SpunNode
from metampc_common.qos import EVENTS, LATCHED, SPARSE, STREAM
from metampc_msgs.msg import PlantInfo, PlantOutput, TrainingProgress
from metampc_msgs.srv import Adapt, MetaTrain, ResetPlant, SetActive, SetBuffering
from rcl_interfaces.srv import SetParameters
from rclpy.duration import Duration
from rclpy.parameter import Parameter
from std_msgs.msg import String

RESEND_S = 1.0          # first resend of an unanswered request that carries an id, s
RESEND_MAX_S = 30.0     # longest gap between two sends of it, s


class ExperimentError(RuntimeError):
    """A phase of the experiment failed; the message names the phase and the cause."""


@dataclass
class Sample:
    """What the orchestrator keeps of one plant sample."""

    step: int
    stamp: float        # header stamp, s (sim time in lockstep)
    diverged: bool


def time_seconds(stamp: Any) -> float:
    """A builtin_interfaces/Time in s."""
    return stamp.sec + 1e-9 * stamp.nanosec


def stamp_seconds(msg: Any) -> float:
    """A message's header stamp in s."""
    return time_seconds(msg.header.stamp)


class Call:
    """One logical service call: the request, sent again with the same id while unanswered.

    rmw_fastrtps drops a response whose writer has not matched the client's reader within
    100 ms, so a first call can lose its answer however long one waits. A request with a
    ``request_id`` (every state-changing service of the graph,
    :mod:`metampc_common.replies`) is resent after RESEND_S, then twice as long each time
    (at most RESEND_MAX_S); the server answers a repeated id with the first answer, so the
    call runs once whichever answer arrives. A request without one is sent once.
    """

    def __init__(self, client: Any, request: Any, notify: Callable[[], None]):
        self.client, self.request, self._notify = client, request, notify
        self.futures: List[Any] = []
        self.sends = 0
        self._repeatable = bool(getattr(request, 'request_id', ''))
        self._wait = RESEND_S
        self._next = 0.0
        self._send()

    def _send(self) -> None:
        future = self.client.call_async(self.request)
        future.add_done_callback(lambda _: self._notify())
        self.futures.append(future)
        self.sends += 1
        self._next = time.monotonic() + self._wait
        self._wait = min(2 * self._wait, RESEND_MAX_S)

    def resend_if_due(self) -> None:
        """Send the request again if it carries an id and its time has come."""
        if self._repeatable and not self.done() and time.monotonic() >= self._next:
            self._send()

    def _answered(self) -> Optional[Any]:
        return next((f for f in self.futures if f.done()), None)

    def done(self) -> bool:
        return self._answered() is not None

    def result(self) -> Any:
        """The first answer; the other sends are dropped."""
        answered = self._answered()
        self._drop(answered)
        return answered.result()

    def exception(self) -> Optional[BaseException]:
        return self._answered().exception()

    def cancel(self) -> None:
        self._drop(None)

    def _drop(self, keep: Any) -> None:
        for future in self.futures:
            if future is not keep and not future.done():
                self.client.remove_pending_request(future)
                future.cancel()


class ExperimentClient(SpunNode):
    """Service clients, sample tracking and the events publisher of one experiment run.

    Args:
        controllers: controller name -> its ``set_active`` service name.
        alive: returns None while every node process runs, else a text naming the one
            that ended; checked while waiting, so a dead node fails the phase at once.
    """

    def __init__(self, controllers: Dict[str, str], alive: Callable[[], Optional[str]]):
        super().__init__('metampc_orchestrator', threads=4)
        node = self.node
        self._alive = alive
        self._cond = threading.Condition()
        self.last: Optional[Sample] = None
        self.samples = 0                    # y messages since the last reset_counts
        self.plant_info: Optional[PlantInfo] = None
        self.progress: Optional[TrainingProgress] = None
        node.create_subscription(PlantOutput, 'y', self._on_y, STREAM)
        node.create_subscription(PlantInfo, 'plant_info', self._on_info, LATCHED)
        node.create_subscription(TrainingProgress, 'progress', self._on_progress, SPARSE)
        self._events = node.create_publisher(String, EVENTS_TOPIC, EVENTS)
        self.clients = {
            'reset': node.create_client(ResetPlant, 'reset'),
            'meta_train': node.create_client(MetaTrain, 'meta_train'),
            'adapt': node.create_client(Adapt, 'adapt'),
            'set_buffering': node.create_client(SetBuffering, 'set_buffering'),
            **{name: node.create_client(SetActive, service)
               for name, service in controllers.items()},
        }
        self._param_clients: Dict[str, Any] = {}
        self._calls = 0     # request ids given so far

    # --- subscriptions ---------------------------------------------------------------------

    def _on_y(self, msg: PlantOutput) -> None:
        with self._cond:
            self.last = Sample(msg.step, stamp_seconds(msg), msg.diverged)
            self.samples += 1
            self._cond.notify_all()

    def _on_info(self, msg: PlantInfo) -> None:
        with self._cond:
            self.plant_info = msg
            self._cond.notify_all()

    def _on_progress(self, msg: TrainingProgress) -> None:
        self.progress = msg

    def _notify(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def reset_counts(self) -> None:
        with self._cond:
            self.samples = 0

    # --- waiting ---------------------------------------------------------------------------

    def check_alive(self, what: str) -> None:
        dead = self._alive()
        if dead:
            raise ExperimentError(f'{what}: {dead}')

    def wait_until(self, predicate: Callable[[], bool], timeout: float, what: str,
                   tick: Optional[Callable[[], None]] = None) -> None:
        """Wait (on sample/plant_info events, checking the processes twice a second) until
        `predicate` holds; ExperimentError naming `what` on timeout or a dead node."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate():
                self.check_alive(what)
                if tick:
                    tick()
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ExperimentError(f'{what}: no result within {timeout:g} s')
                self._cond.wait(min(left, 0.5))

    def subscribers(self, topic: str) -> List[str]:
        """Names of the nodes subscribed to `topic` (relative names resolve as ours do)."""
        name = self.node.resolve_topic_name(topic)
        return [info.node_name for info in self.node.get_subscriptions_info_by_topic(name)]

    def wait_ready(self, subscribers: Dict[str, List[str]], timeout: float) -> None:
        """Every service answering, the latched plant_info here, and each topic of
        `subscribers` subscribed by the nodes named: the graph is ready, with no sleeping on
        a guess."""
        deadline = time.monotonic() + timeout
        for name, client in self.clients.items():
            while not client.wait_for_service(timeout_sec=0.5):
                self.check_alive('start-up')
                if time.monotonic() > deadline:
                    raise ExperimentError(f'start-up: service {client.srv_name!r} ({name}) '
                                          f'not available within {timeout:g} s')
        for topic, nodes in subscribers.items():
            self.wait_until(lambda: set(nodes) <= set(self.subscribers(topic)),
                            max(deadline - time.monotonic(), 0.0),
                            f'start-up: {", ".join(nodes)} subscribed to {topic!r}')
        self.wait_until(lambda: self.plant_info is not None,
                        max(deadline - time.monotonic(), 0.0), 'start-up: latched plant_info')

    # --- services --------------------------------------------------------------------------

    def call(self, name: str, request: Any, timeout: float, what: str,
             tick: Optional[Callable[[], None]] = None, refused_ok: bool = False) -> Any:
        """Call service `name`; the response if it succeeded (or, with `refused_ok`, was
        answered with success false), else ExperimentError."""
        return self.finish(self.start(name, request), timeout, what, tick, refused_ok)

    def start(self, name: str, request: Any) -> 'Call':
        """Send a request to service `name` and return the call at once: the caller does
        other work meanwhile and then :meth:`finish` es it (or cancels it on failure)."""
        return self._send(self.clients[name], request)

    def _send(self, client: Any, request: Any) -> 'Call':
        if hasattr(request, 'request_id') and not request.request_id:
            self._calls += 1
            request.request_id = f'{self.node.get_name()}-{os.getpid()}-{self._calls}'
        return Call(client, request, self._notify)

    def finish(self, call: 'Call', timeout: float, what: str,
               tick: Optional[Callable[[], None]] = None, refused_ok: bool = False) -> Any:
        """Wait up to `timeout` s for a started call, resending a request that carries an id
        while it is unanswered (:class:`Call`); the response if it succeeded, else
        ExperimentError (the call is cancelled on any failure, Ctrl-C included)."""
        def waiting() -> None:
            call.resend_if_due()
            if tick:
                tick()
        try:
            self.wait_until(call.done, timeout, what, waiting)
        except BaseException:   # ExperimentError, or Ctrl-C while the call runs
            # Cancelled, a pending call is dropped with the node; left pending, the node's
            # destruction would fail it later with an exception nobody retrieves (printed).
            call.cancel()
            raise
        response = call.result()
        if response is None:
            raise ExperimentError(f'{what}: the call failed ({call.exception()})')
        if hasattr(response, 'success') and not response.success and not refused_ok:
            raise ExperimentError(f'{what}: {response.message}')
        return response

    def set_active(self, controller: str, active: bool, until_step: int = 0,
                   stop_at_escape: bool = False,
                   wait_delivered: bool = False) -> SetActive.Response:
        """Activate (optionally bounded: ``until_step``, ``stop_at_escape``) or deactivate
        (``wait_delivered``: once the readers acknowledged every answer, before a stop) a
        controller; its response (answered step, model version, delivery)."""
        request = SetActive.Request(active=active, until_step=until_step,
                                    stop_at_escape=stop_at_escape,
                                    wait_delivered=wait_delivered)
        return self.call(controller, request, 20.0, f'set_active({active}) of {controller}')

    def deliver_and_deactivate(self, controller: str, what: str) -> None:
        """Deactivate `controller` once every answer it sent reached every reader (before it
        is stopped: the recorder may be behind a fast run); a warning if not within 10 s."""
        if not self.set_active(controller, False, wait_delivered=True).delivered:
            logging.getLogger('metampc.orchestrator').warning(
                '%s: some answers of %s were not acknowledged by every reader within 10 s: '
                'the recording may lack them', what, controller)

    def set_buffering(self, buffering: bool, what: str, least: int = 0
                      ) -> SetBuffering.Response:
        """(Re)start or stop the learner's buffering (stop: only once it holds `least`
        samples, else ``success`` false); its response (counts, matched y)."""
        return self.call('set_buffering', SetBuffering.Request(buffering=buffering, least=least),
                         10.0, what, refused_ok=least > 0)

    def poll_inactive(self, controller: str, until: Callable[[SetActive.Response], bool],
                      timeout: float, period: float) -> bool:
        """Ask the controller (keeping it inactive) every `period` s until its answer meets
        `until`; False after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not until(self.set_active(controller, False)):
            if time.monotonic() > deadline:
                return False
            time.sleep(period)
        return True

    def wait_model(self, controller: str, version: int, timeout: float) -> None:
        """Wait until the (inactive) controller has model `version` ready for its next tick
        (it builds a model on a worker thread after the weights arrive; no topic says when)."""
        if not self.poll_inactive(controller, lambda a: a.model_version == version, timeout,
                                  0.05):
            raise ExperimentError(f'{controller} did not take model version {version} '
                                  f'within {timeout:g} s')

    def set_parameters(self, node_name: str, values: Dict[str, Any], what: str) -> None:
        """Set live parameters of node `node_name` (``ros2 param set``'s service); an
        ExperimentError naming `what` if the node refuses one (with its reason)."""
        client = self._param_clients.get(node_name)
        if client is None:
            client = self.node.create_client(SetParameters, f'/{node_name}/set_parameters')
            self._param_clients[node_name] = client
        if not client.wait_for_service(timeout_sec=10.0):
            raise ExperimentError(f'{what}: {node_name} offers no set_parameters service')
        request = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        response = self.finish(self._send(client, request), 10.0, what)
        refused = [f'{name}: {r.reason}' for name, r in zip(values, response.results)
                   if not r.successful]
        if refused:
            raise ExperimentError(f'{what}: {"; ".join(refused)}')

    # --- events ----------------------------------------------------------------------------

    def event(self, event: ExperimentEvent) -> None:
        """Publish one experiment event for the recording."""
        self._events.publish(String(data=event.encode()))

    def close(self, ack_timeout: float = 5.0) -> None:
        """Close once every subscriber (the recorder) has acknowledged the events, or after
        `ack_timeout` s: a writer destroyed at once can take its last samples with it (the
        final events were missing from recordings)."""
        self._events.wait_for_all_acked(Duration(seconds=ack_timeout))
        super().close()


def response_dict(response: Any, fields: List[str]) -> Dict[str, Any]:
    """Selected fields of a service response as plain Python values (arrays -> lists)."""
    return {f: (list(getattr(response, f)) if not isinstance(getattr(response, f),
                                                             (str, int, float, bool))
                else getattr(response, f)) for f in fields}


def process_status(procs: Dict[str, subprocess.Popen]) -> Optional[str]:
    """None while every process runs, else which ended and with what code."""
    for name, proc in procs.items():
        code = proc.poll()
        if code is not None:
            return f'{name} exited with status {code} (log: {proc.log_path})'
    return None
