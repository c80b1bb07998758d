"""Recording fixtures shared by the metampc_recording and metampc_bringup tests (a plugin of
the root conftest): MCAP walking by hand, recorder processes, and one recorded closed-loop run of
the real lockstep plant for the whole session, shared by the recorder and replay tests."""
from dataclasses import dataclass
import io
import math
from pathlib import Path
import time
from typing import Any, Dict, List, Set, Tuple

from mcap.data_stream import ReadDataStream
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
import pytest

LATCHED_DEPTH, STREAM_DEPTH = 1, 1000
REFERENCE = (0.8, -0.5)      # set-point of x1 before and from step 20 of an episode
EPISODE_STEPS = (40, 20)     # outputs of episode 0 (then a reset) and of episode 1
MISSED = {(0, 10), (0, 11), (1, 5)}      # (episode, step) the controller does not answer
CLOCK = 'rosgraph_msgs/msg/Clock'
STEP_HOLD = 'metampc_msgs/msg/StepHold'
# s: the probe holds the run's last step this long (the plant then waits it out instead of
# stepping on after its input_timeout; beside two suites SIGINT once came after 0.5 s).
LAST_HOLD_S = 120.0


def reference(k: int) -> float:
    """Set-point of y[0] at step k."""
    return REFERENCE[0] if k < 20 else REFERENCE[1]


def _messages_in_complete_chunks(data: bytes) -> int:
    """Messages inside the Chunk records wholly present in MCAP bytes `data`.

    The records are walked by hand (opcode, uint64 length, body), independently of the
    project's reader: a record that runs past the end of `data` ends the walk.
    """
    count, pos = 0, 8    # after the magic
    while pos + 9 <= len(data):
        opcode, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], 'little')
        if pos + 9 + length > len(data):
            break
        if opcode == 0x06:
            chunk = Chunk.read(ReadDataStream(io.BytesIO(data[pos + 9:pos + 9 + length])))
            count += sum(isinstance(r, Message) for r in breakup_chunk(chunk))
        pos += 9 + length
    return count


@pytest.fixture
def complete_chunk_messages():
    """f(data: bytes) -> number of messages in the complete chunks of an MCAP byte string."""
    return _messages_in_complete_chunks


