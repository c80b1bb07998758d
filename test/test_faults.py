"""Fault-injection suite (issue 10): each fault case of the issue, one test each.

Every test starts the nodes it needs as real processes (`ros2 run`, in the session's own
domain), injects one kind of fault from the probe node or with a signal, and asserts the
documented outcome (docs/faults.md lists the cases and outcomes). Every test that runs nodes
ends with the same checks (:meth:`Rig.finish`):

* nothing crashed that was not killed: each node still runs when the test ends, exits 0 on
  SIGINT without a traceback and leaves no process behind (a killed one leaves none either);
* no NaN published: every ``y`` (output and applied input), ``u`` and ``mpc_status`` (planned
  inputs) the probe received from the nodes is finite;
* nothing recorded lost: where a recorder runs, its finished file holds every message of its
  topics that the probe received from the first one recorded on until the nodes are stopped
  (the recorded topics have one publisher for the whole test: a restarted publisher is matched
  anew by every subscriber, and what it sends before the recorder has matched it is not
  recorded, as with rosbag2; a sample published as its node is being stopped can go down with
  the node's writer, whose context SIGINT has shut down, before it reaches any subscriber).
"""
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Set

from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantInfo, PlantOutput
from metampc_msgs.srv import Adapt, MetaTrain, ResetPlant
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.integrate import solve_ivp

from metampc_bringup.orchestration.experiment_client import (ExperimentClient, ExperimentError,
                                                             process_status)
from metampc_recording.recorder_config import RecorderConfig
from metampc_recording.recording_reader import read_recording
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params
from metampc_model.nssm_config import NssmConfig
from metampc_model.weights_codec import fields_from_weights
from metampc_plant.simulator import Plant, PlantConfig
from metampc_testing import own_lines, session_pids

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
NAN, INF = float('nan'), float('inf')
TYPES = {'y': PlantOutput, 'u': ControlInput, 'mpc_status': MpcStatus}
CONTROLLER = {'use_sim_time': True, 'reference': 'setpoint', 'reference_values': [0.5]}
# The learner of test_learner_node, smaller still: seconds per job, ~0.1 s per outer step.
LEARNER = {'n_systems': 4, 'episodes_per_system': 1, 'episode_samples': 40, 'history': 3,
           'loss_horizon': 3, 'hidden': [16], 'n_z': 3, 'batch_size': 2, 'inner_steps': 2,
           'cg_steps': 2, 'windows_per_task': 8, 'torch_threads': 1, 'target_buffer_size': 40,
           'heldout_fraction': 0.25, 'progress_period': 0.25, 'buffer_on_start': False}


def weights(version: int, theta: float = 0.5, **model) -> NssmWeights:
    """The hand-built NSSM (the plant linearised at the origin, dt = 0.1) as a message."""
    config, norm, params = linearised_vdp_nssm(theta, 0.1, **model)
    return NssmWeights(version=version, method='manual', stage='adapted',
                       **fields_from_weights(config, norm, params))


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def finite(msg) -> bool:
    """The signals of a y (output, applied input), u (input) or mpc_status (planned inputs;
    its cost and prediction are NaN by design when the data were not finite) are finite."""
    if isinstance(msg, PlantOutput):
        values = [*msg.y, *msg.u_applied]
    else:
        values = msg.u if isinstance(msg, ControlInput) else msg.u_plan
    return all(math.isfinite(v) for v in values)


