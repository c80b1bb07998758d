"""Each node started with `ros2 run` joins the graph and exits 0 on SIGINT, with no traceback."""
import pytest

from metampc_testing import session_pids

NODES = [('metampc_plant', 'plant'), ('metampc_controller', 'controller'),
         ('metampc_learner', 'learner'), ('metampc_bringup', 'recorder')]


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
    assert session_pids(proc.pid) == [], 'a process of the node outlived ros2 run'
