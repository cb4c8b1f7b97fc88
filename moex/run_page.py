"""`report.md`, one page per run folder: what was trained, the metric table with the paper's
symbols, and every figure the folder holds, readable in any Markdown viewer (GitHub, an IDE)."""

from pathlib import Path

import pandas as pd

from moex import io, provenance
from moex.metrics.table import METRICS, REPORTED
from moex.report import to_markdown

NAME = "report.md"
FIGURE_ORDER = ("learning_curves", "trajectory", "runs", "gates", "residence_times",
                "phase_portrait", "experts")


def write(out_dir: Path, cfg, metrics: pd.DataFrame | None, title: str) -> Path:
    """Write `out_dir`/report.md from the config, the metric table (None when not evaluated)
    and the figures in `out_dir`/figures."""
    out_dir = Path(out_dir)
    train, model, task = cfg.train, cfg.model, cfg.task
    lines = [f"# {title}", "",
             f"Task `{task.name}`, {cfg.num_runs} network(s) from seed {cfg.seed}; "
             f"{model.num_experts} experts of M = {model.experts.context_size}, gating RNN of "
             f"NC = {model.gating.context_size}; {train.experts.steps} + {train.gating.steps} "
             f"training steps; {cfg.precision}, backend {cfg.backend} on {cfg.device}.", ""]
    if metrics is not None:
        shown = ["run"] + [c for c in REPORTED if c in metrics] + ["failed"]
        table = metrics[shown].rename(columns={c: METRICS[c].text for c in shown
                                               if c in METRICS})
        lines += ["## Metrics (one row per network)", "", to_markdown(table), "",
                  "; ".join(f"{METRICS[c].text}: {METRICS[c].meaning}" for c in shown
                            if c in METRICS) + ".", ""]
    figures = sorted((out_dir / io.FIGURES).glob("*.*"), key=lambda p: (
        FIGURE_ORDER.index(p.stem) if p.stem in FIGURE_ORDER else len(FIGURE_ORDER), p.name))
    if figures:
        lines += ["## Figures", ""]
        lines += [f"![{p.stem.replace('_', ' ')}]({io.FIGURES}/{p.name})" + "\n"
                  for p in figures]
    lines += [provenance.summary_line(provenance.records(out_dir)), "",
              "The whole configuration: `.hydra/config.yaml` (training) and "
              "`eval_config.yaml` (a re-evaluation).", ""]
    path = out_dir / NAME
    return io.atomic_write(path, lambda tmp: Path(tmp).write_text("\n".join(lines)))