class Rig:
    """The processes of one fault case and what the probe hears of them.

    Args:
        procs: the test's ProcessGroup. probe: the test's TestNode.
        watch: topics the probe records; only the nodes may publish on them (the no-NaN check
            applies to everything received on them).
    """

    def __init__(self, procs, probe, tmp_path, watch: Sequence[str] = ('y', 'u', 'mpc_status')):
        self.procs = procs
        self.probe = probe
        self.tmp_path = tmp_path
        self.nodes: Dict[str, subprocess.Popen] = {}
        self.killed: Set[str] = set()
        self.heard: Dict[str, list] = {topic: [] for topic in watch}
        self._subs = {topic: probe.node.create_subscription(
            TYPES[topic], topic, self.heard[topic].append, RELIABLE) for topic in watch}
        self.recording: Optional[str] = None
        self.recorded_topics: List[str] = []
        self._announce = []

    @property
    def ys(self) -> list:
        return self.heard['y']

    def start(self, name: str, pkg: str, exe: str, params: dict) -> subprocess.Popen:
        self.nodes[name] = self.procs.start(pkg, exe, params=params, name=name)
        return self.nodes[name]

    def wait_matched(self, topic: str) -> None:
        """Until the probe's subscription of `topic` has matched a node's publisher.

        A node's publisher counts a reader as matched as soon as it has discovered it, which
        may be before the reader has matched the publisher: a sample published in between is
        lost to that (volatile) reader. A lockstep plant's start gate sees the former, so tests
        that must hear y_0 open the gate (a `u` publisher) only after this."""
        own = sum(pub.topic_name.lstrip('/') == topic for pub in self._announce)
        sub = self._subs[topic]
        self.probe.wait_for(lambda: sub.get_publisher_count() > own, 60.0,
                            f"the probe's {topic} subscription matched")

    def record(self, topics: Sequence[str], **params) -> subprocess.Popen:
        """Start a recorder of `topics` and wait until it has subscribed to each of them.

        The recorder subscribes to a topic once it has a publisher (it takes the type and the
        QoS from it): the probe announces each topic with a publisher that never publishes,
        so the recorder reads it before any node publishes on it.
        """
        self.recording = str(self.tmp_path / 'faults.mcap')
        self.recorded_topics = list(topics)
        node = self.probe.node
        self._announce = [node.create_publisher(TYPES[t], t, RELIABLE) for t in topics]
        config = RecorderConfig(output=self.recording, topics=list(topics), flush_period=0.1,
                                **params)
        proc = self.start('recorder', 'metampc_recording', 'recorder', config.to_parameters())

        def subscribed(topic):
            return any(i.node_name == 'recorder'
                       for i in node.get_subscriptions_info_by_topic('/' + topic))
        self.probe.wait_for(lambda: all(subscribed(t) for t in topics), 60.0,
                            f'the recorder to subscribe to {list(topics)}')
        return proc

    def kill(self, name: str) -> None:
        """SIGKILL the node's `ros2 run` and the node."""
        proc = self.nodes[name]
        self.procs.kill(proc)
        self.killed.add(name)
        self.probe.wait_for(lambda: session_pids(proc) == [], 10.0,
                            f'every process of the killed {name} gone')

    def wait_steps(self, n: int, timeout: float = 60.0) -> None:
        """Until the probe has received n more plant samples than now."""
        target = len(self.ys) + n
        self.probe.wait_for(lambda: len(self.ys) >= target, timeout, f'{n} more samples')

    def wait_status(self, predicate: Callable[[MpcStatus], bool], what: str,
                    timeout: float = 60.0) -> MpcStatus:
        status = self.heard['mpc_status']
        self.probe.wait_for(lambda: status and predicate(status[-1]), timeout, what)
        return status[-1]

    def output(self, name: str) -> str:
        return self.procs.output(self.nodes[name])

    def stop(self, name: str) -> str:
        """SIGINT one node: exit 0, no traceback, nothing left running; return its output."""
        proc = self.nodes[name]
        code = self.procs.interrupt(proc, timeout=30.0)
        out = self.procs.output(proc)
        assert code == 0 and 'Traceback' not in out, f'{name} exited with {code}:\n{out}'
        assert session_pids(proc) == [], f'a process of {name} outlived ros2 run'
        self.killed.add(name)   # stopped: not to be stopped again by finish()
        return out

    def finish(self) -> Dict[str, str]:
        """The checks of every case (module docstring); return each stopped node's output."""
        running = [name for name in self.nodes if name not in self.killed]
        for name in running:
            assert self.nodes[name].poll() is None, (
                f'{name} ended by itself (status {self.nodes[name].returncode}):\n'
                f'{self.output(name)}')
        heard = {topic: len(msgs) for topic, msgs in self.heard.items()}   # before any stop
        outputs = {name: self.stop(name) for name in reversed(running) if name != 'recorder'}
        for topic, msgs in self.heard.items():
            bad = [m for m in msgs if not finite(m)]
            assert not bad, f'{len(bad)} non-finite messages on {topic}, first: {bad[0]}'
        if 'recorder' in running:
            deadline = time.monotonic() + 30.0
            while self._unrecorded(heard=heard) and time.monotonic() < deadline:
                time.sleep(0.1)
            lost = self._unrecorded(heard=heard)
            assert not lost, f'heard but not recorded: {lost}'
            outputs['recorder'] = self.stop('recorder')
            recording = read_recording(self.recording)
            assert recording.complete, 'the stopped recorder did not finish its file'
            assert not self._unrecorded(recording, heard)
        return outputs

    def recorded(self, recording=None) -> Dict[str, list]:
        """Decoded messages per recorded topic (the unfinished file as it is now, if None)."""
        recording = recording or read_recording(self.recording)
        out = {topic: [] for topic in self.recorded_topics}
        for topic, _, msg in recording.decoded(['/' + t for t in self.recorded_topics]):
            out[topic.name[1:]].append(msg)
        return out

    def _unrecorded(self, recording=None, heard: Optional[Dict[str, int]] = None
                    ) -> Dict[str, str]:
        """Per recorded topic: messages heard from the first recorded one on (the first
        heard[topic] heard, if given), not recorded."""
        if not os.path.exists(self.recording):
            return {'(all)': 'no file yet'}
        missing = {}
        for topic, msgs in self.recorded(recording).items():
            if topic not in self.heard:
                continue
            keys = {(stamp_ns(m), m.step) for m in msgs}
            first = min(keys, default=(math.inf, 0))[0]
            upto = self.heard[topic][:(heard or {}).get(topic)]
            lost = [m for m in upto
                    if stamp_ns(m) >= first and (stamp_ns(m), m.step) not in keys]
            if lost or not keys:
                missing[topic] = (f'{len(lost)} of {len(self.heard[topic])} heard, '
                                  f'{len(msgs)} recorded')
        return missing


