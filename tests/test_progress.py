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


@pytest.mark.parametrize("columns", [80, 100, 200])
def test_summary_lines_fit_the_terminal_and_never_split_a_number(columns, monkeypatch):
    """`packed` fits the terminal's width less the time stamp (at most 100 columns in all) and
    moves a whole "name value" pair to the next line rather than splitting it ("0.0358 / 5")."""
    import os

    from moex.progress import STAMP, packed

    # (as shutil's own: pytest -v asks it for its progress column with fallback= meanwhile)
    monkeypatch.setattr("shutil.get_terminal_size",
                        lambda *a, **k: os.terminal_size((columns, 24)))
    parts = [f"metric{i} {0.0358 * i:.4g} ± {i / 7:.2g}" for i in range(12)]
    lines = packed("run 0:", parts)
    assert all(STAMP + len(line) <= min(columns, 100) for line in lines)
    assert " ".join(line.strip() for line in lines) == "run 0: " + ", ".join(parts)
    assert all(line.startswith("    ") for line in lines[1:])


def test_on_a_terminal_the_bar_replaces_the_periodic_progress_lines(monkeypatch):
    """The console's filter drops progress records on a terminal (the bar shows them) and keeps
    them in pipes and files; other records always pass."""
    import logging

    from moex.progress import BarOrLines

    progress = logging.LogRecord("moex.train", logging.INFO, "", 0, "experts: step 10/100",
                                 None, None)
    progress.progress = True
    other = logging.LogRecord("moex.train", logging.INFO, "", 0, "final", None, None)
    for tty, kept in ((True, False), (False, True)):
        monkeypatch.setattr(sys.stdout, "isatty", lambda tty=tty: tty)
        assert BarOrLines().filter(progress) is kept and BarOrLines().filter(other)
