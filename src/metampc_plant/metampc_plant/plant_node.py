"""The `plant` node: a thin ROS 2 adapter over the simulator core of any plant family.

Integrates eq. (sys) (x' = f(x, u, theta), y = g(x, u, theta); :mod:`metampc_plant.simulator`)
and wires it to ROS: publishes ``y`` (PlantOutput: y_k, the input u_k held over (k-1, k] after
saturation, step k, theta(k dt), saturated/diverged flags), the latched ``plant_info`` and, in
lockstep, ``/clock``; takes ``u`` (ControlInput answering step k), ``u_hold`` (StepHold) and
the ``reset`` service. The lockstep rules are :class:`metampc_plant.lockstep.Lockstep`'s, a
theta schedule :mod:`metampc_plant.theta_schedule`'s. Refuses: a bad parameter (one error line,
exit 2), a NaN/inf or wrong-length input (counted, the previous one held); saturates an
out-of-bound input; never publishes a diverged state (freezes, flags it, waits for ``reset``).
Parameters: :data:`metampc_plant.plant_params.PARAMETERS`; interfaces, clock modes and faults:
docs/plant.md.
"""
import math
import sys
import time
from array import array
from functools import partial
from typing import Optional, Sequence, Tuple

from builtin_interfaces.msg import Time
from metampc_common.held_publisher import held_qos, HeldPublisher
from metampc_common.node_main import (declare_parameters, EventCounts, LiveParameters,
                                      loop_executor, run_node)
from metampc_common.qos import LATCHED, STREAM
from metampc_common.replies import Replies
from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput, StepHold
from metampc_msgs.srv import ResetPlant
from metampc_plant.lockstep import Lockstep
from metampc_plant.plant_params import PARAMETERS, parse_params, PlantNodeConfig
from metampc_plant.simulator import Plant
from metampc_plant.theta_schedule import ThetaSchedule
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Header

GATE_PERIOD_S = 0.02    # lockstep start: how often to look for a subscriber and a publisher
COUNTERS = ('stale', 'rejected', 'timeouts', 'holds', 'dropped')


