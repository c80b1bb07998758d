"""What Linux's /proc says about a process: resident memory, CPU time and /proc/PID/status
fields, read once or sampled once a second.

Used by the soak and the benchmarks to watch node processes and themselves. No rclpy here.
"""
import contextlib
import math
import os
import threading
import time
from typing import Dict, Iterable, List, Mapping, Tuple, Union

PAGE = os.sysconf('SC_PAGE_SIZE')     # bytes per page of /proc/PID/statm
TICKS = os.sysconf('SC_CLK_TCK')      # clock ticks per s of /proc/PID/stat
Pid = Union[int, str]                 # a pid or 'self'


def rss_bytes(pid: Pid) -> int:
    """Resident set size of a process now, bytes."""
    with open(f'/proc/{pid}/statm') as f:
        return int(f.read().split()[1]) * PAGE


def cpu_seconds(pid: Pid) -> float:
    """User + system CPU time of a process so far, s."""
    with open(f'/proc/{pid}/stat') as f:
        # after the command name, which may itself hold ') '
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS     # utime, stime (fields 14 and 15)


def live_cpu_seconds(pids: Iterable[int]) -> float:
    """:func:`cpu_seconds` summed over those of `pids` that still exist, s."""
    total = 0.0
    for pid in pids:
        with contextlib.suppress(OSError):      # ended since it was listed
            total += cpu_seconds(pid)
    return total


def status_kib(field: str, pid: Pid = 'self') -> int:
    """A KiB field of /proc/PID/status (e.g. 'VmRSS', or 'VmHWM': the peak RSS)."""
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith(field + ':'):
                return int(line.split()[1])
    raise RuntimeError(f'{field} not in /proc/{pid}/status')


def reset_peak_rss(pid: Pid = 'self') -> None:
    """Set the peak RSS (VmHWM) to the RSS now (Linux >= 4.0)."""
    with open(f'/proc/{pid}/clear_refs', 'w') as f:
        f.write('5')


def uptime_s() -> float:
    """Seconds since boot: the clock of the start times in /proc/PID/stat."""
    with open('/proc/uptime') as f:
        return float(f.read().split()[0])


def pids_with_env(env: Mapping[str, str], started_before: float = math.inf) -> List[int]:
    """Running processes (zombies excluded) whose initial environment holds every key=value
    of `env` and that started before `started_before` (s since boot, :func:`uptime_s`).

    A process's own later changes to its environment are not seen (/proc/PID/environ is
    the one it was started with)."""
    wanted = {f'{key}={value}'.encode() for key, value in env.items()}
    pids = []
    for entry in filter(str.isdigit, os.listdir('/proc')):
        try:
            with open(f'/proc/{entry}/environ', 'rb') as f:
                if not wanted <= set(f.read().split(b'\0')):
                    continue
            with open(f'/proc/{entry}/stat') as f:
                fields = f.read().rsplit(')', 1)[1].split()
        except OSError:     # ended, or not ours to read
            continue
        if fields[0] != 'Z' and int(fields[19]) / TICKS < started_before:
            pids.append(int(entry))
    return pids


class UsageSampler(threading.Thread):
    """RSS and CPU time of named processes every `period` s from :meth:`start` to :meth:`stop`.

    Attributes:
        samples: name -> [(monotonic ns, RSS bytes, CPU s)]; a process that has ended gets no
            further samples.
    """

    def __init__(self, pids: Dict[str, int], period: float = 1.0):
        super().__init__(daemon=True)
        self.pids = pids
        self.period = period
        self.samples: Dict[str, List[Tuple[int, int, float]]] = {name: [] for name in pids}
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            now = time.monotonic_ns()
            for name, pid in self.pids.items():
                with contextlib.suppress(OSError):
                    self.samples[name].append((now, rss_bytes(pid), cpu_seconds(pid)))
            self._halt.wait(self.period)

    def stop(self) -> None:
        self._halt.set()
        self.join()