def start_loop(rig: Rig, plant: dict, controller: dict) -> None:
    """Controller first, plant once the graph shows the controller reading y: the plant's start
    gate then opens with the controller matched, and y_0 is answered."""
    rig.start('controller', 'metampc_controller', 'controller', {**CONTROLLER, **controller})
    rig.probe.wait_for(lambda: any(
        i.node_name == 'controller' for i in rig.probe.node.get_subscriptions_info_by_topic('/y')),
        60.0, 'the controller subscribed to y')
    rig.start('plant', 'metampc_plant', 'plant', plant)


# --- the plant -------------------------------------------------------------------------------

BAD_INPUTS = [[NAN], [INF], [-INF], [], [0.1, 0.2]]


def test_plant_nan_inf_and_wrong_length_inputs_are_rejected(procs, probe, tmp_path):
    """Each step k answered by the probe: a bad input for k % 6 < 5, else a valid one. The plant
    must hold the last valid input (and still step): its outputs equal those of the plant core
    fed the held inputs, bit for bit."""
    n = 30

    def answer(k: int) -> List[float]:
        return BAD_INPUTS[k % 6] if k % 6 < 5 else [0.8 * math.sin(0.3 * k)]

    rig = Rig(procs, probe, tmp_path, watch=('y',))
    rig.start('plant', 'metampc_plant', 'plant',
              {'theta': 0.5, 'x0': [0.5, 0.0], 'input_timeout': 30.0})
    rig.wait_matched('y')
    answers = probe.node.create_subscription(PlantOutput, 'y', lambda m: pub.publish(
        ControlInput(step=m.step, u=answer(m.step))) if m.step < n else None, RELIABLE)
    probe.wait_for(lambda: answers.get_publisher_count() > 0, 60.0, 'y matched')
    pub = probe.node.create_publisher(ControlInput, 'u', RELIABLE)    # opens the start gate
    probe.wait_for(lambda: rig.ys and rig.ys[-1].step == n, 60.0, f'y_{n}')

    core = Plant(PlantConfig(theta=(0.5,), x0=(0.5, 0.0)))
    held, expected_u, expected_y = 0.0, [0.0], [core.output()]
    for k in range(n):
        held = answer(k)[0] if k % 6 == 5 else held
        expected_u.append(held)
        expected_y.append(core.step([held]))
    ys = rig.ys[-(n + 1):]
    assert [m.step for m in ys] == list(range(n + 1))
    assert [m.u_applied[0] for m in ys] == expected_u
    assert np.array_equal([list(m.y) for m in ys], expected_y)
    out = rig.finish()['plant']
    assert f'0 stale, {sum(k % 6 < 5 for k in range(n))} rejected, 0 timeouts' in out, out
    assert 'rejected the input for step 0 (non-finite input [nan])' in out


