"""Every command the README, docs/*.md and docs/studies/*.md show for copying still matches
the code: each `python scripts/X.py --flag` names a flag the script's --help lists, each `ros2
run PKG EXE --ros-args -p name:=value` names an executable and a parameter that node declares,
and each other `ros2 VERB ...` of a code block parses as written (metampc_ros2cli's parser,
ros2cli's syntax), and each `ros2 run` of a command-line program names flags its --help lists.
The commands are read from fenced and indented code blocks and from inline code spans (`python
scripts/` and `ros2 run` only: a span may name a verb without its arguments)."""
import contextlib
import functools
import glob
import os
import re
import shlex
import signal
import subprocess
import sys

import pytest

from metampc_common.node_main import QOS_OVERRIDES, ROS_PARAMETERS
from metampc_controller import controller_params, send_model_node
from metampc_learner import learner_params
from metampc_plant import bridge_node, plant_params
from metampc_recording import foxglove_params, recorder_config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NODES = {('metampc_plant', 'plant'): plant_params.PARAMETERS,
         ('metampc_plant', 'bridge'): bridge_node.PARAMETERS,
         ('metampc_controller', 'controller'): controller_params.PARAMETERS,
         ('metampc_controller', 'send_model'): send_model_node.PARAMETERS,
         ('metampc_learner', 'learner'): learner_params.PARAMETERS,
         ('metampc_recording', 'recorder'): recorder_config.PARAMETERS,
         ('metampc_recording', 'foxglove'): foxglove_params.PARAMETERS}
# Command-line programs of `ros2 run` (argparse, no ROS parameters): their parser's module.
CLIS = {('metampc_bringup', 'adapt_offline'): 'metampc_bringup.adapt_offline'}
# A usage template, not a command: `ros2 run PKG EXE`, `-p name:=value`.
TEMPLATE = re.compile(r'ros2 run [A-Z_]+ |-p name:=value')
PAGES = ['README.md'] + sorted(os.path.relpath(p, ROOT)
                               for p in glob.glob(os.path.join(ROOT, 'docs', '*.md'))
                               + glob.glob(os.path.join(ROOT, 'docs', 'studies', '*.md')))


def _commands(text: str):
    """Command lines of a page: code blocks (fenced or indented, continuation lines joined)
    and inline code spans that start with `python scripts/` or `ros2 run`."""
    lines, block, fenced = [], [], False
    for line in text.splitlines():
        if line.strip().startswith('```'):
            fenced = not fenced
            continue
        if fenced or line.startswith('    '):
            block.append(line.strip())
    joined = '\n'.join(block).replace('\\\n', ' ')
    lines += joined.splitlines()
    lines += re.findall(r'`((?:python scripts/|ros2 run )[^`]+)`', text)
    commands = [re.sub(r'\s#.*$', '', c).strip() for c in lines
                if c.startswith(('python scripts/', 'ros2 '))]
    return [c for c in commands if not TEMPLATE.search(c)]


def _all_commands():
    out = []
    for page in PAGES:
        with open(os.path.join(ROOT, page)) as f:
            out += [(page, c) for c in _commands(f.read())]
    return out


