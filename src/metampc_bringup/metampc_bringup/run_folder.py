"""A run folder belongs to one configuration: a new one is created, an interrupted or failed
one is resumed by the same command.

The folder's config.yaml (the resolved configuration) names its run; a seed is done once its
``seed_<s>/report.json`` is written (after its recording is complete). Resuming runs only the
seeds not done, after removing what an unfinished try of them left; a folder of another
configuration, or one that is not a run folder, is refused before anything is written.
"""
import logging
import os
import shutil
from typing import Any, Dict, List, Sequence

import yaml

log = logging.getLogger('metampc.run_folder')


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
            log.info('seed %d: removing the unfinished try in %s', seed, unfinished)
            shutil.rmtree(unfinished)
    return todo