def test_plant_with_negative_theta_escapes_flagged_never_nan(procs, probe, tmp_path):
    """theta = -1 outside its (unstable) limit cycle: the state escapes to infinity in finite
    time. The plant alone (u = 0 held after each input timeout) flags the divergence at the
    first sample beyond the state bound of an independent integration (scipy RK45 to 1e-10),
    then repeats its last finite sample, that integration's state one sample earlier; no NaN
    is published or recorded, and plant_info tells a late subscriber."""
    theta, x0, bound, dt = -1.0, [2.2, 0.0], 10.0, 0.1
    sol = solve_ivp(lambda t, x: [x[1], theta * x[1] * (1 - x[0] ** 2) - x[0]], (0, 10), x0,
                    t_eval=np.arange(100) * dt, rtol=1e-10, atol=1e-10)
    assert not sol.success, 'the solution escapes to infinity within 10 s'
    beyond = np.abs(sol.y).max(axis=0) > bound
    escape = int(np.argmax(beyond)) if beyond.any() else len(sol.t)

    rig = Rig(procs, probe, tmp_path, watch=('y',))
    rig.record(['y'])
    # start_subscribers 2: y_0 waits for the recorder too (under load its subscription had
    # matched the plant only after the 30 steps of this run: nothing was recorded).
    rig.start('plant', 'metampc_plant', 'plant', {
        'theta': theta, 'x0': x0, 'state_bound': bound, 'dt': dt, 'input_timeout': 0.05,
        'start_subscribers': 2})
    # A silent `u` publisher opens the plant's start gate once the probe has matched the
    # plant: the probe hears y from y_0 on.
    rig.wait_matched('y')
    gate = probe.node.create_publisher(ControlInput, 'u', RELIABLE)
    probe.wait_for(lambda: any(m.diverged for m in rig.ys), 60.0, 'the divergence flag')
    rig.wait_steps(5)
    ys = list(rig.ys)
    assert [m.step for m in ys] == list(range(len(ys)))
    first = next(k for k, m in enumerate(ys) if m.diverged)
    assert first == escape
    np.testing.assert_allclose(ys[first - 1].y, sol.y[:, first - 1], rtol=1e-5)
    assert all(np.abs(m.y).max() <= bound for m in ys)
    assert all(m.diverged and list(m.y) == list(ys[first - 1].y) for m in ys[first:])
    infos = []
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    probe.wait_for(lambda: infos and infos[-1].diverged, 30.0, 'plant_info with diverged')
    out = rig.finish()['plant']
    assert out.count('plant diverged at step') == 1, out
    assert f'plant diverged at step {escape} ' in out
    probe.node.destroy_publisher(gate)


# --- the controller --------------------------------------------------------------------------

def _malformed_offsets(msg: NssmWeights) -> NssmWeights:
    msg.shape_offsets[1] = 99
    return msg


def _truncated(msg: NssmWeights) -> NssmWeights:
    msg.params = msg.params[:-1]
    return msg


def _nan(msg: NssmWeights) -> NssmWeights:
    msg.params[7] = NAN
    return msg


def _wrong_shape(msg: NssmWeights) -> NssmWeights:
    msg.shapes[0] += 1
    return msg


def _other_plant(msg: NssmWeights) -> NssmWeights:
    """A valid NSSM, but of a plant with 3 outputs."""
    config = NssmConfig(n_u=1, n_y=3, n_z=3, history=2, hidden=(8,))
    fields = fields_from_weights(config, Normalisation.identity(config),
                                 init_params(config, seed=0))
    return NssmWeights(version=msg.version, method=msg.method, stage=msg.stage, **fields)


BAD_WEIGHTS = [  # (change, the reason the controller gives)
    (_malformed_offsets, 'shape_offsets'),
    (_truncated, 'parameters, shapes need'),
    (_nan, 'non-finite'),
    (_wrong_shape, 'encoder.0.weight has shape'),
    (_other_plant, 'model has n_u = 1, n_y = 3; the plant has 1 input(s), 2 output(s)'),
]


