import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

# Without CUDA the GPU backend's Triton kernels run in Triton's interpreter (read when the kernels
# are defined, so before anything imports them): CI checks them on the CPU.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")
# The cpu kernels compiled once for every network size (`moex.kernels.cpu.lanes.sizes`): the suite
# meets dozens of sizes, each a compile of its own otherwise; the tests that compare the two
# (the same bits) set it themselves. Read when a problem is made: subprocesses inherit it.
os.environ.setdefault("MOEX_CPU_SIZES", "runtime")

from moex.config import Config
from moex.config.model import ExpertsConfig, GatingConfig, ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.kernels import Backend, available
from moex.tasks import task_config
from tests.helpers import backend_params

torch.set_default_dtype(torch.float64)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist starts its workers
def pytest_sessionstart(session):
    """The whole suite on several workers with cpu kernels not cached (a fresh checkout, an edit of
    a kernel): compile them once, both precisions side by side (`tests/precompile.py`), before the
    workers start, instead of in every worker and subprocess that needs them before the cache
    has them. A stamp beside numba's cache (`moex.compile_helper.stamp`) says it was done for
    these sources."""
    from moex import compile_helper

    config = session.config
    if (hasattr(config, "workerinput") or config.args_source != pytest.Config.ArgsSource.TESTPATHS
            or not config.getoption("numprocesses", None) or config.option.collectonly
            or compile_helper.stamp("suite").exists()):
        return
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    reporter.write_line("compiling the cpu kernels once for all workers (float64 and float32; "
                        "about a minute on 2 cores)")
    root = Path(__file__).resolve().parents[1]
    helpers = [subprocess.Popen([sys.executable, "-m", "tests.precompile", precision], cwd=root,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
               for precision in ("float64", "float32")]
    errors = [helper.communicate()[1] for helper in helpers]
    failed = [err[-500:] for helper, err in zip(helpers, errors, strict=True) if helper.returncode]
    if failed:  # the tests then compile for themselves (and show what is wrong)
        reporter.write_line("tests/precompile.py failed: " + " | ".join(failed))
    else:
        compile_helper.mark_cached("suite")


@pytest.fixture
def tiny_cfg() -> Config:
    """A lissajous2 config small enough to train both phases in about a second."""
    return Config(
        task=task_config("lissajous2", num_series=2, length=40, num_test_series=1),
        model=ModelConfig(num_experts=2, delay=1, experts=ExpertsConfig(context_size=4),
                          gating=GatingConfig(context_size=5)),
        train=TrainConfig(experts=ExpertPhaseConfig(steps=15, log_every=5),
                          gating=GatingPhaseConfig(steps=10, log_every=5)),
        num_runs=2,
    )


@pytest.fixture
def moex_here(capsys, monkeypatch):
    """The `moex` command run in this process (`moex.cli.main`, in the folder `cwd`), for commands
    refused before any work starts: a `CompletedProcess` with the exit code and the output, as a
    subprocess would give it, without a subprocess's seconds of imports."""
    from moex.cli import main

    def run(args: list[str], cwd) -> subprocess.CompletedProcess:
        monkeypatch.chdir(cwd)
        capsys.readouterr()
        handlers = list(logging.getLogger().handlers)
        try:
            main(list(args))
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
        out = capsys.readouterr()
        started = logging.getLogger().handlers != handlers  # Hydra set up a run's logging
        logging.getLogger().handlers[:] = handlers
        assert not started, f"moex {' '.join(args)} started a run: test it in a subprocess"
        return subprocess.CompletedProcess(args, code, out.out, out.err)

    return run


@pytest.fixture(params=backend_params())
def backend(request) -> Backend:
    """Each backend on the device it runs on here (gpu: CUDA, else Triton's interpreter); where
    one cannot run (Triton missing), its tests are skipped with the reason."""
    chosen, why = available(request.param)
    if chosen is None:
        pytest.skip(f"backend {request.param} cannot run here: {why}")
    return chosen
