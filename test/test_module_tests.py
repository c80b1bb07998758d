"""One module, one test file named after it; module docstrings short. Read from the code.

- Every library module (src/<pkg>/<pkg>/**.py, __init__ aside) that defines a function or a
  method has a test file ``test_<module>.py`` in its package's test/ or in test/, unless
  :data:`TESTED_ELSEWHERE` says which test covers it and why that one is named otherwise (a
  system test across nodes, or one reference shared by several modules), or :data:`WIRING` says
  why there is nothing of its own to test. A module of type declarations alone (dataclasses, a
  NamedTuple, constants) has no behaviour to test and needs neither. An entry whose module has
  a test of its own by now, or no longer exists, must leave its table, so the tables only
  shrink.
- Every library module has a docstring of at most :data:`MAX_DOCSTRING_LINES` lines: what the
  module is, the paper equations it implements by name, its contract (docs/ holds the rest).
  12 lines hold the longest contract written so far (a node's: its topics, what it refuses,
  where its parameters and docs are) and, being a screen's third, still read at a glance.
"""
import ast
from pathlib import Path
from typing import Dict, Iterator, List, Tuple

ROOT = Path(__file__).resolve().parents[1]
MAX_DOCSTRING_LINES = 12

# Modules tested by a test named otherwise: module -> (test file, why not one of its own).
_SYSTEM = 'test/test_experiment.py'
_META_GRADIENTS = ('src/metampc_learner/test/test_hypergradient.py',
                   'the meta-gradients against one dense / autograd reference on one problem')
_FAMILIES = ('src/metampc_plant/test/test_families.py',
             'every registered family against its equations written out again, through the '
             'registry')
_FOXGLOVE = ('test/test_foxglove.py', 'the live view as a Foxglove client sees it, node to '
             'client: server, front and adapters are its parts')
_GRAPH_VERBS = ('src/metampc_ros2cli/test/test_graph_verbs.py',
                'the `ros2 node|topic|service|interface` verbs against one live plant')
_RUN_SERIES = ('src/metampc_bringup/test/test_run_series.py',
               'the replay of synthetic recordings exercises them together')
_ROS2 = ('src/metampc_ros2cli/test/test_graph_verbs.py',
         'the `ros2` command as a user runs it, in every verb test')
TESTED_ELSEWHERE: Dict[str, Tuple[str, str]] = {
    'metampc_learner.imaml': _META_GRADIENTS,
    'metampc_learner.maml': _META_GRADIENTS,
    'metampc_learner.curvature': _META_GRADIENTS,
    'metampc_learner.objective': _META_GRADIENTS,
    'metampc_plant.family': _FAMILIES,
    'metampc_plant.registry': _FAMILIES,
    'metampc_plant.families.duffing': _FAMILIES,
    'metampc_plant.families.pendulum': _FAMILIES,
    'metampc_plant.families.quadruple_tank': _FAMILIES,
    'metampc_plant.families.vanderpol': _FAMILIES,
    'metampc_bringup.orchestration.seed_jobs': (
        _SYSTEM, '--jobs 2 (the embedded cluster) against --jobs 1, resume, Ctrl-C of both '
        'seeds: processes end to end'),
    'metampc_bringup.analysis.experiment_report': (
        _SYSTEM, 'the report of a real experiment against the recording read by rosbags'),
    'metampc_bringup.analysis.retrack': (
        _SYSTEM, 'the recorded tracking costs reproduced from a real run\'s models'),
    'metampc_bringup.orchestration.cpu_budget': (
        _SYSTEM, '--jobs beyond the usable cores refused, as a user runs it'),
    'metampc_bringup.orchestration.experiment_client': (
        'test/test_idempotent_calls.py', 'its calls against live nodes, a first answer dropped'),
    'metampc_bringup.orchestration.domain': (
        'src/metampc_bringup/test/test_lifeline.py', 'a domain held by a killed run\'s nodes'),
    'metampc_bringup.studies.learning_setup': (
        'src/metampc_bringup/test/test_tuning.py', 'the job runner under the search and sweep'),
    'metampc_bringup.analysis.input_sources': _RUN_SERIES,
    'metampc_bringup.analysis.plots': (
        'src/metampc_bringup/test/test_run_report.py', 'the plots of a real recording'),
    'metampc_recording.synthetic_run': _RUN_SERIES,
    'metampc_recording.recording_reader': (
        'src/metampc_recording/test/test_mcap_writer.py', 'what the writer wrote, read back'),
    'metampc_recording.foxglove_node': _FOXGLOVE,
    'metampc_recording.foxglove_server': _FOXGLOVE,
    'metampc_recording.foxglove_client': _FOXGLOVE,
    'metampc_recording.subprotocol_front': _FOXGLOVE,
    'metampc_recording.rclpy_adapters': _FOXGLOVE,
    'metampc_recording.foxglove_params': (
        'test/test_docs.py', 'a parameter table: its rows and defaults against the docs'),
    'metampc_plant.plant_params': (
        'src/metampc_plant/test/test_plant_node.py', 'a parameter table, parsed by the node'),
    'metampc_plant.integrate': (
        'src/metampc_plant/test/test_simulator.py', 'the RK4 kernel of the simulators'),
    'metampc_controller.closed_loop': (
        'src/metampc_controller/test/test_controller_core.py',
        'run_episode against an independent replay of the core'),
    'metampc_controller.terminal_cost': (
        'src/metampc_controller/test/test_mpc.py', 'the DARE terminal cost inside the MPC'),
    'metampc_controller.send_model_node': (
        'src/metampc_controller/test/test_controller_node.py', 'the model it sends, flown'),
    'metampc_model.latent_model': (
        'src/metampc_controller/test/test_mpc.py', 'the model the MPC plans with'),
    'metampc_model.normalisation': (
        'src/metampc_model/test/test_nssm.py', 'the NSSM\'s units'),
    'metampc_model.nssm_config': (
        'src/metampc_model/test/test_nssm.py', 'the NSSM\'s architecture'),
    'metampc_model.manual_model': (
        'src/metampc_model/test/test_weights_codec.py', 'the hand-built model, encoded and run'),
    'metampc_learner.oracle': (
        'src/metampc_learner/test/test_learner_session.py', 'the oracle baseline of adapt'),
    'metampc_common.entry': (
        'test/test_nodes_start.py', 'Ctrl-C while a node module imports, in a real process'),
    'metampc_common.hold_config': (
        'src/metampc_common/test/test_held_publisher.py', 'the held writers\' settings'),
    'metampc_ros2cli.bag_info': (
        'src/metampc_ros2cli/test/test_bag.py', '`ros2 bag info` of real and rosbag2 bags'),
    'metampc_ros2cli.verbs.node': _GRAPH_VERBS,
    'metampc_ros2cli.verbs.topic': _GRAPH_VERBS,
    'metampc_ros2cli.verbs.service': _GRAPH_VERBS,
    'metampc_ros2cli.verbs.interface': _GRAPH_VERBS,
    'metampc_ros2cli.names': _GRAPH_VERBS,
    'metampc_ros2cli.api': _ROS2,
    'metampc_ros2cli.cli': _ROS2,
}

