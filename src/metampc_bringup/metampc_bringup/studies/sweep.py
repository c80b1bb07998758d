"""Where does iMAML win? The inner-steps sweep: held-out target loss, time and memory against M.

Meta-trains iMAML (eq. (inner_imaml), Gauss-Newton curvature, eq. (cg)), first-order MAML and
unrolled MAML (eqs. (inner_maml), (outer_maml); M <= :data:`UNROLLED_MAX_M`) at each inner-step
count M on the learning cores without ROS (:mod:`metampc_bringup.studies.learning_setup`): each
(method, M) tuned on validation data with the same budget (:data:`GRIDS`, :data:`ADAPT_LRS`),
then tested on the experiment's seeds; iMAML and first-order MAML compared paired by seed
(:func:`metampc_bringup.analysis.paired_stats.paired_claim`). Runs: jobs of
:mod:`.study_jobs`, each in a fresh process. Out: ``OUT/`` (report.md, sweep.json, plots;
runs cached in ``OUT/cache/``: a stopped sweep resumes); a folder of a sweep of other settings
is refused (:class:`SweepError`). Cost model: :data:`COST_PER_STEP`, :func:`estimate_cpu_s`.
Protocol, budget and measured costs: docs/sweep.md. No rclpy here.
"""
import hashlib
import json
import math
import os
import resource
import time
from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from metampc_bringup.analysis.paired_stats import claim_cells, median_ci, paired_claim
from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.experiment_config import ExperimentConfig, load
from metampc_bringup.studies.learning_setup import (CURVE_STEPS, Job, request_meta_config,
                                                    run_job, Settings, settings_from,
                                                    TEST_HELDOUT_SAMPLES, validation,
                                                    VALIDATION_SEED)
from metampc_bringup.studies.study_jobs import ResultCache, run_jobs
from metampc_learner.meta_train import META_METHODS

NAMES = {'imaml': 'iMAML', 'maml': 'first-order MAML', 'maml_unrolled': 'unrolled MAML'}
DEFAULT_MS = (1, 5, 10, 25, 50)
UNROLLED_MAX_M = 10
# Per (method, M) the same number of configurations, around the tuned values (iMAML lr_inner
# 0.1, gamma 1, and the earlier 0.05, 3; MAML lr_inner 0.02); lr_outer etc. from the
# experiment.
_MAML_GRID = tuple({'lr_inner': a} for a in (0.01, 0.02, 0.05, 0.1))
GRIDS: Dict[str, Tuple[Dict[str, float], ...]] = {
    'imaml': tuple({'lr_inner': a, 'gamma': g} for a in (0.05, 0.1) for g in (1.0, 3.0)),
    'maml': _MAML_GRID, 'maml_unrolled': _MAML_GRID}
SWEPT = ('iterations', 'inner_steps', 'lr_inner', 'gamma')
ADAPT_LRS = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5)
# CPU s per outer step = a + b M (B = 16, default NSSM, 1 thread; docs/sweep.md).
COST_PER_STEP = {'imaml': (0.145, 0.0225), 'maml': (0.02, 0.024),
                 'maml_unrolled': (0.02, 0.048)}
JOB_START_S = 6.0    # CPU s: spawn a worker, import torch, simulate the data
ADAPT_S = 0.5        # CPU s: one target and step size, 20 adaptation steps
N_BOOT = 10000
BOOT_SEED = 0
PAIRS = (('imaml', 'maml'), ('maml', 'maml_unrolled'))
REPORT_K = (0, 20)   # adaptation steps shown in the figure and the paired comparison


class SweepError(ValueError):
    """Arguments the sweep cannot run with; the message says which and why."""


