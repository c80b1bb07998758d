"""The cluster's command-line arguments, one helper for every command with --jobs
(metampc_bringup.orchestration.cluster_cli): the embedded cluster within the cpu budget, a
scheduler address checked before any connection, --jobs not with --scheduler, the --tls-*
files together; and the four commands take the same arguments from it."""
import argparse
import importlib.util
from pathlib import Path

import pytest

from metampc_bringup.orchestration import cluster_cli
from metampc_bringup.orchestration.cluster import ClusterSpec, TlsFiles
from metampc_bringup.orchestration.cpu_budget import usable_cores

ROOT = Path(__file__).resolve().parents[3]


def _spec(argv, jobs_default=2, threads=1):
    parser = argparse.ArgumentParser()
    cluster_cli.add_arguments(parser, 'jobs at once')
    return cluster_cli.cluster_spec(parser.parse_args(argv), jobs_default, threads)


def test_the_embedded_cluster_and_a_scheduler():
    assert _spec([], jobs_default=1) == ClusterSpec(1)
    assert _spec(['--jobs', '1'], threads=usable_cores() + 1) == ClusterSpec(1)
    assert _spec(['--scheduler', 'tcp://127.0.0.1:8786']) == ClusterSpec(
        1, 'tcp://127.0.0.1:8786')
    assert _spec(['--scheduler', 'tcp://10.0.0.5:8786', '--insecure', '--jobs', '1']) == \
        ClusterSpec(1, 'tcp://10.0.0.5:8786', True)
    tls = ['--tls-ca-file', 'ca.pem', '--tls-cert', 'c.pem', '--tls-key', 'c.key']
    assert _spec(['--scheduler', 'tls://head:8786', *tls]) == ClusterSpec(
        1, 'tls://head:8786', False, TlsFiles('ca.pem', 'c.pem', 'c.key'))


@pytest.mark.parametrize('argv, message', [
    (['--jobs', '0'], '--jobs must be >= 1'),
    (['--jobs', str(usable_cores() + 1)], 'exceeds the'),
    (['--scheduler', 'tcp://127.0.0.1:8786', '--jobs', '2'], 'not with --scheduler'),
    (['--scheduler', 'tcp://10.0.0.5:8786'], 'refused without --insecure'),
    (['--scheduler', 'tls://head:8786'], 'tls:// needs --tls-ca-file'),
    (['--scheduler', 'tls://head:8786', '--tls-ca-file', 'ca.pem'], 'go together'),
    (['--scheduler', 'tcp://127.0.0.1:8786', '--tls-ca-file', 'a', '--tls-cert', 'b',
      '--tls-key', 'c'], 'for a tls:// scheduler')])
def test_refused_before_any_connection(argv, message):
    with pytest.raises(ValueError, match=message):
        _spec(argv)


@pytest.mark.parametrize('script', ['run_experiment', 'robustness', 'sweep_inner_steps', 'tune'])
def test_every_command_with_jobs_takes_the_clusters_arguments_from_the_helper(
        script, monkeypatch):
    spec = importlib.util.spec_from_file_location(script, ROOT / 'scripts' / f'{script}.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    added = []

    def spy(parser, jobs_help):
        added.append(jobs_help)
        raise SystemExit(0)     # the arguments are in: stop before anything runs

    monkeypatch.setattr(module, 'add_arguments', spy)
    with pytest.raises(SystemExit):
        module.main(['--out', 'unused'])
    assert len(added) == 1
