"""A session of the stand-in joint robot (examples/joint_robot) behind the machine bridge,
simulated without ROS, and what a user would have recorded of it; a small meta-model.

The robot's equations and integration step are the example's; it publishes JointState every
20 ms stamped by its clock (no delay). The bridge's own core (BridgeCore, the example mapping)
takes the samples and ticks every dt; a stand-in controller answers each y_k 2 ms later with
an excitation level (held 0.5 s, uniform in +-amplitude: beyond the bounds the bridge clips).
What the bridge gave the controller (y_k, u_applied_k, saturated) is kept as the independent
answer; the robot's topics (JointState, the Float64MultiArray commands, stamped by when they
were written; rosbags' message classes, serialized as on the wire) go into a bag (rosbags
writer, MCAP or sqlite3) and a logger's CSV has the
robot's state and torque at every t_k. A pytest plugin (conftest.py): its session fixtures
are built once per worker, for the test files of group 'robot_recording'.
"""
import csv
import functools
import importlib.util
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
MAPPING = str(ROOT / 'examples' / 'joint_robot' / 'mapping.yaml')
JOINTS, COMMANDS = '/joint_states', '/effort_controller/commands'
START_S = 1000          # the robot's clock at its first sample, s
PUBLISH_MS, ANSWER_MS = 20, 2


