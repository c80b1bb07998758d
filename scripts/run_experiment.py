#!/usr/bin/env python3
"""Run the paper's experiment on the ROS 2 graph and write a run folder with its report.

Examples:
    python scripts/run_experiment.py                          # defaults: 1 seed, both classes
    python scripts/run_experiment.py --seeds 10 --methods imaml,maml,supervised,oracle,arx,nmpc
    python scripts/run_experiment.py --seeds 10 --jobs 2      # two seeds at a time
    python scripts/run_experiment.py --seeds 10 --out runs/ten   # again after Ctrl-C: resumes
    python scripts/run_experiment.py --seeds 10 --scheduler tcp://127.0.0.1:8786   # a cluster
    python scripts/run_experiment.py --seeds 5 --protocol paper_settings   # Algorithm 1 as written
    python scripts/run_experiment.py --report runs/<time>     # recompute its reports
    python scripts/run_experiment.py --config config/ci.yaml --methods imaml,maml --theta 0.5
    python scripts/run_experiment.py --family duffing --seeds 5   # config/duffing.yaml
    python scripts/run_experiment.py --scenario drift --seeds 5   # config/drift.yaml
    python scripts/run_experiment.py --foxglove               # live view on ws://127.0.0.1:8765
    # As root: plant | controllers | learner and recorder, one network namespace each.
    python scripts/run_experiment.py --hosts 'plant|controller,controller_nmpc|learner,recorder'

The defaults are config/default.yaml (tuned hyperparameters, see docs/experiments.md);
with --family F and no --config, config/F.yaml when it exists (docs/families.md); with
--scenario drift and no --config, config/drift.yaml (docs/adaptation.md).
Exit status: 0 done, 1 a phase failed (the message names it) or the scheduler was lost, 2 bad
arguments or configuration, a cluster refused or not answering, or an --out of another
configuration, 130 interrupted (the nodes are stopped, the recordings stay readable, an
unfinished seed's folder is marked INCOMPLETE).
"""
import argparse
import datetime
import logging
import os
import signal
import sys

from metampc_bringup.orchestration.cluster_cli import add_arguments

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_CONFIG = os.path.join(ROOT, 'config', 'default.yaml')


def config_path(family, scenario=None) -> str:
    """config/drift.yaml for --scenario drift, config/<family>.yaml when it exists, else
    config/default.yaml."""
    if scenario == 'drift':
        return os.path.join(ROOT, 'config', 'drift.yaml')
    own = os.path.join(ROOT, 'config', f'{family}.yaml')
    return own if family and os.path.exists(own) else DEFAULT_CONFIG


def numbers(text):
    """'0.2,-0.6,1.1' -> [0.2, -0.6, 1.1]; None stays None; ValueError names the text."""
    if text is None:
        return None
    try:
        return [float(v) for v in text.split(',')]
    except ValueError:
        raise ValueError(f'--theta needs comma-separated numbers, got {text!r}') from None


