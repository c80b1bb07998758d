#!/usr/bin/env python3
"""Re-run a run folder's tracking in one process under other controller settings, paired by seed.

Every seed's recorded adapted models fly again against the plant core (no ROS) under each
variant of the controller's parameters; the true-model NMPC runs once per seed as the
yardstick. Prints a table per variant (tracking cost / NMPC, median and worst, escapes, steady
offsets, the paired comparison with the first variant: seeds where it is cheaper, median ratio
with its 95 % bootstrap interval, Wilcoxon p) and writes RUN_DIR/retrack.json and
RUN_DIR/retrack.png (steady offset and cost ratio per seed, per variant and method). Results
are cached per (seed, variant) in RUN_DIR/retrack/, so a stopped run resumes.

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
import hashlib
import concurrent.futures as futures
from dataclasses import asdict
import json
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


def _job(run_dir: str, seed: int, recording: str, overrides: Dict[str, Any],
         nmpc: bool) -> Dict[str, Any]:
    """The recorded models of one seed under `overrides`, or (`nmpc`) the NMPC alone."""
    from metampc_bringup.experiment_config import load
    from metampc_bringup.analysis.retrack import retrack_seed
    import torch
    torch.set_num_threads(1)
    experiment = load(os.path.join(run_dir, 'config.yaml'))
    results = retrack_seed(experiment, seed, recording, overrides, nmpc=nmpc,
                           methods=[] if nmpc else None)
    return {m: asdict(r) for m, r in results.items()}


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
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('run_dir', help='a run folder of scripts/run_experiment.py')
    parser.add_argument('--variant', action='append', default=[], metavar='NAME:k=v,...',
                        help='controller settings to compare (repeatable; default: the '
                             "recorded settings, as 'recorded')")
    parser.add_argument('--nmpc', default='', metavar='k=v,...',
                        help="the NMPC yardstick's controller settings (e.g. nmpc_tail=20); "
                             'default: the recorded ones')
    parser.add_argument('--jobs', type=int, default=1, help='seeds at once (processes)')
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
    except ValueError as err:
        parser.error(str(err))
    from metampc_bringup.experiment_config import ConfigError, load
    from metampc_bringup.analysis.run_report import json_safe
    from metampc_bringup.orchestration.lifeline import hold_in_worker
    from metampc_bringup.analysis.paired_stats import format_claim
    from metampc_bringup.analysis.plots import plot_episodes, plot_variants
    from metampc_bringup.analysis.retrack import (check_verdicts, controller_config, retrack_seed,
                                                  seed_recordings, summarise)
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

    def cached(seed: int, name: str, overrides: Dict[str, Any]) -> str:
        digest = hashlib.sha1(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:12]
        return os.path.join(cache_dir, f'seed_{seed}_{name}_{digest}.json')

    recorded = {} if args.recompute_nmpc or yardstick else recorded_nmpc(args.run_dir)
    for seed, episode in recorded.items():
        path = cached(seed, 'nmpc', {})
        if seed in recordings and not os.path.exists(path):
            with open(path, 'w') as f:
                json.dump({'nmpc': episode}, f)
    todo = []       # the NMPC once per seed (the yardstick), then every variant
    for seed, rec in recordings.items():
        for name, overrides in [('nmpc', yardstick)] + variants:
            path = cached(seed, name, overrides)
            if not os.path.exists(path):
                todo.append((seed, rec, overrides, name == 'nmpc', path))
    print(f'retrack: {len(recordings)} seeds x {len(variants)} variants, {len(todo)} to run',
          file=sys.stderr)
    with futures.ProcessPoolExecutor(max(1, args.jobs), initializer=hold_in_worker) as pool:
        running = {pool.submit(_job, args.run_dir, seed, rec, overrides, nmpc): path
                   for seed, rec, overrides, nmpc, path in todo}
        for done, fut in enumerate(futures.as_completed(running), 1):
            with open(running[fut], 'w') as f:
                json.dump(fut.result(), f)
            print(f'retrack: {done}/{len(todo)} {os.path.basename(running[fut])[:-5]}',
                  file=sys.stderr)

    per_seed = {}
    for seed in recordings:
        nmpc = json.load(open(cached(seed, 'nmpc', yardstick)))['nmpc']
        per_seed[seed] = {name: {**json.load(open(cached(seed, name, overrides))), 'nmpc': nmpc}
                          for name, overrides in variants}
    summary = summarise(per_seed)
    first = variants[0][0]
    print(f'{"variant":<12}{"method":<10}{"median":>8}{"worst":>10}{"escapes":>9}'
          f'{"offset":>9}  {"vs " + first:<44} ratios by seed')
    for name, methods in summary.items():
        for method, row in methods.items():
            claim = row.get('vs_' + first)
            print(f'{name:<12}{method:<10}{row["median"]:>8.3f}{row["worst"]:>10.3f}'
                  f'{row["escapes"]:>9}{row["mean_offset"]:>9.4f}  '
                  f'{format_claim(claim) if claim else "":<44} '
                  + ' '.join(f'{r:.2f}' for r in row['ratios'].values()))
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
