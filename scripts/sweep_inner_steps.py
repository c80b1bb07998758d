#!/usr/bin/env python3
"""Where does iMAML win? Sweep the inner steps M of iMAML, first-order and unrolled MAML.

Each (method, M) is tuned with the same small budget on validation data, then its winner is
meta-trained on the experiment's source set of every test seed and adapted to that seed's
target: held-out loss after K in {0, 1, 5, 20} steps, meta-training wall time per outer step
and peak RSS per run (the logic: ``metampc_bringup.studies.sweep``). Protocol, budget, its
measured cost and resuming: docs/sweep.md.

Usage: python scripts/sweep_inner_steps.py --out runs/sweep [--ms 1,5,10,25,50]
       [--methods imaml,maml,maml_unrolled] [--seeds 5] [--iterations 300]
       [--tune-iterations 100] [--jobs 2]
Writes OUT/sweep.json, OUT/report.md, OUT/loss_vs_M.png, OUT/memory_vs_M.png and prints one
JSON line; run the same command again to resume. Exit 2 on bad arguments.
"""
import argparse
import json
import sys

from metampc_bringup.experiment_config import ConfigError
from metampc_bringup.studies.sweep import DEFAULT_MS, main as run_sweep, Plan, SweepError
from metampc_learner.meta_train import META_METHODS


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default='config/default.yaml', help='experiment YAML')
    parser.add_argument('--out', required=True, help='result folder (resumes if it exists)')
    parser.add_argument('--methods', default=','.join(META_METHODS))
    parser.add_argument('--ms', default=','.join(map(str, DEFAULT_MS)),
                        help='inner steps M (unrolled MAML: those <= 10)')
    parser.add_argument('--seeds', type=int, default=5, help='test seeds first-seed, ...')
    parser.add_argument('--first-seed', type=int, default=0)
    parser.add_argument('--iterations', type=int, default=300, help='outer steps, test runs')
    parser.add_argument('--tune-iterations', type=int, default=100,
                        help='outer steps, tuning runs')
    parser.add_argument('--thetas', type=int, default=4, help='validation targets (tuning)')
    parser.add_argument('--adapt-steps', type=int, default=20)
    parser.add_argument('--heldout-samples', type=int, default=2000,
                        help='held-out samples of each test target')
    parser.add_argument('--jobs', type=int, default=2, help='worker processes')
    parser.add_argument('--threads', type=int, default=1, help='torch threads per worker')
    args = parser.parse_args(argv)
    try:
        ms = tuple(int(v) for v in args.ms.split(','))
    except ValueError:
        print(f'sweep_inner_steps: --ms must be integers separated by commas, got {args.ms!r}',
              file=sys.stderr)
        return 2
    plan = Plan(tuple(args.methods.split(',')), ms,
                tuple(range(args.first_seed, args.first_seed + args.seeds)),
                args.iterations, args.tune_iterations, args.thetas, args.adapt_steps,
                args.heldout_samples)
    try:
        line = run_sweep(args.config, plan, args.out, args.jobs, args.threads)
    except (SweepError, ConfigError) as err:    # raised before any run starts
        print(f'sweep_inner_steps: {err}', file=sys.stderr)
        return 2
    print(json.dumps(line))
    return 0


if __name__ == '__main__':
    sys.exit(main())
