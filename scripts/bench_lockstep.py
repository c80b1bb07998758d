#!/usr/bin/env python3
"""Closed-loop throughput of the experiment's lockstep tracking, recorder on; ONE JSON line.

Runs the experiment's graph as ``run_experiment.py`` does (recorder, learner, lockstep plant,
latent-MPC controller and the inactive NMPC controller, the orchestrator's client), on the
CI-sized learning set-up of config/ci.yaml but with ``--steps`` tracking steps per method
(default 1000; the experiment's runs are 300), once per variant (``--variants``): ``held``,
the defaults (the plant's y and the controller's u and mpc_status keep all and wait while the
recorder, which keeps all, is full: metampc_common.held_publisher), and ``unheld``, as before
that (writers and recorder keep the last 1000: a recorder that falls behind loses messages,
docs/speed.md). Per variant, from the seed report:

- steps_per_s.<method>: tracking steps of that method's run / the wall time of its tracking
  phase (episode start handshake included), for the latent-MPC methods;
- steps_per_s_nmpc: the same for the true-model NMPC (its solve, not the transport, sets it);
- recorded: the outputs, inputs and MpcStatus the recording holds of each run; all of them
  (``recording_complete``: every step's u and mpc_status, at least one y per step, no missed
  tick) or the rate was bought with lost data;
- foreign_inputs: inputs on u the replay did not pair with a status of the controller (0 in a
  run where nothing else publishes on u);
- ratio_to_bare: the slowest method's rate over ``bare_round_trips_per_s``, a lockstep plant
  and a controller that echoes u = 0 at once (``bench_plant.py``'s ROS part), the transport's
  ceiling on this machine, measured in the same run.

Then ``held_over_unheld_steps_per_s`` (what the flow control costs, both in one run) and the
load average before and after (wall-clock rates depend on other processes).

Usage: python scripts/bench_lockstep.py [--steps 1000] [--methods imaml,maml]
       [--variants held,unheld]
"""
import argparse
import json
import os
import sys
import tempfile
import time
from typing import Any, Dict, List

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# held: the defaults (writers keep all and wait for a full recorder, which keeps all);
# unheld: as before (writers and the recorder keep the last 1000).
VARIANTS = {'held': {},
            'unheld': {'plant': {'hold_for_readers': False},
                       'controller': {'hold_for_readers': False},
                       'recorder': {'qos_depth': 1000}}}


def run(steps: int, methods: List[str], overrides: Dict[str, Any]) -> Dict[str, Any]:
    """One experiment on config/ci.yaml with `steps` tracking steps per method; its rates and
    what its recording holds."""
    from metampc_bringup.experiment import run_experiment
    from metampc_bringup.experiment_config import load
    config = load(os.path.join(ROOT, 'config', 'ci.yaml'), {
        'methods': methods + ['nmpc'], 'track_duration': steps * 0.1, **overrides})
    with tempfile.TemporaryDirectory() as tmp:
        started = time.monotonic()
        report = run_experiment(config, os.path.join(tmp, 'run'), progress=False)
        wall = time.monotonic() - started
    seed = report['per_seed'][0]
    timings = seed['timings']
    steps = config.track_steps()
    rates = {m: steps / timings[f'track_{m}'] for m in methods}
    tracking = {m: seed['methods'][m]['tracking'] for m in methods}
    return {
        'steps': steps, 'steps_per_s': rates, 'steps_per_s_min': min(rates.values()),
        'steps_per_s_nmpc': steps / timings['track_nmpc'],
        'escaped': {m: t['escaped'] for m, t in tracking.items()},
        'recorded': {m: t['samples'] for m, t in tracking.items()},
        'foreign_inputs': {m: t['foreign_inputs']['count'] for m, t in tracking.items()},
        'recording_complete': all(
            t['ticks']['missed'] == 0 and t['samples']['inputs'] == steps
            and t['samples']['mpc_status'] == steps and t['samples']['outputs'] >= steps
            for t in tracking.values()),
        'experiment_wall_s': wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--steps', type=int, default=1000, help='tracking steps per method')
    parser.add_argument('--methods', default='imaml,maml',
                        help='latent-MPC methods to track (nmpc is always measured)')
    parser.add_argument('--variants', default='held,unheld',
                        help='held (the defaults), unheld (no flow control, as before)')
    args = parser.parse_args(argv)
    if args.steps < 100:
        print('bench_lockstep: --steps must be >= 100', file=sys.stderr)
        return 2
    from metampc_bringup.orchestration.domain import isolate
    sys.path.insert(0, os.path.join(ROOT, 'scripts'))
    from bench_plant import bench_lockstep

    isolate()       # the bare pair's domain; the experiment claims one of its own

    methods = args.methods.split(',')
    variants = args.variants.split(',')
    if not set(variants) <= set(VARIANTS):
        print(f'bench_lockstep: --variants out of {", ".join(VARIANTS)}', file=sys.stderr)
        return 2
    load_before = os.getloadavg()
    result = {v: run(args.steps, methods, VARIANTS[v]) for v in variants}
    bare = bench_lockstep(args.steps, 120.0)
    for entry in result.values():
        entry['ratio_to_bare'] = entry['steps_per_s_min'] / bare
    if len(variants) == 2:
        result['held_over_unheld_steps_per_s'] = (result['held']['steps_per_s_min']
                                                  / result['unheld']['steps_per_s_min'])
    print(json.dumps({**result, 'bare_round_trips_per_s': bare,
                      'load_before': load_before, 'load_after': os.getloadavg(),
                      'time': time.strftime('%Y-%m-%d %H:%M:%S')}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
