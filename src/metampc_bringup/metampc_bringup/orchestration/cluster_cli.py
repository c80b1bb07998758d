"""The command-line face of the cluster layer (:mod:`.cluster`), one for every command that
runs a batch of jobs (run_experiment.py, robustness.py, sweep_inner_steps.py, tune.py):
``--jobs N`` (the embedded cluster's workers, within the cpu budget, :mod:`.cpu_budget`),
``--scheduler ADDRESS`` with ``--insecure`` and the ``--tls-*`` files, and the
:class:`.cluster.ClusterSpec` they make, refused (ValueError) before any connection."""
import argparse
from typing import Optional

from metampc_bringup.orchestration.cluster import check_address, ClusterSpec, TlsFiles
from metampc_bringup.orchestration.cpu_budget import check_jobs


def add_arguments(parser: argparse.ArgumentParser, jobs_help: str) -> None:
    """--jobs (default None: the command's own), --scheduler, --insecure, --tls-ca-file,
    --tls-cert, --tls-key."""
    parser.add_argument('--jobs', type=int, help=jobs_help)
    parser.add_argument('--scheduler', metavar='ADDRESS',
                        help='run the jobs on an existing dask cluster, tcp://HOST:PORT or '
                             'tls://HOST:PORT (docs/experiments.md#on-a-cluster)')
    parser.add_argument('--insecure', action='store_true',
                        help='allow a --scheduler tcp:// address off this machine (anyone who '
                             'reaches that scheduler can run code on its workers)')
    for name, what in (('ca-file', "the CA that signed the cluster's certificates"),
                       ('cert', "this client's certificate"), ('key', "this client's key")):
        parser.add_argument(f'--tls-{name}', metavar='PEM',
                            help=f'a tls:// --scheduler: {what} (docs/security.md)')


def tls_files(args: argparse.Namespace) -> Optional[TlsFiles]:
    """The --tls-* files (all three, or None for none; ValueError otherwise)."""
    given = (args.tls_ca_file, args.tls_cert, args.tls_key)
    if not any(given):
        return None
    if not all(given):
        raise ValueError('--tls-ca-file, --tls-cert and --tls-key go together')
    return TlsFiles(*given)


def cluster_spec(args: argparse.Namespace, jobs_default: int, threads: int,
                 threads_name: str = '--threads') -> ClusterSpec:
    """The cluster of the arguments of :func:`add_arguments`: embedded with --jobs (default
    `jobs_default`) workers, jobs x `threads` within the usable cores; or --scheduler, its
    address checked (:func:`.cluster.check_address`), where --jobs > 1 is refused (the
    cluster's workers run the jobs); the --tls-* files only with a scheduler, readable and
    PEM. ValueError naming the argument, before any connection."""
    tls = tls_files(args)
    if args.scheduler is not None:
        check_address(args.scheduler, args.insecure, tls is not None)
        if args.jobs is not None and args.jobs > 1:
            raise ValueError("--jobs sets the embedded cluster's workers: not with --scheduler "
                             "(the cluster's workers run the jobs)")
    elif tls is not None:
        raise ValueError('the --tls-* files are for a tls:// --scheduler, not for the '
                         'embedded cluster')
    if tls is not None:
        tls.check()
    jobs = (jobs_default if args.scheduler is None else 1) if args.jobs is None else args.jobs
    check_jobs(jobs, threads, threads_name)
    return ClusterSpec(jobs, args.scheduler, args.insecure, tls)
