#!/usr/bin/env python3
"""Cost of meta-training: time per outer step, fast vs eager, vmap vs loop, memory vs M.

Prints one JSON line. Set-up: the default NSSM (H = 10, T = 10, encoder 128-128, n_z = 5), the
default source set (100 systems), MetaConfig defaults (B = 16, M = 10, 64 windows per task,
5 CG steps), `--threads` torch threads (default 1, so that the CPU-time figures are per core and
the run leaves the second core of a shared 2-core machine to others).

- s_per_outer_step: wall time of meta_train per outer step (task sampling included), mean
  over `--steps` steps after one warm-up step, eager backend (tasks vmapped); for iMAML with
  Gauss-Newton and with exact-Hessian curvature, first-order MAML and unrolled MAML.
  cpu_s_per_outer_step: the process CPU time of the same steps (not inflated when other
  processes take the core).
- fast vs eager (iMAML-GN and first-order MAML): `--rounds` rounds of `--steps` outer steps
  with each backend, interleaved (eager then fast, then fast then eager, ...) after one
  warm-up step of each, so that both see the same load; s_per_outer_step_fast /
  cpu_s_per_outer_step_fast and s_per_outer_step_eager / cpu_s_per_outer_step_eager are the
  means over all rounds, fast_over_eager the ratio of CPU times (fast_over_eager_wall of wall
  times). max_abs_diff_grad: the largest difference between the two backends' meta-gradients
  of one batch (B = 16, same omega and windows), with the largest entry beside it.
- vmap_speedup: CPU time per step with a Python loop over the tasks divided by that with vmap,
  both measured back to back (wall-clock ratio beside it).
- memory: peak resident set size (RSS) added by ONE batched meta-gradient (B = 16) for
  M in {5, 10, 20, 50}, each in a fresh process: the peak is reset just before the call
  (/proc/self/clear_refs), then VmHWM after minus VmRSS before (/proc/self/status); it
  includes one-time allocations common to every M. imaml_gn_fast: the same with the fast
  backend (the others: eager).

Load average and the time are in the line: wall-clock numbers depend on other processes.

Usage: python scripts/bench_meta.py [--threads 1] [--steps 5] [--rounds 3] [--speed-only]
(--speed-only: only the fast vs eager comparison; its time: docs/learning.md).

CUDA check: python scripts/bench_meta.py --device cuda [--steps 5] [--rounds 3] prints one
JSON line with the fast backend on cuda vs on the cpu (s and CPU s per outer step, the ratio)
and the largest absolute difference of the meta-gradient on cuda vs cpu (same batch), for
iMAML-GN and first-order MAML, whether two cuda runs of the same seed give the same weights,
and the eager backend on cuda vs cpu. Needs only torch and numpy besides the sources:
PYTHONPATH=src/metampc_common:src/metampc_controller:src/metampc_plant:src/metampc_learner:\
src/metampc_bringup python3 scripts/bench_meta.py --device cuda
"""
import argparse
import importlib
import json
import os
import subprocess
import sys
import time
from typing import Tuple

import numpy as np
import torch

from metampc_bringup.orchestration.procfs import reset_peak_rss, status_kib
from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.data import normalisation_from, simulate_source, SourceConfig, SourceSet
from metampc_learner.meta_train import batch_gradient_fn, meta_train, MetaConfig
from metampc_learner.objective import FlatObjective
from metampc_plant.registry import DEFAULT, get_family, register, UnknownFamily

MEMORY_STEPS = (5, 10, 20, 50)
VARIANTS = {'imaml_gn': dict(method='imaml', curvature='gauss_newton'),
            'imaml_hessian': dict(method='imaml', curvature='hessian'),
            'fomaml': dict(method='maml'),
            'maml_unrolled': dict(method='maml_unrolled')}
LOOPED = ('imaml_gn', 'fomaml')
FAST = ('imaml_gn', 'fomaml')


def setup():
    try:
        get_family(DEFAULT)
    except UnknownFamily:      # run from the sources (PYTHONPATH), no installed entry points
        register(importlib.import_module(f'metampc_plant.families.{DEFAULT}').FAMILY)
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


