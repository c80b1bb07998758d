"""Replay of synthetic recordings written as the recorder writes them
(metampc_recording.synthetic_run): bounded memory, foreign inputs on u, per-episode step ranges,
one row per training job's end."""
import gc
import re
import subprocess
import sys
import tracemalloc
import weakref
from pathlib import Path

from metampc_bringup.analysis.run_report import analyse
from metampc_bringup.analysis.input_sources import controller_inputs
from metampc_bringup.analysis.run_series import (CONTROL_INPUT, MPC_STATUS, PLANT_OUTPUT,
                                                 SeriesBuilder)
from metampc_recording.synthetic_run import SyntheticRun, write_synthetic_run
import numpy as np
import pytest

REPLAY = str(Path(__file__).resolve().parents[3] / 'scripts' / 'replay.py')


def replay(path, out):
    """The report of `scripts/replay.py PATH --json` and its summary table."""
    result = subprocess.run([sys.executable, REPLAY, str(path), '--no-plots', '--out', str(out)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return analyse(str(path), out_dir=str(out), plots=False), result.stdout


class Message:
    """A message the builder reads attributes of, which can be watched with a weak reference."""

    def __init__(self, **fields):
        self.__dict__.update(fields)


def test_the_series_builder_keeps_no_message():
    builder = SeriesBuilder()
    header = Message(stamp=Message(sec=1, nanosec=0))
    alive = []
    for k in range(200):
        msgs = [(PLANT_OUTPUT, Message(header=header, step=k, y=[0.1 * k, 1.0], u_applied=[0.0],
                                       saturated=False, diverged=False)),
                (CONTROL_INPUT, Message(header=header, step=k, u=[0.5], model_version=1)),
                (MPC_STATUS, Message(
                    header=header, step=k, cost=1.0, solve_time=1e-3, tick_time=2e-3,
                    solver_status='solved', iterations=3, fallback=False,
                    terminal_fallback=False, model_version=1, planner='latent_mpc',
                    y_ref=[1.0, 0.0] * 50, q=[1.0, 0.0], config_version=0))]
        for type_name, msg in msgs:
            builder.add(type_name, msg, k)
            alive.append(weakref.ref(msg))
        del msgs, msg
    gc.collect()
    assert sum(ref() is not None for ref in alive) == 0
    series = builder.build()
    assert series.outputs.step.tolist() == series.inputs.step.tolist() == list(range(200))
    assert series.status.y_ref0.tolist() == [[1.0, 0.0]] * 200


def test_replay_memory_does_not_grow_with_the_message_size(tmp_path):
    # 8000 ticks whose MpcStatus plans are 50 rows long (y_ref alone 100 values): the
    # replay keeps a few numbers per message, not the messages (about 260 bytes a message
    # where holding them took 2.8 kB a message with a 20-row horizon).
    path = tmp_path / 'long.mcap'
    n = write_synthetic_run(str(path), SyntheticRun(ticks=8000, horizon=50))
    tracemalloc.start()
    try:
        report = analyse(str(path), out_dir=str(tmp_path), plots=False, report_name=None)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert report['recording']['message_count'] == n > 20_000
    assert peak / n < 600, f'{peak / n:.0f} bytes a message at the peak'


PLAY_PEAK = """import sys, tracemalloc
from metampc_recording.player import PlayConfig, run_player
tracemalloc.start()
counts = run_player(sys.argv[1], PlayConfig(rate=1e6))
print(sum(counts.values()), tracemalloc.get_traced_memory()[1])"""


def test_play_streams_the_recording(tmp_path):
    # --play of 2000 and of 8000 ticks (horizon 50), as fast as it goes (no subscriber): the
    # peak of Python's allocations does not grow with the recording's length.
    got = {}
    for ticks in (2000, 8000):
        path = _written(tmp_path / f'{ticks}.mcap', SyntheticRun(ticks=ticks, horizon=50))
        child = subprocess.run([sys.executable, '-c', PLAY_PEAK, str(path)],
                               capture_output=True, text=True, timeout=300)
        assert child.returncode == 0, child.stderr
        got[ticks] = [int(v) for v in child.stdout.split()[-2:]]
    (short, short_peak), (long, long_peak) = got[2000], got[8000]
    assert long - short > 17_000
    assert long_peak - short_peak < 1_000_000, f'{(long_peak - short_peak) / 2 ** 20:.1f} MiB'


def test_an_injected_input_is_counted_apart_and_breaks_nothing(tmp_path):
    # docs/nodes.md's `ros2 topic pub --once /u "{step: 3, ...}"` in the middle of a run.
    run = SyntheticRun(ticks=3000, episode_steps=1000, missed_every=100)
    clean, _ = replay(_written(tmp_path / 'clean.mcap', run), tmp_path / 'a')
    run.foreign_inputs = [(1500, 3)]
    injected, table = replay(_written(tmp_path / 'injected.mcap', run), tmp_path / 'b')
    m0, m1 = clean['metrics'], injected['metrics']
    answered = sum(run.answered(t) for t in range(3000))
    window = 2999   # every output but the last; the answer to the last is not counted
    assert m1['ticks'] == m0['ticks'] == {'considered': window, 'answered': answered - 1,
                                          'missed': window - answered + 1}
    assert m0['ticks']['missed'] == 30      # step % 100 == 5, 10 per episode
    assert m1['tracking'] == m0['tracking']
    assert m1['samples'] == m0['samples'] and m1['samples']['inputs'] == answered
    assert m0['foreign_inputs'] == {'count': 0, 'steps': [], 'log_times': []}
    assert m1['foreign_inputs']['count'] == 1 and m1['foreign_inputs']['steps'] == [3]
    assert re.search(r'foreign inputs \(u not from the controller\) +1 \(steps 3\)', table)
    assert injected['recording']['topics']['/u']['count'] == answered + 1


def test_a_foreign_input_of_another_width_is_counted_not_an_error():
    # `ros2 topic pub --once /u ... "{step: 3, u: [0.2, 0.1]}"` to a plant of one input.
    builder = SeriesBuilder()
    header = Message(stamp=Message(sec=0, nanosec=0))
    for k in range(6):
        builder.add(CONTROL_INPUT, Message(header=header, step=k, u=[0.1 * k],
                                           model_version=1), 10 * k)
        builder.add(MPC_STATUS, Message(
            header=header, step=k, cost=0.0, solve_time=0.0, tick_time=0.0,
            solver_status='solved', iterations=1, fallback=False, terminal_fallback=False,
            model_version=1, planner='latent_mpc', y_ref=[], q=[]), 10 * k + 1)
        if k == 4:
            builder.add(CONTROL_INPUT, Message(header=header, step=3, u=[0.2, 0.1],
                                               model_version=0), 10 * k + 5)
    series = builder.build()
    assert series.inputs.step.tolist() == list(range(6))
    assert series.inputs.u[:, 0].tolist() == [0.1 * k for k in range(6)]
    assert series.foreign_inputs.step.tolist() == [3]
    assert series.foreign_inputs.u.tolist() == [[0.2, 0.1]]


def test_pairing_is_by_step_and_stamp_and_not_across_episodes():
    # Episode 0 (steps 0..9, stamps 0.0..0.9) and episode 1 (steps 0..14, stamps 1.0..2.4), the
    # stamps of a lockstep plant (n dt, never back). A foreign input of step 12 stamped 0 (as
    # `ros2 topic pub` sends it) and a second input of episode 0's (3, 0.3) recorded after the
    # controller's own: both foreign, and no other.
    keys = [(k, 0.1 * k) for k in range(10)] + [(k, 1.0 + 0.1 * k) for k in range(15)]
    statuses = np.array(keys)
    inputs = np.array([(12, 0.0)] + keys[:5] + [(3, 0.3)] + keys[5:])
    ours = controller_inputs(inputs[:, 0].astype(int), inputs[:, 1],
                             statuses[:, 0].astype(int), statuses[:, 1])
    assert np.flatnonzero(~ours).tolist() == [0, 6]
    no_status = np.array([], dtype=float)
    assert controller_inputs(np.array([5, 5]), np.array([0.5, 0.5]), no_status.astype(int),
                             no_status).tolist() == [True, True]


def test_inputs_recorded_long_after_their_statuses_are_still_the_controller_s():
    # The recorder takes u and mpc_status on two subscriptions; on a loaded machine one topic
    # may fall hundreds of messages behind the other; the former rule (pairing within 100
    # statuses) counted such answers foreign.
    builder = SeriesBuilder()
    status = dict(cost=0.0, solve_time=0.0, tick_time=0.0, solver_status='solved',
                  iterations=1, fallback=False, terminal_fallback=False, model_version=1,
                  planner='latent_mpc', y_ref=[], q=[])
    steps = 500
    for k in range(steps):
        header = Message(stamp=Message(sec=k // 10, nanosec=(k % 10) * 10 ** 8))
        builder.add(MPC_STATUS, Message(header=header, step=k, **status), 10 * k)
        builder.add(CONTROL_INPUT, Message(header=header, step=k, u=[0.1], model_version=1),
                    10 * (k + 300) + 5)
    series = builder.build()
    assert series.inputs.step.tolist() == list(range(steps))
    assert series.foreign_inputs.step.size == 0


def test_step_ranges_stay_within_an_episode(tmp_path):
    # Episodes of 1000 steps; the tuning changes at tick 1500: version 0 spans the reset at
    # tick 1000, version 1 the one at tick 2000.
    run = SyntheticRun(ticks=3000, episode_steps=1000, retune_tick=1500)
    report, table = replay(_written(tmp_path / 'retuned.mcap', run), tmp_path / 'out')
    printed = re.findall(r'(\d+)-(\d+) \(episode (\d+)\)', table)
    assert printed == [('0', '999', '0'), ('0', '499', '1'), ('500', '999', '1'),
                       ('0', '999', '2')], table
    segments = report['metrics']['tracking_segments']
    assert [(s['config_version'], s['ranges']) for s in segments] == [
        (0, [{'episode': 0, 'first_step': 0, 'last_step': 999},
             {'episode': 1, 'first_step': 0, 'last_step': 499}]),
        (1, [{'episode': 1, 'first_step': 500, 'last_step': 999},
             {'episode': 2, 'first_step': 0, 'last_step': 999}])]


def test_the_end_of_each_training_job_is_a_row_of_its_own(tmp_path):
    report, table = replay(_written(tmp_path / 'trained.mcap', SyntheticRun(ticks=600)),
                           tmp_path / 'out')
    assert re.findall(r'^training (.*?)  ', table, re.M) == [
        'meta_train imaml', 'meta_train imaml done', 'adapt imaml', 'adapt imaml done'], table
    rows = [(t['job'], t['phase'], t['iteration'], t['messages'])
            for t in report['metrics']['training']]
    # synthetic_run: meta_train of 3 steps (iteration 0..3, then done), adapt of 2 steps.
    assert rows == [('meta_train', 'meta_train', 3, 4), ('meta_train', 'done', 3, 1),
                    ('adapt', 'adapt', 2, 3), ('adapt', 'done', 2, 1)]


def _written(path, run):
    write_synthetic_run(str(path), run)
    return path


@pytest.fixture(autouse=True)
def _no_leftover_tracemalloc():
    yield
    assert not tracemalloc.is_tracing()
