"""The stop request of a command: SIGINT/SIGTERM turned into a flag that training checks every
step (it then saves and stops) and evaluation between chunks."""

import signal
import threading


class StopRequest:
    """Turns SIGINT/SIGTERM into a flag that training checks each step (then saves and stops)."""

    def __init__(self):
        self.signum = 0

    def __call__(self) -> bool:
        return self.signum != 0

    def __enter__(self):
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        self.signum = signum

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
