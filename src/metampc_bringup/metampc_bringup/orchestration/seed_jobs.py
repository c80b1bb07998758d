"""Seeds in parallel: ``run_experiment.py --jobs N`` runs up to N seeds at once.

Each seed runs in a child process (``python -m metampc_bringup.orchestration.seed_jobs OUT
SEED``) with a ROS domain (:mod:`.domain`) and a session of its own, running
:class:`.orchestrator.SeedRun` as the one-process experiment does; the parent starts no node
and no rclpy, keeps N children running and merges their reports. A lockstep seed's report
equals that of ``--jobs 1``. A child dies with the parent (:mod:`.lifeline`); Ctrl-C or SIGTERM
in the parent starts no new seed and sends SIGINT to every running child (each stops its nodes,
recorder last). A seed that fails lets the running ones finish and raises
:class:`.experiment_client.ExperimentError` naming it. Measured: docs/speed.md#seeds-in-parallel.
"""
import logging
import os
import signal
import subprocess
import sys
import time
from typing import Dict, List, Sequence

from metampc_bringup.orchestration.experiment_client import ExperimentError
from metampc_bringup.orchestration.lifeline import child_env, hold
from metampc_bringup.orchestration.processes import signals_held

log = logging.getLogger('metampc.seed_jobs')

POLL_S = 0.2            # how often the parent looks at its children
STOP_S = 120.0          # s for an interrupted child to stop its nodes before SIGKILL
INTERRUPTED = 130       # a child's exit status after Ctrl-C


def seed_dir(out_dir: str, seed: int) -> str:
    """The folder of one seed's run inside the run folder."""
    return os.path.join(out_dir, f'seed_{seed}')


def run_seeds(out_dir: str, seeds: Sequence[int], jobs: int) -> None:
    """Run `seeds` of the experiment in `out_dir` (its config.yaml written) in `jobs` children.

    Raises:
        ExperimentError: a seed failed (the others ran to their end).
        KeyboardInterrupt: Ctrl-C or SIGTERM (every child stopped first).
    """
    pending: List[int] = list(seeds)
    running: Dict[int, subprocess.Popen] = {}
    failed: List[str] = []
    try:
        while pending or running:
            while pending and not failed and len(running) < jobs:
                _start(out_dir, pending.pop(0), running)
            time.sleep(POLL_S)
            for seed, child in list(running.items()):
                if child.poll() is None:
                    continue
                del running[seed]
                if child.returncode == 0:
                    log.info('seed %d: done (%d of %d)', seed,
                             len(seeds) - len(pending) - len(running) - len(failed), len(seeds))
                else:
                    failed.append(f'seed {seed} (exit status {child.returncode}; logs in '
                                  f'{seed_dir(out_dir, seed)}/logs)')
                    if pending:
                        log.warning('seed %d failed: no new seed starts; %d running go on',
                                    seed, len(running))
    except KeyboardInterrupt:
        _stop(running.values())
        raise
    if failed:
        raise ExperimentError('failed: ' + ', '.join(failed)
                              + (f'; not run: seeds {pending}' if pending else ''))


def _start(out_dir: str, seed: int, running: Dict[int, subprocess.Popen]) -> None:
    # A Ctrl-C between the fork and the bookkeeping would leave a child that the parent does
    # not stop: it is held until the child is in `running`.
    with signals_held():
        running[seed] = subprocess.Popen(
            [sys.executable, '-m', 'metampc_bringup.orchestration.seed_jobs', out_dir, str(seed)],
            stdin=subprocess.DEVNULL, start_new_session=True, env=child_env())


def _stop(children) -> None:
    """SIGINT to each child (its orchestrator stops its nodes, recorder last), then wait."""
    children = list(children)
    for child in children:
        if child.poll() is None:
            child.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_S
    for child in children:
        try:
            child.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()


def child_main(argv: Sequence[str]) -> int:
    """One seed of the run folder argv[0] (its config.yaml), seed argv[1]; the exit status."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    out_dir, seed = argv[0], int(argv[1])
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s',
                        datefmt='%H:%M:%S')
    try:
        hold(signal.SIGINT)    # the parent killed: stop the nodes as on Ctrl-C
        from metampc_bringup.orchestration.domain import isolated
        from metampc_bringup.experiment_config import load
        from metampc_bringup.orchestration.orchestrator import SeedRun, terminate_as_interrupt
        config = load(os.path.join(out_dir, 'config.yaml'))
        with terminate_as_interrupt(), isolated() as domain:
            log.info('seed %d: ROS_DOMAIN_ID=%d (localhost discovery)', seed, domain)
            SeedRun(config, seed, seed_dir(out_dir, seed), progress=False).run()
    except ExperimentError as err:
        print(f'run_experiment: seed {seed} failed: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return INTERRUPTED
    return 0


if __name__ == '__main__':
    sys.exit(child_main(sys.argv[1:]))
