#!/usr/bin/env python3
"""Benchmark replay on a large recording: wall time and peak memory of `scripts/replay.py`.

    python scripts/bench_replay.py [--messages 1000000] [--recording PATH] [--no-plots]

Writes a synthetic closed-loop recording of about --messages messages
(:mod:`metampc_recording.synthetic_run`: y, u, mpc_status per tick with horizon 20, resets every
50000 steps, a live parameter change, one foreign u, two training jobs) unless --recording
names an existing file, then runs `scripts/replay.py RECORDING --json` in a child process with
its output in a temporary folder, and prints ONE JSON line:

  messages, file_mb     the recording
  write_s               time to write it (null with --recording)
  wall_s                wall time of the replay process
  peak_rss_mb           its peak resident memory (ru_maxrss of the child, MiB)
  ticks, foreign_inputs the replay's tick accounting and foreign-input count (a sanity check)

Run after `source scripts/env.sh`.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

REPLAY = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'replay.py')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--messages', type=int, default=1_000_000,
                        help='messages of the synthetic recording (3 per tick)')
    parser.add_argument('--recording', help='replay this MCAP file (written first if absent)')
    parser.add_argument('--no-plots', action='store_true', help='replay with --no-plots')
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix='bench_replay_') as tmp:
        path = args.recording or os.path.join(tmp, 'recording.mcap')
        write_s = None
        if not os.path.exists(path):
            from metampc_recording.synthetic_run import SyntheticRun, write_synthetic_run
            ticks = args.messages // 3
            start = time.monotonic()
            write_synthetic_run(path, SyntheticRun(ticks=ticks, episode_steps=50_000,
                                                   retune_tick=ticks // 2,
                                                   foreign_inputs=[(ticks // 3, 3)]))
            write_s = time.monotonic() - start
        out = os.path.join(tmp, 'out')
        command = [sys.executable, REPLAY, path, '--json', '--out', out]
        start = time.monotonic()
        child = subprocess.Popen(command + (['--no-plots'] if args.no_plots else []),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        stdout, stderr = child.communicate()
        wall = time.monotonic() - start
        peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss   # the one child
        if child.returncode != 0:
            print(f'bench_replay: replay failed: {stderr.decode().strip()}', file=sys.stderr)
            return 1
        report = json.loads(stdout)
        metrics = report['metrics']
        print(json.dumps({
            'messages': report['recording']['message_count'],
            'file_mb': round(os.path.getsize(path) / 2 ** 20, 1),
            'write_s': None if write_s is None else round(write_s, 1),
            'wall_s': round(wall, 1), 'peak_rss_mb': round(peak_kib / 1024, 1),
            'plots': not args.no_plots, 'ticks': metrics['ticks'],
            'foreign_inputs': metrics.get('foreign_inputs')}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