def test_controller_rejects_malformed_nan_and_wrong_shape_weights(procs, probe, tmp_path):
    """Each bad model is rejected with its reason in MpcStatus.model_status while model 1 stays
    in use and the loop goes on; then a good model is still taken."""
    rig = Rig(procs, probe, tmp_path)
    pub = probe.node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
    pub.publish(weights(1))
    start_loop(rig, {'theta': 0.5, 'input_timeout': 2.0}, {})
    rig.wait_status(lambda s: s.model_version == 1 and s.model_status == 'ok', 'model 1')
    for version, (change, reason) in enumerate(BAD_WEIGHTS, start=2):
        pub.publish(change(weights(version)))
        st = rig.wait_status(lambda s: reason in s.model_status, f'version {version} rejected')

        def heard_events():
            return [e for s in list(rig.heard['mpc_status']) for e in s.model_events
                    if e.version == version]
        # the event may ride on a later status than the first that names the refusal
        rig.probe.wait_for(lambda: heard_events(), 60.0, f'version {version} event')
        events = heard_events()
        assert [(e.outcome, e.cause) for e in events] == [('refused', 'weights')], events
        assert st.model_status == f'rejected: {events[0].reason}' and st.model_version == 1, st
        rig.wait_steps(3)
        assert {s.model_version for s in rig.heard['mpc_status'][-3:]} == {1}
    good = len(BAD_WEIGHTS) + 2
    pub.publish(weights(good, theta=0.6))
    rig.wait_status(lambda s: s.model_version == good and s.model_status == 'ok',
                    f'model {good}')
    out = rig.finish()['controller']
    assert all(f'rejected weights version {v}' in out for v in range(2, good)), out


def test_capped_qp_falls_back_to_a_finite_bounded_input(procs, probe, tmp_path):
    """OSQP capped at one iteration (max_iter 1) never solves: every tick with a model is a
    fallback, and with no plan ever found the fallback holds the applied input (mpc.md), so
    each input equals the u_applied of the sample it answers, within [u_min, u_max]. (The QP
    has box constraints only, with u_min <= u_max checked at start-up: it cannot be made
    infeasible; a capped solve stands for every solver failure.)"""
    rig = Rig(procs, probe, tmp_path)
    pub = probe.node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
    start_loop(rig, {'theta': 0.5, 'input_timeout': 2.0},
               {'max_iter': 1, 'pre_model_input': 'excitation', 'excitation_amplitude': 0.7,
                'excitation_seed': 1})
    rig.wait_steps(8)
    pub.publish(weights(1))
    rig.wait_status(lambda s: s.model_version == 1, 'model 1')

    def with_model():
        """Model 1's statuses, its inputs whose y the probe has heard, the applied inputs."""
        applied = {m.step: m.u_applied[0] for m in rig.ys}
        return ([s for s in rig.heard['mpc_status'] if s.model_version == 1],
                [m for m in rig.heard['u'] if m.model_version == 1 and m.step in applied],
                applied)

    def enough():
        statuses, answers, _ = with_model()
        return len(statuses) >= 20 and len(answers) >= 15
    # Counts, not a number of steps: y, u and mpc_status are three topics (mpc_status follows
    # u, which the plant's next y may overtake), each of which may reach the probe late.
    probe.wait_for(enough, 60.0, '20 statuses and 15 inputs with model 1')
    statuses, answers, applied = with_model()
    assert all(s.fallback and s.solver_status == 'maximum iterations reached'
               and s.iterations == 1 for s in statuses)
    assert all(m.u[0] == applied[m.step] and -0.7 <= m.u[0] <= 0.7 for m in answers)
    assert len({m.u[0] for m in answers}) == 1, 'the input held since the model came'
    out = rig.finish()['controller']
    assert 'fallbacks' in out


# --- services --------------------------------------------------------------------------------

def call(probe, client, request, timeout: float = 30.0):
    future = client.call_async(request)
    probe.wait_for(future.done, timeout, f'the answer of {client.srv_name}')
    return future.result()


BAD_RESETS = [  # (request fields, the reason)
    ({'x0': [1.0, 2.0, 3.0]}, 'x0 must have 2 values'),
    ({'x0': [NAN, 0.0]}, 'x0 must be finite'),
    ({'theta': [INF]}, 'theta of family vanderpol needs 1 finite value(s)'),
    ({'theta': [0.1, 0.2]}, 'theta of family vanderpol needs 1 finite value(s)'),
    ({'x0': [50.0, 0.0]}, 'lies outside state_bound'),
]