# Modules with a function but nothing of their own to test: module -> why.
_ENTRY = 'console-script entry points, one metampc_common.entry.run call each (test_nodes_start)'
WIRING: Dict[str, str] = {
    'metampc_controller.main': _ENTRY,
    'metampc_learner.main': _ENTRY,
    'metampc_plant.main': _ENTRY,
    'metampc_recording.main': _ENTRY,
}


def library_modules() -> Iterator[Tuple[str, Path]]:
    """(dotted name, path) of every module of every package under src/."""
    for pkg in sorted((ROOT / 'src').glob('*/*/__init__.py')):
        top = pkg.parent
        if top.name != top.parent.name:
            continue
        for path in sorted(top.rglob('*.py')):
            parts = path.relative_to(top.parent).with_suffix('').parts
            yield '.'.join(p for p in parts if p != '__init__'), path


def has_logic(tree: ast.AST) -> bool:
    return any(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) for n in ast.walk(tree))


def own_tests(dotted: str) -> List[Path]:
    """The test files named after the module: in its package's test/ or in test/."""
    name = f'test_{dotted.rsplit(".", 1)[-1]}.py'
    dirs = (ROOT / 'src' / dotted.split('.')[0] / 'test', ROOT / 'test')
    return [d / name for d in dirs if (d / name).is_file()]


def parsed(packages: bool = True) -> Dict[str, ast.AST]:
    """Module name -> syntax tree; `packages`: the __init__ modules too."""
    return {name: ast.parse(path.read_text(), str(path)) for name, path in library_modules()
            if packages or path.name != '__init__.py'}


def test_every_module_with_logic_has_a_test_named_after_it():
    missing = [name for name, tree in parsed(packages=False).items()
               if has_logic(tree) and not own_tests(name)
               and name not in TESTED_ELSEWHERE and name not in WIRING]
    assert not missing, f'modules with logic and no test_<module>.py: {missing}'


def test_the_tables_only_shrink():
    trees = parsed()
    for name, (test, _) in TESTED_ELSEWHERE.items():
        assert name in trees, f'{name} is gone: remove it from TESTED_ELSEWHERE'
        assert (ROOT / test).is_file(), f'{name}: {test} does not exist'
        assert not own_tests(name), f'{name} has a test of its own: remove it from the table'
    for name in WIRING:
        assert name in trees and has_logic(trees[name]), f'{name}: remove it from WIRING'
        assert not own_tests(name), f'{name} has a test of its own: remove it from WIRING'


def test_every_library_module_has_a_short_docstring():
    lengths = {name: len((ast.get_docstring(tree) or '').splitlines())
               for name, tree in parsed().items()}
    undocumented = sorted(name for name, n in lengths.items() if n == 0)
    assert not undocumented, f'modules without a docstring: {undocumented}'
    long = {name: n for name, n in lengths.items() if n > MAX_DOCSTRING_LINES}
    assert not long, f'module docstrings over {MAX_DOCSTRING_LINES} lines: {long}'
