"""The compile helper's process (`python -m moex.kernels.cpu.helper <precision>`) between its start
by the `moex` command (`moex.launch`, before the command's heavy imports) and its adoption by the
run (`moex.kernels.cpu.warm.start`). Imports nothing of moex, so the command can start it at once
and neither side imports the other."""

import atexit
import subprocess
import sys

helper: tuple[str, subprocess.Popen] | None = None  # (precision, process) until the run adopts it


def spawn(precision: str) -> subprocess.Popen:
    """A helper process compiling the kernels of `precision` into the cache."""
    return subprocess.Popen([sys.executable, "-m", "moex.kernels.cpu.helper", precision],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def start(precision: str) -> None:
    """Start a helper for `precision` before the command's imports; stopped at exit unless
    adopted."""
    global helper
    helper = precision, spawn(precision)
    atexit.register(stop)


def adopt(precision: str) -> subprocess.Popen | None:
    """The started helper when it compiles for `precision` (the run owns it from now on); one of
    another precision is stopped; None when there is none to adopt."""
    global helper
    if helper is not None and helper[0] == precision:
        process, helper = helper[1], None
        return process
    stop()
    return None


def stop() -> None:
    """Stop a helper the run has not adopted."""
    global helper
    if helper is not None:
        helper[1].kill()
        helper[1].wait()
        helper = None
