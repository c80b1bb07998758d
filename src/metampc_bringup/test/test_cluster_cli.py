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


def _pem_files(folder):
    """Three PEM-looking files (what cluster_spec checks; no TLS handshake here)."""
    paths = [str(folder / name) for name in ('ca.pem', 'c.pem', 'c.key')]
    for path in paths:
        with open(path, 'w') as f:
            f.write('-----BEGIN CERTIFICATE-----\nAA==\n-----END CERTIFICATE-----\n')
    return paths


def test_the_embedded_cluster_and_a_scheduler(tmp_path):
    assert _spec([], jobs_default=1) == ClusterSpec(1)
    assert _spec(['--jobs', '1'], threads=usable_cores() + 1) == ClusterSpec(1)
    assert _spec(['--scheduler', 'tcp://127.0.0.1:8786']) == ClusterSpec(
        1, 'tcp://127.0.0.1:8786')
    assert _spec(['--scheduler', 'tcp://10.0.0.5:8786', '--insecure', '--jobs', '1']) == \
        ClusterSpec(1, 'tcp://10.0.0.5:8786', True)
    files = _pem_files(tmp_path)
    tls = ['--tls-ca-file', files[0], '--tls-cert', files[1], '--tls-key', files[2]]
    assert _spec(['--scheduler', 'tls://head:8786', *tls]) == ClusterSpec(
        1, 'tls://head:8786', False, TlsFiles(*files))
    assert _spec(['--scheduler', 'tcp://[::1]:8786']) == ClusterSpec(1, 'tcp://[::1]:8786')


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


@pytest.mark.parametrize('argv, message', [
    (['--scheduler', 'tcp://127.0.0.1'], 'expected tcp://HOST:PORT or tls://HOST:PORT'),
    (['--scheduler', 'tcp://127.0.0.1:99999'], 'expected tcp://HOST:PORT'),
    (['--scheduler', '[::1]'], 'expected tcp://HOST:PORT'),
    (['--scheduler', 'notanaddress'], 'expected tcp://HOST:PORT or tls://HOST:PORT'),
    (['--jobs', '2', 'TLS'], 'are for a tls:// --scheduler, not for the embedded cluster'),
    (['--scheduler', 'tls://head:8786', 'TLS', 'missing'],
     r'--tls-ca-file \S+missing.pem: cannot be read \(No such file or directory\)'),
    (['--scheduler', 'tls://head:8786', 'TLS', 'not PEM'],
     r'--tls-ca-file \S+ca.pem: not a PEM file')])
def test_issue_52_addresses_and_tls_files_refused_by_name(argv, message, tmp_path):
    """Issue 52: a scheduler without a port waited 20-24 s and raised a traceback; a malformed
    address was told to use --insecure; missing or non-PEM --tls-* files failed only at the
    connection (a traceback, or 'no answer within 10 s (SSLError)'), and with --jobs they
    were ignored."""
    files = _pem_files(tmp_path)
    if 'missing' in argv:
        files[0] = str(tmp_path / 'missing.pem')
    if 'not PEM' in argv:
        with open(files[0], 'w') as f:
            f.write('not a certificate\n')
    argv = [a for a in argv if a not in ('missing', 'not PEM')]
    if 'TLS' in argv:
        at = argv.index('TLS')
        argv[at:at + 1] = ['--tls-ca-file', files[0], '--tls-cert', files[1],
                           '--tls-key', files[2]]
    with pytest.raises(ValueError, match=message) as err:
        _spec(argv)
    assert '\n' not in str(err.value) and '--insecure' not in str(err.value)


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
