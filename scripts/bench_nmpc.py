#!/usr/bin/env python3
"""The true-model NMPC's tracking cost and speed per solver, family and seed; one JSON line.

For each family (its experiment configuration: config/default.yaml for van der Pol, else
config/FAMILY.yaml) and each seed, the NMPC's tracking episode of the experiment (theta* of
the seed, track_x0, the reference, the controller section) in one process against the plant
core (:func:`metampc_bringup.analysis.retrack.track_models`: what the NMPC node computes
under a lockstep plant, without ROS), once per solver (``nmpc_solver``), the solvers in turn
per seed so that both see the same machine load. Per run: the tracking cost (the
experiment's), whether it escaped, steps/s (episode steps over its wall time, the planner's
set-up included; and over the process's CPU time, which other processes on a loaded machine
inflate less: run with OMP_NUM_THREADS=1 so that it is one core's), the ticks whose solve
converged ('solved') and that fell back to the shifted plan, and the mean and largest
iteration counts. Progress on stderr.

Usage: python scripts/bench_nmpc.py [--families vanderpol,duffing,pendulum,quadruple_tank]
                                    [--seeds 0 1 2] [--solvers ipopt,lbfgsb]
"""
import argparse
import json
import os
import sys
import time

import numpy as np

from metampc_bringup import experiment_config
from metampc_bringup.analysis.retrack import track_models


def config_path(family: str) -> str:
    return 'config/default.yaml' if family == 'vanderpol' else f'config/{family}.yaml'


def run(family: str, seed: int, solver: str) -> dict:
    cfg = experiment_config.load(config_path(family))
    episodes = {}
    start, cpu = time.perf_counter(), time.process_time()
    res = track_models(cfg, seed, {'nmpc_solver': solver}, {'nmpc': None}, episodes)['nmpc']
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    ticks = episodes['nmpc'].ticks
    iters = np.array([t.iterations for t in ticks])
    return {'cost': res.cost, 'escaped': res.escaped, 'steps': len(ticks),
            'steps_per_s': round(len(ticks) / wall, 2), 'wall_s': round(wall, 1),
            'steps_per_cpu_s': round(len(ticks) / cpu, 2),
            'solved': sum(t.solver_status == 'solved' for t in ticks),
            'fallbacks': sum(bool(t.fallback) for t in ticks),
            'iter_mean': round(float(iters.mean()), 2), 'iter_max': int(iters.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--families', default='vanderpol,duffing,pendulum,quadruple_tank')
    parser.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    parser.add_argument('--solvers', default='ipopt,lbfgsb')
    args = parser.parse_args()
    out = {'loadavg_1min': round(os.getloadavg()[0], 2), 'families': {}}
    for family in args.families.split(','):
        rows = out['families'][family] = {}
        for seed in args.seeds:
            rows[seed] = {}
            for solver in args.solvers.split(','):
                rows[seed][solver] = run(family, seed, solver)
                print(family, seed, solver, rows[seed][solver], file=sys.stderr, flush=True)
    out['loadavg_1min_end'] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
