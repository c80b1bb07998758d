"""The experiment events (metampc_bringup.experiment_events): each event's text is the one the
orchestrator has always written (plus the fields added since, at the values older recordings
read as), so recordings made before read back to the same events."""
import json
import math
import time

import pytest

from metampc_bringup import experiment_events as events
from metampc_bringup.experiment_events import decode, from_record, read_events

# Event texts of a recording made before the events were typed (consist-runs/c0b, seed 100:
# the loss curves cut to three values), one of each kind but collect_start.
RECORDED = [
    '{"event": "start", "wall_time": 1795801880.5543964, "seed": 100, "theta": '
    '[0.44381551182689793], "methods": ["imaml", "maml", "nmpc"], "nodes": ["controller", '
    '"controller_nmpc", "learner", "plant", "recorder"]}',
    '{"event": "collect_end", "wall_time": 1795801881.1780787, "stamp": 30.1, "samples": 300, '
    '"escapes": 0}',
    '{"event": "track_start", "wall_time": 1795801881.4460382, "method": "nmpc", "run": "nmpc", '
    '"controller": "controller_nmpc", "model_version": 0, "stamp": 30.2, "steps": 300, '
    '"theta_schedule": []}',
    '{"event": "track_end", "wall_time": 1795801925.9448903, "method": "nmpc", "run": "nmpc", '
    '"stamp": 60.2, "steps": 300, "diverged": false}',
    '{"event": "meta_train", "wall_time": 1795801961.0599356, "method": "maml", "request": '
    '{"iterations": 300, "batch_size": 16, "inner_steps": 5, "lr_inner": 0.02, "lr_outer": '
    '0.01}, "model_version": 2, "final_loss": 0.011051361961290241, "loss_curve": '
    '[0.4490690231323242, 0.3534294068813324, 0.3830145597457886], "message": "maml '
    'meta-model v2: 300 outer steps (B=16, M=5, seed 100) in 11.8 s, final meta-test loss '
    '0.01105, 0 tasks skipped"}',
    '{"event": "buffering_stopped", "wall_time": 1795801961.063402, "kept": 300, "skipped": 1, '
    '"lost": 0}',
    '{"event": "adapt", "wall_time": 1795801961.3537986, "method": "imaml", "request": '
    '{"steps": 20, "lr": 1.0}, "model_version": 3, "loss_before": 0.01184881292283535, '
    '"loss_after": 0.00985143706202507, "loss_curve": [0.01184881292283535, '
    '0.01112437155097723, 0.00985143706202507], "message": "imaml model v3 (stage adapted): '
    '20 steps on 240 buffered target samples in 0.2 s, held-out loss 0.01185 -> 0.009851 on '
    '60 samples"}',
    '{"event": "done", "wall_time": 1795801964.4402826, "timings": {"startup": '
    '10.017805671002861, "collect": 0.6234831180008769}, "episode_restarts": 0}',
]


# Fields added to an event since that recording, with the value an older recording reads as:
# written after the recorded ones.
ADDED = {'adapt': ', "fallback": ""'}


def _today(text: str) -> str:
    """A recorded event's text as the orchestrator writes it today."""
    return text[:-1] + ADDED.get(json.loads(text)['event'], '') + '}'


@pytest.mark.parametrize('text', RECORDED, ids=[json.loads(t)['event'] for t in RECORDED])
def test_a_recorded_event_reads_back_to_the_same_text(text):
    event = decode(text)
    assert event.KIND == json.loads(text)['event']
    assert event.encode() == _today(text)
    assert decode(event.encode()) == event


