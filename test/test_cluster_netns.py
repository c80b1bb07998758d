"""A TLS dask cluster over network namespaces (issue 33): `dask scheduler` on one "host", a
one-slot `dask worker` on each of two others, run_experiment.py --scheduler tls://... in a
fourth, with certificates made here (as test_netns splits the nodes of one experiment).

Two seeds of the CI experiment give, seed for seed, the reports of ``--jobs 1``; a worker
SIGKILLed in the middle of a seed changes nothing but the time (its seed runs again); a client
without the cluster's certificate is refused by the scheduler. Every address is inside the
namespaces made here (10.201.0.0/24 behind their own bridge); nothing of the test outlives it.
Needs root and iproute2 (skipped otherwise, as test_netns).
"""
import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from typing import Callable

import pytest

from metampc_bringup.orchestration import netns
from metampc_bringup.orchestration.lifeline import ENV as LIFELINE
from metampc_testing import (alive, dask_cluster, make_certificates, per_seed_reports,
                             timing_free)
from test_netns import needs_root, ours, root_links

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, 'scripts', 'run_experiment.py')
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')
# Two seeds, one per worker slot (queued seeds: test_experiment's scheduler case).
RUN = ['--config', CI_CONFIG, '--no-progress', '--methods', 'maml', '--seeds', '2']
PORT = 8786
JOIN_S = 120.0      # s for both workers to register (imports on a loaded machine)

pytestmark = needs_root


def _run(args, namespace=None, timeout: float = 600) -> subprocess.CompletedProcess:
    """run_experiment.py with `args`, in `namespace` if given, to its end."""
    prefix = ['ip', 'netns', 'exec', namespace] if namespace else []
    return subprocess.run([*prefix, sys.executable, SCRIPT, *args], stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=timeout)


@pytest.fixture(scope='module')
def serial(tmp_path_factory):
    """The seeds of RUN with ``--jobs 1`` (one process, no cluster): their reports."""
    out = str(tmp_path_factory.mktemp('serial') / 'run')
    done = _run([*RUN, '--jobs', '1', '--out', out])
    assert done.returncode == 0, done.stdout
    return per_seed_reports(out)


@pytest.fixture(scope='module')
def cluster(tmp_path_factory):
    """Hosts h0 (scheduler), h1 and h2 (a one-slot worker each) and the client's namespace,
    on tls:// with one certificate of a CA made here (dask checks the CA, not the host name:
    the certificate names 127.0.0.1); yields a dict of the net, address, files, worker logs,
    and the seconds of the undisturbed run (the first test's, for the rerun's cost).
    Afterwards no namespace of this process is left and the machine's links are as before."""
    folder = tmp_path_factory.mktemp('cluster')
    files = make_certificates(folder, 'ca')
    links = root_links()
    with netns.linked_hosts(3) as net:
        logs = [folder / f'worker-h{i}.log' for i in (1, 2)]
        workers = [(['ip', 'netns', 'exec', net.namespaces[i]], net.address(i), logs[i - 1], 1)
                   for i in (1, 2)]
        with dask_cluster(net.address(0), PORT, workers, files,
                          ['ip', 'netns', 'exec', net.namespaces[0]]) as (address, procs):
            deadline = time.monotonic() + JOIN_S
            while not all('Registered to' in log.read_text() for log in logs):
                assert time.monotonic() < deadline and all(p.poll() is None for p in procs), \
                    '\n'.join(log.read_text() for log in logs)
                time.sleep(0.2)
            yield {'net': net, 'address': address, 'files': files, 'logs': logs,
                   'tls': ['--tls-ca-file', str(files[0]), '--tls-cert', str(files[1]),
                           '--tls-key', str(files[2])]}
    assert ours(os.getpid()) == [] and root_links() == links


def _since_now(logs) -> Callable[[int], str]:
    """A reader of the lines worker log i gets from now on (not the earlier tests')."""
    known = [log.stat().st_size for log in logs]

    def new(i: int) -> str:
        with open(logs[i]) as f:
            f.seek(known[i])
            return f.read()
    return new


