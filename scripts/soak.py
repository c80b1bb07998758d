#!/usr/bin/env python3
"""Real-time soak: a realtime plant and the latent-MPC controller for a long run; one JSON line.

The plant runs in ``realtime`` mode (a wall-clock timer at --rate Hz, zero-order hold of the
latest input) and the controller on its own wall-clock timer with a trained model: the
hand-built NSSM of ``metampc_controller.manual_model`` (the plant linearised at the origin,
discretised at the plant's dt) or a checkpoint (--weights). It tracks a sine reference of x1;
a little measurement noise keeps every input distinct. This script observes ``y``, ``u`` and
``mpc_status`` from a third process and samples each process's resident memory once a second.

Reported (after a warm-up that is left out):

* deadline misses: steps k whose input was not there before the plant's step k + 1. The plant
  applies the latest input it has, so y_{k+1}.u_applied is the answer to step k exactly when
  that answer was in time; a miss is a step whose y_{k+1} carries another input, or whose
  answer never came. Steps whose answer equals the previous one bit for bit cannot be told
  apart and are counted as ``ambiguous`` (none expected with noise);
* tick time and solve time percentiles (from ``mpc_status``), ms; and the response time seen
  by this observer (y_k received -> u for step k received);
* dropped messages: plant steps this observer never received, steps never answered, inputs
  without their ``mpc_status``;
* memory and CPU: resident set size (RSS) of the plant and the controller at the end of the
  warm-up, at the end, the growth in percent, the peak, and their CPU share (100 = one core);
* the load average at start and end (the machine has 2 cores shared with other jobs).

Goals (issue 10): deadline misses <= 0.1 % and memory growth <= 5 % at 100 Hz for 10 minutes.

    python scripts/soak.py                           # 100 Hz for 10 minutes
    python scripts/soak.py --duration 60 --out /tmp/soak1
    python scripts/soak.py --rate 50 --weights runs/x/ckpt/adapted_imaml_v5.pt --dt 0.1

The controller's timer runs at --controller-rate (default twice --rate). Its tick answers the
newest unanswered sample, or the next sample on arrival when there is none; at twice the
plant's rate every other tick finds none, so each sample is answered on arrival. At the
plant's own rate the two timers keep a fixed phase, and when the controller's tick comes late
in the plant's period every answer is late (try ``--controller-rate 100``).
"""
import argparse
import json
import math
import os
import re
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional

import numpy as np

from metampc_bringup.domain import isolate
from metampc_bringup.processes import ProcessGroup, session_pids

PAGE = os.sysconf('SC_PAGE_SIZE')
TICKS = os.sysconf('SC_CLK_TCK')
GOALS = {'deadline_miss_pct': 0.1, 'rss_growth_pct': 5.0}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rate', type=float, default=100.0, help='plant rate, Hz')
    parser.add_argument('--duration', type=float, default=600.0, help='measured time, s')
    parser.add_argument('--warmup', type=float, default=30.0,
                        help='s left out at the start (start-up, first model)')
    parser.add_argument('--controller-rate', type=float,
                        help='controller timer rate, Hz (default: 2 x --rate)')
    parser.add_argument('--dt', type=float,
                        help='plant sample time, s (default: 1/rate: real time)')
    parser.add_argument('--weights', help='checkpoint to control with (default: the '
                                          'hand-built linearised model)')
    parser.add_argument('--theta', type=float, default=0.5, help='plant damping')
    parser.add_argument('--horizon', type=int, default=20, help='MPC horizon N')
    parser.add_argument('--seed', type=int, default=0, help='measurement noise seed')
    parser.add_argument('--out', help='folder for logs and soak.png (default: a new temp dir)')
    args = parser.parse_args(argv)
    args.controller_rate = args.controller_rate or 2.0 * args.rate
    args.dt = args.dt or 1.0 / args.rate
    if min(args.rate, args.duration, args.controller_rate, args.dt) <= 0 or args.warmup < 0:
        parser.error('rates, duration and dt must be > 0, warmup >= 0')
    return args


def model_message(args: argparse.Namespace):
    """The NssmWeights to control with (version 1)."""
    from metampc_controller.weights_codec import fields_from_weights
    from metampc_msgs.msg import NssmWeights
    if args.weights:
        from metampc_learner.checkpoint import load_checkpoint
        ckpt = load_checkpoint(args.weights)
        fields = fields_from_weights(ckpt.model.config, ckpt.model.norm, ckpt.params)
        method, stage = ckpt.info.get('method', 'imaml'), ckpt.info.get('stage', 'adapted')
    else:
        from metampc_controller.manual_model import linearised_vdp_nssm
        fields = fields_from_weights(*linearised_vdp_nssm(args.theta, args.dt))
        method, stage = 'manual', 'adapted'
    return NssmWeights(version=1, method=method, stage=stage, **fields)


