"""The `bridge` node: any machine's own topics and types as a metampc plant, by one mapping file.

Subscribes to the machine's topics with their types (best effort: it matches any writer), and
on a timer of the mapping's dt publishes ``y`` (PlantOutput: y_k held from the machine's stamps,
the input held over (k-1, k], clipped or not) and, once, the latched ``plant_info`` (the
mapping's dt, bounds, names and units; no theta; clock mode realtime). Takes ``u``
(ControlInput) and writes the machine's command topic in its type; writes the safe value while
the machine's samples or the controller's answers are stale, says so in the log and on
``diagnostics`` (diagnostic_msgs/DiagnosticArray). A mapped topic that the graph carries in
another type is warned about once (and listed in the diagnostics while it lasts).
Rules: :mod:`metampc_plant.bridge_core`;
refuses a bad mapping (one error line, exit 2). Parameters: :data:`PARAMETERS`; docs/bridge.md.
"""
from array import array
from dataclasses import dataclass
import math
import sys
from typing import Dict, List, Set

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from metampc_common.node_main import (declare_parameters, EventCounts, loop_executor,
                                      run_node)
from metampc_common.params import build, param, ParameterError, ParamSpec, Section, table
from metampc_common.qos import BACKLOG, LATCHED, MACHINE, SPARSE, STREAM
from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput
from rclpy.node import Node
from std_msgs.msg import Header

from metampc_plant.bridge_core import (BridgeCore, DROPPED, FOLLOWING, OFFSET, STALE, Tick,
                                       type_mismatches)
from metampc_plant.machine_mapping import load_mapping, MappingError

DIAGNOSTICS_PERIOD_S = 1.0     # how often the bridge's status goes out besides its changes
LEVELS = {FOLLOWING: DiagnosticStatus.OK, STALE: DiagnosticStatus.STALE}   # else WARN
COUNTERS = (DROPPED, OFFSET, 'refused_inputs', 'safe_periods')


@dataclass
class BridgeParams:
    """The bridge's parameters (the rest is in the mapping file)."""

    mapping_file: str = param('', 'the mapping file (YAML): outputs, command, dt, '
                                  'stale_timeout (docs/bridge.md); required')


SECTION = Section(BridgeParams)
PARAMETERS: Dict[str, ParamSpec] = table([SECTION])


