"""The packed launcher (`hydra/launcher=packed`, moex.packing) and the training core it shares with
`moex train` (moex.jobs.train_jobs): a packed job equals the same job run alone, its folder holds
the same files, and an interrupted batch resumes (packed or alone) to the same networks."""

import dataclasses
import json

import pandas as pd
import pytest
import torch

from moex import checkpoint
from moex.data import load_task
from moex.jobs import Job, train_jobs
from moex.packing import Planned, groups, prepare
from moex.train import TrainingInterrupted
from tests.test_cli import TINY, _moex

SWEEP = [*[a for a in TINY if not a.startswith("task.length")], "task.length=300",
         "task.switch_prob=0.5,0.25", "seed=0,5"]


def _close(a, b):
    for name in ("experts", "gating"):
        for k in getattr(a, name):
            torch.testing.assert_close(getattr(a, name)[k], getattr(b, name)[k], rtol=0,
                                       atol=1e-10, msg=f"{name}.{k}")
    if a.beta is not None:
        torch.testing.assert_close(a.beta, b.beta, rtol=0, atol=1e-10)


def test_a_packed_sweep_writes_what_the_basic_launcher_writes(tmp_path):
    packed, basic = tmp_path / "packed", tmp_path / "basic"
    done = _moex(["train", "-m", *SWEEP, "hydra/launcher=packed",
                  f"hydra.sweep.dir={packed}"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "packed: 4 jobs, 8 networks in one batch" in done.stdout + done.stderr
    done = _moex(["train", "-m", *SWEEP, f"hydra.sweep.dir={basic}"], tmp_path)
    assert done.returncode == 0, done.stderr
    for job in ("0", "1", "2", "3"):
        files = {p.relative_to(packed / job) for p in (packed / job).rglob("*")}
        assert files == {p.relative_to(basic / job) for p in (basic / job).rglob("*")}
        a, b = checkpoint.load(packed / job), checkpoint.load(basic / job)
        assert a.config == b.config
        _close(a, b)
        for table in ("history.csv", "metrics.csv"):
            pd.testing.assert_frame_equal(pd.read_csv(packed / job / table),
                                          pd.read_csv(basic / job / table), rtol=1e-9)
        records = json.loads((packed / job / "provenance.json").read_text())
        assert records[0]["packed"]["networks"] == 8 and "phase 1" in records[0]["seconds"]
        status = json.loads((packed / job / "status.json").read_text())
        assert status["status"] == "done"
        # its time includes its share (2 of 8 networks) of the batch's training
        batch = sum(part["wall"] for part in records[0]["seconds"].values())
        assert status["seconds"] >= round(batch * 2 / 8, 1) - 0.1, (status, batch)
    # the same command again: every folder is finished, nothing is retrained
    again = _moex(["train", "-m", *SWEEP, "hydra/launcher=packed",
                   f"hydra.sweep.dir={packed}"], tmp_path)
    assert again.returncode == 0 and "in one batch" not in again.stdout + again.stderr


def _jobs(tiny_cfg, tmp_path, saved=None) -> list[Job]:
    jobs = []
    for i, (p, seed, runs) in enumerate(((0.5, 0, 2), (0.25, 3, 1))):
        cfg = dataclasses.replace(tiny_cfg, seed=seed, num_runs=runs)
        cfg.task = dataclasses.replace(cfg.task, length=200, switch_prob=p)
        folder = tmp_path / str(i)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / checkpoint.NAME
        jobs.append(Job(cfg, load_task(cfg), folder,
                        checkpoint.load(path) if saved and path.exists() else None))
    return jobs


class _StopAfter:
    def __init__(self, calls):
        self.calls = calls

    def __call__(self):
        self.calls -= 1
        return self.calls < 0


def test_an_interrupted_batch_resumes_packed_or_alone_to_the_same_networks(tiny_cfg, tmp_path):
    whole = train_jobs(_jobs(tiny_cfg, tmp_path / "whole"))
    for stop_at in (7, 19):  # in phase 1, in phase 2 (15 + 10 steps)
        cut = tmp_path / f"cut{stop_at}"
        with pytest.raises(TrainingInterrupted):
            train_jobs(_jobs(tiny_cfg, cut), _StopAfter(stop_at))
        jobs = _jobs(tiny_cfg, cut, saved=True)
        assert {j.saved.phase for j in jobs} == {"experts" if stop_at < 15 else "gating"}
        for ended, reference in zip(train_jobs(jobs), whole, strict=True):
            _close(ended, reference)
            assert ended.experts_rows == reference.experts_rows
    with pytest.raises(TrainingInterrupted):  # a packed checkpoint continued alone
        train_jobs(_jobs(tiny_cfg, tmp_path / "solo"), _StopAfter(7))
    (solo,) = train_jobs([_jobs(tiny_cfg, tmp_path / "solo", saved=True)[1]])
    _close(solo, whole[1])


def test_groups_share_key_shape_and_step_and_respect_max_runs(tiny_cfg, tmp_path):
    def planned(**changes):
        cfg = dataclasses.replace(tiny_cfg, **changes)
        return prepare(cfg, tmp_path / str(len(items)))

    items: list[Planned] = []
    for changes in ({}, {"seed": 1}, {"seed": 2, "num_runs": 3}, {"precision": "float32"},
                    {"seed": 3, "cache_dir": str(tmp_path / "cache")}):
        items.append(planned(**changes))
    longer = dataclasses.replace(tiny_cfg, seed=4)
    longer.task = dataclasses.replace(longer.task, length=80)
    items.append(prepare(longer, tmp_path / "long"))
    batches = groups(items)
    assert [[j.cfg.seed for j in b] for b in batches] == [[0, 1, 2]]  # the others run alone
    assert [[j.cfg.seed for j in b] for b in groups(items, max_runs=4)] == [[0, 1]]
    broken = dataclasses.replace(tiny_cfg)
    broken.model = dataclasses.replace(broken.model, num_experts=1)  # refused by load_task
    assert prepare(broken, tmp_path / "broken").job is None


def test_packed_groups_go_to_submitit_as_one_task_each(tmp_path):
    """`hydra.launcher.submitit` sends each batch as one task (submitit's in-process `debug`
    cluster here; `cluster: slurm` on a cluster), with the same folders as a local run."""
    sweep = tmp_path / "sweep"
    done = _moex(["train", "-m", *SWEEP, "hydra/launcher=packed", "hydra.launcher.max_runs=4",
                  "hydra.launcher.submitit={cluster:debug}", f"hydra.sweep.dir={sweep}"],
                 tmp_path)
    assert done.returncode == 0, done.stderr
    assert (sweep / ".submitit").is_dir()
    for job in ("0", "1", "2", "3"):
        record = json.loads((sweep / job / "provenance.json").read_text())[0]
        assert record["packed"]["networks"] == 4  # 2 jobs x 2 runs per batch (max_runs=4)
        assert (sweep / job / "metrics.csv").is_file()
        assert json.loads((sweep / job / "status.json").read_text())["status"] == "done"


def test_the_slurm_preset_composes(tmp_path):
    done = _moex(["train", "hydra/launcher=packed_slurm", "--cfg", "hydra",
                  "-p", "hydra.launcher"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "cluster: slurm" in done.stdout and "packed_launcher.PackedLauncher" in done.stdout


def test_a_negative_max_runs_is_refused_before_anything_runs(tmp_path, moex_here):
    sweep = tmp_path / "sweep"
    done = moex_here(["train", "-m", *SWEEP, "hydra/launcher=packed",
                      "hydra.launcher.max_runs=-1", f"hydra.sweep.dir={sweep}"], tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "moex: error: hydra.launcher.max_runs=-1 must be >= 0 (the most networks in one batch; "
        "0: no limit)"]
    assert not sweep.exists()
