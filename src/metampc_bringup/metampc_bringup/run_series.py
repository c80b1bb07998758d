"""Time series of a closed-loop run, rebuilt from metampc messages.

:class:`SeriesBuilder` takes messages one at a time, with their ROS type name, and works the
same on messages decoded from a recording (mcap_ros2) and on live rclpy messages: it only reads
attributes. So the metrics of a run (:mod:`metampc_bringup.metrics`) can be computed from a
recording after the fact or by the orchestrator while the run goes on, from the same messages.

Shapes: ``n`` samples, ``n_y`` outputs, ``n_u`` inputs; times in s (header stamps) and ns (log
times). No rclpy here.
"""
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np

PLANT_OUTPUT = 'metampc_msgs/msg/PlantOutput'
CONTROL_INPUT = 'metampc_msgs/msg/ControlInput'
MPC_STATUS = 'metampc_msgs/msg/MpcStatus'
NSSM_WEIGHTS = 'metampc_msgs/msg/NssmWeights'
TRAINING_PROGRESS = 'metampc_msgs/msg/TrainingProgress'
PLANT_INFO = 'metampc_msgs/msg/PlantInfo'
PARAMETER_EVENT = 'rcl_interfaces/msg/ParameterEvent'
# Type -> default topic name (relative; docs/architecture.md, 'Graph').
DEFAULT_TOPICS = {PLANT_OUTPUT: 'y', CONTROL_INPUT: 'u', MPC_STATUS: 'mpc_status',
                  NSSM_WEIGHTS: 'nssm_weights', TRAINING_PROGRESS: 'progress',
                  PLANT_INFO: 'plant_info', PARAMETER_EVENT: 'parameter_events'}
# rcl_interfaces/ParameterValue: the field holding the value of each ParameterType.
_VALUE_FIELDS = {1: 'bool_value', 2: 'integer_value', 3: 'double_value', 4: 'string_value',
                 5: 'byte_array_value', 6: 'bool_array_value', 7: 'integer_array_value',
                 8: 'double_array_value', 9: 'string_array_value'}


def _stamp(msg: Any) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def parameter_value(value: Any) -> Any:
    """The Python value of an rcl_interfaces/ParameterValue (arrays as lists; None: not set)."""
    field_name = _VALUE_FIELDS.get(int(value.type))
    if field_name is None:
        return None
    got = getattr(value, field_name)
    return got if isinstance(got, (bool, int, float, str)) else list(got)


def _matrix(rows: List[List[float]]) -> np.ndarray:
    """Stack rows of equal length into (n, width); (0, 0) when empty."""
    if not rows:
        return np.zeros((0, 0))
    return np.array(rows, dtype=float)


@dataclass
class OutputSeries:
    """PlantOutput: step [n], stamp [n] s, log_time [n] ns, y [n, n_y], u_applied [n, n_u],
    saturated [n], diverged [n]."""

    step: np.ndarray
    stamp: np.ndarray
    log_time: np.ndarray
    y: np.ndarray
    u_applied: np.ndarray
    saturated: np.ndarray
    diverged: np.ndarray


@dataclass
class InputSeries:
    """ControlInput: step [n], stamp [n] s, log_time [n] ns, u [n, n_u], model_version [n]."""

    step: np.ndarray
    stamp: np.ndarray
    log_time: np.ndarray
    u: np.ndarray
    model_version: np.ndarray


@dataclass
class StatusSeries:
    """MpcStatus per tick; ``y_ref0`` [n, n_y] is the first row of y_ref, the reference for
    the output of step ``step + 1`` (NaN where a status has no reference); ``q`` the output
    weights of the controller's tracking cost, as its first status gives them ((0,): none);
    ``config_version`` [n] the controller's tuning (0 in recordings made before the field)."""

    step: np.ndarray
    stamp: np.ndarray
    log_time: np.ndarray
    cost: np.ndarray
    solve_time: np.ndarray
    tick_time: np.ndarray
    iterations: np.ndarray
    fallback: np.ndarray
    terminal_fallback: np.ndarray
    model_version: np.ndarray
    solver_status: List[str]
    planner: List[str]
    y_ref0: np.ndarray
    q: np.ndarray
    config_version: np.ndarray


@dataclass
class ProgressSeries:
    """TrainingProgress: one entry per message."""

    log_time: np.ndarray
    phase: List[str]
    method: List[str]
    iteration: np.ndarray
    total: np.ndarray
    loss: np.ndarray
    elapsed: np.ndarray
    skipped_tasks: np.ndarray


@dataclass
class RunSeries:
    """All series of one run; `weights`, `plant_info` and the parameter changes (each
    /parameter_events message that changed a value: log_time, stamp s, node, {name: value})
    as plain dicts."""

    outputs: OutputSeries
    inputs: InputSeries
    status: StatusSeries
    progress: ProgressSeries
    weights: List[Dict[str, Any]] = field(default_factory=list)
    plant_info: Optional[Dict[str, Any]] = None
    parameter_changes: List[Dict[str, Any]] = field(default_factory=list)

    @property
    def n_y(self) -> int:
        """Output dimension (0 without outputs)."""
        return self.outputs.y.shape[1]