def interleaved(model, source, steps: int, rounds: int, variants, **kw):
    """{variant: (wall, CPU) s per outer step}: `rounds` rounds of `steps` outer steps of
    each variant (a dict of MetaConfig fields), alternating which goes first; one warm-up
    step of each before."""
    names = list(variants)
    for name in names:
        meta_train(model, source, MetaConfig(iterations=1, **kw, **variants[name]))
    wall = {name: 0.0 for name in names}
    cpu = {name: 0.0 for name in names}
    for r in range(rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            start = time.process_time()
            wall[name] += meta_train(model, source, MetaConfig(iterations=steps, **kw,
                                                               **variants[name])).elapsed
            cpu[name] += time.process_time() - start
    n = steps * rounds
    return {name: (wall[name] / n, cpu[name] / n) for name in names}


def one_batch(model, source, config: MetaConfig, device='cpu'):
    """The batched meta-gradient of one fixed batch (B = 16, tasks 0..15, seed 0) at the
    initial weights, on `device`; returned on the CPU."""
    objective = FlatObjective(model)
    train, test = source.sample(range(config.batch_size), config.windows_per_task,
                                np.random.default_rng(0))
    omega = objective.spec.flatten(model.params())
    args = [x.to(device) for x in (omega, train.u, train.y, test.u, test.y)]
    return batch_gradient_fn(objective, config)(*args).grad.cpu()


def fast_vs_eager(model, source, steps: int, rounds: int) -> dict:
    """The fast backend against the eager reference, interleaved (see the docstring)."""
    out = {key: {} for key in ('s_per_outer_step_fast', 'cpu_s_per_outer_step_fast',
                               's_per_outer_step_eager', 'cpu_s_per_outer_step_eager',
                               'fast_over_eager', 'fast_over_eager_wall',
                               'max_abs_diff_grad', 'max_abs_grad')}
    for name in FAST:
        kw = VARIANTS[name]
        t = interleaved(model, source, steps, rounds,
                        {'eager': dict(backend='eager'), 'fast': dict(backend='fast')}, **kw)
        for backend in ('fast', 'eager'):
            out[f's_per_outer_step_{backend}'][name] = round(t[backend][0], 4)
            out[f'cpu_s_per_outer_step_{backend}'][name] = round(t[backend][1], 4)
        out['fast_over_eager'][name] = round(t['fast'][1] / t['eager'][1], 3)
        out['fast_over_eager_wall'][name] = round(t['fast'][0] / t['eager'][0], 3)
        eager = one_batch(model, source, MetaConfig(backend='eager', **kw))
        fast = one_batch(model, source, MetaConfig(backend='fast', **kw))
        out['max_abs_diff_grad'][name] = float((fast - eager).abs().max())
        out['max_abs_grad'][name] = float(eager.abs().max())
    return out


def cuda_check(args) -> dict:
    """The fast backend on cuda vs on the cpu (see the module docstring)."""
    model, source = setup()
    out = {'bench': 'meta_cuda', 'time': time.strftime('%Y-%m-%dT%H:%M:%S'),
           'load_avg_at_start': os.getloadavg()[0], 'threads': args.threads,
           'steps': args.steps, 'rounds': args.rounds, 'torch': torch.__version__,
           'gpu': torch.cuda.get_device_name(0)}
    for key in ('s_per_outer_step', 'cpu_s_per_outer_step', 'cuda_over_cpu_wall',
                'max_abs_diff_grad_cuda_vs_cpu', 'max_abs_grad', 'cuda_same_seed_same_weights',
                'eager_cuda_max_abs_diff_grad_vs_cpu'):
        out[key] = {}
    for name in FAST:
        kw = VARIANTS[name]
        t = interleaved(model, source, args.steps, args.rounds,
                        {'cpu': dict(device='cpu'), 'cuda': dict(device='cuda')}, **kw)
        out['s_per_outer_step'][name] = {d: round(v[0], 4) for d, v in t.items()}
        out['cpu_s_per_outer_step'][name] = {d: round(v[1], 4) for d, v in t.items()}
        out['cuda_over_cpu_wall'][name] = round(t['cuda'][0] / t['cpu'][0], 3)
        cpu = one_batch(model, source, MetaConfig(**kw))
        gpu = one_batch(model, source, MetaConfig(device='cuda', **kw), 'cuda')
        out['max_abs_diff_grad_cuda_vs_cpu'][name] = float((gpu - cpu).abs().max())
        out['max_abs_grad'][name] = float(cpu.abs().max())
        runs = [meta_train(model, source, MetaConfig(iterations=3, device='cuda', **kw))
                for _ in range(2)]
        out['cuda_same_seed_same_weights'][name] = all(
            torch.equal(runs[0].params[k], runs[1].params[k]) for k in runs[0].params)
        try:
            eager = one_batch(model, source, MetaConfig(backend='eager', device='cuda', **kw),
                              'cuda')
            ref = one_batch(model, source, MetaConfig(backend='eager', **kw))
            out['eager_cuda_max_abs_diff_grad_vs_cpu'][name] = float((eager - ref).abs().max())
        except Exception as err:      # reported, not fatal: the fast path is what is checked
            out['eager_cuda_max_abs_diff_grad_vs_cpu'][name] = f'{type(err).__name__}: {err}'
    out['load_avg_1min'] = os.getloadavg()[0]
    return out


def memory_probe(name: str, inner_steps: int) -> int:
    """Peak RSS (bytes) added by one batched meta-gradient; runs in its own process
    (`name` with the suffix '_fast': the fast backend, else the eager one)."""
    model, source = setup()
    backend = 'fast' if name.endswith('_fast') else 'eager'
    config = MetaConfig(inner_steps=inner_steps, backend=backend,
                        **VARIANTS[name[:-len('_fast')] if backend == 'fast' else name])
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
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--speed-only', action='store_true')
    parser.add_argument('--device', choices=('cpu', 'cuda'), default='cpu')
    parser.add_argument('--memory-probe', nargs=2, metavar=('METHOD', 'M'),
                        help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.memory_probe:
        print(memory_probe(args.memory_probe[0], int(args.memory_probe[1])))
        return
    if args.device == 'cuda':
        print(json.dumps(cuda_check(args)))
        return
    load_start = os.getloadavg()[0]
    model, source = setup()
    fast = fast_vs_eager(model, source, args.steps, args.rounds)
    head = {'bench': 'meta', 'time': time.strftime('%Y-%m-%dT%H:%M:%S'),
            'load_avg_1min': os.getloadavg()[0], 'load_avg_at_start': load_start,
            'threads': args.threads, 'steps': args.steps, 'rounds': args.rounds,
            'batch_size': 16, 'inner_steps': 10, 'windows_per_task': 64, 'cg_steps': 5}
    goal = {'fast_over_eager_le_0.5': max(fast['fast_over_eager'].values()) <= 0.5}
    if args.speed_only:
        print(json.dumps({**head, **fast, 'goals': goal}))
        return
    timing, loop = {}, {}
    for name, kw in VARIANTS.items():
        timing[name] = seconds_per_step(model, source, args.steps, backend='eager', **kw)
        if name in LOOPED:
            loop[name] = seconds_per_step(model, source, args.steps, vectorise=False,
                                          backend='eager', **kw)
    memory = {}
    for name in ('imaml_gn', 'imaml_gn_fast', 'maml_unrolled'):
        memory[name] = {}
        for m in MEMORY_STEPS:
            out = subprocess.run([sys.executable, __file__, '--threads', str(args.threads),
                                  '--memory-probe', name, str(m)],
                                 check=True, capture_output=True, text=True)
            memory[name][str(m)] = int(out.stdout.split()[-1])
    ratio = {name: memory[name]['50'] / memory[name]['5'] for name in memory}
    speedup = {name: loop[name][1] / timing[name][1] for name in loop}
    wall_speedup = {name: loop[name][0] / timing[name][0] for name in loop}
    head['load_avg_1min'] = os.getloadavg()[0]
    print(json.dumps({
        **head, **fast,
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
                  'vmap_speedup_ge_2.5': min(speedup.values()) >= 2.5, **goal},
    }))


if __name__ == '__main__':
    main()