def test_bad_and_concurrent_service_calls(procs, probe, tmp_path):
    """Bad plant resets are refused with the reason (the plant goes on, a good reset still
    works); adapt with too few samples is refused; of two meta_train requests sent at once one
    runs and the other is answered busy at once, as is an adapt meanwhile."""
    rig = Rig(procs, probe, tmp_path, watch=('y',))
    rig.start('learner', 'metampc_learner', 'learner', LEARNER)
    rig.start('plant', 'metampc_plant', 'plant', {'start_timeout': 0.2, 'input_timeout': 0.05})
    reset = probe.node.create_client(ResetPlant, 'reset')
    meta = probe.node.create_client(MetaTrain, 'meta_train')
    adapt = probe.node.create_client(Adapt, 'adapt')
    for client in (reset, meta, adapt):
        assert client.wait_for_service(timeout_sec=60.0), client.srv_name

    for fields, reason in BAD_RESETS:
        result = call(probe, reset, ResetPlant.Request(theta=fields.get('theta', []),
                                                       x0=fields.get('x0', [])))
        assert not result.success and result.message.startswith('reset rejected'), fields
        assert reason in result.message, result.message
    rig.wait_steps(3)
    result = call(probe, reset, ResetPlant.Request(theta=[0.3], x0=[0.1, 0.0]))
    assert result.success, result.message
    probe.wait_for(lambda: any(m.step == 0 and list(m.y) == [0.1, 0.0] for m in rig.ys),
                   30.0, 'y_0 of the good reset')

    result = call(probe, adapt, Adapt.Request(method='supervised'))
    assert not result.success
    assert result.message.startswith('adapt failed: too few target samples: 0 buffered')

    long_job = MetaTrain.Request(iterations=100000, seed=3)
    first, second = meta.call_async(long_job), meta.call_async(long_job)
    probe.wait_for(lambda: first.done() or second.done(), 60.0, 'one meta_train answered')
    refused, running = (first, second) if first.done() else (second, first)
    assert not refused.result().success
    assert refused.result().message.startswith('busy: ')
    result = call(probe, adapt, Adapt.Request())
    assert not result.success and result.message.startswith('busy: meta_train (imaml)')
    assert not running.done()
    rig.finish()    # SIGINT cancels the running job: the learner exits 0


# --- SIGKILL ---------------------------------------------------------------------------------

def test_sigkill_recorder_mid_run_leaves_a_file_readable_to_its_last_chunk(
        procs, probe, tmp_path):
    """A plant alone steps every 50 ms; the recorder (4 kB chunks, written every 0.1 s) is
    killed mid-run. The unfinished file still reads: every message of its complete chunks, at
    least those on disk before the kill, equal to what the probe received, in order."""
    rig = Rig(procs, probe, tmp_path, watch=('y',))
    gate = probe.node.create_publisher(ControlInput, 'u', RELIABLE)    # the probe hears y_0 on
    rig.record(['y'], chunk_size=4096)
    rig.start('plant', 'metampc_plant', 'plant', {'input_timeout': 0.05})

    def recorded():
        return read_recording(rig.recording).topics.get('/y') if os.path.exists(
            rig.recording) else None
    probe.wait_for(lambda: recorded() and recorded().count >= 60, 60.0, '60 samples on disk')
    before = recorded().count
    rig.kill('recorder')
    rig.wait_steps(5)   # the plant goes on without it
    recording = read_recording(rig.recording)
    assert not recording.complete and recording.statistics is None
    got = rig.recorded(recording)['y']
    assert len(got) >= before
    heard = {m.step: m for m in rig.ys}
    steps = [m.step for m in got]
    assert steps == list(range(steps[0], steps[0] + len(steps))), 'in order, no gap'
    assert all(list(m.y) == list(heard[m.step].y) and stamp_ns(m) == stamp_ns(heard[m.step])
               for m in got if m.step in heard)
    assert sum(m.step in heard for m in got) >= len(got) - 5
    rig.finish()
    probe.node.destroy_publisher(gate)


