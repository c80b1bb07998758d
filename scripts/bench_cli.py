#!/usr/bin/env python3
"""Benchmark the `ros2` verbs a user types first: how long until they answer, and whether the
listings are complete.

Prints ONE JSON line. A realtime plant (y at 10 Hz) and an inactive controller run; for each
discovery range (SUBNET: a user's default; LOCALHOST: what the tests use), in a ROS_DOMAIN_ID of
its own (metampc_bringup.orchestration.domain, as the tests), over --runs runs, process start
included:
  <range>_<verb>_s_p50 / _max       wall time of `ros2 node list`, `ros2 service list`,
                                    `ros2 topic list` answered by the daemon (the first run
                                    starts it: its warm-up is in that run's time)
  <range>_<verb>_complete           runs whose listing held every node / service / topic of
                                    the two nodes
  <range>_<verb>_no_daemon_...      the same with --no-daemon (a node of the verb's own, its
                                    --spin-time 0.5 s)
  <range>_echo_once_s_p50 / _max    `ros2 topic echo /y --once` until it has printed
  <range>_echo_once_fails           runs that did not print a message
With --session instead (issue 52): the 4-node session by hand (`ros2 launch metampc_bringup
by_hand.launch.yaml`: recorder, plant at 10 Hz, controller, learner), LOCALHOST discovery, the
daemon started first; for each verb of :data:`SESSION_VERBS`:
  session_<verb>_s_p50 / _max       wall time, process start included
  session_<verb>_right              runs with its expected exit status and output
  session_<verb>_no_daemon_...      the same with --no-daemon (a node of the verb's own: how
                                    every one of these verbs answered before issue 52)
and load_avg_start / load_avg_end (os.getloadavg()).
The daemons and nodes are stopped before the script returns. Run from the repository root
after `source scripts/env.sh`.
"""
import argparse
import itertools
import json
import os
import re
import signal
import statistics
import subprocess
import tempfile
import time

from metampc_bringup.orchestration.domain import isolate
from metampc_bringup.orchestration.processes import ProcessGroup

EXPECTED = {'node': {'/plant', '/controller'},
            'service': {'/reset', '/set_active', '/plant/get_parameters',
                        '/controller/get_parameters'},
            'topic': {'/y', '/u', '/mpc_status', '/plant_info'}}


# The session's verbs: (name, arguments, exit status, a regular expression its output
# matches). /y has 1 publisher and 3 subscribers (recorder, controller, learner) until the
# learner's D_target is full (30 s), then 2 (docs/nodes.md).
SESSION_VERBS = (
    ('topic_info', ('topic', 'info', '/y'), 0,
     r'^Type: metampc_msgs/msg/PlantOutput\nPublisher count: 1\nSubscription count: [23]\n$'),
    ('topic_info_v', ('topic', 'info', '/y', '-v'), 0,
     r'Publisher count: 1\n\nNode name: plant\n(.|\n)*Subscription count: [23]\n'
     r'(.|\n)*Node name: (recorder|controller)\n(.|\n)*Node name: (recorder|controller)\n'),
    ('node_info', ('node', 'info', '/controller'), 0, r'^/controller\n  Subscribers:\n'),
    ('param_get', ('param', 'get', '/plant', 'theta'), 0, r'^Double value is: 0\.5\n$'),
    ('param_set', ('param', 'set', '/controller', 'adaptation', 'periodic'), 0,
     r'^Set parameter successful\n$'),
    ('param_describe', ('param', 'describe', '/plant', 'theta'), 0, r'  Type: double\n'),
    ('node_list', ('node', 'list'), 0, r'/learner\n'),
    ('topic_list', ('topic', 'list'), 0, r'/mpc_status\n'),
    ('service_list', ('service', 'list'), 0, r'/meta_train\n'),
    ('node_info_unknown', ('node', 'info', '/nope'), 1, r"^Unable to find node '/nope'\n$"),
    ('topic_info_unknown', ('topic', 'info', '/nope'), 1, r"^Unknown topic '/nope'\n$"),
    ('param_get_unknown', ('param', 'get', '/nope', 'theta'), 1, r'^Node not found\n$'))


def timed(cmd, env):
    t0 = time.monotonic()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    return time.monotonic() - t0, out


