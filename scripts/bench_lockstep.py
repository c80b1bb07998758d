#!/usr/bin/env python3
"""Closed-loop throughput of the experiment's lockstep tracking, recorder on; ONE JSON line.

Runs the experiment's graph as ``run_experiment.py`` does (recorder, learner, lockstep plant,
latent-MPC controller and the inactive NMPC controller, the orchestrator's client), on the
CI-sized learning set-up of config/ci.yaml but with ``--steps`` tracking steps per method
(default 1000: the depth of the recorder's queues, see recording_complete; the experiment's
runs are 300), and reads the tracking phases' wall times from the seed report:

- steps_per_s.<method>: tracking steps of that method's run / the wall time of its tracking
  phase (episode start handshake included), for the latent-MPC methods;
- steps_per_s_nmpc: the same for the true-model NMPC (its solve, not the transport, sets it);
- recorded: the answers (u and MpcStatus) the recording holds of each run; all of them
  (``recording_complete``) or the rate was bought with lost data. The recorder takes some
  2000-2500 messages/s (3 per step) with the CPU the loop leaves it; its queues hold 1000
  (qos.BACKLOG), so a run much longer than that at full speed can lose answers (measured:
  72 of 2000 once, docs/speed.md);
- bare_round_trips_per_s: a lockstep plant and a controller that echoes u = 0 at once
  (``bench_plant.py``'s ROS part), the transport's ceiling on this machine, measured in the
  same run;
- load average before and after (wall-clock rates depend on other processes).

Usage: python scripts/bench_lockstep.py [--steps 1000] [--methods imaml,maml]
"""
import argparse
import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--steps', type=int, default=1000, help='tracking steps per method')
    parser.add_argument('--methods', default='imaml,maml',
                        help='latent-MPC methods to track (nmpc is always measured)')
    args = parser.parse_args(argv)
    if args.steps < 100:
        print('bench_lockstep: --steps must be >= 100', file=sys.stderr)
        return 2
    from metampc_bringup.domain import isolate
    from metampc_bringup.experiment import run_experiment
    from metampc_bringup.experiment_config import load
    sys.path.insert(0, os.path.join(ROOT, 'scripts'))
    from bench_plant import bench_lockstep

    isolate()       # the bare pair's domain; the experiment claims one of its own

    methods = args.methods.split(',')
    load_before = os.getloadavg()
    config = load(os.path.join(ROOT, 'config', 'ci.yaml'), {
        'methods': methods + ['nmpc'], 'track_duration': args.steps * 0.1})
    with tempfile.TemporaryDirectory() as tmp:
        started = time.monotonic()
        report = run_experiment(config, os.path.join(tmp, 'run'), progress=False)
        wall = time.monotonic() - started
    seed = report['per_seed'][0]
    timings = seed['timings']
    steps = config.track_steps()
    rates = {m: steps / timings[f'track_{m}'] for m in methods}
    bare = bench_lockstep(args.steps, 120.0)
    print(json.dumps({
        'steps': steps, 'steps_per_s': rates,
        'steps_per_s_min': min(rates.values()),
        'steps_per_s_nmpc': steps / timings['track_nmpc'],
        'bare_round_trips_per_s': bare,
        'ratio_to_bare': min(rates.values()) / bare,
        'escaped': {m: seed['methods'][m]['tracking']['escaped'] for m in methods},
        'recorded': {m: seed['methods'][m]['tracking']['samples'] for m in methods},
        'recording_complete': all(
            seed['methods'][m]['tracking']['ticks']['missed'] == 0
            and seed['methods'][m]['tracking']['samples']['inputs'] == steps for m in methods),
        'experiment_wall_s': wall, 'load_before': load_before, 'load_after': os.getloadavg(),
        'time': time.strftime('%Y-%m-%d %H:%M:%S')}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
