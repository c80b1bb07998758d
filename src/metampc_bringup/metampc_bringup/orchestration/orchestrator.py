"""The experiment of the paper, run on the ROS 2 graph: one bring-up and one recording per seed.

For each seed (:class:`SeedRun`), in a ROS domain of its own: start the recorder, learner,
plant (lockstep) and controllers, waiting on their services and the recorder's subscriptions
(no sleeps); **collect** D_target with the excitation input; **meta-train** each meta method
(Algorithm 1: eqs. (inner_imaml), (outer), (Qb), (cg) for iMAML, (outer_maml) for MAML; the
true-model NMPC tracks meanwhile); per method **adapt** (eq. (infer)) and **track** for
``track_duration`` s; stop the nodes, recorder last, and analyse the recording
(:mod:`metampc_bringup.analysis.experiment_report`). Every phase publishes an event
(:mod:`metampc_bringup.experiment_events`), so the report comes from the recording alone.
Ctrl-C (SIGINT) or SIGTERM stops the nodes in the same order, leaving no process and a
readable recording. The steps in full: docs/experiments.md.
"""
import contextlib
import json
import logging
import math
import os
import signal
import threading
import time
from typing import Any, Callable, Dict, Iterator, List, Optional

from metampc_bringup import experiment_events as events
from metampc_bringup.experiment_config import ExperimentConfig, learner_method
from metampc_bringup.orchestration.experiment_client import (ExperimentClient, ExperimentError,
                                                             process_status, response_dict,
                                                             time_seconds)
from metampc_bringup.orchestration.processes import ProcessGroup, StopTimeout
from metampc_msgs.srv import Adapt, MetaTrain, ResetPlant
from metampc_recording.recorder_config import RecorderConfig
from tqdm import tqdm

log = logging.getLogger('metampc.orchestrator')

RECORDED_TOPICS = ('y', 'u', 'mpc_status', 'nssm_weights', 'progress', 'plant_info',
                   events.EVENTS_TOPIC)
