"""The model package's imports, read from its source: it stands on metampc_common alone and
its modules import each other without a cycle (imports under TYPE_CHECKING included)."""
import ast
from pathlib import Path

import metampc_model

PACKAGE = Path(metampc_model.__file__).resolve().parent


def _imports():
    """{module: set of metampc_* modules it imports}, every import statement of the file."""
    out = {}
    for path in PACKAGE.glob('*.py'):
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module)
        out[path.stem] = {n for n in names if n.startswith('metampc_')}
    return out


def test_the_model_imports_only_common_and_itself():
    outside = {m: sorted(n for n in names if n.split('.')[0] not in (
        'metampc_common', 'metampc_model')) for m, names in _imports().items()}
    assert not any(outside.values()), outside


def test_no_import_cycle_between_the_model_modules():
    graph = {m: {n.split('.')[1] for n in names if n.startswith('metampc_model.')}
             for m, names in _imports().items()}
    done, path = set(), []

    def visit(module):
        assert module not in path, ' -> '.join(path[path.index(module):] + [module])
        if module in done:
            return
        path.append(module)
        for other in sorted(graph.get(module, ())):
            visit(other)
        path.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)
