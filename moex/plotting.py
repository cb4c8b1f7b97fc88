"""Figures from DataFrames and arrays only: each `plot_*` draws on an Axes (or a figure of its
own) and returns it. One look for all of them: the style below, labels and scales from the
metric table (`moex.metrics.table`), colour-blind-safe colours, a symlog axis for Lyapunov
exponents (their sign is what matters), integer ticks for counts."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib import colors as mcolors  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from moex.io import atomic_write  # noqa: E402
from moex.metrics.switching import rle  # noqa: E402
from moex.metrics.table import METRICS, label  # noqa: E402

FORMATS = ("png", "pdf", "svg")
STYLE = {"font.size": 9, "axes.titlesize": 9, "axes.labelsize": 9, "legend.fontsize": 8,
         "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.spines.top": False,
         "axes.spines.right": False, "axes.formatter.useoffset": False, "legend.frameon": False}
plt.rcParams.update(STYLE)
OKABE_ITO = ["#0072B2", "#E69F00", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#F0E442",
             "#000000"]  # distinguishable with every common colour-vision deficiency
LINTHRESH = 1e-4  # λ_max below this in size is drawn linearly around 0


def palette(n: int) -> list:
    """n distinct colours: Okabe-Ito up to 8, tab20 up to 20, evenly spaced on turbo beyond."""
    if n <= len(OKABE_ITO):
        return OKABE_ITO[:n]
    if n <= 20:
        return list(plt.get_cmap("tab20").colors[:n])
    return [plt.get_cmap("turbo")(x) for x in np.linspace(0.05, 0.95, n)]


def scale_axis(ax, column: str, axis: str = "y") -> None:
    """The metric table's scale for `column` on one axis: log, symlog (exponents) or linear."""
    scale = METRICS[column].scale if column in METRICS else "linear"
    setter = ax.set_yscale if axis == "y" else ax.set_xscale
    if scale == "symlog":
        setter("symlog", linthresh=LINTHRESH)
        (ax.axhline if axis == "y" else ax.axvline)(0, color="0.5", lw=0.6, ls=":")
    elif scale == "log":
        setter("log")


LEARNING_PANELS = [  # (phase, column, title)
    ("experts", "E", "phase 1"),
    ("gating", "E_g", "phase 2"),
    ("gating", "lr_scale", "phase 2"),
    ("gating", "block_kl_train", "phase 2"),
    ("gating", "max_lyapunov", "phase 2"),
]


def plot_history(history: pd.DataFrame, column: str, ax=None):
    """`column` against the learning step: one line per run (its own colour) for up to 8 runs,
    with a band of ± 2 standard errors where the history has `<column>_se` (the tracked λ_max:
    a change inside the band is not told from the estimate's noise); beyond 8 runs, every run
    thin and grey with the median over runs on top."""
    ax = ax or plt.figure().gca()
    data = history.dropna(subset=[column])
    runs = sorted(data["run"].unique())
    colours = palette(len(runs)) if len(runs) <= 8 else None
    sparse = data.groupby("run").size().max() <= 30 if len(data) else False  # few logged steps
    for i, (run, group) in enumerate(data.groupby("run")):
        if colours:  # markers where the steps are few, so that lines are not read as dense data
            ax.plot(group["step"], group[column], lw=1, color=colours[i], label=f"run {run}",
                    marker="o" if sparse else None, ms=3)
            if f"{column}_se" in group:
                band = 2 * group[f"{column}_se"]
                ax.fill_between(group["step"], group[column] - band, group[column] + band,
                                color=colours[i], alpha=0.2, lw=0)
        else:
            ax.plot(group["step"], group[column], lw=0.5, color="0.65",
                    label=f"each of {len(runs)} runs" if run == runs[0] else None)
    if colours is None:
        median = data.groupby("step")[column].median()
        ax.plot(median.index, median.to_numpy(), lw=2, color=OKABE_ITO[0],
                label="median over runs")
    ax.set_xlabel("learning step")
    ax.set_ylabel(label(column))
    scale_axis(ax, column)
    return ax


