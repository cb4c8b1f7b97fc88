"""Training data: deterministic task generators behind a name registry (paper Sec. 3).

A task is one module: its config (a `TaskConfig` subclass whose `name` names it), the function
that makes its `Dataset` and its `Task` entries in a tuple `TASKS`; the module's line below adds
it to the registry, and a YAML in conf/task/ to the command line (`typed_config` types its keys
by the task it names). Every task returns a `Dataset`: series (S, T, D), the true primitive label
of every step, and everything that differs between tasks when a run is evaluated: the rule that
turns generated steps into symbols, the length of a primitive, the switching law, a grammar to
check.
"""

import dataclasses
import difflib

import numpy as np
from omegaconf import OmegaConf

from moex.errors import check, closest_first
from moex.tasks import files, lissajous, primitives, reber
from moex.tasks.base import Dataset, Task, TaskConfig, user_data
from moex.tasks.scaling import Scale

TASKS: dict[str, Task] = {task.name: task for module in (lissajous, primitives, reber, files)
                          for task in module.TASKS}


def task_class(name: str) -> type[TaskConfig]:
    """The config class of task `name` (a `ConfigError` naming the tasks for an unknown one)."""
    check(name in TASKS, f"task.name={name!r} is unknown; choose one of "
                         f"{', '.join(closest_first(name, TASKS))}")
    return TASKS[name].config


def own_keys(task: dict, default: str) -> dict:
    """The keys of `task` (a plain dict) that the task it names (else `default`) has: a dict
    written before each task had its own config holds every task's keys."""
    names = {f.name for f in dataclasses.fields(task_class(task.get("name", default)))}
    return {k: v for k, v in task.items() if k in names}


def check_task(cfg: TaskConfig) -> None:
    """A known task whose config is its own class (`task.name=reber` given to another task's
    keys is refused here: choose the task with `task=reber`)."""
    own = task_class(cfg.name)
    check(isinstance(cfg, own), f"task.name={cfg.name!r} with the keys of another task "
                                f"({type(cfg).__name__}); choose the task with task={cfg.name}")


def task_config(name: str, **keys) -> TaskConfig:
    """The config of task `name` with `keys` (a `ConfigError` for an unknown task or key)."""
    own = task_class(name)
    unknown = sorted(set(keys) - {f.name for f in dataclasses.fields(own)})
    check(not unknown, f"task.{unknown[0] if unknown else ''} is not a key of task {name}")
    return own(**keys)


def typed_config(schema: type, data: dict):
    """`data` (plain: as Hydra composed it, or as a checkpoint stores it) as a `schema` dataclass
    (`Config` or a subclass) whose `task` is the config class of the task it names (default:
    the schema's); an unknown task or key is refused in one line naming the task's keys."""
    task = dict(data.get("task") or {})
    default = next(f for f in dataclasses.fields(schema) if f.name == "task").default_factory
    own = task_class(task.get("name", default.name))
    keys = [f.name for f in dataclasses.fields(own)]
    unknown = sorted(set(task) - set(keys))
    if unknown:
        ranked = difflib.get_close_matches(unknown[0], keys, n=len(keys), cutoff=0)
        allowed = ", ".join(f"task.{k}" for k in ranked + sorted(set(keys) - set(ranked)))
        check(False, f"unknown key task.{unknown[0]} (task {own.name}); allowed keys: {allowed}")
    node = OmegaConf.structured(schema)
    node.task = OmegaConf.structured(own)
    return OmegaConf.to_object(OmegaConf.merge(node, {**data, "task": task}))


def planned_shape(cfg: TaskConfig) -> tuple[int, int, int] | None:
    """(S, T, D) of the training data a generated task will have, known before generating it
    (None for files: their size is known once read)."""
    check_task(cfg)
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
    check_task(cfg)
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


__all__ = ["TaskConfig", "Dataset", "Scale", "Task", "check_task", "make_task", "planned_shape",
           "own_keys", "task_class", "task_config", "task_of_run", "typed_config", "user_data",
           "TASKS"]
