"""moex.resume: a checkpoint's config rebuilt as it was written (by this version or an older
one), and continued only by the config that wrote it (its evaluation settings aside)."""

import dataclasses

import pytest
import torch

from moex import checkpoint
from moex.config import Config
from moex.errors import ConfigError
from moex.resume import check_same_training, config_from_dict, open_checkpoint
from moex.tasks import task_config
from moex.tasks.lissajous import Lissajous2Config
from moex.tasks.reber import ReberConfig


def test_checkpoint_configs_with_old_key_names_still_load():
    """Run folders written before `time_constant` became `epsilon` (and `dtype` `precision`)."""
    old = {"dtype": "float32", "model": {"experts": {"context_size": 7, "time_constant": 0.3},
                                         "gating": {"time_constant": 0.05}}}
    cfg = config_from_dict(old)
    assert (cfg.model.experts.epsilon, cfg.model.gating.epsilon) == (0.3, 0.05)
    assert cfg.model.experts.context_size == 7 and cfg.precision == "float32"
    assert isinstance(cfg.task, Lissajous2Config)  # the default task


def test_a_checkpoint_holding_every_tasks_keys_loads_as_its_own_task():
    """Checkpoints written before each task had its own config class hold all tasks' keys."""
    every = {"name": "reber", "num_series": 4, "length": 500, "num_test_series": 4,
             "period": 25.0, "switch_prob": 0.5, "transition_rule": "paper", "choice_prob": 0.3,
             "burn_in": 100, "primitives": [], "transition": [], "path": "", "labels": "",
             "columns": [], "scale": "none", "data_seed": -1}
    cfg = config_from_dict({"task": every, "num_runs": 3})
    assert cfg.task == ReberConfig(num_series=4, length=500, num_test_series=4, choice_prob=0.3)
    assert dataclasses.asdict(config_from_dict(dataclasses.asdict(cfg))) == \
        dataclasses.asdict(cfg)  # what this version writes reads back the same
    with pytest.raises(ConfigError, match="task.name='nope' is unknown"):
        config_from_dict({"task": {**every, "name": "nope"}})


def test_only_the_config_that_wrote_a_checkpoint_continues_it(tmp_path):
    cfg = Config(task=task_config("lissajous2", num_series=2, length=40), num_runs=2)
    saved = dataclasses.asdict(cfg)
    check_same_training(saved, cfg, tmp_path)
    other = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, num_samples=3))
    check_same_training(saved, other, tmp_path)  # evaluation settings may change
    other = dataclasses.replace(cfg, task=task_config("lissajous2", num_series=2, length=40,
                                                      switch_prob=0.25))
    with pytest.raises(ConfigError, match=r"was trained with task.switch_prob=0.5, not 0.25; "
                                          r"use another output folder"):
        check_same_training(saved, other, tmp_path / "checkpoint.pt")
    other = dataclasses.replace(cfg, task=task_config("reber", num_series=2, length=40))
    with pytest.raises(ConfigError, match="was trained with task.name=lissajous2, not reber"):
        check_same_training(saved, other, tmp_path)


def test_a_new_folder_has_no_checkpoint_and_a_written_one_is_checked(tmp_path):
    cfg = Config(task=task_config("lissajous2", num_series=1, length=5), num_runs=1)
    assert open_checkpoint(cfg, tmp_path) is None
    record = checkpoint.Checkpoint(dataclasses.asdict(cfg), "experts",
                                   torch.zeros(1, 5, 2), torch.zeros(1, 5, dtype=torch.int64))
    record.save(tmp_path / checkpoint.NAME)
    assert open_checkpoint(cfg, tmp_path).phase == "experts"
    with pytest.raises(ConfigError, match="was trained with seed=0, not 1"):
        open_checkpoint(dataclasses.replace(cfg, seed=1), tmp_path)
