"""One execution layer for batches of independent jobs: a dask.distributed cluster.

Embedded (:func:`connect` without an address): a LocalCluster of ``jobs`` single-threaded
worker processes on 127.0.0.1, no dashboard, stopped on return. An address: an existing cluster
(``dask scheduler`` / ``dask worker``, dask-jobqueue; docs/experiments.md#on-a-cluster): a
``tls://`` one with certificates (:class:`TlsFiles`), anywhere; a plain ``tcp://`` one off this
machine is refused without ``insecure``, before any connection (a scheduler runs whatever it
is sent; docs/security.md). Each job holds one worker slot (resource :data:`SLOT`),
so jobs never crowd a host. A job runs in a worker thread that lives as long as the job, so
the lifelines (:mod:`.lifeline`) of the processes it forks hold: they die with the worker, and
the scheduler runs the job again on another. Ctrl-C asks the running jobs to stop and takes
what they send back (:func:`run_batch`); the scheduler gone is :class:`SchedulerLost`.
"""
import contextlib
import dataclasses
import ipaddress
import logging
import signal
import tempfile
import time
import uuid
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Set, Tuple

log = logging.getLogger('metampc.cluster')

SLOT = 'slot'               # the worker resource a job holds: one job per slot
CONNECT_TIMEOUT_S = 10.0    # s for a scheduler to answer, and for a first worker to show up
STOP_S = 120.0              # s for the processes of a stopped embedded cluster's jobs to end
DRAIN_S = 180.0             # s for the jobs asked to stop (Ctrl-C) to send back what they have
LOOPBACK_NAMES = ('localhost',)


class ClusterError(Exception):
    """The cluster cannot be used: no answer, no worker with a slot, or (embedded) it did not
    start."""


class SchedulerLost(ClusterError):
    """The client lost its scheduler in the middle of a batch: the jobs done by then were
    handed to ``done``, the others are lost."""


@dataclasses.dataclass(frozen=True)
class TlsFiles:
    """PEM files of a TLS connection to a scheduler: the CA that signed the cluster's
    certificates, and this client's certificate and key (dask's Security, encryption
    required; the scheduler and workers take the same options, docs/security.md)."""

    ca_file: str
    cert: str
    key: str

    def check(self) -> None:
        """ValueError naming a file that cannot be read or is not PEM (a TLS handshake with it
        fails only at the connection, as "no answer within 10 s (SSLError)")."""
        for name, path in dataclasses.asdict(self).items():
            flag = f'--tls-{name.replace("_", "-")} {path}'
            try:
                with open(path, 'rb') as f:
                    text = f.read(1 << 20)
            except OSError as err:
                raise ValueError(f'{flag}: cannot be read ({err.strerror})') from None
            if b'-----BEGIN ' not in text:
                raise ValueError(f'{flag}: not a PEM file (no -----BEGIN line)')

    def security(self) -> Any:
        """The dask Security of these files (ValueError naming one that cannot be read or is
        not PEM: :meth:`check`)."""
        self.check()
        from distributed.security import Security
        return Security(tls_ca_file=self.ca_file, tls_client_cert=self.cert,
                        tls_client_key=self.key, require_encryption=True)


@dataclasses.dataclass
class ClusterSpec:
    """Where a batch runs.

    Attributes:
        jobs: workers of the embedded cluster (jobs at once); unused with ``scheduler``.
        scheduler: address of an existing scheduler (``tcp://`` or ``tls://host:port``);
            None: embedded.
        insecure: allow a plain ``tcp://`` scheduler that is not on loopback.
        tls: the certificates of a ``tls://`` scheduler.
    """
    jobs: int = 1
    scheduler: Optional[str] = None
    insecure: bool = False
    tls: Optional[TlsFiles] = None


