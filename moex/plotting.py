"""Figures from DataFrames and arrays only: each `plot_*` draws on an Axes and returns it."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
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
    """E and the log-likelihood of phase 1; E^g, the adaptive rate and, when tracked, the block KL
    and λ_max of phase 2 (paper Figs. 3, 6, 11), one line per run."""
    panels = [("experts", "E", True), ("experts", "log_likelihood", False),
              ("gating", "E_g", True), ("gating", "lr_scale", True),
              ("gating", "block_kl_train", False), ("gating", "max_lyapunov", False)]
    panels = [p for p in panels if p[1] in history
              and history.loc[history["phase"] == p[0], p[1]].notna().any()]
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


def plot_trajectory(points: np.ndarray, ax=None, title: str = "", color=None):
    """A 2-D orbit (T, D >= 2), equal aspect, coloured by time or by `color` (T,)."""
    ax = ax or plt.figure().gca()
    ax.scatter(points[:, 0], points[:, 1], s=2, c=np.arange(len(points)) if color is None
               else color, cmap="viridis" if color is None else "tab10", rasterized=True)
    ax.set_aspect("equal")
    ax.set_title(title)
    return ax


def plot_gate_series(outputs: np.ndarray, gates: np.ndarray, symbols: np.ndarray,
                     names: list[str], axes=None, bad: np.ndarray | None = None):
    """Outputs (T, D) over gate openings (T, K), each step labelled with its winning symbol;
    steps flagged in `bad` (T,) are labelled in red (paper Fig. 4). D = 0 plots the gates alone."""
    if axes is None:
        rows = 2 if outputs.shape[1] else 1
        _, axes = plt.subplots(rows, 1, figsize=(10, 2 * rows + 0.5), sharex=True,
                               constrained_layout=True, squeeze=False)
        axes = list(axes[:, 0]) if rows == 2 else [axes[0, 0], axes[0, 0]]
    for d in range(outputs.shape[1]):
        axes[0].plot(outputs[:, d], lw=1, label=f"y[{d}]")
    if outputs.shape[1]:
        axes[0].set_ylabel("output")
    axes[1].imshow(gates.T, aspect="auto", origin="lower", cmap="Greys", vmin=0, vmax=1,
                   interpolation="nearest")
    axes[1].set_ylabel("gate")
    axes[1].set_xlabel("step")
    if names and len(symbols) <= 120:
        for n, s in enumerate(symbols):
            axes[1].text(n, gates.shape[1] - 0.4, names[s], ha="center", fontsize=6,
                         color="red" if bad is not None and bad[n] else "black")
    return axes


def plot_phase_portrait(gating_u: np.ndarray, ax=None):
    """Two gating potentials u^g_1 against u^g_2 (paper Figs. 4 and 15)."""
    ax = ax or plt.figure().gca()
    ax.plot(gating_u[:, 0], gating_u[:, 1], lw=0.3, rasterized=True)
    ax.set_xlabel("u^g_1")
    ax.set_ylabel("u^g_2")
    return ax


def plot_residence(model_hist: np.ndarray, ax=None, switch_prob: float | None = None):
    """Distribution of repetitions of a curve: model (pooled over runs) as bars, the geometric
    law (1 - P)^(k-1) P of the task as a line when P is known (paper Fig. 9)."""
    ax = ax or plt.figure().gca()
    model = model_hist.sum(0) / max(model_hist.sum(), 1)
    k = np.arange(len(model))
    top = max(int(np.flatnonzero(model).max()) + 2 if model.any() else 10, 10)
    ax.bar(k[1:top], model[1:top], color="tab:blue", alpha=0.6, label="trained networks")
    if switch_prob is not None:
        ax.plot(k[1:top], (1 - switch_prob) ** (k[1:top] - 1) * switch_prob, "k.-",
                label=f"geometric, P={switch_prob:g}")
    ax.set_xlabel("repetitions of a curve")
    ax.set_ylabel("probability")
    if model[1:top].any():
        ax.set_yscale("log")
    ax.legend()
    return ax


def plot_expert_panels(outputs: np.ndarray, gates: np.ndarray, axes=None):
    """Output y_n where expert i wins (s_n = i), one panel per expert (paper Fig. 12b)."""
    K = gates.shape[1]
    winners = gates.argmax(1)
    if axes is None:
        cols = int(np.ceil(np.sqrt(K)))
        _, axes = plt.subplots(int(np.ceil(K / cols)), cols, figsize=(2 * cols, 2 * cols),
                               constrained_layout=True, squeeze=False)
    for i, ax in enumerate(np.ravel(axes)):
        ax.set_xticks([])
        ax.set_yticks([])
        if i < K and (winners == i).any():
            ax.scatter(outputs[winners == i, 0], outputs[winners == i, 1], s=1)
            ax.set_xlim(-1, 1)
            ax.set_ylim(-1, 1)
        ax.set_title(f"expert {i}", fontsize=7)
    return axes


def plot_heatmap(table: pd.DataFrame, x: str, y: str, value: str, title: str = "", ax=None):
    """NT × LT phase plot of one column (paper Figs. 14 and 16); missing cells stay blank."""
    grid = table.pivot_table(index=y, columns=x, values=value, aggfunc="mean")
    if ax is None:
        fig, ax = plt.subplots(figsize=(4.5, 3.6), constrained_layout=True)
    mesh = ax.imshow(grid.to_numpy(dtype=float), origin="lower", cmap="viridis", aspect="auto")
    ax.set_xticks(range(grid.shape[1]), [f"{v:g}" for v in grid.columns])
    ax.set_yticks(range(grid.shape[0]), [f"{v:g}" for v in grid.index])
    ax.set_xlabel(f"{x} (NT)" if x == "num_series" else x)
    ax.set_ylabel(f"{y} (LT)" if y == "length" else y)
    ax.set_title(f"{value} {title}".strip())
    ax.figure.colorbar(mesh, ax=ax)
    return ax.figure


def plot_residence_panels(hists: dict[float, np.ndarray]):
    """Residence-time distributions, one panel per switching probability P (paper Fig. 9)."""
    fig, axes = plt.subplots(1, len(hists), figsize=(4 * len(hists), 3.2),
                             constrained_layout=True, squeeze=False)
    for ax, (p, hist) in zip(axes[0], sorted(hists.items(), reverse=True), strict=True):
        plot_residence(hist, ax=ax, switch_prob=p)
        ax.set_title(f"P = {p:g}")
    return fig