class SeriesBuilder:
    """Accumulates messages (any object with the message fields) into a :class:`RunSeries`."""

    def __init__(self):
        self._rows: Dict[str, List[Any]] = {t: [] for t in DEFAULT_TOPICS}

    def add(self, type_name: str, msg: Any, log_time_ns: int = 0) -> bool:
        """Add one message of ROS type `type_name`; False (ignored) for other types."""
        if type_name not in self._rows:
            return False
        self._rows[type_name].append((log_time_ns, msg))
        return True

    def build(self) -> RunSeries:
        """The series of everything added so far."""
        outs, ins, stats, prog = (self._rows[t] for t in (
            PLANT_OUTPUT, CONTROL_INPUT, MPC_STATUS, TRAINING_PROGRESS))
        outputs = OutputSeries(
            step=np.array([m.step for _, m in outs], dtype=np.int64),
            stamp=np.array([_stamp(m) for _, m in outs], dtype=float),
            log_time=np.array([t for t, _ in outs], dtype=np.int64),
            y=_matrix([list(m.y) for _, m in outs]),
            u_applied=_matrix([list(m.u_applied) for _, m in outs]),
            saturated=np.array([bool(m.saturated) for _, m in outs], dtype=bool),
            diverged=np.array([bool(m.diverged) for _, m in outs], dtype=bool))
        inputs = InputSeries(
            step=np.array([m.step for _, m in ins], dtype=np.int64),
            stamp=np.array([_stamp(m) for _, m in ins], dtype=float),
            log_time=np.array([t for t, _ in ins], dtype=np.int64),
            u=_matrix([list(m.u) for _, m in ins]),
            model_version=np.array([m.model_version for _, m in ins], dtype=np.int64))
        n_y = outputs.y.shape[1]
        status = StatusSeries(
            step=np.array([m.step for _, m in stats], dtype=np.int64),
            stamp=np.array([_stamp(m) for _, m in stats], dtype=float),
            log_time=np.array([t for t, _ in stats], dtype=np.int64),
            cost=np.array([m.cost for _, m in stats], dtype=float),
            solve_time=np.array([m.solve_time for _, m in stats], dtype=float),
            tick_time=np.array([m.tick_time for _, m in stats], dtype=float),
            iterations=np.array([m.iterations for _, m in stats], dtype=np.int64),
            fallback=np.array([bool(m.fallback) for _, m in stats], dtype=bool),
            terminal_fallback=np.array([bool(m.terminal_fallback) for _, m in stats],
                                       dtype=bool),
            model_version=np.array([m.model_version for _, m in stats], dtype=np.int64),
            solver_status=[str(m.solver_status) for _, m in stats],
            planner=[str(m.planner) for _, m in stats],
            y_ref0=np.array([list(m.y_ref[:n_y]) if len(m.y_ref) >= n_y else [np.nan] * n_y
                             for _, m in stats], dtype=float).reshape(len(stats), n_y),
            q=np.array(list(getattr(stats[0][1], 'q', ())) if stats else [], dtype=float),
            config_version=np.array([getattr(m, 'config_version', 0) for _, m in stats],
                                    dtype=np.int64))
        progress = ProgressSeries(
            log_time=np.array([t for t, _ in prog], dtype=np.int64),
            phase=[str(m.phase) for _, m in prog], method=[str(m.method) for _, m in prog],
            iteration=np.array([m.iteration for _, m in prog], dtype=np.int64),
            total=np.array([m.total for _, m in prog], dtype=np.int64),
            loss=np.array([m.loss for _, m in prog], dtype=float),
            elapsed=np.array([m.elapsed for _, m in prog], dtype=float),
            skipped_tasks=np.array([m.skipped_tasks for _, m in prog], dtype=np.int64))
        weights = [{'log_time': t, 'version': int(m.version), 'method': str(m.method),
                    'stage': str(m.stage), 'train_loss': float(m.train_loss),
                    'train_steps': int(m.train_steps), 'train_samples': int(m.train_samples),
                    'seed': int(m.seed)} for t, m in self._rows[NSSM_WEIGHTS]]
        info_rows = self._rows[PLANT_INFO]
        plant_info = None
        if info_rows:
            info = info_rows[-1][1]
            plant_info = {name: getattr(info, name) for name in (
                'theta', 'dt', 'substeps', 'u_min', 'u_max', 'process_noise_std',
                'measurement_noise_std', 'seed', 'clock_mode', 'rate_hz', 'state_bound',
                'diverged', 'n_resets')}
            # Fields of the plant families (absent in recordings made before them).
            plant_info.update({name: list(getattr(info, name, [])) for name in (
                'theta_names', 'input_names', 'input_units', 'output_names', 'output_units')})
            plant_info['family'] = str(getattr(info, 'family', ''))
        changes = [{'log_time': t, 'stamp': m.stamp.sec + 1e-9 * m.stamp.nanosec,
                    'node': str(m.node),
                    'parameters': {str(p.name): parameter_value(p.value)
                                   for p in m.changed_parameters}}
                   for t, m in self._rows[PARAMETER_EVENT] if len(m.changed_parameters)]
        return RunSeries(outputs, inputs, status, progress, weights, plant_info, changes)
