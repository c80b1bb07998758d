"""Recorder parameters: defaults, the round trip of to_parameters, one clear error per value."""
from metampc_recording.recorder_config import parse_params, PARAMETERS, RecorderConfig
from metampc_common.params import ParameterError
import pytest


def values(**overrides):
    """Parameter values as the node reads them: the declared defaults, then `overrides`."""
    raw = {name: spec.default for name, spec in PARAMETERS.items()}
    raw.update(overrides)
    return raw


def test_defaults_match_the_config_and_round_trip():
    assert parse_params(values(output='r.mcap')) == RecorderConfig(output='r.mcap')
    config = RecorderConfig(output='runs/a/recording.mcap', topics=['y', '/u'],
                            record_clock=True, chunk_size=4096, compression='zstd',
                            metadata_json='{"seed": 3}', discovery_period=0.5,
                            flush_period=0.0, qos_depth=10)
    assert parse_params(values(**config.to_parameters())) == config
    assert 'topics' not in RecorderConfig(output='x').to_parameters()
    assert parse_params(values(output='x', topics=b'')).topics == ()   # as rclpy declares []
    assert config.writer_config().run_config == {'seed': 3}


@pytest.mark.parametrize('overrides,message', [
    ({}, 'output'),
    ({'compression': 'gzip'}, 'compression'),
    ({'metadata_json': '{"seed": '}, 'not JSON'),
    ({'metadata_json': '[1, 2]'}, 'JSON object'),
    ({'chunk_size': 0}, 'chunk_size'),
    ({'chunk_size': 1.5}, 'chunk_size'),
    ({'qos_depth': -1}, 'qos_depth'),
    ({'discovery_period': 0.0}, 'discovery_period'),
    ({'flush_period': -1.0}, 'flush_period'),
    ({'record_clock': 'yes'}, 'record_clock'),
    ({'topics': ['y', '']}, 'topics'),
    ({'topics': [b'y']}, 'topics'),
])
def test_bad_values_name_the_parameter(overrides, message):
    raw = values(**{'output': 'r.mcap', **overrides}) if overrides else values()
    with pytest.raises(ParameterError, match=message):
        parse_params(raw)
