"""A ROS_DOMAIN_ID of one's own: claimed with an exclusive lock file, held until the process and
the nodes it started (they inherit the lock) end.

Concurrent test sessions and experiments on one machine then never share a DDS domain. No
rclpy here: claim the domain before ``rclpy.init`` and before starting any node process.
"""
import contextlib
import fcntl
import os
import tempfile
from typing import IO, Iterator, List

DOMAINS = range(1, 102)     # ids 1..101 are valid with the default DDS port mapping
ENV_KEYS = ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_LOCALHOST_ONLY')
_held: List[IO] = []        # lock handles, kept open for the life of the process


def claim_domain() -> int:
    """Lock and return the first free domain id in 1..101; RuntimeError if none is free."""
    for domain in DOMAINS:
        handle = open(os.path.join(tempfile.gettempdir(), f'metampc-ros-domain-{domain}.lock'),
                      'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _held.append(handle)
        return domain
    raise RuntimeError('no free ROS_DOMAIN_ID in 1..101 (each metampc test session or '
                       'experiment holds one)')


def held_fds() -> List[int]:
    """File descriptors of the domain locks this process holds. A node started with them
    (:class:`.processes.ProcessGroup` passes them on) keeps its domain claimed until it ends:
    a run killed before its nodes have stopped leaves no domain that a new run could share
    with them."""
    return [handle.fileno() for handle in _held]


def isolate(discovery_range: str = 'LOCALHOST') -> int:
    """Claim a domain and set it, with the discovery range, in os.environ; return the id."""
    domain = claim_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = discovery_range
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    return domain


@contextlib.contextmanager
def isolated(discovery_range: str = 'LOCALHOST') -> Iterator[int]:
    """:func:`isolate` inside the block; the previous environment and the lock are given back
    after it (for a caller, such as a test session, that goes on in its own domain)."""
    saved = {k: os.environ.get(k) for k in ENV_KEYS}
    domain = isolate(discovery_range)
    handle = _held[-1]
    try:
        yield domain
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        _held.remove(handle)
        handle.close()
