"""The `moex` command's entry point: starts compiling before the command's own imports.

A first `moex train` on the cpu backend (an empty numba cache) compiles its kernels, about 40 s
of CPU: the run compiles the phase-1 kernel while a helper process (`moex.precompile`)
compiles the closed loop and phase 2. Here the helper starts before the command imports PyTorch
and Hydra (about 3 s on a 2-core machine), when the command line says the run trains on the cpu
backend (`moex.compile_helper`); the run adopts it (`warm.start`). One it never adopts (a bad
override, a run that ends early) is stopped when the command exits. The helper itself exits at
once when the kernels are already in the cache. A command that ran ends without the
interpreter's teardown (`leave`).
"""

import atexit
import os
import sys
from typing import NoReturn

from moex import compile_helper

_NOT_TRAINING = {"--help", "-h", "--hydra-help", "--info", "--cfg", "-c"}


def helper_precision(argv: list[str]) -> str | None:
    """The precision a helper should compile for when `argv` (the command's arguments) trains on
    the cpu backend in this process, by its overrides (the config's defaults otherwise: backend
    auto, device cpu, float64); None for other verbs and flags, another backend, device or
    launcher, or a sweep over precisions."""
    if not argv or argv[0] != "train" or _NOT_TRAINING & set(argv):
        return None
    values = dict(arg.lstrip("+").split("=", 1) for arg in argv[1:] if "=" in arg)
    if values.get("backend", "auto") not in ("auto", "cpu", "compiled") \
            or values.get("device", "cpu") != "cpu" or "hydra/launcher" in values:
        return None
    precision = values.get("precision", "float64")
    return precision if precision in ("float64", "float32") else None


def main() -> None:
    if sys.argv[1:2] in (["--version"], ["-V"]):  # without importing PyTorch and Hydra
        from importlib import metadata

        print(f"moex {metadata.version('moex')}")
        return
    if sys.argv[1:] in (["-sc", "query=bash"], ["-sc", "query=fish"]):  # a Tab (zsh asks as
        # bash does): answered without the heavy imports
        from moex.completion import answer

        answer()
        return
    precision = helper_precision(sys.argv[1:])
    if precision is not None:
        compile_helper.start(precision)
    from moex.cli import main as run_command

    try:
        run_command()
    except SystemExit as done:
        leave(done.code)
    leave(0)


def leave(code) -> NoReturn:
    """End the process as `sys.exit(code)` would (None is 0, a message is printed and exits 1),
    without the interpreter's teardown of the imported modules: PyTorch's alone takes about 0.5 s
    of every command. The exit handlers run first (logging's flush, `compile_helper.stop`), then
    the standard streams are flushed; no thread of the command is working by then (the kernels'
    threads wait for work)."""
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except OSError:  # a reader that went away (`moex ... | head`)
            pass
    os._exit(code)
