"""The `learner` node as a process (`ros2 run metampc_learner learner`) beside a lockstep plant.

The plant runs without a controller (short input_timeout: it holds u = 0 and steps every
20 ms on its limit cycle), so ``y`` flows while the learner trains. The probe calls the
services, watches ``progress`` and ``y``, and subscribes late to ``nssm_weights``.
"""
import itertools
import math
import os

from metampc_msgs.msg import AdaptRefusal, MpcStatus, NssmWeights, TrainingProgress
from metampc_msgs.srv import Adapt, MetaTrain, SetBuffering
import numpy as np
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
import torch

from metampc_model.weights_codec import fields_of, weights_from_fields
from metampc_learner.checkpoint import load_checkpoint
from metampc_testing import own_lines, session_pids

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Several seconds of training, so several progress heartbeats: 80 iterations took ~0.5 s on the
# fast meta-gradient backend and gave 3 distinct progress iterations once (a flaky > 3).
ITERATIONS = 800
CAPACITY = 40       # D_target; 10 held out (heldout_fraction 0.25), window H + T = 6
TINY = {'n_systems': 4, 'episodes_per_system': 1, 'episode_samples': 40, 'history': 3,
        'loss_horizon': 3, 'hidden': [16], 'n_z': 3, 'batch_size': 2, 'inner_steps': 2,
        'cg_steps': 2, 'windows_per_task': 8, 'iterations': ITERATIONS, 'torch_threads': 1,
        'target_buffer_size': CAPACITY, 'heldout_fraction': 0.25, 'adapt_steps': 5,
        'oracle_episodes': 4, 'oracle_steps': 10, 'oracle_batch': 32,
        'progress_period': 0.25, 'buffer_on_start': False}
PLANT = {'theta': 1.0, 'x0': [1.0, 0.0], 'start_timeout': 0.2, 'input_timeout': 0.02}


def call(probe, client, request, timeout=30.0, resend_every=None):
    return probe.call(client, request, timeout, resend_every)


_IDS = itertools.count()


def buffering_call(probe, client, on: bool, least: int = 0):
    """set_buffering with an id of its own, resent while unanswered: a repeat is answered
    with the first answer (docs/nodes.md), so a lost answer costs nothing."""
    request = SetBuffering.Request(buffering=on, least=least, request_id=f'test-{next(_IDS)}')
    return probe.call(client, request, 30.0, resend_every=5.0)


class Latest:
    """A late-joining latched subscriber of nssm_weights."""

    def __init__(self, probe):
        self.msgs = []
        probe.node.create_subscription(NssmWeights, 'nssm_weights', self.msgs.append, LATCHED)


def check_weights_equal_checkpoint(msg, path):
    decoded = weights_from_fields(fields_of(msg))
    ckpt = load_checkpoint(path)
    assert ckpt.info['version'] == msg.version and ckpt.info['stage'] == msg.stage
    assert (decoded.config.n_z, decoded.config.history, decoded.config.hidden) == (
        ckpt.model.config.n_z, ckpt.model.config.history, ckpt.model.config.hidden)
    assert set(decoded.params) == set(ckpt.params)
    assert all(np.array_equal(decoded.params[k], ckpt.params[k].numpy()) for k in ckpt.params)
    for name in ('u_mean', 'u_std', 'y_mean', 'y_std'):
        assert np.array_equal(getattr(decoded.norm, name), getattr(ckpt.model.norm, name))
    return decoded


