"""The /proc readers on this test process, against the kernel's other accounts of it
(os.times, getrusage, ps) and a known allocation."""
import os
import resource
import subprocess
import time

import numpy as np
import pytest

from metampc_bringup.orchestration import procfs

NO_PID = 2**22      # above any pid_max: no such process


def _burn(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_cpu_seconds_agrees_with_os_times():
    _burn(0.3)
    before = os.times()
    ours = procfs.cpu_seconds(os.getpid())
    after = os.times()
    # Both count in clock ticks; os.times covers the same process (all threads).
    assert before.user + before.system - 0.02 <= ours <= after.user + after.system + 0.02
    assert ours >= 0.3 - 0.02


def test_live_cpu_seconds_sums_and_skips_processes_that_are_gone():
    pids = [os.getpid(), os.getpid(), NO_PID]
    assert procfs.live_cpu_seconds(pids) == pytest.approx(
        2 * procfs.cpu_seconds(os.getpid()), abs=0.05)
    assert procfs.live_cpu_seconds([]) == 0.0


def test_rss_grows_by_an_allocation_and_matches_ps():
    before = procfs.rss_bytes(os.getpid())
    block = np.ones(64 * 2**20, dtype=np.uint8)       # 64 MiB, every page touched
    grown = procfs.rss_bytes('self') - before
    assert 56 * 2**20 <= grown <= 72 * 2**20
    ps = subprocess.run(['ps', '-o', 'rss=', '-p', str(os.getpid())], capture_output=True,
                        text=True, check=True)
    assert procfs.rss_bytes(os.getpid()) == pytest.approx(int(ps.stdout) * 1024, rel=0.05)
    del block


def test_status_fields_and_peak_reset():
    rss_kib = procfs.status_kib('VmRSS')
    assert rss_kib * 1024 == pytest.approx(procfs.rss_bytes(os.getpid()), rel=0.05)
    # getrusage's peak (KiB on Linux) is the process's high-water mark as well
    assert procfs.status_kib('VmHWM', os.getpid()) == pytest.approx(
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, rel=0.05)
    block = np.ones(64 * 2**20, dtype=np.uint8)
    del block
    assert procfs.status_kib('VmHWM') - procfs.status_kib('VmRSS') >= 56 * 1024
    procfs.reset_peak_rss()
    assert procfs.status_kib('VmHWM') - procfs.status_kib('VmRSS') < 8 * 1024
    with pytest.raises(RuntimeError, match='NoSuchField'):
        procfs.status_kib('NoSuchField')


def test_sampler_samples_until_stopped():
    sampler = procfs.UsageSampler({'me': os.getpid(), 'gone': NO_PID}, period=0.05)
    start = time.monotonic_ns()
    sampler.start()
    time.sleep(0.3)
    sampler.stop()
    me = list(sampler.samples['me'])
    assert sampler.samples['gone'] == [] and len(me) >= 2
    times = [t for t, _, _ in me]
    assert times == sorted(times) and times[0] >= start
    assert min(b - a for a, b in zip(times, times[1:])) >= 0.05e9 * 0.9
    assert all(rss > 0 and cpu > 0 for _, rss, cpu in me)
    time.sleep(0.1)
    assert sampler.samples['me'] == me      # none after stop
