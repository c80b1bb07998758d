"""Type names and the generated classes they name."""
from metampc_common.message_types import message_class, split_type_name
import pytest
from sensor_msgs.msg import JointState


def test_type_names_split_with_and_without_the_namespace():
    assert split_type_name('sensor_msgs/msg/JointState') == ('sensor_msgs', 'msg', 'JointState')
    assert split_type_name('sensor_msgs/JointState') == ('sensor_msgs', 'msg', 'JointState')
    assert split_type_name('std_srvs/srv/Trigger') == ('std_srvs', 'srv', 'Trigger')
    for bad in ('JointState', 'a/b/c/d', 'sensor_msgs/msg/', '1pkg/msg/T'):
        with pytest.raises(ValueError, match='invalid type name'):
            split_type_name(bad)


def test_message_class_imports_the_generated_class_or_says_it_is_not_installed():
    assert message_class('sensor_msgs/msg/JointState') is JointState
    with pytest.raises(ImportError):
        message_class('no_such_msgs/msg/Thing')
    with pytest.raises(AttributeError):
        message_class('sensor_msgs/msg/NoSuchType')
