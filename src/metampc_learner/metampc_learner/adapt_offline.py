"""`ros2 run metampc_learner adapt_offline`: adaptation from a recording, on the command line.

    ros2 run metampc_learner adapt_offline RECORDING MAPPING CHECKPOINT --out ADAPTED.pt
        [--method M] [--steps N] [--lr R] [--gamma G] [--rule R] [--cg-steps N]
        [--config YAML] [--samples N]
        [--holdout F] [--seed S] [--keep-saturated] [--time-column NAME] [--arx-order P]

A thin layer over :mod:`.offline_adaptation`: it writes ADAPTED.pt, ADAPTED.json and
ADAPTED.md, prints the markdown report, and logs each phase and step on stderr. Bad input (a
wrong mapping, a topic or column missing, a checkpoint that does not fit) is one line on stderr
and exit status 2. docs/offline_adaptation.md.
"""
import argparse
import sys

from metampc_learner.adapt import RULES
from metampc_learner.meta_train import META_METHODS
from metampc_learner.offline_adaptation import (ARX, OfflineConfig, report_markdown,
                                                run_offline, SUPERVISED)


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f'must be in (0, 1), got {text}')
    return value


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0, got {text}')
    return value


def parser() -> argparse.ArgumentParser:
    """The command line (see the module docstring)."""
    p = argparse.ArgumentParser(prog='adapt_offline', description='Adapt a meta-model to a '
                                'machine from its recording (docs/offline_adaptation.md).')
    p.add_argument('recording', help='a bag (rosbag2 folder, .mcap or .db3) or a .csv file')
    p.add_argument('mapping', help="the machine's mapping file (the bridge's YAML)")
    p.add_argument('checkpoint', help='the meta-model checkpoint (the learner\'s .pt)')
    p.add_argument('--out', required=True, help='the adapted checkpoint to write (.pt); the '
                   'report goes beside it (.json, .md)')
    p.add_argument('--method', default='', choices=['', *META_METHODS, SUPERVISED, ARX],
                   help="default: the checkpoint's; supervised: from random weights; arx: the "
                   'linear ARX baseline by least squares (the checkpoint gives H and scaling)')
    p.add_argument('--steps', type=_count, help='adaptation steps (default: --config, else 20)')
    p.add_argument('--lr', type=float, help='step size (default: --config, else 0.05)')
    p.add_argument('--gamma', type=float, help='proximal strength of eq. (infer) (default: '
                   '--config, else 0)')
    p.add_argument('--rule', choices=RULES, help='step rule: gradient (backtracked from --lr) or '
                   'gauss_newton (Levenberg-Marquardt; default: --config, else gradient)')
    p.add_argument('--cg-steps', type=int, help='CG iterations per gauss_newton step '
                   '(default: --config, else 30)')
    p.add_argument('--config', default='', help='an experiment configuration whose adapt.<method> '
                   'gives the defaults of --steps, --lr, --gamma and whose learner section those '
                   'of --rule, --cg-steps (e.g. config/pendulum.yaml)')
    p.add_argument('--samples', type=_count, default=0,
                   help='use the first N usable samples (default 0: all)')
    p.add_argument('--holdout', type=_fraction, default=0.2,
                   help='the last share of them held out (default 0.2)')
    p.add_argument('--seed', type=_count, default=0, help="the supervised baseline's initial "
                   'weights (default 0)')
    p.add_argument('--keep-saturated', action='store_true',
                   help='keep samples whose input is at a bound (default: skip them)')
    p.add_argument('--arx-order', type=int, default=2, help='order p of --method arx '
                   '(default 2)')
    p.add_argument('--time-column', help='the CSV\'s time column, s (default: "time" if it has '
                   'one, else one row per dt)')
    return p


def main(args=None) -> int:
    """Run the command; its exit status (0, or 2 for bad input)."""
    opts = parser().parse_args(args)
    config = OfflineConfig(method=opts.method, steps=opts.steps, lr=opts.lr, gamma=opts.gamma,
                           rule=opts.rule, cg_steps=opts.cg_steps,
                           config_file=opts.config, samples=opts.samples,
                           holdout=opts.holdout, seed=opts.seed,
                           keep_saturated=opts.keep_saturated, time_column=opts.time_column,
                           arx_order=opts.arx_order)

    def log(text: str) -> None:
        print(f'adapt_offline: {text}', file=sys.stderr, flush=True)

    try:
        report = run_offline(opts.recording, opts.mapping, opts.checkpoint, opts.out, config,
                             log, progress=sys.stderr.isatty())
    except (OSError, ValueError) as err:
        print(f'adapt_offline: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 2
    print(report_markdown(report), end='')
    return 0


if __name__ == '__main__':
    sys.exit(main())
