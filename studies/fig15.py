"""Fig. 15 looked for: flips of the tracked λ_max between consecutive tracking points, against the
noise floor of the tracking estimate, from a `paper_fig15` run folder.

    python -m studies.fig15 outputs/paper_fig15/<date> [NOISY_EVAL_DIR]
    python -m studies.fig15 --power     # the detector's power to see the paper's flip

writes docs/fig15_summary.csv (per network: the noise floor, flips, and the evaluation's λ_max and
switching, with ρ² = 10⁻⁴ beside them when NOISY_EVAL_DIR, a `moex evaluate ... eval.noise_var=
0.0001` folder, is given) and docs/fig15_tracked.png (the tracked λ_max of every network against
its ±2-sd band); docs/fig15_end_summary.csv and docs/fig15_end_tracked.png for a run tracked from
`eval.track_from` on (the end of training).

The paper's flip: λ_max from −5.4·10⁻⁵ to +9.95·10⁻⁴ within 10 learning steps. A flip here is a
pair of consecutive tracked points (eval.every apart) going from below −FLOOR_FACTOR × floor to
above +FLOOR_FACTOR × floor, where the floor is the standard deviation of the tracking estimate
(track_samples × track_steps) of the trained network over REPEATS independent sets of initial
states: a change smaller than that is the estimator's noise, not the network's. `--power`
injects the paper's flip into series that scatter by each network's floor and counts how often
the detector finds it (docs/fig15_power.csv).
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import torch

from moex import checkpoint
from moex.closed_loop import closed_loop_lyapunov
from moex.kernels import get_backend
from moex.model import random_state
from moex.report import to_markdown
from moex.resume import config_from_dict
from studies.common import DOCS

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
        state = random_state(saved.experts, saved.gating, cfg.eval.track_samples, num_features=D,
                             delay=cfg.model.delay, generator=generator)
        with torch.no_grad():
            lam = closed_loop_lyapunov(saved.experts, saved.gating, state, cfg.eval.track_steps,
                                       min(cfg.eval.transient, cfg.eval.track_steps),
                                       generator=generator, backend=get_backend())
        estimates.append(lam[..., 0].mean(1).numpy())
    return np.std(estimates, axis=0, ddof=1)


def flips(history: pd.DataFrame, floor: np.ndarray) -> pd.DataFrame:
    tracked = history[(history["phase"] == "gating") & history["max_lyapunov"].notna()]
    if tracked.empty:
        return pd.DataFrame()
    runs, at = tracked["run"].to_numpy(), tracked["step"].to_numpy()
    order = np.lexsort((at, runs))  # by run, then step
    runs, at, values = runs[order], at[order], tracked["max_lyapunov"].to_numpy()[order]
    starts = np.flatnonzero(np.diff(runs, prepend=runs[:1] - 1))  # each run's first row
    rows = []
    for run, lam, steps in zip(runs[starts], np.split(values, starts[1:]),
                               np.split(at, starts[1:]), strict=True):
        band = FLOOR_FACTOR * floor[run]
        up = np.flatnonzero((lam[:-1] < -band) & (lam[1:] > band))
        rows.append({"run": run, "floor": floor[run], "final": lam[-1],
                     "flips_up": len(up), "last_flip_step": int(steps[up[-1] + 1]) if len(up)
                     else -1, "sign_changes": int((np.diff(np.sign(lam)) != 0).sum()),
                     "share_positive_last_1000": float((lam[steps >= steps[-1] - 1000] > band)
                                                       .mean())})
    return pd.DataFrame(rows)


PAPER_FLIP = (-5.4e-5, 9.95e-4)  # the paper's λ_max before and after its flip (Fig. 15)


def power(floor: float, flip: tuple[float, float] = PAPER_FLIP, trials: int = 4000,
          seed: int = 0) -> float:
    """The share of `trials` in which `flips` finds a flip of λ_max from flip[0] to flip[1]
    injected into a tracked series whose estimates scatter by the network's own noise floor
    (normal, sd `floor`) around its true value: the detector's power for that flip."""
    rng = np.random.default_rng(seed)
    truth = np.array([flip[0]] * 5 + [flip[1]] * 5)  # the flip between steps 40 and 50
    lam = truth + rng.normal(0.0, floor, (trials, len(truth)))
    history = pd.DataFrame({"run": np.repeat(np.arange(trials), len(truth)), "phase": "gating",
                            "step": np.tile(np.arange(len(truth)) * 10, trials),
                            "max_lyapunov": lam.ravel()})
    found = flips(history, np.full(trials, floor))
    return float((found["flips_up"] > 0).mean())


