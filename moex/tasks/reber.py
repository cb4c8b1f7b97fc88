"""The ergodic Reber automaton of the preliminary experiment (paper Sec. 3.1, Fig. 2)."""

from dataclasses import dataclass

import numpy as np

from moex.errors import check, check_range
from moex.tasks.base import Dataset, Task, TaskConfig

SYMBOLS = ("T", "P", "S", "X", "V", "E", "B")

# state -> ((symbol, next state) of the first option, (symbol, next state) of the second)
AUTOMATON = {
    0: (("T", 1), ("P", 2)),
    1: (("S", 1), ("X", 3)),
    2: (("T", 2), ("V", 4)),
    3: (("X", 2), ("S", 5)),
    4: (("P", 3), ("V", 5)),
    5: (("E", 6), ("E", 6)),
    6: (("B", 0), ("B", 0)),
}


def generate_reber(length: int, burn_in: int, choice_prob: float,
                   rng: np.random.Generator) -> np.ndarray:
    """Symbol indices (length,) of one walk, after discarding `burn_in` symbols from state 0.

    The first option is taken with probability `choice_prob` (1/2 in the paper).
    """
    state, out = 0, []
    while len(out) < burn_in + length:
        option = 0 if rng.random() < choice_prob else 1
        symbol, state = AUTOMATON[state][option]
        out.append(SYMBOLS.index(symbol))
    return np.array(out[burn_in:], dtype=np.int64)


def _emitted(states, s) -> set:
    """The states reached from `states` by emitting symbol index `s`; none for an index beyond
    the grammar's symbols (`eval.symbol_rule=threshold` gives index 7 to "no gate above 0.5")."""
    name = SYMBOLS[s] if 0 <= s < len(SYMBOLS) else None
    return {nxt for st in states for sym, nxt in AUTOMATON[st] if sym == name}


def accepts(symbols: np.ndarray) -> bool:
    """Whether some start state of the automaton emits exactly this symbol sequence."""
    states = set(AUTOMATON)
    for s in symbols:
        states = _emitted(states, s)
        if not states:
            return False
    return True


def violations(symbols: np.ndarray) -> np.ndarray:
    """(T,) bool: steps whose symbol cannot follow the recent history (paper Fig. 4, red labels).

    The automaton state is tracked as a set of possible states and restarted after a violation
    (from every state, or from the states that emit the symbol when it is a grammar symbol).
    """
    bad = np.zeros(len(symbols), dtype=bool)
    states = set(AUTOMATON)
    for n, s in enumerate(symbols):
        nxt = _emitted(states, s)
        if not nxt:
            bad[n] = True
            nxt = _emitted(AUTOMATON, s) or set(AUTOMATON)
        states = nxt
    return bad


@dataclass
class ReberConfig(TaskConfig):
    """Walks of the automaton; the first of two paths with `choice_prob` (1/2 in the paper)."""

    name: str = "reber"
    choice_prob: float = 0.5
    burn_in: int = 100  # symbols discarded from the start state

    def __post_init__(self):
        super().__post_init__()
        check_range("task.choice_prob", self.choice_prob, 0.0, 1.0)
        check(self.burn_in >= 0, f"task.burn_in={self.burn_in} must be >= 0")


def _walks(cfg: ReberConfig, rng, min_length) -> Dataset:
    def sample(count):
        labels = np.stack([generate_reber(cfg.length, cfg.burn_in, cfg.choice_prob, rng)
                           for _ in range(count)])
        series = np.zeros(labels.shape + (0,))
        return series, labels, np.eye(len(SYMBOLS))[labels]

    common = dict(symbol_names=list(SYMBOLS), symbol_of=np.arange(len(SYMBOLS)),
                  violations=violations)
    test = None
    if cfg.num_test_series:
        s, lab, g = sample(cfg.num_test_series)
        test = Dataset(s, lab, **common, gate_targets=g)
    s, lab, g = sample(cfg.num_series)
    return Dataset(s, lab, **common, gate_targets=g, test=test)


TASKS = (Task(ReberConfig, _walks, lambda cfg: 0),)