@dataclass(frozen=True)
class Plan:
    """What to sweep.

    Attributes:
        methods: out of :data:`META_METHODS`.
        ms: inner steps M (unrolled MAML takes those <= UNROLLED_MAX_M).
        seeds: test seeds (the experiment's: source set, meta seed and theta* of seed s).
        iterations: outer steps of the test runs.
        tune_iterations: outer steps of the tuning runs.
        thetas: validation targets of the tuning.
        adapt_steps: adaptation steps (the held-out loss is reported after CURVE_STEPS).
        heldout_samples: held-out samples of each test target.
    """

    methods: Tuple[str, ...] = META_METHODS
    ms: Tuple[int, ...] = DEFAULT_MS
    seeds: Tuple[int, ...] = (0, 1, 2, 3, 4)
    iterations: int = 300
    tune_iterations: int = 100
    thetas: int = 4
    adapt_steps: int = 20
    heldout_samples: int = TEST_HELDOUT_SAMPLES

    def check(self) -> 'Plan':
        """Raise SweepError naming the first bad field; return self."""
        bad = [m for m in self.methods if m not in META_METHODS]
        if bad or not self.methods:
            raise SweepError(f'unknown method {", ".join(bad) or "(none)"}; expected some of '
                             f'{", ".join(META_METHODS)}')
        if not self.ms or any(m < 1 for m in self.ms):
            raise SweepError(f'every M must be >= 1, got {list(self.ms)}')
        if not self.seeds or any(not 0 <= s < VALIDATION_SEED for s in self.seeds):
            raise SweepError(f'test seeds must lie in [0, {VALIDATION_SEED}) (validation '
                             f'source sets from {VALIDATION_SEED}), got {list(self.seeds)}')
        for name in ('iterations', 'tune_iterations', 'thetas', 'adapt_steps',
                     'heldout_samples'):
            if getattr(self, name) < 1:
                raise SweepError(f'{name} must be >= 1, got {getattr(self, name)}')
        if not self.cells():
            raise SweepError(f'no (method, M) to run: unrolled MAML only up to M = '
                             f'{UNROLLED_MAX_M}')
        return self

    def cells(self) -> List[Tuple[str, int]]:
        """(method, M) pairs of the sweep, in order."""
        return [(method, m) for method in self.methods for m in sorted(set(self.ms))
                if method != 'maml_unrolled' or m <= UNROLLED_MAX_M]


def base_hyper(experiment: ExperimentConfig, method: str) -> Dict[str, Any]:
    """The experiment's request fields of `method` the sweep keeps fixed (lr_outer, batch
    size, CG steps); unrolled MAML, which has no tuned request, takes first-order MAML's."""
    fields = request_meta_config(experiment, method)
    if method == 'maml_unrolled' and not fields:
        fields = request_meta_config(experiment, 'maml')
    return {k: v for k, v in fields.items() if k not in SWEPT}


def tune_jobs(experiment: ExperimentConfig, plan: Plan) -> List[Job]:
    """Every configuration of :data:`GRIDS` at every (method, M), on validation data."""
    return [Job(method, i, {**base_hyper(experiment, method), 'inner_steps': m, **config},
                plan.tune_iterations, ADAPT_LRS, 'tune')
            for method, m in plan.cells() for i, config in enumerate(GRIDS[method])]


def _cell(run: dict) -> Tuple[str, int]:
    return run['method'], int(run['hyper']['inner_steps'])


def winners(tune_runs: Sequence[dict]) -> Dict[Tuple[str, int], dict]:
    """Per (method, M): the tuning run with the lowest finite score (none: every one failed)."""
    out: Dict[Tuple[str, int], dict] = {}
    for run in tune_runs:
        best = out.get(_cell(run))
        if math.isfinite(run['score']) and (best is None or run['score'] < best['score']):
            out[_cell(run)] = run
    return out


def evaluation_jobs(experiment: ExperimentConfig, plan: Plan,
                    best: Dict[Tuple[str, int], dict]) -> List[Job]:
    """The winner of every (method, M) on every test seed's source set and target."""
    return [Job(method, w['index'], w['hyper'], plan.iterations, (w['best_lr'],), 'test', s,
                target_theta=experiment.target_theta(s), heldout_samples=plan.heldout_samples)
            for (method, _), w in best.items() for s in plan.seeds]


