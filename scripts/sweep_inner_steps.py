#!/usr/bin/env python3
"""Where does iMAML win? Sweep the inner steps M of iMAML, first-order and unrolled MAML.

Each (method, M) is tuned with the same small budget on validation data, then its winner is
meta-trained on the experiment's source set of every test seed and adapted to that seed's
target: held-out loss after K in {0, 1, 5, 20} steps, meta-training wall time per outer step
and peak RSS per run (the logic: ``metampc_bringup.studies.sweep``). Protocol, budget, its
measured cost and resuming: docs/sweep.md. The runs are jobs of an embedded dask cluster
(``--jobs``) or of ``--scheduler ADDRESS`` (docs/experiments.md#on-a-cluster).

Usage: python scripts/sweep_inner_steps.py --out runs/sweep [--ms 1,5,10,25,50]
       [--methods imaml,maml,maml_unrolled] [--seeds 5] [--iterations 300]
       [--tune-iterations 100] [--jobs 2] [--scheduler tcp://127.0.0.1:8786]
Writes OUT/sweep.json, OUT/report.md, OUT/loss_vs_M.png, OUT/memory_vs_M.png and prints one
JSON line; run the same command again to resume. Exit status: 0 done, 1 runs raised (the others
are cached) or the scheduler was lost, 2 bad arguments or a cluster refused, 130 interrupted.
"""
import argparse
import json
import logging
import sys

from metampc_bringup.orchestration.cluster import slots
from metampc_bringup.orchestration.cluster_cli import add_arguments, cluster_spec
from metampc_bringup.studies.study_jobs import run_study
from metampc_bringup.studies.sweep import check, DEFAULT_MS, Plan, summary_line, sweep
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
    add_arguments(parser, 'runs at once on an embedded cluster (default 2; jobs x threads '
                          '<= cores)')
    parser.add_argument('--threads', type=int, default=1, help='torch threads per run')
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
        cluster = cluster_spec(args, 2, args.threads)
        check(args.config, plan, args.out)
    except ValueError as err:    # SweepError, ConfigError: before any run starts
        print(f'sweep_inner_steps: {err}', file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    status, report = run_study('sweep_inner_steps', cluster, lambda client: sweep(
        client, args.config, plan, args.out, slots(client), args.threads))
    if status:
        return status
    print(json.dumps(summary_line(report, args.out)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
