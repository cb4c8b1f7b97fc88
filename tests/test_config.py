from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser

from moex.cli import CONF_DIR, _override_variants, register_configs, typed
from moex.config import Config
from moex.data import load_task
from moex.jobs import phase1_cache

TASKS = sorted(p.stem for p in (Path(CONF_DIR) / "task").glob("*.yaml"))


@pytest.fixture(scope="module", autouse=True)
def _schema():
    register_configs()


@pytest.mark.parametrize("task", TASKS)
def test_every_task_config_composes(task, tmp_path):
    overrides = [f"task={task}"] + ([f"task.path={tmp_path}/x.csv"] if task == "csv" else [])
    if task == "csv":
        (tmp_path / "x.csv").write_text("0.1 0.2\n" * 20)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = typed(compose("config", overrides=overrides))
    assert isinstance(cfg, Config)
    assert cfg.task.name == task
    data = load_task(cfg)
    if task == "csv":  # the file's own data, one series
        np.testing.assert_array_equal(data.series, np.full((1, 20, 2), [0.1, 0.2]))
    else:
        assert data.series.shape[:2] == (cfg.task.num_series, cfg.task.length)


def test_paper_settings_of_lissajous2():
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = typed(compose("config", overrides=["task=lissajous2"]))
    assert (cfg.model.num_experts, cfg.model.delay, cfg.model.sigma_min) == (2, 1, 0.05)
    assert (cfg.model.experts.context_size, cfg.model.gating.context_size) == (10, 15)
    assert (cfg.model.experts.epsilon, cfg.model.gating.epsilon) == (0.2, 0.04)
    assert (cfg.train.experts.steps, cfg.train.gating.steps) == (30000, 10000)
    assert cfg.train.experts.gate_prior_std == 10.0 and cfg.train.gating.adaptive_lr


def test_sweep_overrides_are_validated_value_by_value():
    variants = _override_variants(["task.switch_prob=0.5,0.25", "num_runs=2", "seed=1,2"])
    assert ["task.switch_prob=0.5", "num_runs=2", "seed=1"] in variants
    assert ["task.switch_prob=0.25", "num_runs=2", "seed=1"] in variants
    assert ["task.switch_prob=0.5", "num_runs=2", "seed=2"] in variants
    assert len(variants) == 3


EXPERIMENTS = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))


def sweep_values(key: str, values) -> list[str]:
    """The values a sweeper param expands to, as Hydra parses them (lists, `range(...)`)."""
    override = OverridesParser.create().parse_override(f"{key}={values}")
    return list(override.sweep_string_iterator()) if override.is_sweep_override() else [str(values)]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes_with_each_sweep_value(experiment):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        base = compose("config", overrides=[f"experiment={experiment}"],
                       return_hydra_config=True)
        params = base.hydra.sweeper.params or {}
        variants = [[f"experiment={experiment}"]] + [
            [f"experiment={experiment}", f"{key}={value}"]
            for key, values in params.items() for value in sweep_values(key, values)]
        for overrides in variants:
            cfg = typed(compose("config", overrides=overrides))
            assert isinstance(cfg, Config)
            load_task(cfg)


CACHED = [e for e in EXPERIMENTS
          if "cache_dir:" in (Path(CONF_DIR) / "experiment" / f"{e}.yaml").read_text()]


@pytest.mark.parametrize("experiment", CACHED)
def test_cached_sweeps_vary_phase1_settings_fastest(experiment):
    """In a sweep that caches phase 1, every key listed before the last phase-1 key leaves the
    cache file unchanged, so parallel neighbouring jobs never train the same phase 1 twice."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        base = compose("config", overrides=[f"experiment={experiment}"],
                       return_hydra_config=True)
        params = dict(base.hydra.sweeper.params or {})
        changes = []
        for key, values in params.items():
            paths = {phase1_cache(typed(compose(
                "config", overrides=[f"experiment={experiment}", f"{key}={v}"])))
                for v in sweep_values(key, values)}
            changes.append(len(paths) > 1)
    assert True in changes  # the grid does contain phase-1 settings
    first_phase1 = changes.index(True)
    assert all(changes[first_phase1:]), f"{experiment}: order {list(params)}"
