"""Resumable runs, fault isolation between runs, failed jobs that do not stop a sweep."""

import json
import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import open_dict

from moex import cli
from moex.cli import register_configs
from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.jobs import run_seeds
from moex.kernels import get_backend
from moex.model import init_experts, init_gating
from moex.tasks import make_task, task_config
from moex.train import train_experts
from tests.helpers import generators

MOEX = [sys.executable, "-c", "from moex.cli import main; main()"]
ARGS = ["train", "task=lissajous2", "task.num_series=2", "task.length=40",
        "model.experts.context_size=4", "model.gating.context_size=5", "num_runs=2",
        "train.experts.steps=3000", "train.gating.steps=1500", "train.experts.adaptive_lr=true",
        "train.checkpoint_every=25", "eval.enabled=false"]


def _run(args, cwd, **kw):
    return subprocess.Popen(MOEX + args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, **kw)


def _tensors(checkpoint):
    for part in ("experts", "gating"):
        yield from ((f"{part}.{k}", v) for k, v in checkpoint[part].items())
    yield "beta", checkpoint["beta"]


def test_sigterm_then_resume_is_bit_identical(tmp_path):
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    reference = _run(ARGS + [f"hydra.run.dir={clean}"], tmp_path)
    proc = _run(ARGS + [f"hydra.run.dir={killed}"], tmp_path)
    deadline = time.time() + 120
    while not (killed / "checkpoint.pt").exists() and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "interrupted" in err
    stopped = torch.load(killed / "checkpoint.pt", weights_only=True)
    assert stopped["phase"] in ("experts", "gating") and stopped["train_state"]["step"] > 0
    assert json.loads((killed / "status.json").read_text())["status"] == "interrupted"
    resumed = _run(ARGS + [f"hydra.run.dir={killed}"], tmp_path)
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    step = stopped["train_state"]["step"]  # the resumed run says so, and from which step
    assert f"{stopped['phase']} phase from step {step}" in out + err
    _, err = reference.communicate(timeout=300)
    assert reference.returncode == 0, err
    a = torch.load(clean / "checkpoint.pt", weights_only=True)
    b = torch.load(killed / "checkpoint.pt", weights_only=True)
    for (name, x), (_, y) in zip(_tensors(a), _tensors(b), strict=True):
        assert torch.equal(x, y), name
    pd.testing.assert_frame_equal(pd.read_csv(clean / "history.csv"),
                                  pd.read_csv(killed / "history.csv"))
    assert json.loads((killed / "status.json").read_text())["status"] == "done"
    # a finished run is not redone
    again = _run(ARGS + [f"hydra.run.dir={killed}"], tmp_path)
    _, err = again.communicate(timeout=120)
    assert again.returncode == 0 and torch.equal(
        torch.load(killed / "checkpoint.pt", weights_only=True)["gating"]["w_out"],
        b["gating"]["w_out"])


def test_resume_with_another_config_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    args = ARGS[:-4] + ["train.experts.steps=3", "train.gating.steps=2", "eval.enabled=false",
                        f"hydra.run.dir={run_dir}"]
    assert _run(args, tmp_path).wait(timeout=120) == 0
    proc = _run(args + ["model.gating.context_size=6"], tmp_path)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert "was trained with model.gating.context_size=5, not 6" in err, err


@pytest.mark.parametrize("group", ["w_rec", "w_out"])
def test_a_nan_run_leaves_the_others_identical(group):
    """A NaN weight of one expert fails its run (a NaN output weight too: the compiled exp once
    clamped NaN to e^-700, so that run trained on with that expert ignored)."""
    task = make_task(task_config("lissajous2", num_series=2, length=30), seed=0)
    series = torch.as_tensor(task.series)
    model = ModelConfig()
    model.experts.context_size = 4
    seeds = run_seeds(3, 3)
    phase = ExpertPhaseConfig(steps=15, adaptive_lr=True)
    for adaptive in (True, False):
        phase.adaptive_lr = adaptive
        clean = init_experts(model, 2, 2, generators(seeds))
        broken = {k: v.clone() for k, v in clean.items()}
        broken[group][1, 0, 0, 0] = float("nan")
        trained_clean, beta_clean, _ = train_experts(clean, series, model, phase, TrainConfig(),
                                                     backend=get_backend())
        trained, beta, rows = train_experts(broken, series, model, phase, TrainConfig(),
                                            backend=get_backend())
        for k in trained:
            for r in (0, 2):
                assert torch.equal(trained[k][r], trained_clean[k][r]), k
        assert torch.equal(beta[0], beta_clean[0]) and torch.equal(beta[2], beta_clean[2])
        assert all(row["failed"] == (row["run"] == 1) for row in rows)


