"""The learning studies' jobs (:mod:`.learning_setup`) on the cluster layer
(:mod:`metampc_bringup.orchestration.cluster`): ``--jobs N`` or ``--scheduler ADDRESS`` of
robustness.py, sweep_inner_steps.py and tune.py.

A job (``fn(job)``, default :func:`.learning_setup.run_job`) runs on a worker with the study's
settings and torch threads (:func:`.learning_setup.use`), or with ``fresh`` in a child process of
its own (the sweep's peak RSS per run; the child dies with the worker,
:mod:`..orchestration.lifeline`). Its result comes back to the client (no shared filesystem),
which keeps it in the study's :class:`ResultCache` as soon as it lands: a stopped study resumes
with only the missing jobs. A job that raises is reported with its error (:class:`StudyError`)
after the others finished.
"""
import contextlib
import dataclasses
import functools
import json
import logging
import os
import pickle
import subprocess
import sys
import tempfile
from typing import Any, Callable, Iterator, List, Optional, Sequence, Tuple, TypeVar

from metampc_bringup.orchestration.cluster import (ClusterError, ClusterSpec, connect,
                                                   job_cancelled, run_batch, SchedulerLost)
from metampc_bringup.orchestration.lifeline import child_env, hold
from metampc_bringup.studies.learning_setup import Job, run_job, Settings, use

log = logging.getLogger('metampc.study_jobs')

T = TypeVar('T')
TAIL_LINES = 20     # lines of a failed child's stderr in its error


class StudyError(Exception):
    """Jobs of a study raised; the others finished and are in the cache."""


class ResultCache:
    """The results of finished jobs on the client's disk, ``<folder>/<key>.json`` (the key:
    :meth:`.learning_setup.Job.key` of the job and the settings), written whole or not at all."""

    def __init__(self, folder: str, settings: Settings):
        self.folder = folder
        self.settings = settings
        os.makedirs(folder, exist_ok=True)

    def _path(self, job: Job) -> str:
        return os.path.join(self.folder, f'{job.key(self.settings)}.json')

    def get(self, job: Job) -> Optional[dict]:
        """The job's result, or None when it has not run."""
        path = self._path(job)
        if not os.path.exists(path):
            return None
        with open(path) as f:
            return json.load(f)

    def put(self, job: Job, result: dict) -> None:
        """Keep the job's result (Python's json keeps inf and nan, the scores of failed
        runs)."""
        path = self._path(job)
        with open(path + '.tmp', 'w') as f:
            json.dump(result, f)
        os.replace(path + '.tmp', path)     # a kill never leaves half a result


def run_jobs(client, jobs: Sequence[Job], what: str, settings: Settings, cache: ResultCache,
             fn: Callable[[Job], dict] = run_job, threads: int = 1, fresh: bool = False,
             landed: Optional[Callable[[Job, dict], None]] = None,
             progress: bool = True) -> List[dict]:
    """The results of `jobs` (in their order): from `cache`, or run on `client`'s cluster,
    longest first (:meth:`.learning_setup.Job.cost`), each cached as it lands. ``landed(job,
    result)`` for each, cached ones first. `what` labels the progress line.

    Raises:
        StudyError: jobs raised (the others ran to their end and are cached).
        SchedulerLost: the scheduler is gone (the jobs done by then are cached).
    """
    results: List[Optional[dict]] = [cache.get(job) for job in jobs]
    todo = sorted((i for i, r in enumerate(results) if r is None), key=lambda i: -jobs[i].cost())
    if landed is not None:
        for job, result in zip(jobs, results):
            if result is not None:
                landed(job, result)
    if not todo:
        return results
    log.info('%s: %d job(s) to run, %d cached in %s', what, len(todo), len(jobs) - len(todo),
             cache.folder)
    position = {id(jobs[i]): i for i in todo}

    def done(job: Job, result: dict) -> None:
        if isinstance(result, NotStarted):
            return
        cache.put(job, result)
        results[position[id(job)]] = result
        if landed is not None:
            landed(job, result)

    failed = run_batch(client, functools.partial(_on_worker, fn, settings, threads, fresh),
                       [jobs[i] for i in todo], what, done, progress)
    if failed:
        for job, err in failed:
            log.warning('%s: job %s raised %s: %s', what, job, err.__class__.__name__, err)
        first, err = failed[0]
        raise StudyError(f'{len(failed)} of {len(todo)} {what} job(s) raised (first: {first}: '
                         f'{err.__class__.__name__}: {err}); the {len(todo) - len(failed)} '
                         f'others are cached in {cache.folder}: the same command runs only '
                         'the missing ones')
    return results


