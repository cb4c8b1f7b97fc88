"""The top-level `Config`, assembled from each component's own dataclass (this package's modules,
and each task's own in its module), and the configs of the other verbs. `moex.cli.register_configs`
registers them as Hydra's schemas (`base_config`, ...), so that every YAML value is type-checked
when composed; nothing here imports Hydra, a registry or what trains and evaluates: a value that
needs a registry to be checked (a backend's or a task's name) is checked where the registry
lives (`moex.kernels.check_name`, `moex.tasks.check_task`), by the verbs before they write."""

from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Any, Optional

import torch
import yaml

from moex.config.evaluation import EvalConfig
from moex.config.model import ModelConfig
from moex.config.plot import PlotConfig
from moex.config.train import TrainConfig
from moex.errors import check
from moex.tasks.base import TaskConfig
from moex.tasks.lissajous import Lissajous2Config

_PACKAGE_CONF = Path(__file__).resolve().parent.parent / "conf"  # in a wheel; a checkout: ../conf
CONF_DIR = _PACKAGE_CONF if _PACKAGE_CONF.is_dir() else _PACKAGE_CONF.parent.parent / "conf"
PRECISIONS = ("float64", "float32")
DEVICES = ("cpu", "cuda")


@dataclass
class Config:
    task: TaskConfig = field(default_factory=Lissajous2Config)  # a task's own subclass
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    seed: int = 0
    num_runs: int = 1  # R networks trained side by side, run r seeded by (seed, r)
    precision: str = "float64"  # of training and evaluation; tests and defaults use float64
    device: str = "cpu"
    backend: str = "auto"  # auto | reference (PyTorch) | cpu (numba) | gpu (Triton) (checked by
    # the verbs: moex.kernels.check_backend)
    resume: bool = False  # continue the latest run folder of this task (or hydra.run.dir)
    cache_dir: str = ""  # phase-1 results shared by jobs that differ only in the gating net
    plot: PlotConfig = field(default_factory=PlotConfig)

    def __post_init__(self):
        check(self.num_runs >= 1, f"num_runs={self.num_runs} must be >= 1")
        check(self.seed >= 0, f"seed={self.seed} must be >= 0")
        check(self.precision in PRECISIONS,
              f"precision={self.precision!r}; choose float64 or float32")
        check(self.device in DEVICES, f"device={self.device!r}; choose cpu or cuda")
        check(self.device != "cuda" or torch.cuda.is_available(),
              f"device=cuda but this machine has no CUDA device PyTorch can use (torch "
              f"{torch.__version__}); use device=cpu")


# every EvalConfig key, optional: what `moex evaluate` overrides in the run's own eval config
EvalOverrides = make_dataclass(
    "EvalOverrides", [(f.name, Optional[f.type], None) for f in fields(EvalConfig)])  # noqa: UP045


@dataclass
class RunFolder:
    """A finished training run and where a tool writes (default: `<run_dir>/<verb>/<date>/`)."""

    run_dir: str = ""
    out_dir: str = ""  # instead of <run_dir>/<verb>/<date>/

    def __post_init__(self):
        check(bool(self.run_dir), "run_dir is required: run_dir=outputs/<task>/<date>")
        check(not self.out_dir or Path(self.out_dir).resolve() != Path(self.run_dir).resolve(),
              f"out_dir={self.out_dir} is the run folder itself; its files are never "
              f"overwritten: choose another folder or leave out_dir out")


@dataclass
class EvaluateConfig(RunFolder):
    """`moex evaluate`: recompute every metric of a finished run."""

    eval: EvalOverrides = field(default_factory=EvalOverrides)  # None: the run's own value
    paper_sizes: bool = False  # set by eval=paper: the paper's sizes for the run's task


SIZE_KEYS = ("num_samples", "lyapunov_steps", "transient", "track_samples", "track_steps")


def paper_eval_sizes(task_name: str) -> dict:
    """The paper's evaluation sizes for a task: the `EvalConfig` defaults (Lissajous: 50 × 100
    000 steps) with the task's own file (conf/task/<name>.yaml, e.g. Reber: 200 × 10 000) on top."""
    sizes = {k: getattr(EvalConfig(), k) for k in SIZE_KEYS}
    path = CONF_DIR / "task" / f"{task_name}.yaml"
    own = (yaml.safe_load(path.read_text()) or {}).get("eval", {}) if path.is_file() else {}
    return {**sizes, **{k: v for k, v in own.items() if k in SIZE_KEYS}}


@dataclass
class GenerateConfig(RunFolder):
    """`moex generate`: closed-loop samples of a finished run."""

    steps: int = 10000  # closed-loop steps per sample
    num_samples: int = 4  # random initial states per network
    noise_var: float = 0.0  # ρ², Gaussian noise on x_n at every step (Sec. 4.3)
    from_series: int = -1  # -1: random initial states; k: the trained initial state of series k
    seed: int = 0  # run r draws its initial states and noise from (seed, r) alone

    def __post_init__(self):
        super().__post_init__()
        check(self.steps >= 1, f"steps={self.steps} must be >= 1")
        check(self.num_samples >= 1, f"num_samples={self.num_samples} must be >= 1")
        check(self.noise_var >= 0, f"noise_var={self.noise_var} must be >= 0")


@dataclass
class NewData:
    """The series `moex segment` reads (the csv task's keys of the same names)."""

    path: str = ""  # a CSV/NPY file, glob or folder ("": the run's held-out series)
    columns: list[str] = field(default_factory=list)  # [] : the columns the run trained on
    labels: str = ""  # a column or files of per-step labels ("": the run's label column)
    length: int = 0  # crop every series to this many steps (0: the files' own length)

    def __post_init__(self):
        check(self.length >= 0, f"task.length={self.length} must be >= 0")


def check_prior_std(key: str, value) -> None:
    """ς for segmenting new data: auto, 0 (the run's own) or a positive number."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    check(value == "auto" or (number and value >= 0),
          f"{key}={value!r} must be auto, 0 (the run's own) or a positive number")


@dataclass
class SegmentConfig(RunFolder):
    """`moex segment`: which expert explains which step of new data."""

    task: NewData = field(default_factory=NewData)
    method: str = "smooth"  # smooth: phase 1's estimate, experts fixed | filter: causal
    gate_prior_std: Any = "auto"  # ς of `smooth`: auto (cross-validated on the data), 0 (the
    # run's train.experts.gate_prior_std) or a number
    smooth_steps: int = 500  # optimiser steps of `smooth`

    def __post_init__(self):
        super().__post_init__()
        check(self.method in ("smooth", "filter"), f"method={self.method!r}; choose smooth "
                                                    f"or filter")
        check_prior_std("gate_prior_std", self.gate_prior_std)
        check(self.smooth_steps >= 1, f"smooth_steps={self.smooth_steps} must be >= 1")


MIN_VARIANCE = 0.001  # the C code's compile-time floor of every expert's variance


@dataclass
class ImportConfig(Config):
    """`moex import`: the C tools' save files of one design as a run folder of R networks."""

    source: list[str] = field(default_factory=list)  # folders (globs) holding mre.dat + gn.dat,
    # or rnn.dat: one network each, all trained on the data of `task` with data seed `seed`
    min_variance: float = MIN_VARIANCE  # the MIN_VARIANCE the C tools were compiled with
    out_dir: str = ""  # instead of outputs/imported/<task>/<date>

    def __post_init__(self):
        super().__post_init__()
        check(self.min_variance > 0, f"min_variance={self.min_variance} must be > 0")
