"""Docs for every command: each node parameter has a row on its node's page, each script and
each config key of the experiment is named in the docs."""
import dataclasses
import glob
import importlib
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NODE_PAGES = {
    'metampc_plant.plant_params': 'plant.md',
    'metampc_controller.controller_params': 'controller.md',
    'metampc_learner.learner_params': 'learner.md',
    'metampc_bringup.recorder_config': 'recording.md',
}


def _read(*parts: str) -> str:
    with open(os.path.join(ROOT, *parts)) as f:
        return f.read()


@pytest.mark.parametrize('module, page', sorted(NODE_PAGES.items()))
def test_every_node_parameter_is_documented(module, page):
    text = _read('docs', page)
    names = importlib.import_module(module).PARAMETERS
    missing = [n for n in names if not re.search(rf'`{re.escape(n)}`', text)]
    assert not missing, f'docs/{page} lacks {missing}'


def test_every_script_and_page_is_reachable_from_the_readme_or_docs():
    docs = _read('README.md') + ''.join(_read('docs', os.path.basename(p))
                                        for p in glob.glob(os.path.join(ROOT, 'docs', '*.md')))
    scripts = [os.path.basename(p) for p in glob.glob(os.path.join(ROOT, 'scripts', '*'))]
    assert not [s for s in scripts if s not in docs]
    pages = [os.path.basename(p) for p in glob.glob(os.path.join(ROOT, 'docs', '*.md'))]
    assert not [p for p in pages if f'docs/{p}' not in docs and f'({p})' not in docs]


def test_every_experiment_key_is_documented():
    from metampc_bringup.experiment_config import ExperimentConfig
    text = _read('docs', 'experiments.md')
    missing = [f.name for f in dataclasses.fields(ExperimentConfig) if f'`{f.name}`' not in text]
    assert not missing
