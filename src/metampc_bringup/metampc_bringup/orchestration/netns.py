"""Several "hosts" on one Linux machine: network namespaces joined by a bridge.

The experiment's nodes can be placed in groups, one network namespace ("host") each, so that
every message between groups crosses a network link as between machines: one namespace per
host (lo + a veth link 10.201.0.<i+1>/24), a bridge namespace and one for the orchestrator
(:func:`call_in_namespace`), made with iproute2 (``ip``) as root with both ends of every link
already inside, so nothing appears in the machine's own namespace. :func:`split_hosts` deletes
them on every exit (an exception, Ctrl-C, SIGTERM); those of a SIGKILLed run go with the next
run. Without root it refuses before creating anything. Set-up and what was measured:
docs/experiments.md. No rclpy here.
"""
import contextlib
import itertools
import logging
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterator, List, Sequence

from metampc_bringup.orchestration.domain import isolated
from metampc_bringup.orchestration.lifeline import child_env, hold

log = logging.getLogger('metampc.netns')

NODE_NAMES = ('recorder', 'learner', 'plant', 'controller', 'controller_nmpc')
SUBNET = '10.201.0.{}/24'
ORCHESTRATOR_HOST = 254
NAME_PREFIX = 'metampc-'
_counter = itertools.count()


class NetnsError(RuntimeError):
    """Hosts cannot be made here (not root, no iproute2) or a placement is invalid."""


def parse_hosts(text: str) -> List[List[str]]:
    """'plant|controller,controller_nmpc|learner,recorder' -> one list of node names per host.

    Hosts are separated by '|', the nodes of one host by ','. Names: :data:`NODE_NAMES`, each
    at most once; a node not named runs with the orchestrator, in its namespace.
    """
    hosts = [[n.strip() for n in part.split(',') if n.strip()] for part in text.split('|')]
    check_hosts(hosts)
    return hosts


def check_hosts(hosts: Sequence[Sequence[str]]) -> None:
    """NetnsError unless `hosts` is a placement: non-empty hosts, known nodes, each once."""
    names = [n for host in hosts for n in host]
    if not names or any(not host for host in hosts):
        raise NetnsError(f'hosts {_text(hosts)!r}: every host needs at least one node, e.g. '
                         "'plant|controller,controller_nmpc|learner,recorder'")
    unknown = sorted(set(names) - set(NODE_NAMES))
    if unknown:
        raise NetnsError(f'hosts {_text(hosts)!r}: unknown node(s) {unknown}; nodes: '
                         f'{", ".join(NODE_NAMES)}')
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise NetnsError(f'hosts {_text(hosts)!r}: {twice} placed more than once')


def _text(hosts: Sequence[Sequence[str]]) -> str:
    return '|'.join(','.join(host) for host in hosts)


def check_can_create() -> None:
    """NetnsError unless this process may create network namespaces (root, iproute2)."""
    if os.geteuid() != 0:
        raise NetnsError('placing nodes on hosts needs network namespaces, which only root '
                         'may create; run as root, or run the nodes on real machines '
                         '(docs/experiments.md, "Across hosts")')
    if shutil.which('ip') is None:
        raise NetnsError("placing nodes on hosts needs iproute2's `ip` command (Debian: apt "
                         'install iproute2)')


