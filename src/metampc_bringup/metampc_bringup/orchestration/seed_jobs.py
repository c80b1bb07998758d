"""The seeds of an experiment as jobs of a cluster (:mod:`.cluster`): ``--jobs N`` or
``--scheduler ADDRESS`` of run_experiment.py.

A seed's job (:func:`run_seed`, on a worker) runs the seed in a child process (``python -m
metampc_bringup.orchestration.seed_jobs WORK SEED``, :class:`.orchestrator.SeedRun`) with a ROS
domain (:mod:`.domain`) and a session of its own, in the worker's scratch space; the child dies
with the worker (:mod:`.lifeline`). The seed's folder comes back as a tar into the client's run
folder (no shared filesystem). A lockstep seed's report equals that of ``--jobs 1``. Ctrl-C
stops the jobs (each child stops its nodes, recorder last) and their folders land, marked
incomplete (:mod:`..run_folder`), as does a failed seed's with its logs while the others run
to their end. Measured: docs/speed.md#seeds-in-parallel.
"""
import collections
import dataclasses
import functools
import hashlib
import importlib
import io
import logging
import os
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
from typing import Callable, Deque, List, Sequence

from metampc_bringup.orchestration.cluster import (check_workers, job_cancelled, run_batch,
                                                   SchedulerLost)
from metampc_bringup.orchestration.experiment_client import ExperimentError
from metampc_bringup.orchestration.lifeline import child_env, hold
from metampc_bringup.run_folder import mark_incomplete

log = logging.getLogger('metampc.seed_jobs')

POLL_S = 0.2            # how often a job looks at its child and at its cancellation
STOP_S = 120.0          # s for an interrupted child to stop its nodes before SIGKILL
INTERRUPTED = 130       # a child's exit status after Ctrl-C
TAIL_LINES = 40         # lines of a failed seed's output shown by the client


def seed_dir(out_dir: str, seed: int) -> str:
    """The folder of one seed's run inside the run folder."""
    return os.path.join(out_dir, f'seed_{seed}')


@dataclasses.dataclass
class SeedOutcome:
    """What a seed's job sends back: the child's exit status, its seed folder (a tar holding
    ``seed_<s>/``, empty if the child made none) and the last lines of its output."""
    status: int
    folder: bytes
    tail: str


PACKAGES = ('metampc_bringup', 'metampc_common', 'metampc_controller', 'metampc_learner',
            'metampc_model', 'metampc_plant', 'metampc_recording')   # what a seed runs


def code_fingerprint() -> str:
    """sha256 of the Python sources of :data:`PACKAGES` as installed here: a worker whose
    fingerprint differs from the client's would run other code (or none)."""
    digest = hashlib.sha256()
    for package in PACKAGES:
        root = os.path.dirname(importlib.import_module(package).__file__)
        for folder, dirs, files in os.walk(root):
            dirs.sort()
            for name in sorted(f for f in files if f.endswith('.py')):
                path = os.path.join(folder, name)
                digest.update(os.path.relpath(path, root).encode())
                with open(path, 'rb') as f:
                    digest.update(f.read())
    return digest.hexdigest()


def check_workers_run_this_code(client) -> None:
    """ClusterError unless every worker of `client` runs this code (:func:`code_fingerprint`;
    no metampc at all counts as another)."""
    check_workers(client, code_fingerprint, 'this version of metampc')


def run_seeds(client, out_dir: str, seeds: Sequence[int], landed: Callable[[int], None],
              progress: bool = False) -> None:
    """Run `seeds` of the experiment in `out_dir` (its config.yaml written) on `client`'s
    cluster; as each seed's folder lands in `out_dir`, ``landed(seed)`` (e.g. its report).

    Raises:
        ExperimentError: a seed failed (the others ran to their end).
        KeyboardInterrupt: Ctrl-C or SIGTERM (the jobs stopped, their children's nodes too;
            the folders they had made landed, marked incomplete).
        SchedulerLost: the scheduler is gone (the seeds finished by then landed).
    """
    with open(os.path.join(out_dir, 'config.yaml')) as f:
        config_text = f.read()
    failed: List[str] = []
    finished: List[int] = []

    def done(seed: int, outcome: SeedOutcome) -> None:
        _unpack(outcome.folder, out_dir, seed)
        if outcome.status == INTERRUPTED:
            mark_incomplete(seed_dir(out_dir, seed), 'interrupted')
            return
        if outcome.status != 0:
            mark_incomplete(seed_dir(out_dir, seed), f'failed (exit status {outcome.status})')
            failed.append(f'seed {seed} (exit status {outcome.status}; logs in '
                          f'{seed_dir(out_dir, seed)}/logs)')
            log.warning('seed %d failed (exit status %d); its last lines:\n%s', seed,
                        outcome.status, outcome.tail)
            return
        landed(seed)
        finished.append(seed)
        log.info('seed %d: done (%d of %d)', seed, len(finished), len(seeds))

    try:
        errors = run_batch(client, functools.partial(run_seed, config_text), seeds, 'seeds',
                           done, progress)
    except SchedulerLost as err:
        raise SchedulerLost(f'{err}: {len(finished)} of {len(seeds)} seeds finished in '
                            f'{out_dir}; the same command runs the others') from None
    failed += [f'seed {seed} ({err.__class__.__name__}: {err})' for seed, err in errors]
    if failed:
        raise ExperimentError('failed: ' + ', '.join(failed))


