"""ros_args against the reading of its output: every `-p name:=value` value, parsed as YAML
(how rcl reads a parameter override), gives back the value and type given; remaps and the node
name come as `-r` rules in order."""
import yaml

from metampc_common.ros_args import ros_args

VALUES = {'count': 3, 'negative': -12, 'rate': 0.1, 'tiny': -2.5e-07, 'on': True, 'off': False,
          'quote': "it's", 'empty': '', 'number_text': '1.0', 'yaml_word': 'off',
          'path': 'runs/x/recording.mcap', 'floats': [1.0, -0.5], 'ints': [1, 2],
          'bools': [True, False], 'strings': ['a', 'b c', "d'e"]}


def test_every_parameter_value_reads_back_as_given():
    args = ros_args(VALUES)
    assert args[0] == '--ros-args' and args[1::2] == ['-p'] * len(VALUES)
    read = {}
    for rule in args[2::2]:
        name, sep, value = rule.partition(':=')
        assert sep, rule
        read[name] = yaml.safe_load(value)
    assert read == VALUES
    assert {k: type(v) for k, v in read.items()} == {k: type(v) for k, v in VALUES.items()}


def test_remaps_then_the_node_name():
    assert ros_args(remaps={'y': 'plant/y', '/clock': '/sim_clock'}, name='plant_2') == [
        '--ros-args', '-r', 'y:=plant/y', '-r', '/clock:=/sim_clock', '-r', '__node:=plant_2']
    assert ros_args() == ['--ros-args']
