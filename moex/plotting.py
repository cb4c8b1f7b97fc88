"""Figures from DataFrames and arrays only: each `plot_*` draws on an Axes and returns it."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from moex.io import atomic_write  # noqa: E402


def plot_history(history: pd.DataFrame, column: str, ax=None, log_y: bool = False):
    """One line per run of `column` against the learning step."""
    ax = ax or plt.figure().gca()
    for run, group in history.dropna(subset=[column]).groupby("run"):
        ax.plot(group["step"], group[column], lw=1, alpha=0.8, label=f"run {run}")
    ax.set_xlabel("learning step")
    ax.set_ylabel(column)
    if log_y:
        ax.set_yscale("log")
    return ax


def plot_learning_curves(history: pd.DataFrame):
    """E and the log-likelihood of phase 1, E^g of phase 2, and the adaptive rate of each run."""
    panels = [("experts", "E", True), ("experts", "log_likelihood", False),
              ("gating", "E_g", True), ("gating", "lr_scale", True)]
    panels = [p for p in panels if p[1] in history and (history["phase"] == p[0]).any()]
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(4 * max(len(panels), 1), 3.2),
                             constrained_layout=True, squeeze=False)
    for ax, (phase, column, log_y) in zip(axes[0], panels, strict=False):
        plot_history(history[history["phase"] == phase], column, ax=ax, log_y=log_y)
        ax.set_title(f"{phase}: {column}")
    return fig


def save_figure(fig, path) -> None:
    """Write a PNG atomically and close the figure."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    plt.close(fig)
