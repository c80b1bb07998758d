"""A fair hyperparameter search for iMAML, first-order MAML and supervised training.

The logic of ``scripts/tune.py``: every method gets the same budget of meta-trainings, spent
on validation systems only (source set 1000.., validation thetas from rng([1000 + i, 0x5a1]),
never the experiment's test targets); each model is adapted by eq. (infer) with every step size
of :data:`ADAPT_LRS` and scored by closed-loop tracking against the true-model NMPC ('control')
or by held-out loss ('prediction'); stages 1-2 are an Optuna study per meta method
(:mod:`.search`; the median pruner, :mod:`.pruning`), stage 3 re-runs the finalists and the
incumbent on ``robust_seeds`` source sets. Seeded jobs run on the cluster layer
(:mod:`.study_jobs`); results and studies stay in the search's folder (or a shared
``storage``), so a stopped search resumes. :func:`tune` returns the report (docs/tuning.md).
"""
import hashlib
import itertools
import json
import math
import os
import time
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.experiment_config import load
from metampc_bringup.orchestration.cluster import slots
from metampc_bringup.studies.learning_setup import (HELDOUT_SAMPLES, Job, settings_from,
                                                    THETA_STREAM, VALIDATION_SEED)
from metampc_bringup.studies.pruning import MedianRule
from metampc_bringup.studies.search import Search, Trial, without_password
from metampc_bringup.studies.study_jobs import ResultCache, run_jobs
from metampc_learner.meta_train import MetaConfig

DRAW_STREAM = 0xd7a          # configuration draws: rng([--seed, DRAW_STREAM])
CURVATURE = 'gauss_newton'
CALIBRATION = {n: getattr(MetaConfig(), n) for n in ('inner_steps', 'lr_inner', 'lr_outer',
                                                     'gamma')}   # the learner's defaults
SHARED_GRID = {'inner_steps': (5, 10, 20), 'lr_inner': (0.02, 0.05, 0.1, 0.2),
               'lr_outer': (1e-3, 2e-3, 5e-3, 1e-2)}
GAMMA_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
# CG steps per gamma: the system I + G/gamma (eq. implicit_grad) has condition number up to
# 1 + lambda_max(G)/gamma, and CG needs about its square root in steps: more for small gamma
# (the final relative residual of every run is in its result, ``meta_cg_residual``).
CG_STEPS = {0.01: 20, 0.03: 20, 0.1: 10, 0.3: 10, 1.0: 5, 3.0: 5}
AXES = {'imaml': {**SHARED_GRID, 'gamma': GAMMA_GRID}, 'maml': SHARED_GRID}
ADAPT_LRS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
TUNED_METHODS = ('imaml', 'maml')
INCUMBENT = -1               # index of the configuration in use in stage 3
STUDY_FILE = 'study.journal'     # the Optuna studies' default storage in the search's folder
SEARCH = ('stage 1: the k paired draws, enqueued; stage 2: refine trials of the Optuna TPE '
          'sampler (start-up: stage 1), per_round asked at once per method, seeded per '
          'trial from draw_seed; one Optuna study per meta method in study')
PRUNERS = {
    'median': "Optuna's MedianPruner (5 start-up trials, warm-up a third of the iterations) "
              'on the meta-training loss (mean of every 10 outer steps), the same for every '
              'meta method; thresholds from the trials told before a trial was asked '
              '(metampc_bringup.studies.pruning)',
    'none': 'no pruning: every trial meta-trains all its iterations'}


def draw_jobs(k: int, iterations: int, seed: int) -> List[Job]:
    """K paired meta configurations per meta method (0: calibration) and supervised."""
    rng = np.random.default_rng([seed, DRAW_STREAM])
    names = tuple(SHARED_GRID)
    calibration = tuple(CALIBRATION[n] for n in names)
    grid = [c for c in itertools.product(*SHARED_GRID.values()) if c != calibration]
    if k - 1 > len(grid):
        raise ValueError(f'k = {k} exceeds the grid ({len(grid) + 1} configurations)')
    picks = [calibration] + [grid[i] for i in rng.choice(len(grid), size=k - 1, replace=False)]
    gammas = [CALIBRATION['gamma']] + [float(g) for g in
                                       rng.permutation(np.resize(GAMMA_GRID, k - 1))]
    jobs = []
    for i, (pick, gamma) in enumerate(zip(picks, gammas)):
        shared = {n: (int(v) if n == 'inner_steps' else float(v)) for n, v in zip(names, pick)}
        jobs.append(Job('imaml', i, with_cg('imaml', {**shared, 'gamma': gamma}), iterations,
                        ADAPT_LRS, 'search'))
        jobs.append(Job('maml', i, shared, iterations, ADAPT_LRS, 'search'))
    jobs.append(Job('supervised', 0, {}, 0, ADAPT_LRS, 'search'))
    return jobs


