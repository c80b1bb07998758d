#!/usr/bin/env python3
"""The feature NARX on its locally linear MPC against the true-model NMPC, in one process.

    python scripts/nonlinear_regime.py --thetas 1.0,1.25,1.5,1.75,2.0   # van der Pol, 2 seeds
    python scripts/nonlinear_regime.py --config config/duffing.yaml --seeds 10   # the draws
    python scripts/nonlinear_regime.py --thetas 1.5 --seeds 1 --iterations 300   # quick
    python scripts/nonlinear_regime.py --thetas 1.5 --closed-loop 0.5   # half in closed loop

Targets: --thetas (a one-component family: comma-separated targets; several components: the
targets separated by ';', their values by ','), each with data seeds 0..--seeds-1; without
--thetas, test seeds --first-seed.. with theta* drawn as the experiment draws it.

Prints a line per episode and a summary per model (cost / NMPC median and worst, escapes);
--out FILE writes every row as JSON. Protocol: docs/nonlinear.md.
"""
import argparse
import json
import os
import sys

import yaml


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--config', help='experiment configuration (default: config/default.yaml)')
    ap.add_argument('--thetas', default='', help='test targets theta* (see above; default: '
                    "each seed's draw)")
    ap.add_argument('--seeds', type=int, default=2, help='seeds (per target with --thetas)')
    ap.add_argument('--first-seed', type=int, default=0, help='first seed')
    ap.add_argument('--methods', default='imaml', help='meta-learning methods (imaml, maml)')
    ap.add_argument('--no-oracle', action='store_true', help='leave the oracle out')
    ap.add_argument('--set', action='append', default=[], metavar='KEY=YAML',
                    help='a configuration key on top of the file (section.key merges into '
                         'the section), e.g. controller.reference_values=[1.2,-1.2]')
    ap.add_argument('--iterations', type=int,
                    help="meta-training outer steps (default: NarxMetaConfig's)")
    ap.add_argument('--features', type=int, default=32, help='meta-learned features F')
    ap.add_argument('--closed-loop', type=float, default=0.0,
                    help='share of the target samples collected in closed loop by the model '
                         'adapted to the rest (open loop), then adapted again on all; 0: none')
    ap.add_argument('--exploration', type=float, default=0.0,
                    help="the closed-loop part's exploration added to the input (the "
                         "excitation's band, as a share of the input range)")
    ap.add_argument('--arx-where-the-prior-loses', action='store_true',
                    help="where the adaptation's fit toward the meta-model loses to the ARX "
                         "on the samples, fly the ARX's head (default: a fit toward it)")
    ap.add_argument('--cache', help="a folder where meta-models and each target's rows are "
                    'kept and read back (the same settings: the same file), so a stopped study '
                    'resumes where it stopped')
    ap.add_argument('--out', help='write the rows as JSON to this file (refused if it exists)')
    args = ap.parse_args(argv)
    try:
        parts = args.thetas.split(';') if ';' in args.thetas else args.thetas.split(',')
        thetas = [[float(v) for v in p.split(',')] if ';' in args.thetas else [float(p)]
                  for p in parts if p.strip()]
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
    overrides = {}
    for item in args.set:
        key, eq, value = item.partition('=')
        if not eq or not key:
            print(f'nonlinear_regime: --set needs KEY=VALUE, got {item!r}', file=sys.stderr)
            return 2
        section, dot, name = key.partition('.')
        try:
            parsed = yaml.safe_load(value)
        except yaml.YAMLError:
            print(f'nonlinear_regime: --set {key}: not a YAML value', file=sys.stderr)
            return 2
        if dot:
            overrides.setdefault(section, {})[name] = parsed
        else:
            overrides[key] = parsed
    if args.cache and not os.path.isdir(args.cache):
        print(f'nonlinear_regime: no folder {args.cache} for --cache', file=sys.stderr)
        return 2
    if args.config and not os.path.isfile(args.config):
        print(f'nonlinear_regime: no configuration {args.config}', file=sys.stderr)
        return 2
    if (args.seeds < 1 or args.first_seed < 0 or args.features < 0
            or (args.iterations is not None and args.iterations < 1)):
        print('nonlinear_regime: --seeds and --iterations must be >= 1, --features >= 0',
              file=sys.stderr)
        return 2
    if not 0.0 <= args.closed_loop < 1.0 or not 0.0 <= args.exploration <= 1.0:
        print('nonlinear_regime: --closed-loop must be in [0, 1), --exploration in [0, 1]',
              file=sys.stderr)
        return 2
    import torch
    from metampc_bringup.studies.nonlinear_regime import RegimeConfig, run, summary
    from metampc_learner.narx_learning import NARX_METHODS, NarxMetaConfig
    if not methods or set(methods) - set(NARX_METHODS):
        print(f'nonlinear_regime: --methods takes {",".join(NARX_METHODS)}', file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    config = RegimeConfig(experiment=args.config, thetas=tuple(thetas),
                          seeds=tuple(range(args.first_seed, args.first_seed + args.seeds)),
                          methods=tuple(methods), features=args.features,
                          meta=NarxMetaConfig(**({} if args.iterations is None
                                                 else {'iterations': args.iterations})),
                          oracle=not args.no_oracle, overrides=overrides,
                          closed_loop=args.closed_loop, exploration=args.exploration,
                          toward_arx=not args.arx_where_the_prior_loses)
    try:
        rows = run(config, log=lambda line: print(line, flush=True), cache=args.cache)
    except ValueError as err:        # a configuration or theta the family refuses
        print(f'nonlinear_regime: {err}', file=sys.stderr)
        return 2
    print('\n' + '\n'.join(summary(rows)))
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