def estimate_cpu_s(plan: Plan) -> Dict[str, float]:
    """CPU seconds of the plan at the default NSSM and B = 16 (docs/sweep.md, Budget)."""
    tune = test = 0.0
    for method, m in plan.cells():
        a, b = COST_PER_STEP[method]
        n = len(GRIDS[method])
        tune += n * (plan.tune_iterations * (a + b * m) + JOB_START_S
                     + plan.thetas * len(ADAPT_LRS) * ADAPT_S * plan.adapt_steps / 20)
        test += len(plan.seeds) * (plan.iterations * (a + b * m) + JOB_START_S
                                   + 2 * ADAPT_S * plan.adapt_steps / 20)
    return {'tune': round(tune), 'test': round(test), 'total': round(tune + test)}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0    # Linux: KiB


def measured_run(job: Job) -> dict:
    """:func:`learning_setup.run_job` with its cost: peak RSS of the process (MB) before and after
    meta-training and adaptation, wall time per outer step (s) and of the whole job (s)."""
    start = time.monotonic()
    validation(job.source_seed, job.nssm, job.target_theta, job.heldout_samples)
    before = _peak_rss_mb()
    out = run_job(job)
    out.update(rss_before_meta_mb=round(before, 1), peak_rss_mb=round(_peak_rss_mb(), 1),
               job_wall_s=round(time.monotonic() - start, 1))
    if 'meta_seconds' in out:
        out['s_per_step'] = out['meta_seconds'] / job.iterations
    return out


def heldout_at(run: dict, k: int) -> float:
    """Held-out loss of a test run after k adaptation steps (inf: the run failed)."""
    adapt = run.get('adapt') or []
    return float(adapt[0]['heldout_at'][str(k)][0]) if adapt else math.inf


def summarise(plan: Plan, best: Dict[Tuple[str, int], dict], test_runs: Sequence[dict]
              ) -> List[dict]:
    """Per (method, M): the winner, the held-out loss per seed and its median [95 % CI] after
    each K, the median wall time per outer step (s), meta-training time (s) and peak RSS
    (MB) of the test runs."""
    out = []
    ks = [k for k in CURVE_STEPS if k <= plan.adapt_steps]
    for method, m in plan.cells():
        w = best.get((method, m))
        runs = sorted((r for r in test_runs if _cell(r) == (method, m)),
                      key=lambda r: r['source_seed'])
        row: Dict[str, Any] = {'method': method, 'M': m, 'winner': None,
                               'seeds': [r['source_seed'] for r in runs],
                               'failed': sum(not math.isfinite(heldout_at(r, ks[-1]))
                                             for r in runs)}
        if w is not None:
            row['winner'] = {'index': w['index'], 'hyper': w['hyper'], 'best_lr': w['best_lr'],
                             'tune_score': w['score']}
        row['heldout'] = {}
        for k in ks:
            values = [heldout_at(r, k) for r in runs]
            median, low, high = median_ci(values)
            row['heldout'][str(k)] = {'values': values, 'median': median, 'ci_low': low,
                                      'ci_high': high}
        ok = [r for r in runs if 's_per_step' in r]
        row.update({
            's_per_step': _median([r['s_per_step'] for r in ok]),
            'meta_seconds': _median([r['meta_seconds'] for r in ok]),
            'peak_rss_mb': _median([r['peak_rss_mb'] for r in runs]),
            'peak_rss_mb_max': max((r['peak_rss_mb'] for r in runs), default=math.nan),
            'rss_before_meta_mb': _median([r['rss_before_meta_mb'] for r in runs])})
        out.append(row)
    return out


def _median(values: Sequence[float]) -> float:
    return float(np.median(values)) if len(values) else math.nan