def _unpack(folder: bytes, out_dir: str, seed: int) -> None:
    """The seed's folder from its tar into `out_dir`, whole or not at all."""
    if not folder:
        return
    with tempfile.TemporaryDirectory(prefix=f'.seed_{seed}-', dir=out_dir) as landing:
        with tarfile.open(fileobj=io.BytesIO(folder)) as tar:
            tar.extractall(landing, filter='data')
        os.rename(seed_dir(landing, seed), seed_dir(out_dir, seed))


def run_seed(config_text: str, seed: int) -> SeedOutcome:
    """The job of one seed, on a worker: its child in a scratch folder, then the folder."""
    from distributed import get_worker
    if job_cancelled():     # stopped before it started: nothing to send back
        return SeedOutcome(INTERRUPTED, b'', '')
    with tempfile.TemporaryDirectory(prefix=f'seed_{seed}-',
                                     dir=get_worker().local_directory) as work:
        with open(os.path.join(work, 'config.yaml'), 'w') as f:
            f.write(config_text)
        # Forked by this thread, which waits for it: the child's lifeline holds.
        child = subprocess.Popen(
            [sys.executable, '-m', 'metampc_bringup.orchestration.seed_jobs', work, str(seed)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            start_new_session=True, env=child_env(), text=True)
        tail: Deque[str] = collections.deque(maxlen=TAIL_LINES)
        reader = threading.Thread(target=_tee, args=(child.stdout, tail), daemon=True)
        reader.start()
        try:
            while child.poll() is None:
                if job_cancelled():
                    _stop(child)
                    break
                try:
                    child.wait(POLL_S)
                except subprocess.TimeoutExpired:
                    continue
        finally:
            if child.poll() is None:    # the job itself failed: nothing of it stays
                _stop(child)
        reader.join(STOP_S)
        return SeedOutcome(child.returncode, _tar(work, seed), ''.join(tail))


def _tee(stream, tail: Deque[str]) -> None:
    """The child's output to this worker's (the client's, on the embedded cluster) and the
    last lines into `tail`."""
    for line in stream:
        sys.stdout.write(line)
        sys.stdout.flush()
        tail.append(line)


def _tar(work: str, seed: int) -> bytes:
    folder = seed_dir(work, seed)
    if not os.path.isdir(folder):
        return b''
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode='w') as tar:
        tar.add(folder, arcname=os.path.basename(folder))
    return buffer.getvalue()


def _stop(child: subprocess.Popen) -> None:
    """SIGINT to the child (its orchestrator stops its nodes, recorder last), then wait."""
    child.send_signal(signal.SIGINT)
    try:
        child.wait(STOP_S)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait()


def _interrupt_once(signum, frame) -> None:
    """The first SIGINT or SIGTERM stops the seed (KeyboardInterrupt); later ones, e.g. the
    lifeline's when the worker ends after cancelling the job, would cut its nodes' stopping
    short, and are ignored."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    raise KeyboardInterrupt(f'signal {signum}')


def child_main(argv: Sequence[str]) -> int:
    """One seed of the run folder argv[0] (its config.yaml), seed argv[1]; the exit status."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _interrupt_once)
    out_dir, seed = argv[0], int(argv[1])
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    try:
        hold(signal.SIGINT)    # the worker killed: stop the nodes as on Ctrl-C
        from metampc_bringup.orchestration.domain import isolated
        from metampc_bringup.experiment_config import load
        from metampc_bringup.orchestration.orchestrator import SeedRun
        config = load(os.path.join(out_dir, 'config.yaml'))
        with isolated() as domain:
            log.info('seed %d: ROS_DOMAIN_ID=%d (localhost discovery)', seed, domain)
            SeedRun(config, seed, seed_dir(out_dir, seed), progress=False).run()
    except ExperimentError as err:
        print(f'run_experiment: seed {seed} failed: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return INTERRUPTED
    return 0


def exit_now(status: int) -> None:
    """End the seed child with `status` once its output is flushed, without the interpreter's
    teardown: a Ctrl-C that lands while the orchestrator closes its client node can leave the
    node's daemon spin thread inside rclpy, and the C++ destructors at a normal exit then
    abort the process (seen once in CI: 'terminate called without an active exception', exit
    status -6, after the seed had stopped its nodes)."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


if __name__ == '__main__':
    exit_now(child_main(sys.argv[1:]))
