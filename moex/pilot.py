"""ς for training chosen from the data (`train.experts.gate_prior_std=auto`): a pilot run.

Phase 1 (Eqs. 9-13) runs for `train.experts.pilot_steps` steps (at most `train.experts.steps`)
at the paper's ς = 10 from the job's own initial parameters. The pilot's experts give every
step's log-likelihoods ln N(y_{n+τ}; y^k_n, σ_k² I) on the training series (each series from its
own trained initial state), and the cross-validation of `moex.segment` (steps split by n mod
2, β fitted with one half left out, the left-out steps' ln Σ_k ĝ^k p^k scored for each ς of
0.25, 0.5, ..., 16), summed over the job's runs, chooses one ς for the job (the compiled phase
takes one). Phase 1 then trains from the start at that ς, as if it had been set by hand, and
every output states the number. The choice and its table go to gate_prior.csv in the run
folder; a resumed or repeated run reads them there rather than repeating the pilot (which would
give the same ς: its draws are the job's own).
"""

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import io
from moex.config import Config
from moex.errors import check
from moex.jobs import initial_parameters
from moex.kernels import Backend, get_backend
from moex.model import expert_forward, expert_variances
from moex.objectives import expert_log_densities
from moex.segment import PRIOR_GRID, chosen_prior_std
from moex.tasks import Dataset
from moex.train import train_experts

log = logging.getLogger(__name__)

PILOT_PRIOR_STD = 10.0  # the paper's ς, the pilot's


def _steps(cfg: Config) -> int:
    return min(cfg.train.experts.pilot_steps, cfg.train.experts.steps)


def pilot_table(cfg: Config, dataset: Dataset, backend: Backend) -> pd.DataFrame:
    """The pilot's cross-validation table: per ς of the grid, the left-out steps' summed
    log-likelihood over the job's runs, and which ς is chosen."""
    dtype = getattr(torch, cfg.precision)
    series = torch.as_tensor(dataset.series, dtype=dtype)
    experts, _ = initial_parameters(cfg, *series.shape[::2], dtype)
    phase = dataclasses.replace(cfg.train.experts, steps=_steps(cfg),
                                gate_prior_std=PILOT_PRIOR_STD)
    experts, _, _ = train_experts(experts, series, cfg.model, phase, cfg.train, backend=backend)
    delay = cfg.model.delay
    with torch.no_grad():
        outputs, _ = expert_forward(experts, series[:, :-delay])
        log_p = expert_log_densities(outputs, series[:, delay:],
                                     expert_variances(experts, cfg.model.sigma_min))
    _, table = chosen_prior_std(log_p.double())
    total = table.sum(0)
    return pd.DataFrame({"gate_prior_std": PRIOR_GRID, "left_out_log_likelihood": total,
                         "chosen": np.arange(len(PRIOR_GRID)) == np.argmax(total)})


def check_pilot(cfg: Config, dataset: Dataset) -> None:
    """`auto` needs a phase 1: a task of symbols only is refused."""
    check(cfg.train.experts.gate_prior_std != "auto" or dataset.series.shape[-1] > 0,
          f"train.experts.gate_prior_std=auto needs phase 1; task {cfg.task.name} has symbols "
          f"only")


def settle(cfg: Config, dataset: Dataset, out_dir: Path | None = None, *,
           backend: Backend | None = None) -> None:
    """Replace `train.experts.gate_prior_std=auto` in `cfg` by the pilot's ς (read from
    `out_dir`/gate_prior.csv where an earlier start wrote it), said in the log; nothing for a
    number. The pilot trains on `backend` (default: the config's)."""
    experts = cfg.train.experts
    if experts.gate_prior_std != "auto":
        return
    check_pilot(cfg, dataset)
    chosen = None if out_dir is None else io.chosen_gate_prior(out_dir)
    if chosen is None:
        log.info("train.experts.gate_prior_std=auto: a pilot of %d phase-1 steps at ς = %g",
                 _steps(cfg), PILOT_PRIOR_STD)
        table = pilot_table(cfg, dataset, backend or get_backend(cfg.backend, cfg.device))
        if out_dir is not None:
            io.write_csv(Path(out_dir) / io.GATE_PRIOR, table)
        chosen = float(table.loc[table["chosen"], "gate_prior_std"].iloc[0])
    experts.gate_prior_std = chosen
    log.info("train.experts.gate_prior_std=auto: ς = %g (the pilot's cross-validation over "
             "%s)", chosen, ", ".join(f"{s:g}" for s in PRIOR_GRID))