def check_address(address: str, insecure: bool = False, tls: bool = False) -> None:
    """ValueError unless `address` is a scheduler address this layer may connect to: a
    ``tls://`` address with certificates (`tls`), a ``tcp://`` address on loopback, or anywhere
    with `insecure`. Nothing is resolved or connected: a host name other than localhost
    counts as another machine."""
    scheme, sep, rest = address.partition('://')
    if not sep:
        scheme, rest = 'tcp', address
    if rest.startswith('['):    # [IPv6]:PORT
        host, _, port = rest[1:].partition(']')
        port = port[1:] if port.startswith(':') else ''
    else:
        host, _, port = rest.rpartition(':')
    if scheme not in ('tcp', 'tls') or not host or not port.isdigit() \
            or not 0 < int(port) < 65536:
        raise ValueError(f'--scheduler {address}: expected tcp://HOST:PORT or tls://HOST:PORT')
    if (scheme == 'tls') != tls:
        raise ValueError(f'--scheduler {address}: ' + (
            'tls:// needs --tls-ca-file, --tls-cert and --tls-key (docs/security.md)'
            if scheme == 'tls' else 'the --tls-* files are for a tls:// scheduler'))
    if scheme == 'tls':
        return
    if not (insecure or _loopback(host)):
        raise ValueError(f'--scheduler {address}: a plain tcp:// scheduler off this machine '
                         'runs whatever anyone who reaches it sends; refused without '
                         '--insecure (docs/experiments.md#on-a-cluster)')


def _loopback(host: str) -> bool:
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@contextlib.contextmanager
def connect(spec: ClusterSpec) -> Iterator[Any]:
    """A dask Client of `spec`'s cluster (embedded: started here, stopped on return).

    Raises:
        ValueError: the address is refused (:func:`check_address`), before any connection.
        ClusterError: the scheduler does not answer within :data:`CONNECT_TIMEOUT_S`, or has
            no worker with a slot by then.
    """
    if spec.scheduler is None:
        with _embedded(spec.jobs) as client:
            yield client
        return
    check_address(spec.scheduler, spec.insecure, spec.tls is not None)
    security = spec.tls.security() if spec.tls is not None else None
    from distributed import Client
    from distributed.comm.core import FatalCommClosedError
    try:
        client = Client(spec.scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False,
                        security=security)
    except FatalCommClosedError as err:     # e.g. a certificate of another CA
        raise ClusterError(f'--scheduler {spec.scheduler}: the connection was refused '
                           f'({err})') from None
    except (OSError, TimeoutError) as err:
        raise ClusterError(f'--scheduler {spec.scheduler}: no answer within '
                           f'{CONNECT_TIMEOUT_S:.0f} s ({err.__class__.__name__})') from None
    dask_log = logging.getLogger('distributed.client')
    level = dask_log.level
    try:
        with client:
            _wait_for_slot(client, spec.scheduler)
            try:
                yield client
            except SchedulerLost:
                # Closing a client that lost its scheduler cancels its reconnection, which dask
                # logs as a traceback: the error says it in one line.
                dask_log.setLevel(logging.CRITICAL + 1)
                raise
    finally:
        dask_log.setLevel(level)


@contextlib.contextmanager
def _embedded(jobs: int) -> Iterator[Any]:
    """A LocalCluster of `jobs` one-slot workers on loopback and its client; on return (Ctrl-C
    included) the workers are stopped, and so are the processes their jobs started (their
    lifelines), which are waited for."""
    from distributed import Client, LocalCluster
    # The scheduler and nannies run in this process: their lines are not the run's, and on
    # Ctrl-C they warn of the cancelled jobs and workers killed as intended.
    logging.getLogger('distributed').setLevel(logging.ERROR)
    with tempfile.TemporaryDirectory(prefix='metampc-cluster-') as scratch:
        try:
            cluster = LocalCluster(
                n_workers=jobs, threads_per_worker=1, processes=True, host='127.0.0.1',
                scheduler_port=0, dashboard_address=None, resources={SLOT: 1},
                local_directory=scratch, silence_logs=logging.ERROR, preload=[__name__],
                # Its HTTP server (health, no dashboard) on a free loopback port: dask's default,
                # 8787, is another cluster's when two run, and dask warns on stderr.
                scheduler_kwargs={'dashboard_address': '127.0.0.1:0'})
        except (RuntimeError, OSError, TimeoutError) as err:
            raise ClusterError(f'the embedded cluster did not start: {err}') from None
        pids = {nanny.pid for nanny in cluster.workers.values()}
        try:
            log.info('embedded cluster: %d worker(s) on 127.0.0.1', jobs)
            with Client(cluster, set_as_default=False) as client:
                yield client
        finally:
            pids |= {nanny.pid for nanny in cluster.workers.values()}     # restarted ones
            cluster.close()
            _wait_for_children(pids - {None})


