"""`ros2 param list|get|set|dump|load` against a live controller (and a realtime plant) in the
test's own ROS domain.

Each output is checked against ros2param's (Jazzy) formats and against what the node reports
to a probe that calls its parameter services itself (rcl_interfaces requests, no CLI code) or
publishes (the plant's plant_info)."""
import subprocess

import pytest
import yaml
from metampc_controller.controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from metampc_msgs.msg import PlantInfo
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

NODE = '/controller'
# Discovery of a fresh participant with localhost-only discovery can take ~3 s (see
# test_graph_verbs); --timeout is ros2param's own wait for the node.
WAIT = ('--timeout', '10')
LIST = ('--spin-time', '4')
TYPE_NAMES = {ParameterType.PARAMETER_BOOL: 'boolean', ParameterType.PARAMETER_INTEGER: 'integer',
              ParameterType.PARAMETER_DOUBLE: 'double', ParameterType.PARAMETER_STRING: 'string',
              ParameterType.PARAMETER_BYTE_ARRAY: 'byte array',
              ParameterType.PARAMETER_DOUBLE_ARRAY: 'double array',
              ParameterType.PARAMETER_INTEGER_ARRAY: 'integer array',
              ParameterType.PARAMETER_STRING_ARRAY: 'string array'}


def ros2(*args, timeout=60.0):
    return subprocess.run(['ros2', *args], capture_output=True, text=True, timeout=timeout)