def paired(plan: Plan, summary: Sequence[dict]) -> List[dict]:
    """Per pair of :data:`PAIRS`, M and K of REPORT_K: the claim "a's held-out loss < b's"
    over the seeds both have (paired_claim on the logs: ratio a/b)."""
    cells = {(row['method'], row['M']): row for row in summary}
    out = []
    for a, b in PAIRS:
        for m in sorted(set(plan.ms)):
            if (a, m) not in cells or (b, m) not in cells:
                continue
            ra, rb = cells[(a, m)], cells[(b, m)]
            seeds = sorted(set(ra['seeds']) & set(rb['seeds']))
            for k in REPORT_K:
                if str(k) not in ra['heldout'] or not seeds:
                    continue
                va, vb = ([row['heldout'][str(k)]['values'][row['seeds'].index(s)]
                           for s in seeds] for row in (ra, rb))
                out.append({'a': a, 'b': b, 'M': m, 'K': k, 'seeds': seeds,
                            **paired_claim(va, vb, N_BOOT, BOOT_SEED, log=True)})
    return out


def plain_words(c: dict) -> str:
    """One sentence of a paired comparison."""
    holds, estimate, p, verdict = claim_cells(c)
    return (f"M = {c['M']}, K = {c['K']}: {NAMES[c['a']]} lower on {holds} seeds; median "
            f"ratio {NAMES[c['a']]} / {NAMES[c['b']]} {estimate}; Wilcoxon p = {p}; "
            f"\"{NAMES[c['a']]} < {NAMES[c['b']]}\" {verdict}.")


def _offsets(methods: Sequence[str]) -> Dict[str, float]:
    """Multiplicative x shifts so that the methods' bars at one M do not overlap."""
    return {m: 1.08 ** (i - (len(methods) - 1) / 2) for i, m in enumerate(methods)}


def plot_loss(summary: Sequence[dict], path: str) -> str:
    """Held-out loss after K = 0 and K = 20 steps against M, per method: median over the
    seeds with its bootstrap 95 % interval, log-log."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    methods = list(dict.fromkeys(row['method'] for row in summary))
    shift = _offsets(methods)
    ks = [k for k in REPORT_K if all(str(k) in row['heldout'] for row in summary)]
    fig, axes = plt.subplots(1, len(ks), figsize=(5.5 * len(ks), 4.2), squeeze=False)
    for ax, k in zip(axes[0], ks):
        drawn = []
        for method in methods:
            rows = [r for r in summary if r['method'] == method
                    and math.isfinite(r['heldout'][str(k)]['median'])]
            if not rows:
                continue
            x = np.array([r['M'] * shift[method] for r in rows])
            stats = [r['heldout'][str(k)] for r in rows]
            y = np.array([s['median'] for s in stats])
            # A missing or infinite endpoint draws no bar on that side.
            low = np.array([s['median'] - s['ci_low'] if _finite(s['ci_low']) else 0.0
                            for s in stats])
            high = np.array([s['ci_high'] - s['median'] if _finite(s['ci_high']) else 0.0
                             for s in stats])
            ax.errorbar(x, y, yerr=[low, high], marker='o', capsize=3, label=NAMES[method])
            drawn += list(y)
        _m_axis(ax, [row['M'] for row in summary])
        _log_y_if_positive(ax, drawn)
        ax.set_ylabel('held-out target loss (normalised)')
        ax.set_title(f'after K = {k} adaptation steps (median, 95 % CI)')
    return _save(fig, path)


def plot_memory(summary: Sequence[dict], path: str) -> str:
    """Peak RSS (MB; dashed: RSS before meta-training) and wall time per outer step (s)
    against M, per method, medians over the test runs."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (mem, sec) = plt.subplots(1, 2, figsize=(11, 4.2))
    for method in dict.fromkeys(row['method'] for row in summary):
        rows = [r for r in summary if r['method'] == method]
        ms = [r['M'] for r in rows]
        line, = mem.plot(ms, [r['peak_rss_mb'] for r in rows], marker='o', label=NAMES[method])
        mem.plot(ms, [r['rss_before_meta_mb'] for r in rows], ls='--', color=line.get_color())
        sec.plot(ms, [r['s_per_step'] for r in rows], marker='o', label=NAMES[method])
    mem.set_ylabel('peak RSS of the run, MB')
    mem.set_title('peak RSS (dashed: before meta-training)')
    sec.set_ylabel('s per outer step')
    sec.set_title('meta-training wall time per outer step')
    for ax in (mem, sec):
        _m_axis(ax, [row['M'] for row in summary])
    _log_y_if_positive(sec, [r['s_per_step'] for r in summary])
    return _save(fig, path)


