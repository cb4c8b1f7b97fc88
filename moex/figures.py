"""The figures a run folder gets and what they show: which run the single-run figures show and
why (`plot.run`, else the largest λ_max), titles that state each run's facts, the closed loop's
figures, and the segmentation's figure and tables."""

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from moex import io, plotting, segment
from moex.config import Config
from moex.tasks import Dataset


def _chosen_run(cfg: Config, metrics: pd.DataFrame | None) -> tuple[int, str]:
    """The run the single-run figures show, and a title that says which and why."""
    R = cfg.num_runs
    runs = numbered("run", R) if R > 1 else "the only run"
    if cfg.plot.run >= 0:  # checked against num_runs with the config (load_task)
        return cfg.plot.run, f"run {cfg.plot.run} ({runs}; plot.run)"
    ok = None if metrics is None else metrics[~metrics["failed"].astype(bool)]
    if ok is None or ok["max_lyapunov"].isna().all():
        return 0, f"run 0 ({runs})"
    run = int(ok.loc[ok["max_lyapunov"].idxmax(), "run"])
    lam = ok["max_lyapunov"].max()
    return run, f"run {run} ({runs}; the largest $\\lambda_{{\\max}}$ = {lam:+.1e})"


def numbered(noun: str, shown: int, total: int | None = None) -> str:
    """"run 0", "runs 0-4", "series 0-2 of 10": the indices shown (of `total` where more)."""
    plural = noun if noun.endswith("s") else f"{noun}s"
    text = f"{noun} 0" if shown == 1 else f"{plural} 0-{shown - 1}"
    return text + (f" of {total}" if total is not None and total > shown else "")


def _run_title(row) -> str:
    """A panel title that states the run's facts."""
    if row["failed"]:
        return f"run {row['run']}: failed"
    data = row.get("data_switch_prob", np.nan)
    label = f" ({row['chaos']})" if isinstance(row.get("chaos"), str) and row["chaos"] else ""
    return (f"run {row['run']}: $\\lambda_{{\\max}}$ = {row['max_lyapunov']:+.1e}{label}\n"
            f"switching {row.get('switch_prob', np.nan):.2f}"
            + (f" (data {data:.2f})" if np.isfinite(data) else ""))


def plot_samples(samples: dict, dataset: Dataset, cfg: Config, out_dir: Path,
                  *, metrics: pd.DataFrame | None = None, noise_var: float = 0.0) -> None:
    """Figures of one run's closed-loop sample, and of every run (small multiples, residence
    times) when the metric table is there to title them; titles name the noise on x_n."""
    figures, fmt = out_dir / io.FIGURES, cfg.plot.format
    run, label = _chosen_run(cfg, metrics)
    noisy = f", noise ρ² = {noise_var:g}" if noise_var > 0 else ""
    label += noisy
    outputs, gates = samples["outputs"][run], samples["gates"][run]
    gating_u, symbols = samples["gating_u"][run], samples["symbols"][run]
    if outputs.shape[-1] >= 2:
        fig, axes = plt.subplots(1, 2, figsize=(9, 5), constrained_layout=True, sharex=True,
                                 sharey=True)
        S = len(dataset.series)
        plotting.plot_teaching_data(dataset.scale.to_data(dataset.series[:3]), axes[0],
                                    f"teaching data ({numbered('series', min(3, S), S)})")
        plotting.plot_trajectory(outputs, gates, axes[1],
                                 f"closed loop, {label}\nlast {len(outputs)} steps")
        plotting.save_figure(fig, figures / "trajectory.png", fmt)
    shown = slice(-min(len(symbols), max(100, round(10 * dataset.period))), None)
    bad = dataset.violations(symbols[shown]) if dataset.violations else None
    axes = plotting.plot_gate_series(outputs[shown], gates[shown], symbols[shown],
                                     dataset.symbol_names, bad=bad)
    axes[0].figure.suptitle(f"closed loop, {label}: " + ("outputs, gate openings and symbols"
                                                         if outputs.shape[-1] else
                                                         "gate openings and symbols"),
                            fontsize=10)
    plotting.save_figure(axes[0].figure, figures / "gates.png", fmt)
    if gating_u.shape[-1] >= 2:
        tail = gating_u[len(gating_u) // 10:]  # the first tenth as a transient
        ax = plotting.plot_phase_portrait(tail, title=f"gating potentials, {label}")
        plotting.save_figure(ax.figure, figures / "phase_portrait.png", fmt)
    if metrics is not None and dataset.prototypes is not None:
        pooled = "1 run" if cfg.num_runs == 1 else f"averaged over {cfg.num_runs} runs"
        ax = plotting.plot_residence(samples["residence_hist"], switch_prob=dataset.switch_prob,
                                     censored_hist=samples.get("residence_censored_hist"),
                                     title=f"repetitions of a curve before a switch, {pooled}"
                                           f"{noisy}")
        plotting.save_figure(ax.figure, figures / "residence_times.png", fmt)
    if metrics is not None and outputs.shape[-1] >= 2:
        fig = plotting.plot_run_trajectories(
            samples["outputs"], samples["gates"],
            [_run_title(row) + ("\na fixed point" if np.ptp(out, axis=0).max() < 1e-3 else "")
             for (_, row), out in zip(metrics.iterrows(), samples["outputs"], strict=True)],
            f"the closed loop of {'each of the ' * (cfg.num_runs > 1)}"
            f"{numbered('run', cfg.num_runs)}, last "
            f"{samples['outputs'].shape[1]} steps{noisy}")
        plotting.save_figure(fig, figures / "runs.png", fmt)
    if gates.shape[-1] > 2 and outputs.shape[-1] >= 2:
        axes = plotting.plot_expert_panels(outputs, gates, title=f"where each expert wins, {label}")
        plotting.save_figure(axes.flat[0].figure, figures / "experts.png", fmt)


def write_segments(out_dir: Path, gates: np.ndarray, labels: np.ndarray | None, *, cfg: Config,
                   what: str, table: bool = True, scores: bool = True,
                   prior_std: np.ndarray | None = None) -> segment.Segmentation:
    """figures/segments.png of the run with the best adjusted Rand index (else run 0), with
    `table` segments.csv, with `scores` and labels segment_scores.csv (a training run has its
    scores in metrics.csv; `prior_std`, the ς each run smoothed with, becomes a column and the
    drawn run's enters the title)."""
    result = segment.segmentation(gates, labels, cfg.model.delay)
    if prior_std is not None and len(result.scores):
        result.scores["gate_prior_std"] = prior_std[result.scores["run"].to_numpy()]
    if table:
        io.write_csv(out_dir / io.SEGMENTS, result.table)
    run, matching, scored = 0, None, ""
    if len(result.scores):
        if scores:
            io.write_csv(out_dir / io.SEGMENT_SCORES, result.scores)
        best = result.scores.loc[result.scores["segment_ari"].idxmax()]
        run, matching = int(best["run"]), result.label_of_expert[int(best["run"])]
        scored = f"; ARI {best['segment_ari']:.3f}, accuracy {best['segment_accuracy']:.3f}"
    if prior_std is not None:
        what += f" (ς = {prior_std[run]:g})"
    fig = plotting.plot_segments(gates[run], labels, cfg.model.delay, matching,
                                 f"winning expert per step, run {run}: {what}{scored}")
    plotting.save_figure(fig, out_dir / io.FIGURES / "segments.png", cfg.plot.format)
    return result
