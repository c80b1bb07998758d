"""A run folder belongs to one configuration (metampc_bringup.run_folder): created, resumed
with only its unfinished seeds (their tries kept aside), or refused with nothing changed."""
import os

import pytest

from metampc_bringup.run_folder import (config_text, done_seeds, incomplete, mark_incomplete,
                                        prepare)

CONFIG = {'family': 'vanderpol', 'seeds': 3, 'first_seed': 0, 'methods': ['maml']}


def _files(folder):
    """Every file under `folder` with its bytes and modification time."""
    found = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            with open(path, 'rb') as f:
                found[path] = (f.read(), os.stat(path).st_mtime_ns)
    return found


def test_a_new_folder_gets_its_config_and_every_seed(tmp_path):
    out = str(tmp_path / 'run')
    assert prepare(out, CONFIG, [0, 1, 2]) == [0, 1, 2]
    with open(os.path.join(out, 'config.yaml')) as f:
        assert f.read() == config_text(CONFIG)
    (tmp_path / 'empty').mkdir()
    assert prepare(str(tmp_path / 'empty'), CONFIG, [0]) == [0]


def test_a_resumed_folder_runs_only_the_seeds_without_a_report(tmp_path):
    out = tmp_path / 'run'
    prepare(str(out), CONFIG, [0, 1, 2])
    for seed in (0, 2):
        (out / f'seed_{seed}').mkdir()
        (out / f'seed_{seed}' / 'recording.mcap').write_bytes(b'complete')
    (out / 'seed_0' / 'report.json').write_text('{}')
    kept = _files(out / 'seed_0')
    mark_incomplete(str(out / 'seed_2'), 'interrupted')
    assert incomplete(str(out / 'seed_2')) and not incomplete(str(out / 'seed_0'))
    assert (out / 'seed_2' / 'INCOMPLETE').read_text() == \
        'interrupted; no report: the same command runs this seed again\n'
    unfinished = _files(out / 'seed_2')
    assert done_seeds(str(out), CONFIG, [0, 1, 2]) == [0]
    assert prepare(str(out), CONFIG, [0, 1, 2]) == [1, 2]
    assert not (out / 'seed_2').exists(), 'the seed runs again in a new folder'
    assert _files(out / 'seed_0') == kept
    assert [(p.replace('incomplete/seed_2.1', 'seed_2'), v[0]) for p, v in
            _files(out / 'incomplete' / 'seed_2.1').items()] == \
        [(p, v[0]) for p, v in unfinished.items()], 'the unfinished try is kept'
    (out / 'seed_2').mkdir()        # a second try, unfinished too
    assert prepare(str(out), CONFIG, [0, 1, 2]) == [1, 2]
    assert sorted(os.listdir(out / 'incomplete')) == ['seed_2.1', 'seed_2.2']
    mark_incomplete(str(out / 'seed_1'), 'never made')
    assert not (out / 'seed_1').exists()


def test_a_folder_of_another_run_is_refused_with_nothing_changed(tmp_path):
    out = tmp_path / 'run'
    prepare(str(out), CONFIG, [0, 1, 2])
    (out / 'seed_1').mkdir()
    (out / 'seed_1' / 'recording.mcap').write_bytes(b'partial')
    before = _files(out)
    with pytest.raises(FileExistsError, match='another configuration'):
        prepare(str(out), {**CONFIG, 'seeds': 4}, [0, 1, 2, 3])
    assert _files(out) == before
    (tmp_path / 'other').mkdir()
    (tmp_path / 'other' / 'notes.txt').write_text('mine')
    with pytest.raises(FileExistsError, match='not a run folder'):
        prepare(str(tmp_path / 'other'), CONFIG, [0])
    (tmp_path / 'file').write_text('x')
    with pytest.raises(FileExistsError, match='not a folder'):
        prepare(str(tmp_path / 'file'), CONFIG, [0])
