"""The `controller` node as a process, against the `plant` node in lockstep, in the session's
own domain. The probe node of the test publishes weights, references and service calls and
records y, u and mpc_status.

The model the tests send is the hand-built NSSM of metampc_model.manual_model: the
van der Pol plant linearised at the origin and discretised, with an encoder that reads the
last output (z_t = [y_t; 0...]). It has the plant's equilibria, so a set-point is tracked
without offset for any theta.

Each loop starts the controller first and the plant only once the probe's subscriptions have
matched the controller's publishers: the probe then hears every input from step 0 on (a
subscriber that matches late misses the first messages, which would look like unanswered
steps). It listens to y only from the first input on (see Loop.start), so the ys it hears
start later. The plant's own counters (stale, rejected, timed-out inputs) are a second
witness.

The probe paces the loop: the plant reads its input from `u_paced`, to which the probe passes
each u_k of the controller, unchanged, once it has taken u_k, the mpc_status of step k and
(when it listens to y) y_k. The plant steps only then, so the probe is never more than a step
behind. Unpaced, a lockstep loop runs as fast as the two nodes can answer (hundreds of steps
per second), and a probe starved of CPU on a loaded machine fell hundreds of messages behind:
its lists lagged what the assertions took for the present, and a message beyond the depth of a
history would be lost. Each publisher numbers its messages 1, 2, ...: the probe checks that it
lost no input, and tells a restarted controller's inputs from those of the one before by it.
"""
from collections import Counter
import math
import subprocess
import sys
import time
from typing import List

from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantOutput
from metampc_msgs.srv import SetActive
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.weights_codec import fields_from_weights
from metampc_testing import own_lines, session_pids

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# A long input timeout: a step the controller does not answer stalls the run (and the test
# times out) instead of being covered up by the plant holding its input. No start timeout: the
# plant starts once the probe's input publisher exists (Loop.start), however long that takes.
PLANT = {'theta': 0.5, 'input_timeout': 30.0, 'start_timeout': 0.0}
PACED = {'u': 'u_paced'}    # the plant's remap: its input comes through the probe
# A node's start-up (imports, DDS discovery) took over 30 s on a loaded 2-core machine.
START_TIMEOUT = 90.0
# time_limit: OSQP's wall-clock cap (50 ms) trips when a loaded machine stalls the process;
# the checks of 'solved' below are about the answer, not its speed.
CONTROLLER = {'use_sim_time': True, 'reference': 'setpoint', 'reference_values': [0.5],
              'time_limit': 30.0}


def weights(version: int, theta: float = 0.5, **model) -> NssmWeights:
    config, norm, params = linearised_vdp_nssm(theta, 0.1, **model)
    return NssmWeights(version=version, method='manual', stage='adapted',
                       **fields_from_weights(config, norm, params))


