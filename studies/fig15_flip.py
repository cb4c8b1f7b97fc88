"""Is a tracked flip of λ_max real? A controlled check of one Fig. 15-like jump.

    python -m studies.fig15_flip outputs/paper_fig15/<date> RUN STEP

Network RUN of a `paper_fig15` run is retrained alone, phase 2 only (phase 1's β and experts come
from the run's checkpoint; a run trains identically alone and in a batch), to the parameters the
tracking saw at gating steps STEP - 10 and STEP. The retraining is checked against the run's own
history (the KL of those steps, bit for bit), then λ_max of both parameter sets is estimated with
REPEATS independent sets of SAMPLES initial states × STEPS steps each (the tracking used 4 × 5000),
so the flip's size can be set against the spread of a precise estimate; then the same with noise
of ρ² = 10⁻⁴ on the closed loop's inputs (Fig. 15c). Prints a Markdown table and writes
docs/fig15_flip.csv.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import checkpoint
from moex.closed_loop import closed_loop_lyapunov
from moex.data import load_task
from moex.jobs import initial_parameters, run_seeds
from moex.kernels import get_backend
from moex.model import random_state
from moex.report import to_markdown
from moex.resume import config_from_dict
from moex.train import phase2_targets, train_gating
from studies.common import DOCS

REPEATS, SAMPLES, STEPS = 8, 25, 20000
NOISE_VAR = 1e-4  # ρ² of Fig. 15c


def gating_after(saved, cfg, run: int, updates: int) -> tuple[dict, list[dict]]:
    """Network `run`'s gating parameters after `updates` phase-2 steps, trained alone."""
    dataset = load_task(cfg)
    series = torch.as_tensor(dataset.series, dtype=torch.float64)
    _, gating = initial_parameters(cfg, series.shape[0], series.shape[2], torch.float64)
    alone = {k: v[run:run + 1] for k, v in gating.items()}
    targets = phase2_targets(saved.beta[run:run + 1], dataset, 1, torch.float64,
                             cfg.train.gating.target_temperature)
    phase = cfg.train.gating
    phase.steps, phase.log_every = updates, 10
    return train_gating(alone, targets, series[:, :-cfg.model.delay], cfg.model, phase,
                        rule=cfg.train, seeds=run_seeds(cfg.seed, cfg.num_runs)[run:run + 1],
                        backend=get_backend())


def estimates(saved, cfg, run: int, gating: dict, noise_var: float = 0.0) -> np.ndarray:
    """REPEATS estimates of λ_max, each the mean over SAMPLES initial states."""
    experts = {k: v[run:run + 1] for k, v in saved.experts.items()}
    out = []
    for repeat in range(REPEATS):
        generator = torch.Generator().manual_seed(1000 + repeat)
        state = random_state(experts, gating, SAMPLES, num_features=saved.series.shape[-1],
                             delay=cfg.model.delay, generator=generator)
        with torch.no_grad():
            lam = closed_loop_lyapunov(experts, gating, state, STEPS, cfg.eval.transient,
                                       generator=generator, noise_std=noise_var ** 0.5,
                                       backend=get_backend())
        out.append(float(lam[0, :, 0].mean()))
    return np.array(out)


def main() -> None:
    run_dir, run, step = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    saved = checkpoint.load(run_dir)
    cfg = config_from_dict(saved.config)
    history = pd.read_csv(run_dir / "history.csv")
    tracked = history[(history["phase"] == "gating") & (history["run"] == run)].set_index("step")
    rows = []
    for at in (step - 10, step):
        # the tracked λ at step s saw the parameters after s + 1 updates; the KL logged at step
        # s is that of the parameters after s updates
        _, alone_rows = gating_after(saved, cfg, run, at)
        kl_alone = alone_rows[-1]["kl"]
        gating, _ = gating_after(saved, cfg, run, at + 1)
        for noise_var in (0.0, NOISE_VAR):
            lam = estimates(saved, cfg, run, gating, noise_var)
            rows.append({"run": run, "step": at,
                         "tracked_max_lyapunov": tracked.loc[at, "max_lyapunov"],
                         "kl_history": tracked.loc[at, "kl"], "kl_retrained": kl_alone,
                         "same_kl": kl_alone == tracked.loc[at, "kl"], "noise_var": noise_var,
                         "max_lyapunov_mean": lam.mean(), "max_lyapunov_sd": lam.std(ddof=1),
                         "max_lyapunov_min": lam.min(), "max_lyapunov_max": lam.max(),
                         "estimates": f"{REPEATS} x {SAMPLES} samples x {STEPS} steps"})
    table = pd.DataFrame(rows)
    print(to_markdown(table))
    table.to_csv(DOCS / "fig15_flip.csv", index=False)


if __name__ == "__main__":
    main()