def port(text: str, default: int) -> int:
    """'8800' -> 8800, '' (--foxglove without a value) -> default; ValueError names the text."""
    try:
        return int(text) if text else default
    except ValueError:
        raise ValueError(f'--foxglove needs a port number, got {text!r}') from None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', help='YAML file with every hyperparameter (default: '
                                         'config/<family>.yaml, else config/default.yaml)')
    parser.add_argument('--family', help='plant family (docs/families.md); overrides the '
                                         "config's family key")
    parser.add_argument('--methods', help='comma-separated: imaml,maml,maml_unrolled,'
                                          'supervised,oracle,arx (the NSSM), narx_imaml,'
                                          'narx_maml,narx_oracle,narx_arx (the feature NARX), '
                                          'nmpc')
    parser.add_argument('--seeds', type=int, help='number of seeds')
    parser.add_argument('--first-seed', type=int, help='seed of the first run')
    add_arguments(parser, 'seeds run at once on an embedded cluster, each in a ROS domain of '
                          'its own (default 1: one after the other in this process; jobs x '
                          'learner.torch_threads <= cores)')
    parser.add_argument('--theta', help="target theta*, comma-separated values of the family's "
                                        'components (default: drawn per seed)')
    parser.add_argument('--protocol', help="'tuned' (default) or 'paper_settings': the paper's "
                                           'Algorithm 1 and adaptation as written '
                                           '(docs/experiments.md)')
    parser.add_argument('--scenario', help="'adapt_once' (default): adapt once, track once per "
                                           "method; or 'drift': theta* changes while each "
                                           'method tracks, with and without adaptation in the '
                                           'loop (docs/adaptation.md; config/drift.yaml)')
    parser.add_argument('--out', help='run folder to create, or to resume: the same command '
                                      'runs only its seeds without a report (default: '
                                      'runs/<time>)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bars')
    parser.add_argument('--report', metavar='RUN_DIR',
                        help='only recompute the reports of an existing run folder from its '
                             'recordings (report.json, report.md, figures are rewritten)')
    parser.add_argument('--hosts', help="nodes per host, e.g. 'plant|controller,controller_nmpc|"
                                        "learner,recorder': one network namespace each (root)")
    parser.add_argument('--foxglove', nargs='?', const='', metavar='PORT',
                        help='also run the Foxglove live view on ws://127.0.0.1:PORT (default '
                             'PORT 8765; docs/foxglove.md)')
    args = parser.parse_args(argv)
    # Ctrl-C is KeyboardInterrupt even when started from a non-interactive shell in the
    # background, which starts it with SIGINT ignored (and rclpy would chain to that).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:    # torch, rclpy, matplotlib: 1-2 s, in which Ctrl-C is an interruption like later
        from metampc_bringup.experiment import rebuild_report, run_experiment
        from metampc_bringup.orchestration.experiment_client import ExperimentError
        from metampc_bringup.experiment_config import ConfigError, load
        from metampc_recording.foxglove_params import DEFAULT_PORT, FoxgloveConfig
        from metampc_bringup.orchestration.netns import NetnsError, parse_hosts
        from metampc_bringup.orchestration.cluster import ClusterError, SchedulerLost
        from metampc_bringup.orchestration.cluster_cli import cluster_spec
    except KeyboardInterrupt:
        print('run_experiment: interrupted before it started; nothing written', file=sys.stderr)
        return 130
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    if args.report:
        try:
            report = rebuild_report(args.report)
        except (OSError, ValueError) as err:
            print(f'run_experiment: --report {args.report}: {err}', file=sys.stderr)
            return 2
        print(f"report: {os.path.join(args.report, 'report.md')}")
        return 0
    try:
        config = load(args.config or config_path(args.family, args.scenario), {
            'methods': args.methods.split(',') if args.methods else None,
            'seeds': args.seeds, 'first_seed': args.first_seed, 'theta': numbers(args.theta),
            'protocol': args.protocol, 'family': args.family, 'scenario': args.scenario})
        hosts = parse_hosts(args.hosts) if args.hosts else None
        spec = cluster_spec(args, 1, config.node_config('learner', config.first_seed)
                            .torch_threads, 'learner.torch_threads')
        cluster = spec if spec.jobs > 1 or spec.scheduler is not None else None
        if cluster and (hosts or args.foxglove is not None):
            raise ValueError('--jobs > 1 and --scheduler run each seed in a ROS domain of its '
                             'own on a worker: not with --hosts or --foxglove')
        foxglove = None if args.foxglove is None else port(args.foxglove, DEFAULT_PORT)
        if foxglove is not None:
            FoxgloveConfig(port=foxglove).validate()
            if hosts:
                raise ValueError('--foxglove with --hosts: the live view would serve inside '
                                 "the orchestrator's network namespace")
    except (ConfigError, NetnsError, ValueError) as err:
        print(f'run_experiment: {err}', file=sys.stderr)
        return 2
    out = args.out or os.path.join(
        ROOT, 'runs', datetime.datetime.now().strftime('%Y%m%d-%H%M%S'))
    try:
        report = run_experiment(config, out, progress=not args.no_progress, hosts=hosts,
                                foxglove_port=foxglove, cluster=cluster)
    except SchedulerLost as err:
        print(f'run_experiment: {err}', file=sys.stderr)
        return 1
    except (FileExistsError, NetnsError, ClusterError) as err:
        print(f'run_experiment: {err}', file=sys.stderr)
        return 2
    except ExperimentError as err:
        print(f'run_experiment: failed: {err}\nrun folder: {out}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'run_experiment: interrupted; nodes stopped, recordings in {out} (a seed '
              'stopped before its report is marked INCOMPLETE; the same command resumes it)',
              file=sys.stderr)
        return 130
    print(f"run folder: {out}\nreport: {os.path.join(out, 'report.md')} "
          f"({report['wall_time_s']:.0f} s)")
    return 0


if __name__ == '__main__':
    sys.exit(main())