def test_sigkill_and_restart_of_the_controller(procs, probe, tmp_path):
    """The controller is killed mid-run: the plant times out and holds its input; a new
    controller gets the latched model (published once, before either started) and the
    lockstep loop resumes, one answer per sample, each applied. The recording of y loses
    nothing."""
    rig = Rig(procs, probe, tmp_path)
    pub = probe.node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
    pub.publish(weights(1))
    rig.record(['y'])
    start_loop(rig, {'theta': 0.5, 'input_timeout': 0.5}, {})
    rig.wait_status(lambda s: s.model_version == 1, 'model 1')
    rig.wait_steps(10)
    rig.kill('controller')
    # The plant steps on its own, holding its input: at most every 0.5 s (its input timeout)
    # with no controller. Samples the probe has yet to take may predate the kill, and the new
    # controller, which imports no torch, is up within a second: 2 s without one.
    rig.wait_steps(2)
    time.sleep(2.0)
    n_u = len(rig.heard['u'])
    rig.start('controller', 'metampc_controller', 'controller', CONTROLLER)

    def in_lockstep(n: int = 20) -> bool:
        """The new controller's last n answers: consecutive steps, model 1, each applied by
        the plant (y_{k+1} carries u_k: the answer came before the input timeout)."""
        applied = {m.step: m.u_applied[0] for m in rig.ys}
        last = rig.heard['u'][n_u:][-n:]
        steps = [m.step for m in last]
        return (len(last) == n and steps == list(range(steps[0], steps[0] + n))
                and all(m.model_version == 1 and applied.get(m.step + 1) == m.u[0]
                        for m in last))
    # Its first answers may come after the plant's input timeout (start-up on a loaded
    # machine, the model being built); then the loop runs in lockstep again.
    probe.wait_for(in_lockstep, 60.0, '20 answers of the new controller in lockstep')
    new = rig.heard['u'][n_u:]
    versions = [m.model_version for m in new]
    # Before the latched model arrives, the new controller answers with its pre-model input.
    assert versions == sorted(versions) and set(versions) <= {0, 1}, versions
    steps = [m.step for m in new]
    assert steps == sorted(set(steps)), 'each sample answered at most once'
    out = rig.finish()['plant']
    timeouts = int(re.search(r'stopped at step \d+ .* (\d+) timeouts', out).group(1))
    assert timeouts >= 2, out


def test_ctrl_c_of_the_running_loop_prints_no_rcl_error(procs, probe, tmp_path):
    """Ctrl-C to the plant and the controller at once (as to a terminal's process group) while
    the lockstep loop runs: each exits 0 with its stop line and nothing from rcl (issue 31:
    "Failed to publish log message to rosout: publisher's context is invalid" after the
    stop line of each, every time)."""
    rig = Rig(procs, probe, tmp_path)
    pub = probe.node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
    pub.publish(weights(1))
    start_loop(rig, {'theta': 0.5}, {})
    rig.wait_status(lambda s: s.model_version == 1, 'model 1')
    rig.wait_steps(20)
    for name in ('plant', 'controller'):     # one SIGINT each, as `ros2 run` passes it on
        os.killpg(rig.nodes[name].pid, signal.SIGINT)
    for name in ('plant', 'controller'):
        proc = rig.nodes[name]
        code = proc.wait(60.0)
        rig.killed.add(name)
        out = rig.output(name)
        assert code == 0 and 'Traceback' not in out, f'{name} exited with {code}:\n{out}'
        assert session_pids(proc) == [], f'a process of {name} outlived ros2 run'
        assert re.search(r'\[' + name + r'\]: stopped at step \d+', out), out
        assert 'rosout' not in out and 'context is invalid' not in out, out


def test_sigkill_of_the_learner_during_meta_train(procs, probe, tmp_path):
    """The learner is killed while meta_train runs: the orchestrator's call fails at once with
    an ExperimentError naming the learner (a plain rclpy client would wait forever: the server
    is only dropped from the graph after the DDS lease, ~20 s); the controller keeps the model
    the learner published before and the loop goes on."""
    rig = Rig(procs, probe, tmp_path)
    learner = rig.start('learner', 'metampc_learner', 'learner', LEARNER)
    # OSQP's wall-clock cap (50 ms) out of reach: every later tick must be 'solved'.
    start_loop(rig, {'theta': 0.5, 'input_timeout': 2.0}, {'time_limit': 30.0})
    client = ExperimentClient({}, lambda: process_status({'learner': learner}))
    try:
        probe.wait_for(lambda: client.clients['meta_train'].service_is_ready(), 60.0,
                       'the meta_train service')
        done = client.call('meta_train', MetaTrain.Request(iterations=2), 120.0,
                           'meta_train imaml')
        rig.wait_status(lambda s: s.model_version == done.model_version
                        and s.model_status == 'ok', 'the meta-model in the controller')

        def kill_when_training():
            probe.wait_for(lambda: client.progress is not None
                           and client.progress.phase == 'meta_train'
                           and client.progress.total == 100000, 60.0, 'the long job')
            rig.kill('learner')
        killer = threading.Thread(target=kill_when_training)
        killer.start()
        with pytest.raises(ExperimentError) as err:
            client.call('meta_train', MetaTrain.Request(iterations=100000), 120.0,
                        'meta_train imaml')
        killer.join()
        assert 'meta_train imaml: learner exited with status -9' in str(err.value)
    finally:
        client.close()
    n = len(rig.heard['mpc_status'])
    # Counted on mpc_status itself, which the plant's y may overtake on the way to the probe.
    probe.wait_for(lambda: len(rig.heard['mpc_status']) >= n + 15, 60.0, '15 more statuses')
    later = rig.heard['mpc_status'][n:]
    assert all(s.model_version == done.model_version and s.model_status == 'ok'
               and s.solver_status == 'solved' for s in later)
    rig.finish()