def _log_y_if_positive(ax, values: Sequence[float]) -> None:
    """A log y axis where every finite value drawn (the points, not their bars) is positive,
    else linear: a time per step rounded to 0 (meta_seconds has 0.1 s resolution) has no
    place on a log axis."""
    finite = [v for v in values if math.isfinite(v)]
    if finite and min(finite) > 0:
        ax.set_yscale('log')


def _m_axis(ax, ms: Sequence[int]) -> None:
    """Log-scaled x axis of M with a labelled tick at each M swept, grid and legend."""
    ax.set_xscale('log')
    ticks = sorted(set(ms))
    ax.set_xticks(ticks, [str(m) for m in ticks])
    ax.minorticks_off()
    ax.set_xlabel('inner steps M')
    ax.grid(True, alpha=0.3)
    ax.legend()


def _save(fig, path: str) -> str:
    import matplotlib.pyplot as plt
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _finite(x: Optional[float]) -> bool:
    return x is not None and math.isfinite(x)


def _g(x: Optional[float], digits: int = 3) -> str:
    return 'n/a' if x is None or (isinstance(x, float) and math.isnan(x)) else f'{x:.{digits}g}'


def _ci(stats: Dict[str, Any]) -> str:
    return f"{_g(stats['median'])} [{_g(stats['ci_low'])}, {_g(stats['ci_high'])}]"


def markdown(report: Dict[str, Any]) -> str:
    """OUT/report.md of a sweep report (before JSON-safe conversion)."""
    p = report['protocol']
    ks = [k for k in CURVE_STEPS if k <= p['adapt_steps']]
    lines = [
        '# Where does iMAML win? Inner steps M against held-out loss, time and memory', '',
        f"Methods {', '.join(p['methods'])}; M in {p['ms']} (unrolled MAML up to M = "
        f"{UNROLLED_MAX_M}); test seeds {p['seeds']}; config `{p['config']}`.", '',
        f"- Tuning per (method, M): {p['configurations_per_cell']} configurations x "
        f"{p['tune_iterations']} outer steps on validation source set {VALIDATION_SEED}, "
        f"{p['thetas']} validation targets, adaptation step sizes {p['adapt_lrs']}; "
        'score: mean held-out loss after the last adaptation step at the best step size.',
        f"- Test per (method, M) winner: {p['iterations']} outer steps on source set s, "
        f"adaptation ({p['adapt_steps']} steps, the winner's step size) on theta*(s), "
        f"held-out loss on {p['heldout_samples']} samples of theta*(s).",
        f"- Budget: estimated {report['estimate_cpu_s']['total']} CPU s; the runs took "
        f"{report['cpu_s']:.0f} CPU s, sessions {report['wall_s']:.0f} s wall "
        f"({len(report['sessions'])} session(s), {report['sessions'][-1]['jobs']} jobs x "
        f"{report['sessions'][-1]['threads']} thread(s)).", '',
        '## Held-out target loss (median over seeds [bootstrap 95 % CI], normalised units)', '',
        '| method | M | winner (tuning score, adapt lr) | '
        + ' | '.join(f'K = {k}' for k in ks) + ' | failed |',
        '|---|---|---|' + '---|' * len(ks) + '---|']
    for row in report['summary']:
        w = row['winner']
        winner = ('all configurations failed' if w is None else
                  ', '.join(f'{k} {v}' for k, v in w['hyper'].items()
                            if k in ('lr_inner', 'gamma'))
                  + f" ({_g(w['tune_score'])}, {w['best_lr']})")
        lines.append(f"| {NAMES[row['method']]} | {row['M']} | {winner} | "
                     + ' | '.join(_ci(row['heldout'][str(k)]) for k in ks)
                     + f" | {row['failed']}/{len(row['seeds'])} |")
    lines += ['', '## Cost (medians over the test runs, fresh process per run)', '',
              '| method | M | s / outer step | meta-training s | peak RSS MB (max) | '
              'RSS before meta-training MB |', '|---|---|---|---|---|---|']
    lines += [f"| {NAMES[r['method']]} | {r['M']} | {_g(r['s_per_step'])} | "
              f"{_g(r['meta_seconds'])} | {_g(r['peak_rss_mb'], 4)} "
              f"({_g(r['peak_rss_mb_max'], 4)}) | {_g(r['rss_before_meta_mb'], 4)} |"
              for r in report['summary']]
    lines += ['', '## Paired by seed (held-out loss; median ratio a / b over the seeds, '
              'bootstrap 95 % CI)', '']
    lines += [f'- {plain_words(c)}' for c in report['paired']] or ['- (no pairs)']
    lines += ['', '![held-out loss against M](loss_vs_M.png)', '',
              '![memory and time against M](memory_vs_M.png)', '']
    return '\n'.join(lines)


