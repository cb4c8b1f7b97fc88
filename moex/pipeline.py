"""The glue, testable without Hydra: task → model → phase 1 → phase 2 → checkpoint → CSV → plots."""

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import io, plotting
from moex.config import Config
from moex.errors import check
from moex.model import init_experts, init_gating
from moex.tasks import Dataset, make_task
from moex.train import train_experts, train_gating

log = logging.getLogger(__name__)


def run_seeds(seed: int, num_runs: int) -> list[int]:
    """Seed of run r: a function of (seed, r) alone, so run r trains identically in any batch."""
    return [int(np.random.SeedSequence([seed, r]).generate_state(1)[0]) for r in range(num_runs)]


def load_task(cfg: Config) -> Dataset:
    """The task's data, checked against the model config (a `ConfigError` if they disagree)."""
    dataset = make_task(cfg.task, cfg.seed, min_length=cfg.model.delay + 2)
    if dataset.gate_targets is not None:
        V = dataset.gate_targets.shape[-1]
        check(cfg.model.num_experts == V, f"model.num_experts={cfg.model.num_experts} must equal "
                                          f"the {V} symbols of task {cfg.task.name}")
    return dataset


def run_train(cfg: Config, out_dir: Path) -> dict:
    """Train R runs of the mixture on the task and write the run folder.

    Args:
        cfg: the whole, validated config.
        out_dir: the run folder; receives checkpoint.pt, history.csv and figures/.

    Returns:
        the checkpoint payload (plain dict).
    """
    out_dir = Path(out_dir)
    dtype, device = getattr(torch, cfg.dtype), torch.device(cfg.device)
    dataset = load_task(cfg)
    generators = [torch.Generator().manual_seed(s) for s in run_seeds(cfg.seed, cfg.num_runs)]
    series = torch.as_tensor(dataset.series, dtype=dtype)
    S, L, D = series.shape
    delay = cfg.model.delay
    log.info("task %s: %d series x %d steps, %d features; %d runs on %s/%s", cfg.task.name, S, L,
             D, cfg.num_runs, cfg.device, cfg.dtype)
    experts, beta, rows = {}, None, []
    if D > 0:
        experts = init_experts(cfg.model, S, D, generators, dtype)
        experts = {k: v.to(device) for k, v in experts.items()}
        experts, beta, rows = train_experts(experts, series.to(device), cfg.model,
                                            cfg.train.experts, cfg.train)
        gate_targets, gating_inputs = torch.softmax(beta, dim=-1), series[:, :-delay]
    else:  # symbolic task: the gates are the one-hot symbols themselves (paper Sec. 3.1)
        one_hot = torch.as_tensor(dataset.gate_targets, dtype=dtype)
        gate_targets, gating_inputs = one_hot.expand(cfg.num_runs, -1, -1, -1), series
    gating = {k: v.to(device) for k, v in init_gating(cfg.model, S, D, generators, dtype).items()}
    gating, gating_rows = train_gating(gating, gate_targets.to(device), gating_inputs.to(device),
                                       cfg.model, cfg.train.gating, cfg.train)
    rows += gating_rows
    payload = {
        "config": dataclasses.asdict(cfg),
        "experts": {k: v.cpu() for k, v in experts.items()},
        "beta": None if beta is None else beta.cpu(),
        "gating": {k: v.cpu() for k, v in gating.items()},
        "series": series, "labels": torch.as_tensor(dataset.labels),
    }
    io.save_checkpoint(out_dir / io.CHECKPOINT, payload)
    history = pd.DataFrame(rows)
    io.write_csv(out_dir / io.HISTORY, history)
    plotting.save_figure(plotting.plot_learning_curves(history),
                         out_dir / io.FIGURES / "learning_curves.png")
    _log_summary(history)
    return payload


def _log_summary(history: pd.DataFrame) -> None:
    last = history.sort_values("step").groupby(["phase", "run"]).tail(1)
    for phase, group in last.groupby("phase"):
        column = "E" if phase == "experts" else "E_g"
        values = group[column]
        log.info("%s: final %s mean %.3g (min %.3g, max %.3g) over %d runs", phase, column,
                 values.mean(), values.min(), values.max(), len(values))
