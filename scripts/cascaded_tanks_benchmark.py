#!/usr/bin/env python3
"""The Cascaded Tanks benchmark measured on the real data: meta-learned NSSMs against the
supervised NSSM, an ARX model and the grey-box physics model, on the test record and on the
tank's twin in closed loop.

Per meta-training seed (--seed, several in turn): meta-trains iMAML and first-order MAML on
simulated systems of the `cascaded_tanks` family (--config: its learner set-up and
meta-training settings), then fits every model on the estimation record's first 300 samples
and on all 1024: the meta-models adapted with the learner's own eq. (infer), the supervised
NSSM from random weights, ARX, grey-box (these two do not depend on the seed). Every choice
(adaptation step size and steps, ARX orders) is made on the estimation record: fitted on its
head (samples 0..299, or 0..767 for the full record's choice), scored on samples 768..1023.
The test record is then predicted once: free-run simulation RMSE and T-step prediction RMSE,
volts. Beside them, the feature NARX of docs/nonlinear.md (iMAML through its closed-form
solve, on the same simulated systems) and the least-squares ARX(p) of its class: the head
adapted in closed form on every one-step equation of the fitted samples, the order p of
NARX_ORDERS chosen on the estimation record as the ARX orders are (simulation RMSE of
samples 768..1023), the test record simulated from its first p pairs. The twin (the family
at the grey-box fit to all 1024 samples) is tracked by the latent MPC of --config's
controller section on each fitted NSSM and by the true-model NMPC (docs/real_data.md says how
each model runs and where its initial state comes from).

Usage: python scripts/cascaded_tanks_benchmark.py --out runs/cts [--seed 0 1 2 3 4]
       [--config config/cascaded_tanks.yaml] [--figure docs/img/cascaded_tanks_test.png]
       [--twin-figure docs/img/cascaded_tanks_twin.png]
Writes OUT/seed_<s>/benchmark.json and narx.json per seed and OUT/summary.json, prints the
tables; every step is cached in OUT (run the same command again to resume). Exit status: 0
done, 2 bad arguments. The code: metampc_bringup.studies.cascaded_tanks_run.run and the
modules it names.
"""
import argparse
import sys

from metampc_bringup.analysis.cascaded_tanks_report import table, twin_table
from metampc_bringup.studies.cascaded_tanks import OutOfRange, TanksOptions
from metampc_bringup.studies.cascaded_tanks_run import BadOptions, run

DEFAULT = TanksOptions(out='')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', required=True, help='folder of the results and the cache')
    parser.add_argument('--seed', type=int, nargs='+', default=list(DEFAULT.seeds),
                        help='meta-training seeds, run in turn (each: source set, '
                             'meta-training and supervised initial weights; OUT/seed_<s>/)')
    parser.add_argument('--config', default=DEFAULT.config,
                        help='the family\'s experiment configuration (learner, meta_train, '
                             'controller, reference)')
    parser.add_argument('--figure', default=DEFAULT.figure, help='PNG of the test-record free '
                        'runs (the first seed)')
    parser.add_argument('--twin-figure', default=DEFAULT.twin_figure, help='PNG of the tracking '
                        'runs on the twin (the first seed)')
    parser.add_argument('--max-steps', type=int, default=DEFAULT.max_steps,
                        help='adaptation steps searched (0..this) on the estimation record')
    parser.add_argument('--meta-iterations', type=int, default=DEFAULT.meta_iterations,
                        help='outer steps of every meta-training (0: the config\'s for '
                             'the NSSMs, 1000 for the feature NARX)')
    parser.add_argument('--n-systems', type=int, default=DEFAULT.n_systems,
                        help='source systems (0: the config\'s)')
    parser.add_argument('--candidates', type=int, default=DEFAULT.candidates,
                        help='grey-box candidates')
    parser.add_argument('--polish', type=int, default=DEFAULT.polish, help='grey-box searches')
    parser.add_argument('--substeps', type=int, default=DEFAULT.substeps,
                        help='grey-box RK4 steps a sample')
    args = parser.parse_args(argv)
    try:
        result = run(TanksOptions(
            out=args.out, seeds=tuple(args.seed), config=args.config, figure=args.figure,
            twin_figure=args.twin_figure, max_steps=args.max_steps,
            meta_iterations=args.meta_iterations, n_systems=args.n_systems,
            candidates=args.candidates, polish=args.polish, substeps=args.substeps))
    except (BadOptions, OutOfRange) as err:
        print(f'cascaded_tanks_benchmark: {err}', file=sys.stderr)
        return 2
    print(table(result))
    print()
    print(twin_table(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
