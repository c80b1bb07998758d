#!/usr/bin/env python3
"""Meta-training robustness without ROS: each meta method on many source sets.

Meta-trains every method of ``--methods`` at the experiment's request fields (``--config``)
on the source sets of seeds ``--first-seed`` .. ``--first-seed + --seeds - 1`` (the
experiment's own: source seed = meta seed = the run's seed) and reports, per method, the final
meta-test loss of every run, their median, the runs that diverged (final loss non-finite or
above 10x the method's median) and the largest spectral radius of A. ``--set NAME=VALUE``
overrides a MetaConfig field of every run (e.g. ``--set lr_schedule=constant``); ``--adapt``
also scores each meta-model by the held-out loss of the validation targets after 20 adaptation
steps at the experiment's step size of its method (the tuning's criterion: use it with the
validation source sets, ``--first-seed 1000``, when choosing a setting). The runs are jobs of
an embedded dask cluster (``--jobs``) or of ``--scheduler ADDRESS``
(docs/experiments.md#on-a-cluster); each finished run is cached in ``OUT/cache/`` on this
machine: run the same command again to resume.

Usage: python scripts/robustness.py --out runs/robustness [--seeds 20] [--jobs 2]
       [--methods imaml,maml] [--free-latent] [--rho-max 1.0] [--set NAME=VALUE ...]
       [--adapt] [--scheduler tcp://127.0.0.1:8786]
Writes OUT/robustness.json and prints it as one JSON line. Exit status: 0 done, 1 runs raised
(the others are cached) or the scheduler was lost, 2 bad arguments or a cluster refused, 130
interrupted.
"""
import argparse
import dataclasses
import json
import logging
import os
import sys
import time

from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.experiment_config import ConfigError, load
from metampc_bringup.orchestration.cluster import slots
from metampc_bringup.orchestration.cluster_cli import add_arguments, cluster_spec
from metampc_bringup.studies.learning_setup import settings_from
from metampc_bringup.studies.robustness import robustness_jobs, robustness_summary
from metampc_bringup.studies.study_jobs import ResultCache, run_jobs, run_study
from metampc_bringup.studies.tuning import TuneConfig
from metampc_learner.meta_train import META_METHODS, MetaConfig
FIXED = ('method', 'iterations', 'seed')  # set by the job, not by --set


def override(text: str) -> tuple:
    """'NAME=VALUE' -> (name, value typed like MetaConfig's default); ConfigError if bad."""
    name, _, value = text.partition('=')
    defaults = {f.name: f.default for f in dataclasses.fields(MetaConfig)
                if f.name not in FIXED}
    if name not in defaults or not value:
        raise ConfigError(f'--set needs NAME=VALUE with NAME out of {", ".join(defaults)}, '
                          f'got {text!r}')
    kind = type(defaults[name])
    try:
        if kind is bool and value.lower() not in ('true', 'false'):
            raise ValueError(value)
        typed = value.lower() == 'true' if kind is bool else kind(value)
    except ValueError:
        raise ConfigError(f'--set {name}: {value!r} is not a {kind.__name__}') from None
    return name, typed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--config', default='config/default.yaml', help='experiment YAML')
    parser.add_argument('--out', required=True, help='result folder (resumes if it exists)')
    parser.add_argument('--methods', default='imaml,maml')
    parser.add_argument('--seeds', type=int, default=20)
    parser.add_argument('--first-seed', type=int, default=0)
    add_arguments(parser, 'runs at once on an embedded cluster (default 2; jobs x threads '
                          '<= cores)')
    parser.add_argument('--threads', type=int, default=1, help='torch threads per job')
    parser.add_argument('--free-latent', action='store_true',
                        help='A unconstrained (stable_latent false), as before')
    parser.add_argument('--rho-max', type=float, help='bound of the spectral norm of A')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='override a MetaConfig field of every run (repeatable)')
    parser.add_argument('--adapt', action='store_true',
                        help='also score each meta-model on the validation targets')
    args = parser.parse_args(argv)
    methods = args.methods.split(',')
    try:
        experiment = load(args.config)
        bad = [m for m in methods if m not in META_METHODS]
        if bad or args.seeds < 1 or args.first_seed < 0:
            raise ConfigError(f'need meta methods out of {", ".join(META_METHODS)} (got '
                              f'{", ".join(bad) or "them"}), seeds >= 1, first seed >= 0')
        cluster = cluster_spec(args, 2, args.threads)
        if args.rho_max is not None and not args.rho_max > 0:
            raise ConfigError(f'--rho-max must be > 0, got {args.rho_max}')
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise ConfigError(f'--out {args.out} exists and is not a folder')
        overrides = dict(override(text) for text in args.set)
        dataclasses.replace(MetaConfig(), **overrides).validate()
    except ValueError as err:       # ConfigError is one
        print(f'robustness: {err}', file=sys.stderr)
        return 2
    nssm = {}
    if args.free_latent:
        nssm['stable_latent'] = False
    if args.rho_max is not None:
        nssm['rho_max'] = args.rho_max
    start, load_start = time.monotonic(), os.getloadavg()
    tuning = TuneConfig()     # --adapt: the tuning's validation targets and adaptation steps
    settings = (settings_from(args.config, tuning.thetas, tuning.adapt_steps) if args.adapt
                else settings_from(args.config, 0, 0))
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = robustness_jobs(experiment, methods, seeds, nssm, overrides, args.adapt)
    cache = ResultCache(os.path.join(args.out, 'cache'), settings)
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    status, ran = run_study('robustness', cluster, lambda client: (
        run_jobs(client, jobs, 'robustness', settings, cache, threads=args.threads),
        slots(client)))
    if status:
        return status
    runs, jobs_at_once = ran
    report = json_safe({
        'config': args.config, 'nssm': nssm, 'overrides': overrides, 'seeds': list(seeds),
        'summary': robustness_summary(runs), 'runs': runs,
        'wall_s': round(time.monotonic() - start, 1),
        'cpu_s': round(sum(r['cpu_seconds'] for r in runs), 1),
        'jobs': jobs_at_once, 'threads_per_job': args.threads, 'scheduler': args.scheduler,
        'load_avg_start': [round(v, 2) for v in load_start],
        'load_avg_end': [round(v, 2) for v in os.getloadavg()]})
    with open(os.path.join(args.out, 'robustness.json'), 'w') as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
