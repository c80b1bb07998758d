"""A benchmark's helper process: its stdout, and nothing of it left running after the block."""
import os
import textwrap
import time

import pytest

from metampc_bringup.orchestration.script_child import last_json_line, script_child


def _script(tmp_path, body: str) -> str:
    path = tmp_path / 'child.py'
    path.write_text(textwrap.dedent(body))
    return str(path)


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_reads_the_childs_output_and_arguments(tmp_path):
    script = _script(tmp_path, '''
        import json, sys
        print('start', flush=True)
        print(json.dumps({'args': sys.argv[1:]}))
    ''')
    with script_child(script, ['--rate', '5']) as child:
        assert child.stdout.readline() == 'start\n'
        # the rest from the same buffered reader: communicate(timeout) reads the pipe's fd
        # directly and would miss what readline() had already buffered
        out = child.stdout.read()
        child.wait(30)
    assert last_json_line(out) == {'args': ['--rate', '5']}
    assert child.returncode == 0


def test_a_running_child_gets_sigint(tmp_path):
    script = _script(tmp_path, '''
        import time
        masks = [line.strip() for line in open('/proc/self/status')
                 if line.startswith(('SigBlk', 'SigIgn', 'SigCgt'))]
        try:
            print('ready', *masks, flush=True)     # inside: the SIGINT may come right after it
            time.sleep(60)
        except KeyboardInterrupt:
            raise SystemExit(3)
    ''')
    with script_child(script, []) as child:
        ready = child.stdout.readline()     # with the child's signal masks, should this fail
        assert ready.startswith('ready')
    assert child.returncode == 3, ready


def test_a_child_deaf_to_sigint_and_its_own_child_are_killed(tmp_path):
    script = _script(tmp_path, '''
        import signal, subprocess, sys, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        grandchild = subprocess.Popen(['sleep', '60'])
        print(grandchild.pid, flush=True)
        time.sleep(60)
    ''')
    start = time.monotonic()
    with script_child(script, [], stop_s=0.5) as child:
        grandchild = int(child.stdout.readline())
    assert child.returncode == -9 and time.monotonic() - start < 20
    deadline = time.monotonic() + 5
    while not _gone(grandchild) and time.monotonic() < deadline:   # reaped by init
        time.sleep(0.05)
    assert _gone(grandchild)


def test_last_json_line():
    assert last_json_line('noise\n{"a": 1}\n\n') == {'a': 1}
    with pytest.raises(IndexError):
        last_json_line('  \n')
    with pytest.raises(ValueError):
        last_json_line('{"a": 1}\nnot json')
