#!/usr/bin/env python3
"""The drift scenario flown by the feature NARX, with and without the in-loop RLS, in one process.

    python scripts/rls_drift.py --config config/drift.yaml --first-seed 100 --seeds 5 \\
        --variant rls:rls_forgetting=0.95 --cache /tmp/narx
    python scripts/rls_drift.py --config config/quadruple_tank.yaml --centre-step 0.1 ...

Variants: `none` (the controller's defaults) and each --variant NAME:PARAM=VALUE[,PARAM=VALUE]
(controller parameters, e.g. rls_forgetting=0.98,rls_columns=bias). The meta-model: the source
systems of --meta-seed (one for every seed run). Prints a line per episode, then per variant the
after-change cost over none by seed; --out FILE writes every row as JSON. Protocol and results:
docs/adaptation.md#recursive-least-squares-on-the-feature-narx.
"""
import argparse
import json
import os
import sys

import yaml


def _variants(items):
    """{'none': {}, NAME: {param: value}} from --variant arguments (ValueError: malformed)."""
    out = {'none': {}}
    for item in items:
        name, colon, rest = item.partition(':')
        if not colon or not name or name in out:
            raise ValueError(f'--variant needs a new NAME:PARAM=VALUE,..., got {item!r}')
        params = {}
        for pair in rest.split(','):
            key, eq, value = pair.partition('=')
            if not eq or not key:
                raise ValueError(f'--variant {name}: PARAM=VALUE expected, got {pair!r}')
            parsed = yaml.safe_load(value)
            try:        # YAML 1.1 reads 1e-5 as a string
                parsed = float(parsed) if isinstance(parsed, str) else parsed
            except ValueError:
                pass
            params[key] = parsed
        out[name] = params
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--config', default='config/drift.yaml', help='experiment configuration')
    ap.add_argument('--seeds', type=int, default=5, help='seeds')
    ap.add_argument('--first-seed', type=int, default=0, help='first seed')
    ap.add_argument('--meta-seed', type=int, default=0,
                    help='the seed whose source systems meta-train the feature NARX')
    ap.add_argument('--variant', action='append', default=[], metavar='NAME:PARAM=VALUE,...',
                    help='controller parameters of a variant beside none (repeatable)')
    ap.add_argument('--centre-step', type=float,
                    help="theta moves by this toward its prior's middle at half the run "
                         "(default: the configuration's drift.schedule)")
    ap.add_argument('--no-constant', action='store_true', help='leave the constant-theta runs '
                    'out')
    ap.add_argument('--no-nmpc', action='store_true', help='leave the NMPC yardstick out (its '
                    'ratios NaN)')
    ap.add_argument('--cache', help='a folder where meta-models are kept and read back')
    ap.add_argument('--out', help='write the rows as JSON to this file (refused if it exists)')
    args = ap.parse_args(argv)
    try:
        variants = _variants(args.variant)
    except (ValueError, yaml.YAMLError) as err:
        print(f'rls_drift: {err}', file=sys.stderr)
        return 2
    if args.out and os.path.exists(args.out):
        print(f'rls_drift: {args.out} exists; give another --out', file=sys.stderr)
        return 2
    if args.cache and not os.path.isdir(args.cache):
        print(f'rls_drift: no folder {args.cache} for --cache', file=sys.stderr)
        return 2
    if not os.path.isfile(args.config):
        print(f'rls_drift: no configuration {args.config}', file=sys.stderr)
        return 2
    if args.seeds < 1 or args.first_seed < 0 or args.meta_seed < 0:
        print('rls_drift: --seeds must be >= 1, --first-seed and --meta-seed >= 0',
              file=sys.stderr)
        return 2
    import torch
    from metampc_bringup.analysis.paired_stats import format_claim, paired_claim
    from metampc_bringup.studies.nonlinear_regime import RegimeConfig
    from metampc_bringup.studies.rls_drift import paired, run, RlsDriftConfig
    from metampc_common.params import ParameterError
    torch.set_num_threads(1)
    config = RlsDriftConfig(
        regime=RegimeConfig(experiment=args.config, seeds=(args.meta_seed,), oracle=False),
        seeds=tuple(range(args.first_seed, args.first_seed + args.seeds)), variants=variants,
        centre_step=args.centre_step, constant=not args.no_constant, nmpc=not args.no_nmpc)
    try:
        rows = run(config, log=lambda line: print(line, flush=True), cache=args.cache)
    except (ValueError, ParameterError) as err:   # a bad parameter, theta or schedule
        print(f'rls_drift: {err}', file=sys.stderr)
        return 2
    for name in variants:
        for run_name in ('drift', 'constant') if not args.no_constant else ('drift',):
            ratios = paired(rows, name, run=run_name)
            claim = format_claim(paired_claim(list(ratios.values()), [1.0] * len(ratios),
                                              log=True))
            print(f'{name:>16} {run_name:>8} after / none: '
                  + ', '.join(f'{s}: {r:.4f}' for s, r in ratios.items())
                  + (f'; {name} < none: {claim}' if name != 'none' else ''))
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
