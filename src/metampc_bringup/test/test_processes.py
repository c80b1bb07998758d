"""processes.session_pids and ProcessGroup against a reused session number: once a leader is
reaped, its pid may be handed to a new process (pid numbers wrap), and that process's session
is not ours to count or kill."""
import subprocess

from metampc_bringup.orchestration.processes import ProcessGroup, session_pids


def _session_leader() -> subprocess.Popen:
    return subprocess.Popen(['sleep', '60'], start_new_session=True)


def test_a_live_leader_s_session_is_counted():
    other = _session_leader()
    try:
        assert session_pids(other) == [other.pid]
        assert session_pids(other.pid) == [other.pid]
    finally:
        other.kill()
        other.wait()


def test_a_reaped_leader_whose_pid_now_leads_another_session_counts_and_kills_nothing(tmp_path):
    ours = subprocess.Popen(['true'], start_new_session=True)
    ours.wait()
    other = _session_leader()
    try:
        # What the kernel does once pid numbers wrap: the reaped leader's number is reused by
        # a new session leader (forced here by pointing the reaped Popen at that number).
        ours.pid = other.pid
        assert session_pids(ours) == []
        group = ProcessGroup(str(tmp_path))
        group.procs.append(ours)
        group.stop_all()
        assert other.poll() is None, 'stop_all killed a session that was not its own'
    finally:
        other.kill()
        other.wait()
