"""A real-time soak: a realtime plant and the latent-MPC controller for a long run.

The logic of ``scripts/soak.py``: the plant in ``realtime`` mode at ``rate`` Hz, the controller
on its own wall-clock timer at ``controller_rate`` with a trained model (the hand-built NSSM of
:mod:`metampc_model.manual_model` or the checkpoint ``weights``) tracking a sine of x1; an
observer in this process (:mod:`metampc_bringup.soak.soak_observer`) records ``y``, ``u`` and
``mpc_status`` and samples each node's RSS and CPU once a second. After the warm-up the
measures are :mod:`metampc_bringup.soak.soak_metrics`'s, with the load average at start and
end. With ``adaptation`` a learner adapts in the loop while the plant follows
``theta_schedule``. Set-up, timers and measured soaks: docs/faults.md#real-time-soak.
"""
from dataclasses import dataclass
import os
import subprocess
import time
from typing import Dict, Optional, Tuple

from metampc_bringup.analysis.percentiles import percentiles
from metampc_bringup.orchestration.domain import isolate
from metampc_bringup.orchestration.processes import ProcessGroup, session_pids
from metampc_bringup.orchestration.procfs import UsageSampler
from metampc_bringup.soak.soak_metrics import (deadlines, dropped, GOALS, goals_met, observed_rate,
                                               process_usage, responses, stop_counts)
from metampc_bringup.soak.soak_observer import Observer
from metampc_bringup.soak.soak_plot import plot_soak
from metampc_bringup.soak.weights_messages import checkpoint_weights, manual_weights
from metampc_controller.adaptation_trigger import MODES
from metampc_msgs.msg import NssmWeights

START_TIMEOUT = 120.0   # s for both nodes to come up
STOP_TIMEOUT = 20.0     # s for each node to stop after SIGINT


@dataclass
class SoakConfig:
    """The soak's set-up (the flags of ``scripts/soak.py``); rates in Hz, times in s."""

    rate: float = 100.0                     # plant
    duration: float = 600.0                 # measured, after the warm-up
    warmup: float = 30.0                    # left out: start-up, first model
    controller_rate: Optional[float] = None     # default: 2 x rate
    dt: Optional[float] = None              # plant sample time; default: 1 / rate (real time)
    weights: Optional[str] = None           # checkpoint; default: the hand-built model
    theta: float = 0.5                      # plant damping
    horizon: int = 20                       # MPC horizon N
    seed: int = 0                           # measurement noise
    out: Optional[str] = None               # folder for the node logs and soak.png: needed
    # Adaptation in the loop (docs/adaptation.md): the controller's mode, with a learner that
    # loads `weights` as its meta-model and adapts at the controller's requests; the plant's
    # theta over time (rows [t_start, t_end, theta], s of plant time).
    adaptation: str = 'off'
    adapt_period: float = 10.0
    theta_schedule: Tuple[float, ...] = ()

    def __post_init__(self):
        self.controller_rate = self.controller_rate or 2.0 * self.rate
        # a rate <= 0 leaves dt unset for validate() to refuse (not a ZeroDivisionError)
        self.dt = self.dt or (1.0 / self.rate if self.rate > 0 else 0.0)

    def validate(self) -> None:
        """ValueError if a rate, the duration or dt is <= 0, the warm-up < 0, or adaptation
        is asked for without a meta-model checkpoint (``weights``)."""
        if min(self.rate, self.duration, self.controller_rate, self.dt) <= 0 or self.warmup < 0:
            raise ValueError('rates, duration and dt must be > 0, warmup >= 0')
        if self.adaptation not in MODES:
            raise ValueError(f'adaptation must be one of {", ".join(MODES)}')
        if self.adaptation != 'off' and not self.weights:
            raise ValueError('adaptation in the loop needs a learner\'s meta-model: --weights '
                             '(a checkpoint, e.g. written by --weights-from)')


def model_message(cfg: SoakConfig) -> Optional[NssmWeights]:
    """The model to control with (version 1); None when a learner publishes it."""
    if cfg.adaptation != 'off':
        return None
    if cfg.weights:
        return checkpoint_weights(cfg.weights)
    return manual_weights(cfg.theta, cfg.dt)


def node_pid(proc: subprocess.Popen) -> Optional[int]:
    """The node's pid inside the session of its `ros2 run` (which is proc.pid)."""
    others = [p for p in session_pids(proc) if p != proc.pid]
    return others[0] if others else None