def _ip(*args: str) -> str:
    result = subprocess.run(['ip', *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise NetnsError(f'`ip {" ".join(args)}` failed: {result.stderr.strip()}')
    return result.stdout


def namespaces() -> List[str]:
    """Names of the network namespaces of this machine (``ip netns list``)."""
    return [line.split()[0] for line in _ip('netns', 'list').splitlines() if line.strip()]


def _owner_alive(name: str) -> bool:
    found = re.match(rf'{re.escape(NAME_PREFIX)}(\d+)-', name)
    if not found:
        return True
    try:
        os.kill(int(found.group(1)), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def _delete(name: str) -> None:
    """Kill what still runs in namespace `name`, then delete it (its links go with it)."""
    with contextlib.suppress(NetnsError):
        for pid in _ip('netns', 'pids', name).split():
            with contextlib.suppress(ProcessLookupError):
                os.kill(int(pid), signal.SIGKILL)
    with contextlib.suppress(NetnsError):
        _ip('netns', 'delete', name)


def remove_stale() -> List[str]:
    """Delete the namespaces of this module whose creating process is gone; their names."""
    stale = [n for n in namespaces() if n.startswith(NAME_PREFIX) and not _owner_alive(n)]
    for name in stale:
        _delete(name)
    return stale


@dataclass
class HostNetwork:
    """The namespaces of one split: per host its namespace and address, the orchestrator's.

    Attributes:
        hosts: node names per host, in order (none: :func:`linked_hosts`). namespaces: the
            namespace of each host.
        orchestrator: the orchestrator's namespace. bridge: the bridge's namespace.
    """

    hosts: List[List[str]]
    namespaces: List[str]
    orchestrator: str
    bridge: str

    def address(self, host: int) -> str:
        return SUBNET.format(host + 1).split('/')[0]

    def prefix(self) -> Dict[str, List[str]]:
        """Per node name, the command to start it under (``ip netns exec <namespace>``)."""
        return {node: ['ip', 'netns', 'exec', ns]
                for nodes, ns in zip(self.hosts, self.namespaces) for node in nodes}

    def traffic(self) -> Dict[str, Dict[str, int]]:
        """Bytes and packets each host sent and received on its link so far."""
        out = {}
        for ns in [*self.namespaces, self.orchestrator]:
            text = _ip('-n', ns, '-s', 'link', 'show', 'veth0')
            rx, tx = (line.split() for line in text.splitlines()[3:6:2])
            out[ns] = {'rx_bytes': int(rx[0]), 'rx_packets': int(rx[1]),
                       'tx_bytes': int(tx[0]), 'tx_packets': int(tx[1])}
        return out


def _add_host(bridge: str, name: str, port: str, address: str) -> None:
    _ip('netns', 'add', name)
    _ip('-n', name, 'link', 'set', 'lo', 'up')
    _ip('-n', name, 'link', 'add', 'veth0', 'type', 'veth', 'peer', 'name', port,
        'netns', bridge)
    _ip('-n', bridge, 'link', 'set', port, 'master', 'br0', 'up')
    _ip('-n', name, 'addr', 'add', address, 'dev', 'veth0')
    _ip('-n', name, 'link', 'set', 'veth0', 'up')
    _ip('-n', name, 'route', 'add', '224.0.0.0/4', 'dev', 'veth0')


@contextlib.contextmanager
def host_network(hosts: Sequence[Sequence[str]]) -> Iterator[HostNetwork]:
    """Create the namespaces, links and bridge for `hosts`; delete all of them on exit."""
    check_hosts(hosts)
    with _linked(hosts) as net:
        yield net


@contextlib.contextmanager
def linked_hosts(count: int) -> Iterator[HostNetwork]:
    """`count` empty hosts and the orchestrator's namespace (e.g. a dask scheduler, workers
    and their client: test_cluster_netns), linked as by :func:`host_network`, deleted on exit
    with whatever still runs inside."""
    with _linked([[] for _ in range(count)]) as net:
        yield net


@contextlib.contextmanager
def _linked(hosts: Sequence[Sequence[str]]) -> Iterator[HostNetwork]:
    check_can_create()
    for name in remove_stale():
        log.warning('removed namespace %s left by a process that was killed', name)
    tag = f'{NAME_PREFIX}{os.getpid()}-{next(_counter)}'
    net = HostNetwork([list(h) for h in hosts], [f'{tag}-h{i}' for i in range(len(hosts))],
                      f'{tag}-orch', f'{tag}-br')
    made: List[str] = []
    try:
        made.append(net.bridge)
        _ip('netns', 'add', net.bridge)
        _ip('-n', net.bridge, 'link', 'add', 'br0', 'type', 'bridge', 'mcast_snooping', '0')
        _ip('-n', net.bridge, 'link', 'set', 'br0', 'up')
        for i, ns in enumerate(net.namespaces):
            made.append(ns)
            _add_host(net.bridge, ns, f'p{i}', SUBNET.format(i + 1))
        made.append(net.orchestrator)
        _add_host(net.bridge, net.orchestrator, 'porch', SUBNET.format(ORCHESTRATOR_HOST))
        yield net
    finally:
        for name in reversed(made):
            _delete(name)


@contextlib.contextmanager
def split_hosts(hosts: Sequence[Sequence[str]]) -> Iterator[HostNetwork]:
    """The namespaces and links of `hosts` (:func:`host_network`) and, in os.environ (so
    inherited by every process started inside), a ROS domain of its own with subnet
    discovery. Everything is undone on exit, and each host's traffic is logged."""
    with host_network(hosts) as net, isolated('SUBNET') as domain:
        for nodes, ns, i in zip(net.hosts, net.namespaces, itertools.count()):
            log.info('host %s (%s): %s', ns, net.address(i), ', '.join(nodes))
        log.info('orchestrator in %s; ROS_DOMAIN_ID=%d, discovery SUBNET',
                 net.orchestrator, domain)
        try:
            yield net
        finally:
            for ns, t in net.traffic().items():
                log.info('%s: sent %d kB in %d packets, received %d kB in %d packets', ns,
                         t['tx_bytes'] // 1000, t['tx_packets'], t['rx_bytes'] // 1000,
                         t['rx_packets'])


def call_in_namespace(namespace: str, fn: Callable[..., Any], *args: Any,
                      interrupt_timeout: float = 120.0, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` in a new Python process inside network namespace `namespace`;
    its result, or its exception raised here.

    A new process, because the DDS library binds a process to the network it first saw: an
    rclpy participant created in a namespace by a process that has used ROS elsewhere before
    does not discover anything. `fn` and the arguments must pickle (a module-level function).
    The child runs in a session of its own with this process's environment and log settings;
    Ctrl-C or SIGTERM here (KeyboardInterrupt) is passed on to it as one SIGINT, and its own
    KeyboardInterrupt comes back as that. After `interrupt_timeout` s it is killed.
    """
    root = logging.getLogger()
    handler = root.handlers[0] if root.handlers else None
    logs = (root.level, handler.formatter._fmt if handler and handler.formatter else None,
            handler.formatter.datefmt if handler and handler.formatter else None)
    with tempfile.TemporaryDirectory(prefix='metampc-netns-') as tmp:
        call, result = os.path.join(tmp, 'call.pickle'), os.path.join(tmp, 'result.pickle')
        with open(call, 'wb') as f:
            pickle.dump((fn, args, kwargs, logs), f)
        child = subprocess.Popen(['ip', 'netns', 'exec', namespace, sys.executable, '-m',
                                  __name__, call, result], start_new_session=True,
                                 env=child_env())
        try:
            child.wait()
        except KeyboardInterrupt:
            child.send_signal(signal.SIGINT)
            try:
                child.wait(interrupt_timeout)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
            raise
        if not os.path.exists(result):
            raise NetnsError(f'the process in namespace {namespace} ended with status '
                             f'{child.returncode} before it returned')
        with open(result, 'rb') as f:
            ok, value = pickle.load(f)
    if not ok:
        raise value
    return value


def _child(call: str, result: str) -> int:
    """The new process of :func:`call_in_namespace`: run the call, pickle what came of it."""
    with open(call, 'rb') as f:
        fn, args, kwargs, (level, fmt, datefmt) = pickle.load(f)
    logging.basicConfig(level=level, format=fmt, datefmt=datefmt)
    try:
        hold(signal.SIGINT)     # the caller killed: end the call as on Ctrl-C
        outcome = (True, fn(*args, **kwargs))
    except BaseException as err:    # KeyboardInterrupt too goes back to the caller
        outcome = (False, err)
    with open(result, 'wb') as f:
        pickle.dump(outcome, f)
    return 0


if __name__ == '__main__':
    sys.exit(_child(*sys.argv[1:]))
