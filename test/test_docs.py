"""Docs for every command: each node parameter has a row on its node's page, each script and
each config key of the experiment is named in the docs."""
import ast
import dataclasses
import glob
import importlib
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Module of a node's PARAMETERS: its page, or 'page#Section' where the page documents two nodes.
NODE_PAGES = {
    'metampc_plant.plant_params': 'plant.md',
    'metampc_plant.bridge_node': 'bridge.md',
    'metampc_controller.controller_params': 'controller.md#Parameters',
    'metampc_controller.send_model_node': 'controller.md#Sending a model by hand',
    'metampc_learner.learner_params': 'learner.md',
    'metampc_recording.recorder_config': 'recording.md',
    'metampc_recording.foxglove_params': 'foxglove.md',
}


def _read(*parts: str) -> str:
    with open(os.path.join(ROOT, *parts)) as f:
        return f.read()


def _node_page(page: str) -> str:
    """docs/`page`, or its '## Section' for 'page#Section'."""
    name, _, section = page.partition('#')
    text = _read('docs', name)
    return text.split(f'\n## {section}\n', 1)[1].split('\n## ', 1)[0] if section else text


@pytest.mark.parametrize('module, page', sorted(NODE_PAGES.items()))
def test_every_node_parameter_is_documented(module, page):
    text = _node_page(page)
    names = importlib.import_module(module).PARAMETERS
    missing = [n for n in names if not re.search(rf'`{re.escape(n)}`', text)]
    assert not missing, f'docs/{page} lacks {missing}'


def _cell_value(text: str):
    """A default as the docs write it: `0.5`, 0.25 s, `''`, true, [128, 128], `cosine`."""
    t = text.strip().replace('`', '')
    t = t[:-2] if t.endswith(' s') else t
    t = t[:-len(' (unset)')] if t.endswith(' (unset)') else t
    if t.lower() in ('true', 'false'):
        return t.lower() == 'true'
    try:
        return ast.literal_eval(t)
    except (ValueError, SyntaxError):
        return t


def _parameter_rows(page: str, table):
    """(names, cells) of each row of the page's parameter tables (those with a 'default'
    column) whose first cell names parameters of `table`."""
    header = ''
    lines = _node_page(page).splitlines()
    for previous, line in zip([''] + lines, lines):
        if line.startswith('|') and not previous.startswith('|'):
            header = line.lower()
        cells = line.split('|')
        if 'default' not in header or len(cells) < 4 or not cells[1].strip().startswith('`'):
            continue
        names = re.findall(r'`([^`]+)`', cells[1])
        if names and all(n in table for n in names):
            yield names, cells


@pytest.mark.parametrize('module, page', sorted(NODE_PAGES.items()))
def test_every_documented_default_is_the_declared_one(module, page):
    """The node's table (declared once on the config fields) and its page agree on defaults;
    a row may name several parameters (`u_min`, `u_max` | -1.0, 1.0)."""
    table = importlib.import_module(module).PARAMETERS
    rows, wrong = 0, []
    for names, cells in _parameter_rows(page, table):
        if '(required)' in cells[2]:
            continue
        values = [cells[2]] if len(names) == 1 else cells[2].split(',')
        if len(values) != len(names):
            wrong.append((names, cells[2]))
            continue
        for name, text in zip(names, values):
            rows += 1
            default = table[name].default
            got = (text.strip().strip('`').replace("''", '') if isinstance(default, str)
                   else _cell_value(text))
            if got != default:
                wrong.append((name, text.strip(), table[name].default))
    assert rows >= len(table) - 1, f'docs/{page}: {rows} default cells for {len(table)}'
    assert not wrong, f'docs/{page}: documented defaults differ from the declared ones: {wrong}'


@pytest.mark.parametrize('module, page', sorted(NODE_PAGES.items()))
def test_live_parameters_are_marked_live_and_only_they(module, page):
    """A row says '(live)' after its names exactly when they are declared live
    (``param(..., live=True)``), and every live parameter has such a row."""
    table = importlib.import_module(module).PARAMETERS
    marked, wrong = set(), []
    for names, cells in _parameter_rows(page, table):
        said = '(live)' in cells[1]
        wrong += [n for n in names if table[n].live != said]
        marked.update(n for n in names if said)
    assert not wrong, f'docs/{page}: the live marker is wrong for {wrong}'
    live = {n for n, spec in table.items() if spec.live}
    assert marked == live, f'docs/{page}: live but not marked: {sorted(live - marked)}'


REFERENCE_PAGES = sorted(glob.glob(os.path.join(ROOT, 'docs', '*.md')))
STUDIES = sorted(p for p in glob.glob(os.path.join(ROOT, 'docs', 'studies', '*.md'))
                 if os.path.basename(p) != 'README.md')


def test_every_script_and_page_is_reachable_from_the_readme_or_docs():
    """Each script is named in the README, a reference page or a study; each reference page is
    linked from the README or a page, the studies' index from a page, each study from the
    index."""
    docs = _read('README.md') + ''.join(_read(p) for p in REFERENCE_PAGES + STUDIES)
    scripts = [os.path.basename(p) for p in glob.glob(os.path.join(ROOT, 'scripts', '*'))]
    assert not [s for s in scripts if s not in docs]
    pages = [os.path.basename(p) for p in REFERENCE_PAGES]
    assert not [p for p in pages if f'docs/{p}' not in docs and f'({p})' not in docs]
    assert 'docs/studies/README.md' in docs or '(studies/README.md)' in docs
    index = _read('docs', 'studies', 'README.md')
    assert not [p for p in STUDIES if f'({os.path.basename(p)})' not in index]


@pytest.mark.parametrize('path', REFERENCE_PAGES, ids=os.path.basename)
def test_a_reference_page_is_at_most_400_lines(path):
    """A reference page says what the code does now; the dated studies live in docs/studies/."""
    lines = len(_read(path).splitlines())
    assert lines <= 400, f'{os.path.relpath(path, ROOT)}: {lines} lines (move its studies out)'


@pytest.mark.parametrize('path', STUDIES, ids=os.path.basename)
def test_a_study_has_its_date_its_command_and_its_seeds(path):
    """docs/studies/YYYY-MM-DD-<topic>.md: a first heading with that date, a code block with
    the command that ran (or the words 'command not recorded') and the seeds named."""
    date = re.fullmatch(r'(\d{4}-\d{2}-\d{2})-[a-z0-9-]+\.md', os.path.basename(path))
    assert date, f'{path}: not named YYYY-MM-DD-<topic>.md'
    text = _read(path)
    first = text.splitlines()[0]
    assert first.startswith('# ') and date.group(1) in first, f'{path}: first line {first!r}'
    code = re.findall(r'```[a-z]*\n(.*?)```', text, flags=re.S) + re.findall(
        r'(?:^|\n\n)((?: {4}.*\n?)+)', text)
    commands = [c for block in code for c in block.splitlines()
                if re.match(r'\s*(python|ros2|git|make|PYTHONPATH=)\b', c)]
    assert commands or 'command not recorded' in text, f'{path}: no command block'
    assert re.search(r'\bseeds?\b[^.\n]*\d', text, flags=re.I), f'{path}: no seeds named'


def test_every_experiment_key_is_documented():
    from metampc_bringup.experiment_config import ExperimentConfig
    text = _read('docs', 'experiments.md')
    missing = [f.name for f in dataclasses.fields(ExperimentConfig) if f'`{f.name}`' not in text]
    assert not missing
