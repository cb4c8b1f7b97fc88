"""Redraw the committed figures of docs/ that come from per-network CSVs, in the current figure
style (the same functions `moex report` and `moex train` use):

    python -m studies.figures

capacity_fig14.png (E^closed and the share with λ_max > 0, the paper's criterion, as NT × LT
heat maps, one panel per NC) and capacity_fig16.png (the nonperiodic share, one row per noise
level), each quantity on one colour range,
table1_kl_vs_lyapunov.png, p05_study_switch_vs_lyapunov.png and learning_curves_{reber,
lissajous2}.png. The figures of single closed-loop samples (trajectories, gates, residence
times) need the run folders and are not redrawn here.
"""


import matplotlib.pyplot as plt
import pandas as pd

from moex import plotting
from moex.report import NEAR, aggregate, heat_limits
from studies.common import DOCS

NETWORKS = "10 networks per cell, P = 0.5, the paper's training"
# Fig. 14: one row per quantity without noise; Fig. 16: one row per noise level ρ²
FIG14 = ["E_closed_mean", "positive_percent"]
FIG16 = "nonperiodic_fraction_mean"
NC, NT, LT = "model.gating.context_size", "task.num_series", "task.length"  # moex report's names


def _heat_row(axes, summary: pd.DataFrame, column: str, limits, row_title: str) -> None:
    """One row of NT × LT panels, one per NC, on one colour range with one colour bar."""
    panels = list(summary.groupby(NC))
    for i, (ax, (nc, cell)) in enumerate(zip(axes, panels, strict=True)):
        plotting.plot_heatmap(cell, NT, LT, column, ax=ax, limits=limits,
                              title=f"NC = {nc:g}{row_title}", colorbar=i == len(panels) - 1)
        if i:
            ax.set_ylabel("")


def capacity() -> None:
    runs = pd.read_csv(DOCS / "capacity_grid_summary.csv").rename(  # the study's short names
        columns={"context_size": NC, "num_series": NT, "length": LT})
    keys = [NT, LT, NC, "noise_var"]
    summary = aggregate(runs, keys)  # positive_percent: λ_max > 0, the paper's criterion
    ncs, noises = summary[NC].nunique(), sorted(summary.noise_var.unique())
    quiet = summary[summary.noise_var == 0]
    fig, axes = plt.subplots(len(FIG14), ncs, figsize=(4.2 * ncs, 3.5 * len(FIG14)),
                             constrained_layout=True, squeeze=False)
    for row, column in zip(axes, FIG14, strict=True):
        _heat_row(row, quiet, column, heat_limits(quiet[column], column), "")
    fig.suptitle(f"Fig. 14: closed-loop error and chaotic networks\n{NETWORKS}")
    plotting.save_figure(fig, DOCS / "capacity_fig14.png")
    fig, axes = plt.subplots(len(noises), ncs, figsize=(4.2 * ncs, 3.5 * len(noises)),
                             constrained_layout=True, squeeze=False)
    for row, noise in zip(axes, noises, strict=True):
        _heat_row(row, summary[summary.noise_var == noise], FIG16, (0.0, 1.0),
                  f", noise ρ² = {noise:g}")
    fig.suptitle("Fig. 16: share of nonperiodic samples (L/R sequence without a period ≤ 100)"
                 f" under noise of variance ρ² on the input\n{NETWORKS}")
    plotting.save_figure(fig, DOCS / "capacity_fig16.png")


def scatters() -> None:
    table1 = pd.read_csv(DOCS / "table1_summary.csv")
    plotting.save_figure(plotting.plot_scatter_by(table1, "max_lyapunov", "block_kl_test",
                                                  NC, log_y=True),
                         DOCS / "table1_kl_vs_lyapunov.png")
    study = pd.read_csv(DOCS / "p05_study_summary.csv")
    plotting.save_figure(plotting.plot_scatter_by(study, "max_lyapunov", "switch_prob", "p05_arm",
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