def robot_module():
    """examples/joint_robot/joint_robot.py, imported (K, C, TAU_MAX, STEP_S)."""
    spec = importlib.util.spec_from_file_location(
        'joint_robot', ROOT / 'examples' / 'joint_robot' / 'joint_robot.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@functools.lru_cache(maxsize=None)
def _store():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def joint_state(stamp_ns: int, position=(), velocity=(), effort=()):
    """A sensor_msgs/msg/JointState (rosbags' class) of one joint."""
    t = _store().types
    stamp = t['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return t['sensor_msgs/msg/JointState'](
        header=t['std_msgs/msg/Header'](stamp=stamp, frame_id=''), name=['joint1'],
        position=np.array(position, dtype=float), velocity=np.array(velocity, dtype=float),
        effort=np.array(effort, dtype=float))


def command(values=()):
    """A std_msgs/msg/Float64MultiArray (rosbags' class) writing `values`."""
    t = _store().types
    return t['std_msgs/msg/Float64MultiArray'](
        layout=t['std_msgs/msg/MultiArrayLayout'](dim=[], data_offset=0),
        data=np.array(values, dtype=float))


@dataclass
class Session:
    """What happened: per tick (k, t_k, y_k or None, u_applied_k, saturated); the messages
    as (log time ns, message); the logger's rows (t_k, q, qd, tau applied after t_k)."""

    ticks: List[Tuple[int, float, Optional[np.ndarray], np.ndarray, bool]] = field(
        default_factory=list)
    joint_states: list = field(default_factory=list)
    commands: list = field(default_factory=list)
    rows: List[Tuple[float, float, float, float]] = field(default_factory=list)


def simulate(seconds: float, seed: int, amplitude: float = 1.2,
             silent: Sequence[float] = (), nan_at: Sequence[float] = ()) -> Session:
    """`seconds` of the session; `silent`: (from, to) s of robot time without JointState;
    `nan_at`: robot times (s) of samples whose velocity is NaN."""
    from metampc_plant.bridge_core import BridgeCore
    from metampc_plant.machine_mapping import load_mapping
    robot = robot_module()
    mapping = load_mapping(MAPPING)
    core = BridgeCore(mapping)
    rng = np.random.default_rng(seed)
    step_ms, dt_ms = round(robot.STEP_S * 1000), round(mapping.dt * 1000)
    q = qd = tau = 0.0
    level, pending = 0.0, []            # (ms at which the robot takes it, torque)
    out, t0 = Session(), None
    for ms in range(0, round(seconds * 1000), step_ms):
        if ms % 500 == 0:
            level = float(rng.uniform(-amplitude, amplitude))
        for when, value in [p for p in pending if p[0] <= ms]:
            tau = min(max(value, -robot.TAU_MAX), robot.TAU_MAX)
            pending.remove((when, value))
        if ms % PUBLISH_MS == 0 and not (silent and silent[0] <= ms / 1000 < silent[1]):
            nan = any(abs(ms / 1000 - t) < 1e-9 for t in nan_at)
            msg = joint_state((START_S * 1000 + ms) * 10**6, [q], [np.nan if nan else qd], [tau])
            received = mapping.stamp(mapping.topics[0], msg, 0.0)
            t0 = received if t0 is None else t0
            core.sample(0, msg, received)
            out.joint_states.append((round(received * 1e9), msg))
        if ms % dt_ms == 0 and t0 is not None:
            tick = core.tick(t0 + len(out.ticks) * mapping.dt)
            out.ticks.append((tick.step, tick.time, tick.y, tick.u_applied, tick.saturated))
            written, at_ms = None, ms
            if tick.write is not None:      # the safe value, written as the tick decides
                written = tick.write
                out.commands.append((round(tick.time * 1e9) + 1000, command(written)))
            if tick.y is not None:
                answer = core.answer(tick.step, [level], tick.time + ANSWER_MS / 1000)
                if answer.write is not None:
                    written, at_ms = answer.write, ms + ANSWER_MS
                    out.commands.append((round((tick.time + ANSWER_MS / 1000) * 1e9),
                                         command(written)))
            if written is not None:
                pending.append((at_ms, float(written[0])))
            out.rows.append((tick.time, q, qd, tau if written is None else float(written[0])))
        qd += robot.STEP_S * (-robot.K * q - robot.C * qd + tau)
        q += robot.STEP_S * qd
    return out


def write_bag(session: Session, path: Path, storage: str = 'mcap') -> Path:
    """The robot's topics as a rosbag2 bag folder (storage 'mcap' or 'sqlite3')."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    store = _store()
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        for topic, type_name, messages in (
                (JOINTS, 'sensor_msgs/msg/JointState', session.joint_states),
                (COMMANDS, 'std_msgs/msg/Float64MultiArray', session.commands)):
            connection = writer.add_connection(topic, type_name, typestore=store)
            for log_ns, msg in messages:
                writer.write(connection, log_ns, store.serialize_cdr(msg, type_name))
    return path


def write_recording(session: Session, path: Path, chunk_size: int) -> Path:
    """The robot's topics as one MCAP file written by metampc's recorder writer (rosbag2's
    layout), in log-time order, a chunk closed every `chunk_size` bytes."""
    from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
    store = _store()
    writer = Rosbag2McapWriter(McapWriterConfig(str(path), chunk_size=chunk_size))
    messages = []
    for topic, type_name, recorded in (
            (JOINTS, 'sensor_msgs/msg/JointState', session.joint_states),
            (COMMANDS, 'std_msgs/msg/Float64MultiArray', session.commands)):
        writer.add_topic(topic, type_name, [])
        messages += [(ns, topic, store.serialize_cdr(m, type_name)) for ns, m in recorded]
    for ns, topic, data in sorted(messages, key=lambda m: m[0]):
        writer.write(topic, bytes(data), ns, ns)
    writer.close()
    return path


def write_csv(session: Session, path: Path, nan_row: Optional[int] = None,
              gap: Sequence[int] = ()) -> Path:
    """The logger's CSV: time, q, qd, tau (the torque from t_k on); qd left empty in row
    `nan_row`, rows gap[0] to gap[1] - 1 missing (the logger stopped)."""
    with open(path, 'w', newline='') as f:
        out = csv.writer(f)
        out.writerow(['time', 'q', 'qd', 'tau'])
        for i, (t, q, qd, tau) in enumerate(session.rows):
            if not (gap and gap[0] <= i < gap[1]):
                out.writerow([repr(t), repr(q), '' if i == nan_row else repr(qd), repr(tau)])
    return path


def tstep_rmse(predictor, u: np.ndarray, y: np.ndarray, horizon: int) -> np.ndarray:
    """Per output, the RMSE of the controller's `horizon`-step predictions (NssmPredictor)
    over every window of consecutive samples u_k (K, n_u), y_k (K, n_y); u_k produced y_k."""
    history = predictor.config.history
    errors = []
    for s in range(len(y) - history - horizon + 1):
        hist, future = slice(s, s + history), slice(s + history, s + history + horizon)
        errors.append(predictor.predict(u[hist], y[hist], u[future]) - y[future])
    return np.sqrt(np.mean(np.square(errors), axis=(0, 1)))


def meta_checkpoint(path: str, method: str = 'maml') -> str:
    """A small meta-model of the van der Pol family (the robot's: n_u 1, n_y 2, dt 0.1 s)."""
    import torch
    from metampc_model.nssm import Nssm
    from metampc_model.nssm_config import NssmConfig
    from metampc_learner.checkpoint import save_checkpoint
    from metampc_learner.data import (normalisation_from, simulate_source, SourceConfig,
                                      SourceSet)
    from metampc_learner.meta_train import meta_train, MetaConfig
    torch.set_num_threads(1)
    data = simulate_source(SourceConfig(n_systems=30, episode_samples=120, seed=0))
    config = NssmConfig(history=5, loss_horizon=5, hidden=(32, 32), n_z=4)
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    model = Nssm(config, norm)
    result = meta_train(model, SourceSet(data, norm, config),
                        MetaConfig(method=method, iterations=300, batch_size=8, inner_steps=5,
                                   windows_per_task=32, lr_outer=3e-3, seed=0))
    save_checkpoint(path, model, result.params, {'method': method, 'stage': 'meta',
                                                 'seed': 0, 'version': 1})
    return path


@pytest.fixture(scope='session')
def robot_meta(tmp_path_factory) -> str:
    """A first-order MAML meta-model checkpoint (meta_checkpoint)."""
    return meta_checkpoint(str(tmp_path_factory.mktemp('meta') / 'meta_maml.pt'))


@pytest.fixture(scope='session')
def robot_session() -> Session:
    """50 s of the robot behind the bridge: silent for 0.7 s at 10 s, NaN velocities at
    20.08 and 20.1 s, excitation up to 1.05 (some answers clipped)."""
    return simulate(50.0, 0, amplitude=1.05, silent=(10.0, 10.7), nan_at=(20.08, 20.1))


@pytest.fixture(scope='session')
def robot_bag(robot_session, tmp_path_factory) -> Path:
    """The session's bag folder (MCAP storage)."""
    return write_bag(robot_session, tmp_path_factory.mktemp('bag') / 'robot')


@pytest.fixture(scope='session')
def fresh_robot():
    """An independent 30-s episode of the same robot (another seed, inputs within bounds),
    as the bridge gave it: (u (K, 1), y (K, 2)), consecutive and complete."""
    ticks = simulate(30.0, 7, amplitude=1.0).ticks[1:]
    assert all(t[2] is not None for t in ticks)
    return np.array([t[3] for t in ticks]), np.array([t[2] for t in ticks])


__all__ = ['MAPPING', 'JOINTS', 'COMMANDS', 'joint_state', 'command', 'Session', 'simulate',
           'write_bag', 'write_recording', 'write_csv', 'tstep_rmse', 'meta_checkpoint']
