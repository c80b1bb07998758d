"""`ros2 launch`: ROS 2's YAML launch format read by its rules (the documented examples of ROS
2's "Using XML, YAML, and Python for ROS 2 Launch Files" and launch_ros's frontend test), the
shipped launch files, a refusal before anything starts, a node that dies reported, and nothing
left running after Ctrl-C or SIGKILL of the launcher."""
import os
import signal
import subprocess
import time

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


def ros2_launch(*args, tmp_path, **kwargs):
    env = {**os.environ, 'ROS_LOG_DIR': str(tmp_path / 'log')}
    return subprocess.Popen(['ros2', 'launch', *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env,
                            start_new_session=True, **kwargs)


def test_a_file_that_cannot_run_is_refused_before_anything_starts(tmp_path):
    bad = tmp_path / 'bad.launch.yaml'
    bad.write_text('launch:\n- node: {pkg: metampc_plant, exec: plant}\n'
                   '- node: {pkg: metampc_plant, exec: nope}\n')
    for args in ([str(bad)], ['metampc_bringup', 'nope.launch.yaml'],
                 ['metampc_bringup', 'by_hand.launch.yaml', 'thetaa:=1']):
        proc = ros2_launch(*args, tmp_path=tmp_path)
        out = proc.communicate(timeout=60)[0]
        assert proc.returncode == 2 and len(out.splitlines()) == 1, out
        assert out.startswith('ros2 launch: '), out
    assert not (tmp_path / 'log').exists()


def _by_hand(tmp_path, probe):
    """The by-hand session launched, its four nodes in the graph; the launcher."""
    proc = ros2_launch('metampc_bringup', 'by_hand.launch.yaml',
                       f'output:={tmp_path / "run" / "recording.mcap"}', tmp_path=tmp_path)
    for node in ('recorder', 'plant', 'controller', 'learner'):
        probe.wait_for_node(node, 120.0)
    return proc


def _session_pids(tmp_path):
    """The launcher and everything it started (their environment holds the test's log
    folder)."""
    from metampc_bringup.orchestration.procfs import pids_with_env
    return pids_with_env({'ROS_LOG_DIR': str(tmp_path / 'log')})


def _wait_gone(tmp_path, timeout):
    deadline = time.monotonic() + timeout
    while (left := _session_pids(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.2)
    return left


@pytest.mark.parametrize('signum, said', [
    (signal.SIGINT, 'user interrupted with ctrl-c'), (signal.SIGTERM, 'signal SIGTERM')])
def test_ctrl_c_or_sigterm_stops_every_node_and_reports_each(tmp_path, probe, signum, said):
    proc = _by_hand(tmp_path, probe)
    os.kill(proc.pid, signum)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 0, out
    assert f'[WARNING] [launch]: {said}' in out
    for label in ('recorder-1', 'plant-2', 'controller-3', 'learner-4'):
        assert f'[INFO] [{label}]: process has finished cleanly' in out, out
    assert '[plant-2] [INFO]' in out    # output: screen
    assert (tmp_path / 'run' / 'recording.mcap').stat().st_size > 0
    assert _wait_gone(tmp_path, 5.0) == []


def test_sigkill_of_the_launcher_leaves_nothing_running(tmp_path, probe):
    proc = _by_hand(tmp_path, probe)
    assert len(_session_pids(tmp_path)) >= 8    # a `ros2 run` and a node per node
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert _wait_gone(tmp_path, 5.0) == []


def test_a_node_that_dies_is_reported_and_the_launcher_ends_with_the_last(tmp_path):
    file = tmp_path / 'dies.launch.yaml'
    file.write_text('launch:\n- node:\n    pkg: metampc_plant\n    exec: plant\n'
                    '    param: [{name: thetaa, value: 1.0}]\n')
    proc = ros2_launch(str(file), tmp_path=tmp_path)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 1, out
    assert '[ERROR] [plant-1]: process has died [pid ' in out and 'exit code 2' in out, out
    log = out.rsplit('its output: ', 1)[1].strip()
    assert 'unknown parameter thetaa' in open(log).read()
