import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

MOEX = [sys.executable, "-c", "from moex.cli import main; main()"]
TINY = ["task.num_series=2", "task.length=40", "task.num_test_series=1",
        "model.experts.context_size=4", "model.gating.context_size=5",
        "train.experts.steps=6", "train.gating.steps=4", "train.experts.log_every=2",
        "train.gating.log_every=2", "num_runs=2", "eval.num_samples=2",
        "eval.lyapunov_steps=200", "eval.transient=20", "eval.plot_steps=100"]


def _moex(args, cwd):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(MOEX + args, cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=300)


def test_train_from_another_directory_leaves_the_documented_files(tmp_path):
    run_dir = tmp_path / "run"
    work = tmp_path / "elsewhere"
    work.mkdir()
    result = _moex(["train", "task=lissajous2", *TINY, f"hydra.run.dir={run_dir}"], cwd=work)
    assert result.returncode == 0, result.stderr
    for name in ("checkpoint.pt", "history.csv", "train.log", ".hydra/config.yaml",
                 "metrics.csv", "samples.npz", "figures/learning_curves.png",
                 "figures/trajectory.png", "figures/gates.png", "figures/residence_times.png"):
        assert (run_dir / name).is_file(), name
    assert list(work.iterdir()) == []  # nothing written to the working directory
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert checkpoint["gating"]["w_out"].shape == (2, 2, 5)
    history = pd.read_csv(run_dir / "history.csv")
    assert {"run", "phase", "step", "E", "E_g", "log_likelihood", "lr_scale"} <= set(history)
    assert set(history["phase"]) == {"experts", "gating"}
    assert set(history["run"]) == {0, 1}
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert metrics["run"].tolist() == [0, 1]
    for column in ("E", "E_g", "E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
                   "switch_prob", "nonperiodic_fraction"):
        assert metrics[column].notna().all(), column

    # evaluate again with other settings, then generate noisy samples, from the checkpoint
    result = _moex(["evaluate", f"run_dir={run_dir}", "eval.num_samples=3",
                    "eval.lyapunov_steps=100", "eval.noise_var=0.001"], cwd=work)
    assert result.returncode == 0, result.stderr
    again = pd.read_csv(run_dir / "metrics.csv")
    assert (again["num_samples"] == 3).all() and (again["noise_var"] == 0.001).all()
    result = _moex(["generate", f"run_dir={run_dir}", "steps=50", "num_samples=2",
                    "noise_var=0.001"], cwd=work)
    assert result.returncode == 0, result.stderr
    samples = np.load(run_dir / "samples.npz")
    assert samples["outputs"].shape == (2, 2, 50, 2) and samples["gates"].shape == (2, 2, 50, 2)
    assert samples["symbols"].shape == (2, 2, 50)
    # from the trained state of series 1, without noise every sample is the same
    result = _moex(["generate", f"run_dir={run_dir}", "steps=30", "num_samples=2",
                    "from_series=1"], cwd=work)
    assert result.returncode == 0, result.stderr
    outputs = np.load(run_dir / "samples.npz")["outputs"]
    assert np.array_equal(outputs[:, 0], outputs[:, 1])
    result = _moex(["generate", f"run_dir={run_dir}", "from_series=5"], cwd=work)
    assert result.returncode == 2 and "from_series=5 is outside [-1, 1]" in result.stderr
    assert list(work.iterdir()) == []