def test_every_kind_is_typed_and_written_in_the_orchestrators_order():
    # The JSON the orchestrator wrote before the dataclasses: {'event', 'wall_time', then its
    # keyword arguments in call order}, NaN and inf as json writes them.
    written = [
        (events.CollectStart(wall_time=1.5, stamp=0.1, theta=[0.5, 0.6]),
         {'event': 'collect_start', 'wall_time': 1.5, 'stamp': 0.1, 'theta': [0.5, 0.6]}),
        (events.MetaTrained(wall_time=2.0, method='imaml', request={'iterations': 3},
                            model_version=1, final_loss=math.nan, loss_curve=[1.0, math.inf],
                            message='diverged'),
         {'event': 'meta_train', 'wall_time': 2.0, 'method': 'imaml',
          'request': {'iterations': 3}, 'model_version': 1, 'final_loss': math.nan,
          'loss_curve': [1.0, math.inf], 'message': 'diverged'}),
        (events.TrackStart(wall_time=3.0, method='imaml', run='imaml/triggered',
                           controller='controller', model_version=3, stamp=60.3, steps=300,
                           theta_schedule=[10.0, 0.1]),
         {'event': 'track_start', 'wall_time': 3.0, 'method': 'imaml',
          'run': 'imaml/triggered', 'controller': 'controller', 'model_version': 3,
          'stamp': 60.3, 'steps': 300, 'theta_schedule': [10.0, 0.1]}),
    ]
    for event, record in written:
        assert event.encode() == json.dumps(record, allow_nan=True)
        back = decode(event.encode())
        assert type(back) is type(event) and back.encode() == event.encode()
    assert set(events.KINDS) == {'start', 'collect_start', 'collect_end', 'buffering_stopped',
                                 'meta_train', 'adapt', 'track_start', 'track_end', 'done'}


def test_an_event_is_stamped_with_the_wall_time_it_was_made_at():
    before = time.time()
    event = events.BufferingStopped(kept=300, skipped=1, lost=0)
    assert before <= event.wall_time <= time.time()


def test_track_events_of_recordings_before_drift_runs_read_as_the_methods_run():
    start = from_record({'event': 'track_start', 'wall_time': 1.0, 'method': 'maml',
                         'controller': 'controller', 'model_version': 4, 'stamp': 90.4,
                         'steps': 300})
    end = from_record({'event': 'track_end', 'wall_time': 2.0, 'method': 'maml',
                       'stamp': 120.4, 'steps': 300, 'diverged': False})
    assert (start.run_name, end.run_name, start.theta_schedule) == ('maml', 'maml', [])
    assert decode(RECORDED[2]).run_name == 'nmpc'


@pytest.mark.parametrize('record, says', [
    ({'event': 'restart', 'wall_time': 1.0}, "unknown experiment event 'restart'"),
    ({'event': 'collect_end', 'wall_time': 1.0, 'stamp': 1.0, 'samples': 3},
     "experiment event 'collect_end'.*escapes"),
    ({'event': 'done', 'wall_time': 1.0, 'timings': {}, 'episode_restarts': 0, 'extra': 1},
     "experiment event 'done'.*extra"),
    ({'event': 'buffering_stopped', 'kept': 3, 'skipped': 0, 'lost': 0},
     "experiment event 'buffering_stopped' without wall_time"),
])
def test_an_event_that_does_not_fit_is_one_clear_error(record, says):
    with pytest.raises(ValueError, match=says):
        from_record(record)


def test_read_events_reads_the_events_topic_of_a_recording(tmp_path):
    from mcap_ros2._dynamic import serialize_dynamic
    from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
    from metampc_recording.msg_schema import DefinitionSource
    from metampc_recording.recording_reader import read_recording
    from metampc_recording.rosbag2_qos import QosProfile
    path = str(tmp_path / 'events.mcap')
    writer = Rosbag2McapWriter(McapWriterConfig(path, 4096, 'lz4', {}))
    name = 'std_msgs/msg/String'
    qos = [QosProfile(history='unknown', depth=0, liveliness='automatic')]
    encode = serialize_dynamic(name, DefinitionSource().get(name).text)[name]
    for topic in ('/experiment_events', '/chatter'):
        writer.add_topic(topic, name, qos)
    for i, text in enumerate(RECORDED):
        writer.write('/experiment_events', encode({'data': text}), 10 + 2 * i, 10 + 2 * i, i)
        writer.write('/chatter', encode({'data': '{"event": "start"}'}), 11 + 2 * i,
                     11 + 2 * i, i)
    writer.close()
    assert [e.encode() for e in read_events(read_recording(path))] == [_today(t) for t in RECORDED]
