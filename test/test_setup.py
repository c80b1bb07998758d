"""The set-up left a usable venv: no wheel-builder paths, idempotent, ros2 on PATH."""
import os
import pathlib
import shutil
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
VENV = ROOT / '.venv'
WHEELS = (VENV / 'share' / 'rclpy').is_dir()


@pytest.mark.skipif(not WHEELS, reason='ROS from apt: the venv holds no ROS wheels to fix up')
def test_no_wheel_builder_paths_in_cmake_files():
    offenders = [str(p) for p in (VENV / 'share').rglob('*.cmake')
                 if '/opt/python/cp3' in p.read_text(errors='replace')]
    assert offenders == []


def test_second_setup_is_a_no_op():
    r = subprocess.run(['bash', str(ROOT / 'scripts' / 'setup.sh')], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert 'is up to date' in r.stdout


def test_ros2_on_path_lists_our_packages():
    ros2 = shutil.which('ros2')
    assert ros2 is not None
    out = subprocess.run([ros2, 'pkg', 'executables'], capture_output=True, text=True,
                         timeout=30, env=os.environ).stdout.splitlines()
    for line in ('metampc_plant plant', 'metampc_controller controller',
                 'metampc_learner learner', 'metampc_recording recorder'):
        assert line in out
