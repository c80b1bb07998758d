"""Live parameters in a lockstep loop (issue 17, item 2): `ros2 param set /controller r ...`
and a set-point change take effect at a known tick, and an out-of-range value is refused with
its reason while the loop goes on.

Two runs of plant + controller (+ a recorder in the second), lockstep, the same seeds and the
hand-built model: lockstep runs are deterministic, so the run without a change is what the
run with changes would have done without them. The probe paces the loop (the plant reads its
input from `u_paced`, to which the probe passes each u_k of the controller once it has u_k
and the status of step k) and holds it at chosen steps while the `ros2` command runs as a
subprocess; a change accepted while the loop waits at step k applies from step k + 1 on.
"""
import math
import subprocess
import threading

from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantInfo, PlantOutput
from metampc_msgs.srv import SetActive
import numpy as np
import pytest

from metampc_bringup.analysis.run_report import analyse
from metampc_recording.recorder_config import RecorderConfig
from test_faults import LATCHED, RELIABLE, weights

DT = 0.1
PLANT = {'theta': 0.5, 'measurement_noise_std': 0.01, 'seed': 3, 'input_timeout': 30.0,
         'start_timeout': 0.0}
# time_limit: OSQP's wall-clock cap would make a loaded machine's run differ from another's.
CONTROLLER = {'use_sim_time': True, 'reference': 'setpoint', 'reference_values': [0.5],
              'time_limit': 30.0}
R_AT, SETPOINT_AT = 30, 60      # the loop is held at these steps while `ros2 param set` runs
START_TIMEOUT = 90.0
WAIT = ('--timeout', '20')      # ros2param's wait for the node (discovery under load)


def ros2(*args):
    return subprocess.run(['ros2', *args], capture_output=True, text=True, timeout=120)


class PacedLoop:
    """The probe's side of one run: records u, mpc_status and y by step; passes u_k on to the
    plant (on `u_paced`) once it has u_k and the status of step k, for steps below `limit`."""

    def __init__(self, probe):
        self.probe = probe
        self.us, self.status, self.ys, self.infos = {}, {}, [], []
        self.limit = 0
        self._lock = threading.Lock()
        self._passed = set()
        node = probe.node
        self._entities = [
            node.create_subscription(ControlInput, 'u', self._on_u, RELIABLE),
            node.create_subscription(MpcStatus, 'mpc_status', self._on_status, RELIABLE),
            node.create_subscription(PlantOutput, 'y', self._on_y, RELIABLE),
            node.create_subscription(PlantInfo, 'plant_info', self.infos.append, LATCHED),
            node.create_publisher(ControlInput, 'u_paced', RELIABLE)]
        self._paced = self._entities[-1]
        self.weights = node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
        self._entities.append(self.weights)

    def _on_u(self, msg):
        with self._lock:
            self.us.setdefault(msg.step, []).append(msg)
        self._pass_on()

    def _on_status(self, msg):
        with self._lock:
            self.status.setdefault(msg.step, []).append(msg)
        self._pass_on()

    def _on_y(self, msg):
        with self._lock:
            self.ys.append(msg)

    def _pass_on(self):
        with self._lock:
            ready = [k for k in self.us if k < self.limit and k in self.status
                     and k not in self._passed]
            for k in sorted(ready):
                self._paced.publish(self.us[k][0])
                self._passed.add(k)

    def run_to(self, step, timeout=60.0):
        """Let the loop run until the controller has answered `step` (u and status); the
        plant then waits at y_step."""
        self.limit = step
        self._pass_on()
        self.probe.wait_for(lambda: step in self.us and step in self.status, timeout,
                            f'the answer to step {step}')

    def release(self):
        """Let the loop run on, unheld."""
        self.limit = 10 ** 9
        self._pass_on()

    def newest(self):
        return max(self.status, default=-1)

    def close(self):
        for entity in self._entities:
            if hasattr(entity, 'publish'):
                self.probe.node.destroy_publisher(entity)
            else:
                self.probe.node.destroy_subscription(entity)


def start_run(procs, probe, subscribers_of_y=2):
    """Controller with the model in use, then the plant; the loop is held at step 0."""
    loop = PacedLoop(probe)
    ctl = procs.start('metampc_controller', 'controller', params=CONTROLLER)
    loop.weights.publish(weights(1))
    client = probe.node.create_client(SetActive, 'set_active')
    assert client.wait_for_service(timeout_sec=START_TIMEOUT)

    asked = []

    readers = subscribers_of_y - 1     # of u and mpc_status: the probe (and the recorder)

    def ready():      # the model a tick would use (y_0 is answered with it); readers matched
        # A first answer can be lost (docs/nodes.md): resent with its id, answered once.
        asked.append(f'ready-{len(asked)}')
        answer = probe.call(client, SetActive.Request(active=True, request_id=asked[-1]), 30.0,
                            resend_every=2.0)
        # An answer sent before a reader's match never reaches it (seen under two suites:
        # the recorder missed the first 31 statuses).
        return (answer.model_version == 1 and answer.matched_subscribers >= readers
                and answer.matched_status_subscribers >= readers)
    probe.wait_for(ready, START_TIMEOUT, 'the model in use and the readers matched')
    probe.node.destroy_client(client)
    plant = procs.start('metampc_plant', 'plant', remaps={'u': 'u_paced'},
                        params={**PLANT, 'start_subscribers': subscribers_of_y})
    loop.run_to(0, START_TIMEOUT)
    return loop, ctl, plant


