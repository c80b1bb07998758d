"""The worked examples of the docs, run as written (only scratch folders are moved into the test's
temporary folder): docs/learner.md's plant + learner commands and its service client."""
import os
import re
import signal
import subprocess
import sys

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
    assert session_pids(nodes.pid) == []
