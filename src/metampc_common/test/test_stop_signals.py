"""Ctrl-C under run_node (metampc_common.stop_signals): the callback that runs when SIGINT
arrives finishes, its publish and its log line included, before the context is shut down.

The race of a real loop (a callback publishing at the moment of Ctrl-C) made certain: the
node's one callback sleeps, and SIGINT comes during the sleep. With rclpy's own handler the
context was shut down at once and the publish after the sleep failed.
"""
import signal
import subprocess
import sys
import time

import pytest

TIMEOUT = 60.0      # s: generous, for a loaded 2-core machine
NODE = '''
import sys
import time

from rclpy.node import Node
from std_msgs.msg import String

from metampc_common.node_main import loop_executor, run_node


class Slow(Node):
    def __init__(self):
        super().__init__('slow')
        self.pub = self.create_publisher(String, 'slow', 10)
        self.timer = self.create_timer(0.01, self.tick)

    def tick(self):
        self.timer.cancel()
        print('in the callback', flush=True)
        time.sleep(2.0)     # SIGINT arrives here
        self.pub.publish(String(data='after'))
        self.get_logger().info('published after the signal')


sys.exit(run_node(Slow, 'slow', executor=loop_executor if sys.argv[1] == 'events' else None))
'''


@pytest.mark.parametrize('executor', ['single', 'events'])
def test_a_callback_running_at_ctrl_c_finishes_and_publishes(tmp_path, executor):
    log = tmp_path / 'node.log'
    with open(log, 'w') as out:
        proc = subprocess.Popen([sys.executable, '-c', NODE, executor], stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + TIMEOUT
        while 'in the callback' not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert code == 0, text
    assert 'published after the signal' in text, text
    assert 'context is invalid' not in text and 'Traceback' not in text, text
