"""moex: a mixture of RNN experts that learns stochastic switching by chaos (Namikawa & Tani)."""

from moex.config import Config
from moex.errors import ConfigError
from moex.model import (
    ModelConfig,
    expert_forward,
    gating_forward,
    init_experts,
    init_gating,
    leaky_scan,
)
from moex.pipeline import run_train
from moex.tasks import Dataset, TaskConfig, make_task
from moex.train import TrainConfig, train_experts, train_gating

__all__ = [
    "Config", "ConfigError", "Dataset", "ModelConfig", "TaskConfig", "TrainConfig",
    "expert_forward", "gating_forward", "init_experts", "init_gating", "leaky_scan",
    "make_task", "run_train", "train_experts", "train_gating",
]
