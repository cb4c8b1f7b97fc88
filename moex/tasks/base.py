"""What every task shares: its config's common keys (`TaskConfig`, which each task's own config
extends), the `Dataset` it makes and its registry entry (`Task`)."""

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from moex.errors import check
from moex.metrics.symbols import symbolize_argmax, symbolize_nearest
from moex.tasks.scaling import Scale


@dataclass
class TaskConfig:
    """The keys of every task: its name and sizes. A task's own keys (the Lissajous period, the
    csv task's path, ...) are those of its subclass, in the task's module."""

    name: str = ""
    num_series: int = 10  # the paper's NT
    length: int = 1000  # the paper's LT (0 for files: their own length)
    num_test_series: int = 10  # held-out series from the same source
    data_seed: int = -1  # the data's own seed; -1: the run's `seed` (data and networks together)
    FILES: ClassVar[bool] = False  # read from the user's files, not generated

    def __post_init__(self):
        least = 0 if self.FILES else 1  # 0: every series and step the files hold
        check(self.num_series >= least, f"task.num_series={self.num_series} must be >= {least}")
        check(self.num_test_series >= 0,
              f"task.num_test_series={self.num_test_series} must be >= 0")
        check(self.length >= 0 if self.FILES else self.length >= 3,
              f"task.length={self.length} must be >= 3")
        check(self.data_seed >= -1, f"task.data_seed={self.data_seed} must be >= 0, or -1 for "
                                    f"the run's seed")


@dataclass
class Dataset:
    """Training (and held-out) data of one task.

    Attributes:
        series: (S, T, D) signal; D = 0 for purely symbolic tasks.
        labels: (S, T) index of the true primitive at each step (-1 where unknown).
        symbol_names: the V symbols; `symbol_of[k]` is the symbol of primitive k.
        transition: (K, K) true transition matrix between primitives, or None.
        prototypes: (P, D) points on the primitives and their symbols (P,), used to read a
            symbol off a generated output (nearest point); None where outputs are symbols.
        gate_targets: (S, T, V) one-hot symbols for tasks without experts (D = 0), else None.
        test: held-out data from the same source, or None.
        period: steps a primitive lasts (1 where every step is a symbol), to count repetitions.
        violations: symbols (T,) -> (T,) bool, the steps a grammar forbids (Reber), or None.
        scale: the map from the model's units back to the data's (user data, `task.scale`).
    """

    series: np.ndarray
    labels: np.ndarray
    symbol_names: list[str]
    symbol_of: np.ndarray
    transition: np.ndarray | None = None
    prototypes: np.ndarray | None = None
    prototype_symbols: np.ndarray | None = None
    gate_targets: np.ndarray | None = None
    test: "Dataset | None" = None
    period: float = 1.0
    violations: Callable[[np.ndarray], np.ndarray] | None = None
    scale: Scale = field(default_factory=Scale)

    def symbolize(self, outputs: np.ndarray, gates: np.ndarray, nearest=None) -> np.ndarray:
        """Symbols (..., T) of generated steps: the symbol of the nearest prototype point of the
        output where the task has primitives, else the winning gate (Eq. 22). `nearest` is the
        implementation of the first rule (a backend's `nearest_symbols`, tensors in and out;
        default: `symbolize_nearest` on the host)."""
        if self.prototypes is None:
            return symbolize_argmax(gates)
        if nearest is None:
            return symbolize_nearest(outputs, self.prototypes, self.prototype_symbols)
        labels = nearest(torch.as_tensor(outputs), torch.as_tensor(self.prototypes),
                         torch.as_tensor(self.prototype_symbols))
        return labels.cpu().numpy()

    @property
    def switch_prob(self) -> float | None:
        """The probability of moving on from a primitive, where the task has one for all (the
        residence times are then geometric with that parameter), else None."""
        if self.transition is None or len(self.symbol_names) != len(self.transition):
            return None
        stay = np.diag(self.transition)
        return float(1 - stay[0]) if np.allclose(stay, stay[0]) else None


def user_data(series: np.ndarray, scale: Scale | None = None,
              labels: np.ndarray | None = None) -> Dataset:
    """A `Dataset` of a user's series (S, T, D) in model units, with their labels (S, T) where
    the user has them (-1: unknown); no symbols."""
    labels = -np.ones(series.shape[:2], dtype=np.int64) if labels is None else labels
    return Dataset(series, labels, symbol_names=[], symbol_of=np.zeros(0, dtype=np.int64),
                   scale=scale or Scale())


@dataclass(frozen=True)
class Task:
    """A task of the registry: its config class (whose `name` default names the task),
    `make(cfg, rng, min_length)` that builds its `Dataset`, and `features(cfg)`: D, known before
    the data are made (for the memory check), None where the data come from the user's files
    (their size is known once read, and a finished run keeps its series in its checkpoint)."""

    config: type[TaskConfig]
    make: Callable[[TaskConfig, np.random.Generator, int], Dataset]
    features: Callable[[TaskConfig], int] | None = None

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def files(self) -> bool:
        return self.config.FILES
