"""`ros2 run metampc_bringup adapt_offline`: adaptation from a recording, on the command line.

    ros2 run metampc_bringup adapt_offline RECORDING MAPPING CHECKPOINT --out ADAPTED.pt
        [--method M] [--steps N] [--lr R] [--gamma G] [--rule R] [--cg-steps N] [--config F]
        [--samples N] [--holdout F] [--seed S] [--keep-saturated] [--time-column C] [--arx-order P]

A thin layer over ``metampc_learner.offline_adaptation``, with --config read by the experiment
configuration's reader (:func:`experiment_settings`): it writes ADAPTED.pt, ADAPTED.json and
ADAPTED.md, prints the markdown report, and logs each phase and step on stderr. Bad input (a
wrong mapping, a topic or column missing, a checkpoint that does not fit) is one line on stderr
and exit status 2; a file that does not exist, an --out that exists or whose folder does not,
before torch is imported (:func:`check_paths`). docs/offline_adaptation.md.
"""
import argparse
import importlib
import os
import sys
from typing import Any, List, Optional


class LaterChoices:
    """The choices of an option whose names are declared in a module that imports torch
    ('module:NAME', a tuple or one name): argparse lets every value through, main() checks it
    (:meth:`check`) after the paths, and only a listing (the help) imports the module."""

    def __init__(self, *declared: str) -> None:
        self.declared = declared

    def names(self) -> List[str]:
        out: List[str] = []
        for spec in self.declared:
            module, name = spec.split(':')
            value = getattr(importlib.import_module(module), name)
            out += [value] if isinstance(value, str) else list(value)
        return out

    def __contains__(self, value: Any) -> bool:
        return True

    def __iter__(self) -> Any:
        return iter(self.names())

    def check(self, p: argparse.ArgumentParser, option: str, value: Optional[str]) -> None:
        """argparse's own error (exit 2) unless `value` (None: not given) is one of them."""
        names = self.names()
        if value is not None and value not in names:
            p.error(f"argument {option}: invalid choice: '{value}' (choose from "
                    f"{', '.join(repr(n) for n in names)})")


METHOD_CHOICES = LaterChoices('metampc_learner.meta_train:META_METHODS',
                              'metampc_learner.target_fit:SUPERVISED',
                              'metampc_learner.target_fit:ARX')
RULE_CHOICES = LaterChoices('metampc_learner.adapt:RULES')


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
    p.add_argument('--method', choices=METHOD_CHOICES, metavar='METHOD',
                   help="%(choices)s; default: the checkpoint's; supervised: from random "
                   'weights; arx: the linear ARX baseline by least squares (the checkpoint '
                   'gives H and scaling)')
    p.add_argument('--steps', type=_count, help='adaptation steps (default: --config, else 20)')
    p.add_argument('--lr', type=float, help='step size (default: --config, else 0.05)')
    p.add_argument('--gamma', type=float, help='proximal strength of eq. (infer) (default: '
                   '--config, else 0)')
    p.add_argument('--rule', choices=RULE_CHOICES, metavar='RULE', help='step rule: gradient '
                   '(backtracked from --lr) or gauss_newton (Levenberg-Marquardt; default: '
                   '--config, else gradient)')
    p.add_argument('--cg-steps', type=int, help='CG iterations per gauss_newton step '
                   '(default: --config, else 30)')
    p.add_argument('--config', default='', help='an experiment configuration whose adapt.<method> '
                   'gives the defaults of --steps, --lr, --gamma and whose learner section those '
                   'of --rule, --cg-steps, --arx-order and the gain check, as its learner node '
                   'takes them (e.g. config/pendulum.yaml)')
    p.add_argument('--samples', type=_count, default=0,
                   help='use the first N usable samples (default 0: all)')
    p.add_argument('--holdout', type=_fraction, default=0.2,
                   help='the last share of them held out (default 0.2)')
    p.add_argument('--seed', type=_count, default=0, help="the supervised baseline's initial "
                   'weights (default 0)')
    p.add_argument('--keep-saturated', action='store_true',
                   help='keep samples whose input is at a bound (default: skip them)')
    p.add_argument('--arx-order', type=int, help='order p of --method arx and of the gain '
                   "check's ARX (default: --config, else 2)")
    p.add_argument('--time-column', help='the CSV\'s time column, s (default: "time" if it has '
                   'one, else one row per dt)')
    return p


def check_paths(opts: argparse.Namespace) -> Optional[str]:
    """What is wrong with the paths of the command line, before any work (None: nothing):
    a recording, mapping or checkpoint that does not exist, an --out that exists (results are
    never overwritten) or whose folder does not exist (it was found only when the adapted
    model was written)."""
    for path, what in ((opts.recording, 'recording'), (opts.mapping, 'mapping file'),
                       (opts.checkpoint, 'checkpoint')):
        if not os.path.exists(path):
            return f'{path}: no such {what}'
    if os.path.exists(opts.out):
        return f'--out {opts.out} exists; results are never overwritten'
    folder = os.path.dirname(opts.out) or '.'
    if not os.path.isdir(folder):
        return f'--out {opts.out}: the folder {folder} does not exist'
    return None


def experiment_settings(path: str, seed: int):
    """What the experiment configuration `path` says about adaptation
    (``offline_adaptation.Experiment``), read by its own reader: the learner configuration of
    its run `seed`, its Adapt request fields by method, the learner parameters it sets.

    Raises:
        ConfigError (ValueError): an unreadable or invalid file.
    """
    from metampc_bringup.experiment_config import learner_config, load
    from metampc_learner.learner_params import ADAPT_METHODS
    from metampc_learner.offline_adaptation import Experiment
    experiment = load(path)
    return Experiment(path, learner_config(experiment, seed),
                      {m: experiment.adapt_request(m) for m in ADAPT_METHODS},
                      tuple(experiment.learner))


def main(args=None) -> int:
    """Run the command; its exit status (0, or 2 for bad input)."""
    p = parser()
    opts = p.parse_args(args)
    wrong = check_paths(opts)
    if wrong:
        print(f'adapt_offline: error: {wrong}', file=sys.stderr)
        return 2
    METHOD_CHOICES.check(p, '--method', opts.method)
    RULE_CHOICES.check(p, '--rule', opts.rule)
    from metampc_learner.offline_adaptation import OfflineConfig, report_markdown, run_offline

    def log(text: str) -> None:
        print(f'adapt_offline: {text}', file=sys.stderr, flush=True)

    try:
        experiment = experiment_settings(opts.config, opts.seed) if opts.config else None
        config = OfflineConfig(method=opts.method or '', steps=opts.steps, lr=opts.lr,
                               gamma=opts.gamma, rule=opts.rule, cg_steps=opts.cg_steps,
                               arx_order=opts.arx_order, experiment=experiment,
                               samples=opts.samples, holdout=opts.holdout, seed=opts.seed,
                               keep_saturated=opts.keep_saturated,
                               time_column=opts.time_column)
        report = run_offline(opts.recording, opts.mapping, opts.checkpoint, opts.out, config,
                             log, progress=sys.stderr.isatty())
    except (OSError, ValueError) as err:
        print(f'adapt_offline: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 2
    print(report_markdown(report), end='')
    return 0


if __name__ == '__main__':
    sys.exit(main())
