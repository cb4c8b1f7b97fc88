"""moex.budget: a command's memory estimated from its config and refused before any work when
it exceeds what the machine has, with the estimate, the limit and what to reduce."""

import pytest

from moex import budget
from moex.config import Config
from moex.errors import ConfigError
from moex.tasks import task_config


def test_the_estimate_grows_with_every_size_and_halves_in_float32():
    cfg = Config(num_runs=2)
    base = budget.train_bytes(cfg, 10, 1000, 2)
    assert base > 0
    assert budget.train_bytes(Config(num_runs=4), 10, 1000, 2) > 1.9 * base - base * 0.1
    assert budget.train_bytes(cfg, 10, 2000, 2) > base and budget.train_bytes(cfg, 20, 1000, 2) \
        > base
    half = budget.train_bytes(Config(num_runs=2, precision="float32"), 10, 1000, 2)
    assert half < base
    symbolic = Config(num_runs=2, task=task_config("reber"))  # no experts: no phase-1 histories
    assert budget.train_bytes(symbolic, 10, 1000, 0) < base


def test_beyond_the_available_memory_is_refused_with_the_estimate(monkeypatch):
    monkeypatch.setattr(budget, "available_bytes", lambda: 2 * budget.GIB)
    cfg = Config(num_runs=3)
    budget.check_train(cfg, 10, 1000, 2)  # a paper-sized run fits
    with pytest.raises(ConfigError, match=r"training 3 runs on 10 series x 10000000 steps needs "
                                          r"about .* GiB of memory, more than the 2 GiB "
                                          r"available; reduce num_runs"):
        budget.check_train(cfg, 10, 10**7, 2)
    with pytest.raises(ConfigError, match="generating 3 runs x 4 samples x 10000000000 steps"):
        budget.check_generate(cfg, 10**10, 4)
    cfg.eval.lyapunov_steps = 10**10
    with pytest.raises(ConfigError, match="reduce eval.num_samples or eval.lyapunov_steps"):
        budget.check_evaluate(cfg)


def test_the_available_memory_is_read_from_the_system():
    assert 0 < budget.available_bytes() < 2**50
