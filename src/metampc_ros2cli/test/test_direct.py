"""Ctrl-C ends a verb that waits for an answer at once (ros2cli does), even when the server
never answers: `ros2 service call` against a service whose callback sleeps for an hour."""
import signal
import subprocess
import sys
import textwrap
import time

SERVER = textwrap.dedent('''
    import time
    import rclpy
    from std_srvs.srv import Trigger
    rclpy.init()
    node = rclpy.create_node('never_answers')
    node.create_service(Trigger, 'never_answers', lambda req, resp: time.sleep(3600))
    print('up', flush=True)
    rclpy.spin(node)
''')


def test_service_call_ends_on_ctrl_c_while_it_waits_for_the_answer():
    server = subprocess.Popen([sys.executable, '-c', SERVER], stdout=subprocess.PIPE,
                              text=True, start_new_session=True)
    caller = None
    try:
        assert server.stdout.readline() == 'up\n'
        caller = subprocess.Popen(['ros2', 'service', 'call', '/never_answers',
                                   'std_srvs/srv/Trigger'], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, start_new_session=True)
        for line in caller.stdout:
            if line.startswith('requester: making request'):
                break
        time.sleep(1.0)     # now in the wait for the answer
        interrupted = time.monotonic()
        caller.send_signal(signal.SIGINT)
        assert caller.wait(10.0) == 0
        assert time.monotonic() - interrupted < 2.0
    finally:
        for proc in (caller, server):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            if proc is not None:
                proc.stdout.close()
