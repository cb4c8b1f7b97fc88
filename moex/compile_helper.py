"""The compile helper's process (`python -m moex.precompile <precision>`) between its start
by the `moex` command (`moex.launch`, before the command's heavy imports) and its adoption by the
run (`moex.kernels.cpu.warm.start`). Imports nothing of moex, so the command can start it at once
and neither side imports the other.

A run that finds the helper's kernels in numba's cache leaves a stamp beside the cache
(`mark_cached`), named after the kernels' sources, numba's and Python's versions and the
precision; while it is there the command starts no helper (which would import PyTorch and numba,
about 2.2 s of CPU, only to find the kernels cached). An edit or an upgrade changes the name; a
wrong stamp costs only the early start: the run checks the cache itself (`warm.start`)."""

import atexit
import functools
import hashlib
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

helper: tuple[str, subprocess.Popen] | None = None  # (precision, process) until the run adopts it


def spawn(precision: str) -> subprocess.Popen:
    """A helper process compiling the kernels of `precision` into the cache (phase 2's for the
    sizes the run `tell`s it)."""
    argv, env = python("-m", "moex.precompile", precision)
    return subprocess.Popen(argv, env=env, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, text=True)


def python(*args: str) -> tuple[list[str], dict[str, str]]:
    """The command line and environment of a Python process that imports this very moex: its
    folder first on PYTHONPATH, and the working directory not on the path at all (`-P`), where
    `python -m` would put it first. A folder holding another moex (a checkout of another version
    beside an installed one) had the helper compile that one's kernels, which the run cannot use:
    it compiled its own beside the helper, a first run 66-94 s instead of 33-45."""
    path = [str(Path(__file__).resolve().parent.parent), os.environ.get("PYTHONPATH", "")]
    return [sys.executable, "-P", *args], {**os.environ,
                                           "PYTHONPATH": os.pathsep.join(filter(None, path))}


def tell(process: subprocess.Popen, gating: tuple[int, int, int]) -> None:
    """Write the gating RNN's units, inputs and outputs to the helper (`moex.precompile` reads
    them once it has compiled the closed loop); nothing where it has ended."""
    try:
        process.stdin.write(" ".join(map(str, gating)) + "\n")
        process.stdin.close()
    except (OSError, ValueError):  # a helper that ended (or was told already)
        pass


KERNELS = Path(__file__).resolve().parent / "kernels" / "cpu"


@functools.cache
def kernel_sources() -> bytes:
    """sha256 over every Python source of the cpu kernels' package (`KERNELS`) and the noise
    module they inline (`moex/kernels/noise.py`), name and text, in name order: what their
    compiled code depends on. The key of their entries in numba's cache
    (`moex.kernels.cpu.cache`) and part of the stamp's name. Read once a process: a process runs
    the kernels it imported."""
    digest = hashlib.sha256()
    for path in sorted([*KERNELS.glob("*.py"), KERNELS.parent / "noise.py"]):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.digest()


def stamp(precision: str) -> Path:
    """The stamp that says the helper's kernels of `precision` are cached (see above), in numba's
    cache folder: NUMBA_CACHE_DIR, or the kernels' __pycache__."""
    digest = hashlib.sha256(f"{metadata.version('numba')} {sys.version} {precision}".encode())
    digest.update(kernel_sources())
    folder = Path(os.environ.get("NUMBA_CACHE_DIR") or KERNELS / "__pycache__")
    return folder / f"moex-helper-{digest.hexdigest()[:16]}.cached"


def mark_cached(precision: str) -> None:
    """Leave the stamp (nothing where the folder cannot be written)."""
    path = stamp(precision)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
    except OSError:
        pass


def start(precision: str) -> None:
    """Start a helper for `precision` before the command's imports, unless the stamp says its
    kernels are cached; stopped at exit unless adopted."""
    global helper
    if stamp(precision).exists():
        return
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
