"""bringup's roles: which sub-package imports which (read from the code), and no analysis
module imports rclpy, directly or through another module (each is imported in a fresh process
in which importing rclpy, or a submodule of it, raises ImportError)."""
import ast
import glob
import json
import os
import subprocess
import sys

import pytest

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       'metampc_bringup')
ANALYSIS = sorted(f'metampc_bringup.analysis.{name[:-3]}'
                  for name in os.listdir(os.path.join(PACKAGE, 'analysis'))
                  if name.endswith('.py') and name != '__init__.py')
ROLES = ('orchestration', 'analysis', 'studies', 'soak')
# The roles each role may import (any may import the modules on top); of those on top,
# experiment_config and experiment_events import no role, experiment.py any.
MAY_IMPORT = {'orchestration': set(), 'analysis': set(), 'studies': {'analysis', 'orchestration'},
              'soak': {'analysis', 'orchestration'}, 'experiment_config': set(),
              'experiment_events': set()}
# Imports each module named on the command line with rclpy blocked; prints one JSON object,
# {module: the ImportError's text} for those that failed.
IMPORT_WITHOUT_RCLPY = '''
import importlib, importlib.abc, json, sys

class NoRclpy(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == 'rclpy' or name.startswith('rclpy.'):
            raise ImportError(f'{name} is blocked here')
        return None

sys.meta_path.insert(0, NoRclpy())
failed = {}
for module in sys.argv[1:]:
    try:
        importlib.import_module(module)
    except ImportError as err:
        failed[module] = str(err)
print(json.dumps(failed))
'''


def imports_failing_without_rclpy(modules):
    """{module: error} of `modules` that cannot be imported without rclpy."""
    done = subprocess.run([sys.executable, '-c', IMPORT_WITHOUT_RCLPY, *modules],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def imported_roles(role: str) -> dict:
    """{role imported by the modules of `role` (a role or a module on top): 'file:line' of its
    first import}, every import counted (top level and inside functions)."""
    path = os.path.join(PACKAGE, role)
    paths = [path + '.py'] if os.path.exists(path + '.py') else glob.glob(f'{path}/*.py')
    found = {}
    for file in sorted(paths):
        for node in ast.walk(ast.parse(open(file).read(), file)):
            if isinstance(node, ast.ImportFrom):
                names = [f'{node.module}.{alias.name}' for alias in node.names]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            for name in names:
                parts = name.split('.')
                if parts[0] == 'metampc_bringup' and len(parts) > 1 and parts[1] in ROLES \
                        and parts[1] != role:
                    found.setdefault(parts[1], f'{os.path.basename(file)}:{node.lineno}')
    return found


def test_every_sub_package_is_a_role():
    packages = {os.path.basename(os.path.dirname(p))
                for p in glob.glob(os.path.join(PACKAGE, '*', '__init__.py'))}
    assert packages == set(ROLES)


@pytest.mark.parametrize('role', sorted(MAY_IMPORT))
def test_a_role_imports_only_the_roles_it_may(role):
    wrong = {r: where for r, where in imported_roles(role).items() if r not in MAY_IMPORT[role]}
    assert not wrong, f'{role} imports {wrong}'


def test_the_analysis_package_has_its_modules():
    assert {'metampc_bringup.analysis.experiment_report',
            'metampc_bringup.analysis.drift_report'} <= set(ANALYSIS)


def test_no_analysis_module_imports_rclpy():
    assert imports_failing_without_rclpy(ANALYSIS) == {}


def test_the_block_catches_rclpy_imported_through_another_module():
    # The client reaches rclpy through other modules (spun_node, metampc_common.qos).
    failed = imports_failing_without_rclpy(['metampc_bringup.orchestration.experiment_client'])
    assert 'rclpy' in failed['metampc_bringup.orchestration.experiment_client']
