"""The soak's set-up without running it (scripts/soak.py runs it): defaults, checks, the
model and the node's pid."""
import os
import signal
import subprocess

import pytest

from metampc_bringup.soak.realtime_soak import model_message, node_pid, SoakConfig


def test_defaults_follow_the_plant_rate():
    cfg = SoakConfig(rate=50.0)
    assert (cfg.controller_rate, cfg.dt) == (100.0, 0.02)
    cfg = SoakConfig(rate=50.0, controller_rate=50.0, dt=0.1)
    assert (cfg.controller_rate, cfg.dt) == (50.0, 0.1)
    cfg.validate()


@pytest.mark.parametrize('bad', [dict(duration=0.0), dict(warmup=-1.0), dict(dt=-0.01),
                                 dict(controller_rate=-5.0), dict(rate=0.0)])
def test_validate_names_the_ranges(bad):
    with pytest.raises(ValueError, match='must be > 0, warmup >= 0'):
        SoakConfig(**bad).validate()


def test_the_default_model_is_the_hand_built_one_at_the_plant_dt():
    msg = model_message(SoakConfig(rate=20.0, theta=0.3))
    assert (msg.version, msg.method, msg.stage, msg.n_z) == (1, 'manual', 'adapted', 2)


def test_node_pid_is_the_other_process_of_the_session():
    # a shell that starts a child, as `ros2 run` starts the node
    proc = subprocess.Popen(['bash', '-c', 'sleep 30 & echo $!; wait'], stdout=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        child = int(proc.stdout.readline())
        assert node_pid(proc) == child
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()


def test_adaptation_needs_a_meta_model_and_a_known_mode():
    with pytest.raises(ValueError, match='needs a learner'):
        SoakConfig(adaptation='periodic').validate()
    with pytest.raises(ValueError, match='adaptation must be one of'):
        SoakConfig(adaptation='always', weights='meta.pt').validate()
    # With a learner, the learner publishes the model: the soak sends none.
    assert model_message(SoakConfig(adaptation='triggered', weights='meta.pt')) is None


def test_a_recorded_model_written_as_a_checkpoint_loads_as_the_same_weights(tmp_path):
    from metampc_bringup.soak.weights_messages import (checkpoint_weights, manual_weights,
                                                       save_weights)
    msg = manual_weights(0.5, 0.1, version=3)
    msg.method, msg.stage = 'imaml', 'meta'
    save_weights(msg, str(tmp_path / 'meta.pt'))
    back = checkpoint_weights(str(tmp_path / 'meta.pt'), version=3)
    assert (back.method, back.stage) == ('imaml', 'meta')
    assert list(back.params) == list(msg.params) and list(back.names) == list(msg.names)
    assert list(back.y_std) == list(msg.y_std)