class Observer:
    """Receive times (monotonic ns) and the fields the figures need, per topic."""

    def __init__(self, weights):
        from metampc_bringup.spun_node import SpunNode
        from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantOutput
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        stream = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.spun = SpunNode('metampc_soak', threads=1)
        node = self.spun.node
        self.y: List[tuple] = []        # (t, step, u_applied)
        self.u: List[tuple] = []        # (t, step, u, model_version)
        self.status: List[tuple] = []   # (t, step, tick_time, solve_time, fallback)
        node.create_subscription(PlantOutput, 'y', self._on_y, stream)
        node.create_subscription(ControlInput, 'u', self._on_u, stream)
        node.create_subscription(MpcStatus, 'mpc_status', self._on_status, stream)
        self.weights = node.create_publisher(NssmWeights, 'nssm_weights', latched)
        self.weights.publish(weights)

    def _on_y(self, msg) -> None:
        self.y.append((time.monotonic_ns(), msg.step, msg.u_applied[0]))

    def _on_u(self, msg) -> None:
        self.u.append((time.monotonic_ns(), msg.step, msg.u[0], msg.model_version))

    def _on_status(self, msg) -> None:
        self.status.append((time.monotonic_ns(), msg.step, msg.tick_time, msg.solve_time,
                            msg.fallback))

    def subscribed(self, topic: str, node_name: str) -> bool:
        return any(i.node_name == node_name
                   for i in self.spun.node.get_subscriptions_info_by_topic(topic))

    def close(self) -> None:
        self.spun.close()


def node_pid(proc) -> Optional[int]:
    """The node's pid inside the session of its `ros2 run` (which is proc.pid)."""
    others = [p for p in session_pids(proc.pid) if p != proc.pid]
    return others[0] if others else None


def rss_bytes(pid: int) -> int:
    with open(f'/proc/{pid}/statm') as f:
        return int(f.read().split()[1]) * PAGE


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, s."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


class MemorySampler(threading.Thread):
    """RSS and CPU time of each process once a second: name -> [(monotonic ns, bytes, s)]."""

    def __init__(self, pids: Dict[str, int], period: float = 1.0):
        super().__init__(daemon=True)
        self.pids = pids
        self.period = period
        self.samples: Dict[str, List[tuple]] = {name: [] for name in pids}
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            now = time.monotonic_ns()
            for name, pid in self.pids.items():
                try:
                    self.samples[name].append((now, rss_bytes(pid), cpu_seconds(pid)))
                except OSError:
                    pass
            self._halt.wait(self.period)

    def stop(self) -> None:
        self._halt.set()
        self.join()


def percentiles(values, scale: float = 1.0) -> Dict[str, float]:
    """p50, p99, p99.9 and max of values * scale, rounded."""
    if len(values) == 0:
        return {}
    v = np.asarray(values, dtype=float) * scale
    return {'p50': round(float(np.percentile(v, 50)), 4),
            'p99': round(float(np.percentile(v, 99)), 4),
            'p999': round(float(np.percentile(v, 99.9)), 4),
            'max': round(float(v.max()), 4)}


def deadlines(ys: List[tuple], us: List[tuple], start_ns: int) -> Dict[str, object]:
    """Deadline misses among the steps k whose y_k arrived after start_ns and whose y_{k+1}
    arrived (see the module docstring); per-step outcome for the figure."""
    applied = {step: u for _, step, u in ys}
    arrived = {step: t for t, step, _ in ys}
    answer = {}
    for _, step, u, _ in us:
        answer.setdefault(step, u)
    outcome = {}    # step -> 'hit' | 'late' | 'unanswered' | 'ambiguous'
    for step, t in arrived.items():
        if t < start_ns or step + 1 not in applied:
            continue
        if step not in answer:
            outcome[step] = 'unanswered'
        elif answer[step] == answer.get(step - 1):
            outcome[step] = 'ambiguous'
        else:
            outcome[step] = 'hit' if applied[step + 1] == answer[step] else 'late'
    counts = {kind: sum(o == kind for o in outcome.values())
              for kind in ('hit', 'late', 'unanswered', 'ambiguous')}
    decided = counts['hit'] + counts['late'] + counts['unanswered']
    misses = counts['late'] + counts['unanswered']
    return {'steps': decided, 'misses': misses, 'late': counts['late'],
            'unanswered': counts['unanswered'], 'ambiguous': counts['ambiguous'],
            'miss_pct': round(100.0 * misses / decided, 4) if decided else math.nan,
            'outcome': outcome, 'arrived': arrived}