def dask_setup(worker) -> None:
    """An embedded worker (its preload) ignores SIGINT: Ctrl-C reaches the terminal's whole
    process group, and the client, not the worker, decides what stops (:func:`run_batch`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _wait_for_slot(client, address: str) -> None:
    """ClusterError unless a worker with a slot joins within CONNECT_TIMEOUT_S."""
    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except TimeoutError:
        raise ClusterError(f'--scheduler {address}: no worker joined within '
                           f'{CONNECT_TIMEOUT_S:.0f} s') from None
    have = slots(client)
    if not have:
        raise ClusterError(f'--scheduler {address}: no worker has a {SLOT} (start each with '
                           f'`dask worker {address} --nthreads 1 --resources {SLOT}=1`)')
    log.info('cluster %s: %d worker(s), %d slot(s)', address,
             len(client.scheduler_info()['workers']), have)


def slots(client) -> int:
    """The slots of `client`'s workers now: how many jobs run at once."""
    workers = client.scheduler_info()['workers'].values()
    return int(sum(w.get('resources', {}).get(SLOT, 0) for w in workers))


def _wait_for_children(worker_pids: Iterable[int]) -> None:
    """Wait (up to :data:`STOP_S`) until the processes that the embedded workers started have
    ended: killed with the cluster, they get their lifelines' signal and stop their nodes."""
    from metampc_bringup.orchestration.lifeline import ENV
    from metampc_bringup.orchestration.procfs import pids_with_env
    deadline = time.monotonic() + STOP_S
    while any(pids_with_env({ENV: str(w)}) for w in worker_pids) \
            and time.monotonic() < deadline:
        time.sleep(0.1)


def check_workers(client, probe: Callable[[], str], what: str) -> None:
    """ClusterError unless ``probe()`` gives on every worker of `client` what it gives here
    (e.g. a fingerprint of the code the jobs run); a worker where it fails counts too."""
    mine = probe()
    theirs = client.run(probe, on_error='return')
    wrong = sorted(address for address, value in theirs.items() if value != mine)
    if wrong:
        sample = theirs[wrong[0]]
        reason = (f'{sample.__class__.__name__}: {sample}' if isinstance(sample, BaseException)
                  else 'another version')
        raise ClusterError(f'{len(wrong)} of {len(theirs)} worker(s) do not run {what} '
                           f'({wrong[0]}: {reason}); install and build this commit there')


_STOPPING: Set[str] = set()     # on a worker: keys of the jobs asked to stop (Ctrl-C)


def _stop_jobs(keys: Sequence[str]) -> None:
    """On each worker (client.run): the jobs of `keys` are to stop and send back what they
    have (:func:`job_cancelled` says so)."""
    _STOPPING.update(keys)


def job_cancelled() -> bool:
    """In a job on a worker: whether it is to stop what it started and return; it was asked
    to (Ctrl-C: its result is still wanted), or the client no longer wants its result
    (cancelled, or the client gone)."""
    from distributed import get_worker
    worker = get_worker()
    key = worker.get_current_task()
    task = worker.state.tasks.get(key)
    return key in _STOPPING or task is None or task.state not in ('executing', 'long-running')


