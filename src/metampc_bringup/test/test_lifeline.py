"""A process dies with whoever started it (metampc_bringup.orchestration.lifeline), SIGKILL
included; a node keeps its domain claimed until it has ended; a process nobody of ours started
is left alone.

Each test starts a middle process that starts a child, SIGKILLs the middle one and watches the
child through /proc (a zombie counts as ended: it runs nothing and holds no file).
"""
import fcntl
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time

import pytest

from metampc_bringup.orchestration.lifeline import ENV
from metampc_bringup.orchestration.processes import session_pids
from metampc_testing import alive

GONE_S = 5.0    # the bound: nothing of a killed run left 5 s later


def _wait_gone(pids, timeout: float = GONE_S) -> list:
    """The pids still running after `timeout` s (empty as soon as none is)."""
    deadline = time.monotonic() + timeout
    while any(map(alive, pids)) and time.monotonic() < deadline:
        time.sleep(0.02)
    return [p for p in pids if alive(p)]


def _middle(body: str, env=None) -> subprocess.Popen:
    """`python -c body` in a session of its own, stdout piped; body prints one JSON line."""
    return subprocess.Popen([sys.executable, '-c', textwrap.dedent(body)], text=True,
                            stdout=subprocess.PIPE, start_new_session=True, env=env)


def _kill_all(pids) -> None:
    for pid in pids:
        if alive(pid):
            os.kill(pid, signal.SIGKILL)


SLEEPER = ('import sys, time; from metampc_bringup.orchestration.lifeline import hold; '
           'print(hold(), flush=True); time.sleep(60)')


@pytest.mark.parametrize('spawned', [True, False])
def test_a_child_dies_with_its_killed_parent_only_when_a_spawner_of_ours_asked(spawned):
    """With the spawner's variable: SIGTERM to the child when the parent is SIGKILLed. Without
    it (a user's `nohup ros2 run ... &`): no lifeline, the child lives on."""
    middle = _middle(f'''
        import json, subprocess, sys, time
        from metampc_bringup.orchestration.lifeline import child_env
        child = subprocess.Popen([sys.executable, '-c', {SLEEPER!r}], stdout=subprocess.PIPE,
                                 text=True, env=child_env() if {spawned} else None)
        held = child.stdout.readline().strip()
        print(json.dumps({{'pid': child.pid, 'held': held}}), flush=True)
        time.sleep(60)
    ''')
    child = None
    try:
        line = json.loads(middle.stdout.readline())
        child = line['pid']
        assert line['held'] == str(spawned)
        middle.kill()
        middle.wait()
        left = _wait_gone([child], GONE_S if spawned else 1.0)
        assert left == ([] if spawned else [child])
    finally:
        _kill_all([middle.pid] + ([child] if child else []))
        middle.stdout.close()


def test_a_child_whose_parent_is_gone_before_it_asked_ends_at_once():
    """The race between fork and prctl: the variable names a pid that is no longer the parent
    (the child was re-parented), so the child sends itself the signal at once."""
    other = os.getppid()    # a live process that is not the child's parent
    env = {**os.environ, ENV: str(other)}
    start = time.monotonic()
    proc = subprocess.run([sys.executable, '-c', SLEEPER], env=env, capture_output=True,
                          timeout=30)
    assert proc.returncode == -signal.SIGTERM, proc.stderr
    assert time.monotonic() - start < 20.0


def test_a_node_dies_with_the_killed_process_that_started_it_and_frees_the_domain_last(
        tmp_path):
    """A ProcessGroup's node (its `ros2 run` and the node) is gone within 5 s of a SIGKILL of
    the process that started it; the domain that process claimed stays locked until then."""
    middle = _middle(f'''
        import json, time
        from metampc_bringup.orchestration.domain import isolate
        from metampc_bringup.orchestration.processes import ProcessGroup, session_pids
        domain = isolate()
        group = ProcessGroup({str(tmp_path)!r})
        proc = group.start('metampc_plant', 'plant', params={{'mode': 'realtime',
                                                              'rate_hz': 20.0}})
        deadline = time.monotonic() + 60
        while len(session_pids(proc)) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        print(json.dumps({{'domain': domain, 'session': proc.pid}}), flush=True)
        time.sleep(120)
    ''')
    pids = []
    try:
        line = json.loads(middle.stdout.readline())
        pids = session_pids(line['session'])
        assert len(pids) == 2       # the `ros2 run` shim and the node
        middle.kill()
        middle.wait()
        lock = os.path.join(tempfile.gettempdir(), f'metampc-ros-domain-{line["domain"]}.lock')
        with open(lock, 'w') as handle:
            deadline = time.monotonic() + GONE_S
            while True:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError:
                    assert time.monotonic() < deadline, 'the domain is still claimed'
                    time.sleep(0.02)
            # Free means nothing of the killed run is left in it.
            assert [p for p in pids if alive(p)] == []
    finally:
        _kill_all([middle.pid] + pids)
        middle.stdout.close()
