"""Parameters declared once (metampc_common.params): the declaration table, parsing with type
and range checks, renames and prefixes, and the checks of configs built in code."""
from dataclasses import dataclass, field
from typing import Tuple

import numpy as np
import pytest

from metampc_common.params import (build, check_fields, param, ParameterError, ParamSpec,
                                   Section, table)


@dataclass
class Inner:
    rate: float = param(0.5, 'a rate', gt=0, le=1)
    steps: int = param(3, 'steps', ge=0)
    kind: str = param('a', 'a kind', choices=('a', 'b'))
    flag: bool = param(True, 'a flag')
    widths: Tuple[int, ...] = param((4, 4), 'widths', ge=1)
    point: Tuple[float, ...] = param((0.0, 0.0), 'a point', length=2)
    names: Tuple[str, ...] = param((), 'names', item=str)
    seed: int = param(0, 'a seed', ge=0)
    hidden: float = 1.0             # not a parameter

    def validate(self):
        check_fields(self)
        if self.steps > 10 * len(self.widths):
            raise ValueError('steps too many for the widths')


@dataclass
class Outer:
    inner: Inner = field(default_factory=Inner)
    period: float = param(1.0, 'a period, s', gt=0)


INNER = Section(Inner, 'in_', rename={'seed': 'inner_seed'})
OUTER = Section(Outer)


def _values(**overrides):
    values = {name: spec.default for name, spec in table([INNER, OUTER]).items()}
    values.update(overrides)
    return values


def test_table_names_defaults_and_ranges_from_the_fields():
    got = table([INNER, OUTER])
    assert list(got) == ['in_rate', 'in_steps', 'in_kind', 'in_flag', 'in_widths', 'in_point',
                         'in_names', 'inner_seed', 'period']
    assert got['in_rate'] == ParamSpec(0.5, 'a rate (in (0, 1])')
    assert got['in_steps'] == ParamSpec(3, 'steps (>= 0)')
    assert got['in_kind'] == ParamSpec('a', 'a kind (one of a, b)')
    assert got['in_flag'] == ParamSpec(True, 'a flag')
    assert got['in_widths'] == ParamSpec([4, 4], 'widths (>= 1)')     # lists, as ROS declares
    assert got['period'] == ParamSpec(1.0, 'a period, s (> 0)')
    with pytest.raises(ValueError, match='declared twice'):
        table([INNER, Section(Inner, 'in_')])


def test_build_types_the_values_and_nests():
    outer = build(OUTER, _values(period=2), inner=build(INNER, _values(
        in_rate=1, in_widths=[8, 16], in_point=[1, 2], in_names=['x'], inner_seed=5)))
    assert outer == Outer(Inner(rate=1.0, widths=(8, 16), point=(1.0, 2.0), names=('x',),
                                seed=5), period=2.0)
    assert isinstance(outer.period, float) and isinstance(outer.inner.rate, float)


@pytest.mark.parametrize('overrides, message', [
    ({'in_rate': 0.0}, 'in_rate must be in (0, 1], got 0'),
    ({'in_rate': 1.5}, 'in_rate must be in (0, 1], got 1.5'),
    ({'in_rate': float('nan')}, 'in_rate must be finite'),
    ({'in_rate': 'fast'}, "in_rate must be a number, got 'fast'"),
    ({'in_rate': True}, 'in_rate must be a number, got True'),
    ({'in_steps': 2.0}, 'in_steps must be an integer, got 2.0'),
    ({'in_steps': -1}, 'in_steps must be >= 0, got -1'),
    ({'in_kind': 'c'}, "in_kind must be one of a, b, got 'c'"),
    ({'in_flag': 1}, 'in_flag must be true or false, got 1'),
    ({'in_widths': 'wide'}, "in_widths must be a list of integers, got 'wide'"),
    ({'in_widths': [4, 0]}, 'in_widths must be >= 1, got 0'),
    ({'in_point': [1.0]}, 'in_point must be a list of 2 numbers, got [1.0]'),
    ({'in_names': [3]}, 'in_names must be a string, got 3'),
    ({'inner_seed': -2}, 'inner_seed must be >= 0, got -2'),
    ({'in_steps': 30}, 'steps too many for the widths'),      # the config's own rule
])
def test_build_names_the_first_bad_parameter(overrides, message):
    with pytest.raises(ParameterError) as err:
        build(INNER, _values(**overrides))
    assert str(err.value).startswith(message)


def test_configs_built_in_code_are_checked_by_field_name():
    Inner(steps=np.int64(4), rate=np.float32(0.25)).validate()   # numpy scalars are numbers
    with pytest.raises(ValueError, match='rate must be in'):
        Inner(rate=2.0).validate()
    with pytest.raises(ValueError, match='kind must be one of a, b'):
        Inner(kind='z').validate()
    check_fields(Inner(rate=2.0), skip=('rate',))


def test_an_empty_list_from_the_command_line_is_the_empty_list():
    """rclpy types `-p name:=[]` as NOT_SET (value None), as checked on rclpy itself, and an
    empty list of no declared type as an empty byte array."""
    import rclpy
    from rclpy.node import Node
    from rcl_interfaces.msg import ParameterDescriptor
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '-p', 'in_names:=[]', '-p', 'in_widths:=[]'],
               context=context)
    try:
        node = Node('params_empty_list', context=context)
        for name in ('in_names', 'in_widths'):
            node.declare_parameter(name, [7], ParameterDescriptor(dynamic_typing=True))
        given = {n: node.get_parameter(n).value for n in ('in_names', 'in_widths')}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert given == {'in_names': None, 'in_widths': None}
    config = build(INNER, _values(**given, in_steps=0))
    assert (config.names, config.widths) == ((), ())
    assert build(INNER, _values(in_names=b'')).names == ()
    with pytest.raises(ParameterError, match='in_rate must be a number, got None'):
        build(INNER, _values(in_rate=None))


@dataclass
class Mode:
    mode: str = param('off', 'a mode', choices=('off', 'periodic'))


def test_off_read_by_ros_as_a_yaml_boolean_is_the_choice_off():
    """`-p mode:=off` reaches the node as False (YAML 1.1); a choice spelled off is meant."""
    section = Section(Mode)
    assert build(section, {'mode': False}) == Mode('off')
    with pytest.raises(ParameterError, match="mode must be a string, got True"):
        build(section, {'mode': True})      # `on` is not a choice here
