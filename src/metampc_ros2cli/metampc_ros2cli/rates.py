"""The statistics of `ros2 topic hz` and `ros2 topic bw`, over a window of received messages.

Pure Python: times are integers in ns of the clock the verb uses (node clock, or wall time with
``--wall-time``). The printed lines are ros2cli's (Jazzy).
"""
import math
from collections import deque
from typing import Deque, Optional, Tuple

HZ_WINDOW = 10000      # messages, ros2 topic hz's default window
BW_WINDOW = 100        # messages, ros2 topic bw's default window
PRINT_EVERY_NS = 10 ** 9


class RateWindow:
    """Intervals between the last `window` messages; a report at most once per second."""

    def __init__(self, window: int = HZ_WINDOW) -> None:
        self.intervals: Deque[int] = deque(maxlen=window)
        self.last_ns = -1
        self.printed_ns = 0

    def add(self, now_ns: int) -> Optional[str]:
        """A message received at `now_ns`; a line to print, or None.

        A clock that went back (a replayed or reset sim time) restarts the window.
        """
        if now_ns == 0:
            self.intervals.clear()
            return None
        if self.last_ns < 0 or now_ns < self.last_ns:
            self.intervals.clear()
            self.printed_ns = 0
        else:
            self.intervals.append(now_ns - self.last_ns)
        self.last_ns = now_ns
        return self.report()

    def stats(self) -> Tuple[float, float, float, float, int]:
        """(rate Hz, min s, max s, std dev s, window) of the intervals held."""
        n = len(self.intervals)
        mean = sum(self.intervals) / n
        std = math.sqrt(sum((x - mean) ** 2 for x in self.intervals) / n)
        return (1e9 / mean if mean > 0 else 0.0, min(self.intervals) * 1e-9,
                max(self.intervals) * 1e-9, std * 1e-9, n)

    def report(self) -> Optional[str]:
        """ros2cli's two lines, once a second of message time has passed since the last."""
        if not self.intervals:
            return None
        if self.printed_ns == 0:
            self.printed_ns = self.last_ns
            return None
        if self.last_ns < self.printed_ns + PRINT_EVERY_NS:
            return None
        self.printed_ns = self.last_ns
        rate, low, high, std, n = self.stats()
        return (f'average rate: {rate:.3f}\n\tmin: {low:.3f}s max: {high:.3f}s '
                f'std dev: {std:.5f}s window: {n}')


def _size(num: float, unit: str) -> str:
    return {'B': f'{num:.0f} B', 'KB': f'{num / 1e3:.2f} KB', 'MB': f'{num / 1e6:.2f} MB'}[unit]


class BandwidthWindow:
    """Receipt times and serialized sizes of the last `window` messages."""

    def __init__(self, window: int = BW_WINDOW) -> None:
        self.samples: Deque[Tuple[int, int]] = deque(maxlen=window)

    def add(self, now_ns: int, size: int) -> None:
        """A message of `size` bytes (CDR) received at `now_ns`."""
        self.samples.append((now_ns, size))

    def report(self, now_ns: int) -> Optional[str]:
        """ros2cli's two lines for the window at `now_ns`, or None with under two messages."""
        if len(self.samples) < 2:
            return None
        t0 = self.samples[0][0]
        if now_ns <= t0:
            self.samples.clear()
            return None
        sizes = [s for _, s in self.samples]
        per_s = sum(sizes) / ((now_ns - t0) * 1e-9)
        unit = 'B' if per_s < 1e3 else 'KB' if per_s < 1e6 else 'MB'
        mean = sum(sizes) / len(sizes)
        return (f'{_size(per_s, unit)}/s from {len(sizes)} messages\n\tMessage size mean: '
                f'{_size(mean, unit)} min: {_size(min(sizes), unit)} '
                f'max: {_size(max(sizes), unit)}')
