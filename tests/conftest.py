import logging
import os
import subprocess

import pytest
import torch

# Without CUDA the GPU backend's Triton kernels run in Triton's interpreter (read when the kernels
# are defined, so before anything imports them): CI checks them on the CPU.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from moex.config import Config
from moex.config.model import ExpertsConfig, GatingConfig, ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.kernels import Backend, available
from moex.tasks import task_config
from tests.helpers import backend_params

torch.set_default_dtype(torch.float64)


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