def _worker_state(client, left: Dict[Any, Any]
                  ) -> Optional[Tuple[Dict[str, List[Any]], int]]:
    """Per worker address, the items of `left` (future -> item) it holds (running, or
    waiting for its slot), and how many run: per worker at most its slots. None when the
    scheduler does not answer (as_completed then says it is lost)."""
    items = {future.key: item for future, item in left.items()}
    try:
        processing, workers = client.processing(), client.scheduler_info()['workers']
    except OSError:
        return None
    held = {worker: [items[key] for key in keys if key in items]
            for worker, keys in sorted(processing.items())}
    running = sum(min(len(v), int(workers.get(w, {}).get('resources', {}).get(SLOT, 1)))
                  for w, v in held.items())
    return held, running


def run_batch(client, job: Callable[..., Any], items: Sequence[Any], name: str,
              done: Callable[[Any, Any], None], progress: bool = False
              ) -> List[Tuple[Any, BaseException]]:
    """Run ``job(item)`` for every item on `client`'s cluster, one slot each; ``done(item,
    result)`` in this process as each finishes. Returns the (item, exception) of the jobs
    that raised (the others ran to their end).

    Ctrl-C asks the jobs to stop (:func:`job_cancelled`) and hands what they return within
    :data:`DRAIN_S` to ``done`` (a second Ctrl-C: at once), cancels the rest and re-raises.
    `name` labels the progress line (tqdm: done, running, failed, ETA) when `progress`; each
    finished job logs the count and how many jobs every worker holds (INFO, ``metampc.cluster``).

    Raises:
        SchedulerLost: the connection to the scheduler is lost (the jobs done by then were
            handed to ``done``).
    """
    from distributed import as_completed
    from tqdm import tqdm
    items = list(items)
    futures: Dict[Any, Any] = {}
    left: Dict[Any, Any] = {}       # submitted and not done: what a Ctrl-C drains
    failed: List[Tuple[Any, BaseException]] = []
    bar = tqdm(total=len(items), desc=name, unit='job', disable=not progress)
    try:
        for item in items:          # a Ctrl-C while submitting drains what was submitted
            future = client.submit(job, item, key=f'{name}-{item}-{uuid.uuid4().hex[:12]}',
                                   pure=False, resources={SLOT: 1})
            futures[future] = left[future] = item
        for future in as_completed(futures, loop=client.loop):
            item = left.pop(future)
            if future.status == 'cancelled':    # never by this client but on Ctrl-C
                raise SchedulerLost(f'lost the scheduler {client.scheduler.address}')
            if future.status == 'error':
                failed.append((item, future.exception()))
            else:
                done(item, future.result())
            state = _worker_state(client, left)
            if state is not None:
                held, running = state
                bar.set_postfix(running=running, failed=len(failed), refresh=False)
                log.info('%s: %d of %d done (%d failed); %s', name, len(futures) - len(left),
                         len(futures), len(failed), '; '.join(
                             f'{w}: {len(v)} held' if v else f'{w}: idle'
                             for w, v in held.items()))
            bar.update()
    except KeyboardInterrupt:
        _drain(client, left, done)
        raise
    finally:
        bar.close()
    return failed


def _drain(client, left: Dict[Any, Any], done: Callable[[Any, Any], None]) -> None:
    """After Ctrl-C: ask the jobs of `left` (future: item) to stop, hand what they return
    within :data:`DRAIN_S` to ``done`` and cancel the others."""
    from distributed import as_completed
    log.info('stopping %d job(s) and taking back what they hold (Ctrl-C again: not '
             'waiting)', len(left))
    try:
        client.run(_stop_jobs, [future.key for future in left])
        for future in as_completed(list(left), loop=client.loop, timeout=DRAIN_S):
            item = left.pop(future)
            if future.status == 'finished':
                done(item, future.result())
    except (KeyboardInterrupt, TimeoutError, OSError) as err:
        log.warning('not waiting for the stopped jobs (%s)', err.__class__.__name__)
    client.cancel(list(left))
