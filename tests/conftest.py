import os

import pytest
import torch

# Without CUDA the GPU backend's Triton kernels run in Triton's interpreter (read when the kernels
# are defined, so before anything imports them): CI checks them on the CPU.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from moex.config import Config
from moex.model import ExpertsConfig, GatingConfig, ModelConfig
from moex.tasks import TaskConfig
from moex.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig

torch.set_default_dtype(torch.float64)


@pytest.fixture
def tiny_cfg() -> Config:
    """A lissajous2 config small enough to train both phases in about a second."""
    return Config(
        task=TaskConfig(name="lissajous2", num_series=2, length=40, num_test_series=1),
        model=ModelConfig(num_experts=2, delay=1, experts=ExpertsConfig(context_size=4),
                          gating=GatingConfig(context_size=5)),
        train=TrainConfig(experts=ExpertPhaseConfig(steps=15, log_every=5),
                          gating=GatingPhaseConfig(steps=10, log_every=5)),
        num_runs=2,
    )


def generators(seeds):
    return [torch.Generator().manual_seed(s) for s in seeds]


FAST_BACKENDS = ("cpu", "gpu")  # every backend the law tests hold to the reference


def fast_backend(name: str):
    """The named backend on its device (gpu: CUDA, or Triton's interpreter on the CPU); skipped,
    with the reason, where it cannot run."""
    from moex.kernels import _gpu_module, get_backend

    if name == "gpu":
        gpu, why = _gpu_module()
        if gpu is None:
            pytest.skip(f"backend gpu: Triton is not installed ({why})")
        return get_backend("gpu", "cuda" if torch.cuda.is_available() else "cpu")
    return get_backend(name)
