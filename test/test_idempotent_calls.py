"""The orchestrator's calls that change state are safe to repeat: with the first response
dropped by construction, the call is answered once and run once (metampc_common.replies,
ExperimentClient's Call).

The first send's future is removed from the client's pending requests as soon as it is sent:
its response arrives and is discarded, as rmw_fastrtps discards one whose writer has not
matched the client within 100 ms. The request itself ran. The client must send again, with
the same id, and the server must answer from the first run, not run it twice: the next call's
count (model version, reset number) shows how many runs there were.
"""
from metampc_bringup.orchestration.experiment_client import ExperimentClient
from metampc_msgs.srv import MetaTrain, ResetPlant
import pytest

TINY = {'n_systems': 4, 'episodes_per_system': 1, 'episode_samples': 40, 'history': 3,
        'loss_horizon': 3, 'hidden': [16], 'n_z': 3, 'batch_size': 2, 'inner_steps': 2,
        'cg_steps': 2, 'windows_per_task': 8, 'iterations': 200, 'torch_threads': 1,
        'buffer_on_start': False}
PLANT = {'theta': 1.0, 'x0': [1.0, 0.0], 'start_timeout': 0.2, 'input_timeout': 0.02}


@pytest.fixture
def client():
    client = ExperimentClient({}, lambda: None)
    yield client
    client.close()


def drop_first_response(rclpy_client) -> list:
    """Make the next call_async of `rclpy_client` lose its response; the sends are listed."""
    real = rclpy_client.call_async
    sends = []

    def call_async(request):
        future = real(request)
        sends.append(request.request_id)
        if len(sends) == 1:
            rclpy_client.remove_pending_request(future)     # its answer is discarded
        return future
    rclpy_client.call_async = call_async
    return sends


def test_a_reset_whose_answer_was_lost_is_answered_once_and_run_once(procs, client):
    procs.start('metampc_plant', 'plant', params=PLANT)
    assert client.clients['reset'].wait_for_service(timeout_sec=60.0)
    sends = drop_first_response(client.clients['reset'])
    answer = client.call('reset', ResetPlant.Request(theta=[0.7]), 60.0, 'reset')
    assert answer.message.startswith('reset 1:'), answer.message
    assert len(sends) >= 2 and len(set(sends)) == 1 and sends[0]     # resent, same id
    answer = client.call('reset', ResetPlant.Request(theta=[0.8]), 60.0, 'reset')
    assert answer.message.startswith('reset 2:'), answer.message     # the first ran once


def test_a_meta_training_whose_answer_was_lost_is_answered_once_and_run_once(procs, client):
    procs.start('metampc_learner', 'learner', params=TINY)
    assert client.clients['meta_train'].wait_for_service(timeout_sec=60.0)
    sends = drop_first_response(client.clients['meta_train'])
    answer = client.call('meta_train', MetaTrain.Request(method='maml'), 120.0, 'meta_train')
    assert answer.success and answer.model_version == 1, answer.message
    assert len(sends) >= 2 and len(set(sends)) == 1
    answer = client.call('meta_train', MetaTrain.Request(method='maml', iterations=5), 120.0,
                         'meta_train')
    assert answer.model_version == 2, answer.message    # the first trained once
