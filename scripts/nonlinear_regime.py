#!/usr/bin/env python3
"""The feature NARX on its locally linear MPC against the true-model NMPC, in one process.

    python scripts/nonlinear_regime.py                       # van der Pol theta* 1.0 .. 2.0
    python scripts/nonlinear_regime.py --thetas 1.5 --seeds 1 --iterations 300   # quick

Prints a line per episode and a summary per model (cost / NMPC median and worst, escapes);
--out FILE writes every row as JSON. Protocol: docs/nonlinear.md.
"""
import argparse
import json
import math
import os
import sys

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--thetas', default='1.0,1.25,1.5,1.75,2.0',
                    help='test targets theta*, comma-separated (default: %(default)s)')
    ap.add_argument('--seeds', type=int, default=2, help='data seeds per target (0..N-1)')
    ap.add_argument('--methods', default='imaml,maml', help='meta-learning methods')
    ap.add_argument('--iterations', type=int, default=1000, help='meta-training outer steps')
    ap.add_argument('--features', type=int, default=32, help='meta-learned features F')
    ap.add_argument('--out', help='write the rows as JSON to this file (refused if it exists)')
    args = ap.parse_args(argv)
    try:
        thetas = [float(v) for v in args.thetas.split(',')]
    except ValueError:
        print(f'nonlinear_regime: --thetas needs numbers, got {args.thetas!r}', file=sys.stderr)
        return 2
    methods = [m for m in args.methods.split(',') if m]
    if args.out and os.path.exists(args.out):
        print(f'nonlinear_regime: {args.out} exists; give another --out', file=sys.stderr)
        return 2
    if args.out and not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        print(f'nonlinear_regime: no folder for {args.out}', file=sys.stderr)
        return 2
    if args.seeds < 1 or args.iterations < 1 or args.features < 0:
        print('nonlinear_regime: --seeds and --iterations must be >= 1, --features >= 0',
              file=sys.stderr)
        return 2
    import torch
    from metampc_bringup.studies.nonlinear_regime import RegimeConfig, run
    from metampc_learner.narx_learning import METHODS, NarxMetaConfig
    if not methods or set(methods) - set(METHODS):
        print(f'nonlinear_regime: --methods takes {",".join(METHODS)}', file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    config = RegimeConfig(thetas=tuple(thetas), data_seeds=tuple(range(args.seeds)),
                          methods=tuple(methods), features=args.features,
                          meta=NarxMetaConfig(iterations=args.iterations, gamma=1e-5))
    rows = run(config, log=lambda line: print(line, flush=True))
    print('\nmodel            cost / NMPC median   worst   escapes   held-out l_SSM median')
    for name in dict.fromkeys(r['model'] for r in rows):
        ratios = [r['ratio'] for r in rows if r['model'] == name]
        held = [r['heldout'] for r in rows if r['model'] == name]
        esc = sum(not math.isfinite(r['cost']) for r in rows if r['model'] == name)
        print(f'{name:>14}   {np.median(ratios):18.3f}   {max(ratios):6.3f}   {esc:7d}   '
              f'{np.median(held):.2e}')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
