#!/usr/bin/env python3
"""Latency of the latent MPC's solve() against raw OSQP on the identical QP; prints one JSON line.

For each horizon N, a receding-horizon run on a seeded random stable latent model (n_z = 5,
n_y = 2, n_u = 1, |u| <= 1) tracks the paper's set-point task (dt = 0.1 s), so the input bounds
go active and inactive. Each tick times LatentMpc.solve() (z_t, u_t, r -> result: building q,
warm start, OSQP, clipping, prediction, cost) and, interleaved so that both see the same
machine load, a second osqp.OSQP set up with the same matrices and settings doing the minimum
per-tick work of any OSQP user: update(q), warm_start(x) with the same vector, solve().
ratio = p50 of ours / p50 of raw: our Python overhead. LatentMpc calls OSQP's compiled solver
under the wrapper directly (the three calls the wrapper's update, warm_start and solve make,
without the namespace of OSQP's info that its solve() builds); raw_ext_* times a third
osqp.OSQP doing exactly those calls, the floor of any Python user, and ratio_ext_p50 = ours /
raw_ext (our own work around OSQP). Wall-clock times include preemption by other processes
(reported: the load average); cpu_p99 (thread CPU time) excludes it.

Usage: python scripts/bench_mpc.py [--ticks 1000] [--seed 0]
"""
import argparse
import json
import os
import time

import numpy as np
import osqp

from metampc_bringup.analysis.percentiles import percentiles
from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.references import make_reference

DT = 0.1


def random_model(rng: np.random.Generator, n_z: int = 5, radius: float = 0.95) -> LatentModel:
    """A random latent model with spectral radius `radius`."""
    a = rng.normal(size=(n_z, n_z))
    a *= radius / max(abs(np.linalg.eigvals(a)))
    return LatentModel(A=a, B=rng.normal(size=(n_z, 1)), C=rng.normal(size=(2, n_z)),
                       e=0.1 * rng.normal(size=n_z), d=0.1 * rng.normal(size=2))


def bench(horizon: int, ticks: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    model = random_model(rng)
    cfg = MpcConfig(horizon=horizon)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    reference = make_reference('setpoint_sequence')
    raw = ext = None
    order = np.random.default_rng(seed + 1)
    z, u = np.zeros(model.n_z), np.zeros(model.n_u)
    ours, ours_cpu, raws, raws_cpu, it_ours, it_raw, fallbacks = [], [], [], [], [], [], 0
    exts, it_ext = [], []

    def time_raw(qp) -> None:
        c0, t0 = time.thread_time(), time.perf_counter()
        raw.update(q=qp.q)
        if qp.x_warm is not None:
            raw.warm_start(x=qp.x_warm)
        raw_res = raw.solve(raise_error=False)
        t1, c1 = time.perf_counter(), time.thread_time()
        raws.append(t1 - t0)
        raws_cpu.append(c1 - c0)
        it_raw.append(raw_res.info.iter)

    def time_ext(qp) -> None:
        t0 = time.perf_counter()
        ext.update_data_vec(qp.q, None, None)
        if qp.x_warm is not None:
            ext.warm_start(qp.x_warm, None)
        ext.solve()
        info = ext.info
        if info.status_val == osqp.SolverStatus.OSQP_SOLVED:
            ext.solution.x
        exts.append(time.perf_counter() - t0)
        it_ext.append(info.iter)

    pending = []
    for k in range(ticks):
        y_ref = reference.evaluate(k * DT, DT, horizon)
        for timer, qp in pending:
            timer(qp)
        pending = []
        c0, t0 = time.thread_time(), time.perf_counter()
        res = mpc.solve(z, u, y_ref)
        t1, c1 = time.perf_counter(), time.thread_time()
        ours.append(t1 - t0)
        ours_cpu.append(c1 - c0)
        it_ours.append(res.iterations)
        fallbacks += res.fallback
        qp = mpc.last_qp()
        if raw is None:
            # Set up as LatentMpc does (q = 0: OSQP's cost scaling depends on q at set-up).
            raw = osqp.OSQP()
            raw.setup(P=qp.P, q=np.zeros_like(qp.q), A=qp.A, l=qp.l, u=qp.u,
                      **cfg.osqp_settings())
            ext_solver = osqp.OSQP()
            ext_solver.setup(P=qp.P, q=np.zeros_like(qp.q), A=qp.A, l=qp.l, u=qp.u,
                             **cfg.osqp_settings())
            ext = ext_solver._solver
        # Each raw OSQP runs right after ours (OSQP's code and data hot) or just before our
        # next tick, at random and in random order, so that no side always gets the warm
        # caches.
        timers = [time_raw, time_ext]
        order.shuffle(timers)
        for timer in timers:
            if order.random() < 0.5:
                timer(qp)
            else:
                pending.append((timer, qp))
        u = res.u
        z = model.step(z, u)
    for timer, qp in pending:
        timer(qp)
    us = dict(scale=1e6, digits=1)
    stats = {**percentiles(ours, (50, 99), key='{}_us', **us),
             **percentiles(ours_cpu, (99,), key='cpu_{}_us', **us),
             **percentiles(raws, (50, 99), key='raw_{}_us', **us),
             **percentiles(raws_cpu, (99,), key='raw_cpu_{}_us', **us),
             **percentiles(exts, (50, 99), key='raw_ext_{}_us', **us)}
    return {
        **stats,
        'ratio_p50': round(stats['p50_us'] / stats['raw_p50_us'], 2),
        'ratio_p99': round(stats['p99_us'] / stats['raw_p99_us'], 2),
        'ratio_ext_p50': round(stats['p50_us'] / stats['raw_ext_p50_us'], 2),
        'iter_mean': round(float(np.mean(it_ours)), 2), 'iter_max': int(np.max(it_ours)),
        'iter_equal_raw': bool(np.array_equal(it_ours, it_raw)
                               and np.array_equal(it_ours, it_ext)),
        'fallbacks': int(fallbacks),
        'terminal_fallback': bool(res.terminal_fallback),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--ticks', type=int, default=1000)
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    out = {'n_z': 5, 'ticks': args.ticks, 'loadavg_1min': round(os.getloadavg()[0], 2)}
    for horizon in (10, 20, 50):
        out[f'N{horizon}'] = bench(horizon, args.ticks, args.seed)
    n20 = out['N20']
    out['goals_met'] = {'N20_p99_le_500us': n20['p99_us'] <= 500.0,
                        'N20_ratio_p50_le_1.5': n20['ratio_p50'] <= 1.5,
                        'N20_ratio_p50_le_1.3': n20['ratio_p50'] <= 1.3}
    out['loadavg_1min_end'] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
