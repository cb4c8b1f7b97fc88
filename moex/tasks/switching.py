"""Markov switching between periodic primitives (paper Sec. 3.2).

One phase φ_n = 2πn/P runs for the whole series and never jumps; the active primitive draws its
point from the current phase, and a switch can happen only once the active primitive has run its
length (a float count of steps whose remainder is kept), so every transition is continuous.
"""

from dataclasses import dataclass

import numpy as np

from moex.errors import check, check_range
from moex.tasks.base import Dataset, TaskConfig


@dataclass(frozen=True)
class Primitive:
    """A Lissajous primitive y_j(φ) = amplitude_j · sin(frequency_j · φ + phase_j) + offset_j.

    `length` is in periods P, `name` is its symbol (quarters of one curve share a name).
    """

    name: str
    amplitude: tuple[float, ...]
    frequency: tuple[float, ...]
    phase: tuple[float, ...]
    offset: tuple[float, ...]
    length: float = 1.0

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        """Points (..., D) of the curve at phases `phi` (...)."""
        a, f, p, o = (np.asarray(v, dtype=float) for v in
                      (self.amplitude, self.frequency, self.phase, self.offset))
        return a * np.sin(f * np.asarray(phi)[..., None] + p) + o


def check_transition(transition: np.ndarray, num_primitives: int, key: str) -> np.ndarray:
    """Validate a row-stochastic (K, K) matrix, naming `key` in the error."""
    transition = np.asarray(transition, dtype=float)
    check(transition.shape == (num_primitives, num_primitives),
          f"{key} must be a {num_primitives}x{num_primitives} matrix, got shape "
          f"{transition.shape}")
    for i, row in enumerate(transition):
        for p in row:
            check_range(f"{key}[{i}]", float(p), 0.0, 1.0)
        check(abs(row.sum() - 1.0) < 1e-9, f"{key}[{i}] sums to {row.sum():g}, not 1")
    return transition


def generate_switching(primitives: list[Primitive], transition: np.ndarray, length: int,
                       period: float, *, rng: np.random.Generator,
                       initial: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sample one series of Markov switching between primitives.

    Args:
        primitives: the K primitives; all must have the same number of features D.
        transition: (K, K) row-stochastic matrix, row = current primitive.
        length: number of time steps T.
        period: P, steps per full turn of the phase.
        rng: the only source of randomness.
        initial: index of the first primitive; uniform at random when None.

    Returns:
        series (T, D) and labels (T,), the index of the active primitive at each step.
    """
    num_primitives = len(primitives)
    current = int(rng.integers(num_primitives)) if initial is None else initial
    phi = 2.0 * np.pi * np.arange(length) / period
    series = np.empty((length, len(primitives[0].amplitude)))
    labels = np.empty(length, dtype=np.int64)
    counter = 0.0
    for n in range(length):
        series[n] = primitives[current](phi[n])
        labels[n] = current
        counter += 1.0
        steps = primitives[current].length * period
        if counter >= steps - 1e-9:
            counter -= steps
            current = int(rng.choice(num_primitives, p=transition[current]))
    return series, labels


def symbol_table(primitives: list[Primitive]) -> tuple[list[str], np.ndarray]:
    """Distinct symbol names and the (K,) map from primitive index to symbol index."""
    names = list(dict.fromkeys(p.name for p in primitives))
    return names, np.array([names.index(p.name) for p in primitives], dtype=np.int64)


def prototype_points(primitives: list[Primitive], samples: int = 64) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """Points sampled along every primitive, (P, D), and each point's symbol index (P,).

    A generated output is labelled with the symbol of its nearest prototype point.
    """
    _, symbol_of = symbol_table(primitives)
    points, labels = [], []
    for k, prim in enumerate(primitives):
        phi = 2 * np.pi * np.linspace(0.0, 1.0, samples, endpoint=False)
        points.append(prim(phi))
        labels.append(np.full(samples, symbol_of[k]))
    return np.concatenate(points), np.concatenate(labels)


def switching_dataset(primitives: list[Primitive], transition: np.ndarray, cfg: TaskConfig,
                      rng: np.random.Generator, initial: int | None = None) -> Dataset:
    """The training and held-out series of a switching task (`cfg.period` steps per period)
    with its symbols and prototype points."""
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
