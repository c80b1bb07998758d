"""The `learner` node: a thin ROS 2 adapter over LearnerSession.

Buffers target samples from ``y`` into D_target (:class:`TargetBuffer`, ``set_buffering``),
serves ``meta_train`` (Algorithm 1, eq. (outer)) and ``adapt`` (eq. (infer), or the
'supervised' / 'oracle' baselines) and publishes every model it makes on the latched
``nssm_weights`` (:mod:`metampc_model.weights_codec`) and job heartbeats on ``progress``; with
``loop_adaptation`` it answers the controller's ``adapt_request`` on ``mpc_status``
(:mod:`metampc_learner.loop_adaptation`). One training job at a time (:class:`JobSlot`); a
second is answered 'busy' at once. Refuses: a bad parameter, an unreadable
``meta_model_path`` or a plant whose dt is not ``dt`` (one error line, exit 2); a request it
cannot carry out (success=false, what is missing). Parameters: :data:`.learner_params.PARAMETERS`;
interfaces, threads and live request defaults: docs/learner.md.
"""
from concurrent.futures import ThreadPoolExecutor
import sys
import threading
import traceback
from typing import Any, Optional, Tuple

from metampc_common.node_main import declare_parameters, LiveParameters, run_node
from metampc_common.params import ParameterError
from metampc_common.qos import BACKLOG, LATCHED, SPARSE
from metampc_common.replies import Replies
from metampc_msgs.msg import (AdaptRefusal, MpcStatus, NssmWeights, PlantInfo, PlantOutput,
                              TrainingProgress)
from metampc_msgs.srv import Adapt, MetaTrain, SetBuffering
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
import torch

from metampc_learner.job_slot import JobCancelled, JobSlot, JobStatus
from metampc_learner.learner_params import (LearnerNodeConfig, parse_params, PARAMETERS,
                                            request_class, resolve_adapt_request,
                                            resolve_meta_request, resolve_narx_request)
from metampc_learner.learner_session import LearnerError, LearnerSession, ModelRecord
from metampc_learner.loop_adaptation import BEYOND_WINDOW, RecentSamples
from metampc_learner.meta_train import MetaTrainingError
from metampc_learner.target_buffer import TargetBuffer
from metampc_plant.plant_description import PlantDescription

# One thread trains, one answers a second request 'busy', one buffers y, one beats progress.
EXECUTOR_THREADS = 4
# Longest wait at shutdown for a running job to reach its next step and stop, s.
CANCEL_TIMEOUT_S = 10.0
# A service request waits this long for a running adaptation in the loop (seconds long)
# instead of being refused busy, s.
LOOP_JOB_WAIT_S = 60.0
# Longest wait of a loop adaptation for the sample of its request (its y may come after the
# controller's status: two publishers), s.
SAMPLE_WAIT_S = 5.0
# Errors of a request that cannot be carried out (the others are bugs: logged with traceback).
REQUEST_ERRORS = (LearnerError, MetaTrainingError, ValueError)