def _time(t: float) -> Time:
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class BridgeNode(Node):
    """ROS 2 front end of one :class:`BridgeCore` (see the module docstring)."""

    def __init__(self):
        super().__init__('bridge')
        cfg = build(SECTION, declare_parameters(self, PARAMETERS))
        if not cfg.mapping_file:
            raise ParameterError('mapping_file: required (a YAML file, docs/bridge.md)')
        try:
            self.mapping = load_mapping(cfg.mapping_file)
        except MappingError as err:
            raise ParameterError(f'mapping_file {cfg.mapping_file}: {err}') from None
        self.core = BridgeCore(self.mapping)
        self._events = EventCounts(self, COUNTERS)
        self._warn = self._events.warn
        mapping, command = self.mapping, self.mapping.command
        for index, topic in enumerate(mapping.topics):
            self.create_subscription(topic.cls, topic.topic,
                                     lambda msg, i=index: self._on_sample(i, msg), MACHINE)
        self._pub_command = self.create_publisher(command.cls, command.topic, SPARSE)
        self._pub_y = self.create_publisher(PlantOutput, 'y', BACKLOG)
        self._pub_info = self.create_publisher(PlantInfo, 'plant_info', LATCHED)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, 'diagnostics', SPARSE)
        self.create_subscription(ControlInput, 'u', self._on_input, STREAM)
        self._y_msg = PlantOutput()
        self._last_diagnostics = -math.inf
        self._mismatches: List[str] = []    # type_mismatches at the last diagnostics
        self._warned_types: Set[str] = set()
        self._ever_fresh = False
        self._pub_info.publish(PlantInfo(
            header=self._stamp(), family=mapping.name, dt=mapping.dt,
            u_min=mapping.u_min.tolist(), u_max=mapping.u_max.tolist(),
            input_names=[i.name for i in command.inputs],
            input_units=[i.unit for i in command.inputs],
            output_names=[o.name for o in mapping.outputs],
            output_units=[o.unit for o in mapping.outputs], clock_mode='realtime',
            rate_hz=1.0 / mapping.dt, state_bound=math.inf))
        self.create_timer(mapping.dt, self._on_tick)
        self.get_logger().info(
            f'bridge {mapping.name}: y = {[o.name for o in mapping.outputs]} from '
            f'{[t.topic for t in mapping.topics]}, u = {[i.name for i in command.inputs]} to '
            f'{command.topic} ({command.type}), dt = {mapping.dt} s, safe value '
            f'{mapping.safe.tolist()} after {mapping.stale_timeout} s without samples or inputs')

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _stamp(self) -> Header:
        return Header(stamp=self.get_clock().now().to_msg())

    def _on_sample(self, index: int, msg) -> None:
        kind, warning = self.core.sample(index, msg, self._now())
        if kind:
            self._warn(kind, warning)

    def _write(self, u) -> None:
        self._pub_command.publish(self.mapping.command_message(
            u, self.get_clock().now().to_msg()))

    def _on_input(self, msg: ControlInput) -> None:
        answer = self.core.answer(msg.step, msg.u, self._now())
        if answer.write is None:
            self._warn('refused_inputs', f'refused the input for step {msg.step}: {answer.why}')
            return
        self._write(answer.write)
        if answer.resumed:
            self.get_logger().info(f'the command follows the controller from its answer to '
                                   f'step {msg.step}')
            self._diagnose(self.core.state, '', msg.step, ())

    def _on_tick(self) -> None:
        tick = self.core.tick(self._now())
        if tick.y is not None:
            self._publish_y(tick)
        if tick.write is not None:
            self._write(tick.write)
        if tick.changed:
            self._log_change(tick)
        self._ever_fresh |= tick.state != STALE
        if tick.changed or tick.time - self._last_diagnostics >= DIAGNOSTICS_PERIOD_S:
            self._check_types()
            self._diagnose(tick.state, tick.reason, tick.step, tick.ages)

    def _check_types(self) -> None:
        """The mapped topics the graph carries in another type: each warned about once."""
        writers = {t.topic: [e.topic_type for e in self.get_publishers_info_by_topic(t.topic)]
                   for t in self.mapping.topics}
        readers = [e.topic_type for e in
                   self.get_subscriptions_info_by_topic(self.mapping.command.topic)]
        self._mismatches = type_mismatches(self.mapping, writers, readers)
        for line in self._mismatches:
            if line not in self._warned_types:
                self._warned_types.add(line)
                self.get_logger().warning(line)

    def _log_change(self, tick: Tick) -> None:
        log = self.get_logger()
        if tick.state == STALE or tick.previous == FOLLOWING:
            self._events.counts['safe_periods'] += 1
            log.warning(f'step {tick.step}: command -> safe value {tick.write.tolist()} '
                        f'({tick.reason})')
        elif tick.previous == STALE:
            again = ' again' if self._ever_fresh else ''
            log.info(f'step {tick.step}: the machine\'s samples are fresh{again}; the safe '
                     'value until the controller answers')
        else:
            log.info(f'step {tick.step}: safe value {tick.write.tolist()} until the controller '
                     f'answers ({tick.reason})')

    def _publish_y(self, tick: Tick) -> None:
        msg = self._y_msg
        msg.header.stamp = _time(tick.time)
        msg.step = tick.step
        msg.y = array('d', tick.y)
        msg.u_applied = array('d', tick.u_applied)
        msg.saturated = tick.saturated
        self._pub_y.publish(msg)

    def _diagnose(self, state: str, reason: str, step: int, ages) -> None:
        self._last_diagnostics = self._now()
        values = [KeyValue(key='step', value=str(step)), KeyValue(key='state', value=state)]
        values += [KeyValue(key=f'age {topic.topic}', value=f'{age:.3f}')
                   for topic, age in zip(self.mapping.topics, ages)]
        values += [KeyValue(key='type mismatch', value=line) for line in self._mismatches]
        status = DiagnosticStatus(
            level=LEVELS.get(state, DiagnosticStatus.WARN), name=f'bridge: {self.mapping.name}',
            message=reason or 'following the controller', hardware_id=self.mapping.name,
            values=values)
        self._pub_diagnostics.publish(DiagnosticArray(header=self._stamp(), status=[status]))

    def destroy_node(self) -> None:
        """Destroy the node, then log what was counted over the run."""
        super().destroy_node()
        self.get_logger().info(f'stopped in state {self.core.state}: {self._events.summary()}')


def main(args=None) -> int:
    """`ros2 run metampc_plant bridge --ros-args -p mapping_file:=FILE`; returns the exit code."""
    return run_node(BridgeNode, 'bridge', args, executor=loop_executor)


if __name__ == '__main__':
    sys.exit(main())