def stamp_s(msg) -> float:
    """A message's header stamp, s."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def test_learner_trains_while_buffering_and_publishes_latched_weights(procs, probe, tmp_path):
    progress = []
    probe.node.create_subscription(TrainingProgress, 'progress', progress.append, RELIABLE)
    meta = probe.node.create_client(MetaTrain, 'meta_train')
    adapt = probe.node.create_client(Adapt, 'adapt')
    buffering = probe.node.create_client(SetBuffering, 'set_buffering')
    ckpt = tmp_path / 'ckpt'
    learner = procs.start('metampc_learner', 'learner',
                          params={**TINY, 'checkpoint_dir': str(ckpt)})
    procs.start('metampc_plant', 'plant', params=PLANT)
    for client in (meta, adapt, buffering):
        assert client.wait_for_service(timeout_sec=60.0), client.srv_name

    # Requests that cannot be carried out say what is missing. They change nothing, so they
    # are resent while unanswered: the first answer of a service can be lost (SpunNode.call).
    result = call(probe, adapt, Adapt.Request(), resend_every=5.0)
    assert not result.success and 'no meta-model yet' in result.message, result.message
    result = call(probe, adapt, Adapt.Request(method='supervised'))
    assert not result.success, result.message
    assert result.message.startswith('adapt failed: too few target samples: 0 buffered')
    result = call(probe, adapt, Adapt.Request(method='reptile'))
    assert not result.success and "unknown method 'reptile'" in result.message
    result = call(probe, meta, MetaTrain.Request(method='supervised'), resend_every=5.0)
    assert not result.success and "call adapt with method 'supervised'" in result.message

    first = meta.call_async(MetaTrain.Request())
    probe.wait_for(first.done, 300.0, 'the meta_train answer')
    done = first.result()
    assert done.success, done.message
    assert done.model_version == 1 and len(done.loss_curve) == ITERATIONS
    assert all(math.isfinite(v) for v in done.loss_curve)
    assert done.final_loss == np.mean(done.loss_curve[-10:])
    probe.wait_for(lambda: progress and progress[-1].phase == 'done', 30.0, 'the final progress')
    job = [m for m in progress if m.phase in ('meta_train', 'done')]
    assert [m.phase for m in job].count('done') == 1 and job[-1].phase == 'done'
    assert job[0].iteration == 0 and job[-1].iteration == ITERATIONS
    assert all(m.total == ITERATIONS and m.method == 'imaml' for m in job)
    iterations = [m.iteration for m in job]
    assert iterations == sorted(iterations) and len(set(iterations)) > 3
    # The heartbeat goes on while the job trains: its rate by the learner's own stamps, within
    # a factor 2 of 1 / progress_period (a loaded machine delays single beats).
    beats = (stamp_s(job[-1]) - stamp_s(job[0])) / (len(job) - 1)
    assert len(job) > 4 and beats < 2 * TINY['progress_period'], (
        f'{len(job)} progress messages, one per {beats:.2f} s')
    assert job[-1].loss == done.loss_curve[-1]
    assert math.isfinite(job[-1].cg_residual)

    late = Latest(probe)
    probe.wait_for(lambda: late.msgs, 30.0, 'the latched meta-model')
    msg = late.msgs[-1]
    assert (msg.version, msg.stage, msg.method) == (1, 'meta', 'imaml')
    assert msg.train_steps == ITERATIONS and msg.train_loss == done.final_loss
    meta_weights = check_weights_equal_checkpoint(msg, ckpt / 'meta_imaml_v1.pt')

    # A job that cannot end by itself: what follows happens while it trains, by construction.
    endless = meta.call_async(MetaTrain.Request(iterations=100000, seed=5))
    probe.wait_for(lambda: progress[-1].phase == 'meta_train' and progress[-1].total == 100000,
                   60.0, 'the long job')
    # A second job is refused while it trains (the answers do not wait for it: it is still
    # running below), buffering is served and goes on.
    for client, request in ((meta, MetaTrain.Request()), (adapt, Adapt.Request())):
        result = call(probe, client, request)
        assert not result.success and result.message.startswith('busy: meta_train (imaml)')
    # Stopping a stopped buffer changes nothing: safe to resend while the first answer is out.
    buffering_call(probe, buffering, False)
    result = buffering_call(probe, buffering, True)
    assert result.success and (result.cleared, result.capacity) == (0, CAPACITY), result
    # The learner says when its y subscription has matched the plant (its side of DDS).
    probe.wait_for(lambda: buffering_call(probe, buffering, True).matched_publishers == 1, 60.0,
                   "the learner's y matched to the plant")
    probe.wait_for(lambda: 'D_target full: 40 samples' in procs.output(learner), 60.0,
                   'a full D_target')
    result = buffering_call(probe, buffering, False)
    # Nothing lost while the job trains: the step index never jumped ahead.
    assert (result.kept, result.skipped, result.lost, result.cleared) == (CAPACITY, 0, 0, 0)
    assert result.message == f'buffering stopped: {CAPACITY} samples kept (0 skipped, 0 lost)'
    assert not endless.done() and progress[-1].phase == 'meta_train'
    # Stopped, the learner is not subscribed to y at all; restarted, it subscribes again and
    # fills D_target anew.
    probe.wait_for(lambda: 'learner' not in {
        i.node_name for i in probe.node.get_subscriptions_info_by_topic('/y')}, 30.0,
        "the learner's y subscription gone")
    assert buffering_call(probe, buffering, False).matched_publishers == 0
    probe.wait_for(lambda: buffering_call(probe, buffering, True).matched_publishers == 1, 60.0,
                   "the learner's new y subscription matched to the plant")
    # A stop that asks for `least` samples is answered success false (buffering goes on, the
    # counts so far) until D_target holds them: the plant fills it at 10 Hz, ~4 s after the
    # restart, the first ask comes milliseconds after it.
    answers = []
    probe.wait_for(lambda: answers.append(buffering_call(probe, buffering, False,
                                                         least=CAPACITY)) or answers[-1].success,
                   60.0, 'a stop once D_target holds its capacity')
    assert len(answers) > 1 and all(not a.success and a.kept < CAPACITY for a in answers[:-1])
    assert answers[0].message.startswith('buffering goes on: ')
    assert (answers[-1].kept, answers[-1].lost) == (CAPACITY, 0), answers[-1]

    # Ctrl-C during the long job: the job is cancelled at its next step, the node exits 0.
    code = procs.interrupt(learner, timeout=60.0)
    out = procs.output(learner)
    assert code == 0 and 'Traceback' not in out and 'exception' not in out, out
    assert 'did not stop within' not in out, out
    assert session_pids(learner) == []
    assert sorted(os.listdir(ckpt)) == ['meta_imaml_v1.pt']

    # A new learner loads the saved meta-model and publishes it at start; versions go on.
    learner = procs.start('metampc_learner', 'learner', params={
        **TINY, 'checkpoint_dir': str(ckpt), 'meta_model_path': str(ckpt / 'meta_imaml_v1.pt')})
    fresh = Latest(probe)
    probe.wait_for(lambda: fresh.msgs, 60.0, 'the loaded meta-model')
    assert (fresh.msgs[-1].version, fresh.msgs[-1].stage) == (2, 'meta')
    loaded = check_weights_equal_checkpoint(fresh.msgs[-1], ckpt / 'meta_imaml_v2.pt')
    assert all(np.array_equal(loaded.params[k], meta_weights.params[k])
               for k in loaded.params)

    # Adaptation of the loaded meta-model to freshly buffered target samples.
    for client in (adapt, buffering):
        assert client.wait_for_service(timeout_sec=60.0), client.srv_name
    buffering_call(probe, buffering, False)
    result = buffering_call(probe, buffering, True)
    assert result.success, result.message
    probe.wait_for(lambda: 'D_target full: 40 samples' in procs.output(learner), 60.0,
                   'a full D_target')
    result = call(probe, adapt, Adapt.Request(), timeout=120.0)
    assert result.success, result.message
    assert result.model_version == 3 and len(result.loss_curve) == 6
    assert (result.loss_before, result.loss_after) == (result.loss_curve[0],
                                                       result.loss_curve[-1])
    probe.wait_for(lambda: fresh.msgs[-1].version == 3, 30.0, 'the adapted model')
    msg = fresh.msgs[-1]
    assert (msg.stage, msg.method, msg.train_steps) == ('adapted', 'imaml', 5)
    assert msg.train_samples == CAPACITY - 10, 'the first 30 buffered samples train'
    adapted = check_weights_equal_checkpoint(msg, ckpt / 'adapted_imaml_v3.pt')
    assert any(not np.array_equal(adapted.params[k], meta_weights.params[k])
               for k in adapted.params)

    # The oracle takes theta from the latched plant_info.
    result = call(probe, adapt, Adapt.Request(method='oracle'), timeout=120.0)
    assert result.success, result.message
    probe.wait_for(lambda: fresh.msgs[-1].version == 4, 30.0, 'the oracle model')
    assert (fresh.msgs[-1].method, fresh.msgs[-1].stage) == ('oracle', 'adapted')
    assert sorted(os.listdir(ckpt)) == [
        'adapted_imaml_v3.pt', 'adapted_oracle_v4.pt', 'meta_imaml_v1.pt', 'meta_imaml_v2.pt']


def y_subscribers(probe) -> set:
    return {i.node_name for i in probe.node.get_subscriptions_info_by_topic('/y')}


def test_a_full_d_target_takes_no_more_samples(procs, probe):
    """Once D_target is full the learner leaves y (before: it stayed subscribed and took every
    sample only to drop it, most of a core beside a free-running lockstep loop); buffering
    restarted, it subscribes again."""
    buffering = probe.node.create_client(SetBuffering, 'set_buffering')
    learner = procs.start('metampc_learner', 'learner', params={**TINY, 'buffer_on_start': True})
    # The plant starts only once the subscription is seen: 40 samples at 20 ms fill D_target in
    # under a second, so a plant started at once could fill it (and the learner leave y) before
    # the probe's graph showed the subscription (CI stop 39).
    probe.wait_for(lambda: 'learner' in y_subscribers(probe), 60.0, "the learner's y")
    procs.start('metampc_plant', 'plant', params=PLANT)
    probe.wait_for(lambda: 'D_target full: 40 samples' in procs.output(learner), 120.0,
                   'a full D_target')
    assert 'y unsubscribed until buffering restarts' in procs.output(learner)
    probe.wait_for(lambda: 'learner' not in y_subscribers(probe), 30.0,
                   "the learner's y subscription gone")
    assert buffering_call(probe, buffering, True).cleared == CAPACITY
    probe.wait_for(lambda: 'learner' in y_subscribers(probe), 30.0, "the learner's y again")
    assert procs.interrupt(learner, timeout=60.0) == 0


def test_a_request_it_cannot_serve_is_refused_on_adapt_refusals(procs, probe):
    """A loop adaptation request whose sample never arrives (no plant here) gets a typed
    refusal naming its step, so the controller gives it up at once instead of holding the
    loop for its adapt_timeout."""
    refusals = []
    probe.node.create_subscription(AdaptRefusal, 'adapt_refusals', refusals.append, RELIABLE)
    status = probe.node.create_publisher(MpcStatus, 'mpc_status', RELIABLE)
    learner = procs.start('metampc_learner', 'learner',
                          params={**TINY, 'loop_adaptation': True})
    probe.wait_for(lambda: status.get_subscription_count() > 0, 60.0, "the learner's status")
    status.publish(MpcStatus(step=7, model_version=1, adapt_request=True,
                             adapt_trigger='periodic'))
    probe.wait_for(lambda: refusals, 60.0, 'a refusal')
    assert refusals[0].request_step == 7
    assert refusals[0].reason.startswith('adaptation request of step 7'), refusals[0].reason
    assert procs.interrupt(learner, timeout=60.0) == 0


BAD_PARAMS = {
    'iterations': ({'iterations': 0}, 'iterations must be >= 1'),
    'method': ({'method': 'reptile'}, 'method must be one of'),
    'buffer': ({'target_buffer_size': 20}, 'target_buffer_size: its training / held-out'),
    'path': ({'meta_model_path': '/nonexistent/meta.pt'}, 'meta_model_path: cannot load'),
}


def test_bad_parameters_one_line_and_exit_2(procs):
    started = {case: procs.start('metampc_learner', 'learner', params=params)
               for case, (params, _) in BAD_PARAMS.items()}
    for case, proc in started.items():
        code = proc.wait(60.0)
        lines = own_lines(procs.output(proc))
        assert code == 2, (case, lines)
        assert len(lines) == 1 and 'invalid parameter' in lines[0], (case, lines)
        assert BAD_PARAMS[case][1] in lines[0], (case, lines)


def test_an_unreadable_meta_model_is_one_line_and_exit_2(procs, tmp_path):
    """A text file, an empty file and a torch file of something else: one error line naming
    the file, exit status 2, no traceback (before: ~30 lines, exit 1)."""
    empty, listing = tmp_path / 'empty.pt', tmp_path / 'list.pt'
    empty.write_bytes(b'')
    torch.save([1, 2, 3], listing)
    readme = os.path.join(os.path.dirname(__file__), '..', '..', '..', 'README.md')
    files = {'readme': (os.path.abspath(readme), 'not a torch checkpoint'),
             'empty': (str(empty), 'not a torch checkpoint'),
             'list': (str(listing), 'not a metampc.nssm/1 checkpoint')}
    started = {case: procs.start('metampc_learner', 'learner', name=f'learner_{case}',
                                 params={'meta_model_path': path})
               for case, (path, _) in files.items()}
    for case, proc in started.items():
        code = proc.wait(60.0)
        lines = own_lines(procs.output(proc))
        assert code == 2 and len(lines) == 1, (case, lines)
        assert 'invalid parameter: meta_model_path: cannot load meta-model' in lines[0]
        assert files[case][0] in lines[0] and files[case][1] in lines[0], (case, lines)
