"""The suite's orphan check (conftest.pytest_sessionfinish) fails a session that leaves a
process running, names it and kills it; a clean session passes. Run on a session of its own
(a pytest in a subprocess, with this checkout's conftest as a plugin)."""
import os
import signal
import subprocess
import sys
import time

from metampc_testing import alive, session_pids

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LEAVES = '''
import atexit
import subprocess


def test_leaves_a_process_behind():
    child = subprocess.Popen(['sleep', '60'], start_new_session=True)
    print('PID', child.pid)
    with open(f'/proc/{child.pid}/environ', 'rb') as f:
        print('ITS SESSION VARIABLE', [v for v in f.read().split(b'\\0')
                                       if v.startswith(b'METAMPC_TEST_SESSION=')])
    # Once (CI, under load) the check found nothing: was the process still running then?
    atexit.register(lambda: print('AT EXIT: its exit status', child.poll(), flush=True))
'''
CLEAN = '''
import subprocess


def test_stops_what_it_started():
    proc = subprocess.Popen(['sleep', '60'], start_new_session=True)
    proc.kill()
    proc.wait()
'''


WAITS = '''
import os
import subprocess
import sys
import time

from metampc_bringup.orchestration.lifeline import child_env


def test_starts_a_child_and_waits():
    child = subprocess.Popen([sys.executable, '-c',
                              'from metampc_bringup.orchestration.lifeline import hold; '
                              'hold(); import time; time.sleep(60)'], env=child_env())
    with open(os.environ['PIDS_FILE'] + '.tmp', 'w') as f:
        f.write(f'{os.getpid()} {child.pid}')
    os.rename(os.environ['PIDS_FILE'] + '.tmp', os.environ['PIDS_FILE'])
    time.sleep(60)
'''


def _command(tmp_path, body: str, *args: str) -> list:
    path = tmp_path / 'test_inner.py'
    path.write_text(body)
    return [sys.executable, '-m', 'pytest', '-q', '-p', 'conftest', '-p', 'no:cacheprovider',
            '--rootdir', str(tmp_path), *args, str(path)]


def _env(**extra: str) -> dict:
    """test/ on the path, as pytest.ini's pythonpath puts it for the suite (the conftest's
    plugins and helpers live there)."""
    return {**os.environ, **extra, 'PYTHONPATH': os.pathsep.join(
        [os.path.join(ROOT, 'test')] + os.environ.get('PYTHONPATH', '').split(os.pathsep))}


def session(tmp_path, body: str) -> subprocess.CompletedProcess:
    return subprocess.run(_command(tmp_path, body, '-s'), cwd=ROOT, capture_output=True,
                          text=True, timeout=120, env=_env())


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


def test_a_killed_pytest_takes_its_xdist_worker_and_the_worker_s_children_with_it(tmp_path):
    """SIGKILL of a `pytest -n 1` while its test runs: 5 s later neither the worker nor the
    process its test started runs (a worker outlived its pytest, with a controller)."""
    pids_file = tmp_path / 'pids'
    proc = subprocess.Popen(_command(tmp_path, WAITS, '-n', '1'), cwd=ROOT,
                            env=_env(PIDS_FILE=str(pids_file)), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60.0
        while not pids_file.exists():
            assert proc.poll() is None and time.monotonic() < deadline, 'the test never ran'
            time.sleep(0.05)
        worker, child = map(int, pids_file.read_text().split())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        time.sleep(5.0)
        assert [pid for pid in (worker, child) if alive(pid)] == []
    finally:
        for pid in session_pids(proc):
            os.kill(pid, signal.SIGKILL)
        for pid in [int(p) for p in (pids_file.read_text().split()
                                     if pids_file.exists() else []) if alive(int(p))]:
            os.kill(pid, signal.SIGKILL)
