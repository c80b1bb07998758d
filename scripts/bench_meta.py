#!/usr/bin/env python3
"""Cost of meta-training: time per outer step, vmap vs loop, meta-gradient memory vs M.

Prints one JSON line. Set-up: the default NSSM (H = 10, T = 10, encoder 128-128, n_z = 5), the
default source set (100 systems), MetaConfig defaults (B = 16, M = 10, 64 windows per task,
5 CG steps), `--threads` torch threads (default 1, so that the CPU-time figures are per core and
the run leaves the second core of a shared 2-core machine to others).

- s_per_outer_step: wall time of meta_train per outer step (task sampling included), mean
  over `--steps` steps after one warm-up step, tasks vmapped; for iMAML with Gauss-Newton and
  with exact-Hessian curvature, first-order MAML and unrolled MAML. cpu_s_per_outer_step: the
  process CPU time of the same steps (not inflated when other processes take the core).
- vmap_speedup: CPU time per step with a Python loop over the tasks divided by that with vmap,
  both measured back to back (wall-clock ratio beside it).
- memory: peak resident set size (RSS) added by ONE batched meta-gradient (B = 16) for
  M in {5, 10, 20, 50}, each in a fresh process: the peak is reset just before the call
  (/proc/self/clear_refs), then VmHWM after minus VmRSS before (/proc/self/status); it
  includes one-time allocations common to every M.

Load average and the time are in the line: wall-clock numbers depend on other processes.

Usage: python scripts/bench_meta.py [--threads 1] [--steps 5]
"""
import argparse
import json
import os
import subprocess
import sys
import time
from typing import Tuple

import numpy as np
import torch

from metampc_bringup.procfs import reset_peak_rss, status_kib
from metampc_controller.nssm import Nssm, NssmConfig
from metampc_learner.data import normalisation_from, simulate_source, SourceConfig, SourceSet
from metampc_learner.meta_train import batch_gradient_fn, meta_train, MetaConfig
from metampc_learner.objective import FlatObjective

MEMORY_STEPS = (5, 10, 20, 50)
METHODS = {'imaml_gn': dict(method='imaml', curvature='gauss_newton'),
           'imaml_hessian': dict(method='imaml', curvature='hessian'),
           'fomaml': dict(method='maml'),
           'maml_unrolled': dict(method='maml_unrolled')}
LOOPED = ('imaml_gn', 'fomaml')


def setup():
    data = simulate_source(SourceConfig())
    config = NssmConfig()
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    return Nssm(config, norm), SourceSet(data, norm, config)


def seconds_per_step(model, source, steps: int, **kw) -> Tuple[float, float]:
    """(wall, CPU) seconds per outer step of meta_train, after one warm-up step."""
    meta_train(model, source, MetaConfig(iterations=1, **kw))
    cpu = time.process_time()
    wall = meta_train(model, source, MetaConfig(iterations=steps, **kw)).elapsed
    return wall / steps, (time.process_time() - cpu) / steps


def memory_probe(name: str, inner_steps: int) -> int:
    """Peak RSS (bytes) added by one batched meta-gradient; runs in its own process."""
    model, source = setup()
    config = MetaConfig(inner_steps=inner_steps, **METHODS[name])
    objective = FlatObjective(model)
    train, test = source.sample(range(config.batch_size), config.windows_per_task,
                                np.random.default_rng(0))
    omega = objective.spec.flatten(model.params())
    fn = batch_gradient_fn(objective, config)
    reset_peak_rss()
    before = status_kib('VmRSS')
    out = fn(omega, train.u, train.y, test.u, test.y)
    peak = status_kib('VmHWM')
    assert torch.isfinite(out.grad).all()
    return 1024 * (peak - before)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--steps', type=int, default=5)
    parser.add_argument('--memory-probe', nargs=2, metavar=('METHOD', 'M'),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.memory_probe:
        print(memory_probe(args.memory_probe[0], int(args.memory_probe[1])))
        return
    load_start = os.getloadavg()[0]
    model, source = setup()
    timing, loop = {}, {}
    for name, kw in METHODS.items():
        timing[name] = seconds_per_step(model, source, args.steps, **kw)
        if name in LOOPED:
            loop[name] = seconds_per_step(model, source, args.steps, vectorise=False, **kw)
    memory = {}
    for name in ('imaml_gn', 'maml_unrolled'):
        memory[name] = {}
        for m in MEMORY_STEPS:
            out = subprocess.run([sys.executable, __file__, '--threads', str(args.threads),
                                  '--memory-probe', name, str(m)],
                                 check=True, capture_output=True, text=True)
            memory[name][str(m)] = int(out.stdout.split()[-1])
    ratio = {name: memory[name]['50'] / memory[name]['5'] for name in memory}
    speedup = {name: loop[name][1] / timing[name][1] for name in loop}
    wall_speedup = {name: loop[name][0] / timing[name][0] for name in loop}
    print(json.dumps({
        'bench': 'meta', 'time': time.strftime('%Y-%m-%dT%H:%M:%S'),
        'load_avg_1min': os.getloadavg()[0], 'load_avg_at_start': load_start,
        'threads': args.threads, 'steps': args.steps,
        'batch_size': 16, 'inner_steps': 10, 'windows_per_task': 64, 'cg_steps': 5,
        's_per_outer_step': {k: round(v[0], 4) for k, v in timing.items()},
        'cpu_s_per_outer_step': {k: round(v[1], 4) for k, v in timing.items()},
        's_per_outer_step_loop': {k: round(v[0], 4) for k, v in loop.items()},
        'cpu_s_per_outer_step_loop': {k: round(v[1], 4) for k, v in loop.items()},
        'vmap_speedup': {k: round(v, 2) for k, v in speedup.items()},
        'vmap_speedup_wall': {k: round(v, 2) for k, v in wall_speedup.items()},
        'memory_method': 'peak RSS added by one batched meta-gradient (peak reset, then VmHWM '
                         'after - VmRSS before), fresh process per point',
        'memory_bytes': memory,
        'memory_ratio_m50_m5': {k: round(v, 3) for k, v in ratio.items()},
        'goals': {'imaml_memory_ratio_le_1.3': ratio['imaml_gn'] <= 1.3,
                  'unrolled_memory_grows': memory['maml_unrolled']['50']
                  > 2 * memory['maml_unrolled']['5'],
                  'vmap_speedup_ge_2.5': min(speedup.values()) >= 2.5},
    }))


if __name__ == '__main__':
    main()
