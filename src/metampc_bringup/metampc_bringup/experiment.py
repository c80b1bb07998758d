"""An experiment from nothing to a report: every seed's run (:class:`SeedRun`), then the
analysis of the recordings (:mod:`.analysis.experiment_report`).

``scripts/run_experiment.py`` is its command line; ``make run`` runs it with the defaults. In:
an :class:`~metampc_bringup.experiment_config.ExperimentConfig` and an output folder; out, in
it: config.yaml (resolved), report.json and report.md, the figures, and per seed
``seed_<s>/`` its recording.mcap, report.json, plots and node logs; :func:`rebuild_report`
recomputes the reports from the recordings alone. The run folder: docs/experiments.md.
"""
import contextlib
import json
import logging
import os
import time
from typing import Any, Callable, Dict, List, Optional

import yaml

from metampc_bringup.analysis.drift_report import drift_experiment_report, seed_drift_report
from metampc_bringup.analysis.experiment_report import experiment_report, seed_report
from metampc_bringup.experiment_config import ExperimentConfig
from metampc_bringup.orchestration.domain import isolated
from metampc_bringup.orchestration.netns import call_in_namespace, split_hosts
from metampc_bringup.orchestration.orchestrator import SeedRun, terminate_as_interrupt
from metampc_bringup.orchestration.cluster import ClusterSpec, connect
from metampc_bringup.orchestration.seed_jobs import (check_workers_run_this_code, run_seeds,
                                                     seed_dir)
from metampc_bringup.run_folder import done_seeds, incomplete, mark_incomplete, prepare

log = logging.getLogger('metampc.experiment')


def reporters(scenario: str):
    """(per-seed report, experiment report) of a scenario: the paper's claims, or drift's."""
    if scenario == 'drift':
        return seed_drift_report, drift_experiment_report
    return seed_report, experiment_report


def run_experiment(config: ExperimentConfig, out_dir: str, progress: bool = True,
                   prefix: Optional[Dict[str, List[str]]] = None,
                   hosts: Optional[List[List[str]]] = None,
                   foxglove_port: Optional[int] = None,
                   cluster: Optional[ClusterSpec] = None) -> Dict[str, Any]:
    """Run every seed of `config` into the folder `out_dir`; return the report.

    A new folder is created; the folder of an earlier, unfinished run of the same
    configuration is resumed: only its seeds without a report run (:mod:`.run_folder`).
    The process joins a ROS domain of its own first (``ROS_DOMAIN_ID``, localhost discovery)
    unless ``prefix`` places nodes on other hosts (then the environment's settings stand).
    ``hosts`` (node names per host, :func:`.orchestration.netns.parse_hosts`) runs each group in
    a network namespace of its own instead, and the orchestration in one more (root only:
    :class:`.orchestration.netns.NetnsError` otherwise), all of them removed on return. Ctrl-C
    or SIGTERM stops the nodes of the running seed (on a cluster: of every running seed), leaves
    its recording readable in its folder, marked incomplete (:mod:`.run_folder`), and re-raises
    KeyboardInterrupt. ``foxglove_port``: each seed's graph also runs the Foxglove live view
    on that port (not with ``hosts``: it would serve inside the orchestrator's namespace).
    ``cluster`` runs the seeds as jobs of a dask cluster (embedded, or an existing one), each
    in a child process with a ROS domain of its own on its worker
    (:mod:`.orchestration.seed_jobs`; not with ``hosts``, ``prefix`` or ``foxglove_port``);
    the per-seed results are those of the one-process run.

    Raises:
        FileExistsError: `out_dir` is not the run folder of this configuration (before
            anything is written).
        ValueError, ClusterError: the cluster is refused, does not answer, or has a worker
            that runs other code (idem).
    """
    if cluster is not None and (hosts or prefix or foxglove_port is not None):
        raise ValueError('a cluster runs each seed on a worker in a domain of its own: not '
                         'with hosts, prefix or the Foxglove live view')
    if hosts:
        with terminate_as_interrupt(), split_hosts(hosts) as net:
            return call_in_namespace(net.orchestrator, run_experiment, config, out_dir,
                                     progress, net.prefix())
    seeds = config.seed_list()
    done_seeds(out_dir, config.to_dict(), seeds)     # refused before any cluster starts
    seed_report, experiment_report = reporters(config.scenario)
    reports: Dict[int, Dict[str, Any]] = {}

    def land(seed: int) -> None:
        reports[seed] = seed_report(seed_dir(out_dir, seed))

    started = time.monotonic()
    if cluster is not None:
        with terminate_as_interrupt(), connect(cluster) as client:
            check_workers_run_this_code(client)
            run_seeds(client, out_dir, prepare(out_dir, config.to_dict(), seeds), land,
                      progress)
    else:
        _run_here(config, out_dir, prepare(out_dir, config.to_dict(), seeds), land, progress,
                  prefix, foxglove_port)
    for seed in seeds:      # done by an earlier try
        if seed not in reports:
            land(seed)
    return experiment_report([reports[s] for s in seeds], out_dir, config.to_dict(),
                             time.monotonic() - started)


def _run_here(config: ExperimentConfig, out_dir: str, seeds: List[int],
              land: Callable[[int], None], progress: bool,
              prefix: Optional[Dict[str, List[str]]], foxglove_port: Optional[int]) -> None:
    """`seeds` one after the other in this process."""
    exported = os.environ.get('ROS_DOMAIN_ID')
    with terminate_as_interrupt(), (contextlib.nullcontext() if prefix else isolated()) as domain:
        if domain is not None:
            log.info('ROS_DOMAIN_ID=%d (localhost discovery)%s', domain,
                     f'; not the exported ROS_DOMAIN_ID={exported}: each experiment claims a '
                     'free domain of its own, so that two never share one'
                     if exported not in (None, str(domain)) else '')
        for seed in seeds:
            try:
                SeedRun(config, seed, seed_dir(out_dir, seed), progress, prefix,
                        foxglove_port).run()
            except BaseException as err:
                mark_incomplete(seed_dir(out_dir, seed), 'interrupted'
                                if isinstance(err, KeyboardInterrupt) else f'failed ({err})')
                raise
            land(seed)


def rebuild_report(out_dir: str) -> Dict[str, Any]:
    """Recompute every report of the run folder `out_dir` from its recordings alone (e.g.
    after the analysis gained a metric): each ``seed_<s>/report.json``, ``report.json``,
    ``report.md`` and the figures are written again; the recordings are only read.

    Raises:
        FileNotFoundError: no config.yaml or no seed_<s>/recording.mcap in `out_dir` (a
            seed's folder marked incomplete, :mod:`.run_folder`, does not count).
    """
    with open(os.path.join(out_dir, 'config.yaml')) as f:
        config = yaml.safe_load(f)
    seeds = sorted((int(name[len('seed_'):]) for name in os.listdir(out_dir)
                    if name.startswith('seed_') and name[len('seed_'):].isdigit()
                    and os.path.exists(os.path.join(out_dir, name, 'recording.mcap'))
                    and not incomplete(os.path.join(out_dir, name))))
    if not seeds:
        raise FileNotFoundError(f'{out_dir}: no seed_<s>/recording.mcap of a finished seed')
    wall = float('nan')
    previous = os.path.join(out_dir, 'report.json')
    if os.path.exists(previous):
        with open(previous) as f:
            wall = json.load(f).get('wall_time_s') or wall
    seed_report, experiment_report = reporters(config.get('scenario', 'adapt_once'))
    reports = [seed_report(os.path.join(out_dir, f'seed_{s}')) for s in seeds]
    return experiment_report(reports, out_dir, config, wall)
