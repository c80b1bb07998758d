"""Each node started with `ros2 run` joins the graph and exits 0 on SIGINT, with no traceback."""
import os
import signal
import time

import pytest

from metampc_testing import session_pids

NODES = [('metampc_plant', 'plant'), ('metampc_controller', 'controller'),
         ('metampc_learner', 'learner'), ('metampc_recording', 'recorder')]


@pytest.mark.parametrize('pkg,exe', NODES, ids=[exe for _, exe in NODES])
def test_node_starts_and_stops_cleanly(procs, probe, tmp_path, pkg, exe):
    params = {'output': str(tmp_path / 'rec.mcap')} if exe == 'recorder' else {}
    proc = procs.start(pkg, exe, params=params)
    probe.wait_for_node(exe, timeout=30.0)
    assert proc.poll() is None
    code = procs.interrupt(proc)
    out = procs.output(proc)
    assert code == 0, out
    assert 'Traceback' not in out, out
    assert session_pids(proc) == [], 'a process of the node outlived ros2 run'


def test_sigusr1_prints_every_thread_stack_and_the_node_goes_on(procs, probe):
    """How a hang is diagnosed (ProcessGroup.interrupt does it before SIGKILL): the node's
    threads are printed, and it still stops cleanly afterwards."""
    proc = procs.start('metampc_plant', 'plant')
    probe.wait_for_node('plant', timeout=30.0)
    (node,) = [pid for pid in session_pids(proc) if pid != proc.pid]
    os.kill(node, signal.SIGUSR1)
    # The dump streams in while it is read: wait for the main thread's frames themselves.
    probe.wait_for(lambda: 'most recent call first' in procs.output(proc)
                   and 'plant_node.py' in procs.output(proc), 30.0,
                   "a stack dump with the main thread's frames (plant_node.py)")
    assert proc.poll() is None
    assert procs.interrupt(proc) == 0


def test_a_learner_expecting_another_dt_than_the_plants_refuses_at_start_up(procs, probe):
    """The plant's plant_info is the one source of truth for dt: a learner whose source systems
    sample at another dt ends with one line and exit status 2 (not at its first adapt)."""
    plant = procs.start('metampc_plant', 'plant', params={'dt': 0.1})
    probe.wait_for_node('plant', timeout=30.0)
    learner = procs.start('metampc_learner', 'learner', params={'dt': 0.2})
    probe.wait_for(lambda: learner.poll() is not None, 60.0, 'the learner to exit')
    out = procs.output(learner)
    assert learner.returncode == 2, out
    assert 'invalid parameter: dt: the plant samples at dt = 0.1 s' in out, out
    assert 'Traceback' not in out, out
    assert procs.interrupt(plant) == 0


def _maps(pid: int, library: str) -> bool:
    try:
        with open(f'/proc/{pid}/maps') as maps:
            return library in maps.read()
    except OSError:       # gone, or not ours to read
        return False


# A library each node's module imports (0.5-2 s) before any node exists.
IMPORTING = [('metampc_controller', 'controller', 'osqp'), ('metampc_learner', 'learner', 'torch')]


@pytest.mark.parametrize('pkg,exe,library', IMPORTING, ids=[exe for _, exe, _ in IMPORTING])
def test_ctrl_c_while_the_node_module_imports_is_a_clean_exit(procs, pkg, exe, library):
    """Ctrl-C while the controller or the learner imports its libraries, before any node
    exists, is exit 0 without a traceback too (metampc_common.entry), as the docs promise."""
    proc = procs.start(pkg, exe)
    # Once the library is mapped, metampc_common.entry's handler is in place: a SIGINT before
    # it, inside the interpreter's start or the console script's own imports, is a plain
    # KeyboardInterrupt (a fixed 0.3 s landed there once under load).
    deadline = time.monotonic() + 60.0
    while not any(_maps(pid, library) for pid in session_pids(proc) if pid != proc.pid):
        assert proc.poll() is None and time.monotonic() < deadline, procs.output(proc)
        time.sleep(0.01)
    code = procs.interrupt(proc)
    out = procs.output(proc)
    assert code == 0, out
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out