def dropped(ys, us, statuses, start_ns: int) -> Dict[str, int]:
    """Messages lost on the way: plant steps never received here (gaps in the step index),
    steps without an answer, inputs without their mpc_status."""
    steps = sorted(step for t, step, _ in ys if t >= start_ns)
    answered = {step for _, step, _, _ in us}
    reported = {step for _, step, *_ in statuses}
    window = set(steps)
    return {'y_missing': (steps[-1] - steps[0] + 1 - len(window)) if steps else 0,
            'u_missing': len(window - answered - {steps[-1] if steps else None}),
            'status_missing': len({s for s in answered if s in window} - reported)}


def processes(samples: Dict[str, List[tuple]], start_ns: int) -> Dict[str, Dict[str, float]]:
    """Per process over the measured time: RSS at its start and end (MiB), peak, growth in
    percent of the start, and the CPU share (100: one core)."""
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


def stop_counts(text: str) -> Dict[str, int]:
    """The counts of a node's stop line ('stopped at step N...: 3 stale, 0 rejected, ...')."""
    lines = [line for line in text.splitlines() if 'stopped at step' in line]
    if not lines:
        return {}
    counts = lines[-1].split('stopped at step', 1)[1].split(':', 1)[-1]
    return {name: int(n) for n, name in re.findall(r'(\d+) (\w+)', counts)}


