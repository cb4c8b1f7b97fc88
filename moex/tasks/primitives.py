"""Markov switching between primitives the user lists (task `markov_primitives`): each a
Lissajous curve given by its amplitude, frequency, phase and offset per dimension, switched by
the user's transition matrix on the switching engine of the paper's tasks (Sec. 3.2)."""

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from moex.errors import check, check_positive
from moex.tasks.base import Task, TaskConfig
from moex.tasks.switching import Primitive, check_transition, switching_dataset


@dataclass
class MarkovPrimitivesConfig(TaskConfig):
    """`primitives`: mappings of amplitude, frequency, phase, offset (and name, length in
    periods); `transition`: the (K, K) matrix between them."""

    name: str = "markov_primitives"
    period: float = 25.0  # P, steps per period
    primitives: list[Any] = field(default_factory=list)
    transition: list[Any] = field(default_factory=list)

    def __post_init__(self):
        super().__post_init__()
        check_positive("task.period", self.period)


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


def _switching(cfg: MarkovPrimitivesConfig, rng, min_length):
    check(len(cfg.primitives) >= 1, "task.primitives is empty: list at least one primitive")
    primitives = [_primitive_from_dict(p, i) for i, p in enumerate(cfg.primitives)]
    dims = {len(p.amplitude) for p in primitives}
    check(len(dims) == 1, f"task.primitives have different dimensions {sorted(dims)}")
    transition = check_transition(np.array([list(r) for r in cfg.transition], dtype=float),
                                  len(primitives), "task.transition")
    return switching_dataset(primitives, transition, cfg, rng)



def _primitive_dims(cfg: MarkovPrimitivesConfig) -> int:
    return len(dict(cfg.primitives[0]).get("amplitude", ())) if cfg.primitives else 0


TASKS = (Task(MarkovPrimitivesConfig, _switching, _primitive_dims),)