def protocol(config: str, settings: Settings, experiment: ExperimentConfig, plan: Plan
             ) -> Dict[str, Any]:
    """What fixes the sweep's results (a folder holds one): plan, grids, fixed fields, and a
    hash of the settings (the experiment's learner set-up)."""
    return json.loads(json.dumps({
        'config': config, **asdict(plan), 'configurations_per_cell': len(GRIDS['imaml']),
        'grids': GRIDS, 'adapt_lrs': ADAPT_LRS,
        'fixed': {m: base_hyper(experiment, m) for m in plan.methods},
        'settings_sha': hashlib.sha256(repr(settings).encode()).hexdigest()[:16]}))


def sweep(client, config: str, plan: Plan, out: str, jobs: int = 1,
          threads: int = 1) -> Dict[str, Any]:
    """Run (or resume) the sweep on `client`'s cluster (`jobs` at once, `threads` torch
    threads each, every run in a fresh process: its peak RSS is its own), write
    OUT/sweep.json, report.md and the figures; return the report.

    Raises:
        SweepError: OUT/sweep.json holds a sweep with another protocol.
        StudyError, SchedulerLost: runs raised, the scheduler was lost (the finished runs are
            cached).
    """
    start, load_start = time.monotonic(), os.getloadavg()
    started = time.strftime('%Y-%m-%dT%H:%M:%S', time.localtime())
    experiment, settings = load(config), settings_for(config, plan)
    proto = protocol(config, settings, experiment, plan)
    report_path = os.path.join(out, 'sweep.json')
    check_out(out, proto)
    cache = ResultCache(os.path.join(out, 'cache'), settings)
    cached_before = len(os.listdir(cache.folder))
    tune_runs = run_jobs(client, tune_jobs(experiment, plan), 'tune', settings, cache,
                         measured_run, threads, fresh=True)
    best = winners(tune_runs)
    test_runs = run_jobs(client, evaluation_jobs(experiment, plan, best), 'test', settings,
                         cache, measured_run, threads, fresh=True)
    session = {'started': started, 'wall_s': round(time.monotonic() - start, 1),
               'jobs': jobs, 'threads': threads,
               'runs_done': len(os.listdir(cache.folder)) - cached_before,
               'load_avg_start': [round(v, 2) for v in load_start],
               'load_avg_end': [round(v, 2) for v in os.getloadavg()]}
    with open(os.path.join(out, 'sessions.jsonl'), 'a') as f:
        f.write(json.dumps(session) + '\n')
    with open(os.path.join(out, 'sessions.jsonl')) as f:
        sessions = [json.loads(line) for line in f if line.strip()]
    summary = summarise(plan, best, test_runs)
    report = {
        'protocol': proto, 'estimate_cpu_s': estimate_cpu_s(plan),
        'validation_thetas': list(settings.thetas),
        'test_thetas': {str(s): experiment.target_theta(s) for s in plan.seeds},
        'winners': [{'method': row['method'], 'M': row['M'], 'winner': row['winner']}
                    for row in summary],
        'summary': summary, 'paired': paired(plan, summary),
        'cpu_s': sum(r['cpu_seconds'] for r in tune_runs + test_runs),
        'wall_s': sum(s['wall_s'] for s in sessions), 'sessions': sessions,
        'tune_runs': tune_runs, 'test_runs': test_runs}
    with open(report_path + '.tmp', 'w') as f:
        json.dump(json_safe(report), f, indent=1)
    os.replace(report_path + '.tmp', report_path)
    plot_loss(summary, os.path.join(out, 'loss_vs_M.png'))
    plot_memory(summary, os.path.join(out, 'memory_vs_M.png'))
    with open(os.path.join(out, 'report.md'), 'w') as f:
        f.write(markdown(report))
    return report


