"""Fixtures of the metampc_bringup tests (the recording ones are in test/recording_fixtures.py):
an experiment small enough for the offline scripts' tests."""
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
    """An experiment YAML small enough to meta-train in seconds (the offline scripts'
    tests)."""
    path = tmp_path / 'tiny.yaml'
    path.write_text(TINY_EXPERIMENT)
    return path
