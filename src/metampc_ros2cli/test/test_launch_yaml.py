"""ROS 2's YAML launch format read by its rules (launch_yaml): the documented examples of ROS 2's
"Using XML, YAML, and Python for ROS 2 Launch Files" and launch_ros's frontend test, and what
the subset refuses."""
import pytest

from metampc_ros2cli.launch_yaml import LaunchError, read

# The YAML example of ROS 2's how-to guide, its arg and node actions (the include and group
# actions are not of this reader's subset).
ROS_DOCS_EXAMPLE = '''
launch:
# args that can be set from the command line or a default will be used
- arg:
    name: "background_r"
    default: "0"
- arg:
    name: "background_g"
    default: "255"
- arg:
    name: "background_b"
    default: "0"
# start a turtlesim_node in the turtlesim1 namespace
- node:
    pkg: "turtlesim"
    exec: "turtlesim_node"
    name: "sim"
    namespace: "turtlesim1"
# start another turtlesim_node in the turtlesim2 namespace and use args to set parameters
- node:
    pkg: "turtlesim"
    exec: "turtlesim_node"
    name: "sim"
    namespace: "turtlesim2"
    param:
    -
      name: "background_r"
      value: "$(var background_r)"
    -
      name: "background_g"
      value: "$(var background_g)"
    -
      name: "background_b"
      value: "$(var background_b)"
# perform remap so both turtles listen to the same command topic
- node:
    pkg: "turtlesim"
    exec: "mimic"
    name: "mimic"
    remap:
    -
        from: "/input/pose"
        to: "/turtlesim1/turtle1/pose"
    -
        from: "/output/cmd_vel"
        to: "/turtlesim2/turtle1/cmd_vel"
'''


def test_the_ros_docs_example_reads_as_launch_ros_reads_it():
    sim1, sim2, mimic = read(ROS_DOCS_EXAMPLE, [])
    assert (sim1.pkg, sim1.exec, sim1.name, sim1.namespace, sim1.params, sim1.output) == (
        'turtlesim', 'turtlesim_node', 'sim', '/turtlesim1', {}, 'log')
    assert sim2.params == {'background_r': 0, 'background_g': 255, 'background_b': 0}
    assert mimic.remaps == [('/input/pose', '/turtlesim1/turtle1/pose'),
                            ('/output/cmd_vel', '/turtlesim2/turtle1/cmd_vel')]
    assert read(ROS_DOCS_EXAMPLE, ['background_b:=128'])[1].params['background_b'] == 128


def test_parameter_values_are_typed_as_launch_ros_types_them():
    """launch_ros's test_node_frontend (its `let`s as args here): a substituted string is read
    as YAML, a YAML value is kept, the strings of a list stay strings."""
    text = '''
launch:
- arg: {name: a_string, default: "'[2, 5, 8]'"}
- arg: {name: a_list, default: '[2, 5, 8]'}
- node:
    pkg: demo_nodes_py
    exec: talker_qos
    output: screen
    param:
    - {name: param1, value: ads}
    - {name: param2, value: 2}
    - {name: param3, value: [2, 5, 8]}
    - {name: param4, value: $(var a_list)}
    - {name: param5, value: $(var a_string)}
    - {name: param6, value: [2., 5., 8.]}
    - {name: param7, value: ['2', '5', '8']}
    - {name: param12, value: ''}
'''
    node, = read(text, [])
    assert node.output == 'screen'
    assert node.params == {'param1': 'ads', 'param2': 2, 'param3': [2, 5, 8],
                           'param4': [2, 5, 8], 'param5': '[2, 5, 8]',
                           'param6': [2., 5., 8.], 'param7': ['2', '5', '8'], 'param12': ''}


@pytest.mark.parametrize('text, given, message', [
    ('launch:\n- include: {file: x.launch.yaml}\n', [], "'include' is not supported"),
    ('launch:\n- node: {pkg: p, exec: e, args: -v}\n', [], "unsupported keys ['args']"),
    ('launch:\n- node: {pkg: p, exec: e, param: [{from: f.yaml}]}\n', [], 'no parameter files'),
    ('launch:\n- node: {pkg: p, exec: $(find-pkg-share p)}\n', [], 'only $(var NAME)'),
    ('launch:\n- node: {pkg: p, exec: $(var e)}\n', [], "no arg named 'e'"),
    ('launch:\n- arg: {name: e}\n', [], "missing required launch argument(s) ['e']"),
    ('launch:\n- arg: {name: e, default: x}\n', ['f:=1'], "unknown launch argument 'f'"),
    ('launch:\n- arg: {name: e, default: x}\n', ['e=1'], "malformed launch argument 'e=1'"),
    ('nodes: []\n', [], "the one top-level key must be 'launch'"),
])
def test_what_the_subset_lacks_is_refused_by_name(text, given, message):
    with pytest.raises(LaunchError) as err:
        read(text, given)
    assert message in str(err.value) and '\n' not in str(err.value)
