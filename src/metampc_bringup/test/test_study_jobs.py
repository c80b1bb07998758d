"""The offline studies' jobs on the cluster layer (metampc_bringup.studies.study_jobs): a job
gives the result of a direct call (the process pool's before), on a worker that served other
settings before too and in a fresh process; a job that raises is reported with its error
after the others finished and were cached; the same call again runs only what is missing."""
import functools
import os
import signal
import threading
import time

import pytest

from metampc_bringup.orchestration.cluster import ClusterSpec, job_cancelled
from metampc_bringup.studies.learning_setup import Job, settings_from
from metampc_bringup.studies.study_jobs import (ResultCache, run_jobs, study_cluster,
                                                StudyError)
from metampc_bringup.studies.sweep import measured_run

FAILING = set()     # indices of the jobs that _made_up raises for


def _made_up(job: Job) -> dict:
    if job.index in FAILING:
        raise RuntimeError(f'boom {job.index}')
    return {'index': job.index, 'score': 1.0 / (1 + job.index)}


def _jobs():
    maml = Job('maml', 0, {'inner_steps': 2}, 3, (0.05, 0.2), 'search')
    return [maml, Job('imaml', 1, {'inner_steps': 2, 'gamma': 1.0, 'cg_steps': 2}, 3, (0.2,),
                      'search'), Job('supervised', 0, {}, 0, (0.2,), 'search')]


def test_jobs_on_two_workers_give_the_results_of_direct_calls(tmp_path, tiny_config, direct,
                                                              untimed):
    """Then the same maml job with other settings (two validation targets, the same source
    seed) on workers that built the first settings' set-up: its own targets, not those."""
    one, two = (settings_from(str(tiny_config), n, 3) for n in (1, 2))
    jobs = _jobs()
    with study_cluster(ClusterSpec(2)) as client:
        first = run_jobs(client, jobs, 'one', one, ResultCache(str(tmp_path / 'one'), one),
                         progress=False)
        second = run_jobs(client, jobs[:1], 'two', two, ResultCache(str(tmp_path / 'two'), two),
                          progress=False)
        fresh = run_jobs(client, jobs[:1], 'fresh', one,
                         ResultCache(str(tmp_path / 'fresh'), one), measured_run, fresh=True,
                         progress=False)
    assert [untimed(r) for r in first] == [direct(one, job) for job in jobs]
    assert untimed(second[0]) == direct(two, jobs[0])
    assert len(second[0]['adapt'][0]['heldout_final']) == 2
    assert untimed(fresh[0]) == direct(one, jobs[0], measured_run)
    assert fresh[0]['peak_rss_mb'] > 0


class Counting:
    """A dask client that counts the jobs submitted to it."""

    def __init__(self, client):
        self.client, self.submitted = client, 0

    def submit(self, *args, **kwargs):
        self.submitted += 1
        return self.client.submit(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.client, name)


@pytest.fixture
def threads_cluster():
    """A dask cluster of one one-slot worker thread in this process (the jobs see this
    process's state, e.g. FAILING; they set its torch threads, restored after)."""
    import torch
    from distributed import Client, LocalCluster
    threads = torch.get_num_threads()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None, resources={'slot': 1}) as cluster, \
            Client(cluster, set_as_default=False) as client:
        yield client
    torch.set_num_threads(threads)


def test_a_job_that_raises_is_reported_after_the_others_and_the_rerun_runs_only_it(
        tmp_path, tiny_config, threads_cluster):
    settings = settings_from(str(tiny_config), 1, 3)
    cache = ResultCache(str(tmp_path / 'cache'), settings)
    jobs = [Job('maml', i, {}, 1, (), 'search') for i in range(4)]
    FAILING.add(1)
    run = functools.partial(run_jobs, fn=_made_up, progress=False)
    try:
        with pytest.raises(StudyError, match=r'1 of 4 search job\(s\) raised \(first: '
                                             r'maml-search-1-seed1000: RuntimeError: boom 1\); '
                                             r'the 3 others are cached'):
            run(threads_cluster, jobs, 'search', settings, cache)
    finally:
        FAILING.clear()
    assert [cache.get(job) is not None for job in jobs] == [True, False, True, True]
    landed = []
    counting = Counting(threads_cluster)
    results = run(counting, jobs, 'search', settings, cache,
                  landed=lambda job, result: landed.append(job.index))
    assert counting.submitted == 1
    assert results == [_made_up(job) for job in jobs]
    assert landed == [0, 2, 3, 1]      # the cached ones first
    counting = Counting(threads_cluster)
    assert run(counting, jobs, 'search', settings, cache) == results
    assert counting.submitted == 0


STARTED = []        # indices of the jobs whose function _until_asked ran


def _until_asked(job: Job) -> dict:
    """Runs until the client asks its jobs to stop (Ctrl-C), then sends back its result."""
    STARTED.append(job.index)
    while not job_cancelled():
        time.sleep(0.02)
    return _made_up(job)


def test_ctrl_c_starts_no_waiting_job_and_keeps_the_running_one_s_result(
        tmp_path, tiny_config, threads_cluster):
    """Four jobs on one slot, Ctrl-C while the first runs: it sends back its result (cached),
    the three waiting for the slot never start (before: each ran to its end while the client
    drained, up to 180 s), and the same call runs only them."""
    settings = settings_from(str(tiny_config), 1, 3)
    cache = ResultCache(str(tmp_path / 'cache'), settings)
    jobs = [Job('maml', i, {}, 1, (), 'search') for i in range(4)]

    def ctrl_c():
        while not STARTED:
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)
    threading.Thread(target=ctrl_c, daemon=True).start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run_jobs(threads_cluster, jobs, 'search', settings, cache, fn=_until_asked,
                     progress=False)
        assert STARTED == [0]
    finally:
        STARTED.clear()
    assert [cache.get(job) is not None for job in jobs] == [True, False, False, False]
    counting = Counting(threads_cluster)
    assert run_jobs(counting, jobs, 'search', settings, cache, fn=_made_up,
                    progress=False) == [_made_up(job) for job in jobs]
    assert counting.submitted == 3