def plot_learning_curves(history: pd.DataFrame, title: str = ""):
    """E of phase 1; E^g, the adaptive rate and, when tracked, the block KL and λ_max of phase 2
    (paper Figs. 3, 6, 11), at most three panels a row (four as 2 × 2), one legend; `title`
    names the task and runs. The adaptive rate is the factor α/α̃ by which the adaptive rule
    (Sec. 2.1.4) has scaled the learning rate: it grows by 1.05 per accepted step with a falling
    error and shrinks by 0.7 per rejected one."""
    panels = [p for p in LEARNING_PANELS if p[1] in history
              and history.loc[history["phase"] == p[0], p[1]].notna().any()]
    cols = 2 if len(panels) == 4 else min(max(len(panels), 1), 3)
    rows = -(-max(len(panels), 1) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.8 * rows + 0.5),
                             constrained_layout=True, squeeze=False)
    for ax, (phase, column, name) in zip(axes.flat, panels, strict=False):
        plot_history(history[history["phase"] == phase], column, ax=ax)
        band = " (band ± 2 s.e.)" if f"{column}_se" in history else ""
        ax.set_title(f"{name}: {label(column)}{band}")
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 8))
    if any(column == "lr_scale" for _, column, _ in panels):
        title = (f"{title}\n" if title else "") + ("α/α̃: the adaptive rule's factor on the "
                                                  "learning rate (×1.05 after a step that "
                                                  "lowers the error, ×0.7 per retry)")
    if title:
        fig.suptitle(title, fontsize=9)
    return fig


def save_figure(fig, path, fmt: str = "png") -> Path:
    """Write the figure atomically as `fmt` (png, pdf or svg; the suffix of `path` follows) and
    close it."""
    path = Path(path).with_suffix(f".{fmt}")
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=150, format=fmt, bbox_inches="tight"))
    plt.close(fig)
    return path


def _output_axes(ax, D: int) -> None:
    ax.set_aspect("equal")
    ax.set_xlabel("$y_1$")
    ax.set_ylabel("$y_2$" if D > 1 else "")


def plot_teaching_data(series: np.ndarray, ax=None, title: str = "teaching data"):
    """Training series (S, T, D >= 2) as dark lines in the (y_1, y_2) plane."""
    ax = ax or plt.figure().gca()
    for s in series:
        ax.plot(s[:, 0], s[:, 1], color="black", lw=0.6, alpha=0.7)
    _output_axes(ax, series.shape[-1])
    ax.set_title(title)
    return ax


def plot_trajectory(points: np.ndarray, gates: np.ndarray, ax=None, title: str = ""):
    """A closed-loop orbit (T, D >= 2), each step coloured by its winning expert (gates (T, K),
    K distinct colours), with a key of the experts that win somewhere below the plot."""
    ax = ax or plt.figure().gca()
    winners = gates.argmax(-1)
    colours = palette(gates.shape[-1])
    for k in np.unique(winners):
        mask = winners == k
        ax.scatter(points[mask, 0], points[mask, 1], s=2, color=colours[k], rasterized=True,
                   label=f"expert {k} ({mask.mean():.0%})")
    _output_axes(ax, points.shape[-1])
    ax.set_title(title)
    ax.legend(markerscale=4, loc="upper center", bbox_to_anchor=(0.5, -0.17),
              ncol=min(len(np.unique(winners)), 4), title="winning expert (share of steps)")
    return ax