class Loop:
    """Probe side of a closed loop, which it paces (see the module docstring): records y, u
    and mpc_status, passes each u on to the plant; publishes weights. Every callback runs on
    the probe's one executor thread."""

    def __init__(self, probe):
        self.probe = probe
        self.ys, self.us, self.status = [], [], []
        self._numbered_us = []      # (publication sequence number, u), in arrival order
        self._pending = {}          # step -> u not passed on yet
        self._status_steps = set()  # steps whose mpc_status came and whose u is not passed on
        self._paced = None          # the plant's input publisher (Loop.start)
        node = probe.node
        self._subs = [node.create_subscription(ControlInput, 'u', self._on_u, RELIABLE),
                      node.create_subscription(MpcStatus, 'mpc_status', self._on_status,
                                               RELIABLE)]
        self.weights = node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)

    def _on_u(self, msg: ControlInput, info) -> None:
        self._numbered_us.append((info['publication_sequence_number'], msg))
        self.us.append(msg)
        self._pending[msg.step] = msg
        self._pass_on()

    def _on_status(self, msg: MpcStatus) -> None:
        self.status.append(msg)
        self._status_steps.add(msg.step)
        self._pass_on()

    def _on_y(self, msg: PlantOutput) -> None:
        self.ys.append(msg)
        self._pass_on()

    def _pass_on(self) -> None:
        """Pass u_k on once the probe has its mpc_status and, once it hears y, y_k (the plant
        steps no further than the probe has taken; its steps only grow in these tests)."""
        if self._paced is None:
            return
        for step in sorted(self._pending):
            if step in self._status_steps and (not self.ys or self.ys[-1].step >= step):
                self._paced.publish(self._pending.pop(step))
                self._status_steps.discard(step)

    def start(self, procs, plant_params: dict, controller_params: dict):
        """Start the controller, wait until the probe hears it, start the plant, and listen to
        y once the controller has answered y_0: the plant sends y_0 when y has a subscriber
        (and u a publisher), and that subscriber must be the controller, not the probe. The
        plant's input publisher is created once the probe knows the plant's subscription, so
        it is matched from its first message on (and the plant's start gate opens on it)."""
        ctl = procs.start('metampc_controller', 'controller', params=controller_params)
        self.probe.wait_for(lambda: all(s.get_publisher_count() > 0 for s in self._subs),
                            START_TIMEOUT, 'the controller publishers matched')
        plant = procs.start('metampc_plant', 'plant', params=plant_params, remaps=PACED)
        self.probe.wait_for(lambda: self.probe.node.count_subscribers(PACED['u']) > 0,
                            START_TIMEOUT, 'the plant subscribed to its input')
        self._paced = self.probe.node.create_publisher(ControlInput, PACED['u'], RELIABLE)
        self.probe.wait_for(lambda: self.us, START_TIMEOUT, 'the answer to y_0')
        self.probe.node.create_subscription(PlantOutput, 'y', self._on_y, RELIABLE)
        return plant, ctl

    def controller_runs(self) -> List[List[ControlInput]]:
        """The inputs heard, one list per controller process, in order: a publisher numbers its
        messages 1, 2, ..., a new one from 1 again. Asserts that the probe lost none after the
        first it heard of each (it may miss the first answers of a controller started while
        the loop runs, before discovery matched them: the plant then holds its input)."""
        runs, last = [], None
        for seq, msg in list(self._numbered_us):
            if last is None or seq <= last:
                runs.append([])
            else:
                assert seq == last + 1, f'inputs {last + 1}..{seq - 1} of a controller lost'
            runs[-1].append(msg)
            last = seq
        return runs

    def wait_steps(self, n: int, timeout: float = 30.0) -> None:
        """Until the plant has published n more samples than now."""
        target = len(self.ys) + n
        self.probe.wait_for(lambda: len(self.ys) >= target, timeout, f'{n} more samples')

    def wait_tracked(self, value: float, tol: float = 0.02, timeout: float = 60.0) -> None:
        """Until the last 5 samples have |y_1 - value| < tol."""
        self.probe.wait_for(lambda: len(self.ys) >= 5 and all(
            abs(m.y[0] - value) < tol for m in self.ys[-5:]), timeout, f'y_1 at {value}')

    def wait_status(self, predicate, what: str, timeout: float = 30.0) -> MpcStatus:
        self.probe.wait_for(lambda: self.status and predicate(self.status[-1]), timeout, what)
        return self.status[-1]

    def wait_event(self, version: int, what: str, timeout: float = 30.0):
        """(the first model event about `version`, the status that carried it)."""
        def found():
            return next(((e, s) for s in list(self.status) for e in s.model_events
                         if e.version == version), None)
        self.probe.wait_for(found, timeout, what)
        return found()

    def inputs(self, steps: int) -> dict:
        """{k: u_k[0]} for k < steps, once the probe has them (u and y are different topics:
        y_{k+1} may reach the probe before the u_k it answers)."""
        def missing():
            return sorted(set(range(steps)) - {m.step for m in self.us})

        try:
            self.probe.wait_for(lambda: not missing(), 30.0, f'the inputs of steps < {steps}')
        except AssertionError as err:
            raise AssertionError(f'{err}; missing {missing()[:20]}') from None
        return {m.step: m.u[0] for m in self.us}

    def check_one_answer_per_step(self) -> None:
        """Every step before the newest y_k answered exactly once (the probe hears every input,
        see the module docstring), and each y the probe heard applied the input of the step
        before (the probe's y subscription may match the plant after y_0: the ys heard need
        only be contiguous)."""
        ys = list(self.ys)
        last = ys[-1].step
        sent = self.inputs(last)
        assert len(self.controller_runs()) == 1, 'one controller'
        us = list(self.us)      # the loop goes on: it may hold answers beyond `last` by now
        answers = Counter(m.step for m in us)
        assert all(answers[k] == 1 for k in range(last)), 'each step answered exactly once'
        # The probe may hear u_k before y_k (other topic), so it waits for the ys to catch up.
        newest = max(answers)
        self.probe.wait_for(lambda: self.ys[-1].step >= newest, 30.0,
                            f'y_{newest} (answered): no answer for a step not yet published')
        heard = [m.step for m in ys]
        assert heard == list(range(heard[0], last + 1)), 'one episode, no gap'
        assert all(y.u_applied[0] == sent[y.step - 1] for y in ys if y.step), 'inputs applied'