def soak(cfg: SoakConfig) -> dict:
    """Run the soak; the report (for one JSON line; nan where undefined). Node logs and
    soak.png go to cfg.out, which must be set.

    Raises:
        RuntimeError: a node did not start or ended early (its log named).
    """
    cfg.validate()
    logs = os.path.join(cfg.out, 'logs')
    os.makedirs(logs, exist_ok=True)
    domain = isolate()      # before rclpy: a ROS domain of our own, localhost discovery
    load_start = os.getloadavg()
    group = ProcessGroup(logs)
    obs = Observer(model_message(cfg))
    sampler = None
    try:
        nodes = _start_nodes(cfg, group, obs)
        t0 = obs.y[0][0]
        sampler = UsageSampler({name: node_pid(proc) for name, proc in nodes.items()})
        sampler.start()
        end = time.monotonic() + cfg.warmup + cfg.duration
        while time.monotonic() < end:
            for name, proc in nodes.items():
                if proc.poll() is not None:
                    raise RuntimeError(f'the {name} ended: see {proc.log_path}')
            time.sleep(0.5)
    finally:
        if sampler is not None:
            sampler.stop()
        obs.close()
        group.stop_all(timeout=STOP_TIMEOUT)
    warmup_ns = int(cfg.warmup * 1e9)
    start_ns = t0 + warmup_ns
    dl = deadlines(obs.y, obs.u, start_ns)
    measured = [s for s in obs.status if s[0] >= start_ns]
    usage = process_usage(sampler.samples, start_ns)
    png = os.path.join(cfg.out, 'soak.png')
    plot_soak(png, obs.y, obs.u, obs.status, sampler.samples, dl, t0, warmup_ns)
    return {
        'bench': 'soak', 'rate_hz': cfg.rate, 'controller_rate_hz': cfg.controller_rate,
        'dt': cfg.dt, 'duration_s': cfg.duration, 'warmup_s': cfg.warmup,
        'model': cfg.weights or 'manual', 'horizon': cfg.horizon,
        'observed_rate_hz': round(observed_rate(obs.y), 3),
        'deadline': {k: v for k, v in dl.items() if k not in ('outcome', 'arrived')},
        'tick_ms': percentiles([s[2] for s in measured], scale=1e3),
        'solve_ms': percentiles([s[3] for s in measured], scale=1e3),
        'response_ms': percentiles([r for _, r in responses(obs.y, obs.u, start_ns)],
                                   scale=1e-6),
        'fallbacks': sum(s[4] for s in measured),
        'model_versions': sorted({v for t, _, _, v in obs.u if t >= start_ns}),
        'adaptation': cfg.adaptation, 'theta_schedule': list(cfg.theta_schedule),
        'adapt_requests': [k for t, k in obs.requests if t >= start_ns],
        'dropped': dropped(obs.y, obs.u, obs.status, start_ns),
        'processes': usage,
        'node_counts': {name: stop_counts(ProcessGroup.output(proc))
                        for name, proc in nodes.items()},
        'goals': GOALS,
        'pass': goals_met(dl, usage),
        'ros_domain_id': domain, 'loadavg_start': [round(v, 2) for v in load_start],
        'loadavg_end': [round(v, 2) for v in os.getloadavg()], 'cpus': os.cpu_count(),
        'png': png, 'logs': logs,
    }


def _start_nodes(cfg: SoakConfig, group: ProcessGroup, obs: Observer
                 ) -> Dict[str, subprocess.Popen]:
    """Start the controller, then, once it listens to y, the plant; wait for the first y.

    Returns:
        {'plant': its `ros2 run` process, 'controller': ...}.
    """
    nodes = {}
    if cfg.adaptation != 'off':
        nodes['learner'] = group.start('metampc_learner', 'learner', name='learner', params={
            'meta_model_path': cfg.weights, 'dt': cfg.dt, 'loop_adaptation': True,
            'loop_window': 100, 'loop_steps': 10, 'loop_lr': 1.0, 'buffer_on_start': False,
            'torch_threads': 1})
    controller = group.start('metampc_controller', 'controller', name='controller', params={
        'rate_hz': cfg.controller_rate, 'horizon': cfg.horizon, 'reference': 'sine',
        'reference_amplitude': 0.5, 'reference_period': 5.0, 'adaptation': cfg.adaptation,
        'adapt_period': cfg.adapt_period})
    deadline = time.monotonic() + START_TIMEOUT
    while not obs.subscribed('/y', 'controller'):
        if controller.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f'the controller did not start: see {controller.log_path}')
        time.sleep(0.1)
    plant = group.start('metampc_plant', 'plant', name='plant', params={
        'mode': 'realtime', 'rate_hz': cfg.rate, 'dt': cfg.dt, 'theta': cfg.theta,
        'x0': [0.0, 0.0], 'measurement_noise_std': 1e-3, 'seed': cfg.seed,
        'theta_schedule': list(cfg.theta_schedule)})
    while not (obs.y and node_pid(plant)):
        if plant.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f'the plant did not start: see {plant.log_path}')
        time.sleep(0.1)
    return {**nodes, 'plant': plant, 'controller': controller}
