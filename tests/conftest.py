import pytest
import torch

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
