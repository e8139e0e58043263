"""The one home of signals (ttmjx/commandline.py): a training loop's handlers record the first
SIGINT/SIGTERM for the loop to stop at the end of its iteration, exit at once with 128 + signal
on a second, and give the previous handlers back."""
import os
import signal
import subprocess
import sys

from ttmjx.commandline import install_stop_signals, restore_signals, signal_exit_code


class Loop:
    def __init__(self):
        self._stop, self.said = 0, []

    def log(self, message):
        self.said.append(message)


def test_the_first_signal_asks_the_loop_to_stop_and_the_old_handlers_come_back():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    loop = Loop()
    install_stop_signals(loop)
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        assert loop._stop == signal.SIGTERM and "SIGTERM: finishing this iteration" in loop.said[0]
    finally:
        restore_signals(loop)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_a_second_signal_exits_at_once_with_128_plus_it():
    code = ("import os, signal, time\n"
            "from ttmjx.commandline import install_stop_signals\n"
            "class L:\n    _stop = 0\n    def log(self, m): pass\n"
            "install_stop_signals(L())\n"
            "os.kill(os.getpid(), signal.SIGINT); os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(5)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(os.path.dirname(__file__)), timeout=60)
    assert done.returncode == signal_exit_code(signal.SIGTERM) == 143