def plot_gate_series(outputs: np.ndarray, gates: np.ndarray, symbols: np.ndarray,
                     names: list[str], *, axes=None, bad: np.ndarray | None = None):
    """Outputs (T, D) over the gate openings (T, K), labelled with the symbol of each step
    (beyond 120 steps, of each run of one symbol that is not a brief flicker); steps flagged in
    `bad` (T,) are labelled in red (paper Figs. 4, 8 and 13), a symbol beyond `names` (the
    threshold rule's "no gate above 0.5") as "–". D = 0: the gates alone."""
    if axes is None:
        rows = 2 if outputs.shape[1] else 1
        fig, axes = plt.subplots(rows, 1, figsize=(10, 2.2 * rows + 0.6), sharex=True,
                                 constrained_layout=True, squeeze=False)
        axes = list(axes[:, 0]) if rows == 2 else [axes[0, 0], axes[0, 0]]
    for d in range(outputs.shape[1]):  # black and grey: the experts' colours mean experts
        axes[0].plot(outputs[:, d], lw=1, color=("black", "0.55", "0.8")[d % 3],
                     ls=("-", "-", "--")[d % 3], label=f"$y_{{{d + 1}}}$")
    if outputs.shape[1]:  # the legend beside the panel, never over the signal
        axes[0].set_ylabel("output")
        axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    K = gates.shape[1]
    image = axes[1].imshow(gates.T, aspect="auto", origin="lower", cmap="Greys", vmin=0, vmax=1,
                           interpolation="nearest", extent=(-0.5, len(gates) - 0.5, -0.5, K - 0.5))
    if outputs.shape[1] or len(names) != K:
        axes[1].set_yticks(range(0, K, max(1, int(np.ceil(K / 12)))))  # at most 12 labels
        axes[1].set_ylabel("expert")
    else:  # no signal (Reber): one gate per symbol, named by it
        axes[1].set_yticks(range(K), [f"{k} ({name})" for k, name in enumerate(names)])
        axes[1].set_ylabel("gate (its symbol)")
    axes[1].set_xlabel(f"step (the last {len(gates)} steps of the sample)")
    axes[1].figure.colorbar(image, ax=axes[1], label="gate opening g", pad=0.01, fraction=0.03)
    if names:  # every step's symbol in a short window, else the middle of each run of one
        # symbol lasting at least 1/40 of the window (no overlapping labels for flickers)
        steps = range(len(symbols))
        if len(symbols) > 120:
            _, lengths = rle(symbols)
            starts = np.cumsum(lengths) - lengths
            steps = (starts + lengths // 2)[lengths >= len(symbols) / 40]
        for n in steps:
            name = names[symbols[n]] if symbols[n] < len(names) else "–"  # no gate above 0.5
            axes[1].text(n, K - 0.45, name, ha="center", va="bottom", fontsize=8,
                         color="red" if bad is not None and bad[n] else "black")
        source = ("the symbol its largest gate emits" if not outputs.shape[1] else
                  "the primitive the output is nearest to")
        axes[1].set_title(f"symbol of each step ({source}; red: a step the grammar forbids)"
                          if bad is not None else f"symbol of each step ({source}: "
                          + ", ".join(names) + ")", fontsize=8, loc="left", pad=16)
    return axes


def plot_phase_portrait(gating_u: np.ndarray, ax=None, title: str = ""):
    """The first two gating potentials u^g_0 against u^g_1 (paper Figs. 4 and 15; units counted
    from 0, as experts and runs are), one dot per step; a fixed point or a short cycle is said so
    in the title."""
    ax = ax or plt.figure(figsize=(4.2, 4)).gca()
    points = gating_u[:, :2]
    span = np.ptp(points, axis=0).max() if len(points) else 0.0
    distinct = len(np.unique(np.round(points, 6), axis=0)) if len(points) else 0
    ax.scatter(points[:, 0], points[:, 1], s=0.5, color=OKABE_ITO[0], rasterized=True,
               alpha=0.6 if len(points) > 2000 else 1.0, lw=0)
    if span < 1e-9:
        note = f"a fixed point at ({points[0, 0]:.4g}, {points[0, 1]:.4g})"
        ax.plot(points[:1, 0], points[:1, 1], "o", ms=6, color=OKABE_ITO[0])  # visible alone
        ax.set_xlim(points[0, 0] - 0.1, points[0, 0] + 0.1)
        ax.set_ylim(points[0, 1] - 0.1, points[0, 1] + 0.1)
    elif distinct <= 50:
        note = f"{distinct} distinct points: a cycle"
    else:
        note = f"{len(points)} steps"
    H = gating_u.shape[-1]
    ax.xaxis.set_major_locator(plt.MaxNLocator(5))  # tick labels that never overprint
    ax.set_xlabel(f"$u^g_0$ (gating unit 0 of 0-{H - 1})")
    ax.set_ylabel("$u^g_1$ (gating unit 1)")
    ax.set_title(f"{title}\n{note}".strip())
    return ax


def plot_residence(model_hist: np.ndarray, ax=None, switch_prob: float | None = None,
                   title: str = "repetitions of a curve before a switch",
                   censored_hist: np.ndarray | None = None):
    """Distribution of repetitions of a curve, (runs, bins) counts: the runs' own distributions
    averaged (each run weighs the same, as in paper Fig. 9) as bars, the geometric law
    (1 - P)^(k-1) P of the task as a line when P is known. Stays cut off by the end of a sample
    (`censored_hist`, their true length is at least the one shown) are stacked on top, hatched;
    the last bin holds every longer stay."""
    ax = ax or plt.figure(figsize=(5, 3.6)).gca()
    cut = np.zeros_like(model_hist) if censored_hist is None else censored_hist
    totals = (model_hist.sum(1) + cut.sum(1))[:, None]
    weight = np.divide(1.0, totals, out=np.zeros(totals.shape), where=totals > 0)
    runs = max(int((totals > 0).sum()), 1)
    model, censored = (model_hist * weight).sum(0) / runs, (cut * weight).sum(0) / runs
    k = np.arange(len(model))
    both = model + censored
    top = max(int(np.flatnonzero(both).max()) + 2 if both.any() else 10, 10)
    # bars at least 1/50 of the axis wide (the last bin of 100 is no 1-pixel sliver)
    width = np.full(len(k[1:top]), 0.8)
    if top >= len(k):  # the overflow bin
        width[-1] = max(0.8, len(k) / 50)
    if both[1:top].any():
        ax.bar(k[1:top], model[1:top], width=width, color=OKABE_ITO[0], alpha=0.6,
               label="trained networks")
    if censored.any():
        ax.bar(k[1:top], censored[1:top], width=width, bottom=model[1:top], color="none",
               edgecolor=OKABE_ITO[0], hatch="///", label="cut off by the sample's end (≥)")
    if switch_prob is not None:
        law = (1 - switch_prob) ** (k[1:top] - 1) * switch_prob
        if top >= len(k):  # the last bin holds every longer stay: the law's tail mass
            law[-1] = (1 - switch_prob) ** (k[-1] - 1)
        ax.plot(k[1:top], law, ".-", color="black", label=f"data: geometric, P = {switch_prob:g}")
    if not both[1:top].any():
        ax.text(0.5, 0.5, "no stay recorded: the closed loop never completed a curve",
                ha="center", va="center", transform=ax.transAxes)
    last = f" (the last bar, {len(k) - 1}: every stay at least as long)" \
        if top >= len(k) and both[-1] > 0 else ""
    ax.set_xlabel(f"repetitions of a curve{last}")
    ax.set_ylabel("probability")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_yscale("log")  # always: panels compare; down to a tenth of the rarest count
    floor = both[both > 0].min() / 10 if both.any() else 1e-3
    ax.set_ylim(min(floor, 1e-3), 1.5)
    ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    return ax


def plot_run_trajectories(outputs: np.ndarray, gates: np.ndarray, titles: list[str],
                          title: str = ""):
    """Small multiples: the closed-loop orbit of every run (R, T, D) on one common scale,
    coloured by the winning expert (one key for all), each titled (e.g. by its λ_max and
    switching probability); spare panels hidden."""
    R, K = len(outputs), gates.shape[-1]
    cols = min(R, 5)
    rows = -(-R // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(max(2.3 * cols, 5.0), 2.6 * rows + 1.2),
                             layout="constrained", squeeze=False, sharex=True, sharey=True)
    if title:  # wrapped to the figure's width (about 9 characters an inch at this size)
        import textwrap

        fig.suptitle("\n".join(textwrap.wrap(title, int(fig.get_figwidth() * 9))))
    colours = np.array(palette(K), dtype=object)
    # one scale for all, a margin beyond the farthest point (never on the spine), at least ±0.1
    reach = max(1.15 * float(np.nanmax(np.abs(outputs[..., :2]))) if outputs.size else 1.0, 0.1)
    for ax, points, gate, title in zip(axes.flat, outputs, gates, titles, strict=False):
        ax.scatter(points[:, 0], points[:, 1], s=0.5, c=list(colours[gate.argmax(-1)]),
                   rasterized=True)
        ax.set_aspect("equal")
        ax.set_xlim(-reach, reach)
        ax.set_ylim(-reach, reach)
        ax.set_title(title, fontsize=9)  # as large as the tick labels
    for ax in list(axes.flat)[R:]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("$y_1$")
    for ax in axes[:, 0]:
        ax.set_ylabel("$y_2$")
    won = np.unique(gates.argmax(-1)).tolist()  # the key lists only the winners
    if len(won) <= 12:
        handles = [plt.Line2D([], [], ls="", marker="o", color=colours[k], label=f"expert {k}")
                   for k in won]
        fig.legend(handles=handles, loc="outside lower center", ncol=min(len(won), 6),
                   title="colour: the winning expert")
    return fig


def plot_expert_panels(outputs: np.ndarray, gates: np.ndarray, axes=None, title: str = ""):
    """Output y_n where expert i wins (s_n = i), one panel per expert that wins somewhere, on one
    common scale (paper Fig. 12b); the experts that never win are listed in the figure's
    title."""
    K = gates.shape[1]
    winners = gates.argmax(1)
    shown = [i for i in range(K) if (winners == i).any()]
    if axes is None:
        cols = int(np.ceil(np.sqrt(len(shown))))
        _, axes = plt.subplots(int(np.ceil(len(shown) / cols)), cols,
                               figsize=(2 * cols, 2 * cols + 0.4), constrained_layout=True,
                               squeeze=False)
    colours = palette(K)
    grid = np.atleast_2d(axes)
    for j, ax in enumerate(np.ravel(axes)):
        if j >= len(shown):  # the grid's spare panels
            ax.set_visible(False)
            continue
        i = shown[j]
        ax.scatter(outputs[winners == i, 0], outputs[winners == i, 1], s=1, color=colours[i])
        ax.set_xlim(-1.05, 1.05)  # the common scale [-1, 1], a point on its edge off the spine
        ax.set_ylim(-1.05, 1.05)
        ax.set_aspect("equal")
        ax.set_xticks([-1, 0, 1])
        ax.set_yticks([-1, 0, 1])
        ax.tick_params(labelsize=6)
        # labels on the outer panels only: y_1 where no panel is below, y_2 in the first column
        ax.set_xlabel("$y_1$" if j + grid.shape[1] >= len(shown) else "", fontsize=7)
        ax.set_ylabel("$y_2$" if j % grid.shape[1] == 0 else "", fontsize=7)
        ax.set_title(f"expert {i} ({(winners == i).mean():.0%})", fontsize=7)
    never = [i for i in range(K) if i not in shown]
    lines = [title] if title else []
    if never:
        lines.append(f"{len(never)} of {K} experts never win: {', '.join(map(str, never))}")
    if lines:
        np.ravel(axes)[0].figure.suptitle("\n".join(lines), fontsize=8)
    return axes


HEAT_LABELS = {"positive_percent": r"share with $\lambda_{\max} > 0$, the paper's criterion (%)",
               "chaotic_percent": r"share chaotic: $\lambda_{\max}$ above 0 beyond its error (%)",
               "task.num_series": "number of series NT", "task.length": "length of a series LT"}


def _column_label(column: str, sep: str = " ") -> str:
    """`E_closed_mean` -> the metric's label, `sep`, "(mean over networks)"."""
    if column in HEAT_LABELS:
        return HEAT_LABELS[column]
    base = column.removesuffix("_mean")
    return f"{label(base)}{sep}(mean over networks)" if base != column else label(column)


def plot_heatmap(table: pd.DataFrame, x: str, y: str, value: str, *, title: str = "", ax=None,
                 limits: tuple[float, float] | None = None, colorbar: bool = True):
    """NT × LT phase plot of one column (paper Figs. 14 and 16), the value written in each cell;
    a missing cell stays blank and says "not run". `limits`: the colour range, shared by the
    panels compared; `colorbar=False` leaves the colour bar to a neighbouring panel of that
    range."""
    grid = table.pivot_table(index=y, columns=x, values=value, aggfunc="mean")
    if ax is None:
        fig, ax = plt.subplots(figsize=(4.6, 3.6), constrained_layout=True)
    values = grid.to_numpy(dtype=float)
    log = value.removesuffix("_mean") in METRICS and METRICS[
        value.removesuffix("_mean")].scale == "log" and np.nanmin(values, initial=1) > 0
    norm = matplotlib.colors.LogNorm(*limits) if log and limits else None
    mesh = ax.imshow(values, origin="lower", cmap="viridis", aspect="auto", norm=norm,
                     vmin=None if norm else (limits or (None, None))[0],
                     vmax=None if norm else (limits or (None, None))[1])
    for (i, j), v in np.ndenumerate(values):
        if np.isfinite(v):
            shade = mesh.norm(v)
            ax.text(j, i, f"{v:.3g}", ha="center", va="center", fontsize=8,
                    color="black" if shade > 0.6 else "white")
        else:
            ax.text(j, i, "not run", ha="center", va="center", fontsize=7, color="0.45")
    ax.set_xticks(range(grid.shape[1]), [f"{v:g}" for v in grid.columns])
    ax.set_yticks(range(grid.shape[0]), [f"{v:g}" for v in grid.index])
    ax.set_xlabel(HEAT_LABELS.get(x, x))
    ax.set_ylabel(HEAT_LABELS.get(y, y))
    ax.spines[["top", "right"]].set_visible(True)
    ax.set_title(title)
    if colorbar:
        ax.figure.colorbar(mesh, ax=ax, label=_column_label(value, sep="\n"))
    return ax.figure


def plot_heatmaps(panels: list[tuple[str, pd.DataFrame]], x: str, y: str, value: str,
                  limits: tuple[float, float]):
    """Several NT × LT heat maps of one column side by side (up to 4 a row), one colour range
    and one colour bar for all; `panels`: (title, table) each."""
    columns = min(len(panels), 4)
    rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.9 * columns + 0.9, 3.4 * rows),
                             constrained_layout=True, squeeze=False)
    for i, ax in enumerate(axes.flat):
        if i >= len(panels):
            ax.set_visible(False)
            continue
        title, table = panels[i]
        plot_heatmap(table, x, y, value, title=title, ax=ax, limits=limits,
                     colorbar=i == len(panels) - 1)
    return fig