def with_cg(method: str, hyper: Dict[str, float]) -> Dict[str, float]:
    """iMAML's configuration with the CG steps its gamma needs (:data:`CG_STEPS`)."""
    return {**hyper, 'cg_steps': CG_STEPS[hyper['gamma']]} if method == 'imaml' else hyper


def robust_jobs(results: Sequence[dict], finalists: int, iterations: int,
                seeds: Sequence[int], incumbents: Optional[Dict[str, dict]] = None
                ) -> List[Job]:
    """Stage 3: the `finalists` best configurations of each meta method, and its incumbent
    (index -1; skipped when it is one of them), on every seed."""
    jobs = []
    for method in TUNED_METHODS:
        ranked = sorted((r for r in results if r['method'] == method and
                         math.isfinite(r['score'])), key=lambda r: r['score'])
        picked = [(r['index'], r['hyper']) for r in ranked[:finalists]]
        incumbent = (incumbents or {}).get(method)
        if incumbent is not None and incumbent not in [h for _, h in picked]:
            picked.append((INCUMBENT, incumbent))
        jobs.extend(Job(method, index, hyper, iterations, ADAPT_LRS, 'robust', seed)
                    for index, hyper in picked for seed in seeds)
    return jobs


def incumbents(path: str) -> Dict[str, dict]:
    """The configurations in use: each meta method's request fields in the experiment
    YAML at `path`, as search configurations: the searched fields and iMAML's CG steps as the
    request has them (a method whose request lacks a searched field has none)."""
    requests = load(path).meta_train
    out = {}
    for method in TUNED_METHODS:
        fields = requests.get(method) or {}
        if all(n in fields for n in AXES[method]):
            out[method] = {n: fields[n] for n in (*AXES[method], 'cg_steps') if n in fields}
    return out


def robust_scores(runs: Sequence[dict]) -> List[dict]:
    """Per finalist: mean over source seeds of each step size's score; the best step size."""
    groups: Dict[Tuple[str, int], List[dict]] = {}
    for run in runs:
        groups.setdefault((run['method'], run['index']), []).append(run)
    out = []
    for (method, index), group in groups.items():
        by_lr = {}
        for run in group:
            for a in run['adapt'] or [{'lr': lr, 'score': math.inf} for lr in ADAPT_LRS]:
                by_lr.setdefault(a['lr'], []).append(a['score'])
        lr = min(by_lr, key=lambda x: np.mean(by_lr[x]))
        out.append({'method': method, 'index': index, 'hyper': group[0]['hyper'],
                    'best_lr': lr, 'score': float(np.mean(by_lr[lr])),
                    'source_seeds': [r['source_seed'] for r in group],
                    'score_per_seed': by_lr[lr],
                    'meta_final_loss_per_seed': [r.get('meta_final_loss', math.inf)
                                                 for r in group]})
    return out


def best_of(method: str, results: Sequence[dict]) -> dict:
    """The result of the method's configuration with the lowest score."""
    return min((r for r in results if r['method'] == method), key=lambda r: r['score'])


def request_fields(best: dict, full_iterations: int, batch_size: int, adapt_steps: int
                   ) -> dict:
    """A winner as the experiment's meta_train / adapt request fields (config/default.yaml)."""
    out = {'index': best['index'], 'score': best['score'],
           'adapt': {'steps': adapt_steps, 'lr': best['best_lr']}}
    if best['method'] != 'supervised':
        out['meta_train'] = {'iterations': full_iterations, 'batch_size': batch_size,
                             **best['hyper']}
    return out


SCORES = {
    'control': 'geometric mean over the validation thetas of the closed-loop tracking cost / '
               'true-model NMPC of the adapted model (the experiment\'s controller and '
               'reference, in one process; an escape is inf), best adaptation step size per '
               'configuration; the held-out loss is kept as prediction_score',
    'prediction': 'mean over validation thetas of held-out l_SSM after adapt_steps steps '
                  '(normalised units), best adaptation step size per configuration'}