class PlantNode(Node):
    """ROS 2 front end of one :class:`Plant` (see the module docstring)."""

    def __init__(self):
        super().__init__('plant')
        values = declare_parameters(self, PARAMETERS)
        self.cfg = parse_params(values)
        self.plant = Plant(self.cfg.plant)
        self.family = self.plant.family
        self._zero_u = (0.0,) * self.family.n_u
        self.lockstep: Optional[Lockstep] = None   # realtime: none
        self._applied_u = self._zero_u     # last applied (saturated) input
        self._requested_u = self._zero_u  # realtime: latest accepted input, before saturation
        self._y0 = self.plant.output()  # y_0 of the first episode, drawn before any step
        self._n_resets = 0
        self._events = EventCounts(self, COUNTERS)
        self._counts = self._events.counts
        self._warn = self._events.warn
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._y_msg = PlantOutput()
        self._clock_msg = ClockMsg()

        lockstep = self.cfg.mode == 'lockstep'
        # Held back while a reader that keeps all (the recorder) is full: nothing lost.
        self._pub_y = HeldPublisher(
            self.create_publisher(PlantOutput, 'y', held_qos(self.cfg.hold)), self.cfg.hold,
            partial(self._warn, 'dropped'))
        self._pub_info = self.create_publisher(PlantInfo, 'plant_info', LATCHED)
        self._pub_clock = (self.create_publisher(ClockMsg, '/clock', STREAM)
                           if lockstep and self.cfg.publish_clock else None)
        self._sub_u = self.create_subscription(ControlInput, 'u', self._on_input, STREAM)
        self._replies = Replies(Future)     # a repeated request id: the first answer
        self.create_service(ResetPlant, 'reset', self._replies.wrap(self._on_reset))

        self._timeout_timer = None
        self._hold_timer = None         # the timeout of a step the controller holds
        self._gate_timer = None
        self._tick_timer = None
        self._pace_timer = None
        self._paced_u: Optional[Tuple[float, ...]] = None  # an answer held back by the pace
        self._pace_open = True          # the pace lets the next answer step at once
        if lockstep:
            self.lockstep = Lockstep(self.cfg.plant.dt, self.cfg.input_timeout,
                                     self.cfg.start_timeout, time.monotonic())
            if self.lockstep.timeout_s is not None:
                self._timeout_timer = self.create_timer(
                    self.lockstep.timeout_s, self._on_timeout, clock=self._steady,
                    autostart=False)
            self._gate_timer = self.create_timer(GATE_PERIOD_S, self._on_gate,
                                                 clock=self._steady)
            self.create_subscription(StepHold, 'u_hold', self._on_hold, STREAM)
            if self.cfg.pace_s() > 0:
                self._pace_timer = self.create_timer(self.cfg.pace_s(), self._on_pace,
                                                     clock=self._steady, autostart=False)
        else:
            period = 1.0 / self.cfg.sample_rate_hz()
            self._tick_timer = self.create_timer(period, self._on_tick, clock=self._steady)
        LiveParameters(self, PARAMETERS, values, self.cfg, parse_params, self._on_params)
        self._publish_info()
        sim = self.cfg.plant
        self.get_logger().info(
            f'{self.cfg.mode} {self.family.name} plant: theta={list(sim.theta)}, dt={sim.dt} s, '
            f'x0={list(sim.x0)}, u in [{list(sim.u_min)}, {list(sim.u_max)}]'
            + (f'; y_0 goes out once y has {self.cfg.start_subscribers} subscriber(s) and u a '
               f'publisher (at the latest after start_timeout = {self.cfg.start_timeout} s)'
               + (f'; at most {self.cfg.real_time_factor:g}x real time'
                  if self.cfg.real_time_factor > 0 else '')
               if lockstep
               else f', {self.cfg.sample_rate_hz()} Hz: '
               f'{self.cfg.sample_rate_hz() * sim.dt:g}x real time'))
        if not lockstep:
            self._start()

    # --- time and publication -------------------------------------------------------------

    def _stamp(self) -> Time:
        """Sim time of the current tick (lockstep) or the node clock's time (realtime)."""
        if self.lockstep is not None:
            t_ns = self.lockstep.stamp_ns
            return Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return self.get_clock().now().to_msg()

    def _publish_y(self, y: np.ndarray, u_applied: Sequence[float], saturated: bool) -> None:
        """Publish y_k (then /clock in lockstep) and restart the input timeout."""
        if self.lockstep is not None:
            self.lockstep.published()
        msg = self._y_msg
        msg.header.stamp = self._stamp()
        msg.step = self.plant.step_index
        msg.y = array('d', y)
        msg.u_applied = array('d', u_applied)
        msg.theta = array('d', self.plant.theta)
        msg.saturated = saturated
        msg.diverged = self.plant.diverged
        self._pub_y.publish(msg)
        # /clock after y: a sim-time timer woken by this tick then already has y_k in hand.
        if self._pub_clock is not None:
            self._clock_msg.clock = msg.header.stamp
            self._pub_clock.publish(self._clock_msg)
        if self._hold_timer is not None:
            self.destroy_timer(self._hold_timer)
            self._hold_timer = None
        if self._timeout_timer is not None:
            self._timeout_timer.reset()
        if self._pace_timer is not None:
            self._pace_open, self._paced_u = False, None
            self._pace_timer.reset()

    def _publish_info(self) -> None:
        sim, fam = self.cfg.plant, self.family
        self._pub_info.publish(PlantInfo(
            family=fam.name, theta=list(self.plant.theta),
            theta_schedule=list(self.plant.schedule.flat()),
            theta_names=[c.name for c in fam.theta], dt=sim.dt, substeps=sim.substeps,
            u_min=list(sim.u_min), u_max=list(sim.u_max),
            input_names=[s.name for s in fam.inputs], input_units=[s.unit for s in fam.inputs],
            output_names=[s.name for s in fam.outputs],
            output_units=[s.unit for s in fam.outputs],
            process_noise_std=sim.process_noise_std,
            measurement_noise_std=sim.measurement_noise_std, seed=sim.seed,
            clock_mode=self.cfg.mode,
            rate_hz=0.0 if self.lockstep is not None else self.cfg.sample_rate_hz(),
            state_bound=sim.state_bound, diverged=self.plant.diverged,
            n_resets=self._n_resets, header=Header(stamp=self._stamp())))

    # --- stepping -----------------------------------------------------------------------

    def _end_gate(self) -> None:
        """Leave the lockstep start gate (idempotent): from now on inputs answer steps."""
        if self._gate_timer is not None:
            self.destroy_timer(self._gate_timer)
            self._gate_timer = None
        if self.lockstep is not None:
            self.lockstep.start()

    def _start(self) -> None:
        """Publish y_0 of the first episode."""
        self._end_gate()
        self._publish_y(self._y0, self._zero_u, False)

    def _advance(self, u_requested: Tuple[float, ...]) -> None:
        """Hold u_requested (finite) over one sample, then publish y_{k+1}."""
        u, saturated = self.plant.saturate(u_requested)
        was_diverged = self.plant.diverged
        schedule = self.plant.schedule
        passed = schedule.boundaries_passed(self.plant.time)
        y = self.plant.step(u)
        if schedule.boundaries_passed(self.plant.time) != passed:   # a segment starts or ends
            self.get_logger().info(f'theta {list(self.plant.theta)} from step '
                                   f'{self.plant.step_index} (t = {self.plant.time:g} s)')
            self._publish_info()
        self._applied_u = u
        if self.plant.diverged and not was_diverged:
            self.get_logger().error(
                f'plant diverged at step {self.plant.step_index} (theta='
                f'{list(self.plant.theta)}): the state left |x|_inf <= '
                f'{self.cfg.plant.state_bound} or turned non-finite; holding '
                'the last finite state until reset')
            self._publish_info()
        self._publish_y(y, u, saturated)

    def _check_input(self, values) -> Tuple[Optional[Tuple[float, ...]], str]:
        """(u, '') for a valid ControlInput.u, else (None, why it was rejected)."""
        n_u = self.family.n_u
        if len(values) != n_u:
            return None, f'expected {n_u} input value(s), got {len(values)}'
        u = tuple(float(v) for v in values)
        if not all(math.isfinite(v) for v in u):
            return None, f'non-finite input {list(u)}'
        return u, ''

    def _answered(self, u: Tuple[float, ...]) -> None:
        """Lockstep: the current step is answered with u; step now, or when the pace allows."""
        if self._pace_open:
            self._advance(u)
            return
        self._paced_u = u
        if self._timeout_timer is not None:
            self._timeout_timer.cancel()

    def _on_pace(self) -> None:
        self._pace_timer.cancel()
        u, self._paced_u = self._paced_u, None
        if u is None:
            self._pace_open = True
        else:
            self._advance(u)

    def _on_input(self, msg: ControlInput) -> None:
        step = self.plant.step_index
        if self.lockstep is not None and (not self.lockstep.answers(msg.step, step)
                                          or self._paced_u is not None):
            self._warn('stale', f'ignored an input for step {msg.step}: waiting for step '
                       f'{step}' + (' (answered)' if self._paced_u is not None else ''))
            return
        u, why = self._check_input(msg.u)
        if u is None:
            self._warn('rejected', f'rejected the input for step {msg.step} ({why}); holding '
                       f'u = {list(self._applied_u)}')
            if self.lockstep is not None:
                self._answered(self._applied_u)
            return
        if self.lockstep is not None:
            self._answered(u)
        else:
            self._requested_u = u

    def _on_timeout(self) -> None:
        self._warn('timeouts', f'no input for step {self.plant.step_index} within '
                   f'{self.cfg.input_timeout} s; holding u = {list(self._applied_u)}')
        self._answered(self._applied_u)

    def _on_hold(self, msg: StepHold) -> None:
        """The controller holds its answer to msg.step: wait as long as it said, then the
        input timeout (Lockstep.hold_timeout_s)."""
        hold_s = msg.hold_s if math.isfinite(msg.hold_s) and msg.hold_s >= 0 else 0.0
        wait = self.lockstep.hold_timeout_s(msg.step, self.plant.step_index, hold_s)
        if wait is None:
            return
        self._timeout_timer.cancel()
        if self._hold_timer is not None:
            self.destroy_timer(self._hold_timer)
        self._hold_timer = self.create_timer(wait, self._on_timeout, clock=self._steady)
        self._counts['holds'] += 1
        self.get_logger().info(f'the controller holds step {msg.step} for up to {hold_s:g} s '
                               f'(it waits for a model): step {msg.step} waits {wait:g} s')

    def _on_gate(self) -> None:
        matched = (self._pub_y.get_subscription_count() >= self.cfg.start_subscribers
                   and self._sub_u.get_publisher_count() > 0)
        if self.lockstep.gate(time.monotonic(), matched):
            self._start()

    def _on_tick(self) -> None:
        self._advance(self._requested_u)

    def _on_params(self, config: PlantNodeConfig, changes: dict) -> None:
        """An accepted change of the noise levels (the live parameters): from the next step."""
        self.cfg = config
        sim = config.plant
        self.plant.set_noise(sim.process_noise_std, sim.measurement_noise_std)
        self._publish_info()
        self.get_logger().info(f'noise levels from step {self.plant.step_index + 1} on: '
                               f'process {sim.process_noise_std}, measurement '
                               f'{sim.measurement_noise_std}')

    # --- reset --------------------------------------------------------------------------

    def _reset_error(self, theta, x0, schedule) -> str:
        """Why a reset request is invalid, or '' if it is fine."""
        fam = self.family
        if len(theta):
            try:
                fam.check_theta_in_support(theta)
            except ValueError as err:
                return f'{err} (or none to keep the current one)'
        try:
            ThetaSchedule.parse(schedule or self.cfg.plant.theta_schedule, fam,
                                theta if len(theta) else self.plant.schedule.start)
        except ValueError as err:
            return str(err)
        if len(x0) not in (0, fam.n_x):
            return (f'x0 must have {fam.n_x} values (or none to use the parameter), got '
                    f'{len(x0)}')
        if not all(math.isfinite(v) for v in x0):
            return f'x0 must be finite, got {list(x0)}'
        bound = self.cfg.plant.state_bound
        if any(abs(v) > bound for v in x0):
            return f'x0 {list(x0)} lies outside state_bound {bound}'
        return ''

    def _on_reset(self, request: ResetPlant.Request, response: ResetPlant.Response
                  ) -> ResetPlant.Response:
        why = self._reset_error(request.theta, request.x0, request.theta_schedule)
        if why:
            response.success, response.message = False, f'reset rejected: {why}'
            self.get_logger().warning(response.message)
            return response
        y0 = self.plant.reset(list(request.theta) or None, list(request.x0) or None,
                              list(request.theta_schedule) or None)
        self._applied_u = self._requested_u = self._zero_u
        self._n_resets += 1
        self._publish_info()
        self._end_gate()  # a reset before the lockstep start starts it
        self._publish_y(y0, self._zero_u, False)
        if self._tick_timer is not None:  # realtime: y_1 one full period after y_0
            self._tick_timer.reset()
        response.success = True
        response.message = (f'reset {self._n_resets}: theta={list(self.plant.theta)}, '
                            f'x0={self.plant.x.tolist()}'
                            + (f', theta_schedule={list(self.plant.schedule.flat())}'
                               if self.plant.schedule.segments else ''))
        self.get_logger().info(response.message)
        return response

    def destroy_node(self) -> None:
        """Destroy the node, then log what was counted over the run."""
        super().destroy_node()
        # Logged after destruction on purpose: the node's /rosout publisher is gone then, so
        # this also works after a SIGINT has already shut the context down.
        self.get_logger().info(
            f'stopped at step {self.plant.step_index} after {self._n_resets} reset(s): '
            + self._events.summary())


def main(args=None) -> int:
    """`ros2 run metampc_plant plant [--ros-args -p name:=value ...]`; returns the exit code."""
    return run_node(PlantNode, 'plant', args, executor=loop_executor)


if __name__ == '__main__':
    sys.exit(main())
