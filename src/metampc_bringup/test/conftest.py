"""Fixtures of the metampc_bringup tests (the recording ones are in test/recording_fixtures.py):
an experiment small enough for the study scripts' tests."""
from pathlib import Path

import pytest

TINY_EXPERIMENT = """
methods: [imaml, maml]
target_samples: 60
learner: {n_systems: 4, episodes_per_system: 1, episode_samples: 40, hidden: [8], n_z: 2,
          history: 3, loss_horizon: 3, windows_per_task: 4}
meta_train:
  imaml: {batch_size: 4, lr_outer: 0.005, cg_steps: 2}
  maml: {batch_size: 4, lr_outer: 0.01}
"""


@pytest.fixture
def tiny_config(tmp_path) -> Path:
    """An experiment YAML small enough to meta-train in seconds (the study scripts'
    tests)."""
    path = tmp_path / 'tiny.yaml'
    path.write_text(TINY_EXPERIMENT)
    return path


# What a study's job measures of its run (time, memory), not what it computes.
MEASURED = ('cpu_seconds', 'meta_seconds', 'adapt_seconds', 'job_wall_s', 's_per_step',
            'peak_rss_mb', 'rss_before_meta_mb')


@pytest.fixture
def untimed():
    """A study job's result without what it measures of its run (:data:`MEASURED`)."""
    return lambda result: {k: v for k, v in result.items() if k not in MEASURED}


@pytest.fixture
def direct(monkeypatch, untimed):
    """``direct(settings, job, fn=run_job)``: a study's job run in this process as the
    process pool's workers ran it before the cluster layer (1 torch thread, the settings
    set), untimed; this process's torch threads and job state are restored after."""
    import torch
    from metampc_bringup.studies import learning_setup
    monkeypatch.setattr(learning_setup, '_VALIDATIONS', {})
    monkeypatch.setattr(learning_setup, '_SETTINGS', None)
    threads = torch.get_num_threads()

    def run(settings, job, fn=learning_setup.run_job):
        learning_setup.use(settings, 1)
        return untimed(fn(job))

    yield run
    torch.set_num_threads(threads)
