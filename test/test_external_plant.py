"""A plant written only against metampc_msgs (examples/external_plant: a stand-in for a real
robot, with equations the stack does not know) is learned and controlled like the simulated
one: the learner, told a source family by name (duffing: one input, two outputs), buffers its
samples, meta-trains, adapts and publishes; the controller tracks with the adapted model.
"""
import math
import os

from metampc_msgs.msg import ControlInput, MpcStatus, PlantInfo, PlantOutput
from metampc_msgs.srv import Adapt, MetaTrain
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from metampc_testing import example_script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, 'examples', 'external_plant', 'external_plant.py')
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
LEARNER = {'family': 'duffing', 'n_systems': 4, 'episodes_per_system': 1,
           'episode_samples': 40, 'history': 3, 'loss_horizon': 3, 'hidden': [16], 'n_z': 3,
           'batch_size': 2, 'inner_steps': 2, 'cg_steps': 2, 'windows_per_task': 8,
           'torch_threads': 1, 'target_buffer_size': 40, 'heldout_fraction': 0.25}
CONTROLLER = {'reference': 'setpoint', 'reference_values': [0.3], 'pre_model_input': 'excitation',
              'rate_hz': 10.0}


def call(probe, client, request, timeout: float = 60.0):
    future = client.call_async(request)
    probe.wait_for(future.done, timeout, f'the answer of {client.srv_name}')
    return future.result()


def test_an_external_plant_is_learned_and_controlled(procs, probe, tmp_path):
    ys, infos, inputs, statuses = [], [], [], []
    probe.node.create_subscription(PlantOutput, 'y', ys.append, RELIABLE)
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    probe.node.create_subscription(ControlInput, 'u', inputs.append, RELIABLE)
    probe.node.create_subscription(MpcStatus, 'mpc_status', statuses.append, RELIABLE)
    with example_script([SCRIPT, '0.1'], tmp_path / 'external_plant.log'):
        learner = procs.start('metampc_learner', 'learner', params=LEARNER)
        controller = procs.start('metampc_controller', 'controller', params=CONTROLLER)
        meta = probe.node.create_client(MetaTrain, 'meta_train')
        adapt = probe.node.create_client(Adapt, 'adapt')
        for client in (meta, adapt):
            assert client.wait_for_service(timeout_sec=60.0), client.srv_name
        probe.wait_for(lambda: infos and len(ys) > 5, 60.0, 'the external plant on the graph')
        assert (infos[-1].family, list(infos[-1].theta)) == ('external_spring', [])

        result = call(probe, meta, MetaTrain.Request(method='imaml', iterations=4))
        assert result.success, result.message
        # D_target: 40 samples of the plant under the controller's pre-model excitation, as the
        # learner counts them (the probe's count ran ahead of a learner that matched y late).
        probe.wait_for(lambda: 'D_target full: 40 samples' in procs.output(learner), 60.0,
                       "the learner's 40 samples of the plant")
        result = call(probe, adapt, Adapt.Request(method='imaml', steps=3))
        assert result.success, result.message
        version = result.model_version
        probe.wait_for(lambda: sum(m.model_version == version for m in inputs) >= 20, 60.0,
                       f'20 inputs of the adapted model v{version}')
        used = [s for s in statuses if s.model_version == version]
        assert used and all(s.solver_status == 'solved' or s.fallback for s in used)
        assert all(abs(m.u[0]) <= 1.0 for m in inputs)
        assert all(all(math.isfinite(v) for v in m.y) and not m.diverged for m in ys)
        for proc in (controller, learner):
            assert procs.interrupt(proc) == 0, procs.output(proc)
