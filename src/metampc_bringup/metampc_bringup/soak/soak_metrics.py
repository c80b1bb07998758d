"""The measures of a real-time soak (:mod:`metampc_bringup.soak.realtime_soak`), on what an
observer received and on process samples.

In, each in the order received, times in monotonic ns at the observer: ys [(t, step,
u_applied)], us [(t, step, u, model_version)], statuses [(t, step, tick_time s, solve_time s,
fallback)] and samples name -> [(t, RSS bytes, CPU s)]; only what arrived from ``start_ns`` on
is measured. Out: deadline misses (a step whose answer was not applied at step k + 1: late,
unanswered; ambiguous when the answer equals the previous one), dropped messages, and per
process RSS at start and end, peak, growth and CPU share. Goals: misses <= 0.1 % and RSS growth
<= 5 %. Definitions: docs/faults.md#real-time-soak. No rclpy here.
"""
import math
import re
from typing import Dict, List, Sequence, Tuple

GOALS = {'deadline_miss_pct': 0.1, 'rss_growth_pct': 5.0}
OUTCOMES = ('hit', 'late', 'unanswered', 'ambiguous')
STOP_LINE = 'stopped at step'     # a metampc node's last log line


def deadlines(ys: Sequence[tuple], us: Sequence[tuple], start_ns: int) -> Dict[str, object]:
    """Deadline misses among the steps k whose y_k arrived from start_ns on and whose y_{k+1}
    arrived.

    Returns:
        steps (decided: hit, late or unanswered), misses, late, unanswered, ambiguous,
        miss_pct (of steps; nan without any), and for the figure outcome (step -> one of
        :data:`OUTCOMES`) and arrived (step -> t of y_k, ns).
    """
    applied = {step: u for _, step, u in ys}
    arrived = {step: t for t, step, _ in ys}
    answer = {}
    for _, step, u, _ in us:
        answer.setdefault(step, u)
    outcome = {}
    for step, t in arrived.items():
        if t < start_ns or step + 1 not in applied:
            continue
        if step not in answer:
            outcome[step] = 'unanswered'
        elif answer[step] == answer.get(step - 1):
            outcome[step] = 'ambiguous'
        else:
            outcome[step] = 'hit' if applied[step + 1] == answer[step] else 'late'
    counts = {kind: sum(o == kind for o in outcome.values()) for kind in OUTCOMES}
    decided = counts['hit'] + counts['late'] + counts['unanswered']
    misses = counts['late'] + counts['unanswered']
    return {'steps': decided, 'misses': misses, 'late': counts['late'],
            'unanswered': counts['unanswered'], 'ambiguous': counts['ambiguous'],
            'miss_pct': round(100.0 * misses / decided, 4) if decided else math.nan,
            'outcome': outcome, 'arrived': arrived}


def dropped(ys: Sequence[tuple], us: Sequence[tuple], statuses: Sequence[tuple],
            start_ns: int) -> Dict[str, int]:
    """Messages lost on the way, among the steps whose y arrived from start_ns on.

    Returns:
        y_missing: steps between the first and the last received that never arrived;
        u_missing: received steps without an answer (but the last, whose answer may still
        have been on its way); status_missing: answered steps without an mpc_status.
    """
    steps = sorted(step for t, step, _ in ys if t >= start_ns)
    answered = {step for _, step, _, _ in us}
    reported = {step for _, step, *_ in statuses}
    window = set(steps)
    return {'y_missing': (steps[-1] - steps[0] + 1 - len(window)) if steps else 0,
            'u_missing': len(window - answered - {steps[-1] if steps else None}),
            'status_missing': len({s for s in answered if s in window} - reported)}


def responses(ys: Sequence[tuple], us: Sequence[tuple], start_ns: int = 0
              ) -> List[Tuple[int, int]]:
    """[(t of y_k, response ns)]: y_k received -> the answer to step k received (its last
    copy), for the answered steps whose y arrived from start_ns on, in the order of ys."""
    sent = {step: t for t, step, _, _ in us}
    return [(t, sent[step] - t) for t, step, _ in ys if t >= start_ns and step in sent]


def process_usage(samples: Dict[str, Sequence[Tuple[int, int, float]]], start_ns: int
                  ) -> Dict[str, Dict[str, float]]:
    """Per process with two samples or more from start_ns on: rss_start_mb, rss_end_mb,
    rss_peak_mb (MiB), growth_pct (of the start) and cpu_pct (100: one core busy)."""
    out = {}
    for name, series in samples.items():
        after = [s for s in series if s[0] >= start_ns]
        if len(after) < 2:
            continue
        (t0, first, cpu0), (t1, last, cpu1) = after[0], after[-1]
        out[name] = {'rss_start_mb': round(first / 2**20, 1), 'rss_end_mb': round(last / 2**20, 1),
                     'rss_peak_mb': round(max(s[1] for s in after) / 2**20, 1),
                     'growth_pct': round(100.0 * (last - first) / first, 2),
                     'cpu_pct': round(100.0 * (cpu1 - cpu0) / ((t1 - t0) / 1e9), 1)}
    return out


def goals_met(deadline: Dict[str, object], usage: Dict[str, Dict[str, float]]) -> bool:
    """Both :data:`GOALS`: the miss percentage and every process's RSS growth."""
    return bool(deadline['miss_pct'] <= GOALS['deadline_miss_pct'] and all(
        m['growth_pct'] <= GOALS['rss_growth_pct'] for m in usage.values()))


def observed_rate(ys: Sequence[tuple]) -> float:
    """Rate of y at the observer, Hz (nan with fewer than two)."""
    if len(ys) < 2:
        return math.nan
    return (len(ys) - 1) / ((ys[-1][0] - ys[0][0]) / 1e9)


def stop_counts(text: str) -> Dict[str, int]:
    """The counters of a node's last stop line in its output `text` ('... stopped at step N
    after 0 reset(s): 3 stale, 0 rejected, ...'); {} without one."""
    lines = [line for line in text.splitlines() if STOP_LINE in line]
    if not lines:
        return {}
    counts = lines[-1].split(STOP_LINE, 1)[1].split(':', 1)[-1]
    return {name: int(n) for n, name in re.findall(r'(\d+) (\w+)', counts)}
