#!/usr/bin/env python3
"""Re-run a run folder's tracking in one process under other controller settings, paired by seed.

Every seed's recorded adapted models fly again against the plant core (no ROS) under each
variant of the controller's parameters; the true-model NMPC runs once per seed as the
yardstick. Prints a table per variant (tracking cost / NMPC, median and worst, escapes, steady
offsets, the paired comparison with the first variant: seeds where it is cheaper, median ratio
with its 95 % bootstrap interval, Wilcoxon p) and writes RUN_DIR/retrack.json and
RUN_DIR/retrack.png (steady offset and cost ratio per seed, per variant and method). The runs are
jobs of an embedded dask cluster (``--jobs``) or of ``--scheduler ADDRESS``
(docs/experiments.md#on-a-cluster; the library: metampc_bringup/studies/retrack_batch.py), each
result kept in RUN_DIR/retrack/ as it lands, so a stopped run resumes.

    python scripts/retrack.py runs/vdp --variant none:offset_free=none \\
        --variant state:offset_free=state --variant input:offset_free=input --jobs 2

``--seeds 100,106`` takes only those of the run's seeds.

A variant is NAME:key=value,key=value with controller parameter names (docs/controller.md);
values are YAML (``0.3``, ``none``, ``[1.0, 0.0]``; YAML reads ``off`` as false). ``--nmpc
key=value,...`` sets the yardstick's own parameters (e.g. ``nmpc_tail=20``: then the NMPC runs
again instead of its recorded cost being taken, and every ratio is against it; ``--check`` and
``--trajectory`` fly it with them too). A bad name or value is one error line, exit 2.
"""
import argparse
import json
import logging
import os
import sys
from typing import Any, Dict, Tuple

import yaml


def parse_variant(text: str) -> Tuple[str, Dict[str, Any]]:
    """'name:k=v,k=v' -> (name, {k: yaml(v)})."""
    name, _, rest = text.partition(':')
    if not name or name == 'nmpc':
        raise ValueError(f'variant {text!r}: expected NAME:key=value,... (NAME not nmpc)')
    values = {}
    for item in filter(None, rest.split(',')):
        key, eq, value = item.partition('=')
        if not eq:
            raise ValueError(f'variant {name}: {item!r} is not key=value')
        values[key.strip()] = yaml.safe_load(value)
    return name, values


