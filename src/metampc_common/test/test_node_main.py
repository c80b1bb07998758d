"""Live parameters (metampc_common.node_main.LiveParameters) on an rclpy node in-process: a
change is parsed as at start-up and refused with the start-up message, or applied; the
parameters not marked live are read-only (rclpy's own refusal)."""
from dataclasses import dataclass
from typing import Tuple

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from metampc_common.node_main import declare_parameters, LiveParameters
from metampc_common.params import build, param, ParameterError, Section, table


@dataclass
class Config:
    rate: float = param(0.5, 'a rate', gt=0, le=1, live=True)
    weights: Tuple[float, ...] = param((1.0,), 'weights', gt=0, scalar=True, live=True)
    low: float = param(-1.0, 'lower bound', live=True)
    high: float = param(1.0, 'upper bound', live=True)
    steps: int = param(3, 'steps', ge=0)

    def validate(self):
        if self.low > self.high:
            raise ValueError(f'need low <= high, got {self.low}, {self.high}')


SECTION = Section(Config)
TABLE = table([SECTION])


def parse(values):
    return build(SECTION, values)


def startup_error(**values) -> str:
    """The line a start with these values fails with (after 'invalid parameter: ')."""
    with pytest.raises(ParameterError) as err:
        parse({**{n: s.default for n, s in TABLE.items()}, **values})
    return str(err.value)


class Harness:
    """A node with the table declared and LiveParameters watching it; applied configs kept."""

    def __init__(self, check=lambda config: ''):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('live_params_test', context=self.context)
        values = declare_parameters(self.node, TABLE)
        self.applied = []
        self.live = LiveParameters(self.node, TABLE, values, parse(values), parse,
                                   lambda config, changes: self.applied.append((config, changes)),
                                   check=check)

    def set(self, **values):
        """One set_parameters call per value, as `ros2 param set` makes; the results."""
        return self.node.set_parameters([Parameter(n, value=v) for n, v in values.items()])

    def value(self, name):
        return self.node.get_parameter(name).value

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def harness():
    h = Harness()
    yield h
    h.close()


def test_table_marks_live_parameters_and_the_node_declares_the_others_read_only(harness):
    assert [n for n, spec in TABLE.items() if spec.live] == ['rate', 'weights', 'low', 'high']
    described = {d.name: d.read_only for d in harness.node.describe_parameters(list(TABLE))}
    assert described == {'rate': False, 'weights': False, 'low': False, 'high': False,
                         'steps': True}


def test_accepted_change_hands_the_new_config_to_the_node(harness):
    [result] = harness.set(rate=0.25)
    assert result.successful and result.reason == ''
    assert harness.applied == [(Config(rate=0.25), {'rate': 0.25})]
    assert harness.value('rate') == 0.25 and harness.live.config == Config(rate=0.25)
    # A lone number for a list (scalar=True), as at start-up; the earlier change is kept.
    [result] = harness.set(weights=2)
    assert result.successful
    assert harness.applied[-1] == (Config(rate=0.25, weights=(2.0,)), {'weights': 2})


@pytest.mark.parametrize('values, expected', [
    ({'rate': 1.5}, 'rate must be in (0, 1], got 1.5'),
    ({'rate': 'fast'}, "rate must be a number, got 'fast'"),
    ({'weights': [1.0, -2.0]}, 'weights must be > 0, got -2'),
    ({'low': 2.0}, 'need low <= high, got 2.0, 1.0'),        # the config's own validate()
])
def test_out_of_range_is_refused_with_the_startup_message(harness, values, expected):
    [result] = harness.set(**values)
    assert not result.successful
    assert result.reason == expected == startup_error(**values)
    assert harness.applied == []
    name = next(iter(values))
    assert harness.value(name) == TABLE[name].default      # the node goes on with its value


def test_read_only_parameter_is_refused_by_rclpy(harness):
    [result] = harness.set(steps=5)
    assert not result.successful
    assert result.reason == 'Trying to set a read-only parameter: steps.'
    assert harness.applied == [] and harness.value('steps') == 3


