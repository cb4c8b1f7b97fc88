"""The paper's Lissajous tasks (Sec. 3.2): two circles touching at the origin and the nine
curves around a central circle, as the authors' C tools generate them, on the switching engine."""

import math
from dataclasses import dataclass

import numpy as np

from moex.errors import check, check_positive, check_range
from moex.tasks.base import Task, TaskConfig
from moex.tasks.switching import Primitive, switching_dataset

HALF_PI = math.pi / 2


def two_circles() -> list[Primitive]:
    """L and R: circles of radius 0.4 centred at (∓0.4, 0), touching at the origin."""
    return [
        Primitive("L", (0.4, 0.4), (1, 1), (HALF_PI, 0.0), (-0.4, 0.0)),
        Primitive("R", (-0.4, 0.4), (1, 1), (HALF_PI, 0.0), (0.4, 0.0)),
    ]


def two_circles_transition(switch_prob: float) -> np.ndarray:
    """Stay with 1 − P, switch with P (paper Table 2)."""
    return np.array([[1 - switch_prob, switch_prob], [switch_prob, 1 - switch_prob]])


def nine_curves() -> list[Primitive]:
    """Quarters 0-3 of the central circle C, then LL, LS, B0, B8, RL, RS, T0, T8."""
    quarters = [Primitive("C", (-0.2, 0.2), (1, 1), (0.0, HALF_PI), (0.0, 0.0), 0.25)] * 4
    outer = [
        Primitive("LL", (0.32, 0.32), (1, 1), (0.0, HALF_PI), (-0.52, 0.0)),
        Primitive("LS", (0.16, 0.16), (1, 1), (0.0, HALF_PI), (-0.36, 0.0)),
        Primitive("B0", (0.32, -0.32), (1, 1), (0.0, HALF_PI), (0.0, -0.52)),
        Primitive("B8", (0.24, -0.32), (2, 1), (0.0, HALF_PI), (0.0, -0.52)),
        Primitive("RL", (0.32, 0.32), (1, 1), (0.0, HALF_PI), (0.52, 0.0)),
        Primitive("RS", (0.16, 0.16), (1, 1), (0.0, HALF_PI), (0.36, 0.0)),
        Primitive("T0", (0.32, -0.32), (1, 1), (0.0, HALF_PI), (0.0, 0.52)),
        Primitive("T8", (0.24, -0.32), (2, 1), (0.0, HALF_PI), (0.0, 0.52)),
    ]
    return quarters + outer


def nine_curves_transition(rule: str) -> np.ndarray:
    """(12, 12) transition matrix of the nine-curve task.

    `paper`: keep the current curve or move on with equal probability (Fig. 11 caption) — a
    quarter of C goes on to the next quarter with 1/2 or to each of the two outer curves at its
    end point with 1/4; an outer curve repeats with 1/2, or moves to its sibling or back to the
    next quarter of C with 1/4 each. `mregn`: the C code's 0.8/0.1/0.1 and 0.4/0.4/0.2.
    """
    keep, branch, repeat, sibling, back = {
        "paper": (0.5, 0.25, 0.5, 0.25, 0.25),
        "mregn": (0.8, 0.1, 0.4, 0.4, 0.2),
    }[rule]
    p = np.zeros((12, 12))
    for k in range(4):
        first, second = 4 + 2 * k, 5 + 2 * k  # the outer pair at the end point of quarter k
        p[k, (k + 1) % 4] = keep
        p[k, first] = p[k, second] = branch
        for this, other in ((first, second), (second, first)):
            p[this, this], p[this, other], p[this, (k + 1) % 4] = repeat, sibling, back
    return p


@dataclass
class Lissajous2Config(TaskConfig):
    """Two circles (Table 2): switch at the origin with probability `switch_prob`."""

    name: str = "lissajous2"
    period: float = 25.0  # P, steps per Lissajous period
    switch_prob: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        check_positive("task.period", self.period)
        check_range("task.switch_prob", self.switch_prob, 0.0, 1.0)


@dataclass
class Lissajous9Config(TaskConfig):
    """Nine curves (Table 1); `transition_rule`: the paper's or the C tools' (mregn)."""

    name: str = "lissajous9"
    period: float = 25.0  # P, steps per Lissajous period
    transition_rule: str = "paper"

    def __post_init__(self):
        super().__post_init__()
        check_positive("task.period", self.period)
        check(self.transition_rule in ("paper", "mregn"),
              f"task.transition_rule={self.transition_rule!r}; choose paper or mregn")


def _two(cfg: Lissajous2Config, rng, min_length):
    return switching_dataset(two_circles(), two_circles_transition(cfg.switch_prob), cfg, rng)


def _nine(cfg: Lissajous9Config, rng, min_length):
    return switching_dataset(nine_curves(), nine_curves_transition(cfg.transition_rule), cfg,
                             rng, initial=0)


TASKS = (Task(Lissajous2Config, _two, lambda cfg: 2), Task(Lissajous9Config, _nine, lambda cfg: 2))
