"""The execution layer (metampc_bringup.orchestration.cluster): which schedulers it refuses
before connecting, one that does not answer, the lifeline of a job's process when its worker
is killed, workers that run other code, Ctrl-C, the scheduler lost. Tests address loopback
only."""
import functools
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import cloudpickle
import pytest

from metampc_bringup.orchestration import cluster
from metampc_bringup.orchestration.cluster import (check_address, check_workers, ClusterError,
                                                   ClusterSpec, connect, job_cancelled,
                                                   run_batch, SchedulerLost, TlsFiles)
from metampc_bringup.orchestration.lifeline import child_env, ENV
from metampc_bringup.orchestration.procfs import pids_with_env
from metampc_bringup.orchestration.seed_jobs import code_fingerprint
from metampc_testing import alive, loopback_dask, make_certificates

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
SCRIPT = os.path.join(ROOT, 'scripts', 'run_experiment.py')
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')
# Written as addresses only, never reached: connecting fails the test first.
OFF_HOST = ('tcp://192.0.2.7:8786', 'tcp://scheduler.example.org:8786', '192.0.2.7:8786',
            'tcp://[2001:db8::1]:8786')


@pytest.fixture
def no_connection(monkeypatch):
    """Any name lookup or connection (socket, dask Client) fails the test."""
    def refuse(*args, **kwargs):
        pytest.fail(f'a connection was tried: {args}')
    monkeypatch.setattr(socket, 'getaddrinfo', refuse)
    monkeypatch.setattr(socket, 'create_connection', refuse)
    monkeypatch.setattr(socket.socket, 'connect', refuse)
    monkeypatch.setattr(socket.socket, 'connect_ex', refuse)
    import distributed
    monkeypatch.setattr(distributed, 'Client', refuse)
    monkeypatch.setattr(distributed, 'LocalCluster', refuse)


