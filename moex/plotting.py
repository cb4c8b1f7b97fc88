"""Figures from DataFrames and arrays only: each `plot_*` draws on an Axes and returns it."""

from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from moex.io import atomic_write  # noqa: E402
from moex.metrics.switching import rle  # noqa: E402


@dataclass
class PlotConfig:
    """Which run the single-run figures show: -1 picks the run with the highest λ_max (the most
    chaotic; failed runs never), k picks run k."""

    run: int = -1

    def __post_init__(self):
        if self.run < -1:
            from moex.errors import ConfigError

            raise ConfigError(f"plot.run={self.run} must be -1 (the run with the highest "
                              f"λ_max) or a run index >= 0")


LEARNING_PANELS = [  # (phase, column, log scale, title)
    ("experts", "E", True, "phase 1: mixture error E"),
    ("experts", "log_likelihood", False, "phase 1: ln p(Y | X, θ)"),
    ("gating", "E_g", True, "phase 2: gating error E^g"),
    ("gating", "lr_scale", True, "phase 2: adaptive rate α / α̃"),
    ("gating", "block_kl_train", False, "phase 2: block KL, training data"),
    ("gating", "max_lyapunov", False, "phase 2: λ_max"),
]


def plot_history(history: pd.DataFrame, column: str, ax=None, log_y: bool = False):
    """`column` against the learning step: one labelled line per run for up to 6 runs; beyond,
    every run thin and grey with the median over runs on top."""
    ax = ax or plt.figure().gca()
    data = history.dropna(subset=[column])
    runs = sorted(data["run"].unique())
    for run, group in data.groupby("run"):
        if len(runs) <= 6:
            ax.plot(group["step"], group[column], lw=1, label=f"run {run}")
        else:
            ax.plot(group["step"], group[column], lw=0.5, color="0.6",
                    label=f"each of {len(runs)} runs" if run == runs[0] else None)
    if len(runs) > 6:
        median = data.groupby("step")[column].median()
        ax.plot(median.index, median.to_numpy(), lw=2, color="tab:blue", label="median")
    ax.set_xlabel("learning step")
    ax.set_ylabel(column)
    if log_y:
        ax.set_yscale("log")
    if runs:
        ax.legend(fontsize=7)
    return ax


def plot_learning_curves(history: pd.DataFrame):
    """E and the log-likelihood of phase 1; E^g, the adaptive rate and, when tracked, the block KL
    and λ_max of phase 2 (paper Figs. 3, 6, 11)."""
    panels = [p for p in LEARNING_PANELS if p[1] in history
              and history.loc[history["phase"] == p[0], p[1]].notna().any()]
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(4 * max(len(panels), 1), 3.4),
                             constrained_layout=True, squeeze=False)
    for ax, (phase, column, log_y, title) in zip(axes[0], panels, strict=False):
        plot_history(history[history["phase"] == phase], column, ax=ax, log_y=log_y)
        ax.set_title(title)
    return fig


