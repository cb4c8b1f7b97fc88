import os
import subprocess
import sys

import pytest


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_the_bar_shows_on_a_terminal_that_reports_no_size():
    """A fresh pseudo-terminal reports 0 × 0 (as under `script` without a window); plain tqdm
    draws nothing there, `progress.bar` draws the bar at the fallback width."""
    code = ("import time\nfrom moex.progress import bar\n"
            "for _ in bar(range(20), desc='work', mininterval=0): time.sleep(0.005)\n")
    master, slave = os.openpty()
    assert os.get_terminal_size(slave) == (0, 0)
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    child = subprocess.run([sys.executable, "-c", code], stdin=slave, stdout=slave, stderr=slave,
                           env=env, timeout=120)
    os.close(slave)
    out = b""
    while True:
        try:
            chunk = os.read(master, 65536)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    os.close(master)
    assert child.returncode == 0
    assert b"work:" in out and b"20/20" in out
