"""The top-level `Config`, assembled from each component's own dataclass, and its registration
as Hydra's schema (`base_config`), so that every YAML value is type-checked when composed."""

from dataclasses import dataclass, field, fields, make_dataclass
from typing import Optional

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from moex.errors import check
from moex.evaluate import EvalConfig
from moex.kernels import BACKENDS
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
    eval: EvalConfig = field(default_factory=EvalConfig)
    seed: int = 0
    num_runs: int = 1  # R networks trained side by side, run r seeded by (seed, r)
    dtype: str = "float64"
    device: str = "cpu"
    backend: str = "auto"  # auto | reference | compiled (numba, CPU)
    resume: bool = False  # continue the latest run folder of this task (or hydra.run.dir)
    cache_dir: str = ""  # phase-1 results shared by jobs that differ only in the gating net

    def __post_init__(self):
        check(self.num_runs >= 1, f"num_runs={self.num_runs} must be >= 1")
        check(self.seed >= 0, f"seed={self.seed} must be >= 0")
        check(self.dtype in DTYPES, f"dtype={self.dtype!r}; choose float64 or float32")
        check(self.device in DEVICES, f"device={self.device!r}; choose cpu or cuda")
        check(self.backend in BACKENDS,
              f"backend={self.backend!r}; choose one of {', '.join(BACKENDS)}")


# every EvalConfig key, optional: what `moex evaluate` overrides in the run's own eval config
EvalOverrides = make_dataclass(
    "EvalOverrides", [(f.name, Optional[f.type], None) for f in fields(EvalConfig)])  # noqa: UP045


@dataclass
class ToolConfig:
    """`moex evaluate` and `moex generate`: a trained run folder and what to do with it."""

    run_dir: str = ""
    eval: EvalOverrides = field(default_factory=EvalOverrides)  # None: the run's own value
    steps: int = 10000  # generate: closed-loop steps per sample
    num_samples: int = 4  # generate: random initial states per network
    noise_var: float = 0.0  # generate: ρ²
    from_series: int = -1  # generate: -1 random initial states, k the trained state of series k
    seed: int = 0

    def __post_init__(self):
        check(bool(self.run_dir), "run_dir is required: run_dir=outputs/<task>/<date>")
        check(self.steps >= 1, f"steps={self.steps} must be >= 1")
        check(self.num_samples >= 1, f"num_samples={self.num_samples} must be >= 1")
        check(self.noise_var >= 0, f"noise_var={self.noise_var} must be >= 0")


def register_configs() -> None:
    ConfigStore.instance().store(name="base_config", node=Config)
    ConfigStore.instance().store(name="base_tool", node=ToolConfig)


def config_from_dict(data: dict) -> Config:
    """Rebuild (and re-validate) a `Config` from the plain dict stored in a checkpoint."""
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(Config), data))
