"""metampc_common.renames: an old key or value still works for one release, with one warning
naming the new one; the old and the new key together is an error."""
import pytest

from metampc_common.renames import renamed_key, renamed_value


def test_an_old_key_is_renamed_in_place_with_one_warning(capsys):
    values = {'a': 1, 'old_k1': 2, 'z': 3}
    for _ in range(2):
        assert list(renamed_key(values, 'old_k1', 'new_k1', 'cfg: ').items()) == [
            ('a', 1), ('new_k1', 2), ('z', 3)]
    assert capsys.readouterr().err == (
        'warning: cfg: old_k1 is renamed new_k1; the old name will be removed in the next '
        'release\n')


def test_without_the_old_key_nothing_changes_and_nothing_is_written(capsys):
    assert renamed_key({'new_k2': 1}, 'old_k2', 'new_k2') == {'new_k2': 1}
    assert capsys.readouterr().err == ''


def test_both_keys_given_is_an_error_naming_both():
    with pytest.raises(ValueError, match='old_k3 and new_k3 are both given'):
        renamed_key({'old_k3': 1, 'new_k3': 2}, 'old_k3', 'new_k3')


def test_an_old_value_becomes_the_new_one_and_others_pass(capsys):
    renames = {'old_v': 'new_v'}
    assert renamed_value('old_v', renames, 'kind') == 'new_v'
    assert renamed_value('new_v', renames, 'kind') == 'new_v'
    assert renamed_value(3, renames, 'kind') == 3
    assert capsys.readouterr().err == (
        "warning: kind: 'old_v' is renamed 'new_v'; the old value will be removed in the next "
        'release\n')