def test_seeds_on_a_tls_cluster_of_two_hosts_give_the_reports_of_jobs_1(
        cluster, serial, tmp_path):
    """run_experiment.py --seeds 2 --scheduler tls://<h0> from the client's namespace: both
    workers ran seeds (their lines are in the workers' logs), the seed folders came back over
    the links, and every seed's report equals that of --jobs 1 (lockstep is deterministic)."""
    net, address = cluster['net'], cluster['address']
    before = net.traffic()
    new = _since_now(cluster['logs'])
    out = str(tmp_path / 'run')
    started = time.monotonic()
    done = _run([*RUN, '--out', out, '--scheduler', address, *cluster['tls']],
                net.orchestrator)
    cluster['undisturbed_s'] = time.monotonic() - started
    assert done.returncode == 0, done.stdout
    assert f'cluster {address}: 2 worker(s), 2 slot(s)' in done.stdout, done.stdout
    ran = [re.findall(r'seed (\d): ROS_DOMAIN_ID', new(i)) for i in (0, 1)]
    assert all(ran) and sorted(sum(ran, [])) == ['0', '1'], ran
    assert [timing_free(s) for s in per_seed_reports(out)] == [timing_free(s) for s in serial]
    after = net.traffic()
    received = after[net.orchestrator]['rx_bytes'] - before[net.orchestrator]['rx_bytes']
    assert received > 100_000, 'the seed folders did not come over the client\'s link'


def _cmdline(pid: int) -> list:
    """The arguments of process `pid` (none if it is gone)."""
    with contextlib.suppress(OSError):
        with open(f'/proc/{pid}/cmdline', 'rb') as f:
            return f.read().decode().split('\0')[:-1]
    return []


def _seed_child(namespace: str, seed: int) -> int:
    """The pid of `seed`'s child process (seed_jobs) in `namespace`, 0 if none."""
    for pid in subprocess.run(['ip', 'netns', 'pids', namespace], capture_output=True,
                              text=True).stdout.split():
        args = _cmdline(int(pid))
        if 'metampc_bringup.orchestration.seed_jobs' in args and args[-1] == str(seed):
            return int(pid)
    return 0


def _descendants(pid: int) -> list:
    """`pid` and every process below it now."""
    parents = {}
    for name in filter(str.isdigit, os.listdir('/proc')):
        with contextlib.suppress(OSError):
            with open(f'/proc/{name}/stat') as f:
                parents[int(name)] = int(f.read().rsplit(')', 1)[1].split()[1])
    found, added = {pid}, True
    while added:
        below = {p for p, parent in parents.items() if parent in found} - found
        found |= below
        added = bool(below)
    return sorted(found)