def plot_residence_panels(hists: dict[float, tuple[np.ndarray, np.ndarray | None]]):
    """Residence-time distributions, one panel per switching probability P (paper Fig. 9):
    (completed, cut-off) histograms per P."""
    fig, axes = plt.subplots(1, len(hists), figsize=(4 * len(hists), 3.2),
                             constrained_layout=True, squeeze=False)
    for ax, (p, (hist, cut)) in zip(axes[0], sorted(hists.items(), reverse=True), strict=True):
        plot_residence(hist, ax=ax, switch_prob=p, censored_hist=cut)
        ax.set_title(f"P = {p:g}")
    labels = {ax.get_xlabel() for ax in axes[0]}  # one x label for the row: none overlap
    for ax in axes[0]:
        ax.set_xlabel("")
    fig.supxlabel(max(labels, key=len))
    return fig


def plot_scatter_by(runs: pd.DataFrame, x: str, y: str, group: str, *, reference=None,
                    band: float = 0.0, log_y: bool = False):
    """One point per network, coloured by `group` (e.g. the P = 0.5 study's arms; networks
    without a value, as in a run that is not a study arm, form one group); with
    `reference` (the data's value of `y`), its mean as a line and ±`band` shaded; a dotted
    line at x = 0 (the sign of λ_max is what matters); `log_y` for values spanning decades."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8), constrained_layout=True)
    groups = runs[group].astype(object).where(runs[group].notna(), "all networks")
    names = list(dict.fromkeys(groups))
    colours, markers = palette(min(len(names), 20)), "os^D"  # 80 distinct (colour, marker)
    for i, name in enumerate(names):
        part = runs[groups == name]
        ax.scatter(part[x], part[y], s=24, color=colours[i % len(colours)],
                   marker=markers[i // len(colours) % 4], label=str(name), alpha=0.85,
                   edgecolors="none")
    if reference is not None and len(reference.dropna()):
        levels = reference.groupby(groups).mean()  # the data's value per group
        one = levels.nunique() == 1
        for i, name in enumerate(names):
            level = float(levels[name]) if name in levels and pd.notna(levels[name]) else None
            if level is None or (one and i):
                continue
            ax.axhline(level, color="black" if one else colours[i % len(colours)], lw=1,
                       ls="-" if one else "--",
                       label=f"data ({level:.3f})" if one else f"data of {name} ({level:.3f})")
            if band:
                ax.axhspan(level - band, level + band, color="grey", alpha=0.15, lw=0,
                           label=f"within ±{band:g} of the data" if i == 0 else None)
    ax.axvline(0, color="grey", lw=0.8, ls=":")
    wide = bool((runs[x].abs() > LINTHRESH).any())  # else symlog's ticks fall outside the data
    if wide:
        ax.set_xscale("symlog", linthresh=LINTHRESH)
    else:
        ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 3), useOffset=False)
    ax.margins(x=0.08)
    if log_y:
        ax.set_yscale("log")
    names_of = {"model.gating.context_size": "NC (context units of the gating RNN)",
                "p05_arm": "study arm", "task.switch_prob": "P (the data's switching probability)"}
    ax.set_xlabel(f"{label(x)} (linear within ±{LINTHRESH:g}, logarithmic beyond)" if wide
                  else label(x))
    ax.set_ylabel(label(y))
    ax.set_title(f"{label(y)} against {label(x)}, one point per network")
    import textwrap

    handles, labels = ax.get_legend_handles_labels()  # long setting names wrapped, not wide
    labels = ["\n".join(textwrap.wrap(text, 32)) for text in labels]
    ax.legend(handles, labels, fontsize=7, ncol=2 if len(labels) > 8 else 1, loc="center left",
              bbox_to_anchor=(1.01, 0.5),
              title=names_of.get(group, group) if runs[group].notna().any() else None)
    return fig


def plot_segments(gates: np.ndarray, labels: np.ndarray | None, delay: int,
                  label_of_expert: np.ndarray | None = None, title: str = ""):
    """One run's segmentation of up to 3 series: per series a band of the winning expert over
    time (argmax of gates (S, N, K), at data steps n + τ) under a band of the true labels
    (S, T) where known. An expert matched to a label shares its colour (the best one-to-one
    matching); unmatched experts are grey."""
    S = min(3, len(gates))
    K = gates.shape[-1]
    known = labels is not None and (labels >= 0).any()
    L = int(labels.max()) + 1 if known else 0
    colours = palette(max(L, K))
    if known and label_of_expert is not None:
        expert_colours = [colours[lab] if lab >= 0 else "0.6" for lab in label_of_expert]
    else:
        expert_colours = colours[:K]
    bands = 2 if known else 1
    fig, axes = plt.subplots(S * bands, 1, figsize=(9, 0.7 * S * bands + 1.2), sharex=True,
                             constrained_layout=True, squeeze=False)
    axes = axes[:, 0]
    steps = np.arange(gates.shape[1]) + delay
    for s in range(S):
        rows = [("expert", gates[s].argmax(-1), expert_colours)]
        if known:
            rows.insert(0, ("label", labels[s, delay:], colours[:L] + ["white"]))
        for i, (name, values, cols) in enumerate(rows):
            ax = axes[s * bands + i]
            cmap = mcolors.ListedColormap(cols)
            shown = np.where(values < 0, len(cols) - 1, values)  # unknown labels blank
            ax.imshow(shown[None], aspect="auto", cmap=cmap, vmin=-0.5,
                      vmax=len(cols) - 0.5, interpolation="nearest",
                      extent=(steps[0] - 0.5, steps[-1] + 0.5, 0, 1))
            ax.set_yticks([])
            ax.set_ylabel(f"series {s}\n{name}", rotation=0, ha="right", va="center",
                          fontsize=8)
    axes[-1].set_xlabel("time step")
    handles = [plt.Rectangle((0, 0), 1, 1, color=expert_colours[k]) for k in range(K)]
    names = [f"expert {k}" + (f" = label {label_of_expert[k]}" if known and
                              label_of_expert is not None and label_of_expert[k] >= 0 else "")
             for k in range(K)]
    fig.legend(handles, names, loc="outside lower center", ncol=min(K, 6), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    return fig
