"""The top-level `Config`, assembled from each component's own dataclass, and its registration
as Hydra's schema (`base_config`), so that every YAML value is type-checked when composed."""

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore

from moex.errors import check
from moex.model import ModelConfig
from moex.tasks import TaskConfig
from moex.train import TrainConfig

DTYPES = ("float64", "float32")
DEVICES = ("cpu", "cuda")


@dataclass
class Config:
    task: TaskConfig = field(default_factory=TaskConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    seed: int = 0
    num_runs: int = 1  # R networks trained side by side, run r seeded by (seed, r)
    dtype: str = "float64"
    device: str = "cpu"

    def __post_init__(self):
        check(self.num_runs >= 1, f"num_runs={self.num_runs} must be >= 1")
        check(self.seed >= 0, f"seed={self.seed} must be >= 0")
        check(self.dtype in DTYPES, f"dtype={self.dtype!r}; choose float64 or float32")
        check(self.device in DEVICES, f"device={self.device!r}; choose cpu or cuda")


def register_configs() -> None:
    ConfigStore.instance().store(name="base_config", node=Config)
