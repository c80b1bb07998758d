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
The daemons and nodes are stopped before the script returns. Run from the repository root
after `source scripts/env.sh`.
"""
import argparse
import json
import os
import statistics
import subprocess
import time

from metampc_bringup.orchestration.domain import isolate
from metampc_bringup.orchestration.processes import ProcessGroup

EXPECTED = {'node': {'/plant', '/controller'},
            'service': {'/reset', '/set_active', '/plant/get_parameters',
                        '/controller/get_parameters'},
            'topic': {'/y', '/u', '/mpc_status', '/plant_info'}}


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=20, help='runs per command (default 20)')
    args = parser.parse_args()
    isolate('LOCALHOST')
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
