"""The suite's orphan check (conftest.pytest_sessionfinish) fails a session that leaves a
process running, names it and kills it; a clean session passes. Run on a session of its own
(a pytest in a subprocess, with this checkout's conftest as a plugin)."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LEAVES = '''
import subprocess


def test_leaves_a_process_behind():
    print('PID', subprocess.Popen(['sleep', '60'], start_new_session=True).pid)
'''
CLEAN = '''
import subprocess


def test_stops_what_it_started():
    proc = subprocess.Popen(['sleep', '60'], start_new_session=True)
    proc.kill()
    proc.wait()
'''


def session(tmp_path, body: str) -> subprocess.CompletedProcess:
    path = tmp_path / 'test_inner.py'
    path.write_text(body)
    return subprocess.run([sys.executable, '-m', 'pytest', '-q', '-s', '-p', 'conftest',
                           '-p', 'no:cacheprovider', '--rootdir', str(tmp_path), str(path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_a_session_that_leaves_a_process_running_fails_and_the_process_is_killed(tmp_path):
    done = session(tmp_path, LEAVES)
    pid = int(done.stdout.split('PID ')[1].split()[0])
    assert done.returncode == 1, done.stdout + done.stderr
    assert f'ORPHAN left running after the suite: pid {pid}: sleep 60' in done.stdout
    assert not os.path.exists(f'/proc/{pid}') or open(f'/proc/{pid}/stat').read().rsplit(
        ')', 1)[1].split()[0] == 'Z'


def test_a_clean_session_passes(tmp_path):
    done = session(tmp_path, CLEAN)
    assert done.returncode == 0 and 'ORPHAN' not in done.stdout, done.stdout + done.stderr
