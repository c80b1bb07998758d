"""The `controller` node: a thin ROS 2 adapter over controller_core.

While active, answers each plant sample ``y`` (PlantOutput, step k) once with ``u`` (ControlInput,
step k, held over (k, k+1]) and then ``mpc_status`` (MpcStatus), planning with eq. (mpc) on the
latest accepted NSSM (``nssm_weights``, latched; checked and built on a worker thread) or with the
family's true-model NMPC (theta from every y). Also takes ``plant_info``, an optional ``reference``
override and ``set_active``; publishes ``u_hold`` when a lockstep answer waits for a requested
model (adaptation in the loop: :mod:`metampc_controller.adaptation_trigger`; new models pass
:mod:`metampc_controller.model_gate`, whose events ``mpc_status`` carries). Refuses: a bad
parameter (one error line, exit 2), a bad live change (with the reason), invalid weights (a
refused model event; the model in use stays). Parameters: :data:`metampc_controller.
controller_params.PARAMETERS`; interfaces, ticks, live changes and faults: docs/controller.md.
"""
from array import array
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
import math
import sys
import time
from typing import Optional

from metampc_common.held_publisher import held_qos, HeldPublisher
from metampc_common.node_main import (declare_parameters, EventCounts, LiveParameters,
                                      loop_executor, run_node)
from metampc_common.qos import LATCHED, SPARSE, STREAM
from metampc_common.replies import Replies
from metampc_msgs.msg import (AdaptRefusal, ControlInput, ModelEvent, MpcStatus, NssmWeights,
                              PlantInfo, PlantOutput, StepHold)
from metampc_msgs.srv import SetActive
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future as TaskFuture
from std_msgs.msg import Float64MultiArray

from metampc_controller.adaptation_trigger import Request
from metampc_controller.controller_core import (AnswerRule, build_model, ControllerCore,
                                                TickResult)
from metampc_controller.controller_params import ControllerConfig, PARAMETERS, parse_params
from metampc_controller.model_gate import Cause, Outcome
from metampc_controller.model_gate import ModelEvent as GateEvent
from metampc_model.weights_codec import fields_of, model_from_fields, WeightsError
from metampc_plant.plant_description import PlantDescription

COUNTERS = ('answered', 'pre_model', 'fallbacks', 'models', 'rejected_weights', 'ignored_y',
            'retunes', 'adapt_requests', 'adapt_timeouts', 'adapt_refusals', 'refused_models',
            'reverted_models', 'dropped')
DELIVERY_TIMEOUT = Duration(seconds=10.0)   # deactivation's wait for the readers' acks
HOLD_POLL_S = 0.002     # how often an answer waiting for a requested model looks for it, s


def _doubles(values: np.ndarray) -> array:
    """A float64 array field value without a per-element conversion (tobytes() is in C
    order whatever the layout)."""
    if values.dtype != np.float64:
        values = values.astype(np.float64)
    return array('d', values.tobytes())