def listings(env, runs: int, extra=()) -> dict:
    """Per verb family: the times and the count of complete listings over `runs` runs."""
    out = {}
    for family, expected in EXPECTED.items():
        times, complete = [], 0
        for _ in range(runs):
            took, done = timed(['ros2', family, 'list', *extra], env)
            times.append(took)
            complete += expected <= set(done.stdout.split())
        out[family] = (times, complete)
    return out


def session(runs: int) -> dict:
    """The figures of --session (module docstring)."""
    env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    figures = {'load_avg_start': [round(v, 2) for v in os.getloadavg()]}
    with tempfile.TemporaryDirectory() as folder:
        launch = subprocess.Popen(
            ['ros2', 'launch', 'metampc_bringup', 'by_hand.launch.yaml',
             f'output:={folder}/recording.mcap'], env={**env, 'ROS_LOG_DIR': folder},
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            subprocess.run(['ros2', 'daemon', 'start'], env=env, capture_output=True)
            deadline = time.monotonic() + 120.0
            while '/learner' not in timed(['ros2', 'node', 'list'], env)[1].stdout.split():
                if time.monotonic() > deadline:
                    raise RuntimeError('the session did not come up within 120 s')
                time.sleep(1.0)
            time.sleep(5.0)     # the learner's start-up (torch)
            for (name, verb, status, pattern), (suffix, extra) in itertools.product(
                    SESSION_VERBS, (('', ()), ('_no_daemon', ('--no-daemon',)))):
                times, right = [], 0
                for _ in range(runs):
                    took, out = timed(['ros2', *verb, *extra], env)
                    times.append(took)
                    right += out.returncode == status and bool(re.search(
                        pattern, out.stdout + out.stderr))
                figures[f'session_{name}{suffix}_s_p50'] = round(statistics.median(times), 3)
                figures[f'session_{name}{suffix}_s_max'] = round(max(times), 3)
                figures[f'session_{name}{suffix}_right'] = right
        finally:
            subprocess.run(['ros2', 'daemon', 'stop'], env=env, capture_output=True)
            os.killpg(launch.pid, signal.SIGINT)
            launch.wait(120)
    figures['load_avg_end'] = [round(v, 2) for v in os.getloadavg()]
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=20, help='runs per command (default 20)')
    parser.add_argument('--session', action='store_true',
                        help="the 4-node session's verbs (module docstring)")
    args = parser.parse_args()
    isolate('LOCALHOST')
    if args.session:
        print(json.dumps({**session(args.runs), 'runs': args.runs,
                          'time': time.strftime('%Y-%m-%d %H:%M:%S')}))
        return
    figures = {}
    for discovery in ('SUBNET', 'LOCALHOST'):
        env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': discovery}
        group = ProcessGroup('/tmp', env={'ROS_AUTOMATIC_DISCOVERY_RANGE': discovery})
        subprocess.run(['ros2', 'daemon', 'stop'], env=env, capture_output=True)
        try:
            group.start('metampc_plant', 'plant', params={'mode': 'realtime'})
            group.start('metampc_controller', 'controller', params={'active': False})
            time.sleep(5.0)      # the nodes' own start-up (imports, first sample)
            key = discovery.lower()
            for suffix, extra in (('', ()), ('_no_daemon', ('--no-daemon',))):
                for family, (times, complete) in listings(env, args.runs, extra).items():
                    name = f'{key}_{family}_list{suffix}'
                    figures[f'{name}_s_p50'] = round(statistics.median(times), 3)
                    figures[f'{name}_s_max'] = round(max(times), 3)
                    figures[f'{name}_complete'] = complete
            echo, fails = [], 0
            for _ in range(args.runs):
                took, out = timed(['ros2', 'topic', 'echo', '/y', '--once'], env)
                if 'step:' in out.stdout:
                    echo.append(took)
                else:
                    fails += 1
            figures[f'{key}_echo_once_s_p50'] = round(statistics.median(echo), 3) if echo \
                else None
            figures[f'{key}_echo_once_s_max'] = round(max(echo), 3) if echo else None
            figures[f'{key}_echo_once_fails'] = fails
        finally:
            subprocess.run(['ros2', 'daemon', 'stop'], env=env, capture_output=True)
            group.stop_all()
    figures['runs'] = args.runs
    figures['time'] = time.strftime('%Y-%m-%d %H:%M:%S')
    print(json.dumps(figures))


if __name__ == '__main__':
    main()