def test_a_failing_multirun_job_writes_its_status_and_the_sweep_goes_on(tmp_path):
    register_configs()
    with initialize_config_dir(config_dir=cli.CONF_DIR, version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.mode = RunMode.MULTIRUN
        cfg.hydra.runtime.output_dir = str(tmp_path)
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]

    def explode(*_):
        raise RuntimeError("boom")

    cli._job(explode, "train")(cfg)  # returns instead of raising: the sweep continues
    status = json.loads((tmp_path / "status.json").read_text())
    assert status == {"verb": "train", "status": "failed", "error": "RuntimeError: boom"}


def test_a_sweep_with_a_failed_job_ends_with_exit_status_1(tmp_path, monkeypatch, capsys):
    """The summary after a sweep counts its jobs' ends; a failed one makes the command exit 1
    (a script driving sweeps must not read a failure as success); all done exits normally."""
    for job, status in (("0", "done"), ("1", "failed")):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / "status.json").write_text(json.dumps({"status": status}))
    monkeypatch.setattr(cli, "_sweeps", {tmp_path})
    with pytest.raises(SystemExit) as ended:
        cli._summarise_sweeps("train")
    assert ended.value.code == 1
    out, err = capsys.readouterr()
    assert "2 jobs (1 done, 1 failed" in out and "1 job(s) failed" in err
    (tmp_path / "1" / "status.json").write_text(json.dumps({"status": "done"}))
    cli._summarise_sweeps("train")  # no exit
    assert "2 jobs (2 done" in capsys.readouterr().out


def test_a_nan_gating_run_leaves_the_others_identical(backend):
    """Phase 2 as phase 1 above: run 0 gets an infinite bias and fails; runs 1 and 2 end exactly
    as they do in a batch without it."""
    from moex.train import train_gating

    model = ModelConfig()
    if backend.caps.interpreted:  # Triton's interpreter steps through W_rec column by column
        model.gating.context_size = 5
    ghat = torch.softmax(torch.randn(3, 2, 10, 2, generator=torch.Generator().manual_seed(0)), -1)
    inputs = torch.randn(2, 10, 2, generator=torch.Generator().manual_seed(1)).tanh()
    phase = GatingPhaseConfig(steps=3 if backend.caps.interpreted else 8, log_every=1)
    clean = init_gating(model, 2, 2, generators([0, 1, 2]))
    broken = {k: v.clone() for k, v in clean.items()}
    broken["b_o"][0, 0] = float("inf")
    trained_clean, _ = train_gating(clean, ghat, inputs, model, phase, rule=TrainConfig(),
                                    backend=backend)
    trained, rows = train_gating(broken, ghat, inputs, model, phase, rule=TrainConfig(),
                                 backend=backend)
    assert all(row["failed"] == (row["run"] == 0) for row in rows)
    for k in trained:
        for r in (1, 2):
            assert torch.equal(trained[k][r], trained_clean[k][r]), k


def test_slurm_path_through_submitit_local_survives_a_killed_job(tmp_path):
    """The SLURM launcher's code path without a cluster: a two-job sweep through submitit's local
    executor; one job is killed (SIGKILL, as a node failure would); the same command resumes it
    from its last checkpoint and skips the finished job."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    args = ["train", "-m", "hydra/launcher=submitit_local", *ARGS[2:], "train.experts.steps=2000",
            "train.gating.steps=500", "train.checkpoint_every=100",
            "model.gating.context_size=4,5", f"hydra.sweep.dir={sweep}"]
    sweep_proc = _run(args, tmp_path)
    deadline = time.time() + 240
    while not list(sweep.glob("*/checkpoint.pt")) and time.time() < deadline:
        time.sleep(0.1)
    jobs = subprocess.run(["pgrep", "-f", f"submitit.core._submit.*{sweep}"],
                          capture_output=True, text=True).stdout.split()
    assert jobs, "no submitit job process found"
    os.kill(int(jobs[0]), signal.SIGKILL)
    sweep_proc.communicate(timeout=300)
    statuses = {p.parent.name: json.loads(p.read_text())["status"]
                for p in sweep.glob("*/status.json")}
    assert [d for d in ("0", "1") if statuses.get(d) != "done"], f"none was killed: {statuses}"
    resumed = _run(args, tmp_path)
    _, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    for job in ("0", "1"):
        assert json.loads((sweep / job / "status.json").read_text())["status"] == "done"
    assert pd.read_csv(sweep / "jobs.csv")["folder"].tolist() == [0, 1]
