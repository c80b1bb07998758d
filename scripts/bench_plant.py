#!/usr/bin/env python3
"""Benchmark the plant: simulator core speed and lockstep round trips through ROS 2.

Prints ONE JSON line:
  core_steps_per_s_1        Plant samples/s (one van der Pol system, RK4 with the default
                            substeps)
  core_steps_per_s_1000     BatchPlant samples/s for 1000 systems stepped together
  core_system_steps_per_s_1000   the same times 1000 (system-samples/s)
  lockstep_round_trips_per_s  y -> u -> y cycles/s between the `plant` node (ros2 run) and a
                              minimal echo controller process (this script with --echo)
  lockstep_steps            round trips timed (after a warm-up)

The two processes run in a ROS_DOMAIN_ID of their own (metampc_bringup.orchestration.domain:
claimed with a lock file, as the test sessions do) with discovery on localhost only, and are
stopped before the script returns.
Run from the repository root after `source scripts/env.sh`.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from metampc_bringup.orchestration.domain import isolate
from metampc_bringup.orchestration.lifeline import hold
from metampc_bringup.orchestration.script_child import last_json_line, script_child

WARMUP_STEPS = 200


def _rate(fn, min_seconds: float) -> float:
    """Calls of fn per second, over at least min_seconds of wall time."""
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= min_seconds:
            return n / elapsed


def bench_core(seconds: float) -> dict:
    from metampc_plant.simulator import BatchPlant, Plant, PlantConfig
    config = PlantConfig(theta=(1.0,), dt=0.05, x0=(1.0, 0.0))
    plant = Plant(config)
    single = _rate(lambda: plant.step((0.1,)), seconds)
    batch = BatchPlant(np.linspace(-0.5, 2.0, 1000), config)
    u = np.full((1000, 1), 0.1)
    many = _rate(lambda: batch.step(u), seconds)
    return {'core_steps_per_s_1': round(single), 'core_steps_per_s_1000': round(many, 1),
            'core_system_steps_per_s_1000': round(1000 * many)}


def echo(steps: int) -> None:
    """Minimal controller: answer every y_k with u = 0.1 for step k; time `steps` round trips.

    Prints {"round_trips_per_s": ...} once done and exits.
    """
    from metampc_common.qos import STREAM
    from metampc_msgs.msg import ControlInput, PlantOutput
    import rclpy

    rclpy.init()
    node = rclpy.create_node('bench_echo')
    pub = node.create_publisher(ControlInput, 'u', STREAM)
    marks = {}

    def on_y(msg: PlantOutput) -> None:
        if msg.step in (WARMUP_STEPS, WARMUP_STEPS + steps):
            marks[msg.step] = time.perf_counter()
        pub.publish(ControlInput(step=msg.step, u=[0.1]))

    node.create_subscription(PlantOutput, 'y', on_y, STREAM)
    while rclpy.ok() and len(marks) < 2:
        rclpy.spin_once(node, timeout_sec=1.0)
    elapsed = marks[WARMUP_STEPS + steps] - marks[WARMUP_STEPS]
    print(json.dumps({'round_trips_per_s': steps / elapsed}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def bench_lockstep(steps: int, timeout: float) -> float:
    """Round trips/s between `ros2 run metampc_plant plant` and an echo process."""
    from metampc_bringup.orchestration.processes import ProcessGroup
    with tempfile.TemporaryDirectory(prefix='bench_plant_') as log_dir:
        group = ProcessGroup(log_dir)
        try:
            # input_timeout 0: strict lockstep, so only answered steps are timed.
            plant = group.start('metampc_plant', 'plant',
                                params={'dt': 0.05, 'input_timeout': 0.0})
            with script_child(__file__, ['--echo', str(steps)]) as controller:
                try:
                    out, _ = controller.communicate(timeout=timeout)
                    return last_json_line(out)['round_trips_per_s']
                except (subprocess.TimeoutExpired, IndexError, ValueError, KeyError):
                    raise RuntimeError(f'no lockstep result within {timeout} s; plant log:\n'
                                       + group.output(plant)) from None
        finally:
            group.stop_all()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--steps', type=int, default=5000, help='lockstep round trips to time')
    parser.add_argument('--core-seconds', type=float, default=1.0,
                        help='wall time per core measurement, s')
    parser.add_argument('--timeout', type=float, default=120.0,
                        help='give up on the lockstep run after this many s')
    parser.add_argument('--echo', type=int, metavar='STEPS', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo:
        hold()     # the benchmark's helper: ends with the benchmark
        echo(args.echo)
        return 0
    isolate()
    load_start = os.getloadavg()
    result = bench_core(args.core_seconds)
    try:
        rate = bench_lockstep(args.steps, args.timeout)
    except RuntimeError as err:
        print(f'bench_plant: {err}', file=sys.stderr)
        return 1
    result['lockstep_round_trips_per_s'] = round(rate, 1)
    result['lockstep_steps'] = args.steps
    result['load_avg_start'] = [round(v, 2) for v in load_start]
    result['load_avg_end'] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