def save_figure(fig, path) -> None:
    """Write a PNG atomically and close the figure."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    plt.close(fig)


def _output_axes(ax, D: int) -> None:
    ax.set_aspect("equal")
    ax.set_xlabel("y_1")
    ax.set_ylabel("y_2" if D > 1 else "")


def plot_teaching_data(series: np.ndarray, ax=None, title: str = "teaching data"):
    """Training series (S, T, D >= 2) as dark lines in the (y_1, y_2) plane."""
    ax = ax or plt.figure().gca()
    for s in series:
        ax.plot(s[:, 0], s[:, 1], color="black", lw=0.6, alpha=0.7)
    _output_axes(ax, series.shape[-1])
    ax.set_title(title)
    return ax


def plot_trajectory(points: np.ndarray, gates: np.ndarray, ax=None, title: str = ""):
    """A closed-loop orbit (T, D >= 2), each step coloured by its winning expert (gates (T, K)),
    with a legend of the experts that win somewhere."""
    ax = ax or plt.figure().gca()
    winners = gates.argmax(-1)
    colors = plt.get_cmap("tab10")
    for k in np.unique(winners):
        mask = winners == k
        ax.scatter(points[mask, 0], points[mask, 1], s=2, color=colors(k % 10), rasterized=True,
                   label=f"expert {k} wins ({mask.mean():.0%})")
    _output_axes(ax, points.shape[-1])
    ax.set_title(title)
    ax.legend(fontsize=7, markerscale=4, loc="upper right")
    return ax


def plot_gate_series(outputs: np.ndarray, gates: np.ndarray, symbols: np.ndarray,
                     names: list[str], axes=None, bad: np.ndarray | None = None):
    """Outputs (T, D) over the gate openings (T, K), labelled with the symbol of each step
    (beyond 120 steps, of each run of one symbol that is not a brief flicker); steps flagged in
    `bad` (T,) are labelled in red (paper Figs. 4, 8 and 13). D = 0: the gates alone."""
    if axes is None:
        rows = 2 if outputs.shape[1] else 1
        fig, axes = plt.subplots(rows, 1, figsize=(10, 2.2 * rows + 0.6), sharex=True,
                                 constrained_layout=True, squeeze=False)
        axes = list(axes[:, 0]) if rows == 2 else [axes[0, 0], axes[0, 0]]
    for d in range(outputs.shape[1]):
        axes[0].plot(outputs[:, d], lw=1, label=f"y_{d + 1}")
    if outputs.shape[1]:
        axes[0].set_ylabel("output")
        axes[0].legend(fontsize=7, loc="upper right")
    K = gates.shape[1]
    image = axes[1].imshow(gates.T, aspect="auto", origin="lower", cmap="Greys", vmin=0, vmax=1,
                           interpolation="nearest", extent=(-0.5, len(gates) - 0.5, -0.5, K - 0.5))
    axes[1].set_yticks(range(K))
    axes[1].set_ylabel("expert")
    axes[1].set_xlabel("step")
    axes[1].figure.colorbar(image, ax=list(dict.fromkeys(axes)), label="gate opening g",
                            pad=0.01, fraction=0.03)
    if names:  # every step's symbol in a short window, else the middle of each run of one
        # symbol lasting at least 1/40 of the window (no overlapping labels for flickers)
        steps = range(len(symbols))
        if len(symbols) > 120:
            _, lengths = rle(symbols)
            starts = np.cumsum(lengths) - lengths
            steps = (starts + lengths // 2)[lengths >= len(symbols) / 40]
        for n in steps:
            axes[1].text(n, K - 0.45, names[symbols[n]], ha="center", va="bottom", fontsize=6,
                         color="red" if bad is not None and bad[n] else "black")
    return axes


def plot_phase_portrait(gating_u: np.ndarray, ax=None, title: str = ""):
    """Two gating potentials u^g_1 against u^g_2 (paper Figs. 4 and 15)."""
    ax = ax or plt.figure().gca()
    ax.plot(gating_u[:, 0], gating_u[:, 1], lw=0.3, rasterized=True)
    ax.set_xlabel("u^g_1")
    ax.set_ylabel("u^g_2")
    ax.set_title(title)
    return ax


def plot_residence(model_hist: np.ndarray, ax=None, switch_prob: float | None = None,
                   title: str = "repetitions of a curve before a switch",
                   censored_hist: np.ndarray | None = None):
    """Distribution of repetitions of a curve: model (pooled over runs) as bars, the geometric
    law (1 - P)^(k-1) P of the task as a line when P is known (paper Fig. 9). Stays cut off by
    the end of a sample (`censored_hist`, their true length is at least the one shown) are
    stacked on top, hatched; the last bin holds every longer stay."""
    ax = ax or plt.figure().gca()
    cut = np.zeros_like(model_hist) if censored_hist is None else censored_hist
    total = max(model_hist.sum() + cut.sum(), 1)
    model, censored = model_hist.sum(0) / total, cut.sum(0) / total
    k = np.arange(len(model))
    both = model + censored
    top = max(int(np.flatnonzero(both).max()) + 2 if both.any() else 10, 10)
    ax.bar(k[1:top], model[1:top], color="tab:blue", alpha=0.6, label="trained networks")
    if censored.any():
        ax.bar(k[1:top], censored[1:top], bottom=model[1:top], color="none",
               edgecolor="tab:blue", hatch="///", label="cut off by the sample's end (≥)")
    if switch_prob is not None:
        law = (1 - switch_prob) ** (k[1:top] - 1) * switch_prob
        ax.plot(k[1:top], law, "k.-", label=f"data: geometric, P = {switch_prob:g}")
    ax.set_xlabel("repetitions of a curve")
    ax.set_ylabel("probability")
    if both[1:top].any():
        ax.set_yscale("log")  # down to a tenth of the rarest observed count (or 1e-3)
        ax.set_ylim(min(both[both > 0].min() / 10, 1e-3), 1.5)
    ax.set_title(title)
    ax.legend(fontsize=8)
    return ax


def plot_run_trajectories(outputs: np.ndarray, gates: np.ndarray, titles: list[str]):
    """Small multiples: the closed-loop orbit of every run (R, T, D), coloured by the winning
    expert, each titled (e.g. by its switching probability and λ_max)."""
    R = len(outputs)
    cols = min(R, 6)
    rows = -(-R // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(max(2.2 * cols, 5.0), 2.3 * rows + 0.4),
                             constrained_layout=True, squeeze=False)
    colors = plt.get_cmap("tab10")
    for ax, points, gate, title in zip(axes.flat, outputs, gates, titles, strict=False):
        winners = gate.argmax(-1)
        ax.scatter(points[:, 0], points[:, 1], s=0.5, c=[colors(w % 10) for w in winners],
                   rasterized=True)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=7)
    for ax in list(axes.flat)[R:]:
        ax.axis("off")
    return fig


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
        if i >= K:  # the grid's spare panels
            ax.axis("off")
            continue
        if (winners == i).any():
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


def plot_residence_panels(hists: dict[float, tuple[np.ndarray, np.ndarray | None]]):
    """Residence-time distributions, one panel per switching probability P (paper Fig. 9):
    (completed, cut-off) histograms per P."""
    fig, axes = plt.subplots(1, len(hists), figsize=(4 * len(hists), 3.2),
                             constrained_layout=True, squeeze=False)
    for ax, (p, (hist, cut)) in zip(axes[0], sorted(hists.items(), reverse=True), strict=True):
        plot_residence(hist, ax=ax, switch_prob=p, censored_hist=cut)
        ax.set_title(f"P = {p:g}")
    return fig


def plot_scatter_by(runs: pd.DataFrame, x: str, y: str, group: str, reference=None,
                    band: float = 0.0, log_y: bool = False):
    """One point per network, coloured by `group` (e.g. the P = 0.5 study's arms); with
    `reference` (the data's value of `y`), its mean as a line and ±`band` shaded; a dotted
    line at x = 0 (the sign of λ_max is what matters); `log_y` for values spanning decades."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8), constrained_layout=True)
    names = list(dict.fromkeys(runs[group]))
    colours, markers = plt.get_cmap("tab10").colors, "os^D"  # 40 distinct (colour, marker)
    for i, name in enumerate(names):
        part = runs[runs[group] == name]
        ax.scatter(part[x], part[y], s=24, color=colours[i % 10], marker=markers[i // 10 % 4],
                   label=str(name), alpha=0.85, edgecolors="none")
    if reference is not None and len(reference.dropna()):
        level = float(reference.mean())
        ax.axhline(level, color="black", lw=1, label=f"data ({level:.3f})")
        if band:
            ax.axhspan(level - band, level + band, color="grey", alpha=0.2, lw=0,
                       label=f"±{band:g}")
    ax.axvline(0, color="grey", lw=0.8, ls=":")
    ax.set_xscale("symlog", linthresh=1e-4)
    ax.margins(x=0.08)
    if log_y:
        ax.set_yscale("log")
    label = {"max_lyapunov": "λ_max", "switch_prob": "switching probability",
             "block_kl_test": "block KL, test data", "context_size": "NC"}
    ax.set_xlabel(f"{label.get(x, x)} (symlog axis)")
    ax.set_ylabel(label.get(y, y))
    ax.set_title(f"{label.get(y, y)} against {label.get(x, x)}\n"
                 f"one point per network, by {label.get(group, group)}")
    ax.legend(fontsize=7, ncol=2, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return fig