def seed_list(text: str) -> Tuple[int, ...]:
    """'100,101,106' -> (100, 101, 106); argparse's type for --seeds."""
    try:
        seeds = tuple(int(s) for s in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not seeds separated by commas') from None
    return seeds


def recorded_nmpc(run_dir: str) -> Dict[int, Dict[str, Any]]:
    """{seed: the NMPC's tracking as a MethodResult dict} from RUN_DIR/report.json (empty
    when there is none)."""
    try:
        with open(os.path.join(run_dir, 'report.json')) as f:
            report = json.load(f)
    except (OSError, ValueError):
        return {}
    out = {}
    for entry in report.get('per_seed', []):
        tracking = ((entry.get('methods') or {}).get('nmpc') or {}).get('tracking') or {}
        cost = (tracking.get('tracking') or {}).get('cost')
        if cost is not None:
            out[int(entry['seed'])] = {'cost': float(cost),
                                       'escaped': bool(tracking.get('escaped')),
                                       'rejected': '', 'offsets': []}
    return out


def main(argv=None) -> int:
    from metampc_bringup.orchestration.cluster_cli import add_arguments, cluster_spec
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('run_dir', help='a run folder of scripts/run_experiment.py')
    parser.add_argument('--variant', action='append', default=[], metavar='NAME:k=v,...',
                        help='controller settings to compare (repeatable; default: the '
                             "recorded settings, as 'recorded')")
    parser.add_argument('--nmpc', default='', metavar='k=v,...',
                        help="the NMPC yardstick's controller settings (e.g. nmpc_tail=20); "
                             'default: the recorded ones')
    add_arguments(parser, 'seeds x variants at once on an embedded cluster (default 1)')
    parser.add_argument('--seeds', type=seed_list, metavar='S,S,...',
                        help="only these of the run's seeds (default: all of them)")
    parser.add_argument('--recompute-nmpc', action='store_true',
                        help="run the NMPC again instead of taking its recorded tracking cost "
                             "from RUN_DIR/report.json (the same number: a lockstep run is "
                             'deterministic; the NMPC is the slow part)')
    parser.add_argument('--check', action='store_true',
                        help="also say what the model check (docs/mpc.md) makes of each seed's "
                             "adapted models on the seed's NMPC tracking run, against their "
                             'meta-model and persistence (RUN_DIR/retrack_check.json)')
    parser.add_argument('--trajectory', type=int, metavar='SEED',
                        help="also plot that seed's tracked output, input and disturbance "
                             'estimate under every variant (RUN_DIR/retrack_seed<SEED>.png)')
    args = parser.parse_args(argv)
    try:
        variants = [parse_variant(v) for v in args.variant] or [('recorded', {})]
        yardstick = parse_variant(f'yardstick:{args.nmpc}')[1]
        cluster = cluster_spec(args, 1, 1, 'torch threads')
    except ValueError as err:
        parser.error(str(err))
    from metampc_bringup.experiment_config import ConfigError, load
    from metampc_bringup.analysis.run_report import json_safe
    from metampc_bringup.analysis.plots import plot_episodes, plot_variants
    from metampc_bringup.analysis.retrack import (check_verdicts, controller_config, retrack_seed,
                                                  seed_recordings, summarise)
    from metampc_bringup.studies import retrack_batch as batch
    from metampc_bringup.studies.study_jobs import run_study, StudyError
    from metampc_common.params import ParameterError
    try:
        experiment = load(os.path.join(args.run_dir, 'config.yaml'))
    except ConfigError as err:
        parser.error(f'{args.run_dir}: {err}')
    for name, overrides in variants + [('--nmpc', yardstick)]:
        try:
            controller_config(experiment, experiment.first_seed, overrides)
        except (ParameterError, ValueError) as err:
            parser.error(f'variant {name}: {err}')
    recordings = seed_recordings(args.run_dir)
    if not recordings:
        parser.error(f'{args.run_dir}: no seed_<n>/recording.mcap in it')
    if args.seeds:
        missing = sorted(set(args.seeds) - set(recordings))
        if missing:
            parser.error(f'--seeds: {args.run_dir} has no seed {missing} (it has '
                         f'{sorted(recordings)})')
        recordings = {seed: recordings[seed] for seed in sorted(set(args.seeds))}
    cache_dir = os.path.join(args.run_dir, 'retrack')
    os.makedirs(cache_dir, exist_ok=True)
    recorded = {} if args.recompute_nmpc or yardstick else recorded_nmpc(args.run_dir)
    for seed, episode in recorded.items():
        path = batch.result_path(cache_dir, seed, batch.NMPC, {})
        if seed in recordings and not os.path.exists(path):
            with open(path, 'w') as f:
                json.dump({batch.NMPC: episode}, f)
    todo = batch.missing_jobs(recordings, variants, yardstick, cache_dir)
    print(f'retrack: {len(recordings)} seeds x {len(variants)} variants, {len(todo)} to run',
          file=sys.stderr)
    logging.basicConfig(level=logging.WARNING, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')

    def work(client) -> None:
        failed = batch.run(client, experiment, todo, progress=sys.stderr.isatty())
        if failed:
            job, err = failed[0]
            raise StudyError(f'{len(failed)} of {len(todo)} job(s) raised (first: {job}: '
                             f'{err.__class__.__name__}: {err}); the others are kept in '
                             f'{cache_dir}: the same command runs only the missing ones')
    status, _ = run_study('retrack', cluster, work) if todo else (0, None)
    if status:
        return status

    per_seed = batch.per_seed_results(recordings, variants, yardstick, cache_dir)
    summary = summarise(per_seed)
    print('\n'.join(batch.table(summary, variants[0][0])))
    with open(os.path.join(args.run_dir, 'retrack.json'), 'w') as f:
        json.dump(json_safe({'variants': dict(variants), 'summary': summary}), f, indent=1)
    path = plot_variants(summary, os.path.join(args.run_dir, 'retrack.png'))
    if args.check:
        verdicts = {}
        for seed, rec in recordings.items():
            runs = {}
            retrack_seed(experiment, seed, rec, yardstick, methods=[], episodes=runs)
            verdicts[seed] = check_verdicts(experiment, seed, rec, runs['nmpc'])
            print(f'check, seed {seed}: ' + '; '.join(
                f"{m}: {'flies' if v['vs_meta'] and v['vs_meta']['ok'] else 'refused'} vs meta, "
                f"{'flies' if v['vs_persistence']['ok'] else 'refused'} vs persistence"
                for m, v in verdicts[seed].items()))
        with open(os.path.join(args.run_dir, 'retrack_check.json'), 'w') as f:
            json.dump(json_safe(verdicts), f, indent=1)
    if args.trajectory is not None:
        if args.trajectory not in recordings:
            parser.error(f'--trajectory {args.trajectory}: no such seed in {args.run_dir}')
        runs = {}
        for name, overrides in variants:
            runs[name] = {}
            retrack_seed(experiment, args.trajectory, recordings[args.trajectory], overrides,
                         nmpc=False, episodes=runs[name])
        retrack_seed(experiment, args.trajectory, recordings[args.trajectory], yardstick,
                     methods=[], episodes=runs[variants[0][0]])     # the NMPC, with --nmpc's
        plot_episodes(runs, experiment.resolved().tracked_outputs, os.path.join(
            args.run_dir, f'retrack_seed{args.trajectory}.png'),
            f'{args.run_dir}, seed {args.trajectory}')
    print(f'retrack: {os.path.join(args.run_dir, "retrack.json")}, {path}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