def test_a_plain_tcp_scheduler_off_this_machine_is_refused_before_any_connection(
        no_connection, tmp_path, capsys):
    for address in OFF_HOST:
        with pytest.raises(ValueError, match='refused without --insecure'):
            with connect(ClusterSpec(scheduler=address)):
                pass
        check_address(address, insecure=True)       # the user's explicit choice
    with pytest.raises(ValueError, match='tls:// needs --tls-ca-file, --tls-cert and --tls-key'):
        check_address('tls://192.0.2.7:8786')
    with pytest.raises(ValueError, match='the --tls-\\* files are for a tls:// scheduler'):
        check_address('tcp://127.0.0.1:8786', tls=True)
    check_address('tls://192.0.2.7:8786', tls=True)     # certificates: any host
    for address in ('tcp://127.0.0.1:8786', 'tcp://localhost:8786', 'tcp://[::1]:8786',
                    '127.0.0.2:8786'):
        check_address(address)
    # As a user runs it: one line, exit 2, nothing written.
    import importlib.util
    spec = importlib.util.spec_from_file_location('run_experiment_script', SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / 'run'
    for extra, said in ((['--scheduler', OFF_HOST[0]], '--insecure'),
                        (['--scheduler', 'tls://192.0.2.7:8786'], 'tls:// needs --tls-ca-file'),
                        (['--scheduler', 'tls://192.0.2.7:8786', '--tls-ca-file', 'ca.pem'],
                         '--tls-ca-file, --tls-cert and --tls-key go together'),
                        # Issue 52: a traceback, exit 1 (files) and 53 lines after 20 s (port).
                        (['--scheduler', 'tls://192.0.2.7:8786', '--tls-ca-file', 'ca.pem',
                          '--tls-cert', 'c.pem', '--tls-key', 'c.key'],
                         '--tls-ca-file ca.pem: cannot be read'),
                        (['--scheduler', 'tcp://127.0.0.1'], 'expected tcp://HOST:PORT')):
        assert script.main(['--config', CI_CONFIG, '--out', str(out), '--seeds', '2',
                            *extra]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and said in err, err
        assert not out.exists()


def test_a_scheduler_that_does_not_answer_is_one_line_and_exit_2(tmp_path):
    """A loopback port bound by this test and never listened on: refused connections until
    the timeout, then one line; nothing written."""
    with socket.socket() as held:
        held.bind(('127.0.0.1', 0))
        address = 'tcp://127.0.0.1:%d' % held.getsockname()[1]
        out = tmp_path / 'run'
        started = time.monotonic()
        done = subprocess.run(
            [sys.executable, SCRIPT, '--config', CI_CONFIG, '--out', str(out), '--seeds', '2',
             '--no-progress', '--scheduler', address], stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, timeout=300)
        took = time.monotonic() - started
    assert done.returncode == 2, done.stdout
    assert done.stdout.strip().splitlines() == [
        f'run_experiment: --scheduler {address}: no answer within '
        f'{cluster.CONNECT_TIMEOUT_S:.0f} s (OSError)'], done.stdout
    assert took < cluster.CONNECT_TIMEOUT_S + 120, took      # imports on a loaded machine
    assert not out.exists()


def _job(marker: str) -> int:
    """On a worker: a process holding a lifeline to this worker, waited for (unless `marker`
    exists: the test is over, the job's rerun starts nothing)."""
    if os.path.exists(marker):
        return 0
    return subprocess.call(
        [sys.executable, '-c', 'import time\nfrom metampc_bringup.orchestration.lifeline '
         'import hold\nhold()\ntime.sleep(120)'], env=child_env(), start_new_session=True)


def test_a_jobs_process_dies_with_its_killed_worker(tmp_path):
    """SIGKILL of an embedded worker while its job waits for a process it started from the
    job's thread: that process ends within 5 s (the lifeline holds in a dask worker)."""
    marker = str(tmp_path / 'over')
    cloudpickle.register_pickle_by_value(sys.modules[__name__])    # workers lack test/
    with connect(ClusterSpec(jobs=1)) as client:
        worker, = client.run(os.getpid).values()
        future = client.submit(_job, marker, resources={cluster.SLOT: 1}, pure=False)
        deadline = time.monotonic() + 120
        while not (children := pids_with_env({ENV: str(worker)})):
            assert time.monotonic() < deadline and future.status == 'pending'
            time.sleep(0.05)
        open(marker, 'w').close()
        os.kill(worker, signal.SIGKILL)
        deadline = time.monotonic() + 5.0
        while any(map(alive, children)) and time.monotonic() < deadline:
            time.sleep(0.02)
        left = [p for p in children if alive(p)]
        for pid in left:
            os.kill(pid, signal.SIGKILL)
        assert not left, 'the job\'s process outlived its worker'
        assert future.result(timeout=120) == 0      # run again on the restarted worker


def _pid_probe() -> str:
    return str(os.getpid())


def _missing_probe() -> str:
    if os.environ.get('METAMPC_TEST_CLIENT') != str(os.getpid()):
        raise ModuleNotFoundError("No module named 'metampc_bringup'")
    return 'here'


def test_a_worker_that_runs_other_code_is_refused(monkeypatch):
    """check_workers: a probe (the code's fingerprint, for seeds) that gives another value on
    a worker, or fails there as on a machine without the project: ClusterError naming it;
    the same value everywhere passes."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    monkeypatch.setenv('METAMPC_TEST_CLIENT', str(os.getpid()))
    with connect(ClusterSpec(jobs=1)) as client:
        with pytest.raises(cluster.ClusterError, match=r'1 of 1 worker\(s\) do not run it .*'
                           'another version'):
            check_workers(client, _pid_probe, 'it')
        with pytest.raises(cluster.ClusterError, match='ModuleNotFoundError'):
            check_workers(client, _missing_probe, 'it')
        check_workers(client, code_fingerprint, 'this version of metampc')


def _until_stopped(started: str, item: int) -> str:
    """On a worker: works (a file `started` says so) until it is asked to stop, then sends
    back what it holds."""
    open(started, 'w').close()
    while not job_cancelled():
        time.sleep(0.05)
    return f'partial {item}'


def test_ctrl_c_takes_back_what_the_stopped_jobs_hold(tmp_path):
    """SIGINT to the client and to its embedded worker (a terminal's Ctrl-C reaches both)
    while the first of two jobs runs: the worker lives on, both jobs are asked to stop and
    what they send back is handed to `done` before KeyboardInterrupt."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    started = tmp_path / 'started'
    got = {}
    with connect(ClusterSpec(jobs=1)) as client:
        worker, = client.run(os.getpid).values()

        def ctrl_c():
            while not started.exists():
                time.sleep(0.02)
            os.kill(worker, signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
        threading.Thread(target=ctrl_c, daemon=True).start()
        with pytest.raises(KeyboardInterrupt):
            run_batch(client, functools.partial(_until_stopped, str(started)), [0, 1], 'jobs',
                      got.__setitem__)
        assert list(client.run(os.getpid).values()) == [worker]
    assert got == {0: 'partial 0', 1: 'partial 1'}


def test_the_scheduler_lost_is_scheduler_lost_after_the_jobs_done_by_then(tmp_path):
    """A loopback `dask scheduler` SIGKILLed once the first of two jobs (time.sleep) is done:
    run_batch raises SchedulerLost naming it, the first job's result handed to `done`."""
    got = {}
    with loopback_dask(tmp_path / 'worker.log') as (address, (scheduler, _)):
        def done(item, result):
            got[item] = result
            os.killpg(scheduler.pid, signal.SIGKILL)
        with connect(ClusterSpec(scheduler=address)) as client:
            with pytest.raises(SchedulerLost, match=f'lost the scheduler {address}$'):
                run_batch(client, time.sleep, [0.1, 60.0], 'jobs', done)
    assert got == {0.1: None}


def test_a_tls_scheduler_takes_a_client_of_its_ca_and_no_other(tmp_path):
    """A loopback `dask scheduler` and worker on tls:// with certificates of a CA made here: a
    client with a certificate of that CA runs a job there; one of another CA gets no
    connection (the handshake fails: one ClusterError line); unreadable files are refused
    before any connection."""
    files = make_certificates(tmp_path, 'ca')
    mine = TlsFiles(*map(str, files))
    other = TlsFiles(*map(str, make_certificates(tmp_path, 'other')))
    with loopback_dask(tmp_path / 'worker.log', tls=files) as (address, _):
        with connect(ClusterSpec(scheduler=address, tls=mine)) as client:
            assert client.submit(sum, [40, 2], resources={'slot': 1}).result(60) == 42
        with pytest.raises(ClusterError, match=f'--scheduler {address}: the connection was '
                                               'refused .*TLS certificate does not match'):
            with connect(ClusterSpec(scheduler=address, tls=other)):
                pass
    unreadable = TlsFiles(mine.ca_file, mine.cert, '/nonexistent.key')
    with pytest.raises(ValueError, match='--tls-key /nonexistent.key: cannot be read'):
        with connect(ClusterSpec(scheduler=address, tls=unreadable)):
            pass


def test_each_finished_job_logs_the_count_and_what_every_worker_holds(caplog):
    """Three jobs on one worker slot: after each, one line with the count and how many jobs
    the worker holds then (running or waiting for its slot: those not done), idle at the end."""
    caplog.set_level(logging.INFO, logger='metampc.cluster')
    got = {}
    with connect(ClusterSpec(jobs=1)) as client:
        worker, = client.scheduler_info()['workers']
        assert run_batch(client, time.sleep, [0.3, 0.6, 0.9], 'naps', got.__setitem__) == []
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith('naps: ')]
    assert lines == [f'naps: 1 of 3 done (0 failed); {worker}: 2 held',
                     f'naps: 2 of 3 done (0 failed); {worker}: 1 held',
                     f'naps: 3 of 3 done (0 failed); {worker}: idle']
    assert sorted(got) == [0.3, 0.6, 0.9]
