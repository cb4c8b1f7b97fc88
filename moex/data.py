"""The data a config trains on: the task's data set, generated once per process, checked against
the model and the memory a training needs; held-out series; defaults the data settle
(`model.sigma_min=auto`); generated signals in the data's own units."""

import dataclasses
import logging

import numpy as np

from moex import budget
from moex.config import Config
from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig
from moex.errors import check
from moex.tasks import TASKS, Dataset, make_task, planned_shape
from moex.tasks.scaling import WINDOW, noise_floor

log = logging.getLogger(__name__)


# generated data sets of this process by their settings, oldest first; the oldest go when their
# arrays exceed _BUILT_BYTES
_BUILT: dict[tuple, Dataset] = {}
_BUILT_BYTES = 256 * 2**20


def _nbytes(dataset: Dataset | None) -> int:
    if dataset is None:
        return 0
    arrays = (dataset.series, dataset.labels, dataset.gate_targets)
    return sum(a.nbytes for a in arrays if a is not None) + _nbytes(dataset.test)


def _generated(cfg: Config) -> Dataset:
    """`make_task` for the config, built once per process when the task is generated (not read
    from files): `moex train` checks its config on the data (`cli.validate`) and then trains on
    the same data set; a packed sweep checks every job's and then trains them all. Nothing
    changes a `Dataset` in place."""
    if TASKS[cfg.task.name].files:  # files may change between runs: read afresh
        return make_task(cfg.task, cfg.seed, min_length=cfg.model.delay + 2)
    key = (repr(cfg.task), cfg.seed, cfg.model.delay)
    if key not in _BUILT:
        _BUILT[key] = make_task(cfg.task, cfg.seed, min_length=cfg.model.delay + 2)
        while len(_BUILT) > 1 and sum(map(_nbytes, _BUILT.values())) > _BUILT_BYTES:
            del _BUILT[next(iter(_BUILT))]
    return _BUILT[key]


def held_out(cfg: Config, dataset: Dataset) -> Dataset:
    """The dataset with `eval.test_series` held-out series in place of the task's own: the task
    drawn again with that many (it draws its held-out series first, one after another, so the
    first of them are the run's own; the training series of that draw are not used), built once
    a process as the task itself is (`_generated`)."""
    count = cfg.eval.test_series
    if not count or count == cfg.task.num_test_series:
        return dataset
    check(not TASKS[cfg.task.name].files, f"eval.test_series={count}: task {cfg.task.name} is "
                                          f"a user's files, which have no held-out series to "
                                          f"draw more of")
    more = _generated(dataclasses.replace(cfg, task=dataclasses.replace(
        cfg.task, num_test_series=count)))
    return dataclasses.replace(dataset, test=more.test)


def load_task(cfg: Config) -> Dataset:
    """The task's data, checked against the model config and the memory a training on it needs
    (a `ConfigError` if they disagree, before generating data that could not be trained on).
    `model.sigma_min=auto` is replaced in `cfg` by the value the data give."""
    check(cfg.plot.run < cfg.num_runs,
          f"plot.run={cfg.plot.run} is outside [-1, {cfg.num_runs - 1}] (num_runs={cfg.num_runs})")
    shape = planned_shape(cfg.task)
    if shape is not None:
        budget.check_train(cfg, *shape)
    dataset = _generated(cfg)
    if shape is None:
        budget.check_train(cfg, *dataset.series.shape)
    K, names = cfg.model.num_experts, dataset.symbol_names
    cfg.model = settled(cfg.model, dataset.series)  # before anything trains on the data
    if dataset.gate_targets is not None:  # symbolic: one gate per symbol
        check(K == len(names), f"model.num_experts={K} must equal the {len(names)} symbols of "
                               f"task {cfg.task.name} ({', '.join(names)})")
    elif dataset.prototypes is not None:  # primitives: at least one expert each
        check(K >= len(names), f"model.num_experts={K} is fewer than the {len(names)} "
                               f"primitives of task {cfg.task.name} ({', '.join(names)}); use "
                               f"model.num_experts={len(names)} or more")
    return held_out(cfg, dataset)


def settled(model: ModelConfig, series: np.ndarray) -> ModelConfig:
    """`model` with `sigma_min=auto` replaced by the value the series (S, T, D) give, said in
    the log; `model` itself otherwise."""
    if model.sigma_min != "auto":
        return model
    model = dataclasses.replace(model, sigma_min=noise_floor(series))
    log.info("model.sigma_min=auto: σ̄ = %.4g (half the 10th percentile of the one-step "
             "change's RMS over %d-step windows)", model.sigma_min, WINDOW)
    return model


def in_data_units(samples: dict, dataset: Dataset) -> dict:
    """Generated signals (outputs, closed_outputs) mapped back to the data's own units where
    the data was scaled (`task.scale=auto`); metrics stay in the model's units."""
    return {k: dataset.scale.to_data(v) if k in ("outputs", "closed_outputs") else v
            for k, v in samples.items()}


def warn_ignored(cfg: Config, dataset: Dataset) -> None:
    """Keys the task does not use are named as ignored, not silently dropped: task.num_series of
    a csv task (its files decide), and every train.experts key set away from its default where
    the task has no signal (Reber: symbols only; no experts, no phase 1)."""
    S = len(dataset.series)
    if TASKS[cfg.task.name].files and cfg.task.num_series not in (0, S):
        log.warning("task.num_series=%d ignored: task %s trains on every series its files hold "
                    "(%d)", cfg.task.num_series, cfg.task.name, S)
    if dataset.series.shape[-1] > 0:
        return
    default = dataclasses.asdict(ExpertPhaseConfig())
    changed = [f"train.experts.{k}={v}" for k, v in dataclasses.asdict(cfg.train.experts).items()
               if v != default[k]]
    if changed:
        log.warning("%s ignored: task %s has no signal for experts, so phase 1 does not run",
                    ", ".join(changed), cfg.task.name)
