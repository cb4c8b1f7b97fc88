"""`train.experts.gate_prior_std=auto`: the pilot's ς trains exactly as that ς set by hand, is
written down, stated and reused on a rerun; bad values are refused in one line."""

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch

import moex
from moex.config import Config
from moex.errors import ConfigError
from moex.segment import PRIOR_GRID
from moex.tasks import make_task, task_config

MOEX = [sys.executable, "-c", "from moex.launch import main; main()"]


def _config(prior_std) -> Config:
    cfg = Config(task=task_config("csv"))
    cfg.train.experts.gate_prior_std, cfg.train.experts.pilot_steps = prior_std, 60
    return cfg


def test_the_pilots_choice_trains_as_that_prior_set_by_hand(caplog):
    """Two networks on two-Lissajous series: `auto` says its ς in the log, and its experts, β
    and gating network equal, bit for bit, a training with that ς given as a number."""
    data = make_task(task_config("lissajous2", num_series=3, length=150), seed=2)
    settings = dict(num_experts=2, expert_steps=40, gating_steps=5, num_runs=2)
    with caplog.at_level("INFO"):
        chosen = moex.fit(data.series, config=_config("auto"), **settings)
    prior_std = chosen.config.train.experts.gate_prior_std
    assert prior_std in PRIOR_GRID and f"ς = {prior_std:g} (the pilot's" in caplog.text
    by_hand = moex.fit(data.series, config=_config(prior_std), **settings)
    for mine, theirs in ((chosen.experts, by_hand.experts), (chosen.gating, by_hand.gating)):
        for key in mine:
            torch.testing.assert_close(mine[key], theirs[key], rtol=0, atol=0)
    torch.testing.assert_close(chosen.beta, by_hand.beta, rtol=0, atol=0)


def test_moex_train_writes_the_choice_states_it_and_reuses_it(tmp_path):
    """gate_prior.csv holds the grid's scores and one chosen ς, the run page and the saved
    config state it, and the same command again finds the finished run without a new pilot."""
    rng = np.random.default_rng(0)
    steps = np.arange(160)
    for i in range(2):
        phase = np.cumsum(np.where((steps // 40 + i) % 2, 0.6, 0.25))
        pd.DataFrame({"x": 0.5 * np.sin(phase) + rng.normal(0, 0.01, 160),
                      "y": 0.5 * np.cos(phase)}).to_csv(tmp_path / f"s{i}.csv", index=False)
    run_dir = tmp_path / "run"
    command = MOEX + ["train", "task=csv", f"task.path={tmp_path}", "num_runs=2",
                      "train.experts.steps=30", "train.gating.steps=5", "eval.enabled=false",
                      "train.experts.gate_prior_std=auto", "train.experts.pilot_steps=40",
                      f"hydra.run.dir={run_dir}"]
    first = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert first.returncode == 0, first.stderr
    table = pd.read_csv(run_dir / "gate_prior.csv")
    assert list(table["gate_prior_std"]) == list(PRIOR_GRID) and table["chosen"].sum() == 1
    prior_std = float(table.loc[table["chosen"], "gate_prior_std"].iloc[0])
    assert table["left_out_log_likelihood"].idxmax() == table["chosen"].idxmax()
    assert f"ς = {prior_std:g} (the β prior's scale, chosen from the data" in \
        (run_dir / "report.md").read_text()
    assert moex.load(run_dir).config.train.experts.gate_prior_std == prior_std
    again = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert again.returncode == 0, again.stderr
    assert "a pilot of" in first.stderr + first.stdout
    assert "a pilot of" not in again.stderr + again.stdout
    assert f"ς = {prior_std:g}" in again.stderr + again.stdout


@pytest.mark.parametrize("value, message", [
    (-1.0, "train.experts.gate_prior_std=-1.0 must be positive, or auto"),
    ("wide", "train.experts.gate_prior_std=wide must be positive, or auto"),
])
def test_a_bad_prior_is_refused_in_one_line(value, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        _config(value).train.__post_init__()


def test_auto_on_a_task_without_phase_1_is_refused(tmp_path):
    done = subprocess.run(MOEX + ["train", "task=reber", "train.experts.gate_prior_std=auto",
                                  f"hydra.run.dir={tmp_path}/run"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "gate_prior_std=auto needs phase 1; task reber has symbols only" in done.stderr
    assert not (tmp_path / "run").exists()
