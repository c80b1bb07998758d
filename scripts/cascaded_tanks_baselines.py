#!/usr/bin/env python3
"""The classical baselines on the Cascaded Tanks benchmark's estimation record, validated on
its tail: a linear ARX model (orders chosen on the tail) and the grey-box fit of the
`cascaded_tanks` family's physics (k1..k5 and the initial levels).

Fits on the estimation record's samples 0..FIT-1 (--fit-samples: 768, or 300 as the learner
adapts on), scores on samples --validation-start..1023 (default 768): free-run simulation RMSE
and T-step prediction RMSE, volts (metampc_plant/identification/validation.py; docs/
real_data.md). The test record, loaded with the file, is not used. Prints one JSON line, or
a table with --table.

Usage: python scripts/cascaded_tanks_baselines.py [--fit-samples 768] [--validation-start 768]
       [--history 10] [--horizon 10] [--candidates 512] [--polish 4] [--seed 0]
       [--substeps 4] [--table]
Exit status: 0 done, 2 bad arguments.
"""
import argparse
import json
import sys
import time

import numpy as np

from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.families.cascaded_tanks import GUESS
from metampc_plant.identification.validation import arx_baseline, greybox_baseline, Protocol
from metampc_plant.registry import get_family


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    defaults = Protocol()
    for name, text in (('fit-samples', 'samples 0..N-1 of the estimation record fit the models'),
                       ('validation-start', 'first sample of the scored tail'),
                       ('history', 'H, samples up to a T-step origin a predictor may read'),
                       ('horizon', 'T, samples predicted from each origin'),
                       ('max-order', 'ARX na, nb searched in 1..this'),
                       ('max-delay', 'ARX nk searched in 0..this'),
                       ('candidates', 'grey-box candidates scored in one batch'),
                       ('polish', 'grey-box least-squares searches from the best candidates'),
                       ('seed', 'seed of the grey-box candidates'),
                       ('substeps', 'RK4 steps per 4 s sample of the grey-box model')):
        default = getattr(defaults, name.replace('-', '_'))
        parser.add_argument(f'--{name}', type=int, default=default,
                            help=f'{text} (default {default})')
    parser.add_argument('--table', action='store_true', help='a table instead of JSON')
    args = parser.parse_args(argv)
    protocol = Protocol(args.fit_samples, args.validation_start, args.history, args.horizon,
                        args.max_order, args.max_delay, args.candidates, args.polish,
                        defaults.spread, args.seed, args.substeps)
    data = load_cascaded_tanks()
    try:
        protocol.check(len(data.y_est))
    except ValueError as err:
        print(f'cascaded_tanks_baselines: {err}', file=sys.stderr)
        return 2
    family = get_family('cascaded_tanks')
    u, y = data.u_est, data.y_est
    started = time.perf_counter()
    arx, arx_scores = arx_baseline(u, y, protocol)
    arx_seconds = time.perf_counter() - started
    fit, grey_scores = greybox_baseline(family, u, y, protocol, GUESS,
                                        (np.zeros(family.n_theta), np.full(family.n_theta,
                                                                           np.inf)))
    report = {
        'fit_samples': protocol.fit_samples,
        'validation': [protocol.validation_start, len(y)],
        'history': protocol.history, 'horizon': protocol.horizon,
        'arx': {'na': len(arx.a), 'nb': len(arx.b), 'nk': arx.nk,
                'simulation_rmse': round(arx_scores.simulation_rmse, 4),
                'prediction_rmse': round(arx_scores.prediction_rmse, 4),
                'seconds': round(arx_seconds, 1)},
        'greybox': {'theta': [round(v, 5) for v in fit.theta],
                    'x0': [round(v, 3) for v in fit.x0],
                    'fit_rmse': round(fit.rmse, 4),
                    'simulation_rmse': round(grey_scores.simulation_rmse, 4),
                    'prediction_rmse': round(grey_scores.prediction_rmse, 4),
                    'simulations': fit.evaluations,
                    'seconds': round(time.perf_counter() - started - arx_seconds, 1)}}
    if not args.table:
        print(json.dumps(report))
        return 0
    arx_name = f'ARX({len(arx.a)}, {len(arx.b)}, {arx.nk})'
    print(f'fit on samples 0..{protocol.fit_samples - 1}, scored on '
          f'{protocol.validation_start}..{len(y) - 1} (V)')
    print(f'{"model":<16} {"simulation RMSE":>16} {f"{protocol.horizon}-step RMSE":>14}')
    for name, scores in ((arx_name, arx_scores), ('grey-box', grey_scores)):
        print(f'{name:<16} {scores.simulation_rmse:>16.4f} {scores.prediction_rmse:>14.4f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
