"""Progress bars on a terminal (tqdm), none in log files; the terminal's log line format.

A pseudo-terminal can report a size of 0 × 0 (a session recorded with `script` without a window,
some CI runners): tqdm then draws an empty bar. `bar` asks `shutil.get_terminal_size`, which falls
back to $COLUMNS × $LINES or 80 × 24, and passes that size on.
"""

import logging
import shutil

from tqdm.auto import tqdm


def bar(iterable=None, **kwargs) -> tqdm:
    """`tqdm(iterable, **kwargs)`, off where the output is not a terminal, never zero-width."""
    columns, lines = shutil.get_terminal_size()
    settings = {"ncols": columns, "nrows": lines, "disable": None, "mininterval": 1.0,
                "leave": False}
    return tqdm(iterable, **{**settings, **kwargs})


def steps(start: int, stop: int, **kwargs):
    """range(start, stop) under a bar whose count is always current: tqdm iterating a range
    counts in a local variable it publishes only when it redraws, so a log line in between
    (which redraws the bar) showed a stale count, often 0 %."""
    with bar(total=stop, initial=start, **kwargs) as shown:
        for step in range(start, stop):
            yield step
            shown.update()


class BarOrLines(logging.Filter):
    """On the terminal's handler: a progress line (a record logged with extra={"progress":
    True}) is dropped where a progress bar shows the same on a terminal; log files and piped
    output keep every line."""

    def filter(self, record: logging.LogRecord) -> bool:
        import sys

        return not (getattr(record, "progress", False) and sys.stdout.isatty())


class TerminalFormatter(logging.Formatter):
    """The terminal's log lines: the time and the message, and the level where it is not INFO
    (the run folder's log file keeps the full record)."""

    def __init__(self):
        super().__init__("%(asctime)s %(message)s", "%H:%M:%S")

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        if record.levelno >= logging.WARNING:
            stamp, _, message = line.partition(" ")
            line = f"{stamp} {record.levelname.lower()}: {message}"
        return line


def counted(n: int, noun: str) -> str:
    """"1 run", "2 runs": a count with its noun in the number it needs."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


STAMP = len("00:00:00 ")  # the terminal formatter's time before each message


def packed(head: str, parts: list[str], sep: str = ", ", width: int | None = None) -> list[str]:
    """`head` and `parts` joined by `sep` into lines of at most `width` characters (default: the
    terminal's width less the log's time stamp, at most 100), never splitting a part: a number
    and its name stay on one line; continuation lines are indented by four spaces."""
    if width is None:
        width = min(shutil.get_terminal_size().columns, 100) - STAMP
    lines, line = [], head
    for i, part in enumerate(parts):
        piece = part + (sep.rstrip() if i < len(parts) - 1 else "")
        if line.strip() and len(line) + len(piece) + 1 > width:
            lines.append(line.rstrip())
            line = "    "
        line += ("" if line.endswith(" ") or not line else " ") + piece
    lines.append(line.rstrip())
    return lines
