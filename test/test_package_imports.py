"""Which metampc packages a package may import, read from its code and its package.xml.

The house in layers, lowest first (each package imports only packages of lower layers):

    msgs, common <- plant, model, recording <- controller <- learner <- bringup <- ros2cli

`model` (the NSSM of eq. (SSM)) needs common only; `recording` (recorder, reader, player,
live view) needs nothing of the model, the nodes or the orchestration; the controller reaches
the plant for the true-model NMPC only, the learner reaches the controller for the MPC of online
collection and recording's reader for a recording cut short (adapt_offline); ros2cli, the
command-line face of the stack, reaches recording and common for its verbs and bringup's
process group for `ros2 launch` (inside the verb: a verb's start imports none of it), as
DESIGN.md draws the house. Every import counts: top
level, inside functions, and `from . import` (a relative import, counted as '.', allowed to
no package: every import names its package). Modules import each other without a cycle, in
any package.
"""
import ast
import glob
import os
import xml.etree.ElementTree as ET

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COMMON, MSGS, PLANT, MODEL = 'metampc_common', 'metampc_msgs', 'metampc_plant', 'metampc_model'
RECORDING, CONTROLLER = 'metampc_recording', 'metampc_controller'
LEARNER, ROS2CLI, BRINGUP = 'metampc_learner', 'metampc_ros2cli', 'metampc_bringup'
MAY_IMPORT = {
    MSGS: set(),
    COMMON: set(),
    PLANT: {COMMON, MSGS},
    MODEL: {COMMON},
    RECORDING: {COMMON, MSGS},
    CONTROLLER: {COMMON, MSGS, PLANT, MODEL},
    LEARNER: {COMMON, MSGS, PLANT, MODEL, RECORDING, CONTROLLER},
    BRINGUP: {COMMON, MSGS, PLANT, MODEL, RECORDING, CONTROLLER, LEARNER},
    ROS2CLI: {COMMON, MSGS, RECORDING, BRINGUP},
}


def imported_packages(package: str) -> dict:
    """{metampc package imported by `package`'s modules: 'file:line' of its first import};
    a relative import counts as one of '.'."""
    found = {}
    for path in sorted(glob.glob(os.path.join(ROOT, 'src', package, package, '**', '*.py'),
                                 recursive=True)):
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, ast.ImportFrom):
                tops = ['.'] if node.level else [node.module.split('.')[0]]
            elif isinstance(node, ast.Import):
                tops = [alias.name.split('.')[0] for alias in node.names]
            else:
                continue
            for top in tops:
                if (top == '.' or top.startswith('metampc_')) and top != package:
                    found.setdefault(top, f'{os.path.relpath(path, ROOT)}:{node.lineno}')
    return found


def module_graph() -> dict:
    """{module: the metampc modules it imports}, dotted names, over every package under src/
    (every import statement, inside functions too; `from pkg import sub` counts the submodule
    `pkg.sub` where there is one)."""
    paths = {}
    for path in glob.glob(os.path.join(ROOT, 'src', '*', 'metampc_*', '**', '*.py'),
                          recursive=True):
        rel = os.path.relpath(path, os.path.join(ROOT, 'src'))
        parts = rel[:-3].split(os.sep)[1:]
        paths['.'.join(parts[:-1] if parts[-1] == '__init__' else parts)] = path
    graph = {}
    for module, path in paths.items():
        names = set()
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.update(f'{node.module}.{alias.name}'
                             if f'{node.module}.{alias.name}' in paths else node.module
                             for alias in node.names)
        graph[module] = {n for n in names if n in paths and n != module}
    return graph


def cycle(graph: dict) -> list:
    """A cycle of `graph` as [a, b, ..., a], or [] when there is none."""
    done, path = set(), []

    def visit(node):
        if node in path:
            return path[path.index(node):] + [node]
        if node in done:
            return []
        path.append(node)
        for other in sorted(graph.get(node, ())):
            found = visit(other)
            if found:
                return found
        path.pop()
        done.add(node)
        return []

    for node in sorted(graph):
        found = visit(node)
        if found:
            return found
    return []


def declared_packages(package: str) -> set:
    """The metampc packages of `package`'s package.xml dependencies."""
    root = ET.parse(os.path.join(ROOT, 'src', package, 'package.xml')).getroot()
    return {e.text for e in root if e.tag.endswith('depend') and e.text.startswith('metampc_')}


def layers(may_import: dict) -> list:
    """The packages in layers, lowest first (each imports only lower layers); AssertionError
    naming the packages of a cycle."""
    out, placed = [], set()
    while len(placed) < len(may_import):
        layer = sorted(p for p, deps in may_import.items()
                       if p not in placed and deps <= placed)
        assert layer, f'import cycle among {sorted(set(may_import) - placed)}'
        out.append(layer)
        placed.update(layer)
    return out


def test_every_package_is_in_the_table():
    assert set(os.listdir(os.path.join(ROOT, 'src'))) == set(MAY_IMPORT)


def test_the_table_is_layered_as_the_docstring_draws_it():
    assert layers(MAY_IMPORT) == [[COMMON, MSGS], [MODEL, PLANT, RECORDING],
                                  [CONTROLLER], [LEARNER], [BRINGUP], [ROS2CLI]]


def test_layers_finds_a_cycle():
    with pytest.raises(AssertionError, match='cycle'):
        layers({COMMON: set(), MODEL: {COMMON, CONTROLLER}, CONTROLLER: {MODEL}})


def test_no_import_cycle_between_modules():
    # A package's __init__ importing its own modules is no cycle of ideas: leave them out.
    graph = {m: {n for n in deps if not m.startswith(n + '.')}
             for m, deps in module_graph().items()}
    assert len(graph) > 100     # every module was read
    assert cycle(graph) == []


def test_cycle_finds_one_and_only_one():
    assert cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': set()}) == ['a', 'b', 'c', 'a']
    assert cycle({'a': {'b', 'c'}, 'b': {'c'}, 'c': set()}) == []


@pytest.mark.parametrize('package', sorted(MAY_IMPORT))
def test_package_imports_only_what_it_may(package):
    wrong = {name: where for name, where in imported_packages(package).items()
             if name not in MAY_IMPORT[package]}
    assert not wrong, f'{package} imports {wrong}'


@pytest.mark.parametrize('package', sorted(MAY_IMPORT))
def test_package_xml_declares_what_the_code_imports_and_no_more_than_allowed(package):
    declared = declared_packages(package)
    assert set(imported_packages(package)) - {'.'} <= declared <= MAY_IMPORT[package], declared
