"""Shared helpers for tests that start real ROS 2 processes.

Every process is started through `ros2 run` (the shim or a real ros2) in the test session's
isolated domain (see conftest.py) and is stopped by the test that started it: use the ``procs``
fixture (a metampc_bringup.orchestration.processes.ProcessGroup).
"""
import contextlib
import json
import os
from pathlib import Path
import signal
import socket
import subprocess
import sys

from metampc_bringup.orchestration.processes import ProcessGroup, session_pids  # noqa: F401
from metampc_bringup.orchestration.spun_node import SpunNode
from rosbags.highlevel import AnyReader

# Set by conftest to the pid of the test session (an xdist worker, or pytest) and inherited by
# every process the session starts: the session's orphan check, and tests that tell their own
# processes from another session's, look for it.
SESSION_ENV = 'METAMPC_TEST_SESSION'


def alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie does not)."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def own_lines(text: str) -> list:
    """The non-empty lines of a process's output, without Fast DDS's shared-memory port
    error: when many participants start at once its port mutex times out (after 2 s,
    eProsima/Fast-DDS#6117) and it logs 'RTPS_TRANSPORT_SHM Error ... Failed init_port', then
    goes on with another port. Seen with 14 plants started together on an idle CI machine;
    not a line of ours."""
    return [line for line in text.splitlines() if line.strip()
            and not ('RTPS_TRANSPORT_SHM' in line and 'Failed init_port' in line)]


def free_port() -> int:
    """A loopback TCP port free now."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def loopback_dask(log: Path, workers: int = 1, port: int = 0, tls=None):
    """`dask scheduler` on 127.0.0.1:`port` (0: a free one) and a `dask worker` of `workers`
    one-slot processes (its output in `log`, its scratch space beside it) (:func:`dask_cluster`);
    yields (address, [scheduler, worker] Popens)."""
    with dask_cluster('127.0.0.1', port or free_port(), [([], '127.0.0.1', log, workers)],
                      tls) as cluster:
        yield cluster


@contextlib.contextmanager
def dask_cluster(host: str, port: int, workers, tls=None, prefix=()):
    """`dask scheduler` on `host`:`port` (its command after `prefix`, e.g. ``ip netns exec
    NS``) and one `dask worker` per (prefix, host, log, processes) of `workers`: `processes`
    one-slot processes, output in `log`, scratch space beside it. Each runs in a session of
    its own and is stopped on return if still running (SIGTERM, then SIGKILL after 60 s);
    yields (address, [scheduler, *worker] Popens). `tls`: (CA, certificate, key) PEM paths for
    all, on tls:// (else tcp://)."""
    address = f'{"tls" if tls else "tcp"}://{host}:{port}'
    secure = [] if not tls else ['--tls-ca-file', str(tls[0]), '--tls-cert', str(tls[1]),
                                 '--tls-key', str(tls[2])]
    dask = os.path.join(os.path.dirname(sys.executable), 'dask')
    started = [subprocess.Popen([*prefix, dask, 'scheduler', '--host', host, '--port', str(port),
                                 '--no-dashboard', *secure]
                                + (['--protocol', 'tls'] if tls else []),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)]
    try:
        for worker_prefix, worker_host, log, processes in workers:
            with open(log, 'w') as f:
                started.append(subprocess.Popen(
                    [*worker_prefix, dask, 'worker', address, '--host', worker_host,
                     '--nworkers', str(processes), '--nthreads', '1', '--resources', 'slot=1',
                     '--no-dashboard', '--local-directory', str(log.with_suffix('.scratch')),
                     *secure], stdout=f, stderr=subprocess.STDOUT, start_new_session=True))
        yield address, started
    finally:
        for proc in reversed(started):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                for pid in session_pids(proc):
                    os.kill(pid, signal.SIGKILL)
                proc.wait()


@contextlib.contextmanager
def example_script(args, log: Path):
    """`python ARGS...` (a stand-in machine of examples/) in a session of its own, its output
    in `log`; yields its Popen. Stopped on leaving by SIGINT (also when the body fails), which
    it must answer with exit status 0 and nothing of its session left running."""
    with open(log, 'w') as out:
        proc = subprocess.Popen([sys.executable, *map(str, args)], stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            yield proc
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
            proc.wait(10.0)
    assert proc.returncode == 0, log.read_text()
    assert session_pids(proc) == []


def make_certificates(folder: Path, name: str = 'ca'):
    """A CA of its own (`name`) and a certificate and key for 127.0.0.1 signed by it, made by
    the openssl command in `folder`, valid one day: (CA, certificate, key) PEM paths."""
    ca, ca_key = folder / f'{name}.pem', folder / f'{name}.key'
    cert, key, csr = folder / f'{name}-node.pem', folder / f'{name}-node.key', folder / 'req.csr'
    san = folder / 'san.ext'
    san.write_text('subjectAltName=IP:127.0.0.1\n')
    for args in (['req', '-x509', '-newkey', 'rsa:2048', '-nodes', '-keyout', ca_key, '-out', ca,
                  '-days', '1', '-subj', f'/CN=metampc test {name}'],
                 ['req', '-newkey', 'rsa:2048', '-nodes', '-keyout', key, '-out', csr, '-subj',
                  '/CN=127.0.0.1'],
                 ['x509', '-req', '-in', csr, '-CA', ca, '-CAkey', ca_key, '-CAcreateserial',
                  '-out', cert, '-days', '1', '-extfile', san]):
        subprocess.run(['openssl', *map(str, args)], check=True, capture_output=True)
    return ca, cert, key


def timing_free(report: dict):
    """A seed report without what depends on timing: wall-clock stamps and durations, the
    solve and tick times, and how many samples the plant ran on while the collection was
    being stopped (the learner keeps the first target_samples of them whatever the count);
    and the run's configuration (seeds and first seed differ by design); the learner's count
    of skipped step-0 samples (whether the plant's start-up y_0 reached it after buffering
    began depends on timing; kept and lost are compared by the caller)."""
    timing = ('wall_time', 'tick_time', 'solve_time', 'timings', 'elapsed_s', 'recording',
              'message', 'collect', 'config', 'buffering')
    if isinstance(report, dict):
        return {k: timing_free(v) for k, v in report.items() if k not in timing}
    if isinstance(report, list):
        return [timing_free(v) for v in report]
    return report


def per_seed_reports(out: str) -> list:
    """The per-seed reports of run folder `out` (its report.json)."""
    with open(os.path.join(out, 'report.json')) as f:
        return json.load(f)['per_seed']


class TestNode(SpunNode):
    """An rclpy node spun in a background thread, for probing the graph from a test."""

    __test__ = False    # not a test class, though imported into test modules

    def __init__(self, name: str = 'metampc_test_probe'):
        super().__init__(name)


def read_with_rosbags(mcap_path: str):
    """Events and closed-loop messages of a recording, decoded by rosbags."""
    events, outputs, statuses, inputs = [], [], [], []
    with AnyReader([Path(mcap_path)]) as reader:     # types from the schemas in the file
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            name = conn.topic.rsplit('/', 1)[-1]
            if name == 'experiment_events':
                events.append(json.loads(msg.data))
            elif name in ('y', 'mpc_status', 'u'):
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                {'y': outputs, 'mpc_status': statuses, 'u': inputs}[name].append((stamp, msg))
    return events, outputs, statuses, inputs
