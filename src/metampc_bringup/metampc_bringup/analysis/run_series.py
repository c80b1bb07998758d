"""Time series of a closed-loop run, rebuilt from metampc messages.

:class:`SeriesBuilder` takes messages one at a time, with their ROS type name, and works the
same on messages decoded from a recording (mcap_ros2) and on live rclpy messages: it only reads
attributes. So the metrics of a run (:mod:`metampc_bringup.analysis.metrics`) can be computed
from a recording after the fact or by the orchestrator while the run goes on, from the same
messages.

Shapes: ``n`` samples, ``n_y`` outputs, ``n_u`` inputs; times in s (header stamps) and ns (log
times). No rclpy here.
"""
from array import array
from dataclasses import dataclass, field
import sys
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from metampc_bringup.analysis.input_sources import controller_inputs

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
    as plain dicts. `inputs` are the controller's answers, `foreign_inputs` the ControlInputs
    of other publishers (:mod:`~metampc_bringup.analysis.input_sources`)."""

    outputs: OutputSeries
    inputs: InputSeries
    status: StatusSeries
    progress: ProgressSeries
    weights: List[Dict[str, Any]] = field(default_factory=list)
    plant_info: Optional[Dict[str, Any]] = None
    parameter_changes: List[Dict[str, Any]] = field(default_factory=list)
    foreign_inputs: InputSeries = field(default_factory=lambda: InputSeries(
        *(np.zeros(0, dtype=t) for t in (np.int64, float, np.int64)), np.zeros((0, 0)),
        np.zeros(0, dtype=np.int64)))

    @property
    def n_y(self) -> int:
        """Output dimension (0 without outputs)."""
        return self.outputs.y.shape[1]


class _Table:
    """Compact columns of one message type, filled one message at a time, in any order.

    Numbers go into typed arrays (8 bytes a value), vectors into one flat array with their
    lengths, strings into lists of interned strings: the messages themselves are not kept, so
    a long recording is aggregated in bounded memory.
    """

    def __init__(self, columns: Dict[str, str]):
        """`columns`: name -> 'q' (int), 'd' (float), 'v' (float vector) or 's' (string)."""
        self.kinds = columns
        self.log_time, self.arrival = array('q'), array('q')
        self.data: Dict[str, Any] = {}
        for name, kind in columns.items():
            self.data[name] = [] if kind == 's' else array('d' if kind in 'dv' else 'q')
            if kind == 'v':
                self.data[name + '#'] = array('q')

    def add(self, log_time: int, arrival: int, values: Dict[str, Any]) -> None:
        self.log_time.append(log_time)
        self.arrival.append(arrival)
        for name, kind in self.kinds.items():
            value = values[name]
            if kind == 'v':
                self.data[name].extend(value)
                self.data[name + '#'].append(len(value))
            elif kind == 's':
                self.data[name].append(sys.intern(str(value)))
            else:
                self.data[name].append(value)

    def order(self) -> np.ndarray:
        """Row indices in (log time, arrival) order."""
        return np.lexsort((np.frombuffer(self.arrival, dtype=np.int64),
                           np.frombuffer(self.log_time, dtype=np.int64)))

    def column(self, name: str, rows: np.ndarray, pad: bool = False) -> Any:
        """Column `name` at `rows` (indices): [n]; a list for strings; [n, width] for vectors,
        whose lengths must agree (ValueError) unless `pad`: then NaN fills the shorter."""
        kind, values = self.kinds.get(name), self.data.get(name)
        if name == 'log_time':
            return np.frombuffer(self.log_time, dtype=np.int64)[rows]
        if kind == 's':
            return [values[i] for i in rows.tolist()]
        if kind != 'v':
            return np.frombuffer(values, dtype=np.int64 if kind == 'q' else float)[rows]
        lengths = np.frombuffer(self.data[name + '#'], dtype=np.int64)
        starts = (np.cumsum(lengths) - lengths)[rows]
        lengths = lengths[rows]
        width = int(lengths.max()) if lengths.size else 0
        if not pad and np.any(lengths != width):
            raise ValueError(f'{name} changes length across messages '
                             f'({sorted(set(lengths.tolist()))[:5]})')
        there = np.arange(width)[None, :] < lengths[:, None]
        matrix = np.full((lengths.size, width), np.nan)
        matrix[there] = np.frombuffer(values, dtype=float)[
            (starts[:, None] + np.arange(width)[None, :])[there]]
        return matrix


_OUTPUT_COLUMNS = {'step': 'q', 'stamp': 'd', 'y': 'v', 'u_applied': 'v', 'saturated': 'q',
                   'diverged': 'q'}
_INPUT_COLUMNS = {'step': 'q', 'stamp': 'd', 'u': 'v', 'model_version': 'q'}
_STATUS_COLUMNS = {'step': 'q', 'stamp': 'd', 'cost': 'd', 'solve_time': 'd', 'tick_time': 'd',
                   'iterations': 'q', 'fallback': 'q', 'terminal_fallback': 'q',
                   'model_version': 'q', 'solver_status': 's', 'planner': 's',
                   'y_ref': 'v', 'y_ref_len': 'q', 'config_version': 'q'}
_PROGRESS_COLUMNS = {'phase': 's', 'method': 's', 'iteration': 'q', 'total': 'q', 'loss': 'd',
                     'elapsed': 'd', 'skipped_tasks': 'q'}


class SeriesBuilder:
    """Accumulates messages (any object with the message fields) into a :class:`RunSeries`.

    Messages may come in any order: each series is put in log-time order (ties: the order of
    :meth:`add`) when built. Only the fields the series need are kept, in compact columns, so
    the memory grows by tens of bytes per message whatever the message size (MpcStatus: its
    first y_ref row, not its plans).
    """

    def __init__(self):
        self._arrivals = 0
        self._outputs = _Table(_OUTPUT_COLUMNS)
        self._inputs = _Table(_INPUT_COLUMNS)
        self._status = _Table(_STATUS_COLUMNS)
        self._progress = _Table(_PROGRESS_COLUMNS)
        self._q: Optional[Tuple[Tuple[int, int], List[float]]] = None   # of the first status
        self._n_y: Optional[int] = None     # the first output's width
        self._plant_info: Optional[Tuple[Tuple[int, int], Any]] = None   # the last one
        self._weights: List[Tuple[Tuple[int, int], Dict[str, Any]]] = []
        self._changes: List[Tuple[Tuple[int, int], Dict[str, Any]]] = []

    def add(self, type_name: str, msg: Any, log_time_ns: int = 0) -> bool:
        """Add one message of ROS type `type_name`; False (ignored) for other types."""
        if type_name not in DEFAULT_TOPICS:
            return False
        key = (int(log_time_ns), self._arrivals)
        self._arrivals += 1
        if type_name == PLANT_OUTPUT:
            y = list(msg.y)
            if self._n_y is None:
                self._n_y = len(y)
            self._outputs.add(*key, {
                'step': msg.step, 'stamp': _stamp(msg), 'y': y, 'u_applied': list(msg.u_applied),
                'saturated': bool(msg.saturated), 'diverged': bool(msg.diverged)})
        elif type_name == CONTROL_INPUT:
            self._inputs.add(*key, {'step': msg.step, 'stamp': _stamp(msg), 'u': list(msg.u),
                                    'model_version': msg.model_version})
        elif type_name == MPC_STATUS:
            self._add_status(key, msg)
        elif type_name == TRAINING_PROGRESS:
            self._progress.add(*key, {name: getattr(msg, name) for name in _PROGRESS_COLUMNS})
        elif type_name == NSSM_WEIGHTS:
            self._weights.append((key, {
                'log_time': key[0], 'version': int(msg.version), 'method': str(msg.method),
                'stage': str(msg.stage), 'train_loss': float(msg.train_loss),
                'train_steps': int(msg.train_steps), 'train_samples': int(msg.train_samples),
                'seed': int(msg.seed)}))
        elif type_name == PLANT_INFO:
            if self._plant_info is None or key[0] >= self._plant_info[0][0]:
                self._plant_info = (key, _plant_info(msg))
        elif len(msg.changed_parameters):   # PARAMETER_EVENT
            self._changes.append((key, {
                'log_time': key[0], 'stamp': msg.stamp.sec + 1e-9 * msg.stamp.nanosec,
                'node': str(msg.node), 'parameters': {str(p.name): parameter_value(p.value)
                                                      for p in msg.changed_parameters}}))
        return True

    def _add_status(self, key: Tuple[int, int], msg: Any) -> None:
        # Of y_ref only the first row counts (StatusSeries.y_ref0); its width n_y is the
        # outputs' (known from the first output), which q has too; else all of y_ref is kept.
        y_ref, q = msg.y_ref, getattr(msg, 'q', ())
        n_y = self._n_y if self._n_y is not None else len(q) or None
        head = list(y_ref[:n_y] if n_y is not None else y_ref)
        if self._q is None or key < self._q[0]:
            self._q = (key, list(q))
        self._status.add(*key, {
            **{name: getattr(msg, name) for name in (
                'step', 'cost', 'solve_time', 'tick_time', 'iterations', 'model_version',
                'solver_status', 'planner')},
            'stamp': _stamp(msg), 'fallback': bool(msg.fallback),
            'terminal_fallback': bool(msg.terminal_fallback), 'y_ref': head,
            'y_ref_len': len(y_ref), 'config_version': getattr(msg, 'config_version', 0)})

    def build(self) -> RunSeries:
        """The series of everything added so far."""
        out, o = self._outputs, self._outputs.order()
        outputs = OutputSeries(
            step=out.column('step', o), stamp=out.column('stamp', o),
            log_time=out.column('log_time', o), y=out.column('y', o),
            u_applied=out.column('u_applied', o), saturated=out.column('saturated', o) != 0,
            diverged=out.column('diverged', o) != 0)
        n_y = outputs.y.shape[1]
        status = self._status_series(n_y)
        i = self._inputs.order()
        ours = self._controller_inputs(i)
        prog, p = self._progress, self._progress.order()
        progress = ProgressSeries(
            log_time=prog.column('log_time', p), phase=prog.column('phase', p),
            method=prog.column('method', p), iteration=prog.column('iteration', p),
            total=prog.column('total', p), loss=prog.column('loss', p),
            elapsed=prog.column('elapsed', p), skipped_tasks=prog.column('skipped_tasks', p))
        return RunSeries(
            outputs, self._input_series(i[ours]), status, progress,
            [w for _, w in sorted(self._weights, key=lambda kw: kw[0])],
            self._plant_info[1] if self._plant_info else None,
            [c for _, c in sorted(self._changes, key=lambda kc: kc[0])],
            self._input_series(i[~ours], pad=True))

    def _input_series(self, rows: np.ndarray, pad: bool = False) -> InputSeries:
        """The inputs at `rows`; `pad`: of any lengths of u (foreign inputs: NaN-padded)."""
        inp = self._inputs
        return InputSeries(
            step=inp.column('step', rows), stamp=inp.column('stamp', rows),
            log_time=inp.column('log_time', rows), u=inp.column('u', rows, pad),
            model_version=inp.column('model_version', rows))

    def _status_series(self, n_y: int) -> StatusSeries:
        st, s = self._status, self._status.order()
        heads = st.column('y_ref', s, pad=True)[:, :n_y]
        y_ref0 = np.full((s.size, n_y), np.nan)     # NaN: a status without a reference
        y_ref0[:, :heads.shape[1]] = heads
        y_ref0[np.frombuffer(st.data['y_ref_len'], dtype=np.int64)[s] < n_y] = np.nan
        return StatusSeries(
            step=st.column('step', s), stamp=st.column('stamp', s),
            log_time=st.column('log_time', s), cost=st.column('cost', s),
            solve_time=st.column('solve_time', s), tick_time=st.column('tick_time', s),
            iterations=st.column('iterations', s), fallback=st.column('fallback', s) != 0,
            terminal_fallback=st.column('terminal_fallback', s) != 0,
            model_version=st.column('model_version', s),
            solver_status=st.column('solver_status', s), planner=st.column('planner', s),
            y_ref0=y_ref0, q=np.array(self._q[1] if self._q else [], dtype=float),
            config_version=st.column('config_version', s))

    def _controller_inputs(self, order: np.ndarray) -> np.ndarray:
        """Mask of the inputs (in `order`, the recorded one) that are the controller's
        (input_sources)."""
        inp, st = self._inputs, self._status
        s = st.order()
        return controller_inputs(inp.column('step', order), inp.column('stamp', order),
                                 st.column('step', s), st.column('stamp', s))


def _plant_info(info: Any) -> Dict[str, Any]:
    """The fields of a PlantInfo the analysis uses, as plain values."""
    plant_info = {name: getattr(info, name) for name in (
        'theta', 'dt', 'substeps', 'u_min', 'u_max', 'process_noise_std',
        'measurement_noise_std', 'seed', 'clock_mode', 'rate_hz', 'state_bound',
        'diverged', 'n_resets')}
    # Fields of the plant families (absent in recordings made before them).
    plant_info.update({name: list(getattr(info, name, [])) for name in (
        'theta_names', 'input_names', 'input_units', 'output_names', 'output_units')})
    plant_info['family'] = str(getattr(info, 'family', ''))
    return plant_info
