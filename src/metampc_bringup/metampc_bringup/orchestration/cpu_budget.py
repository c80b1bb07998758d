"""Parallel jobs within the machine's cores: jobs x torch threads per job <= usable cores.

Shared by every command with ``--jobs`` (run_experiment.py, tune.py, sweep_inner_steps.py,
robustness.py). More threads than cores only makes the jobs take turns (and their wall times
noisy); the thread count is never changed behind the user's back, since it is part of what
makes a run reproducible (torch reductions depend on it).
"""
import os


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. a container's limit)."""
    return len(os.sched_getaffinity(0))


def check_jobs(jobs: int, threads: int, threads_name: str = '--threads') -> None:
    """ValueError unless jobs >= 1, threads >= 1 and jobs x threads <= the usable cores.

    One job may use more threads than there are cores (the user's choice, as before); only
    parallel jobs are held to the budget.
    """
    if jobs < 1:
        raise ValueError(f'--jobs must be >= 1, got {jobs}')
    if threads < 1:
        raise ValueError(f'{threads_name} must be >= 1, got {threads}')
    cores = usable_cores()
    if jobs > 1 and jobs * threads > cores:
        raise ValueError(f'--jobs {jobs} x {threads_name} {threads} = {jobs * threads} exceeds '
                         f'the {cores} usable cores: the jobs would take turns on them')
