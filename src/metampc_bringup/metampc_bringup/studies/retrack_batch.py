"""scripts/retrack.py's runs on the cluster layer: every seed's recorded models under each
variant of the controller's settings, and the true-model NMPC once per seed as the yardstick.

A job carries what it flies (the experiment, the seed, the recorded adapted models' fields, the
variant's overrides), so a worker needs no access to the run folder; its result lands on the
client in RUN_DIR/retrack/seed_<s>_<variant>_<digest>.json as it finishes, so a stopped run
resumes with the missing ones. The tracking itself: :func:`..analysis.retrack.track_models`.
"""
from dataclasses import asdict, dataclass
import functools
import hashlib
import json
import os
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from metampc_bringup.analysis.paired_stats import format_claim
from metampc_bringup.analysis.retrack import adapted_models, track_models
from metampc_bringup.experiment_config import ExperimentConfig
from metampc_bringup.orchestration.cluster import run_batch
from metampc_model.weights_codec import fields_of, model_from_fields

NMPC = 'nmpc'       # the yardstick's name among the variants' results


@dataclass(frozen=True)
class RetrackJob:
    """One seed's tracking under one variant (`name`, its controller `overrides`), or with
    `name` NMPC the yardstick alone. `models`: the recorded adapted models' fields by method
    (empty for the yardstick). `path`: where its result is kept on the client."""

    seed: int
    name: str
    overrides: Mapping[str, Any]
    models: Mapping[str, dict]
    path: str

    def __str__(self) -> str:       # the job's label (and dask key)
        return f'seed_{self.seed}_{self.name}'


def result_path(cache_dir: str, seed: int, name: str, overrides: Mapping[str, Any]) -> str:
    """The file of one (seed, variant): its name, and a digest of its overrides."""
    digest = hashlib.sha1(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:12]
    return os.path.join(cache_dir, f'seed_{seed}_{name}_{digest}.json')


def missing_jobs(recordings: Mapping[int, str], variants: Sequence[Tuple[str, dict]],
                 yardstick: Mapping[str, Any], cache_dir: str) -> List[RetrackJob]:
    """The jobs whose result file is not in `cache_dir`: per seed the NMPC under `yardstick`,
    then every variant (each seed's recording read once, here)."""
    jobs = []
    for seed, recording in recordings.items():
        models = None
        for name, overrides in [(NMPC, dict(yardstick))] + list(variants):
            path = result_path(cache_dir, seed, name, overrides)
            if os.path.exists(path):
                continue
            if models is None and name != NMPC:
                models = {m: fields_of(msg) for m, msg in adapted_models(recording).items()}
            jobs.append(RetrackJob(seed, name, dict(overrides),
                                   {} if name == NMPC else models, path))
    return jobs


def fly_job(experiment: ExperimentConfig, job: RetrackJob) -> Dict[str, dict]:
    """A job's tracking results ({method: MethodResult as a dict}), on a worker."""
    import torch
    torch.set_num_threads(1)
    flown = ({NMPC: None} if job.name == NMPC else
             {m: model_from_fields(f) for m, f in sorted(job.models.items())})
    results = track_models(experiment, job.seed, job.overrides, flown)
    return {m: asdict(r) for m, r in results.items()}


def run(client, experiment: ExperimentConfig, jobs: Sequence[RetrackJob],
        progress: bool = True, landed: Optional[Callable[[RetrackJob], None]] = None
        ) -> List[Tuple[RetrackJob, BaseException]]:
    """The jobs on `client`'s cluster, each result written to its path as it lands (whole or
    not at all); ``landed(job)`` after. Returns the (job, exception) of those that raised."""
    def done(job: RetrackJob, result: Dict[str, dict]) -> None:
        with open(job.path + '.tmp', 'w') as f:
            json.dump(result, f)
        os.replace(job.path + '.tmp', job.path)
        if landed is not None:
            landed(job)
    return run_batch(client, functools.partial(fly_job, experiment), list(jobs), 'retrack', done,
                     progress)


def per_seed_results(recordings: Mapping[int, str], variants: Sequence[Tuple[str, dict]],
                     yardstick: Mapping[str, Any], cache_dir: str
                     ) -> Dict[int, Dict[str, Dict[str, dict]]]:
    """{seed: {variant: {method: result, NMPC: the yardstick's}}} from the result files (the
    input of :func:`..analysis.retrack.summarise`)."""
    def read(seed: int, name: str, overrides: Mapping[str, Any]) -> dict:
        with open(result_path(cache_dir, seed, name, overrides)) as f:
            return json.load(f)
    out = {}
    for seed in recordings:
        nmpc = read(seed, NMPC, yardstick)[NMPC]
        out[seed] = {name: {**read(seed, name, overrides), NMPC: nmpc}
                     for name, overrides in variants}
    return out


def table(summary: Mapping[str, Mapping[str, dict]], first: str) -> List[str]:
    """The printed table: per variant and method the cost / NMPC median and worst, escapes,
    mean steady offset, the paired comparison with the variant `first`, the ratios by seed."""
    lines = [f'{"variant":<12}{"method":<10}{"median":>8}{"worst":>10}{"escapes":>9}'
             f'{"offset":>9}  {"vs " + first:<44} ratios by seed']
    for name, methods in summary.items():
        for method, row in methods.items():
            claim = row.get('vs_' + first)
            lines.append(f'{name:<12}{method:<10}{row["median"]:>8.3f}{row["worst"]:>10.3f}'
                         f'{row["escapes"]:>9}{row["mean_offset"]:>9.4f}  '
                         f'{format_claim(claim) if claim else "":<44} '
                         + ' '.join(f'{r:.2f}' for r in row['ratios'].values()))
    return lines


__all__ = ['fly_job', 'missing_jobs', 'NMPC', 'per_seed_results', 'result_path', 'RetrackJob',
           'run', 'table']