def qos(latched: bool = False):
    """Reliable QoS: latched (transient_local, depth 1) or a deep volatile stream."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=LATCHED_DEPTH if latched else STREAM_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


class RecorderHarness:
    """Starts recorder processes and waits on what they write.

    Args:
        procs: a ProcessGroup. probe: a TestNode (waits and graph queries).
    """

    def __init__(self, procs, probe):
        self.procs = procs
        self.probe = probe

    def start(self, output, **params):
        """`ros2 run metampc_recording recorder` writing `output`, with RecorderConfig params."""
        from metampc_recording.recorder_config import RecorderConfig
        config = RecorderConfig(output=str(output), **params)
        return self.procs.start('metampc_recording', 'recorder', params=config.to_parameters(),
                                name='recorder')

    def wait_matched(self, publishers, timeout=30.0):
        """Until every publisher has a subscriber (the recorder's)."""
        publishers = list(publishers)
        self.probe.wait_for(lambda: all(p.get_subscription_count() >= 1 for p in publishers),
                            timeout, 'the recorder to subscribe to every topic')

    def wait_subscribed(self, topics, timeout=30.0):
        """Until the graph shows the recorder subscribed to every topic of `topics`."""
        def subscribed(topic):
            return any(i.node_name == 'recorder'
                       for i in self.probe.node.get_subscriptions_info_by_topic(topic))
        self.probe.wait_for(lambda: all(subscribed(t) for t in topics), timeout,
                            f'the recorder to subscribe to {sorted(topics)}')

    def wait_recorded(self, path, counts, timeout=60.0):
        """Until the (unfinished) file holds at least `counts[topic]` messages per topic.

        The timeout is generous (a loaded 2-core machine once needed more than 20 s); what is
        asserted is the content. On a timeout the message gives what the file held."""
        from metampc_recording.recording_reader import read_recording
        have = {}

        def done():
            if not Path(path).exists():
                return False
            have.update({t.name: t.count for t in read_recording(str(path)).topics.values()})
            return all(have.get(topic, 0) >= n for topic, n in counts.items())
        try:
            self.probe.wait_for(done, timeout, f'{counts} recorded in {path}')
        except AssertionError as err:
            raise AssertionError(f'{err}; the file held {have}') from None


@pytest.fixture
def recorders(procs, probe):
    """A RecorderHarness for this test."""
    return RecorderHarness(procs, probe)


@dataclass
class ClosedLoopRun:
    """A recorded lockstep run, and every message of it as the probe saw it.

    Attributes:
        path: the MCAP file (finished: the recorder was stopped with SIGINT).
        published: topic -> messages in order: those the plant published (as received by the
            probe) and those the probe published.
        types: topic -> ROS type name.
        live: the metrics the probe computed during the run from those messages, fed one by
            one to a SeriesBuilder as they were received or sent (tracked output 0).
        unanswered: (episode, step) of the outputs the probe did not answer.
        run_config: what the recorder was given as metadata_json.
    """

    path: Path
    published: Dict[str, List[Any]]
    types: Dict[str, str]
    live: Dict[str, Any]
    unanswered: Set[Tuple[int, int]]
    run_config: Dict[str, Any]


class ProbeController:
    """Plays the controller and the learner of a lockstep run on the probe node.

    It answers output y_k with a ControlInput (u = r + (r - y[0]) - 1.5 y[1], r the
    reference of step k + 1, not clipped, so the plant saturates some) and an MpcStatus whose
    y_ref rows are the reference of steps k+1..k+3, except the steps of MISSED and the last
    step of each episode (the run's last step it holds, ``u_hold``, so that the plant waits
    for the end instead of stepping on); after episode 0 it publishes adapted weights and
    adaptation progress and resets the plant. Every message it receives or sends is kept per
    topic and fed to a SeriesBuilder at once, as an orchestrator would.
    """

    def __init__(self, node, seed: int = 7):
        import numpy as np
        from metampc_bringup.analysis.run_series import (CONTROL_INPUT, MPC_STATUS, NSSM_WEIGHTS,
                                                         PLANT_INFO, PLANT_OUTPUT, SeriesBuilder,
                                                         TRAINING_PROGRESS)
        from metampc_msgs.msg import (ControlInput, MpcStatus, NssmWeights, PlantInfo,
                                      PlantOutput, StepHold, TrainingProgress)
        from metampc_msgs.srv import ResetPlant
        from rosgraph_msgs.msg import Clock
        self.node = node
        self.rng = np.random.default_rng(seed)
        self.types = {'/y': PLANT_OUTPUT, '/u': CONTROL_INPUT, '/mpc_status': MPC_STATUS,
                      '/nssm_weights': NSSM_WEIGHTS, '/progress': TRAINING_PROGRESS,
                      '/plant_info': PLANT_INFO, '/clock': CLOCK,
                      '/u_hold': STEP_HOLD}
        self.published: Dict[str, List[Any]] = {topic: [] for topic in self.types}
        self.builder = SeriesBuilder()
        self.unanswered: Set[Tuple[int, int]] = set()
        self.episode, self.last_step, self.ticks, self.version = 0, -1, 0, 1
        self.done = False
        self._msg = {'/u': ControlInput, '/mpc_status': MpcStatus, '/nssm_weights': NssmWeights,
                     '/progress': TrainingProgress, '/u_hold': StepHold}
        self.pubs = {'/nssm_weights': node.create_publisher(
                         NssmWeights, 'nssm_weights', qos(latched=True)),
                     '/progress': node.create_publisher(TrainingProgress, 'progress', qos()),
                     '/mpc_status': node.create_publisher(MpcStatus, 'mpc_status', qos()),
                     '/u_hold': node.create_publisher(StepHold, 'u_hold', qos())}
        self.y_subscription = node.create_subscription(PlantOutput, 'y', self._on_y, qos())
        node.create_subscription(PlantInfo, 'plant_info',
                                 lambda m: self._keep('/plant_info', m), qos(latched=True))
        node.create_subscription(Clock, '/clock', lambda m: self._keep('/clock', m), qos())
        self.reset = node.create_client(ResetPlant, 'reset')
        self._reset_request = ResetPlant.Request(theta=[], x0=[0.0, 0.0])

    def _keep(self, topic: str, msg) -> None:
        self.published[topic].append(msg)
        self.builder.add(self.types[topic], msg)

    def send(self, topic: str, **fields) -> None:
        """Publish a message built from `fields` on one of the probe's topics, and keep it."""
        msg = self._msg[topic](**fields)
        self.pubs[topic].publish(msg)
        self._keep(topic, msg)

    def open_input(self) -> None:
        """Create the `u` publisher: the plant's lockstep start gate opens on it."""
        self.pubs['/u'] = self.node.create_publisher(self._msg['/u'], 'u', qos())

    def _on_y(self, msg) -> None:
        if msg.step < self.last_step:
            self.episode += 1
        self.last_step = k = msg.step
        self._keep('/y', msg)
        # The first answer waits until the recorder (as well as the plant) reads `u`.
        deadline = time.monotonic() + 30.0
        while self.pubs['/u'].get_subscription_count() < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        if k == EPISODE_STEPS[self.episode] - 1:
            self.unanswered.add((self.episode, k))
            if self.episode == 0:
                self.version = 2
                self.send('/nssm_weights', version=2, method='imaml', stage='adapted',
                          params=[0.5, -0.25], train_loss=0.01, train_steps=5, seed=7)
                for i in range(1, 6):
                    self.send('/progress', phase='adapt', method='imaml', iteration=i,
                              total=5, loss=0.1 / i, elapsed=0.2 * i, cg_residual=math.nan)
                self.reset.call_async(self._reset_request)
            else:
                self.send('/u_hold', step=k, hold_s=LAST_HOLD_S)
                self.done = True
            return
        if (self.episode, k) in MISSED:
            self.unanswered.add((self.episode, k))
            return
        r = reference(k + 1)
        u = r + (r - msg.y[0]) - 1.5 * msg.y[1]
        solved = self.ticks >= 3
        solve = float(self.rng.uniform(1e-4, 5e-3))
        self.send('/u', step=k, u=[u], model_version=self.version)
        self.send('/mpc_status', step=k, cost=(r - msg.y[0]) ** 2, solve_time=solve,
                  tick_time=solve + 5e-4, solver_status='solved' if solved else 'no_model',
                  iterations=10 + k % 5 if solved else -1, fallback=self.ticks % 9 == 4,
                  terminal_fallback=self.ticks % 13 == 0, model_version=self.version,
                  planner='latent_mpc', model_status='ok', u_plan=[u] * 3,
                  y_pred=[v for j in range(1, 4) for v in (msg.y[0], msg.y[1])],
                  y_ref=[v for j in range(1, 4) for v in (reference(k + j), 0.0)])
        self.ticks += 1


def run_closed_loop(procs, probe, path: Path) -> ClosedLoopRun:
    """Record a lockstep run of the real plant driven by a ProbeController (see conftest doc).

    Order (no sleeps): latched weights v1 before the recorder starts; recorder and plant
    started; the recorder subscribed to every plant and probe topic; training progress; then
    the `u` publisher, which opens the plant's start gate. Ends with SIGINT to the plant, then,
    once everything the probe saw is in the file, SIGINT to the recorder.
    """
    import json
    from metampc_bringup.analysis.metrics import compute_metrics
    recorders = RecorderHarness(procs, probe)
    ctl = ProbeController(probe.node)
    ctl.send('/nssm_weights', version=1, method='imaml', stage='meta', params=[1.0, -2.0],
             names=['a', 'b'], train_loss=0.02, train_steps=15, seed=7)
    run_config = {'tracked_outputs': [0], 'seed': 7, 'note': "it's"}
    recorder = recorders.start(path, record_clock=True, compression='zstd', chunk_size=4096,
                               flush_period=0.2, metadata_json=json.dumps(run_config))
    # start_subscribers 2 and the wait below: y_0 goes out only once the probe's own y
    # subscription has matched the plant as well as the recorder's (under load the plant once
    # opened its gate on the recorder alone, and the probe missed y_0: 59 samples, not 60).
    plant = procs.start('metampc_plant', 'plant', params={
        'theta': 0.5, 'dt': 0.1, 'x0': [0.0, 0.0], 'seed': 3, 'measurement_noise_std': 0.01,
        'input_timeout': 0.5, 'start_timeout': 0.0, 'start_subscribers': 2})
    recorders.wait_matched(ctl.pubs.values())
    recorders.wait_subscribed(['/y', '/plant_info', '/clock'])
    probe.wait_for(lambda: ctl.y_subscription.get_publisher_count() > 0, 60.0,
                   "the probe's y subscription matched the plant")
    probe.wait_for(ctl.reset.service_is_ready, 30.0, 'the reset service')
    for i in range(1, 16):
        ctl.send('/progress', phase='meta_train', method='imaml', iteration=i, total=15,
                 loss=1.0 / i, elapsed=0.1 * i, cg_residual=1e-3 * i)
    ctl.open_input()
    probe.wait_for(lambda: ctl.done, 60.0, 'the end of the lockstep run')
    assert procs.interrupt(plant) == 0, procs.output(plant)
    last = EPISODE_STEPS[-1] - 1
    assert f'the controller holds step {last} ' in procs.output(plant), procs.output(plant)
    counts = {topic: len(msgs) for topic, msgs in ctl.published.items()}
    recorders.wait_recorded(path, counts)
    assert procs.interrupt(recorder) == 0, procs.output(recorder)
    assert {topic: len(msgs) for topic, msgs in ctl.published.items()} == counts
    live = json.loads(json.dumps(compute_metrics(ctl.builder.build(), tracked=[0])))
    return ClosedLoopRun(path, ctl.published, ctl.types, live, ctl.unanswered, run_config)


@pytest.fixture(scope='session')
def closed_loop(tmp_path_factory) -> ClosedLoopRun:
    """One recorded lockstep run for the whole session (its processes already stopped)."""
    from metampc_testing import ProcessGroup, TestNode
    folder = tmp_path_factory.mktemp('closed_loop')
    group = ProcessGroup(str(folder))
    probe = TestNode('closed_loop_probe')
    try:
        return run_closed_loop(group, probe, folder / 'run' / 'recording.mcap')
    finally:
        probe.close()
        group.stop_all()