def test_an_atomic_change_is_checked_as_a_whole():
    h = Harness()
    try:
        # low above the old high alone is refused; with a new high in the same call it is not.
        assert not h.set(low=2.0)[0].successful
        result = h.node.set_parameters_atomically([Parameter('low', value=2.0),
                                                   Parameter('high', value=3.0)])
        assert result.successful
        assert h.applied == [(Config(low=2.0, high=3.0), {'low': 2.0, 'high': 3.0})]
    finally:
        h.close()


def test_node_check_refuses_with_its_reason_and_an_unchanged_config_is_not_applied_again():
    h = Harness(check=lambda c: 'rate above 0.8 not now' if c.rate > 0.8 else '')
    try:
        [result] = h.set(rate=0.9)
        assert (result.successful, result.reason) == (False, 'rate above 0.8 not now')
        [result] = h.set(rate=0.5)          # the value it has: accepted, nothing to apply
        assert result.successful and h.applied == []
        [result] = h.set(use_sim_time=True)     # rclpy's own parameter: not ours to judge
        assert result.successful and h.applied == []
    finally:
        h.close()


@dataclass
class Renamed:
    count: int = param(2, 'count', ge=0, formerly='n')
    mode: str = param('fast', 'mode', choices=('fast', 'slow'), renamed={'quick': 'fast'},
                      live=True)


RENAMED = Section(Renamed, 'my_')


@pytest.fixture
def renamed_node(monkeypatch):
    """make(*ros_args): a node given those arguments (closed at the end); warnings not yet
    written in this process (each is written once per process)."""
    from metampc_common import renames
    monkeypatch.setattr(renames, '_written', set())
    made = []

    def make(*args):
        context = rclpy.Context()
        rclpy.init(context=context)
        made.append((context, Node('renamed_test', context=context,
                                   cli_args=['--ros-args', *args])))
        return made[-1][1]
    yield make
    for context, node in made:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_former_name_is_declared_under_todays_with_one_warning(renamed_node, capsys):
    node = renamed_node('-p', 'my_n:=5')
    values = declare_parameters(node, table([RENAMED]))
    assert values == {'my_count': 5, 'my_mode': 'fast'}
    assert node.get_parameter('my_count').value == 5
    assert capsys.readouterr().err == ('warning: my_n is renamed my_count; the old name will be '
                                       'removed in the next release\n')
    node = renamed_node('-p', 'my_n:=5', '-p', 'my_count:=5')
    with pytest.raises(ParameterError, match='^my_n and my_count are both given: my_n is '
                                             'renamed my_count; give my_count only$'):
        declare_parameters(node, table([RENAMED]))


def test_a_renamed_choice_works_at_start_and_live_with_one_warning(renamed_node, capsys):
    node = renamed_node('-p', 'my_mode:=quick')
    spec = table([RENAMED])

    def parse_renamed(values):
        return build(RENAMED, values)
    values = declare_parameters(node, spec)
    applied = []
    live = LiveParameters(node, spec, values, parse_renamed(values), parse_renamed,
                          lambda config, changes: applied.append(config))
    assert live.config == Renamed(mode='fast')
    assert node.set_parameters([Parameter('my_mode', value='slow')])[0].successful
    assert node.set_parameters([Parameter('my_mode', value='quick')])[0].successful
    assert applied == [Renamed(mode='slow'), Renamed(mode='fast')]
    assert capsys.readouterr().err == ("warning: my_mode: 'quick' is renamed 'fast'; the old "
                                       'value will be removed in the next release\n')


def test_a_task_made_but_not_run_before_the_stop_leaves_no_unawaited_coroutine():
    """Issue 52: the learner printed 'RuntimeWarning: coroutine ... was never awaited' on
    Ctrl-C after service calls by hand: rclpy makes a task's coroutine when an entity is
    ready, and a spin that ended before running it left the coroutine to the garbage
    collector."""
    import gc
    import warnings
    from rclpy.executors import SingleThreadedExecutor
    from metampc_common.node_main import _stop_executor

    async def callback():
        pass

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        executor = SingleThreadedExecutor(context=context)
        executor.create_task(callback)      # made, as for a ready service, never run
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter('always')
            _stop_executor(executor, None)
            del executor
            gc.collect()
        assert not [w for w in caught if 'was never awaited' in str(w.message)], caught
    finally:
        rclpy.try_shutdown(context=context)