def stop_cleanly(procs, proc) -> str:
    # 30 s, not the default 10: a controller beside a second suite once took over 10 s.
    code = procs.interrupt(proc, timeout=30.0)
    out = procs.output(proc)
    assert code == 0, out
    assert 'Traceback' not in out, out
    assert session_pids(proc) == [], 'a process outlived ros2 run'
    return out


def test_excitation_tracking_swaps_rejections_and_restart(procs, probe):
    loop = Loop(probe)
    # input_timeout 3 s: the restart below leaves the step of the stopped controller to it.
    plant, ctl = loop.start(procs, {**PLANT, 'input_timeout': 3.0},
                            {**CONTROLLER, 'pre_model_input': 'excitation',
                             'excitation_amplitude': 0.4, 'excitation_seed': 3})
    # Before a model: the seeded excitation, within +-0.4, held 0.5 s = 5 samples from step 0.
    loop.wait_steps(16)
    u = loop.inputs(15)
    holds = [{u[k] for k in range(start, start + 5)} for start in (0, 5, 10)]
    assert all(len(h) == 1 for h in holds) and len(set.union(*holds)) == 3, holds
    assert all(abs(v) <= 0.4 for v in u.values())
    assert all(s.model_version == 0 and s.solver_status == 'no_model' and s.iterations == -1
               and math.isnan(s.residual) and not s.u_plan and len(s.y_ref) == 40
               for s in loop.status)

    loop.weights.publish(weights(1))
    loop.wait_status(lambda s: s.model_version == 1, 'model 1 in use')
    loop.wait_steps(20)

    # Invalid weights are rejected; model 1 stays in use.
    bad = weights(2)
    bad.params[7] = math.nan
    loop.weights.publish(bad)
    event, st = loop.wait_event(2, 'NaN refused')
    assert (event.outcome, event.cause) == ('refused', 'weights') and 'non-finite' in (
        event.reason) and st.model_version == 1, st
    assert st.model_status == f'rejected: {event.reason}'
    bad = weights(3)
    bad.shapes[0] += 1
    loop.weights.publish(bad)
    event, st = loop.wait_event(3, 'wrong shapes refused')
    assert (event.outcome, event.cause) == ('refused', 'weights') and (
        'encoder.0.weight has shape' in event.reason) and st.model_version == 1, st

    # A model of another architecture is swapped in mid-run without a missed step.
    loop.weights.publish(weights(4, n_z=4, hidden=(8, 8), history=5))
    loop.wait_status(lambda s: s.model_version == 4 and s.model_status == 'ok', 'model 4')
    loop.wait_steps(50)

    loop.check_one_answer_per_step()
    versions = [m.model_version for m in sorted(loop.us, key=lambda m: m.step)]
    assert versions == sorted(versions) and versions[-1] == 4 and 1 in versions
    assert all(abs(m.u[0]) <= 1.0 and math.isfinite(m.u[0]) for m in loop.us)
    assert abs(loop.ys[-1].y[0] - 0.5) < 0.02 and abs(loop.ys[-1].y[1]) < 0.02, 'tracked'
    st = loop.status[-1]
    assert (st.planner, st.solver_status, st.iterations > 0) == ('latent_mpc', 'solved', True)
    assert len(st.u_plan) == 20 and len(st.y_pred) == len(st.y_ref) == 40
    assert st.y_ref[0] == 0.5 and st.y_ref[1] == 0.0 and 0 < st.solve_time <= st.tick_time

    # Restarted mid-run, the controller gets the latched model 4 without a new publish.
    out = stop_cleanly(procs, ctl)
    assert 'rejected weights version 2' in out and 'rejected weights version 3' in out, out
    ctl = procs.start('metampc_controller', 'controller', params=CONTROLLER)

    def restarted() -> List[ControlInput]:
        runs = loop.controller_runs()
        assert len(runs) <= 2, f'{len(runs)} controllers'
        return runs[1] if len(runs) == 2 else []

    # Its first answers may come before discovery has delivered the latched model.
    probe.wait_for(lambda: len(restarted()) > 20 and restarted()[-1].model_version == 4,
                   START_TIMEOUT, 'inputs with model 4 after the restart')
    new = restarted()
    versions = [m.model_version for m in new]
    assert versions == sorted(versions) and set(versions) <= {0, 4}
    steps = [m.step for m in new]
    assert steps == list(range(steps[0], steps[0] + len(steps)))
    assert steps[0] > max(m.step for m in loop.controller_runs()[0]), 'answers y after restart'
    stop_cleanly(procs, ctl)
    out = stop_cleanly(procs, plant)
    assert '0 stale, 0 rejected' in out, out


