"""scripts/retrack.py's batch (studies/retrack_batch): the jobs a run folder still needs, what a
job carries, and its results on an embedded cluster against the tracking run in this process.
The script end to end, on a real run's recording: test/test_experiment.py."""
import json
import os
from types import SimpleNamespace

import pytest

from metampc_bringup.analysis.retrack import track_models
from metampc_bringup.experiment_config import load
from metampc_bringup.orchestration.cluster import ClusterSpec, connect
from metampc_bringup.studies import retrack_batch as batch
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.weights_codec import fields_from_weights, model_from_fields

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')


def manual_fields(theta: float) -> dict:
    return fields_from_weights(*linearised_vdp_nssm(theta, 0.1))


@pytest.fixture
def recorded(monkeypatch):
    """Two seeds whose 'recordings' hold one hand-built model each (theta 0.2 and 0.4); the
    reads of each recording counted."""
    reads = []

    def adapted_models(recording):
        reads.append(recording)
        return {'manual': SimpleNamespace(**manual_fields(0.2 if recording == 'r0' else 0.4))}
    monkeypatch.setattr(batch, 'adapted_models', adapted_models)
    return {0: 'r0', 1: 'r1'}, reads


def test_the_paths_name_seed_and_variant_and_ignore_the_order_of_the_overrides(tmp_path):
    path = batch.result_path(str(tmp_path), 3, 'a', {'r': 0.1, 'horizon': 5})
    assert path == batch.result_path(str(tmp_path), 3, 'a', {'horizon': 5, 'r': 0.1})
    assert os.path.basename(path).startswith('seed_3_a_')
    assert path != batch.result_path(str(tmp_path), 3, 'a', {'horizon': 6, 'r': 0.1})


def test_only_missing_jobs_are_planned_and_they_carry_their_seed_s_models(recorded, tmp_path):
    recordings, reads = recorded
    variants = [('a', {}), ('b', {'r': 0.2})]
    jobs = batch.missing_jobs(recordings, variants, {}, str(tmp_path))
    assert [str(j) for j in jobs] == ['seed_0_nmpc', 'seed_0_a', 'seed_0_b', 'seed_1_nmpc',
                                      'seed_1_a', 'seed_1_b']
    assert reads == ['r0', 'r1']                          # each recording read once
    assert jobs[0].models == {} and jobs[2].overrides == {'r': 0.2}
    assert list(jobs[4].models['manual']['params']) == list(manual_fields(0.4)['params'])
    for job in jobs[:2] + jobs[5:]:                       # those of them done
        with open(job.path, 'w') as f:
            json.dump({}, f)
    left = batch.missing_jobs(recordings, variants, {}, str(tmp_path))
    assert [str(j) for j in left] == ['seed_0_b', 'seed_1_nmpc', 'seed_1_a']


def test_a_batch_on_the_cluster_gives_the_tracking_of_this_process(recorded, tmp_path):
    """The jobs' results, through pickling to a worker and the result files, against
    track_models here on the same models (fails where a job drops its overrides or flies
    another seed's model)."""
    recordings, _ = recorded
    experiment = load(CI_CONFIG)
    variants = [('short', {'horizon': 5})]
    jobs = [j for j in batch.missing_jobs(recordings, variants, {}, str(tmp_path))
            if j.name != batch.NMPC]
    with connect(ClusterSpec(jobs=1)) as client:
        assert batch.run(client, experiment, jobs, progress=False) == []
    for seed, theta in ((0, 0.2), (1, 0.4)):
        here = track_models(experiment, seed, {'horizon': 5},
                            {'manual': model_from_fields(manual_fields(theta))})
        with open(batch.result_path(str(tmp_path), seed, 'short', {'horizon': 5})) as f:
            there = json.load(f)
        assert there['manual']['cost'] == here['manual'].cost
        assert there['manual']['escaped'] == here['manual'].escaped
    other = track_models(experiment, 1, {}, {'manual': model_from_fields(manual_fields(0.4))})
    assert other['manual'].cost != here['manual'].cost    # the overrides matter here


def test_the_table_prints_every_variant_and_method(tmp_path):
    summary = {'a': {'imaml': {'median': 1.5, 'worst': 2.0, 'escapes': 0, 'mean_offset': 0.01,
                               'ratios': {'0': 1.0, '1': 2.0}}}}
    lines = batch.table(summary, 'a')
    assert len(lines) == 2 and lines[1].split()[:6] == ['a', 'imaml', '1.500', '2.000', '0',
                                                        '0.0100']
    assert lines[1].endswith('1.00 2.00')
