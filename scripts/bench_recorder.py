#!/usr/bin/env python3
"""Benchmark the recorder: a 1 kHz PlantOutput stream for 30 s, does it keep up, at what CPU.

Prints ONE JSON line:
  published            PlantOutput messages sent by the publisher process
  recorded             messages in the finished MCAP file (its Statistics record)
  dropped              published - recorded (must be 0)
  in_order             the recorded steps are exactly 0..published-1, in order
  recorder_cpu_share   CPU time of the recorder's processes (`ros2 run` and the node, from
                       /proc/PID/stat utime + stime) over the wall time of the stream, from the
                       first message sent until the publisher has every message acknowledged
                       (1.0 = one core busy all the time)
  recorder_cpu_s, stream_wall_s    the two terms of that share
  publisher_rate_hz    the rate the publisher achieved (messages / time from first to last)
  file_mb, compression, chunk_size   the recording
  loadavg              1, 5 and 15 min load average of the machine after the run

Set-up: `ros2 run metampc_recording recorder` (topics: y, default chunking/compression) and a
publisher process (this script with --publish) with the plant's QoS for y (reliable, keep_last
100: a recorder more than 100 messages behind would lose some), in a ROS_DOMAIN_ID of their
own (claimed with a lock file, as the test sessions do) with discovery on localhost only. Both
are stopped before the script returns. Run after `source scripts/env.sh`.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from metampc_bringup.orchestration.procfs import live_cpu_seconds
from metampc_bringup.orchestration.lifeline import hold
from metampc_bringup.orchestration.script_child import last_json_line, script_child


def publish(rate_hz: float, seconds: float, timeout: float) -> None:
    """Publisher process: wait for a subscriber on y, send rate_hz * seconds PlantOutputs at
    rate_hz, wait until all are acknowledged; print 'start' when the first goes out, then a JSON
    line {"published", "send_s": s from the first to the last message}."""
    from metampc_common.qos import STREAM
    from metampc_msgs.msg import PlantOutput
    import rclpy
    from rclpy.duration import Duration

    rclpy.init()
    node = rclpy.create_node('bench_publisher')
    pub = node.create_publisher(PlantOutput, 'y', STREAM)   # as the plant's
    deadline = time.monotonic() + timeout
    while pub.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            raise SystemExit('bench_recorder: the recorder never subscribed to y')
        time.sleep(0.01)
    n = round(rate_hz * seconds)
    msg = PlantOutput(y=[0.0, 0.0], u_applied=[0.0])
    print('start', flush=True)
    start = time.monotonic()
    for k in range(n):
        due = start + k / rate_hz
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        msg.step = k
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(k * 1_000_000, 1_000_000_000)
        msg.y[0], msg.y[1] = 1e-3 * k, -1e-3 * k
        pub.publish(msg)
    sent = time.monotonic() - start
    pub.wait_for_all_acked(Duration(seconds=timeout))
    print(json.dumps({'published': n, 'send_s': sent}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def check_recording(path: str, published: int) -> dict:
    """Count and order of the recorded messages, from the finished file alone."""
    from mcap.reader import make_reader
    from metampc_recording.recording_reader import read_recording
    with open(path, 'rb') as f:
        recorded = make_reader(f).get_summary().statistics.message_count
    steps = [m.step for _, _, m in read_recording(path).decoded(['/y'])]
    return {'recorded': recorded, 'dropped': published - recorded,
            'in_order': steps == list(range(published))}


def bench(args) -> dict:
    from metampc_bringup.orchestration.processes import ProcessGroup, session_pids
    from metampc_recording.recorder_config import RecorderConfig
    with tempfile.TemporaryDirectory(prefix='bench_recorder_') as folder:
        config = RecorderConfig(output=os.path.join(folder, 'bench.mcap'), topics=['y'])
        group = ProcessGroup(folder)
        try:
            recorder = group.start('metampc_recording', 'recorder', config.to_parameters(),
                                   name='recorder')
            with script_child(__file__, ['--publish', '--rate', str(args.rate), '--seconds',
                                         str(args.seconds), '--timeout', str(args.timeout)]
                              ) as publisher:
                if publisher.stdout.readline().strip() != 'start':
                    raise RuntimeError('the publisher did not start; recorder log:\n'
                                       + group.output(recorder))
                t0, cpu0 = time.monotonic(), live_cpu_seconds(session_pids(recorder))
                out, _ = publisher.communicate(timeout=args.seconds + args.timeout)
                t1, cpu1 = time.monotonic(), live_cpu_seconds(session_pids(recorder))
            sent = last_json_line(out)
            if group.interrupt(recorder) != 0:
                raise RuntimeError('the recorder did not exit 0:\n' + group.output(recorder))
            result = {'published': sent['published']}
            result.update(check_recording(config.output, sent['published']))
            result.update({
                'recorder_cpu_share': round((cpu1 - cpu0) / (t1 - t0), 3),
                'recorder_cpu_s': round(cpu1 - cpu0, 2), 'stream_wall_s': round(t1 - t0, 2),
                'publisher_rate_hz': round(sent['published'] / sent['send_s'], 1),
                'file_mb': round(os.path.getsize(config.output) / 1e6, 2),
                'compression': config.compression, 'chunk_size': config.chunk_size})
            return result
        finally:
            group.stop_all()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--rate', type=float, default=1000.0, help='messages per second')
    parser.add_argument('--seconds', type=float, default=30.0, help='length of the stream, s')
    parser.add_argument('--timeout', type=float, default=60.0,
                        help='s to wait for discovery and for the last acknowledgements')
    parser.add_argument('--publish', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        hold()     # the benchmark's helper: ends with the benchmark
        publish(args.rate, args.seconds, args.timeout)
        return 0
    from metampc_bringup.orchestration.domain import isolate
    isolate()
    try:
        result = bench(args)
    except (RuntimeError, subprocess.TimeoutExpired, ValueError, IndexError) as err:
        print(f'bench_recorder: {err}', file=sys.stderr)
        return 1
    result['loadavg'] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result))
    return 0 if result['dropped'] == 0 and result['in_order'] else 1


if __name__ == '__main__':
    sys.exit(main())