def test_nmpc_reference_override_and_set_active(procs, probe):
    loop = Loop(probe)
    reference = probe.node.create_publisher(Float64MultiArray, 'reference', RELIABLE)
    client = probe.node.create_client(SetActive, 'set_active')
    plant, ctl = loop.start(procs, PLANT, {**CONTROLLER, 'planner': 'nmpc', 'horizon': 10,
                                           'reference_values': [-0.5]})
    loop.wait_tracked(-0.5)     # nmpc tracks with the samples' theta
    st = loop.status[-1]
    assert (st.planner, st.model_version, st.model_status) == ('nmpc', 0, 'none')
    assert len(st.u_plan) == 10 and st.iterations > 0 and st.y_ref[0] == -0.5
    assert st.residual < 1e-8                             # IPOPT's, published

    reference.publish(Float64MultiArray(data=[0.3, 0.0]))
    loop.wait_tracked(0.3)
    assert loop.status[-1].y_ref[0] == 0.3

    assert client.wait_for_service(timeout_sec=10.0)

    def set_active(value: bool) -> SetActive.Response:
        # Deactivating an inactive controller changes nothing: resent while unanswered (a
        # first answer can be lost, SpunNode.call).
        return probe.call(client, SetActive.Request(active=value), 10.0,
                          None if value else 3.0)

    answer = set_active(False)
    assert answer.success and (answer.answered_step, answer.model_version) == (-1, 0), answer
    assert answer.message.startswith('inactive'), answer.message
    # Inactive, the controller answers nothing, so the lockstep plant (input_timeout 30 s)
    # waits on its newest y, y_S, which activation answers at once. What reached the probe
    # before activation shows it, whatever the delays: no input or status for S or later, no
    # y after y_S. (The sleep gives a faulty controller time to publish; nothing is timed.)
    time.sleep(1.0)
    before = {'u': list(loop.us), 'mpc_status': list(loop.status), 'y': list(loop.ys)}
    answer = set_active(True)
    waiting = answer.answered_step
    assert waiting >= 0, f'activation answered nothing: {answer}'
    assert f'answered step {waiting}' in answer.message, answer.message
    assert all(m.step < waiting for m in before['u'] + before['mpc_status']), (
        'inactive: nothing published')
    assert all(m.step <= waiting for m in before['y']), 'the plant waited for an input'
    loop.wait_steps(10)
    loop.check_one_answer_per_step()
    stop_cleanly(procs, ctl)
    out = stop_cleanly(procs, plant)
    assert '0 stale, 0 rejected, 0 timeouts' in out, out