class ControllerNode(Node):
    """ROS 2 front end of one :class:`ControllerCore` (see the module docstring)."""

    def __init__(self):
        super().__init__('controller')
        values = declare_parameters(self, PARAMETERS)
        self.cfg = parse_params(values)
        self.core = ControllerCore(self.cfg)
        self.rule = AnswerRule(self.cfg.active)
        self._events = EventCounts(self, COUNTERS)
        self._counts = self._events.counts
        self._warn = self._events.warn
        self._plant_warnings = set()
        self._stamp = None              # stamp of the newest y
        # One message of each kind, refilled every tick: publish() serialises it at once, and
        # a new MpcStatus per tick cost ~10 us (its constructor, a Header, a Time).
        self._u_msg = ControlInput()
        self._status_msg = MpcStatus()
        # Every callback runs on the one executor thread (the core's tick state needs no
        # lock); building a model or a new tuning's QP (OSQP set-up, the DARE: ~10-100 ms)
        # runs on a worker thread and is handed over as one reference. A MultiThreadedExecutor
        # with the weights in a group of their own measured ~1.6x the CPU per sample and fell
        # behind its y queue at 100 Hz on a loaded 2-core machine (docs/controller.md).
        self._builder = ThreadPoolExecutor(max_workers=1, thread_name_prefix='model_builder')
        # Held back while a reader that keeps all is full: the recorder never loses an
        # answer, however fast the lockstep loop (metampc_common.held_publisher).
        held, hold = partial(self._warn, 'dropped'), self.cfg.hold
        self._pub_u = HeldPublisher(self.create_publisher(ControlInput, 'u', held_qos(hold)),
                                    hold, held)
        self._pub_status = HeldPublisher(
            self.create_publisher(MpcStatus, 'mpc_status', held_qos(hold)), hold, held)
        self._pub_hold = self.create_publisher(StepHold, 'u_hold', STREAM)
        self._hold_msg = StepHold()
        self.create_subscription(PlantOutput, 'y', self._on_y, STREAM)
        self.create_subscription(PlantInfo, 'plant_info', self._on_plant_info, LATCHED)
        self.create_subscription(Float64MultiArray, 'reference', self._on_reference, SPARSE)
        if self.core.kind.learned:     # its models come from the learner
            self.create_subscription(NssmWeights, 'nssm_weights', self._on_weights, LATCHED)
            self.create_subscription(AdaptRefusal, 'adapt_refusals', self._on_refusal, SPARSE)
        self._replies = Replies(TaskFuture)     # a repeated request id: the first answer
        self.create_service(SetActive, 'set_active', self._replies.wrap(self._on_set_active))
        # Adaptation in the loop: a lockstep answer waiting for a requested model resumes
        # when the builder thread has it (or after adapt_timeout s of wall time). A polling
        # timer, only while an answer waits: the EventsExecutor has no guard conditions.
        self._hold_timer = None
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / self.cfg.rate_hz, self._on_timer)
        self._config_version = 0
        self._retuning: Optional[Future] = None     # the latest accepted change's build
        LiveParameters(self, PARAMETERS, values, self.cfg, parse_params, self._on_params,
                       check=self.core.check_tuning)
        mpc = self.cfg.mpc
        self.get_logger().info(
            f'{self.cfg.planner} controller at {self.cfg.rate_hz} Hz: N={mpc.horizon}, '
            f'q={list(mpc.q)}, r={np.atleast_1d(mpc.r).tolist()}, u in '
            f'[{self.core.u_min.tolist()}, {self.core.u_max.tolist()}], reference '
            f'{self.cfg.reference_kind}, pre-model input {self.cfg.pre_model_input}'
            + ('' if self.cfg.active else '; inactive until set_active'))

    # --- ticks ----------------------------------------------------------------------------

    def _on_y(self, msg: PlantOutput) -> None:
        start = time.perf_counter()
        core = self.core
        if (len(msg.y) != core.n_y or len(msg.u_applied) != core.n_u
                or not (all(map(math.isfinite, msg.y))
                        and all(map(math.isfinite, msg.u_applied)))):
            self._warn('ignored_y', f'ignored y of step {msg.step}: expected {core.n_y} '
                       f'finite outputs and {core.n_u} input, got {list(msg.y)}, '
                       f'{list(msg.u_applied)}')
            return
        core.observe(msg.step, msg.u_applied, msg.y, msg.theta)
        if core.nmpc_problem:
            self._warn_once([core.nmpc_problem])
        self._stamp = msg.header.stamp
        if msg.diverged and self.rule.diverged():
            self._stopped_by_itself(f'y of step {msg.step} is diverged')
        if self.rule.on_sample():
            self._answer(start)

    def _on_timer(self) -> None:
        if self.rule.on_tick():
            self._answer(time.perf_counter())

    def _answer(self, start: float) -> None:
        """Publish the input answering the newest y, then its MpcStatus (under a lockstep
        plant, once the model its adaptation request waits for is there)."""
        if self.core.waits_for_model():
            if self._hold_timer is None:
                self._hold_timer = self.create_timer(HOLD_POLL_S, self._on_hold,
                                                     clock=self._steady)
                # The plant waits as long as this answer may (the request is given up by
                # then), not its input_timeout: the swap stays exact.
                hold = self._hold_msg
                hold.header.stamp = self._stamp
                hold.step = self.core.history.step
                hold.hold_s = self.cfg.trigger.adapt_timeout
                self._pub_hold.publish(hold)
            return
        retuning = self._retuning
        if retuning is not None:
            # Under a lockstep plant the first tick after an accepted change uses it (the
            # plant waits meanwhile): a change accepted between the ticks of steps k and k+1
            # applies from step k+1 on, in every run alike. Otherwise no tick waits.
            plant = self.core.plant
            if retuning.done() or (plant is not None and plant.lockstep):
                retuning.result()
                self._retuning = None
        res = self.core.tick()
        msg = self._u_msg
        msg.header.stamp = self._stamp
        msg.step = res.step
        msg.u = _doubles(res.u)
        msg.model_version = res.model_version
        self._pub_u.publish(msg)
        if self.rule.answered(res.step):
            self._stopped_by_itself(f'answered step {res.step}')
        tick_time = time.perf_counter() - start
        self._publish_status(res, tick_time)
        for event in res.events:
            if not event.at_arrival:
                self._decided(res, event)
        self._counts['answered'] += 1
        self._counts['pre_model'] += res.iterations < 0
        self._counts['fallbacks'] += res.fallback

    def _decided(self, res: TickResult, event: GateEvent) -> None:
        """Say what the gate decided at this tick (a requested model's swap step, the end of
        its trial or probation)."""
        outcome, reason = event.outcome, event.reason
        if outcome is Outcome.REVERTED:
            self._counts['reverted_models'] += 1
            self.get_logger().error(f'reverted to model version {res.model_version} at step '
                                    f'{res.step}: {reason}')
        elif outcome is Outcome.REFUSED:
            self._counts['refused_models'] += 1
            self._counts['rejected_weights'] += 1
            self.get_logger().error(f'refused the model tried until step {res.step}: '
                                    f'{reason}; model in use: {res.model_version}')
        elif outcome is Outcome.ON_TRIAL:
            self.get_logger().info(f'model version {event.version} tried from step {res.step} '
                                   f'for {event.trial} samples')
        else:
            self.get_logger().info(f'model version {event.version} in use at step {res.step}'
                                   + (f': {reason}' if reason else ''))

    def _publish_status(self, res: TickResult, tick_time: float) -> None:
        status = self._status_msg
        status.header.stamp = self._stamp
        status.step = res.step
        status.cost = res.cost
        status.solve_time = res.solve_time
        status.tick_time = tick_time
        status.solver_status = res.solver_status
        status.iterations = res.iterations
        status.residual = res.residual
        status.fallback = res.fallback
        status.terminal_fallback = res.terminal_fallback
        status.disturbance = _doubles(res.disturbance)
        status.output_slack = res.slack
        status.model_version = res.model_version
        status.config_version = res.config_version
        status.planner = res.planner
        status.model_status = res.model_status
        status.model_events = [_event_message(e) for e in res.events]
        status.failed_linearisations = res.failed_linearisations
        status.u_plan = _doubles(res.u_plan)
        status.y_pred = _doubles(res.y_pred)
        status.y_ref = _doubles(res.y_ref)
        status.q = res.q
        (status.prediction_error, status.prediction_error_t,
         status.output_change_t) = res.prediction_errors
        status.one_step_std = _doubles(res.one_step_std)
        if res.rls_event:
            self.get_logger().warning(res.rls_event)
        request = res.request
        status.adapt_request = request is not None
        status.adapt_trigger = request.trigger if request is not None else ''
        status.swap_step = request.swap_step if request is not None else 0
        status.detector_statistic, status.detector_baseline = res.detector
        self._pub_status.publish(status)
        if request is not None:
            self._watch_request(request)
            self._counts['adapt_requests'] += 1
            self.get_logger().info(
                f'adaptation request at step {request.step} ({request.trigger}, model '
                f'version {request.version}; CUSUM {res.detector[0]:.2f}, baseline '
                f'{res.detector[1]:.3g}); under lockstep the answer of step '
                f'{request.swap_step} waits for it')

    def _stopped_by_itself(self, why: str) -> None:
        """A bounded activation ended (the rule is inactive now): say why."""
        self.get_logger().info(f'inactive by itself: {why}')

    def _on_set_active(self, request: SetActive.Request, response: SetActive.Response
                       ) -> SetActive.Response:
        answer_now = self.rule.set_active(request.active, request.until_step,
                                          request.stop_at_escape)
        response.success = True
        if not request.active and request.wait_delivered:
            # Reliable readers outside the loop (the recorder) may be behind a fast lockstep
            # run; the answers they have not acknowledged die with this process if it is
            # stopped next (seen: 6 of a run's 300 u missing from a recording). A caller about
            # to stop the node waits here until they are delivered (up to the middleware's
            # next acknowledgement round: about 2.7 s measured, so not on every deactivation).
            response.delivered = all(pub.wait_for_all_acked(DELIVERY_TIMEOUT)
                                     for pub in (self._pub_u, self._pub_status))
        response.answered_step = -1
        if answer_now:
            self._answer(time.perf_counter())
            response.answered_step = self.core.history.step
        # The orchestrator reads the version to know the model for the next tick is ready.
        model = self.core.model
        response.model_version = model.version if model is not None else 0
        # Matched from our side: an input published before the plant's u subscription matched
        # never reaches it, and a lockstep plant would wait for it forever. Callers wait on it.
        response.matched_subscribers = self._pub_u.get_subscription_count()
        response.matched_status_subscribers = self._pub_status.get_subscription_count()
        # Which sample an activation would answer: a caller activates once it is the one meant.
        if self._stamp is not None:
            response.latest_step, response.latest_stamp = self.core.history.step, self._stamp
        else:
            response.latest_step = -1
        response.message = (('active' if request.active else 'inactive: publishing nothing')
                            + (f', answered step {response.answered_step}' if answer_now
                               else '') + f'; model version {response.model_version}')
        self.get_logger().info(f'set_active: {response.message}')
        return response

    # --- configuration from other nodes ---------------------------------------------------

    def _on_plant_info(self, msg: PlantInfo) -> None:
        bounds = list(msg.u_min) + list(msg.u_max)
        if not (all(map(math.isfinite, bounds)) and msg.dt > 0
                and math.isfinite(msg.dt) and len(msg.u_min) == len(msg.u_max)):
            self.get_logger().warning(f'ignored plant_info with dt={msg.dt}, bounds '
                                      f'{list(msg.u_min)}, {list(msg.u_max)}')
            return
        warnings = self.core.set_plant(PlantDescription.of(msg))
        self.rule.lockstep = msg.clock_mode == 'lockstep'
        self._warn_once(warnings)

    def _warn_once(self, warnings) -> None:
        """Log each warning about the plant once, not at every reset or sample."""
        for text in set(warnings) - self._plant_warnings:
            self.get_logger().warning(text)
        self._plant_warnings.update(warnings)

    def _on_reference(self, msg: Float64MultiArray) -> None:
        error = self.core.set_override(msg.data)
        if error:
            self.get_logger().warning(f'ignored reference message: {error}')
        else:
            self.get_logger().info(f'reference override: {list(msg.data)}' if len(msg.data)
                                   else f'reference: back to {self.cfg.reference_kind}')

    def _on_params(self, config: ControllerConfig, changes: dict) -> None:
        """An accepted live change (checked by parse_params and core.check_tuning): the
        builder thread builds its QP, in order with the models, and swaps it in."""
        self.cfg = config
        self._config_version += 1
        self._retuning = self._builder.submit(self._retune, config, self._config_version,
                                              changes)

    def _retune(self, config: ControllerConfig, version: int, changes: dict) -> None:
        """Build the tuning's QP on the builder thread; the next tick uses it."""
        start = time.perf_counter()
        try:
            self.core.retune(config, version)
        except Exception as err:    # check_tuning makes this a bug: say so, keep the old one
            self.get_logger().error(f'parameters {changes} accepted but not applied '
                                    f'({type(err).__name__}: {err}); config version '
                                    f'{self.core.tuning.version} stays in use')
            return
        self._counts['retunes'] += 1
        self.get_logger().info(
            f'parameters {", ".join(f"{k}={v}" for k, v in changes.items())}: config '
            f'version {version} in use from the next tick (built in '
            f'{1e3 * (time.perf_counter() - start):.1f} ms)')

    def _on_hold(self) -> None:
        """An answer waits for a requested model (lockstep): answer once the builder thread
        has queued it, or once the request was given up (:meth:`_watch_request`)."""
        if self.core.waits_for_model():
            return
        self.destroy_timer(self._hold_timer)
        self._hold_timer = None
        if self.rule.active and self.rule.unanswered:
            self._answer(time.perf_counter())

    def _watch_request(self, request: Request) -> None:
        """Give `request` up after adapt_timeout s of wall time if no model answered it by
        then (in either clock mode: an unanswered request blocks the next ones)."""
        def expire():
            self.destroy_timer(timer)
            # Not if answered (or given up) already, or its answer is queued, tried or on
            # probation.
            if self.core.gate.time_out(request):
                self._gave_up('adapt_timeouts', f'no model answered the adaptation request of '
                              f'step {request.step} within {self.cfg.trigger.adapt_timeout} s: '
                              f'going on with model version {request.version}')
        timer = self.create_timer(self.cfg.trigger.adapt_timeout, expire, clock=self._steady)

    def _on_refusal(self, msg: AdaptRefusal) -> None:
        """The learner cannot answer the request of msg.request_step: give it up now."""
        request = self.core.gate.learner_refused(msg.request_step)
        if request is not None:
            self._gave_up('adapt_refusals', f'the learner refused the adaptation request of '
                          f'step {msg.request_step} ({msg.reason}): going on with model '
                          f'version {request.version}')

    def _gave_up(self, counter: str, text: str) -> None:
        """The pending request ended: say why; an answer waiting for it goes on now."""
        self._warn(counter, text)
        if self._hold_timer is not None:
            self._on_hold()

    def _on_weights(self, msg: NssmWeights) -> None:
        """Hand the weights to the builder thread (arrival order is kept)."""
        self._builder.submit(self._build, msg)

    def _build(self, msg: NssmWeights) -> None:
        """Build a model on the builder thread and offer it to the core's gate."""
        core = self.core
        try:    # with the latest tuning: retune() runs on this thread too, in order
            bundle = build_model(model_from_fields(fields_of(msg)), msg.version, msg.method,
                                 msg.stage, core.config.mpc, core.n_u, core.n_y,
                                 core.config.history)
        except WeightsError as err:
            self._refused(msg, core.refuse(msg.version, msg.request_step, str(err)))
            return
        except Exception as err:    # a bug, not bad weights: say so, never lose it silently
            self._refused(msg, core.refuse(msg.version, msg.request_step,
                                           f'{type(err).__name__}: {err}'))
            return
        event = core.offer(bundle, msg.request_step)
        if event.outcome is Outcome.REFUSED:
            self._refused(msg, event)
            return
        self._counts['models'] += 1
        if event.outcome is Outcome.FLEW:
            when = 'in use from the next tick'
        else:
            where = f'step {event.start}' if event.start else 'the next tick'
            when = (f'tried from {where} for {event.trial} samples, in use after if it passes '
                    f'the check' if event.trial else f'in use from {where}')
            when += f' (it answers the request of step {msg.request_step})'
        self.get_logger().info(f'model version {msg.version} ({msg.method}, {msg.stage}) {when}; '
                               f'{bundle.describe()}')

    def _refused(self, msg: NssmWeights, event: GateEvent) -> None:
        """The model in use stays; the event (published with the next status) says why, and
        one log line."""
        self._counts['refused_models'] += event.cause is Cause.CHECK
        self._counts['rejected_weights'] += 1
        model = self.core.model
        kept = model.version if model is not None else 'none'
        self.get_logger().error(f'rejected weights version {msg.version} ({msg.method}, '
                                f'{msg.stage}): {event.reason}; model in use: {kept}')

    def destroy_node(self) -> None:
        """Destroy the node, then log what was counted over the run."""
        self._builder.shutdown(wait=False, cancel_futures=True)
        super().destroy_node()
        # After destruction on purpose, as the plant does: works after a SIGINT too.
        step = self.core.history.step
        self.get_logger().info(
            ('stopped before any sample: ' if step is None else f'stopped at step {step}: ')
            + self._events.summary())


def _event_message(event: GateEvent) -> ModelEvent:
    """The gate's event as MpcStatus carries it (metampc_msgs/ModelEvent)."""
    verdict = event.verdict
    return ModelEvent(outcome=event.outcome.value, version=event.version,
                      request_step=event.request_step, cause=event.cause.value,
                      candidate_error=verdict.candidate if verdict is not None else math.nan,
                      reference_error=verdict.reference if verdict is not None else math.nan,
                      start_step=event.start, trial=event.trial, reason=event.reason)


def main(args=None) -> int:
    """`ros2 run metampc_controller controller [--ros-args -p name:=value ...]`."""
    return run_node(ControllerNode, 'controller', args, executor=loop_executor)


if __name__ == '__main__':
    sys.exit(main())
