#!/usr/bin/env python3
"""Benchmark the `ros2` verbs a user types first: how long until they answer.

Prints ONE JSON line; for each discovery range (SUBNET: a user's default; LOCALHOST: what the
tests use) and command, the median and max wall time in s over --runs runs, process start and
discovery included:
  <range>_node_list_s_p50 / _max      `ros2 node list` (its --spin-time, 0.5 s, included)
  <range>_echo_once_s_p50 / _max      `ros2 topic echo /y --once` until it has printed
  <range>_echo_once_fails              runs that did not print a message
A realtime plant publishes y at 10 Hz (a message waits up to 0.1 s). Each range runs in a
ROS_DOMAIN_ID of its own (metampc_bringup.domain, as the tests); the plant is stopped before
the script returns. Run from the repository root after `source scripts/env.sh`.
"""
import argparse
import json
import os
import statistics
import subprocess
import time

from metampc_bringup.domain import isolate


def timed(cmd, env):
    t0 = time.monotonic()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    return time.monotonic() - t0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=5, help='runs per command (default 5)')
    args = parser.parse_args()
    isolate('LOCALHOST')
    figures = {}
    for discovery in ('SUBNET', 'LOCALHOST'):
        env = {**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': discovery}
        plant = subprocess.Popen(['ros2', 'run', 'metampc_plant', 'plant', '--ros-args', '-p',
                                  'mode:=realtime'], env=env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            time.sleep(3.0)      # the plant's own start-up (imports, first sample)
            key = discovery.lower()
            node_list = [timed(['ros2', 'node', 'list'], env)[0] for _ in range(args.runs)]
            echo, fails = [], 0
            for _ in range(args.runs):
                took, out = timed(['ros2', 'topic', 'echo', '/y', '--once'], env)
                if 'step:' in out.stdout:
                    echo.append(took)
                else:
                    fails += 1
            for name, times in (('node_list', node_list), ('echo_once', echo)):
                figures[f'{key}_{name}_s_p50'] = round(statistics.median(times), 3) if times \
                    else None
                figures[f'{key}_{name}_s_max'] = round(max(times), 3) if times else None
            figures[f'{key}_echo_once_fails'] = fails
        finally:
            os.killpg(plant.pid, 2)
            plant.wait(timeout=30)
    figures['runs'] = args.runs
    print(json.dumps(figures))


if __name__ == '__main__':
    main()
