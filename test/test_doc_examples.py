"""The worked examples of the docs, run as written (only scratch folders are moved into the test's
temporary folder): docs/learner.md's plant + learner commands and its service client,
docs/adaptation.md's recipe by hand (its meta-model made, then the loop run on it)."""
import os
import re
import signal
import subprocess
import sys
import time

from metampc_testing import session_pids

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _blocks(page: str, section: str):
    """The fenced code blocks of `section` (a '## ' heading) of docs/`page`: (language, text)."""
    with open(os.path.join(ROOT, 'docs', page)) as f:
        text = f.read()
    body = text.split(f'\n## {section}\n', 1)[1].split('\n## ', 1)[0]
    return re.findall(r'```(\w*)\n(.*?)```', body, flags=re.S)


def test_learner_md_example_meta_trains_buffers_losslessly_and_adapts(tmp_path):
    blocks = _blocks('learner.md', 'Examples')
    shell = [text for lang, text in blocks if lang == ''][0]
    client = [text for lang, text in blocks if lang == 'python'][0]
    assert 'ros2 run metampc_plant plant' in shell and 'meta_train' in client
    shell = shell.replace('/tmp/metampc-ckpt', str(tmp_path / 'ckpt'))
    nodes = subprocess.Popen(['bash', '-c', shell], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        run = subprocess.run([sys.executable, '-c', client], cwd=ROOT, capture_output=True,
                             text=True, timeout=600)
    finally:
        os.killpg(nodes.pid, signal.SIGINT)
        try:
            log = nodes.communicate(timeout=60)[0]
        except subprocess.TimeoutExpired:
            os.killpg(nodes.pid, signal.SIGKILL)
            log = nodes.communicate()[0]
    out = run.stdout
    assert run.returncode == 0, out + run.stderr + log
    # The answers, without the progress lines printed between them.
    lines = [line for line in out.splitlines() if not line.startswith(('meta_train ', 'adapt ',
                                                                       'done '))]
    assert lines[0].startswith('buffering (re)started'), out
    assert re.match(r'True imaml meta-model v1: 100 outer steps ', lines[1]), out
    # D_target filled while the learner trained (up to 300 samples), none lost on the way.
    kept = re.fullmatch(r'buffering stopped: (\d+) samples kept \(0 skipped, 0 lost\)', lines[2])
    assert kept and int(kept.group(1)) >= 100, out
    assert lines[3].startswith('True imaml model v2 (stage adapted): 20 steps on '), out
    assert sorted(os.listdir(tmp_path / 'ckpt')) == ['adapted_imaml_v2.pt', 'meta_imaml_v1.pt']
    assert nodes.returncode == 0 and 'Traceback' not in log, log
    assert session_pids(nodes) == []


def _start(command: str, log):
    """One terminal of a recipe: `command` in a shell of its own session, output to `log`."""
    return subprocess.Popen(['bash', '-c', f'source scripts/env.sh && exec {command}'],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _stop(proc) -> int:
    """Ctrl-C, as in the terminal; the exit status (SIGKILL after 60 s: a failure)."""
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return proc.wait(60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return -9


def _wait_for(path, text: str, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with open(path) as f:
            out = f.read()
        if text in out:
            return out
        time.sleep(0.5)
    raise AssertionError(f'{text!r} not in {path} within {timeout} s:\n{out}')


# The recipe at a small size: a short meta-training, the plant 10 times faster.
SMALL_META = ' -p n_systems:=20 -p iterations:=20'
FASTER = ('real_time_factor:=1.0', 'real_time_factor:=10.0')


def test_adaptation_md_recipe_makes_its_meta_model_and_runs_the_loop_on_it(tmp_path):
    make, loop = [text for lang, text in _blocks('adaptation.md', 'By hand') if lang == 'bash']
    folder = str(tmp_path / 'adapt')
    make = make.replace('/tmp/metampc-adapt', folder).splitlines()
    learner_cmd = [c for c in make if c.startswith('ros2 run metampc_learner')]
    call_cmd = [c for c in make if c.startswith('ros2 service call /meta_train')]
    assert len(learner_cmd) == len(call_cmd) == 1, make
    names = ('meta', 'call', 'plant', 'learner', 'controller')
    logs = {name: tmp_path / f'{name}.log' for name in names}
    learner = _start(learner_cmd[0] + SMALL_META, open(logs['meta'], 'w'))
    call = _start(call_cmd[0], open(logs['call'], 'w'))
    try:
        # The learner's line, not the call's answer: a first answer can be lost (nodes.md).
        _wait_for(logs['meta'], 'imaml meta-model v1: 20 outer steps', 600.0)
    finally:
        codes = [_stop(call), _stop(learner)]
    assert codes[1] == 0, logs['meta'].read_text()
    meta_pt = os.path.join(folder, 'meta_imaml_v1.pt')
    assert os.listdir(folder) == ['meta_imaml_v1.pt']

    commands = [c.replace(*FASTER) for c in loop.replace('/tmp/metampc-adapt', folder)
                .splitlines() if c.startswith('ros2 run')]
    assert [c.split()[2:4] for c in commands] == [['metampc_plant', 'plant'], [
        'metampc_learner', 'learner'], ['metampc_controller', 'controller']], commands
    assert meta_pt in commands[1] and FASTER[1] in commands[0]
    procs = {name: _start(c, open(logs[name], 'w'))
             for name, c in zip(('plant', 'learner', 'controller'), commands)}
    try:
        _wait_for(logs['learner'], f'loaded imaml meta-model {meta_pt!r}', 300.0)
        _wait_for(logs['controller'], 'model version 1 (imaml, meta', 300.0)
        # Past theta's step at t = 30 s (step 300): the loop ran on the meta-model.
        _wait_for(logs['plant'], 'theta [-0.5] from step 30', 300.0)
    finally:
        codes = {name: _stop(procs[name]) for name in ('plant', 'controller', 'learner')}
    out = '\n'.join(f'{name}: {path.read_text()}' for name, path in logs.items())
    assert codes == {'plant': 0, 'controller': 0, 'learner': 0}, out
    assert 'Traceback' not in out, out
    assert all(session_pids(p) == [] for p in [learner, call, *procs.values()])
