#!/usr/bin/env python3
"""Benchmark the Foxglove live view: latency from the plant to a WebSocket client, and CPU.

Prints ONE JSON line:
  rate_hz              the realtime plant's sample rate (default: 1/dt, the plant's default)
  messages             y messages the client took (after a warm-up of 10)
  in_order             their steps are consecutive (nothing lost)
  ws_latency_ms        p50, p99, max of (client's receipt - the sample's header stamp); a
                       realtime plant stamps y with its wall clock just before publishing it
  ros_latency_ms       the same for a plain rclpy subscriber of y in this script (DDS alone)
  foxglove_cpu_share   CPU time of the live view's processes (`ros2 run` and the node, /proc
                       utime + stime) over the wall time of the measurement (1.0 = one core)
  foxglove_cpu_s, wall_s   the two terms of that share
  loadavg              1, 5 and 15 min load average of the machine after the run

Set-up: a realtime plant (`ros2 run metampc_plant plant`, mode realtime) and the live view
(`ros2 run metampc_recording foxglove`, port 0: a free one) in a ROS_DOMAIN_ID of their own with
discovery on localhost only; the client (metampc_recording.foxglove_client) subscribes to y. Both
processes are stopped before the script returns. Run after `source scripts/env.sh`.
"""
import argparse
import json
import os
import re
import sys
import tempfile
import time

WARM_UP = 10


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def bench(args) -> dict:
    from metampc_recording.foxglove_client import FoxgloveClient
    from metampc_bringup.analysis.percentiles import percentiles
    from metampc_bringup.orchestration.processes import ProcessGroup, session_pids
    from metampc_bringup.orchestration.procfs import live_cpu_seconds
    from metampc_bringup.orchestration.spun_node import SpunNode
    from metampc_common.qos import BACKLOG
    from metampc_msgs.msg import PlantOutput
    from rclpy.serialization import deserialize_message

    with tempfile.TemporaryDirectory(prefix='bench_foxglove_') as folder:
        group = ProcessGroup(folder)
        probe = SpunNode('bench_foxglove_probe')
        direct = {}
        probe.node.create_subscription(
            PlantOutput, 'y', lambda m: direct.setdefault(m.step, time.time_ns() - stamp_ns(m)),
            BACKLOG)
        try:
            live = group.start('metampc_recording', 'foxglove', {'port': 0}, name='foxglove')
            plant = group.start('metampc_plant', 'plant', {
                'mode': 'realtime', 'rate_hz': float(args.rate)}, name='plant')
            url = []
            probe.wait_for(lambda: url.extend(re.findall(r'serving (ws://\S+:\d+)',
                                                         group.output(live))) or url,
                           args.timeout, 'the live view to listen')
            with FoxgloveClient(url[0], args.timeout) as client:
                client.subscribe(client.channel('/y', args.timeout))
                latencies, steps = [], []
                for _ in range(WARM_UP):
                    client.message(args.timeout)
                t0, cpu0 = time.monotonic(), live_cpu_seconds(session_pids(live))
                while len(steps) < args.messages:
                    msg = client.message(args.timeout)
                    y = deserialize_message(msg.data, PlantOutput)
                    latencies.append(msg.received_ns - stamp_ns(y))
                    steps.append(y.step)
                t1, cpu1 = time.monotonic(), live_cpu_seconds(session_pids(live))
            probe.wait_for(lambda: steps[-1] in direct, args.timeout, 'the probe')
            rate = group.output(plant)
            for proc in (plant, live):
                if group.interrupt(proc) != 0:
                    raise RuntimeError(f'{proc.args[3]} did not exit 0:\n' + group.output(proc))
        finally:
            group.stop_all()
            probe.close()
    return {'rate_hz': float(re.search(r'([\d.]+) Hz', rate).group(1)),
            'messages': len(steps),
            'in_order': steps == list(range(steps[0], steps[0] + len(steps))),
            'ws_latency_ms': percentiles(latencies, (50, 99, 100), 1e-6, 3),
            'ros_latency_ms': percentiles([direct[s] for s in steps if s in direct],
                                          (50, 99, 100), 1e-6, 3),
            'foxglove_cpu_share': round((cpu1 - cpu0) / (t1 - t0), 4),
            'foxglove_cpu_s': round(cpu1 - cpu0, 2), 'wall_s': round(t1 - t0, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--rate', type=float, default=0.0,
                        help="plant sample rate, Hz (0: 1/dt, the plant's default)")
    parser.add_argument('--messages', type=int, default=300, help='y messages to time')
    parser.add_argument('--timeout', type=float, default=60.0,
                        help='s to wait for discovery and for each message')
    args = parser.parse_args()
    if args.rate < 0 or args.messages < 2:
        print('bench_foxglove: --rate must be >= 0 and --messages >= 2', file=sys.stderr)
        return 2
    from metampc_bringup.orchestration.domain import isolate
    isolate()
    try:
        result = bench(args)
    except (RuntimeError, TimeoutError, AssertionError) as err:
        print(f'bench_foxglove: {err}', file=sys.stderr)
        return 1
    result['loadavg'] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0 if result['in_order'] else 1


if __name__ == '__main__':
    sys.exit(main())
