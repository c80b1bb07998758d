"""`ros2 launch` (verbs/launch.py): a refusal before anything starts, a node that dies
reported, and nothing left running after Ctrl-C or SIGKILL of the launcher. The format's rules:
test_launch_yaml.py."""
import os
import signal
import subprocess
import time

import pytest


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