@functools.lru_cache(maxsize=None)
def _help(script: str) -> str:
    result = subprocess.run([sys.executable, os.path.join(ROOT, 'scripts', script), '--help'],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f'{script} --help: {result.stderr}'
    return result.stdout


COMMANDS = _all_commands()


def test_the_docs_show_commands_of_both_kinds():
    kinds = {c.split()[0] for _, c in COMMANDS}
    assert kinds == {'python', 'ros2'} and len(COMMANDS) > 30, COMMANDS


@pytest.mark.parametrize('page, command', [pc for pc in COMMANDS if pc[1].startswith('python')])
def test_script_flags_exist(page, command):
    script = command.split()[1].split('/', 1)[1]
    assert os.path.exists(os.path.join(ROOT, 'scripts', script)), f'{page}: {command}'
    flags = {re.sub(r'[\[\]=].*$', '', t.strip('[]')) for t in command.split()
             if t.strip('[').startswith('--')}
    listed = set(re.findall(r'(--[a-z][a-z0-9-]*)', _help(script)))
    assert not flags - listed, f'{page}: `{command}` uses {sorted(flags - listed)}'


RUNS = [pc for pc in COMMANDS if pc[1].startswith('ros2 run ')]


@pytest.mark.parametrize('page, command', [pc for pc in RUNS
                                           if tuple(pc[1].split()[2:4]) not in CLIS])
def test_ros2_run_names_declared_parameters(page, command):
    tokens = command.split()
    node = (tokens[2], tokens[3])
    assert node in NODES, f'{page}: `{command}`: no such node'
    names = re.findall(r'-p\s+["\']?([A-Za-z_][A-Za-z0-9_.]*):=', command)
    unknown = [n for n in names if n not in NODES[node] and n not in ROS_PARAMETERS
               and not n.startswith(QOS_OVERRIDES)]
    assert not unknown, f'{page}: `{command}` sets undeclared {unknown}'


@pytest.mark.parametrize('page, command', [pc for pc in RUNS
                                           if tuple(pc[1].split()[2:4]) in CLIS])
def test_ros2_run_programs_name_their_flags(page, command):
    import importlib
    listed = set(re.findall(r'(--[a-z][a-z0-9-]*)', importlib.import_module(
        CLIS[tuple(command.split()[2:4])]).parser().format_help()))
    flags = {re.sub(r'[\[\]=].*$', '', t.strip('[]')) for t in command.split()
             if t.strip('[').startswith('--')}
    assert not flags - listed, f'{page}: `{command}` uses {sorted(flags - listed)}'


@pytest.mark.parametrize('page, command', [
    pc for pc in COMMANDS if pc[1].startswith('ros2 ')
    and pc[1].split()[1] not in ('run', 'pkg')])
def test_ros2_verbs_parse_as_written(page, command):
    from metampc_ros2cli.cli import parser
    try:
        parser().parse_args(shlex.split(command)[1:])
    except SystemExit:
        pytest.fail(f'{page}: `{command}` is not a valid ros2 command line')


LAUNCH_FILES = sorted(glob.glob(os.path.join(ROOT, 'src', 'metampc_bringup', 'launch',
                                             '*.launch.yaml')))


@pytest.mark.parametrize('path', LAUNCH_FILES, ids=os.path.basename)
def test_shipped_launch_files_name_declared_parameters(path):
    from metampc_ros2cli.launch_yaml import read
    with open(path) as f:
        nodes = read(f.read(), [])
    assert nodes
    for node in nodes:
        assert (node.pkg, node.exec) in NODES, f'{path}: no such node {node.pkg} {node.exec}'
        unknown = [n for n in node.params if n not in NODES[node.pkg, node.exec]
                   and n not in ROS_PARAMETERS]
        assert not unknown, f'{path}: {node.exec} sets undeclared {unknown}'


LAUNCHES = [(page, c) for page, c in COMMANDS if c.startswith('ros2 launch ')]


def test_the_docs_launch_both_shipped_files():
    launched = {c.split()[3] for _, c in LAUNCHES}
    assert launched == {os.path.basename(p) for p in LAUNCH_FILES}, LAUNCHES


@pytest.mark.parametrize('page, command', LAUNCHES)
def test_documented_launches_run_their_graph_and_stop_on_ctrl_c(page, command, probe, tmp_path):
    """The code block of the page that holds the command, run as written (its scratch folder
    /tmp/run1 moved into the test's): the launched graph turns y into u; Ctrl-C of the
    launcher stops every node it started, and the launcher exits 0."""
    from metampc_bringup.orchestration.procfs import pids_with_env
    from metampc_msgs.msg import ControlInput
    with open(os.path.join(ROOT, page)) as f:
        block, = [b for b in re.findall(r'```bash\n(.*?)```', f.read(), flags=re.S)
                  if command in b.replace('\\\n', ' ')]
    logs = str(tmp_path / 'log')
    block = block.replace('/tmp/run1', str(tmp_path / 'run1'))
    inputs = []
    probe.node.create_subscription(ControlInput, 'u', inputs.append, 10)
    shell = subprocess.Popen(['bash', '-c', f'source scripts/env.sh\n{block}'], cwd=ROOT,
                             env={**os.environ, 'ROS_LOG_DIR': logs},
                             stdout=open(tmp_path / 'out.log', 'w'), stderr=subprocess.STDOUT,
                             start_new_session=True)
    try:
        probe.wait_for(lambda: len(inputs) > 3, 180.0, 'u from the launched controller')
        launcher, = [p for p in pids_with_env({'ROS_LOG_DIR': logs}) if b'launch' in open(
            f'/proc/{p}/cmdline', 'rb').read().split(b'\0')]
        shims = set(pids_with_env({'METAMPC_LIFELINE': str(launcher)}))
        nodes = {p for s in shims for p in pids_with_env({'METAMPC_LIFELINE': str(s)})}
        assert len(shims) == len(nodes) >= 3, (shims, nodes)
        os.kill(launcher, signal.SIGINT)
        assert shell.wait(120) == 0     # the block's last command: the launcher
        out = (tmp_path / 'out.log').read_text()
        assert 'user interrupted with ctrl-c' in out and 'process has died' not in out, out
        assert not (shims | nodes) & set(pids_with_env({'ROS_LOG_DIR': logs})), out
    finally:     # the block's other jobs (bridge.md's robot) too
        with contextlib.suppress(ProcessLookupError):
            os.killpg(shell.pid, signal.SIGKILL)
        shell.wait()