RECORDING = 'recording.mcap'
CONTROLLERS = {'controller': 'set_active', 'controller_nmpc': 'set_active_nmpc'}
MAX_COLLECT_ESCAPES = 20
MAX_EPISODE_STARTS = 5
EPISODE_START_S = 3.0   # wall time for the controller to receive y_0 after a reset
Y0_POLL_S = 0.02         # how often to ask the controller for its newest y meanwhile
MATCH_POLL_S = 0.1       # how often to ask whether a node's side has matched the plant
_META_RESULT = ['model_version', 'final_loss', 'loss_curve', 'message']
_ADAPT_RESULT = ['model_version', 'loss_before', 'loss_after', 'loss_curve', 'message',
                 'fallback']


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt in the main thread, as Ctrl-C does, while inside."""
    def handler(signum, frame):
        raise KeyboardInterrupt(f'signal {signum}')
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block ends, then raise KeyboardInterrupt: a stop that
    has begun is not cut halfway (every node stopped, the recording finished). A signal its
    previous handler ignored stays ignored. Only in the main thread (elsewhere: no change)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: List[int] = []

    def handler(signum, frame):
        if previous[signum] is not signal.SIG_IGN:
            caught.append(signum)
    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    if caught:
        raise KeyboardInterrupt(f'signal {caught[0]}')


class SeedRun:
    """One seed of an experiment: bring-up, phases, shut-down; the recording in `out_dir`.

    Args:
        config: the experiment (validated).
        seed: this run's seed (node seeds, target theta).
        out_dir: the seed's folder (created; must not hold a recording yet).
        progress: show progress bars (tqdm) on stderr.
        prefix: per node name ('recorder', 'learner', 'plant', 'controller',
            'controller_nmpc'), a command to start it under (e.g. ``ip netns exec host1``).
        foxglove_port: also start the Foxglove live view (docs/foxglove.md) on this port.
    """

    def __init__(self, config: ExperimentConfig, seed: int, out_dir: str,
                 progress: bool = True, prefix: Optional[Dict[str, List[str]]] = None,
                 foxglove_port: Optional[int] = None):
        self.config = config
        self.foxglove_port = foxglove_port
        self.seed = seed
        self.out_dir = out_dir
        self.theta = config.target_theta(seed)
        self.show_progress = progress
        self.prefix = prefix or {}
        self.recording = os.path.join(out_dir, RECORDING)
        self.timings: Dict[str, float] = {}
        self.procs: Dict[str, Any] = {}
        self.client: Optional[ExperimentClient] = None
        self.restarts = 0       # episodes restarted because a controller missed y_0

    # --- bring-up and shut-down ------------------------------------------------------------

    def run(self) -> Dict[str, Any]:
        """Run every phase; return what happened (also in the recording's events)."""
        os.makedirs(os.path.join(self.out_dir, 'logs'), exist_ok=True)
        group = ProcessGroup(os.path.join(self.out_dir, 'logs'))
        started = time.monotonic()
        try:
            self._bring_up(group)
            self._phases()
        finally:
            # A Ctrl-C that lands here (seen: a seed at its normal end) waits for the stop:
            # cut halfway it left a recording without its end and once aborted the process.
            with interrupts_deferred():
                if self.client is not None:
                    self.client.close()
                # Newest first: controllers, plant, learner, then the recorder finishes its file.
                group.stop_all(timeout=20.0)
            self.timings['total'] = time.monotonic() - started
        return {'seed': self.seed, 'theta': self.theta, 'recording': self.recording,
                'timings': self.timings}

    def _start(self, group: ProcessGroup, name: str, pkg: str, exe: str,
               params: Dict[str, Any], remaps: Optional[Dict[str, str]] = None) -> None:
        self.procs[name] = group.start(pkg, exe, params, remaps=remaps, name=name,
                                       prefix=self.prefix.get(name, ()))

    def _bring_up(self, group: ProcessGroup) -> None:
        config, seed = self.config, self.seed
        t0 = time.monotonic()
        if os.path.exists(self.recording):
            raise ExperimentError(f'{self.recording} exists; choose a new output folder')
        run_config = {'experiment': config.to_dict(), 'seed': seed, 'theta': self.theta,
                      'tracked_outputs': list(config.tracked_outputs)}
        recorder = RecorderConfig(output=self.recording, topics=list(RECORDED_TOPICS),
                                  metadata_json=json.dumps(run_config), **config.recorder)
        self._start(group, 'recorder', 'metampc_recording', 'recorder', recorder.to_parameters())
        if self.foxglove_port is not None:
            self._start(group, 'foxglove', 'metampc_recording', 'foxglove',
                        {'port': self.foxglove_port})
        self._start(group, 'learner', 'metampc_learner', 'learner',
                    config.node_parameters('learner', seed))
        self._start(group, 'plant', 'metampc_plant', 'plant',
                    config.node_parameters('plant', seed))
        controller = config.node_parameters('controller', seed)
        controllers = {'controller': 'set_active'}
        self._start(group, 'controller', 'metampc_controller', 'controller',
                    {**controller, 'planner': 'latent_mpc', 'pre_model_input': 'excitation'})
        if 'nmpc' in config.methods:
            controllers['controller_nmpc'] = CONTROLLERS['controller_nmpc']
            self._start(group, 'controller_nmpc', 'metampc_controller', 'controller',
                        {**controller, 'planner': 'nmpc'},
                        remaps={'set_active': CONTROLLERS['controller_nmpc']})
        self.client = ExperimentClient(controllers, lambda: process_status(self.procs))
        subscribers = {topic: ['recorder'] for topic in RECORDED_TOPICS}
        subscribers['y'] += ['learner', *controllers]
        subscribers['u'] += ['plant']
        self.client.wait_ready(subscribers, config.timeouts.startup)
        for name in controllers:
            self._wait_outputs_matched(name, len(subscribers['u']),
                                       len(subscribers.get('mpc_status', ())),
                                       t0 + config.timeouts.startup)
        self.timings['startup'] = time.monotonic() - t0
        self.client.event(events.Start(seed=seed, theta=self.theta, methods=config.methods,
                                       nodes=sorted(self.procs)))
        log.info('seed %d: graph ready in %.1f s (theta* = %s)', seed,
                 self.timings['startup'], ', '.join(f'{v:.4f}' for v in self.theta))

    # --- phases ----------------------------------------------------------------------------

    def _phases(self) -> None:
        config = self.config
        self._timed('collect', self._collect)
        # The true-model NMPC's tracking needs no model: it runs while the learner trains the
        # first meta-model (the plant idles then), not after every other phase.
        nmpc_meanwhile = 'nmpc' in config.methods and bool(config.meta_methods())
        for i, method in enumerate(config.meta_methods()):
            meanwhile = self._track_nmpc if nmpc_meanwhile and i == 0 else None
            self._timed(f'meta_train_{method}', self._meta_train, method, meanwhile)
        kept = self._stop_buffering()
        self.client.event(events.BufferingStopped(kept=kept.kept, skipped=kept.skipped,
                                                  lost=kept.lost))
        if kept.lost or kept.kept < config.target_samples:
            log.warning('seed %d: the learner kept %d of the %d target samples (%d never '
                        'reached it)', self.seed, kept.kept, config.target_samples, kept.lost)
        if config.scenario == 'drift':
            if 'nmpc' in config.methods and not nmpc_meanwhile:
                self._track_nmpc()
            self._drift_runs()
        for method in config.methods if config.scenario == 'adapt_once' else ():
            if method == 'nmpc':
                if not nmpc_meanwhile:
                    self._track_nmpc()
                continue
            version = self._timed(f'adapt_{method}', self._adapt, method)
            self._timed(f'track_{method}', self._track, method, 'controller', version)
        # The nodes are stopped next, controllers first: their answers must have reached the
        # recorder by then.
        self.client.deliver_and_deactivate('controller', f'seed {self.seed}')
        self.client.event(events.Done(timings=self.timings, episode_restarts=self.restarts))

    def _schedule(self) -> List[float]:
        """The plant's theta_schedule of a drift run for this seed's theta* (paper: none)."""
        if self.config.scenario != 'drift':
            return []
        return self.config.drift_config().theta_schedule(self.theta)

    def _drift_runs(self) -> None:
        """Scenario drift: per method and adaptation mode, a fresh adaptation (the same model
        every time: the same D_target and meta-model), then a tracking run under the schedule
        with the controller's ``adaptation`` set to the mode; and with ``constant_check`` a
        triggered run at constant theta*, whose adaptations are spurious."""
        drift = self.config.drift_config()
        runs = [(mode, self._schedule()) for mode in drift.modes]
        if drift.constant_check:
            runs.append(('constant', []))
        for method in drift.methods:
            for mode, schedule in runs:
                run = f'{method}/{mode}'
                version = self._timed(f'adapt_{run}', self._adapt, method)
                adaptation = 'triggered' if mode == 'constant' else mode
                self.client.set_parameters(
                    'controller', {'adaptation': 'off' if mode == 'none' else adaptation},
                    f'{run}: the controller\'s adaptation mode')
                self._timed(f'track_{run}', self._track, method, 'controller', version, run,
                            schedule)

    def _timed(self, name: str, fn, *args):
        t0 = time.monotonic()
        result = fn(*args)
        self.timings[name] = time.monotonic() - t0
        log.info('seed %d: %s done in %.1f s', self.seed, name, self.timings[name])
        return result

    def _bar(self, total: int, desc: str) -> 'PhaseProgress':
        return PhaseProgress(total, f'seed {self.seed} {desc}', self.show_progress)

    def _start_episode(self, x0: List[float], controller: str, what: str,
                       steps: int = 0, schedule: List[float] = ()) -> float:
        """Reset the plant to theta*, x0 and activate `controller` on the new episode;
        return the stamp of its y_0. ``steps`` > 0 bounds the run: the controller answers
        steps 0..steps-1 and stops by itself (so the plant stops at y_steps), or at a
        diverged y, unanswered (a fast lockstep loop would otherwise run on while the
        orchestrator looks, and how far would depend on timing).

        The controller is activated once it has received this y_0 (its newest y, asked inactive):
        activated before, it answers an older sample at once, and an older y_0 (the one the
        plant sent at start-up) the plant takes for the answer to this one, since it matches
        inputs by step; the controller's answer to the new y_0 is then stale and the loop
        stalls (measured: 1 of 15 runs split over network namespaces on a loaded machine). A
        y_0 that never reaches the controller (sent before the plant's writer matched its
        subscription) restarts the episode (counted and logged). ``schedule``: the plant's
        theta_schedule of the episode (empty: constant theta*).
        """
        client = self.client
        for attempt in range(1, MAX_EPISODE_STARTS + 1):
            client.reset_counts()
            client.call('reset', ResetPlant.Request(theta=list(map(float, self.theta)),
                                                    x0=list(map(float, x0)),
                                                    theta_schedule=list(schedule)),
                        10.0, f'{what}: plant reset')
            client.wait_until(lambda: client.samples > 0 and client.last.step == 0, 10.0,
                              f'{what}: y_0 after the plant reset')
            start = client.last.stamp
            client.reset_counts()   # count the new episode only
            if self._receives_y0(controller, start):
                answered = client.set_active(
                    controller, True, until_step=max(steps - 1, 0),
                    stop_at_escape=steps > 0).answered_step
                if answered != 0:
                    raise ExperimentError(f'{what}: {controller} answered step {answered} on '
                                          'activation, not the y_0 it held')
                return start
            self.restarts += 1
            log.warning('seed %d: %s: %s missed y_0 (attempt %d); restarting the episode',
                        self.seed, what, controller, attempt)
        raise ExperimentError(f'{what}: {controller} never received y_0 in '
                              f'{MAX_EPISODE_STARTS} plant resets')

    def _receives_y0(self, controller: str, stamp: float) -> bool:
        """Whether the (inactive) `controller` receives the y_0 stamped `stamp` within
        EPISODE_START_S s of wall time."""
        return self.client.poll_inactive(
            controller, lambda a: a.latest_step == 0 and time_seconds(a.latest_stamp) == stamp,
            EPISODE_START_S, Y0_POLL_S)

    def _wait_outputs_matched(self, controller: str, readers_u: int, readers_status: int,
                              deadline: float) -> None:
        """Wait until `controller`'s u and mpc_status publishers have matched the `readers_u`
        subscriptions of u (the plant's, the recorder's) and the `readers_status` ones of
        mpc_status (the recorder's) from their own side.

        The graph lists a subscription before the publisher's side of the DDS match is
        complete; an input sent in between never reaches the plant, and a lockstep plant then
        waits for it forever (measured: with the nodes in three network namespaces, 1 of 17
        runs on a loaded 2-core machine stalled so at step 0); a status sent in between is
        missing from the recording (seen: the first 31 of a test's run beside a second suite).
        """
        if not self.client.poll_inactive(
                controller, lambda a: (a.matched_subscribers >= readers_u
                                       and a.matched_status_subscribers >= readers_status),
                max(deadline - time.monotonic(), 0.0), MATCH_POLL_S):
            raise ExperimentError(f"start-up: {controller}'s u and mpc_status publishers never "
                                  f'matched the {readers_u} subscriptions of u and the '
                                  f'{readers_status} of mpc_status within '
                                  f'{self.config.timeouts.startup:g} s')

    def _start_buffering(self) -> None:
        """Start the learner's D_target once its y subscription has matched the plant.

        The graph lists a subscriber before its side of the DDS match is complete; samples
        published in between never reach it (measured: a learner in another network namespace
        kept 119 of 120 collected samples). The learner reports its matched publishers.
        """
        deadline = time.monotonic() + self.config.timeouts.startup
        while True:
            if self.client.set_buffering(True, 'collect: start buffering').matched_publishers:
                return
            if time.monotonic() > deadline:
                raise ExperimentError("collect: the learner's y subscription never matched "
                                      f'the plant within {self.config.timeouts.startup:g} s')
            time.sleep(MATCH_POLL_S)

    def _stop_buffering(self):
        """Stop the learner's D_target once it holds the collection (its buffer's capacity is
        target_samples: the first ones), asking again while it is still taking them in (right
        after the collection, with no meta-training before, it had kept half of them); after
        the phase timeout it stops with what it has. Its last answer (counts)."""
        client, least = self.client, self.config.target_samples
        deadline = time.monotonic() + self.config.timeouts.phase
        while True:
            answer = client.set_buffering(False, 'collect: stop buffering',
                                          least=0 if time.monotonic() > deadline else least)
            if answer.success:
                return answer
            time.sleep(MATCH_POLL_S)

    def _collect(self) -> None:
        """D_target: `target_samples` samples under the exploration input, before any model."""
        client, config = self.client, self.config
        self._start_buffering()
        valid, escapes = 0, 0
        with self._bar(config.target_samples, 'collect') as bar:
            while valid < config.target_samples:
                # Bounded like a tracking run: y_1..y_need, or up to the first diverged y.
                need = config.target_samples - valid
                start = self._start_episode(config.collect_x0, 'controller', 'collect', need)
                if not valid:
                    client.event(events.CollectStart(stamp=start, theta=self.theta))
                client.wait_until(lambda: client.last.step >= need or client.last.diverged,
                                  config.timeouts.phase, 'collect: target samples',
                                  tick=lambda: bar.show(valid + client.last.step))
                client.set_active('controller', False)
                last = client.last      # the episode's final sample: the plant waits there
                valid += min(last.step - 1 if last.diverged else last.step, need)
                if last.diverged and valid < config.target_samples:
                    escapes += 1
                    if escapes > MAX_COLLECT_ESCAPES:
                        raise ExperimentError(f'collect: the plant escaped {escapes} times '
                                              'under the exploration input; lower '
                                              'controller.excitation_amplitude')
                    log.warning('seed %d: the plant escaped while collecting; reset',
                                self.seed)
        client.event(events.CollectEnd(stamp=client.last.stamp, samples=valid,
                                       escapes=escapes))

    def _track_nmpc(self) -> None:
        """The NMPC's tracking run, then its controller is stopped: left running it would take
        every later y (and /clock) for nothing, CPU that the lockstep loops of the other
        methods need on a 2-core machine. Scenario drift: under the schedule, the NMPC told
        theta at every step (from each y)."""
        self._timed('track_nmpc', self._track, 'nmpc', 'controller_nmpc', 0, 'nmpc',
                    self._schedule())
        self.client.deliver_and_deactivate('controller_nmpc', f'seed {self.seed}')
        proc = self.procs.pop('controller_nmpc')
        try:
            code = ProcessGroup.interrupt(proc, timeout=20.0)
        except StopTimeout as err:
            log.warning('seed %d: controller_nmpc did not stop after its run; killed: %s',
                        self.seed, err)
            return
        if code != 0:
            log.warning('seed %d: controller_nmpc exited with status %d after its run '
                        '(log: %s)', self.seed, code, proc.log_path)

    def _meta_train(self, method: str, meanwhile: Optional[Callable[[], None]] = None) -> None:
        """Meta-train `method`; `meanwhile` runs while the learner trains (the request is out
        first; the lockstep plant and the training share nothing, so the results are those
        of the phases one after the other)."""
        client, config = self.client, self.config
        fields = config.meta_request(method)
        name, model_class = learner_method(method)
        request = MetaTrain.Request(method=name, model_class=model_class, **fields)
        client.progress = None
        started = time.monotonic()
        call = client.start('meta_train', request)
        if meanwhile is not None:
            try:
                meanwhile()
            except BaseException:
                call.cancel()
                raise
        with self._bar(request.iterations or 0, f'meta_train {method}') as bar:
            response = client.finish(
                call, max(config.timeouts.meta_train - (time.monotonic() - started), 0.0),
                f'meta_train {method}',
                tick=lambda: _show_progress(bar, client.progress, 'meta_train'))
        client.event(events.MetaTrained(method=method, request=fields,
                                        **response_dict(response, _META_RESULT)))

    def _adapt(self, method: str) -> int:
        client, config = self.client, self.config
        fields = config.adapt_request(method)
        name, model_class = learner_method(method)
        response = client.call('adapt', Adapt.Request(method=name, model_class=model_class,
                                                      **fields),
                               config.timeouts.adapt, f'adapt {method}')
        client.event(events.Adapted(method=method, request=fields,
                                    **response_dict(response, _ADAPT_RESULT)))
        client.wait_model('controller', response.model_version, 30.0)
        return response.model_version

    def _track(self, method: str, controller: str, version: int, run: str = '',
               schedule: List[float] = ()) -> None:
        """One tracking run: steps 0..n of a fresh episode from track_x0 (scenario drift:
        ``drift.duration`` s with the plant's theta `schedule`; `run` names it)."""
        client, config = self.client, self.config
        run = run or method
        duration = (config.drift_config().duration if config.scenario == 'drift'
                    else config.track_duration)
        n = int(round(duration / config.dt))
        start = self._start_episode(config.track_x0, controller, f'track {run}', n, schedule)
        client.event(events.TrackStart(method=method, run=run, controller=controller,
                                       model_version=version, stamp=start, steps=n,
                                       theta_schedule=schedule))
        with self._bar(n, f'track {run}') as bar:
            client.wait_until(lambda: client.last.step >= n or client.last.diverged,
                              config.timeouts.phase, f'track {run}',
                              tick=lambda: bar.show(client.last.step))
        client.set_active(controller, False)
        # The controller stopped by itself at y_n or at the first diverged y (the newest
        # sample, since the plant waits there), however late this loop saw it.
        last = client.last
        steps, diverged = min(last.step, n), last.diverged
        client.event(events.TrackEnd(method=method, run=run, stamp=start + steps * config.dt,
                                     steps=steps, diverged=diverged))
        if diverged:
            log.warning('seed %d: %s let the plant escape at step %d', self.seed, run, steps)


class PhaseProgress:
    """A phase's progress: a tqdm bar, or without one (``--no-progress``, logs of a CI run) a
    log line at most every LOG_PERIOD_S, so a long phase never looks hung."""

    LOG_PERIOD_S = 30.0

    def __init__(self, total: int, desc: str, bar: bool):
        self.desc = desc
        self.bar = tqdm(total=total, desc=desc, unit='step', leave=False, disable=not bar,
                        dynamic_ncols=True)
        self.loss = math.nan
        self._logged = time.monotonic()

    def __enter__(self) -> 'PhaseProgress':
        return self

    def __exit__(self, *exc) -> None:
        self.bar.close()

    def show(self, value: int, total: int = 0, loss: float = math.nan) -> None:
        """Progress is `value` steps (of `total`, when it changes) with the latest `loss`."""
        bar = self.bar
        if total and bar.total != total:
            bar.reset(total=total)
        if math.isfinite(loss):
            self.loss = loss
            bar.set_postfix(loss=f'{loss:.3g}', refresh=False)
        bar.update(max(0, min(value, bar.total or value) - bar.n))
        if bar.disable and time.monotonic() - self._logged >= self.LOG_PERIOD_S:
            self._logged = time.monotonic()
            log.info('%s: %d/%s%s', self.desc, min(value, bar.total or value), bar.total or '?',
                     f', loss {self.loss:.4g}' if math.isfinite(self.loss) else '')


def _show_progress(bar: PhaseProgress, progress, phase: str) -> None:
    if progress is not None and progress.phase == phase:
        bar.show(progress.iteration, progress.total, progress.loss)
