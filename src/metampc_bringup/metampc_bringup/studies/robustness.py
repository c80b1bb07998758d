"""Robustness of meta-training (``scripts/robustness.py``, docs/experiments.md): the
experiment's requests on many source sets as jobs of :mod:`metampc_bringup.studies.learning_setup`,
and which runs diverged."""
import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from metampc_bringup.experiment_config import ExperimentConfig
from metampc_bringup.studies.learning_setup import Job, request_meta_config
from metampc_learner.meta_train import MetaConfig

DIVERGED_FACTOR = 10.0   # a run whose final loss exceeds 10x its method's median diverged


def _diverged(runs: Sequence[dict], values: Sequence[float]) -> Tuple[float, List[int]]:
    """(median of the finite values, source seeds non-finite or above DIVERGED_FACTOR x it)."""
    finite = [v for v in values if math.isfinite(v)]
    median = float(np.median(finite)) if finite else math.inf
    return median, [r['source_seed'] for r, v in zip(runs, values)
                    if not math.isfinite(v) or v > DIVERGED_FACTOR * median]


def robustness_jobs(experiment: ExperimentConfig, methods: Sequence[str], seeds: Sequence[int],
                    nssm: Dict[str, Any], overrides: Optional[Dict[str, Any]] = None,
                    adapt: bool = False) -> List[Job]:
    """Meta-training at the experiment's request fields (with `overrides`, MetaConfig fields,
    on top) on the source sets of `seeds` (the experiment's own: source seed = meta seed = the
    run's seed); with `adapt`, each meta-model is also scored at the experiment's adaptation
    step size of its method (on the settings' validation targets)."""
    jobs = []
    for method in methods:
        hyper = {**request_meta_config(experiment, method), **(overrides or {})}
        iterations = int(hyper.pop('iterations', 0) or MetaConfig().iterations)
        lrs = (float(experiment.adapt[method]['lr']),) if adapt else ()
        jobs.extend(Job(method, seed, hyper, iterations, lrs, 'robust', seed, dict(nssm))
                    for seed in seeds)
    return jobs


def robustness_summary(results: Sequence[dict]) -> Dict[str, Any]:
    """Per method: final losses per seed, median, the runs that diverged (non-finite, failed,
    or a final loss above DIVERGED_FACTOR x the median); the same for the loss of the weights
    returned (`returned_loss`: the best checkpoint's validation loss under the divergence
    guard) and the guard's rollbacks per run; A's largest spectral radius, and when every run
    was adapted, their scores (held-out loss after adaptation on the same validation targets
    for every run), mean, median and the runs above DIVERGED_FACTOR x it."""
    out: Dict[str, Any] = {}
    for method in dict.fromkeys(r['method'] for r in results):
        runs = [r for r in results if r['method'] == method]
        final = [float(r.get('meta_final_loss', math.inf)) for r in runs]
        returned = [float(r.get('meta_returned_loss', math.inf)) for r in runs]
        median, diverged = _diverged(runs, final)
        median_returned, diverged_returned = _diverged(runs, returned)
        out[method] = {
            'seeds': [r['source_seed'] for r in runs], 'final_loss': final,
            'median_final_loss': median, 'worst_final_loss': max(final),
            'max_loss': [r.get('meta_max_loss', math.inf) for r in runs],
            'diverged': diverged, 'n_diverged': len(diverged),
            'returned_loss': returned, 'median_returned_loss': median_returned,
            'worst_returned_loss': max(returned),
            'diverged_returned': diverged_returned,
            'n_diverged_returned': len(diverged_returned),
            'rollbacks': [len(r.get('meta_rollbacks', ())) for r in runs],
            'a_radius': [r.get('a_radius', math.nan) for r in runs],
            'max_a_radius': max(r.get('a_radius', math.nan) for r in runs),
            'meta_seconds': [r.get('meta_seconds') for r in runs]}
        if all(r.get('adapt') for r in runs):
            # The one loss that every run is scored on alike: the same validation targets
            # (a run's returned loss is on held-out tasks of its own source set).
            scores = [float(r['score']) for r in runs]
            median_score, diverged_score = _diverged(runs, scores)
            out[method].update(score=scores, mean_score=float(np.mean(scores)),
                               median_score=median_score, diverged_score=diverged_score,
                               n_diverged_score=len(diverged_score))
    return out
