"""One name per concept: each of the method sets is assigned in one module only (the others
import it), read from the code's own assignments (AST over src/ and scripts/)."""
import ast
import glob
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ONCE = ('METHODS', 'META_METHODS', 'ADAPT_METHODS')


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