def settings_for(config: str, plan: Plan) -> Settings:
    """The settings of the sweep without ROS: the experiment's learner set-up, `plan.thetas`
    validation targets, `plan.adapt_steps` adaptation steps."""
    return settings_from(config, plan.thetas, plan.adapt_steps)


def check_out(out: str, proto: Dict[str, Any]) -> None:
    """Raise SweepError if `out` is a file or holds the report of a sweep with another
    protocol (a finished sweep is resumed, never overwritten by another)."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise SweepError(f'--out {out} exists and is not a folder')
    path = os.path.join(out, 'sweep.json')
    if os.path.exists(path):
        with open(path) as f:
            old = json.load(f).get('protocol')
        if old != proto:
            diff = sorted(k for k in set(old or {}) | set(proto)
                          if (old or {}).get(k) != proto.get(k))
            raise SweepError(f'{out} holds a sweep with other settings ({", ".join(diff)}); '
                             'pick another --out')
    os.makedirs(out, exist_ok=True)


def summary_line(report: Dict[str, Any], out: str) -> Dict[str, Any]:
    """The one JSON line of the script: per (method, M) the median held-out loss at K = 0 and
    20, s per outer step and peak RSS; the paired verdicts; where the report is."""
    return json_safe({
        'out': out, 'cells': len(report['summary']),
        'runs': len(report['tune_runs']) + len(report['test_runs']),
        'runs_done_now': report['sessions'][-1]['runs_done'],
        'wall_s': report['wall_s'], 'cpu_s': round(report['cpu_s'], 1),
        'estimate_cpu_s': report['estimate_cpu_s']['total'],
        'summary': {f"{r['method']}/M{r['M']}": {
            **{f'K{k}': r['heldout'][str(k)]['median'] for k in REPORT_K
               if str(k) in r['heldout']},
            's_per_step': r['s_per_step'], 'peak_rss_mb': r['peak_rss_mb']}
            for r in report['summary']},
        'paired': [_short(c) for c in report['paired']]})


def _short(c: dict) -> str:
    holds, estimate, p, verdict = claim_cells(c)
    return f"{c['a']} < {c['b']} M{c['M']} K{c['K']}: {holds}, ratio {estimate}, p {p}, {verdict}"


def check(config: str, plan: Plan, out: str) -> None:
    """Before the cluster starts: SweepError for a bad plan or an `out` of another sweep
    (:func:`check_out`, which creates `out`)."""
    plan.check()
    check_out(out, protocol(config, settings_for(config, plan), load(config), plan))


__all__ = ['DEFAULT_MS', 'UNROLLED_MAX_M', 'GRIDS', 'ADAPT_LRS', 'COST_PER_STEP',
           'SweepError', 'Plan', 'base_hyper', 'tune_jobs', 'winners', 'evaluation_jobs',
           'estimate_cpu_s', 'measured_run', 'heldout_at', 'summarise', 'paired',
           'plain_words', 'plot_loss', 'plot_memory', 'markdown', 'protocol', 'sweep',
           'settings_for', 'check_out', 'summary_line', 'check']
