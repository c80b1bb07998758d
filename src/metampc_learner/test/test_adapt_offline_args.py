"""adapt_offline's command line refuses bad paths in one line, exit 2, before any work and
before torch is imported (issue 52: an --out into a missing folder ran the whole adaptation,
then a 48-line traceback; an existing --out was overwritten; a missing file took 5 s to refuse,
torch imported first)."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
MAPPING = os.path.join(ROOT, 'examples', 'joint_robot', 'mapping.yaml')
PROBE = '''
import sys
from metampc_learner.adapt_offline import main
rc = main(sys.argv[1:])
print(rc, 'torch' in sys.modules)
'''


@pytest.mark.parametrize('case, message', [
    ('recording', '{tmp}/missing.mcap: no such recording'),
    ('mapping', '{tmp}/missing.yaml: no such mapping file'),
    ('checkpoint', '{tmp}/missing.pt: no such checkpoint'),
    ('out exists', '--out {tmp}/adapted.pt exists; results are never overwritten'),
    ('out folder', '--out {tmp}/nowhere/adapted.pt: the folder {tmp}/nowhere does not exist'),
])
def test_bad_paths_are_refused_before_torch_is_imported(case, message, tmp_path):
    files = {name: tmp_path / name for name in ('robot.mcap', 'meta.pt')}
    for path in files.values():
        path.write_text('')
    argv = [str(files['robot.mcap']), MAPPING, str(files['meta.pt']), '--out',
            str(tmp_path / 'adapted.pt'), '--method', 'imaml', '--rule', 'gauss_newton']
    if case == 'recording':
        argv[0] = str(tmp_path / 'missing.mcap')
    elif case == 'mapping':
        argv[1] = str(tmp_path / 'missing.yaml')
    elif case == 'checkpoint':
        argv[2] = str(tmp_path / 'missing.pt')
    elif case == 'out exists':
        (tmp_path / 'adapted.pt').write_text('kept')
    else:
        argv[4] = str(tmp_path / 'nowhere' / 'adapted.pt')
    run = subprocess.run([sys.executable, '-c', PROBE, *argv], capture_output=True, text=True,
                         timeout=120)
    assert run.stdout == '2 False\n', run.stdout + run.stderr
    assert run.stderr == f'adapt_offline: error: {message.format(tmp=tmp_path)}\n'
    if case == 'out exists':
        assert (tmp_path / 'adapted.pt').read_text() == 'kept'


def test_an_unknown_method_or_rule_is_argparse_s_error(tmp_path, capsys):
    from metampc_learner.adapt_offline import main
    (tmp_path / 'r.mcap').write_text('')
    for option in ('--method', '--rule'):
        with pytest.raises(SystemExit) as end:
            main([str(tmp_path / 'r.mcap'), MAPPING, str(tmp_path / 'r.mcap'), '--out',
                  str(tmp_path / 'a.pt'), option, 'bogus'])
        assert end.value.code == 2
        assert f"argument {option}: invalid choice: 'bogus' (choose from " in \
            capsys.readouterr().err
