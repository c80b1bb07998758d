"""Which metampc packages a package may import, read from its code and its package.xml.

metampc_recording sits on common and msgs only (the recorder, reader, player and live view need
nothing of the model, the nodes or the orchestration); ros2cli reaches recording and common,
never bringup. Every import counts: top level, inside functions, and `from . import`.
"""
import ast
import glob
import os
import xml.etree.ElementTree as ET

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ALLOWED = {'metampc_recording': {'metampc_common', 'metampc_msgs'},
           'metampc_ros2cli': {'metampc_common', 'metampc_msgs', 'metampc_recording'}}


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


def declared_packages(package: str) -> set:
    """The metampc packages of `package`'s package.xml dependencies."""
    root = ET.parse(os.path.join(ROOT, 'src', package, 'package.xml')).getroot()
    return {e.text for e in root if e.tag.endswith('depend') and e.text.startswith('metampc_')}


@pytest.mark.parametrize('package', sorted(ALLOWED))
def test_package_imports_only_what_it_may(package):
    wrong = {name: where for name, where in imported_packages(package).items()
             if name not in ALLOWED[package]}
    assert not wrong, f'{package} imports {wrong}'


@pytest.mark.parametrize('package', sorted(ALLOWED))
def test_package_xml_declares_what_the_code_imports_and_no_more_than_allowed(package):
    declared = declared_packages(package)
    assert set(imported_packages(package)) <= declared <= ALLOWED[package], declared