def test_resume_true_continues_the_latest_run_of_the_task(tmp_path):
    args = ["train", "task=lissajous2", *TINY, "eval.enabled=false"]
    assert _moex(args, cwd=tmp_path).returncode == 0
    (run_dir,) = (tmp_path / "outputs" / "lissajous2").iterdir()
    before = (run_dir / "checkpoint.pt").stat().st_mtime_ns
    result = _moex(args + ["resume=true"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert str(run_dir) in result.stdout
    assert list((tmp_path / "outputs" / "lissajous2").iterdir()) == [run_dir]
    assert (run_dir / "checkpoint.pt").stat().st_mtime_ns == before  # finished: not redone
    result = _moex(["train", "task=reber", "resume=true"], cwd=tmp_path)
    assert result.returncode == 2 and "outputs/reber/ holds no run" in result.stderr


def test_reber_trains_the_gating_network_only(tmp_path):
    run_dir = tmp_path / "run"
    result = _moex(["train", "task=reber", "task.length=30", "task.num_series=2",
                    "train.gating.steps=3", "model.gating.context_size=4", "eval.num_samples=2",
                    "eval.lyapunov_steps=50", "eval.transient=5",
                    f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    history = pd.read_csv(run_dir / "history.csv")
    assert set(history["phase"]) == {"gating"}
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert metrics["block_length"].tolist() == [3] and metrics["E"].isna().all()
    assert metrics["block_kl_test"].notna().all()


@pytest.mark.parametrize("override, message", [
    ("task=nope", "task=nope is unknown; choose one of"),
    ("model.nope=1", "unknown key model.nope"),
    ("model.num_experts=0", "model.num_experts=0 must be >= 1"),
    ("model.experts.time_constant=1.5", "model.experts.time_constant=1.5 is outside (0.0, 1.0]"),
    ("model.gating.time_constant=0", "model.gating.time_constant=0.0 is outside (0.0, 1.0]"),
    ("model.delay=0", "model.delay=0 must be >= 1"),
    ("model.sigma_min=0", "model.sigma_min=0.0 must be positive"),
    ("task.switch_prob=1.2", "task.switch_prob=1.2 is outside [0.0, 1.0]"),
    ("task.switch_prob=0.5,1.2", "task.switch_prob=1.2 is outside [0.0, 1.0]"),
    ("model.gating.context_size=-3", "model.gating.context_size=-3 must be >= 1"),
    ("model.num_experts=abc", "model.num_experts"),
    ("num_runs=0", "num_runs=0 must be >= 1"),
    ("hydra/launcher=nope", "hydra/launcher=nope is unknown; choose one of basic, joblib"),
])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(override, message, tmp_path):
    multirun = ["-m"] if "," in override else []
    result = _moex(["train", *multirun, override, f"hydra.run.dir={tmp_path}/run",
                    f"hydra.sweep.dir={tmp_path}/sweep"], cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("moex: error: "), result.stderr
    assert message in lines[0]
    assert "Traceback" not in result.stderr + result.stdout
    assert sorted(p.name for p in Path(tmp_path).iterdir()) == []


def test_bad_transition_matrix_and_csv(tmp_path):
    (tmp_path / "bad.csv").write_text("0.1,0.2\n0.3,nan\n" * 5)
    (tmp_path / "ragged.csv").write_text("0.1,0.2\n0.3\n" * 5)
    (tmp_path / "short.csv").write_text("0.1,0.2\n0.3,0.1\n")
    for args, message in [
        (["task=csv", f"task.path={tmp_path}/ragged.csv"], "ragged rows"),
        (["task=csv", f"task.path={tmp_path}/short.csv"],
         "series have 2 steps, need at least 3 (model.delay + 2)"),
        (["task=csv", f"task.path={tmp_path}/short.csv", "model.delay=3"],
         "need at least 5 (model.delay + 2)"),
        (["task=markov_primitives", "task.transition=[[0.5,0.4],[0.5,0.5]]"],
         "task.transition[0] sums to 0.9, not 1"),
        (["task=csv", f"task.path={tmp_path}/bad.csv"], "contains NaN or inf"),
        (["task=csv"], "task.path"),
    ]:
        result = _moex(["train", *args, f"hydra.run.dir={tmp_path}/run"], cwd=tmp_path)
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("verb", ["evaluate", "generate"])
def test_run_dir_without_checkpoint(verb, tmp_path):
    result = _moex([verb, f"run_dir={tmp_path}/none"], cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == f"moex: error: run_dir={tmp_path}/none holds no checkpoint.pt"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    result = _moex([verb, f"run_dir={tmp_path}"], cwd=tmp_path)
    assert result.returncode == 2 and "is not a readable moex checkpoint" in result.stderr
    torch.save({"format_version": 99}, tmp_path / "checkpoint.pt")
    result = _moex([verb, f"run_dir={tmp_path}"], cwd=tmp_path)
    assert result.returncode == 2
    assert "has checkpoint format 99, this moex reads format 1" in result.stderr


def test_missing_launcher_plugin_is_named(tmp_path):
    pytest.importorskip("hydra_plugins")
    try:
        import hydra_plugins.hydra_submitit_launcher  # noqa: F401
        pytest.skip("the submitit launcher is installed here")
    except ImportError:
        pass
    result = _moex(["train", "-m", "hydra/launcher=slurm", f"hydra.sweep.dir={tmp_path}/s"],
                   cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == ("moex: error: hydra/launcher: the submitit launcher plugin "
                                     "is not installed; pip install -e '.[slurm]'")


def test_unknown_verb():
    result = _moex(["fly"], cwd=".")
    assert result.returncode == 2 and "unknown verb 'fly'" in result.stderr


def test_csv_run_evaluates_from_another_directory(tmp_path):
    (tmp_path / "a" / "data").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        np.savetxt(tmp_path / "a" / "data" / f"s{i}.csv", rng.uniform(-0.5, 0.5, (30, 2)),
                   delimiter=",")
    run_dir = tmp_path / "run"
    args = ["task=csv", "task.path=data", "train.experts.steps=3", "train.gating.steps=2",
            "eval.num_samples=2", "eval.lyapunov_steps=20", "eval.transient=2"]
    result = _moex(["train", *args, f"hydra.run.dir={run_dir}"], cwd=tmp_path / "a")
    assert result.returncode == 0, result.stderr
    result = _moex(["evaluate", f"run_dir={run_dir}"], cwd=tmp_path / "b")
    assert result.returncode == 0, result.stderr
    assert pd.read_csv(run_dir / "metrics.csv")["E"].notna().all()