def test_bad_parameter_one_line_and_exit_2(procs):
    # Every range check is tested in-process (test_controller_params.py); this one is the
    # node's way of reporting any of them.
    proc = procs.start('metampc_controller', 'controller',
                       params={'horizon': 0, 'reference': 'setpoint'})
    code = proc.wait(60.0)
    lines = own_lines(procs.output(proc))
    assert code == 2, lines
    assert len(lines) == 1 and 'invalid parameter: horizon must be >= 1' in lines[0], lines


def _loads_torch(session: int) -> bool:
    """Whether a process of `session` (a `ros2 run` and its node) has mapped torch's library."""
    for pid in session_pids(session):
        try:
            with open(f'/proc/{pid}/maps') as f:
                if 'libtorch' in f.read():
                    return True
        except OSError:
            pass
    return False


def test_send_model_publishes_the_hand_built_model_latched_and_stops_cleanly(procs, probe):
    """`ros2 run metampc_controller send_model`: a late subscriber gets the model of
    linearised_vdp_nssm(theta, dt, history) with the version asked for; Ctrl-C exits 0 (also
    during the start-up, while it imports torch); a bad value is one line and exit status 2."""
    from metampc_model.weights_codec import fields_of, weights_from_fields
    sender = procs.start('metampc_controller', 'send_model',
                         params={'theta': 0.5, 'dt': 0.05, 'history': 6, 'version': 7})
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got: List[NssmWeights] = []
    probe.wait_for(lambda: 'published the hand-built model v7' in procs.output(sender), 60.0,
                   'the published model')
    probe.node.create_subscription(NssmWeights, 'nssm_weights', got.append, latched)
    probe.wait_for(lambda: got, 30.0, 'the latched model')
    msg = got[0]
    assert (msg.version, msg.method, msg.stage) == (7, 'manual', 'adapted')
    decoded = weights_from_fields(fields_of(msg))
    config, norm, params = linearised_vdp_nssm(0.5, 0.05, history=6)
    assert decoded.config == config
    for name, value in params.items():
        assert decoded.params[name].tolist() == value.numpy().tolist(), name
    code = procs.interrupt(sender, timeout=30.0)
    assert code == 0 and 'Traceback' not in procs.output(sender), procs.output(sender)

    # Ctrl-C while the node imports torch (1-2 s): the entry point notes it. Waited for by
    # torch's libraries appearing in the node's memory map, not by a guessed sleep.
    early = procs.start('metampc_controller', 'send_model')
    probe.wait_for(lambda: _loads_torch(early.pid), 60.0, 'the node importing torch')
    assert procs.interrupt(early, timeout=30.0) == 0, procs.output(early)
    assert 'Traceback' not in procs.output(early), procs.output(early)

    bad = procs.start('metampc_controller', 'send_model', params={'dt': 0.0})
    assert bad.wait(60.0) == 2
    lines = own_lines(procs.output(bad))
    assert len(lines) == 1 and 'invalid parameter: dt must be > 0' in lines[0], lines


def test_the_controller_imports_no_torch():
    """The node and its core decode weights and tick in numpy: they import with torch blocked
    (python -X importtime showed ~1 s of torch import through the model modules)."""
    code = ('import sys; sys.modules["torch"] = None; '
            'import metampc_controller.controller_node, metampc_controller.controller_core')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