def power_table(summary: pd.DataFrame) -> pd.DataFrame:
    """Each tracked network's power to see the paper's flip, at its own noise floor."""
    return pd.DataFrame({"run": summary["run"], "floor": summary["floor"],
                         "power_paper_flip": [power(f) for f in summary["floor"]]})


def plot(history: pd.DataFrame, table: pd.DataFrame, path: Path, ev) -> None:
    """One panel per network: tracked λ_max against the gating step, the ±2-sd band shaded."""
    tracked = history[(history["phase"] == "gating") & history["max_lyapunov"].notna()]
    runs = sorted(tracked["run"].unique())
    cols = 5
    fig, axes = plt.subplots(-(-len(runs) // cols), cols, figsize=(13, 5), sharex=True,
                             sharey=True, squeeze=False)
    for ax, run in zip(axes.flat, runs, strict=False):
        x = tracked[tracked["run"] == run].sort_values("step")
        band = FLOOR_FACTOR * table.set_index("run").loc[run, "floor"]
        ax.axhspan(-band, band, color="0.85", lw=0, label=f"±{FLOOR_FACTOR} sd of the estimate")
        ax.plot(x["step"], x["max_lyapunov"], lw=0.6, color="C0")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_yscale("symlog", linthresh=1e-4)
        ax.set_title(f"network {run}: λ_max ends {x['max_lyapunov'].iloc[-1]:+.1e}", fontsize=9)
    for ax in axes.flat[len(runs):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("gating step")
    for ax in axes[:, 0]:
        ax.set_ylabel(r"tracked $\lambda_{\max}$")
    axes.flat[0].legend(fontsize=8, loc="lower right")
    fig.suptitle(rf"Fig. 15 looked for: $\lambda_{{\max}}$ ({ev.track_samples} samples × "
                 rf"{ev.track_steps} steps) every {ev.every} gating steps"
                 + (f" from step {ev.track_from}" if ev.track_from else "")
                 + ", NT 10 / LT 1000 / NC 30")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    if sys.argv[1:] == ["--power"]:  # the detector's power at the end-of-training floors
        table = power_table(pd.read_csv(DOCS / "fig15_end_summary.csv"))
        table.to_csv(DOCS / "fig15_power.csv", index=False)
        print(to_markdown(table))
        return
    run_dir = Path(sys.argv[1])
    history = pd.read_csv(run_dir / "history.csv")
    table = flips(history, noise_floor(run_dir))
    metrics = pd.read_csv(run_dir / "metrics.csv")[["run", "max_lyapunov", "switch_prob",
                                                     "nonperiodic_fraction"]]
    table = table.merge(metrics.rename(columns={"max_lyapunov": "eval_max_lyapunov"}), on="run")
    if len(sys.argv) > 2:
        noisy = pd.read_csv(Path(sys.argv[2]) / "metrics.csv")[
            ["run", "max_lyapunov_noisy", "switch_prob", "nonperiodic_fraction"]]
        table = table.merge(noisy, on="run", suffixes=("", "_noise1e-4"))
    print(to_markdown(table))
    ev = config_from_dict(checkpoint.load(run_dir).config).eval
    name = "fig15_end" if ev.track_from else "fig15"  # the end of training only: its own files
    table.to_csv(DOCS / f"{name}_summary.csv", index=False)
    plot(history, table, DOCS / f"{name}_tracked.png", ev)


if __name__ == "__main__":
    main()