@dataclass
class TuneConfig:
    """The search's budget and set-up (the flags of ``scripts/tune.py``)."""

    config: str = 'config/default.yaml'
    k: int = 8
    refine: int = 4
    iterations: int = 150
    full_iterations: int = 300
    finalists: int = 3
    robust_seeds: int = 5
    batch_size: int = 16
    adapt_steps: int = 20
    thetas: int = 6
    seed: int = 0
    threads: int = 1
    score: str = 'control'
    per_round: int = 2
    pruner: str = 'median'

    def rule(self) -> Optional[MedianRule]:
        """The pruning rule of the search's trials (None: --pruner none)."""
        return (MedianRule(self.iterations, warmup_steps=self.iterations // 3)
                if self.pruner == 'median' else None)

    def validate(self) -> None:
        """ValueError naming the first setting out of range."""
        for name in ('k', 'iterations', 'full_iterations', 'batch_size', 'thetas', 'threads',
                     'per_round'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
        for name in ('refine', 'finalists', 'robust_seeds', 'adapt_steps', 'seed'):
            if getattr(self, name) < 0:
                raise ValueError(f'{name} must be >= 0, got {getattr(self, name)}')
        if self.score not in SCORES:
            raise ValueError(f'score must be one of {", ".join(SCORES)}, got {self.score!r}')
        if self.pruner not in PRUNERS:
            raise ValueError(f'pruner must be one of {", ".join(PRUNERS)}, got '
                             f'{self.pruner!r}')
        if self.finalists and not self.robust_seeds:
            raise ValueError('robust_seeds must be >= 1 when finalists > 0')
        grid = math.prod(len(axis) for axis in SHARED_GRID.values())
        if self.k + self.refine > grid:
            raise ValueError(f'k + refine = {self.k + self.refine} exceeds the grid '
                             f'({grid} configurations)')


def study_folder(out: str) -> str:
    """Where the search of the report `out` keeps its studies and results: ``runs/t.json``
    -> ``runs/t.study``."""
    return os.path.splitext(out)[0] + '.study'


def check_folder(folder: str, cfg: TuneConfig) -> str:
    """ValueError if `folder` holds a search of another configuration or experiment (it is
    resumed only by the same command); else it is created, with the search's fingerprint.
    Returns the search's id (12 hex digits of the fingerprint's sha256): its studies' tag in
    a storage shared by several searches."""
    with open(cfg.config, 'rb') as f:
        mine = {**asdict(cfg), 'config_sha256': hashlib.sha256(f.read()).hexdigest()}
    path = os.path.join(folder, 'search.json')
    if os.path.exists(path):
        with open(path) as f:
            theirs = json.load(f)
        if theirs != mine:
            diff = sorted(k for k in set(theirs) | set(mine) if theirs.get(k) != mine.get(k))
            raise ValueError(f'{folder} holds a search with other settings ({", ".join(diff)})'
                             '; pick another --out')
    else:
        os.makedirs(folder, exist_ok=True)
        with open(path, 'w') as f:
            json.dump(mine, f, indent=1)
    return hashlib.sha256(json.dumps(mine, sort_keys=True).encode()).hexdigest()[:12]


def searched(job: Job) -> Dict[str, float]:
    """A search job's configuration as its study's parameters (iMAML's CG steps follow from
    gamma)."""
    return {n: job.hyper[n] for n in AXES[job.method]}


def tune(cfg: TuneConfig, client, folder: str, progress: bool = True,
         storage: Optional[str] = None) -> dict:
    """Run (or resume) the three stages on `client`'s cluster, the results kept in `folder`
    (:func:`check_folder` first), the studies in `storage` (an Optuna database URL or a
    journal file; default the journal :data:`STUDY_FILE` in `folder`); the report
    (JSON-safe)."""
    cfg.validate()
    tag = check_folder(folder, cfg)
    storage = storage or os.path.join(folder, STUDY_FILE)
    start, load_start = time.monotonic(), os.getloadavg()
    settings = settings_from(cfg.config, cfg.thetas, cfg.adapt_steps,
                             {'batch_size': cfg.batch_size, 'curvature': CURVATURE},
                             control=cfg.score == 'control')
    cache = ResultCache(os.path.join(folder, 'cache'), settings)
    drawn = draw_jobs(cfg.k, cfg.iterations, cfg.seed)
    search = Search(storage, {m: AXES[m] for m in TUNED_METHODS},
                    {m: [searched(j) for j in drawn if j.method == m] for m in TUNED_METHODS},
                    cfg.refine, cfg.per_round, cfg.seed, cfg.rule(), tag)

    def job(trial: Trial) -> Job:
        return Job(trial.method, trial.number, with_cg(trial.method, trial.params),
                   cfg.iterations, ADAPT_LRS, trial.stage, prune_above=trial.prune_above)

    def told(done: Job, result: dict) -> None:
        if done.method not in TUNED_METHODS:
            return
        reports = result.get('meta_loss_reports', [])
        if 'pruned_at' in result:
            search.prune(done.method, done.index, reports)
        else:
            search.tell(done.method, done.index, result['score'], reports)

    supervised = [j for j in drawn if j.method == 'supervised']
    extra = supervised      # with the first round (cached once run)
    while True:
        trials = search.next_round()
        if not trials and not extra:
            break
        stage = 'refine' if any(t.stage == 'refine' for t in trials) else 'search'
        run_jobs(client, extra + [job(t) for t in trials], stage, settings, cache,
                 threads=cfg.threads, landed=told, progress=progress)
        extra = []
    results = run_jobs(client, [job(t) for t in search.completed()] + supervised, 'search',
                       settings, cache, threads=cfg.threads, progress=progress)
    search_s = time.monotonic() - start
    seeds = [VALIDATION_SEED + j for j in range(cfg.robust_seeds)]
    finalists = robust_jobs(results, cfg.finalists, cfg.full_iterations, seeds,
                            incumbents(cfg.config))
    robust_runs = run_jobs(client, finalists, 'robust', settings, cache, threads=cfg.threads,
                           progress=progress)
    robust = robust_scores(robust_runs)
    best = {m: best_of(m, robust or results) for m in TUNED_METHODS}
    best['supervised'] = best_of('supervised', results)
    winners = {m: request_fields(b, cfg.full_iterations, cfg.batch_size, cfg.adapt_steps)
               for m, b in best.items()}
    return json_safe({
        'protocol': {
            'k': cfg.k, 'refine': cfg.refine, 'search_iterations': cfg.iterations,
            'batch_size': cfg.batch_size,
            'full_iterations': cfg.full_iterations, 'finalists': cfg.finalists,
            'robust_seeds': seeds, 'adapt_steps': cfg.adapt_steps,
            'adapt_lrs': list(ADAPT_LRS), 'shared_grid': SHARED_GRID, 'gamma_grid': GAMMA_GRID,
            'calibration': CALIBRATION,
            'cg_steps': {str(g): n for g, n in CG_STEPS.items()}, 'curvature': CURVATURE,
            'windows_per_task': settings.learner.meta.windows_per_task,
            'n_systems': settings.learner.source.n_systems,
            'hidden': list(settings.learner.nssm.hidden), 'draw_seed': cfg.seed,
            'score': SCORES[cfg.score], 'search': SEARCH, 'per_round': cfg.per_round,
            'pruner': PRUNERS[cfg.pruner],
            'nmpc_costs': list(settings.control.nmpc) if settings.control else None,
            'robust_score': 'mean of the score over the robust_seeds source sets at '
                            'full_iterations outer steps, best adaptation step size'},
        'validation': {
            'thetas': list(settings.thetas), 'source_seed': VALIDATION_SEED,
            'meta_seed': VALIDATION_SEED, 'supervised_init_seed': VALIDATION_SEED,
            'theta_rng': f'rng([{VALIDATION_SEED} + i, {THETA_STREAM:#x}])',
            'target_samples': settings.target_samples, 'heldout_samples': HELDOUT_SAMPLES,
            'data_seeds': {'adapt': f'10 * ({VALIDATION_SEED} + i) + 1',
                           'heldout': f'10 * ({VALIDATION_SEED} + i) + 2'}},
        'configurations': results, 'robust': robust, 'robust_runs': robust_runs,
        'winners': winners,
        'search_wall_s': round(search_s, 1), 'wall_s': round(time.monotonic() - start, 1),
        'cpu_s': round(sum(r['cpu_seconds'] for r in results + robust_runs), 1),
        'study': {'storage': without_password(storage), 'names': search.names},
        'pruned': sorted([r['method'], r['index'], r['pruned_at']] for r in results
                         if 'pruned_at' in r),
        'jobs': slots(client), 'threads_per_job': cfg.threads,
        'load_avg_start': [round(v, 2) for v in load_start],
        'load_avg_end': [round(v, 2) for v in os.getloadavg()]})
