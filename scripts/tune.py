#!/usr/bin/env python3
"""A fair hyperparameter search for iMAML, first-order MAML and supervised training.

The logic is :mod:`metampc_bringup.studies.tuning`, the protocol and results docs/tuning.md.
The jobs run on an embedded dask cluster (``--jobs``) or on ``--scheduler ADDRESS``
(docs/experiments.md#on-a-cluster); the Optuna studies (a journal file, or ``--storage``) and
the finished jobs are kept beside ``--out`` (``runs/t.json`` -> ``runs/t.study/``), so the same
command resumes a stopped search.
Progress goes to stderr (tqdm); stdout gets ONE JSON line (configurations with scores,
robustness runs, winners, wall time, CPU time of the jobs, load average), also written to
``--out``. Exit status: 0 done, 1 jobs raised (the others are kept) or the scheduler was lost,
2 bad arguments (one line on stderr) or a cluster refused, 130 interrupted.

Usage: python scripts/tune.py [--k 8] [--refine 4] [--finalists 3] [--robust-seeds 3]
       [--pruner median|none] [--storage URL]
       [--jobs 2] [--scheduler tcp://127.0.0.1:8786] --out runs/tuning.json
"""
import argparse
import json
import logging
import os
import sys

from metampc_bringup.orchestration.cluster_cli import add_arguments, cluster_spec
from metampc_bringup.studies.search import open_storage
from metampc_bringup.studies.study_jobs import run_study
from metampc_bringup.studies.tuning import check_folder, study_folder, tune, TuneConfig

CLUSTER_ARGS = ('jobs', 'scheduler', 'insecure', 'tls_ca_file', 'tls_cert', 'tls_key')
NOT_SEARCH_ARGS = CLUSTER_ARGS + ('out', 'storage')     # where it runs and is kept, not what


def main(argv=None) -> int:
    d = TuneConfig()
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default=d.config,
                        help='experiment YAML whose learner section sets the NSSM and source')
    parser.add_argument('--k', type=int, default=d.k,
                        help='stage 1: meta configurations per method (paired draws)')
    parser.add_argument('--refine', type=int, default=d.refine,
                        help='stage 2: further trials of the TPE sampler per meta method')
    parser.add_argument('--per-round', type=int, default=d.per_round,
                        help='stage 2: trials asked at once per meta method (part of the '
                             'protocol: the trials depend on it, not on --jobs)')
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
                        help='seed of the configuration draws and of the sampler')
    parser.add_argument('--score', default=d.score, choices=('control', 'prediction'),
                        help='control: closed-loop tracking cost / NMPC of the adapted models '
                             '(default); prediction: their held-out loss')
    parser.add_argument('--pruner', default=d.pruner, choices=('median', 'none'),
                        help="median: Optuna's median pruner on the meta-training loss stops "
                             'hopeless stage-2 trials early, the same rule for every method '
                             '(default); none: every trial runs all its iterations')
    parser.add_argument('--storage', metavar='URL',
                        help='where the Optuna studies are: a database URL (sqlite:///PATH, '
                             'postgresql://USER@HOST/DB) shared by several clients, or a journal '
                             'file (default: OUT without .json + .study/study.journal)')
    add_arguments(parser, 'jobs at once on an embedded cluster (default 2; jobs x threads '
                          '<= cores)')
    parser.add_argument('--threads', type=int, default=d.threads, help='torch threads per job')
    parser.add_argument('--out', required=True,
                        help='JSON file to write (must not exist: config/tuning.json is the '
                             'committed record); the search is kept in OUT without .json + '
                             '.study/')
    args = parser.parse_args(argv)
    options = {k: v for k, v in vars(args).items() if k not in NOT_SEARCH_ARGS}
    cfg = TuneConfig(**options)
    folder = study_folder(args.out)
    try:
        cfg.validate()
        cluster = cluster_spec(args, 2, cfg.threads)
        if os.path.exists(args.out):
            raise ValueError(f'--out {args.out} exists; results are never overwritten')
        if args.storage:
            open_storage(args.storage)
        check_folder(folder, cfg)
    except ValueError as err:
        print(f'tune: {err}', file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    status, report = run_study('tune', cluster,
                               lambda client: tune(cfg, client, folder, storage=args.storage))
    if status:
        return status
    with open(args.out, 'w') as f:
        json.dump(report, f, indent=1)
        f.write('\n')
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