def test_a_worker_sigkilled_in_the_middle_of_a_seed_changes_nothing_but_the_time(
        cluster, serial, tmp_path):
    """The worker process running seed 0 SIGKILLed in its namespace once that seed has
    collected: every process below it then (its seed's child and nodes) ends within 30 s (as
    test_experiment's loopback case), its nanny starts a new one, seed 0 runs again, the run
    ends 0 and every seed's report equals that of --jobs 1. Prints the run's wall time beside
    the undisturbed one's: the rerun's cost."""
    net, address = cluster['net'], cluster['address']
    out = str(tmp_path / 'run')
    new = _since_now(cluster['logs'])
    started = time.monotonic()
    proc = subprocess.Popen(
        ['ip', 'netns', 'exec', net.orchestrator, sys.executable, SCRIPT, *RUN, '--out', out,
         '--scheduler', address, *cluster['tls']],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while (host := next((i for i in (0, 1) if 'seed 0: collect done' in new(i)),
                            None)) is None:
            assert time.monotonic() < deadline and proc.poll() is None, 'seed 0 never collected'
            time.sleep(0.1)
        namespace = net.namespaces[host + 1]
        child = _seed_child(namespace, 0)
        assert child, 'seed 0 has no child process'
        with open(f'/proc/{child}/environ', 'rb') as f:
            worker, = [int(v[len(LIFELINE) + 1:]) for v in f.read().decode().split('\0')
                       if v.startswith(f'{LIFELINE}=')]
        doomed = {pid: ' '.join(_cmdline(pid)) for pid in _descendants(worker)}
        assert child in doomed, doomed
        os.kill(worker, signal.SIGKILL)
        deadline = time.monotonic() + 30.0    # the seed's child stops its nodes (recorder last)
        while any(map(alive, doomed)) and time.monotonic() < deadline:
            time.sleep(0.05)
        left = {pid: line for pid, line in doomed.items() if alive(pid)}
        assert not left, f'processes of the killed worker live on: {left}'
        text = proc.communicate(timeout=600)[0]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    took = time.monotonic() - started
    assert proc.returncode == 0, text
    ran = sum((re.findall(r'seed (\d): ROS_DOMAIN_ID', new(i)) for i in (0, 1)), [])
    assert sorted(ran) == ['0', '0', '1'], ran
    assert [timing_free(s) for s in per_seed_reports(out)] == [timing_free(s) for s in serial]
    print(f'\nSIGKILL of a worker: the run took {took:.1f} s, the undisturbed one '
          f'{cluster.get("undisturbed_s", float("nan")):.1f} s')


PROBE = """
import socket, ssl, sys
ca, host, port, *mine = sys.argv[1:]
ctx = ssl.create_default_context(cafile=ca)
ctx.check_hostname = False      # as dask: the cluster's CA, not host names
if mine:
    ctx.load_cert_chain(*mine)
with socket.create_connection((host, int(port)), 30) as raw:
    try:
        with ctx.wrap_socket(raw) as tls:
            tls.settimeout(5.0)
            print('refused' if tls.recv(1) == b'' else 'open')
    except (ssl.SSLError, ConnectionError):     # its alert, or the connection closed
        print('refused')
    except TimeoutError:                        # taken: waiting for the client to speak
        print('open')
"""


def _probe(namespace: str, *args: str) -> str:
    """A TLS connection from `namespace` to the scheduler by Python's ssl module, not dask:
    'refused' (the scheduler's alert, or it closed the connection) or 'open' (taken, the
    scheduler waits for the client's first message); args: CA, host, port[, cert, key]."""
    done = subprocess.run(['ip', 'netns', 'exec', namespace, sys.executable, '-c', PROBE,
                           *args], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_client_without_the_clusters_certificate_is_refused_by_the_scheduler(
        cluster, tmp_path):
    """From the client's namespace: run_experiment.py with a certificate of another CA gets
    one line and exit 2 (the scheduler's handshake refuses it), nothing written; a TLS client
    that trusts the cluster's CA but has no certificate of its own is refused by the
    scheduler, and the same client with the cluster's certificate is taken."""
    net, address = cluster['net'], cluster['address']
    other = make_certificates(tmp_path, 'other')
    out = tmp_path / 'run'
    done = _run([*RUN, '--out', str(out), '--scheduler', address, '--tls-ca-file', str(other[0]),
                 '--tls-cert', str(other[1]), '--tls-key', str(other[2])], net.orchestrator,
                timeout=300)
    assert done.returncode == 2, done.stdout
    line, = done.stdout.strip().splitlines()
    assert line.startswith(f'run_experiment: --scheduler {address}: the connection was '
                           'refused') and 'certificate' in line.lower(), line
    assert not out.exists()
    host, port = address[len('tls://'):].rsplit(':', 1)
    ca, cert, key = map(str, cluster['files'])
    assert _probe(net.orchestrator, ca, host, port) == 'refused', 'taken without a certificate'
    assert _probe(net.orchestrator, ca, host, port, cert, key) == 'open'
