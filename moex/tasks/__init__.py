"""Training data: deterministic task generators behind a name registry (paper Sec. 3).

Every task returns a `Dataset`: series (S, T, D), the true primitive label of every step, and
everything that differs between tasks when a run is evaluated: the rule that turns generated
steps into symbols, the length of a primitive, the switching law, a grammar to check.
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from moex.errors import check, check_positive, check_range, closest_first
from moex.metrics.symbols import symbolize_argmax, symbolize_nearest
from moex.tasks import files, lissajous, reber
from moex.tasks.scaling import SCALES, Scale, fit_scale
from moex.tasks.switching import (
    Primitive,
    check_transition,
    generate_switching,
    prototype_points,
    symbol_table,
)


@dataclass
class TaskConfig:
    """Which task and its sizes. Keys a task does not use are ignored by it."""

    name: str = "lissajous2"
    num_series: int = 10  # the paper's NT
    length: int = 1000  # the paper's LT (0 for `csv`: the files' own length)
    num_test_series: int = 10  # held-out series from the same source
    period: float = 25.0  # P, steps per Lissajous period
    switch_prob: float = 0.5  # lissajous2: probability of switching curve at the origin
    transition_rule: str = "paper"  # lissajous9: paper | mregn
    choice_prob: float = 0.5  # reber: probability of the first of two paths
    burn_in: int = 100  # reber: symbols discarded from the start state
    primitives: list[Any] = field(default_factory=list)  # markov_primitives
    transition: list[Any] = field(default_factory=list)  # markov_primitives
    path: str = ""  # csv: file, glob or folder
    labels: str = ""  # csv: a column of per-step integer labels, or files of them (scored)
    columns: list[str] = field(default_factory=list)  # csv: columns by header name (all if [])
    scale: str = "none"  # csv: none (data must lie in [-1, 1]) | auto (each feature linearly)
    data_seed: int = -1  # the data's own seed; -1: the run's `seed` (data and networks together)

    def __post_init__(self):
        check(self.name in TASKS, f"task.name={self.name!r} is unknown; choose one of "
                                  f"{', '.join(closest_first(self.name, TASKS))}")
        files = TASKS[self.name].files  # 0: every series and step the files hold
        least = 0 if files else 1
        check(self.num_series >= least, f"task.num_series={self.num_series} must be >= {least}")
        check(self.num_test_series >= 0,
              f"task.num_test_series={self.num_test_series} must be >= 0")
        check(self.length >= 0 if files else self.length >= 3,
              f"task.length={self.length} must be >= 3")
        check_positive("task.period", self.period)
        check_range("task.switch_prob", self.switch_prob, 0.0, 1.0)
        check_range("task.choice_prob", self.choice_prob, 0.0, 1.0)
        check(self.transition_rule in ("paper", "mregn"),
              f"task.transition_rule={self.transition_rule!r}; choose paper or mregn")
        check(self.burn_in >= 0, f"task.burn_in={self.burn_in} must be >= 0")
        check(self.scale in SCALES, f"task.scale={self.scale!r}; choose none or auto")
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


def _switching(primitives: list[Primitive], transition: np.ndarray, cfg: TaskConfig,
               rng: np.random.Generator, initial: int | None = None) -> Dataset:
    def sample(count):
        pairs = [generate_switching(primitives, transition, cfg.length, cfg.period, rng=rng,
                                    initial=initial)
                 for _ in range(count)]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])

    names, symbol_of = symbol_table(primitives)
    points, point_symbols = prototype_points(primitives)
    common = dict(symbol_names=names, symbol_of=symbol_of, transition=transition,
                  prototypes=points, prototype_symbols=point_symbols, period=cfg.period)
    test = Dataset(*sample(cfg.num_test_series), **common) if cfg.num_test_series else None
    return Dataset(*sample(cfg.num_series), **common, test=test)


def _lissajous2(cfg, rng, min_length):
    return _switching(lissajous.two_circles(), lissajous.two_circles_transition(cfg.switch_prob),
                      cfg, rng)


def _lissajous9(cfg, rng, min_length):
    return _switching(lissajous.nine_curves(),
                      lissajous.nine_curves_transition(cfg.transition_rule), cfg, rng, initial=0)


def _primitive_from_dict(item: Any, index: int) -> Primitive:
    key = f"task.primitives[{index}]"
    check(isinstance(item, dict) or hasattr(item, "keys"),
          f"{key} must be a mapping with amplitude, frequency, phase, offset")
    item = dict(item)
    unknown = set(item) - {"name", "amplitude", "frequency", "phase", "offset", "length"}
    check(not unknown, f"{key} has unknown keys {sorted(unknown)}")
    check("amplitude" in item, f"{key}.amplitude is required")
    dims = len(item["amplitude"])
    vectors = {}
    for name in ("amplitude", "frequency", "phase", "offset"):
        value = tuple(float(v) for v in item.get(name, [1.0 if name == "frequency" else 0.0] *
                                                 dims))
        check(len(value) == dims, f"{key}.{name} has {len(value)} entries, expected {dims}")
        vectors[name] = value
    length = float(item.get("length", 1.0))
    check_positive(f"{key}.length", length)
    return Primitive(str(item.get("name", f"p{index}")), length=length, **vectors)


def _markov_primitives(cfg, rng, min_length):
    check(len(cfg.primitives) >= 1, "task.primitives is empty: list at least one primitive")
    primitives = [_primitive_from_dict(p, i) for i, p in enumerate(cfg.primitives)]
    dims = {len(p.amplitude) for p in primitives}
    check(len(dims) == 1, f"task.primitives have different dimensions {sorted(dims)}")
    transition = check_transition(np.array([list(r) for r in cfg.transition], dtype=float),
                                  len(primitives), "task.transition")
    return _switching(primitives, transition, cfg, rng)


def _reber(cfg, rng, min_length):
    def sample(count):
        labels = np.stack([reber.generate_reber(cfg.length, cfg.burn_in, cfg.choice_prob, rng)
                           for _ in range(count)])
        series = np.zeros(labels.shape + (0,))
        return series, labels, np.eye(len(reber.SYMBOLS))[labels]

    common = dict(symbol_names=list(reber.SYMBOLS), symbol_of=np.arange(len(reber.SYMBOLS)),
                  violations=reber.violations)
    test = None
    if cfg.num_test_series:
        s, lab, g = sample(cfg.num_test_series)
        test = Dataset(s, lab, **common, gate_targets=g)
    s, lab, g = sample(cfg.num_series)
    return Dataset(s, lab, **common, gate_targets=g, test=test)


def _csv(cfg, rng, min_length):
    series, labels = files.load_series(cfg.path, cfg.length, min_length, cfg.columns,
                                       cfg.labels)
    series, scale = fit_scale(series, cfg.scale, f"task.path={cfg.path}")
    return user_data(series, scale, labels)


def user_data(series: np.ndarray, scale: Scale | None = None,
              labels: np.ndarray | None = None) -> Dataset:
    """A `Dataset` of a user's series (S, T, D) in model units, with their labels (S, T) where
    the user has them (-1: unknown); no symbols."""
    labels = -np.ones(series.shape[:2], dtype=np.int64) if labels is None else labels
    return Dataset(series, labels, symbol_names=[], symbol_of=np.zeros(0, dtype=np.int64),
                   scale=scale or Scale())


@dataclass(frozen=True)
class Task:
    """A task of the registry: `make(cfg, rng, min_length)` builds its `Dataset`; `features(cfg)`
    is D, known before the data are made (for the memory check), None where the data come from
    the user's files (`files`: read, not generated; their size is known once read, and a finished
    run keeps its series in its checkpoint)."""

    make: Callable[[TaskConfig, np.random.Generator, int], Dataset]
    features: Callable[[TaskConfig], int] | None = None
    files: bool = False


def _primitive_dims(cfg: TaskConfig) -> int:
    return len(dict(cfg.primitives[0]).get("amplitude", ())) if cfg.primitives else 0


# a new task: its generator above (or in a module of its own) and its entry here, and a YAML in
# conf/task/ for the command line
TASKS = {
    "lissajous2": Task(_lissajous2, lambda cfg: 2),
    "lissajous9": Task(_lissajous9, lambda cfg: 2),
    "markov_primitives": Task(_markov_primitives, _primitive_dims),
    "reber": Task(_reber, lambda cfg: 0),
    "csv": Task(_csv, files=True),
}


def planned_shape(cfg: TaskConfig) -> tuple[int, int, int] | None:
    """(S, T, D) of the training data a generated task will have, known before generating it
    (None for files: their size is known once read)."""
    task = TASKS[cfg.name]
    return None if task.files else (cfg.num_series, cfg.length, task.features(cfg))


def make_task(cfg: TaskConfig, seed: int, min_length: int = 3) -> Dataset:
    """Generate (or load) the task's data, deterministically given `seed` (or `cfg.data_seed`
    where it is set: then networks of other seeds train on the same data).

    Args:
        cfg: the task config; `cfg.name` selects the generator.
        seed: data seed; the same seed always gives the same data.
        min_length: shortest series the model can train on (delay + 2).

    Returns:
        the training `Dataset`, with the held-out series in `.test`.
    """
    seed = seed if cfg.data_seed < 0 else cfg.data_seed
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xDA7A]))
    task = TASKS[cfg.name]
    check(task.files or cfg.length >= min_length, f"task.length={cfg.length} is too short for "
                                                  f"model.delay: need at least {min_length} steps")
    return task.make(cfg, rng, min_length)


def task_of_run(cfg: TaskConfig, seed: int, series: np.ndarray, *, scale: Scale,
                min_length: int = 3, labels: np.ndarray | None = None) -> Dataset:
    """The data a finished run was trained on: regenerated from its seed where the task is
    generated (held-out series included), the series (in model units) and scale stored in its
    checkpoint where it came from files (they may have moved since), with their labels."""
    if TASKS[cfg.name].files:
        return user_data(series, scale, labels)
    return make_task(cfg, seed, min_length)


__all__ = ["TaskConfig", "Dataset", "Scale", "Task", "make_task", "planned_shape", "task_of_run",
           "user_data", "TASKS"]
