"""The experiment split across "hosts": network namespaces joined by a bridge (issue 10).

The split runs need root and iproute2's `ip` (only root may create network namespaces); without
them those tests are skipped with that reason, and the refusal is tested instead.
"""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from metampc_bringup.orchestration import netns
from metampc_bringup.experiment import run_experiment
from metampc_bringup.experiment_config import load

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')
HOSTS = 'plant|controller,controller_nmpc|learner,recorder'
needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which('ip') is None,
    reason='network namespaces can only be created by root, with iproute2 (ip)')


def root_links():
    """Interface names of the machine's own network namespace."""
    out = subprocess.run(['ip', '-o', 'link', 'show'], capture_output=True, text=True).stdout
    return sorted(line.split(':')[1].strip() for line in out.splitlines())


def ours(pid: int):
    """The network namespaces that process `pid` made (netns.NAME_PREFIX<pid>-...)."""
    return [n for n in netns.namespaces() if n.startswith(f'{netns.NAME_PREFIX}{pid}-')]


def test_parse_hosts_and_its_errors():
    assert netns.parse_hosts(HOSTS) == [['plant'], ['controller', 'controller_nmpc'],
                                        ['learner', 'recorder']]
    assert netns.parse_hosts(' plant | learner ') == [['plant'], ['learner']]
    for text, message in [('plant|planet', "unknown node(s) ['planet']"),
                          ('plant|plant,learner', "['plant'] placed more than once"),
                          ('plant||learner', 'every host needs at least one node'),
                          ('', 'every host needs at least one node')]:
        with pytest.raises(netns.NetnsError, match=re.escape(message)):
            netns.parse_hosts(text)


def test_without_root_the_split_is_refused_clearly(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(netns.os, 'geteuid', lambda: 1000)
    out = tmp_path / 'run'
    with pytest.raises(netns.NetnsError, match='only root may create'):
        run_experiment(load(CI_CONFIG), str(out), progress=False, hosts=[['plant']])
    assert not out.exists(), 'nothing is created before the refusal'
    sys.path.insert(0, os.path.join(ROOT, 'scripts'))
    try:
        import run_experiment as script
    finally:
        sys.path.pop(0)
    assert script.main(['--config', CI_CONFIG, '--out', str(out), '--hosts', HOSTS]) == 2
    err = capsys.readouterr().err
    assert 'run_experiment: placing nodes on hosts needs network namespaces' in err, err
    assert 'run as root, or run the nodes on real machines' in err


def _seed_report(out: str) -> dict:
    with open(os.path.join(out, 'seed_0', 'report.json')) as f:
        return json.load(f)


@needs_root
def test_ci_experiment_over_three_namespaces_gives_the_one_host_report(tmp_path, caplog):
    """Lockstep runs are deterministic: the CI experiment split plant | controllers | learner +
    recorder gives the report of one host (tracking RMSE and cost of every method, meta-
    training and adaptation loss curves) to float rounding; every host's link carried the
    traffic; no namespace or link is left behind."""
    links = root_links()
    caplog.set_level('INFO', logger='metampc.netns')
    one = str(tmp_path / 'one')
    split = str(tmp_path / 'split')
    run_experiment(load(CI_CONFIG), one, progress=False)
    run_experiment(load(CI_CONFIG), split, progress=False, hosts=netns.parse_hosts(HOSTS))
    a, b = _seed_report(one), _seed_report(split)
    assert set(a['methods']) == set(b['methods']) == set(load(CI_CONFIG).methods)
    for method, ra in a['methods'].items():
        rb = b['methods'][method]
        for key in ('rmse', 'cost', 'samples'):
            np.testing.assert_allclose(rb['tracking']['tracking'][key],
                                       ra['tracking']['tracking'][key], rtol=1e-9,
                                       err_msg=f'{method} tracking {key}')
        for phase in ('meta_train', 'adapt'):
            if phase in ra:
                np.testing.assert_allclose(rb[phase]['loss_curve'], ra[phase]['loss_curve'],
                                           rtol=1e-9, err_msg=f'{method} {phase}')
    # Each host sent and received its share of the traffic through its link.
    traffic = {m.group(1): (int(m.group(2)), int(m.group(3)))
               for m in (re.match(r'(\S+): sent (\d+) kB in \d+ packets, received (\d+) kB',
                                  r.getMessage()) for r in caplog.records) if m}
    assert len(traffic) == 4, caplog.text
    assert all(sent > 50 and received > 50 for sent, received in traffic.values()), traffic
    assert ours(os.getpid()) == [] and root_links() == links


@needs_root
def test_ctrl_c_of_a_split_run_removes_every_namespace(tmp_path):
    """SIGINT once the nodes run in their namespaces: exit 130, every node stopped, every
    namespace (and with it every link) deleted, the machine's links as before."""
    links = root_links()
    out = tmp_path / 'run'
    proc = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--out', str(out), '--no-progress', '--hosts', HOSTS],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)

    def node_pids():
        """Pids of the processes in each host's namespace (empty list: none yet)."""
        return [subprocess.run(['ip', 'netns', 'pids', ns], capture_output=True,
                               text=True).stdout.split()
                for ns in ours(proc.pid) if re.search(r'-h\d+$', ns)]
    try:
        deadline = time.monotonic() + 120.0
        while not (len(node_pids()) == 3 and all(node_pids())):
            assert proc.poll() is None and time.monotonic() < deadline, 'no nodes in the hosts'
            time.sleep(0.2)
        time.sleep(1.0)     # the nodes of every host started: interrupt during the start-up
        nodes = [int(pid) for pids in node_pids() for pid in pids]
        os.kill(proc.pid, signal.SIGINT)
        output = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, output
    assert 'interrupted; nodes stopped' in output
    assert ours(proc.pid) == [] and root_links() == links
    alive = [pid for pid in nodes if os.path.exists(f'/proc/{pid}')]
    assert alive == [], 'a node outlived the interrupted run'
