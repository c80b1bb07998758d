#!/usr/bin/env python3
"""A fair hyperparameter search for iMAML, first-order MAML and supervised training.

The logic is :mod:`metampc_bringup.studies.tuning`, the protocol and results docs/tuning.md.
Progress goes to stderr (tqdm); stdout gets ONE JSON line (configurations with scores,
robustness runs, winners, wall time, CPU time of the jobs, load average), also written to
``--out``. Bad arguments: one line on stderr, exit status 2.

Usage: python scripts/tune.py [--k 8] [--refine 4] [--finalists 3] [--robust-seeds 3]
       [--jobs 2] --out runs/tuning.json
"""
import argparse
import json
import os
import sys

from metampc_bringup.studies.tuning import TuneConfig, tune


def main(argv=None) -> int:
    d = TuneConfig()
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=d.config,
                        help='experiment YAML whose learner section sets the NSSM and source')
    parser.add_argument('--k', type=int, default=d.k, help='meta configurations per method')
    parser.add_argument('--refine', type=int, default=d.refine,
                        help='stage 2: neighbours of the stage-1 winner per meta method')
    parser.add_argument('--iterations', type=int, default=d.iterations,
                        help='outer steps in the search')
    parser.add_argument('--full-iterations', type=int, default=d.full_iterations,
                        help="outer steps of the robustness stage (the experiment's)")
    parser.add_argument('--finalists', type=int, default=d.finalists,
                        help='stage 3: best configurations per meta method (0: no stage 3)')
    parser.add_argument('--robust-seeds', type=int, default=d.robust_seeds,
                        help='stage 3: validation source sets 1000, 1001, ...')
    parser.add_argument('--batch-size', type=int, default=d.batch_size)
    parser.add_argument('--adapt-steps', type=int, default=d.adapt_steps)
    parser.add_argument('--thetas', type=int, default=d.thetas, help='validation targets')
    parser.add_argument('--seed', type=int, default=d.seed,
                        help='seed of the configuration draws')
    parser.add_argument('--score', default=d.score, choices=('control', 'prediction'),
                        help='control: closed-loop tracking cost / NMPC of the adapted models '
                             '(default); prediction: their held-out loss')
    parser.add_argument('--jobs', type=int, default=d.jobs, help='worker processes')
    parser.add_argument('--threads', type=int, default=d.threads,
                        help='torch threads per worker')
    parser.add_argument('--out', required=True,
                        help='JSON file to write (must not exist: config/tuning.json is the '
                             'committed record)')
    args = vars(parser.parse_args(argv))
    out = args.pop('out')
    cfg = TuneConfig(**args)
    try:
        cfg.validate()
        if os.path.exists(out):
            raise ValueError(f'--out {out} exists; results are never overwritten')
    except ValueError as err:
        print(f'tune: {err}', file=sys.stderr)
        return 2
    report = tune(cfg)
    with open(out, 'w') as f:
        json.dump(report, f, indent=1)
        f.write('\n')
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