# --- start-up and outputs --------------------------------------------------------------------

BAD_START = {  # node: (package, executable, one parameter out of range, what the line says)
    'plant': ('metampc_plant', 'plant', {'dt': -0.1}, 'dt must be >= 0'),
    'controller': ('metampc_controller', 'controller', {'horizon': 0}, 'horizon must be >= 1'),
    'learner': ('metampc_learner', 'learner', {'iterations': 0}, 'iterations must be >= 1'),
    'recorder': ('metampc_recording', 'recorder', {'output': '/tmp/x.mcap', 'chunk_size': 0},
                 'chunk_size must be >= 1'),
}


def _each_refused_with_one_line(procs, cases) -> None:
    """Start every node of `cases` at once; each exits 2 with the one line its case names."""
    started = {name: procs.start(pkg, exe, params=params, name=name)
               for name, (pkg, exe, params, _) in cases.items()}
    for name, proc in started.items():
        code = proc.wait(120.0)
        lines = own_lines(procs.output(proc))
        assert code == 2, (name, code, lines)
        assert len(lines) == 1 and 'invalid parameter: ' in lines[0], (name, lines)
        assert cases[name][3] in lines[0], (name, lines)


def test_out_of_range_parameters_at_startup_one_line_exit_2(procs):
    _each_refused_with_one_line(procs, BAD_START)


MISSPELT = {  # node: (package, executable, parameters with one misspelt, what the line says)
    'plant': ('metampc_plant', 'plant', {'thetaa': 1.0}, 'unknown parameter thetaa; did you '
              'mean theta?'),
    'controller': ('metampc_controller', 'controller', {'horizn': 5},
                   'unknown parameter horizn; did you mean horizon?'),
    'learner': ('metampc_learner', 'learner', {'iteration': 5},
                'unknown parameter iteration; did you mean iterations?'),
    'recorder': ('metampc_recording', 'recorder', {'output': '/tmp/never.mcap', 'topic': ['y']},
                 'unknown parameter topic; did you mean topics?'),
}


def test_misspelt_parameter_at_startup_one_line_exit_2(procs):
    """ROS ignores a parameter a node does not declare; the nodes refuse it by name, so a typo
    cannot run the default without a word."""
    _each_refused_with_one_line(procs, MISSPELT)
    assert not os.path.exists('/tmp/never.mcap')


def test_existing_output_path_is_never_overwritten(procs, tmp_path):
    """The recorder refuses an existing file (exit 2, one line, the file untouched);
    run_experiment refuses a non-empty run folder before starting anything (exit 2)."""
    taken = tmp_path / 'taken.mcap'
    taken.write_bytes(b'an earlier run')
    recorder = procs.start('metampc_recording', 'recorder', params={'output': str(taken)},
                           name='recorder')
    run = tmp_path / 'run'
    run.mkdir()
    (run / 'report.md').write_text('an earlier report')
    script = subprocess.run(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         os.path.join(ROOT, 'config', 'ci.yaml'), '--out', str(run), '--no-progress'],
        capture_output=True, text=True, timeout=120)
    assert script.returncode == 2, script.stderr
    assert 'exists and is not empty; runs are never overwritten' in script.stderr
    assert os.listdir(run) == ['report.md'] and (run / 'report.md').read_text() == (
        'an earlier report')
    as_file = subprocess.run(         # --out naming an existing file: the same, not a traceback
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         os.path.join(ROOT, 'config', 'ci.yaml'), '--out', str(run / 'report.md'),
         '--no-progress'], capture_output=True, text=True, timeout=120)
    assert as_file.returncode == 2, as_file.stderr
    assert as_file.stderr.strip().splitlines() == [
        f'run_experiment: {run / "report.md"} exists and is not a folder; runs are never '
        'overwritten']
    assert (run / 'report.md').read_text() == 'an earlier report'
    assert recorder.wait(120) == 2
    lines = own_lines(procs.output(recorder))
    assert len(lines) == 1 and 'exists' in lines[0] and str(taken) in lines[0], lines
    assert taken.read_bytes() == b'an earlier run'
