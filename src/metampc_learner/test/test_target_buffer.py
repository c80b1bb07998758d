"""D_target: the bounded buffer of target samples and its training / held-out split."""
import threading

import numpy as np

from metampc_learner.target_buffer import split_target, TargetBuffer, TargetSamples

NAN = float('nan')


def test_keeps_the_first_capacity_valid_samples_and_counts_the_skipped():
    buf = TargetBuffer(4)
    assert not buf.add(0, [0.0], [1.0, 2.0]), 'y_0 has no input that produced it'
    assert buf.add(1, [0.1], [1.0, 2.0])
    assert not buf.add(2, [NAN], [1.0, 2.0])
    assert not buf.add(3, [0.3], [1.0, float('inf')])
    assert not buf.add(4, [0.4], [1.0, 2.0], diverged=True)
    assert not buf.add(5, [0.5, 0.5], [1.0, 2.0]), 'sizes differ from the first sample'
    assert not buf.add(6, [], [1.0, 2.0])
    for k in range(7, 20):
        buf.add(k, [0.01 * k], [k, -k])
    snap = buf.snapshot()
    assert len(buf) == 4 and buf.full and buf.skipped == 6
    assert snap.steps.tolist() == [1, 7, 8, 9]
    assert snap.u[:, 0].tolist() == [0.1, 0.07, 0.08, 0.09]
    assert snap.y.tolist() == [[1.0, 2.0], [7, -7], [8, -8], [9, -9]]
    assert not buf.add(20, [0.2], [0.0, 0.0]) and buf.skipped == 6, 'full: ignored, not skipped'


def test_counts_the_samples_that_never_arrived():
    buf = TargetBuffer(100)
    for k in (5, 6, 9, 10):                 # 7, 8 lost
        buf.add(k, [0.0], [0.0, 0.0])
    assert buf.lost == 2
    buf.add(0, [0.0], [0.0, 0.0])           # a reset: y_0 (skipped), no loss
    buf.add(1, [0.0], [0.0, 0.0])
    buf.add(3, [0.0], [0.0, 0.0], diverged=True)   # 2 lost; 3 skipped but it arrived
    buf.add(4, [0.0], [0.0, 0.0])
    assert (buf.lost, buf.skipped) == (3, 2)
    buf.add(3, [0.0], [0.0, 0.0])           # a reset whose y_0, y_1 and y_2 never came: y_1, y_2
    assert buf.lost == 5
    assert buf.start() == 7 and buf.lost == 0
    buf.add(50, [0.0], [0.0, 0.0])
    assert buf.lost == 0, 'the first sample after a restart has nothing before it'


def test_restart_clears_and_freeze_keeps():
    buf = TargetBuffer(10)
    for k in range(1, 4):
        buf.add(k, [0.0], [0.0, 0.0])
    buf.freeze()
    assert not buf.enabled and not buf.add(4, [0.0], [0.0, 0.0]) and len(buf) == 3
    assert buf.start() == 3
    assert buf.enabled and len(buf) == 0 and len(buf.snapshot()) == 0
    assert buf.add(9, [1.0], [2.0, 3.0]) and buf.snapshot().steps.tolist() == [9]


def test_concurrent_adds_store_exactly_the_capacity():
    buf = TargetBuffer(1500)

    def feed(offset):
        for k in range(1, 1001):
            buf.add(offset + k, [0.0], [float(k), 0.0])

    threads = [threading.Thread(target=feed, args=(10000 * i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    snap = buf.snapshot()
    assert len(buf) == 1500 and snap.steps.shape == (1500,) and len(set(snap.steps)) == 1500


def _samples(steps, y_big=()):
    steps = np.asarray(steps)
    u = np.arange(steps.size, dtype=float)[:, None]     # u = arrival index
    y = 0.1 * np.stack([u[:, 0], -u[:, 0]], axis=1)
    y[list(y_big)] = 50.0
    return TargetSamples(steps, u, y)


def _runs(trajectories):
    return [(t.steps.tolist(), t.u[:, 0].astype(int).tolist()) for t in trajectories]


def test_split_holds_out_the_last_samples_and_cuts_at_gaps_and_resets():
    # Episode 1: steps 1..10; a plant reset; episode 2: steps 1..10 (arrival order).
    samples = _samples(list(range(1, 11)) + list(range(1, 11)))
    train, held, used = split_target(samples, 0, 0.25, state_bound=10.0)
    assert used == 20
    assert _runs(train) == [(list(range(1, 11)), list(range(10))),
                            ([1, 2, 3, 4, 5], [10, 11, 12, 13, 14])]
    assert _runs(held) == [([6, 7, 8, 9, 10], [15, 16, 17, 18, 19])]

    train, held, used = split_target(samples, 8, 0.25, state_bound=10.0)
    assert used == 8 and _runs(train) == [([1, 2, 3, 4, 5, 6], list(range(6)))]
    assert _runs(held) == [([7, 8], [6, 7])]

    # A lost sample (step 5 missing) and an output beyond the state box split a run.
    gappy = _samples([1, 2, 3, 4, 6, 7, 8, 9, 10, 11], y_big=[7])
    train, held, _ = split_target(gappy, 0, 0.2, state_bound=10.0)
    assert _runs(train) == [([1, 2, 3, 4], [0, 1, 2, 3]), ([6, 7, 8], [4, 5, 6])]
    assert _runs(held) == [([10, 11], [8, 9])]
    assert split_target(_samples([]), 0, 0.2, 10.0) == ([], [], 0)
