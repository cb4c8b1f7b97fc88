"""moex: a mixture of RNN experts that learns stochastic switching by chaos (Namikawa & Tani).

The Python API is `fit` (train on your own arrays) and the `Fitted` it returns (`evaluate`,
`generate`, `save`), and `load` (a run folder of `moex train` as a `Fitted`); the building blocks
below are what it is made of.
"""

from moex.api import Fitted, fit, load
from moex.closed_loop import closed_loop_lyapunov, generate, random_state, trained_state
from moex.config import Config
from moex.errors import ConfigError
from moex.evaluate import EvalConfig, evaluate
from moex.kernels import get_backend
from moex.model import (
    ModelConfig,
    expert_forward,
    gate_estimates,
    gating_forward,
    init_experts,
    init_gating,
    leaky_scan,
)
from moex.pipeline import run_train
from moex.tasks import Dataset, TaskConfig, make_task
from moex.train import TrainConfig, train_experts, train_gating

__all__ = [
    "Config", "ConfigError", "Dataset", "EvalConfig", "Fitted", "ModelConfig", "TaskConfig",
    "TrainConfig", "closed_loop_lyapunov", "evaluate", "expert_forward", "fit", "gate_estimates",
    "gating_forward", "generate", "get_backend", "init_experts", "init_gating", "leaky_scan",
    "load", "make_task", "random_state", "run_train", "train_experts", "train_gating",
    "trained_state",
]
