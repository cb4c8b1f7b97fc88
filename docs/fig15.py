"""Fig. 15 looked for: flips of the tracked λ_max between consecutive tracking points, against the
noise floor of the tracking estimate, from a `paper_fig15` run folder.

    python docs/fig15.py outputs/paper_fig15/<date>

The paper's flip: λ_max from −5.4·10⁻⁵ to +9.95·10⁻⁴ within 10 learning steps. A flip here is a
pair of consecutive tracked points (eval.every apart) going from below −FLOOR_FACTOR × floor to
above +FLOOR_FACTOR × floor, where the floor is the standard deviation of the tracking estimate
(track_samples × track_steps) of the trained network over REPEATS independent sets of initial
states: a change smaller than that is the estimator's noise, not the network's.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import checkpoint
from moex.closed_loop import closed_loop_lyapunov, random_state
from moex.config import config_from_dict
from moex.report import to_markdown

REPEATS = 20
FLOOR_FACTOR = 2


def noise_floor(run_dir: Path) -> np.ndarray:
    """(R,) sd of the tracking estimate of λ_max for each trained network."""
    saved = checkpoint.load(run_dir)
    cfg = config_from_dict(saved.config)
    D = saved.series.shape[-1]
    estimates = []
    for repeat in range(REPEATS):
        generator = torch.Generator().manual_seed(repeat)
        state = random_state(saved.experts, saved.gating, cfg.eval.track_samples, D,
                             cfg.model.delay, generator)
        with torch.no_grad():
            lam = closed_loop_lyapunov(saved.experts, saved.gating, state, cfg.eval.track_steps,
                                       min(cfg.eval.transient, cfg.eval.track_steps), generator)
        estimates.append(lam[..., 0].mean(1).numpy())
    return np.std(estimates, axis=0, ddof=1)


def flips(history: pd.DataFrame, floor: np.ndarray) -> pd.DataFrame:
    tracked = history[(history["phase"] == "gating") & history["max_lyapunov"].notna()]
    rows = []
    for run, x in tracked.groupby("run"):
        lam, steps = x.sort_values("step")["max_lyapunov"].to_numpy(), np.sort(x["step"])
        band = FLOOR_FACTOR * floor[run]
        up = np.flatnonzero((lam[:-1] < -band) & (lam[1:] > band))
        rows.append({"run": run, "floor": floor[run], "final": lam[-1],
                     "flips_up": len(up), "last_flip_step": int(steps[up[-1] + 1]) if len(up)
                     else -1, "sign_changes": int((np.diff(np.sign(lam)) != 0).sum()),
                     "share_positive_last_1000": float((lam[steps >= steps[-1] - 1000] > band)
                                                       .mean())})
    return pd.DataFrame(rows)


def main() -> None:
    run_dir = Path(sys.argv[1])
    table = flips(pd.read_csv(run_dir / "history.csv"), noise_floor(run_dir))
    print(to_markdown(table))


if __name__ == "__main__":
    main()
