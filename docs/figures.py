"""Redraw the committed figures of docs/ that come from per-network CSVs, in the current figure
style (the same functions `moex report` and `moex train` use):

    python docs/figures.py

capacity_*.png (Figs. 14 and 16: NT × LT heat maps of the retrained grid per NC, one colour range
per quantity; "chaotic": λ_max > 10⁻⁴, the threshold docs/capacity_cells.py uses),
table1_kl_vs_lyapunov.png, p05_study_switch_vs_lyapunov.png and learning_curves_{reber,
lissajous2}.png. The figures of single closed-loop samples (trajectories, gates, residence
times) need the run folders and are not redrawn here.
"""

import sys
from pathlib import Path

import pandas as pd

from moex import plotting
from moex.report import NEAR, _limits, aggregate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from capacity_cells import THRESHOLD  # noqa: E402

DOCS = Path(__file__).resolve().parent
HEAT = {"E_closed_mean": "E_closed", "chaotic_percent": "chaotic",
        "nonperiodic_fraction_mean": "nonperiodic"}


def capacity() -> None:
    runs = pd.read_csv(DOCS / "capacity_grid_summary.csv")
    keys = ["num_series", "length", "context_size", "noise_var"]
    chaotic = (runs.max_lyapunov > THRESHOLD).groupby([runs[k] for k in keys]).mean() * 100
    summary = aggregate(runs, keys).merge(chaotic.rename("chaotic_percent").reset_index())
    for column, name in HEAT.items():
        limits = _limits(summary[column], column)
        for (nc, noise), cell in summary.groupby(["context_size", "noise_var"]):
            if column != "nonperiodic_fraction_mean" and noise > 0:
                continue  # noise enters only the periodicity (Sec. 4.3)
            title = f"NC = {nc:g}" + (f", noise ρ² = {noise:g}" if noise > 0 else "")
            fig = plotting.plot_heatmap(cell, "num_series", "length", column, title=title,
                                        limits=limits)
            part = f"_noise{noise:g}" if column == "nonperiodic_fraction_mean" else ""
            plotting.save_figure(fig, DOCS / f"capacity_{name}{part}_NC{nc:g}.png")


def scatters() -> None:
    table1 = pd.read_csv(DOCS / "table1_summary.csv")
    plotting.save_figure(plotting.plot_scatter_by(table1, "max_lyapunov", "block_kl_test",
                                                  "context_size", log_y=True),
                         DOCS / "table1_kl_vs_lyapunov.png")
    study = pd.read_csv(DOCS / "p05_study_summary.csv")
    plotting.save_figure(plotting.plot_scatter_by(study, "max_lyapunov", "switch_prob", "arm",
                                                  reference=study["data_switch_prob"],
                                                  band=NEAR),
                         DOCS / "p05_study_switch_vs_lyapunov.png")


def learning_curves() -> None:
    history = pd.read_csv(DOCS / "learning_curves_history.csv")
    for task in ("reber", "lissajous2"):
        fig = plotting.plot_learning_curves(history[history["task"] == task])
        fig.suptitle(f"{task}: 10 networks at the paper's training, tracked every 100 steps")
        plotting.save_figure(fig, DOCS / f"learning_curves_{task}.png")


if __name__ == "__main__":
    capacity()
    scatters()
    learning_curves()