@dataclasses.dataclass(frozen=True)
class NotStarted:
    """What a job asked to stop (Ctrl-C) before it started sends back: nothing to cache."""

    job: str


def _on_worker(fn: Callable[[Job], dict], settings: Settings, threads: int, fresh: bool,
               job: Job) -> dict:
    """A job on a worker: here, or with `fresh` in a child process of its own. Asked to stop
    before it started (Ctrl-C while it waited for a slot): :class:`NotStarted` at once."""
    if job_cancelled():
        return NotStarted(str(job))
    if not fresh:
        use(settings, threads)
        return fn(job)
    from distributed import get_worker
    with tempfile.TemporaryDirectory(prefix='job-', dir=get_worker().local_directory) as work:
        given, taken = os.path.join(work, 'job.pickle'), os.path.join(work, 'result.pickle')
        with open(given, 'wb') as f:
            pickle.dump((fn, settings, threads, job), f)
        # Forked by this thread, which waits for it: the child's lifeline holds.
        child = subprocess.run(
            [sys.executable, '-m', 'metampc_bringup.studies.study_jobs', given, taken],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            env=child_env(), text=True)
        if child.returncode != 0:
            tail = '\n'.join(child.stderr.strip().splitlines()[-TAIL_LINES:])
            raise RuntimeError(f'its process ended with exit status {child.returncode}:\n'
                               f'{tail}')
        with open(taken, 'rb') as f:
            return pickle.load(f)


def child_main(argv: Sequence[str]) -> int:
    """A fresh job's process: the pickled (fn, settings, threads, job) of argv[0], its result
    pickled into argv[1]."""
    hold()      # the worker killed: this job ends with it
    with open(argv[0], 'rb') as f:
        fn, settings, threads, job = pickle.load(f)
    use(settings, threads)
    result = fn(job)
    with open(argv[1], 'wb') as f:
        pickle.dump(result, f)
    return 0


@contextlib.contextmanager
def study_cluster(spec: ClusterSpec) -> Iterator[Any]:
    """A client of `spec`'s cluster whose workers run this code
    (:func:`..orchestration.seed_jobs.check_workers_run_this_code`)."""
    from metampc_bringup.orchestration.seed_jobs import check_workers_run_this_code
    with connect(spec) as client:
        check_workers_run_this_code(client)
        yield client


def run_study(prog: str, spec: ClusterSpec, work: Callable[[Any], T]
              ) -> Tuple[int, Optional[T]]:
    """``work(client)`` on `spec`'s cluster (:func:`study_cluster`); (exit status, its value).
    A failure is one line on stderr: 1 jobs raised or the scheduler was lost, 2 the cluster
    refused, not answering or running other code, or a bad argument (ValueError), 130
    Ctrl-C; the finished jobs are cached in each case."""
    try:
        with study_cluster(spec) as client:
            return 0, work(client)
    except StudyError as err:
        print(f'{prog}: {err}', file=sys.stderr)
        return 1, None
    except SchedulerLost as err:
        print(f'{prog}: {err}; the finished jobs are cached: the same command runs the others',
              file=sys.stderr)
        return 1, None
    except (ClusterError, ValueError) as err:
        print(f'{prog}: {err}', file=sys.stderr)
        return 2, None
    except KeyboardInterrupt:
        print(f'{prog}: interrupted; the finished jobs are cached: the same command resumes',
              file=sys.stderr)
        return 130, None


if __name__ == '__main__':
    sys.exit(child_main(sys.argv[1:]))