def stop(procs, *nodes):
    for proc in nodes:
        assert procs.interrupt(proc, timeout=30.0) == 0, procs.output(proc)


def contiguous_answers(loop, last):
    """Each step 0..last answered by exactly one u and one status; each y applied the u of
    the step before."""
    assert [len(loop.us.get(k, ())) for k in range(last + 1)] == [1] * (last + 1)
    assert [len(loop.status.get(k, ())) for k in range(last + 1)] == [1] * (last + 1)
    ys = [y for y in loop.ys if 0 < y.step <= last]
    assert [y.step for y in ys] == list(range(ys[0].step, last + 1))
    assert all(list(y.u_applied) == list(loop.us[y.step - 1][0].u) for y in ys)


def test_live_r_and_setpoint_change_at_a_known_tick_and_refusals(procs, probe, tmp_path):
    # Run 1, no change: the baseline.
    base, ctl, plant = start_run(procs, probe)
    base.run_to(R_AT + 5)
    stop(procs, plant, ctl)
    base.close()

    # Run 2, recorded: r at step R_AT, the set-point at SETPOINT_AT, then refusals unheld.
    recording = str(tmp_path / 'live' / 'recording.mcap')
    recorder = procs.start('metampc_recording', 'recorder', params=RecorderConfig(
        output=recording, topics=['y', 'u', 'mpc_status', '/parameter_events'],
        flush_period=0.1).to_parameters())
    probe.wait_for(lambda: any(i.node_name == 'recorder' for i in
                               probe.node.get_subscriptions_info_by_topic('/parameter_events')),
                   START_TIMEOUT, 'the recorder on /parameter_events')
    loop, ctl, plant = start_run(procs, probe, subscribers_of_y=3)   # + the recorder
    loop.run_to(R_AT)
    out = ros2('param', 'set', '/controller', 'r', '2.0', *WAIT)
    assert (out.returncode, out.stdout, out.stderr) == (0, 'Set parameter successful\n', '')
    loop.run_to(SETPOINT_AT)
    out = ros2('param', 'set', '/controller', 'reference_values', '[0.2]', *WAIT)
    assert (out.returncode, out.stdout, out.stderr) == (0, 'Set parameter successful\n', '')

    loop.release()
    refused = {('r', '-0.1'): 'r must be > 0, got -0.1',
               ('u_max', '[2.0]'): ("input bounds [[-1.0], [2.0]] exceed the plant's "
                                    '[[-1.0], [1.0]] (plant_info): a change must stay within '
                                    'them')}
    before = loop.newest()
    for (name, value), reason in refused.items():
        out = ros2('param', 'set', '/controller', name, value, *WAIT)
        assert (out.returncode, out.stdout, out.stderr) == (
            0, '', f'Setting parameter failed: {reason}\n')
    after = loop.newest()
    assert after > before, 'the loop went on while the changes were refused'
    last = after + 20
    loop.run_to(last)
    stop(procs, plant, ctl, recorder)

    # The changes applied from the step after the hold on: u as without change before it,
    # different from it on; no tick dropped; the version says which tuning each tick used.
    contiguous_answers(loop, last)
    u = {k: loop.us[k][0].u[0] for k in range(last + 1)}
    u_base = {k: base.us[k][0].u[0] for k in range(R_AT + 6)}
    assert [u[k] for k in range(R_AT + 1)] == [u_base[k] for k in range(R_AT + 1)]
    assert all(u[k] != u_base[k] for k in range(R_AT + 1, R_AT + 6))
    version = [loop.status[k][0].config_version for k in range(last + 1)]
    assert version == [0] * (R_AT + 1) + [1] * (SETPOINT_AT - R_AT) + [2] * (last - SETPOINT_AT)
    y_ref0 = [loop.status[k][0].y_ref[0] for k in range(last + 1)]
    assert y_ref0 == [0.5] * (SETPOINT_AT + 1) + [0.2] * (last - SETPOINT_AT)

    # The recording shows the changes and the replay metrics split at them.
    metrics = analyse(recording, plots=False, report_name=None)['metrics']
    segments = metrics['tracking_segments']
    assert [(s['config_version'], s['first_step'], s['last_step']) for s in segments] == [
        (0, 0, R_AT), (1, R_AT + 1, SETPOINT_AT), (2, SETPOINT_AT + 1, last)]
    ys = {y.step: y.y[0] for y in loop.ys}
    for s in segments:      # the probe's own pairing: status k with the output of step k + 1
        err = [ys[k + 1] - y_ref0[k] for k in range(s['first_step'], s['last_step'] + 1)
               if k + 1 in ys]
        assert s['tracking']['samples'] == len(err)
        assert math.isclose(s['tracking']['rmse'], math.sqrt(np.mean(np.square(err))),
                            rel_tol=1e-9)
    changes = [c for c in metrics['parameter_changes'] if c['node'] == '/controller']
    assert [c['parameters'] for c in changes] == [{'r': 2.0}, {'reference_values': [0.2]}]
    # Stamped on the controller's sim time: the step the loop was held at.
    assert [c['stamp'] for c in changes] == pytest.approx([R_AT * DT, SETPOINT_AT * DT])