class Parameters:
    """The controller's parameter services, called by the probe."""

    def __init__(self, probe):
        self.probe = probe
        self.infos = []
        probe.node.create_subscription(PlantInfo, 'plant_info', self.infos.append, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.clients = {name: probe.node.create_client(srv, f'{NODE}/{name}') for name, srv in (
            ('list_parameters', ListParameters), ('get_parameters', GetParameters),
            ('describe_parameters', DescribeParameters))}
        for client in self.clients.values():
            assert client.wait_for_service(timeout_sec=60.0)

    def call(self, name, **fields):
        request = self.clients[name].srv_type.Request(**fields)
        future = self.clients[name].call_async(request)
        self.probe.wait_for(future.done, 30.0, name)
        return future.result()

    def names(self):
        return sorted(self.call('list_parameters').result.names)

    def values(self, names):
        """{name: (type, python value)}."""
        from rclpy.parameter import parameter_value_to_python
        got = self.call('get_parameters', names=list(names)).values
        return {n: (v.type, parameter_value_to_python(v)) for n, v in zip(names, got)}


@pytest.fixture(scope='module')
def params(tmp_path_factory):
    """One controller for the module (each test reads what it compares from the node)."""
    from metampc_testing import ProcessGroup, TestNode
    group = ProcessGroup(str(tmp_path_factory.mktemp('logs')))
    probe = TestNode()
    try:
        group.start('metampc_controller', 'controller', params={'horizon': 12, 'r': [0.05]})
        group.start('metampc_plant', 'plant', params={'mode': 'realtime', 'rate_hz': 20.0})
        yield Parameters(probe)
    finally:
        group.stop_all()
        probe.close()


def test_list_prints_the_names_the_node_lists(params):
    names = params.names()
    assert {'horizon', 'r', 'q', 'rate_hz', 'use_sim_time', 'reference_values'} <= set(names)
    out = ros2('param', 'list', NODE, *LIST)
    assert (out.returncode, out.stderr) == (0, '')
    assert out.stdout.splitlines() == [f'  {n}' for n in names]

    every = ros2('param', 'list', *LIST)
    assert every.returncode == 0
    lines = every.stdout.splitlines()
    assert lines[lines.index(f'{NODE}:') + 1:][:len(names)] == [f'  {n}' for n in names]

    typed = ros2('param', 'list', NODE, '--param-type', '--filter', '^reference_', *LIST)
    references = [n for n in names if n.startswith('reference_')]
    described = params.call('describe_parameters', names=references)
    assert references == sorted(n for n in CONTROLLER_PARAMETERS if n.startswith('reference_'))
    assert typed.stdout.splitlines() == [f'  {d.name} (type: {TYPE_NAMES[d.type]})'
                                         for d in described.descriptors]
    assert ros2('param', 'list', '/no_such_node').stderr == 'Node not found\n'


def test_get_prints_the_value_with_its_label(params):
    labels = {'horizon': 'Integer value is:', 'rate_hz': 'Double value is:',
              'active': 'Boolean value is:', 'planner': 'String value is:',
              'r': 'Double values are:', 'reference_outputs': 'Integer values are:'}
    values = params.values(list(labels))
    assert {n: TYPE_NAMES[kind].split()[0] for n, (kind, _) in values.items()} == {
        n: label.split()[0].lower() for n, label in labels.items()}
    for name, label in labels.items():
        out = ros2('param', 'get', NODE, name, *WAIT)
        assert (out.returncode, out.stdout, out.stderr) == (0, f'{label} {values[name][1]}\n', '')
    out = ros2('param', 'get', NODE, 'r', '--hide-type', *WAIT)
    assert out.stdout == f"{values['r'][1]}\n"


def test_describe_prints_the_nodes_descriptors(params):
    names = ['r', 'rate_hz']
    described = params.call('describe_parameters', names=names).descriptors
    out = ros2('param', 'describe', NODE, *names, *WAIT)
    assert (out.returncode, out.stderr) == (0, ''), out
    expected = []
    for d in described:
        expected += [f'Parameter name: {d.name}', f'  Type: {TYPE_NAMES[d.type]}',
                     f'  Description: {d.description}', '  Constraints:']
        expected += ['    Read only: true'] if d.read_only else []
    assert out.stdout.splitlines() == expected
    # r is live (ros2 param set takes it), rate_hz read-only: the node says so
    assert [d.read_only for d in described] == [False, True]


def test_get_of_what_is_not_there_is_an_error_line(params):
    out = ros2('param', 'get', NODE, 'no_such_parameter', *WAIT)
    assert (out.returncode, out.stdout, out.stderr) == (1, '', 'Parameter not set\n')
    out = ros2('param', 'get', '/no_such_node', 'r')
    assert (out.returncode, out.stderr) == (1, 'Node not found\n')


def test_set_changes_a_live_parameter_and_prints_the_refusals(params):
    before = params.values(['horizon', 'u_min', 'rate_hz'])
    out = ros2('param', 'set', NODE, 'r', '0.2', *WAIT)
    assert (out.returncode, out.stdout, out.stderr) == (0, 'Set parameter successful\n', '')
    assert params.values(['r']) == {'r': (ParameterType.PARAMETER_DOUBLE, 0.2)}

    # Out of range: the start-up message, on stderr, exit 0 as ros2param; nothing changed.
    out = ros2('param', 'set', NODE, 'horizon', '0', *WAIT)
    assert (out.returncode, out.stdout) == (0, '')
    assert out.stderr == 'Setting parameter failed: horizon must be >= 1, got 0\n'
    out = ros2('param', 'set', NODE, 'u_min', '[2.0]', *WAIT)
    assert out.stderr == 'Setting parameter failed: need u_min <= u_max, got (2.0,), (1.0,)\n'
    # Not live: rclpy's own refusal.
    out = ros2('param', 'set', NODE, 'rate_hz', '5.0', *WAIT)
    assert out.stderr == ('Setting parameter failed: Trying to set a read-only parameter: '
                          'rate_hz.\n')
    assert params.values(['horizon', 'u_min', 'rate_hz']) == before


def test_dump_is_the_node_parameters_as_a_parameter_file(params):
    names = params.names()
    out = ros2('param', 'dump', NODE, *WAIT)
    assert (out.returncode, out.stderr) == (0, '')
    assert out.stdout.startswith(f'{NODE}:\n  ros__parameters:\n') and out.stdout.endswith('\n\n')
    dumped = yaml.safe_load(out.stdout)
    assert dumped == {NODE: {'ros__parameters': {
        n: value for n, (_, value) in params.values(names).items()}}}


def test_load_sets_each_parameter_of_the_file(params, tmp_path):
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump({NODE: {'ros__parameters': {
        'horizon': 15, 'r': [0.3], 'rate_hz': 5.0, 'q': [1.0, -1.0]}}}, sort_keys=False))
    out = ros2('param', 'load', NODE, str(path), *WAIT)
    assert out.returncode == 0
    assert out.stdout.splitlines() == ['Set parameter horizon successful',
                                       'Set parameter r successful']
    assert out.stderr.splitlines() == [
        'Set parameter rate_hz failed: Trying to set a read-only parameter: rate_hz.',
        'Set parameter q failed: q must be >= 0, got -1']
    assert params.values(['horizon', 'r', 'rate_hz']) == {
        'horizon': (ParameterType.PARAMETER_INTEGER, 15),
        'r': (ParameterType.PARAMETER_DOUBLE_ARRAY, [0.3]),
        'rate_hz': (ParameterType.PARAMETER_DOUBLE, 10.0)}
    missing = ros2('param', 'load', NODE, str(tmp_path / 'none.yaml'))
    assert missing.returncode == 1 and 'none.yaml' in missing.stderr


def test_the_plant_noise_is_live_and_re_sent_on_plant_info(params):
    params.probe.wait_for(lambda: params.infos, 60.0, 'plant_info')
    assert params.infos[-1].measurement_noise_std == 0.0
    out = ros2('param', 'set', '/plant', 'measurement_noise_std', '0.02', *WAIT)
    assert (out.returncode, out.stdout, out.stderr) == (0, 'Set parameter successful\n', '')
    params.probe.wait_for(lambda: params.infos[-1].measurement_noise_std == 0.02, 30.0,
                          'plant_info with the new noise level')
    for name, value, reason in (
            ('process_noise_std', '-1.0', 'process_noise_std must be >= 0, got -1'),
            ('dt', '0.05', 'Trying to set a read-only parameter: dt.')):
        out = ros2('param', 'set', '/plant', name, value, *WAIT)
        assert (out.returncode, out.stderr) == (0, f'Setting parameter failed: {reason}\n')
