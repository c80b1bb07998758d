"""One name per concept: each of the method sets is assigned in one module only (the others
import it), read from the code's own assignments (AST over src/ and scripts/); the modules
that decide by method write no set of method names in their functions, they name a declared
one."""
import ast
import glob
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ONCE = ('METHODS', 'META_METHODS', 'ADAPT_METHODS', 'BASELINES', 'NARX_METHODS',
        'NARX_ADAPT_METHODS', 'NARX_EXPERIMENT_METHODS', 'PREFIXED_NARX_METHODS')
NAMES = {'imaml', 'maml', 'maml_unrolled', 'supervised', 'oracle', 'arx', 'nmpc'}
# Modules cleaned of literal method sets (issue 53); the list only grows.
CLEANED = ('src/metampc_learner/metampc_learner/learner_session.py',
           'src/metampc_learner/metampc_learner/target_fit.py',
           'src/metampc_learner/metampc_learner/offline_adaptation.py',
           'src/metampc_bringup/metampc_bringup/analysis/experiment_report.py',
           'scripts/cascaded_tanks_benchmark.py',
           'src/metampc_bringup/metampc_bringup/studies/cascaded_tanks.py',
           'src/metampc_bringup/metampc_bringup/studies/cascaded_tanks_narx.py',
           'src/metampc_bringup/metampc_bringup/studies/cascaded_tanks_run.py',
           'src/metampc_bringup/metampc_bringup/analysis/cascaded_tanks_report.py')


def assignments(name: str) -> list:
    """'file:line' of every assignment to `name` (plain, annotated or augmented) in the
    modules of src/ and scripts/."""
    paths = sorted(glob.glob(os.path.join(ROOT, 'src', '**', '*.py'), recursive=True)
                   + glob.glob(os.path.join(ROOT, 'scripts', '**', '*.py'), recursive=True))
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, ast.Assign):
                targets = node.targets
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)):
                targets = [node.target]
            else:
                continue
            names = [t.id for target in targets for t in ast.walk(target)
                     if isinstance(t, ast.Name)]
            if name in names:
                found.append(f'{os.path.relpath(path, ROOT)}:{node.lineno}')
    return found


@pytest.mark.parametrize('name', ONCE)
def test_each_method_set_is_assigned_once(name):
    found = assignments(name)
    assert len(found) == 1, f'{name} assigned {len(found)} times: {found}'


def literal_sets(path: str) -> list:
    """'line: names' of every tuple, list or set of two or more method names written inside a
    function of the module `path` (a declaration is a module-level assignment)."""
    tree = ast.parse(open(os.path.join(ROOT, path)).read(), path)
    found = []
    for function in ast.walk(tree):
        if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(function):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and len(node.elts) > 1 and all(
                    isinstance(e, ast.Constant) and e.value in NAMES for e in node.elts):
                found.append(f'{node.lineno}: {[e.value for e in node.elts]}')
    return found


@pytest.mark.parametrize('path', CLEANED)
def test_no_literal_method_set_in_a_function(path):
    assert literal_sets(path) == [], path


def test_a_literal_method_set_is_found(tmp_path):
    module = tmp_path / 'm.py'
    module.write_text("A = ('imaml', 'maml')\n\ndef f(m):\n    return m in ('arx', 'nmpc')\n")
    assert literal_sets(str(module)) == ["4: ['arx', 'nmpc']"]
