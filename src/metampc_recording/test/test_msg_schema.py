"""Complete message definitions: rosbag2's layout, and both independent decoders accept them."""
import os

from mcap_ros2._dynamic import generate_dynamic
from metampc_recording.msg_schema import (DefinitionNotFoundError, DefinitionSource, DELIMITER,
                                          package_share_directory)
import pytest
from rosbags.typesys import get_types_from_msg

METAMPC_TYPES = ['PlantOutput', 'PlantInfo', 'ControlInput', 'NssmWeights', 'MpcStatus',
                 'TrainingProgress', 'StepHold']


def _file(package, name, ext='msg'):
    with open(os.path.join(package_share_directory(package), 'msg', f'{name}.{ext}')) as f:
        return f.read()


def _block(type_name):
    package, name = type_name.split('/')
    return '\n' + DELIMITER + f'MSG: {type_name}\n' + _file(package, name)


def test_plant_output_is_its_file_then_dependencies_depth_first():
    text = DefinitionSource().get('metampc_msgs/msg/PlantOutput')
    assert text.encoding == 'ros2msg'
    expected = (_file('metampc_msgs', 'PlantOutput') + _block('std_msgs/Header')
                + _block('builtin_interfaces/Time'))
    assert text.text == expected


def test_dependencies_sorted_relative_names_qualified_each_once():
    # PoseStamped uses std_msgs/Header and Pose (same package, written without it); Pose uses
    # Point and Quaternion. rosbag2 visits a type's dependencies in sorted order, depth first.
    text = DefinitionSource().get('geometry_msgs/msg/PoseStamped').text
    expected = (_file('geometry_msgs', 'PoseStamped') + _block('geometry_msgs/Pose')
                + _block('geometry_msgs/Point') + _block('geometry_msgs/Quaternion')
                + _block('std_msgs/Header') + _block('builtin_interfaces/Time'))
    assert text == expected
    assert text.count('MSG: builtin_interfaces/Time') == 1


@pytest.mark.parametrize('name', METAMPC_TYPES)
def test_every_metampc_type_parses_with_mcap_ros2_and_rosbags(name):
    type_name = f'metampc_msgs/msg/{name}'
    text = DefinitionSource().get(type_name).text
    assert type_name in generate_dynamic(type_name, text)
    types = get_types_from_msg(text, type_name)
    assert {type_name, 'std_msgs/msg/Header', 'builtin_interfaces/msg/Time'} <= set(types)


def test_idl_fallback_and_missing_types(tmp_path):
    prefix = tmp_path / 'prefix'
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages').mkdir(parents=True)
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'idl_only').touch()
    (prefix / 'share' / 'idl_only' / 'msg').mkdir(parents=True)
    idl = 'module idl_only { module msg { struct Thing { double x; }; }; };\n'
    (prefix / 'share' / 'idl_only' / 'msg' / 'Thing.idl').write_text(idl)
    source = DefinitionSource([str(prefix)])
    definition = source.get('idl_only/msg/Thing')
    assert definition.encoding == 'ros2idl'
    assert definition.text == DELIMITER + 'IDL: idl_only/msg/Thing\n' + idl
    with pytest.raises(DefinitionNotFoundError):
        source.get('idl_only/msg/Missing')
    with pytest.raises(DefinitionNotFoundError):
        source.get('no_such_package/msg/Thing')