def plot(path: str, obs: Observer, mem: Dict[str, List[tuple]], dl: Dict[str, object],
         t0: int, warmup_ns: int) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    def sec(t):
        return (np.asarray(t, dtype=float) - t0) / 1e9

    fig, axes = plt.subplots(4, 1, figsize=(9, 11), sharex=True)
    st = np.array([(t, tick, solve) for t, _, tick, solve, _ in obs.status]).reshape(-1, 3)
    axes[0].plot(sec(st[:, 0]), 1e3 * st[:, 1], '.', ms=1, label='tick')
    axes[0].plot(sec(st[:, 0]), 1e3 * st[:, 2], '.', ms=1, label='solve')
    axes[0].set_ylabel('controller, ms')
    axes[0].set_yscale('log')
    axes[0].legend(loc='upper right', markerscale=8)
    sent = {step: t for t, step, _, _ in obs.u}
    resp = [(t, sent[step] - t) for t, step, _ in obs.y if step in sent]
    if resp:
        r = np.array(resp, dtype=float)
        axes[1].plot(sec(r[:, 0]), r[:, 1] / 1e6, '.', ms=1)
    axes[1].axhline(1e3 / obs_rate(obs), color='r', lw=0.8, label='one period')
    axes[1].set_ylabel('y_k -> u_k seen here, ms')
    axes[1].set_yscale('log')
    axes[1].legend(loc='upper right')
    for name, series in mem.items():
        s = np.array([(t, b) for t, b, _ in series], dtype=float).reshape(-1, 2)
        base = s[s[:, 0] >= t0 + warmup_ns, 1]
        if base.size:
            axes[2].plot(sec(s[:, 0]), 100.0 * (s[:, 1] / base[0] - 1.0),
                         label=f'{name} ({base[0] / 2**20:.0f} MiB after warm-up)')
    axes[2].axhline(GOALS['rss_growth_pct'], color='r', lw=0.8, label='goal')
    axes[2].set_ylabel('RSS growth, %')
    axes[2].legend(loc='upper left')
    missed = sorted(dl['arrived'][k] for k, o in dl['outcome'].items()
                    if o in ('late', 'unanswered'))
    span = float(sec(obs.y[-1][0]))
    width = max(1.0, round(span / 60.0))
    axes[3].hist(sec(missed), bins=np.arange(0.0, span + width, width))
    axes[3].set_ylabel(f'deadline misses / {width:g} s')
    axes[3].set_xlabel('time since start, s')
    for ax in axes:
        ax.axvline(warmup_ns / 1e9, color='gray', ls=':', lw=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def obs_rate(obs: Observer) -> float:
    """Plant rate seen by the observer, Hz."""
    if len(obs.y) < 2:
        return math.nan
    return (len(obs.y) - 1) / ((obs.y[-1][0] - obs.y[0][0]) / 1e9)


def main(argv=None) -> int:
    args = parse_args(argv)
    out = args.out or tempfile.mkdtemp(prefix='metampc-soak-')
    os.makedirs(os.path.join(out, 'logs'), exist_ok=True)
    domain = isolate()      # before rclpy: a ROS domain of our own, localhost discovery
    load_start = os.getloadavg()
    group = ProcessGroup(os.path.join(out, 'logs'))
    obs = Observer(model_message(args))
    try:
        controller = group.start('metampc_controller', 'controller', name='controller', params={
            'rate_hz': args.controller_rate, 'horizon': args.horizon, 'reference': 'sine',
            'reference_amplitude': 0.5, 'reference_period': 5.0})
        deadline = time.monotonic() + 120.0
        while not obs.subscribed('/y', 'controller'):
            if controller.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'the controller did not start: see {controller.log_path}')
            time.sleep(0.1)
        plant = group.start('metampc_plant', 'plant', name='plant', params={
            'mode': 'realtime', 'rate_hz': args.rate, 'dt': args.dt, 'theta': args.theta,
            'x0': [0.0, 0.0], 'measurement_noise_std': 1e-3, 'seed': args.seed})
        while not (obs.y and node_pid(plant)):
            if plant.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'the plant did not start: see {plant.log_path}')
            time.sleep(0.1)
        t0 = obs.y[0][0]
        sampler = MemorySampler({'plant': node_pid(plant), 'controller': node_pid(controller)})
        sampler.start()
        end = time.monotonic() + args.warmup + args.duration
        while time.monotonic() < end:
            for name, proc in (('plant', plant), ('controller', controller)):
                if proc.poll() is not None:
                    raise RuntimeError(f'the {name} ended: see {proc.log_path}')
            time.sleep(0.5)
        sampler.stop()
    except KeyboardInterrupt:
        print(f'soak: interrupted; nodes stopped, logs in {out}', file=sys.stderr)
        return 130
    except RuntimeError as err:
        print(f'soak: {err}', file=sys.stderr)
        return 1
    finally:
        obs.close()
        group.stop_all(timeout=20.0)
    start_ns = t0 + int(args.warmup * 1e9)
    dl = deadlines(obs.y, obs.u, start_ns)
    measured = [s for s in obs.status if s[0] >= start_ns]
    sent = {step: t for t, step, _, _ in obs.u}
    response = [sent[step] - t for t, step, _ in obs.y if t >= start_ns and step in sent]
    mem = processes(sampler.samples, start_ns)
    png = os.path.join(out, 'soak.png')
    plot(png, obs, sampler.samples, dl, t0, int(args.warmup * 1e9))
    report = {
        'bench': 'soak', 'rate_hz': args.rate, 'controller_rate_hz': args.controller_rate,
        'dt': args.dt, 'duration_s': args.duration, 'warmup_s': args.warmup,
        'model': args.weights or 'manual', 'horizon': args.horizon,
        'observed_rate_hz': round(obs_rate(obs), 3),
        'deadline': {k: v for k, v in dl.items() if k not in ('outcome', 'arrived')},
        'tick_ms': percentiles([s[2] for s in measured], 1e3),
        'solve_ms': percentiles([s[3] for s in measured], 1e3),
        'response_ms': percentiles(response, 1e-6),
        'fallbacks': sum(s[4] for s in measured),
        'model_versions': sorted({v for t, _, _, v in obs.u if t >= start_ns}),
        'dropped': dropped(obs.y, obs.u, obs.status, start_ns),
        'processes': mem,
        'node_counts': {name: stop_counts(ProcessGroup.output(proc))
                        for name, proc in (('plant', plant), ('controller', controller))},
        'goals': GOALS,
        'pass': bool(dl['miss_pct'] <= GOALS['deadline_miss_pct'] and all(
            m['growth_pct'] <= GOALS['rss_growth_pct'] for m in mem.values())),
        'ros_domain_id': domain, 'loadavg_start': [round(v, 2) for v in load_start],
        'loadavg_end': [round(v, 2) for v in os.getloadavg()], 'cpus': os.cpu_count(),
        'png': png, 'logs': os.path.join(out, 'logs'),
    }
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
