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


def test_a_log_line_redraws_the_bar_at_the_current_step(monkeypatch):
    """A log line in the middle of a loop (tqdm.write, as logging_redirect_tqdm does) redraws the
    bar with the step reached, not the count of its last timed refresh (0 % before)."""
    import io

    from tqdm import tqdm

    from moex import progress

    screen = io.StringIO()
    monkeypatch.setattr(progress, "bar", lambda **kw: tqdm(file=screen, mininterval=3600,
                                                           ncols=80, **kw))
    for step in progress.steps(0, 10, desc="work"):
        if step == 7:
            tqdm.write("a log line", file=screen)
    drawn = screen.getvalue()
    after = drawn[drawn.index("a log line"):]
    assert "7/10" in after and " 0/10" not in after