class LearnerNode(Node):
    """ROS 2 front end of one :class:`LearnerSession` (see the module docstring)."""

    def __init__(self):
        super().__init__('learner')
        values = declare_parameters(self, PARAMETERS)
        self.cfg = parse_params(values)
        torch.set_num_threads(self.cfg.torch_threads)
        self.session = LearnerSession(self.cfg)
        self.buffer = TargetBuffer(self.cfg.target_buffer_size)
        if not self.cfg.buffer_on_start:
            self.buffer.freeze()
        self._plant: Optional[PlantDescription] = None
        self._slot = JobSlot()
        self._progress_lock = threading.Lock()

        # Adaptation in the loop: the latest samples, and one worker that answers the
        # controller's requests beside the services and the subscriptions.
        loop = self.cfg.loop
        self._loop_window = loop.window or self.cfg.target_buffer_size
        self.recent = (RecentSamples(self._loop_window + BEYOND_WINDOW) if loop.adaptation
                       else None)
        self._loop_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix='loop_adapt')
        self._pub_weights = self.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
        self._pub_progress = self.create_publisher(TrainingProgress, 'progress', SPARSE)
        self._pub_refusal = self.create_publisher(AdaptRefusal, 'adapt_refusals', SPARSE)
        self._data = data = MutuallyExclusiveCallbackGroup()
        self._sub_y = None
        self._subscribe_y()
        self.create_subscription(PlantInfo, 'plant_info', self._on_plant_info, LATCHED,
                                 callback_group=data)
        replies = Replies(Future)   # a repeated request id: the first answer
        self.create_service(SetBuffering, 'set_buffering', replies.wrap(self._on_set_buffering),
                            callback_group=data)
        if self.recent is not None:
            self.create_subscription(MpcStatus, 'mpc_status', self._on_status, BACKLOG,
                                     callback_group=data)
        jobs = ReentrantCallbackGroup()
        self.create_service(MetaTrain, 'meta_train', replies.wrap_async(self._on_meta_train),
                            callback_group=jobs)
        self.create_service(Adapt, 'adapt', replies.wrap_async(self._on_adapt),
                            callback_group=jobs)
        self.create_timer(self.cfg.progress_period, self._on_heartbeat,
                          callback_group=MutuallyExclusiveCallbackGroup(),
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

        LiveParameters(self, PARAMETERS, values, self.cfg, parse_params, self._on_params)
        nssm, narx, src = self.cfg.nssm, self.cfg.narx, self.cfg.source
        if self.cfg.meta_model_path:
            try:
                record = self.session.load_meta(self.cfg.meta_model_path)
            except LearnerError as err:
                raise ParameterError(f'meta_model_path: {err}') from None
            self._publish_weights(record)
            self.get_logger().info(f'loaded {record.method} meta-model '
                                   f'{self.cfg.meta_model_path!r}: published as v{record.version}')
            # the model that adapts is the loaded one
            nssm, narx = ((nssm, record.model.shape) if self.cfg.model_class == 'feature_narx'
                          else (record.model.config, narx))
        model = (f'feature NARX p={narx.order}, F={narx.features}, features {list(narx.hidden)}'
                 if self.cfg.model_class == 'feature_narx' else
                 f'NSSM n_z={nssm.n_z}, H={nssm.history}, T={nssm.loss_horizon}, encoder '
                 f'{list(nssm.hidden)}')
        self.get_logger().info(
            f'learner up: {model}; {src.n_systems} source systems; D_target of '
            f'{self.buffer.capacity} samples, buffering '
            + ('on' if self.buffer.enabled else 'off until set_buffering true'))

    def _on_params(self, config: LearnerNodeConfig, changes: dict) -> None:
        """An accepted change of the request defaults: the next request resolves against it
        (a request reads the config once, as it starts)."""
        self.cfg = self.session.config = config
        self.get_logger().info('request defaults: '
                               + ', '.join(f'{k}={v}' for k, v in changes.items()))

    # --- data -----------------------------------------------------------------------------

    def _subscribe_y(self) -> None:
        if self._sub_y is None:
            self._sub_y = self.create_subscription(PlantOutput, 'y', self._on_y, BACKLOG,
                                                   callback_group=self._data)

    def _unsubscribe_y(self) -> None:
        """Stop taking y unless adaptation in the loop needs it: a sample nobody keeps costs
        its transport and deserialisation all the same (same callback group as _on_y)."""
        if self._sub_y is not None and self.recent is None:
            self.destroy_subscription(self._sub_y)
            self._sub_y = None

    def _on_y(self, msg: PlantOutput) -> None:
        if self.recent is not None:
            self.recent.add(msg.step, msg.u_applied, msg.y, msg.diverged)
        if self.buffer.add(msg.step, msg.u_applied, msg.y, msg.diverged) and self.buffer.full:
            self.get_logger().info(f'D_target full: {len(self.buffer)} samples '
                                   f'({self.buffer.skipped} skipped, {self.buffer.lost} lost)'
                                   + ('' if self.recent is not None else
                                      '; y unsubscribed until buffering restarts'))
            self._unsubscribe_y()

    def _on_plant_info(self, msg: PlantInfo) -> None:
        plant = PlantDescription.of(msg)
        try:
            self.session.check_plant(plant)
        except LearnerError as err:
            # Refuse at once (exit 2 through run_node), not at the first adapt.
            raise ParameterError(str(err)) from None
        self._plant = plant

    def _on_set_buffering(self, request: SetBuffering.Request, response: SetBuffering.Response
                          ) -> SetBuffering.Response:
        buffer = self.buffer
        if request.buffering:
            self._subscribe_y()
            response.cleared = buffer.start()
            response.message = (f'buffering (re)started: {response.cleared} samples cleared, '
                                f'keeping the next {buffer.capacity} valid samples')
        elif buffer.enabled and not buffer.full and len(buffer) < request.least:
            response.kept, response.skipped, response.lost = (len(buffer), buffer.skipped,
                                                              buffer.lost)
            response.capacity = buffer.capacity
            response.message = (f'buffering goes on: {len(buffer)} of the {request.least} '
                                f'samples asked for kept so far')
            return response         # success false: the caller asks again
        else:
            buffer.freeze()
            self._unsubscribe_y()
            response.message = (f'buffering stopped: {len(buffer)} samples kept '
                                f'({buffer.skipped} skipped, {buffer.lost} lost)')
        response.kept, response.skipped, response.lost = len(buffer), buffer.skipped, buffer.lost
        response.capacity = buffer.capacity
        # Matched from our side: samples published before that never reach us, and the
        # graph alone (a subscriber listed) does not say so. Callers wait on it (0 when
        # stopped: no subscription).
        response.matched_publishers = (self._sub_y.get_publisher_count()
                                       if self._sub_y is not None else 0)
        response.success = True
        self.get_logger().info(response.message)
        return response

    # --- publication ----------------------------------------------------------------------

    def _publish_weights(self, record: ModelRecord, request_step: int = 0) -> None:
        msg = NssmWeights(version=record.version, method=record.method, stage=record.stage,
                          train_loss=float(record.train_loss), train_steps=record.train_steps,
                          train_samples=record.train_samples, seed=record.seed,
                          train_time=float(record.train_time), request_step=request_step,
                          **record.fields())
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_weights.publish(msg)

    def _publish_progress(self, status: JobStatus) -> None:
        p = status.progress
        msg = TrainingProgress(phase=status.phase, method=status.method, iteration=p.iteration,
                               total=p.total, loss=float(p.loss), elapsed=float(p.elapsed),
                               skipped_tasks=p.skipped, cg_residual=float(p.cg_residual),
                               validation_loss=float(p.validation_loss),
                               rollbacks=p.rollbacks, best_iteration=p.best_iteration)
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_progress.publish(msg)

    def _on_heartbeat(self) -> None:
        with self._progress_lock:
            status = self._slot.current()
            if status is not None:
                self._publish_progress(status)

    # --- jobs -----------------------------------------------------------------------------

    def _refuse(self, response, message: str):
        response.success, response.message = False, message
        self.get_logger().warning(message)
        return response

    def _job(self, phase: str, method: str, total: int, train, what: str,
             request_step: int = 0) -> Tuple[Any, str, bool]:
        """Run train() as the claimed job: progress at its start and end, the model
        published (with `request_step`), the slot released. Returns (outcome or None, the
        message, cancelled).

        train() returns (outcome, record, message) or raises one of REQUEST_ERRORS (the
        message is then '`what` failed: ...'); it runs synchronously in the calling thread.
        A job cancelled by destroy_node publishes nothing more.
        """
        with self._progress_lock:
            self._publish_progress(self._slot.describe(phase, method, total))
        outcome, cancelled = None, False
        try:
            outcome, record, message = train()
        except JobCancelled:
            cancelled, message = True, f'{what} cancelled'
        except REQUEST_ERRORS as err:
            message = f'{what} failed: {err}'
            self.get_logger().warning(message)
        except Exception as err:  # a bug: say so, keep serving
            message = f'{what} failed: internal error {err!r}'
            self.get_logger().error(message + '\n' + traceback.format_exc())
        else:
            self._publish_weights(record, request_step)
            self.get_logger().info(message)
        with self._progress_lock:
            final = self._slot.release(outcome is not None)
            if final is not None and not cancelled:
                self._publish_progress(final)
        return outcome, message, cancelled

    async def _run(self, response, phase: str, method: str, total: int, train):
        """A service's job (:meth:`_job`): fill response.success/message, return the outcome.

        A job cancelled by destroy_node is never answered: the node and its services are being
        destroyed, and rclpy (Jazzy) has no deferred response, so the callback awaits a
        future that never completes instead of returning a response to a destroyed service.
        """
        outcome, message, cancelled = self._job(phase, method, total, train, phase)
        if cancelled:
            await Future()
        response.success, response.message = outcome is not None, message
        return outcome

    async def _on_meta_train(self, request: MetaTrain.Request, response: MetaTrain.Response
                             ) -> MetaTrain.Response:
        if not self._slot.claim_after('loop_adapt', LOOP_JOB_WAIT_S):
            return self._refuse(response, self._slot.busy_reason())
        try:
            narx = request_class(request, self.cfg) == 'feature_narx'
            config, online = ((resolve_narx_request(request, self.cfg.narx_meta, self.cfg.meta),
                               False) if narx else
                              resolve_meta_request(request, self.cfg.meta,
                                                   self.cfg.online_collection))
        except ValueError as err:
            self._slot.release(False)
            return self._refuse(response, f'meta_train: bad request: {err}')

        def train():
            out = self.session.meta_train(config, online, self._slot.report)
            rec = out.record
            inner = (f'closed-form heads, gamma {config.gamma:g}' if narx
                     else f'M={config.inner_steps}')
            text = (f'{rec.method} meta-model v{rec.version}: {config.iterations} outer steps '
                    f'(B={config.batch_size}, {inner}, seed {config.seed}) in '
                    f'{out.elapsed:.1f} s, final meta-test loss {out.final_loss:.4g}, '
                    f'{out.skipped} tasks skipped')
            if out.collection is not None:
                c = out.collection
                text += (f'; online collection: {c.samples} samples in {c.episodes} episodes '
                         f'({c.escaped} escaped, {c.model_failures} unusable models), '
                         f'{out.collected_samples} kept, {out.dropped_samples} dropped by the cap')
            return out, rec, text

        outcome = await self._run(response, 'meta_train', config.method, config.iterations, train)
        if outcome is not None:
            response.model_version = outcome.record.version
            response.final_loss = float(outcome.final_loss)
            response.loss_curve = [float(v) for v in outcome.losses]
        return response

    async def _on_adapt(self, request: Adapt.Request, response: Adapt.Response
                        ) -> Adapt.Response:
        if not self._slot.claim_after('loop_adapt', LOOP_JOB_WAIT_S):
            return self._refuse(response, self._slot.busy_reason())
        try:
            job = resolve_adapt_request(request, self.cfg.adapt, self.cfg.oracle,
                                        request_class(request, self.cfg))
        except ValueError as err:
            self._slot.release(False)
            return self._refuse(response, f'adapt: bad request: {err}')

        def train():
            out = self.session.adapt(job, self.buffer.snapshot(), self._plant, self._slot.report)
            rec, curve = out.record, out.result.heldout_loss
            source = ('samples of simulated target episodes' if rec.method == 'oracle'
                      else 'buffered target samples')
            how = f'closed-form fit ({out.rule})' if out.rule else f'{job.steps} steps'
            text = (f'{rec.method} model v{rec.version} (stage adapted): {how} on '
                    f'{out.train_samples} {source} in {out.result.elapsed:.1f} s, held-out loss '
                    f'{curve[0]:.4g} -> {curve[-1]:.4g} on {out.heldout_samples} samples')
            if out.gain_check:
                text += f'; {out.gain_check}'
            if out.replaced_by:
                text += (f': the {out.replaced_by} model of the same samples flies in its place '
                         f'(training loss {rec.train_loss:.4g})')
            return out, rec, text

        outcome = await self._run(response, 'adapt',
                                  job.method or self.session.latest.get(job.model_class, ''),
                                  job.steps, train)
        if outcome is not None:
            curve = [float(v) for v in outcome.result.heldout_loss]
            response.model_version = outcome.record.version
            response.loss_before, response.loss_after = curve[0], curve[-1]
            response.loss_curve = curve
            response.fallback = outcome.replaced_by
        return response

    # --- adaptation in the loop -----------------------------------------------------------

    def _on_status(self, msg: MpcStatus) -> None:
        if msg.adapt_request:
            self._loop_worker.submit(self._loop_adapt, msg.step, msg.model_version,
                                     msg.adapt_trigger)

    def _loop_adapt(self, step: int, version: int, trigger: str) -> None:
        """Answer the controller's request of `step` (worker thread): eq. (infer) on the
        latest window from model `version`, published with request_step = step. A request
        that cannot be served (busy, unknown version, too few samples, a window of an escaped
        or frozen plant) is logged and refused on ``adapt_refusals``: the controller then
        goes on with its model at once."""
        what = f'adaptation request of step {step} ({trigger}, model v{version})'
        if not self._slot.claim():
            self._refuse_request(step, f'{what} refused: {self._slot.busy_reason()}')
            return

        def train():
            if not self.recent.wait_for(step, SAMPLE_WAIT_S):
                raise LearnerError(f'sample {step} did not arrive within {SAMPLE_WAIT_S} s')
            why = self.recent.refusal(step, self._loop_window)
            if why:
                raise LearnerError(f'not adapted: {why}')
            out = self.session.loop_adapt(version, self.recent.until(step, self._loop_window),
                                          self._slot.report)
            rec, loss = out.record, out.result.train_loss
            return out, rec, (f'{what}: {rec.method} model v{rec.version} (stage online) on '
                              f'{out.train_samples} samples in {out.result.elapsed:.2f} s, '
                              f'window loss {loss[0]:.4g} -> {loss[-1]:.4g}')

        record = self.session.records.get(version)
        outcome, message, cancelled = self._job('loop_adapt', record.method if record else '',
                                                self.cfg.loop.steps, train, what,
                                                request_step=step)
        if outcome is None and not cancelled:
            self._refuse_request(step, message, logged=True)

    def _refuse_request(self, step: int, message: str, logged: bool = False) -> None:
        """Tell the controller that its request of `step` gets no answer (and why)."""
        if not logged:
            self.get_logger().warning(message)
        msg = AdaptRefusal(request_step=step, reason=message)
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_refusal.publish(msg)

    def stop_work(self) -> None:
        """Cancel a running job and wait for it to stop at its next step (run_node calls it
        before it waits for the callbacks in flight; idempotent)."""
        self._loop_worker.shutdown(wait=False, cancel_futures=True)
        if not self._slot.cancel(CANCEL_TIMEOUT_S):
            self.get_logger().warning(f'the running job did not stop within {CANCEL_TIMEOUT_S} s')

    def destroy_node(self) -> None:
        """Stop the work (:meth:`stop_work`), destroy the node."""
        self.stop_work()
        super().destroy_node()


def main(args=None) -> int:
    """`ros2 run metampc_learner learner [--ros-args -p name:=value ...]`; the exit code."""
    return run_node(LearnerNode, 'learner', args,
                    executor=lambda: MultiThreadedExecutor(num_threads=EXECUTOR_THREADS))


if __name__ == '__main__':
    sys.exit(main())
