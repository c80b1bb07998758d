"""The lockstep rules, in-process: each against a hand-worked sequence of events.

Times are multiples of 1/8 s, exact in binary, so no expectation hangs on float rounding.
"""
from metampc_plant.lockstep import Lockstep


def rules(dt=0.1, input_timeout=1.0, start_timeout=10.0, now=0.0, settle_s=0.5):
    return Lockstep(dt, input_timeout, start_timeout, now, settle_s)


def test_y0_waits_until_the_match_has_held_for_the_settle_time():
    lock = rules(now=1.0)
    # (now, matched) -> y_0 now? The match starts at 1.25; 1.75 is 0.5 s later.
    events = [(1.0, False), (1.25, True), (1.5, True), (1.625, True), (1.75, True)]
    assert [lock.gate(t, m) for t, m in events] == [False, False, False, False, True]


def test_a_break_in_the_match_restarts_the_settle_time():
    lock = rules()
    # Matched at 0.25, lost at 0.5, matched again from 0.75: settled at 1.25, not 0.75.
    events = [(0.25, True), (0.5, False), (0.75, True), (1.0, True), (1.125, True),
              (1.25, True)]
    assert [lock.gate(t, m) for t, m in events] == [False, False, False, False, False, True]


def test_start_timeout_sends_y0_without_a_match():
    lock = rules(start_timeout=2.0, now=3.0)
    # The gate opened at 3.0: 4.875 is 1.875 s later, 5.0 exactly start_timeout.
    assert [lock.gate(t, False) for t in (3.5, 4.875, 5.0)] == [False, False, True]


def test_start_timeout_cuts_a_match_that_has_not_settled():
    lock = rules(start_timeout=1.0)
    assert [lock.gate(t, True) for t in (0.75, 1.0)] == [False, True]


def test_zero_start_timeout_waits_forever():
    lock = rules(start_timeout=0.0)
    assert not any(lock.gate(t, False) for t in (0.0, 10.0, 1e6))
    assert lock.gate(1e6 + 0.5, True) is False      # matched at 1e6 + 0.5: not settled yet
    assert lock.gate(1e6 + 1.0, True) is True


def test_y0_goes_out_once():
    lock = rules()
    lock.gate(0.0, True)
    assert lock.gate(0.5, True)
    lock.start()
    assert [lock.gate(t, m) for t, m in ((0.625, True), (11.0, False))] == [False, False]


def test_a_reset_before_the_gate_starts_the_plant():
    lock = rules()
    lock.gate(0.0, True)
    lock.start()                                    # the node starts on a reset too
    assert lock.started
    assert lock.gate(0.5, True) is False            # would have settled: y_0 is out already


def test_inputs_before_the_start_are_stale():
    lock = rules()
    assert not lock.started
    assert lock.answers(0, 0) is False


def test_only_an_input_for_the_current_step_answers():
    lock = rules()
    lock.start()
    # Plant at step 3: the input for 3 answers; one for 2 came after a timeout stepped on,
    # one for 4 is ahead of the plant.
    assert [lock.answers(step, 3) for step in (2, 3, 4)] == [False, True, False]
    # A reset brings the step back to 0: an input for 0 answers, a late one for 3 does not.
    assert [lock.answers(step, 0) for step in (0, 3)] == [True, False]


def test_input_timeout():
    assert rules(input_timeout=0.05).timeout_s == 0.05
    assert rules(input_timeout=0.0).timeout_s is None           # wait forever


def test_a_step_the_controller_holds_waits_its_hold_then_the_input_timeout():
    lock = rules(input_timeout=0.5)
    assert lock.hold_timeout_s(3, 3, 20.0) is None              # before the start: stale
    lock.start()
    assert lock.hold_timeout_s(3, 3, 20.0) == 20.5              # the current step
    assert [lock.hold_timeout_s(s, 3, 20.0) for s in (2, 4)] == [None, None]   # other steps
    assert rules(input_timeout=0.0).hold_timeout_s(0, 0, 20.0) is None   # waits forever


def test_stamps_advance_by_dt_per_y_across_resets():
    lock = rules(dt=0.1)
    assert lock.stamp_ns == 0                       # plant_info before y_0
    stamps = []
    for _ in range(4):                              # y_0, y_1, then a reset's y_0, y_1
        lock.published()
        stamps.append(lock.stamp_ns)
    assert stamps == [0, 100_000_000, 200_000_000, 300_000_000]
    assert lock.tick == 3


def test_stamps_are_whole_multiples_of_the_rounded_dt():
    # dt = 1/3 s rounds to 333333333 ns; the 3rd y is at 999999999 ns, not 1 s, so the sim
    # time of sample n is n times one fixed step, without drift from summing floats.
    lock = rules(dt=1 / 3)
    for _ in range(4):
        lock.published()
    assert lock.stamp_ns == 999_999_999
    for _ in range(3000):
        lock.published()
    assert lock.stamp_ns == 3003 * 333_333_333
