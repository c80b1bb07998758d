"""A synthetic closed-loop recording, written as the recorder writes one (replay benchmarks and
tests).

:func:`write_synthetic_run` writes, with :class:`~metampc_recording.mcap_writer.Rosbag2McapWriter`,
what a lockstep run publishes on the real topics and types: per tick ``y``, ``u`` and
``mpc_status`` (horizon N), plus ``plant_info``, ``nssm_weights`` and the ``progress`` of a
meta-training and an adaptation job. :class:`SyntheticRun` sets the episodes (a reset every
``episode_steps``), the skipped steps (``missed_every``), a live change at ``retune_tick`` and
``foreign_inputs`` (extra ``u`` of another publisher). Deterministic: the expected metrics
follow from the configuration. No rclpy here.
"""
from dataclasses import dataclass, field
from typing import Dict, List, Tuple

from mcap_ros2._dynamic import serialize_dynamic
from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
from metampc_recording.msg_schema import DefinitionSource
from metampc_recording.rosbag2_qos import QosProfile

TICK_NS = 10_000_000          # 100 Hz
START_NS = 1_700_000_000 * 10 ** 9
TYPES = {'/y': 'PlantOutput', '/u': 'ControlInput', '/mpc_status': 'MpcStatus',
         '/plant_info': 'PlantInfo', '/nssm_weights': 'NssmWeights',
         '/progress': 'TrainingProgress'}


@dataclass
class SyntheticRun:
    """What :func:`write_synthetic_run` writes.

    Attributes:
        ticks: plant outputs (one y each; most answered by a u and an mpc_status).
        episode_steps: outputs per episode (the plant resets after each).
        missed_every: the controller does not answer the steps k with k % missed_every == 5
            (0: it answers every step).
        retune_tick: the tick from which MpcStatus.config_version is 1 (0: never).
        horizon: N, rows of u_plan, y_pred and y_ref.
        foreign_inputs: (tick, step) of each u of another publisher, written after that tick.
        run_config: the ``metampc`` metadata record.
        chunk_size: uncompressed bytes per chunk (the recorder's default).
    """

    ticks: int
    episode_steps: int = 5000
    missed_every: int = 1000
    retune_tick: int = 0
    horizon: int = 20
    foreign_inputs: List[Tuple[int, int]] = field(default_factory=list)
    run_config: Dict[str, object] = field(default_factory=lambda: {'tracked_outputs': [0]})
    chunk_size: int = 1024 * 1024

    def step(self, tick: int) -> int:
        """The plant step of a tick."""
        return tick % self.episode_steps

    def answered(self, tick: int) -> bool:
        """Whether the controller answers the output of a tick."""
        return not (self.missed_every and self.step(tick) % self.missed_every == 5)


def _header(tick: int) -> dict:
    ns = tick * TICK_NS
    return {'stamp': {'sec': ns // 10 ** 9, 'nanosec': ns % 10 ** 9}, 'frame_id': ''}


def _progress(phase: str, total: int) -> List[dict]:
    """The messages of one training job: iteration 0 at its start, each step, then 'done'."""
    steps = [{'phase': phase, 'method': 'imaml', 'iteration': i, 'total': total,
              'loss': 1.0 / (i + 1), 'elapsed': 0.1 * i} for i in range(total + 1)]
    return steps + [{**steps[-1], 'phase': 'done'}]


def write_synthetic_run(path: str, run: SyntheticRun) -> int:
    """Write `run` to a new MCAP file `path`; returns the number of messages written."""
    definitions = DefinitionSource()
    writer = Rosbag2McapWriter(McapWriterConfig(path, run.chunk_size, 'lz4', run.run_config))
    encode = {}
    for topic, kind in TYPES.items():
        name = f'metampc_msgs/msg/{kind}'
        writer.add_topic(topic, name, [QosProfile(history='unknown', depth=0,
                                                  liveliness='automatic')])
        encode[topic] = serialize_dynamic(name, definitions.get(name).text)[name]
    count = 0
    sequence = {topic: 0 for topic in TYPES}

    def put(topic: str, msg: dict, t: int, own: bool = True) -> None:
        nonlocal count
        sequence[topic] += own
        writer.write(topic, encode[topic](msg), t, t, sequence[topic] if own else 1)
        count += 1

    put('/plant_info', {'family': 'vanderpol', 'dt': 0.01, 'u_min': [-2.0], 'u_max': [2.0],
                        'clock_mode': 'lockstep'}, START_NS - 2)
    put('/nssm_weights', {'version': 1, 'method': 'imaml', 'stage': 'meta'}, START_NS - 1)
    jobs = _progress('meta_train', 3) + _progress('adapt', 2)
    foreign = dict(run.foreign_inputs)
    n = run.horizon
    for tick in range(run.ticks):
        t = START_NS + tick * TICK_NS
        k, header = run.step(tick), _header(tick)
        y = [0.001 * (tick % 997), -0.002 * (tick % 101)]
        put('/y', {'header': header, 'step': k, 'y': y, 'u_applied': [0.1]}, t)
        if run.answered(tick):
            u = 0.5 - y[0]
            put('/u', {'header': header, 'step': k, 'u': [u], 'model_version': 1}, t + 1000)
            put('/mpc_status', {
                'header': header, 'step': k, 'cost': y[0] ** 2, 'solve_time': 1e-3,
                'tick_time': 1.5e-3, 'solver_status': 'solved', 'iterations': 7,
                'model_version': 1, 'config_version': int(bool(run.retune_tick)
                                                          and tick >= run.retune_tick),
                'planner': 'latent_mpc', 'model_status': 'ok', 'u_plan': [u] * n,
                'y_pred': y * n, 'y_ref': [0.5, 0.0] * n, 'q': [1.0, 0.0]}, t + 2000)
        if tick in foreign:
            put('/u', {'step': foreign[tick], 'u': [0.2]}, t + TICK_NS // 2, own=False)
        if jobs and tick % max(1, run.ticks // 16) == 1:
            put('/progress', jobs.pop(0), t + TICK_NS // 2 + 1)
    writer.close()
    return count
