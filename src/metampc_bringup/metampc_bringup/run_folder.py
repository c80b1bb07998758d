"""A run folder belongs to one configuration: a new one is created, an interrupted or failed
one is resumed by the same command.

The folder's config.yaml (the resolved configuration) names its run; a seed is done once its
``seed_<s>/report.json`` is written (after its recording is complete). A seed stopped before
(Ctrl-C, a failure) keeps its folder, marked by an :data:`INCOMPLETE` file. Resuming runs only
the seeds not done, after moving what an unfinished try of them left to
``incomplete/seed_<s>.<try>/``; a folder of another configuration, or one that is not a run
folder, is refused before anything is written.
"""
import logging
import os
from typing import Any, Dict, List, Sequence

import yaml

log = logging.getLogger('metampc.run_folder')

INCOMPLETE = 'INCOMPLETE'       # in a seed's folder: why it stopped before its report


def config_text(config: Dict[str, Any]) -> str:
    """The config.yaml of a run of `config` (its resolved dict)."""
    return yaml.safe_dump(config, sort_keys=False)


def done_seeds(out_dir: str, config: Dict[str, Any], seeds: Sequence[int]) -> List[int]:
    """The `seeds` already done in `out_dir` (none if it does not exist or is empty); only
    reads.

    Raises:
        FileExistsError: `out_dir` is not a folder, not a run folder, or the run folder of
            another configuration.
    """
    if not os.path.exists(out_dir):
        return []
    if not os.path.isdir(out_dir):
        raise FileExistsError(f'{out_dir} exists and is not a folder; runs are never '
                              'overwritten')
    if not os.listdir(out_dir):
        return []
    path = os.path.join(out_dir, 'config.yaml')
    if not os.path.isfile(path):
        raise FileExistsError(f'{out_dir} exists and is not empty; runs are never overwritten '
                              '(no config.yaml: not a run folder to resume)')
    with open(path) as f:
        if f.read() != config_text(config):
            raise FileExistsError(f'{out_dir} holds the run of another configuration (its '
                                  'config.yaml differs); runs are never overwritten: choose '
                                  'another --out')
    return [s for s in seeds
            if os.path.isfile(os.path.join(out_dir, f'seed_{s}', 'report.json'))]


def prepare(out_dir: str, config: Dict[str, Any], seeds: Sequence[int]) -> List[int]:
    """Create `out_dir` with its config.yaml, or resume it: the seeds to run, in order
    (:func:`done_seeds` raises first); what unfinished tries left of them is removed."""
    done = done_seeds(out_dir, config, seeds)
    todo = [s for s in seeds if s not in done]
    path = os.path.join(out_dir, 'config.yaml')
    if os.path.exists(path):
        log.info('resuming %s: %d of %d seeds done; running %d: %s', out_dir, len(done),
                 len(seeds), len(todo), ', '.join(map(str, todo)) or 'none')
    else:
        os.makedirs(out_dir, exist_ok=True)
        with open(path, 'w') as f:
            f.write(config_text(config))
    for seed in todo:
        unfinished = os.path.join(out_dir, f'seed_{seed}')
        if os.path.exists(unfinished):
            kept = _free_try(out_dir, seed)
            log.info('seed %d: the unfinished try in %s kept in %s', seed, unfinished, kept)
            os.makedirs(os.path.dirname(kept), exist_ok=True)
            os.rename(unfinished, kept)
    return todo


def _free_try(out_dir: str, seed: int) -> str:
    """The first ``incomplete/seed_<seed>.<try>`` of `out_dir` not taken (try from 1)."""
    tries = 1
    while os.path.exists(path := os.path.join(out_dir, 'incomplete', f'seed_{seed}.{tries}')):
        tries += 1
    return path


def mark_incomplete(seed_folder: str, why: str) -> None:
    """Mark a seed's folder that stopped before its report (its recording is readable up to
    there): an :data:`INCOMPLETE` file saying `why`; nothing if the folder was not made."""
    if os.path.isdir(seed_folder):
        with open(os.path.join(seed_folder, INCOMPLETE), 'w') as f:
            f.write(f'{why}; no report: the same command runs this seed again\n')


def incomplete(seed_folder: str) -> bool:
    """Whether a seed's folder is marked incomplete (:func:`mark_incomplete`)."""
    return os.path.exists(os.path.join(seed_folder, INCOMPLETE))
