"""`report.md`, one page per run folder: what was trained, the metric table with the paper's
symbols, and every figure the folder holds, readable in any Markdown viewer (GitHub, an IDE)."""

from pathlib import Path

import pandas as pd

from moex import io, provenance
from moex.metrics.lyapunov import chaos_labels
from moex.metrics.table import METRICS, REPORTED
from moex.report import to_markdown

NAME = "report.md"
STARTS = {"random": "random initial states",  # eval.initial_states, in the page's words
          "trained": "trained initial states (sample n from series n mod S)"}
FIGURE_ORDER = ("learning_curves", "trajectory", "runs", "gates", "residence_times",
                "phase_portrait", "experts")


def lyapunov_cells(metrics: pd.DataFrame) -> list[str]:
    """λ_max ± its standard error and its chaos label, per run ("1 sample" where there is no
    error to give; "failed" for a failed run)."""
    labels = chaos_labels(metrics)
    samples = (metrics["lyapunov_samples"] if "lyapunov_samples" in metrics
               else metrics.get("num_samples", pd.Series(2, index=metrics.index)))
    se = metrics.get("max_lyapunov_se", pd.Series(float("nan"), index=metrics.index))
    return ["failed" if not pd.notna(v) else f"{v:.3g} (1 sample; {label})" if n == 1
            else f"{v:.3g} ± {s:.2g} ({label})"
            for v, s, n, label in zip(metrics["max_lyapunov"], se, samples, labels, strict=True)]


def trained_steps(out_dir: Path, cfg) -> str:
    """What training the networks had, as it happened: the C tools' epochs of an import (from
    imported_from.csv), phase 2 alone where the history has no phase 1 (a task without a signal
    for experts: Reber), else both phases' steps."""
    sources = Path(out_dir) / "imported_from.csv"
    if sources.exists():
        files = pd.read_csv(sources)
        files["name"] = files["file"].map(lambda f: Path(f).name)
        spans = files.groupby("name")["epochs"].agg(["min", "max"])
        epochs = ", ".join(f"{name} {lo}" + (f"-{hi}" if hi != lo else "")
                           for name, (lo, hi) in spans.iterrows())
        return f"trained by the authors' C tools (epochs: {epochs}), imported"
    if not _has_experts(out_dir):
        return f"{cfg.train.gating.steps} gating-phase steps (no experts: phase 1 does not run)"
    return f"{cfg.train.experts.steps} + {cfg.train.gating.steps} training steps"


def _has_experts(out_dir: Path) -> bool:
    """Whether the folder's history has phase-1 rows (True where there is no history)."""
    history = Path(out_dir) / io.HISTORY_CSV
    return not history.exists() or "experts" in set(pd.read_csv(history, usecols=["phase"])
                                                   ["phase"])


CHOSEN = ", chosen from the data by a pilot run: gate_prior.csv"


def write(out_dir: Path, cfg, metrics: pd.DataFrame | None, title: str) -> Path:
    """Write `out_dir`/report.md from the config, the metric table (None when not evaluated)
    and the figures in `out_dir`/figures."""
    out_dir = Path(out_dir)
    model, task = cfg.model, cfg.task
    lines = [f"# {title}", "",
             f"Task `{task.name}`, {cfg.num_runs} network(s) from seed {cfg.seed}; "
             f"{model.num_experts} experts of M = {model.experts.context_size}, gating RNN of "
             f"NC = {model.gating.context_size}, σ̄ = {model.sigma_min:.3g} (the floor of the "
             f"experts' σ), ς = {cfg.train.experts.gate_prior_std:g} (the β prior's scale"
             f"{CHOSEN if (out_dir / io.GATE_PRIOR).is_file() else ''}); "
             f"{trained_steps(out_dir, cfg)}; "
             f"{cfg.precision}, backend {cfg.backend} on {cfg.device}.", ""]
    if metrics is not None:
        ev = cfg.eval
        shown = ["run"] + [c for c in REPORTED if c in metrics] + ["failed"]
        table = metrics[shown].copy()
        for column in shown:  # four significant figures; λ_max with its standard error
            if column in METRICS and table[column].dtype.kind == "f":
                table[column] = table[column].map(lambda v: f"{v:.4g}")
        if "max_lyapunov" in metrics:
            table["max_lyapunov"] = lyapunov_cells(metrics)
        table = table.rename(columns={c: METRICS[c].text for c in shown if c in METRICS})
        lines += ["## Metrics (one row per network)", "",
                  f"Evaluated on {ev.num_samples} {STARTS[ev.initial_states]} × "
                  f"{ev.lyapunov_steps} closed-loop steps per network (after {ev.transient} "
                  f"discarded), noise "
                  f"variance {ev.noise_var:g}, symbol blocks of length {ev.block_length}.", "",
                  to_markdown(table), "",
                  "; ".join(f"{METRICS[c].text}: {METRICS[c].meaning}" for c in shown
                            if c in METRICS) + f"; λ_max ± its standard error (sd of the "
                  f"samples' own exponents / √samples) and its label: chaotic or not chaotic "
                  f"where it lies more than {ev.chaos_z:g} standard errors (and at least "
                  f"1/{ev.lyapunov_steps} per step) from 0, else undetermined; the paper "
                  f"calls λ_max > 0 chaotic whatever its error.", ""]
    figures = sorted((out_dir / io.FIGURES).glob("*.*"), key=lambda p: (
        FIGURE_ORDER.index(p.stem) if p.stem in FIGURE_ORDER else len(FIGURE_ORDER), p.name))
    if figures:
        lines += ["## Figures", ""]
        lines += [f"![{p.stem.replace('_', ' ')}]({io.FIGURES}/{p.name})" + "\n"
                  for p in figures]
    lines += [provenance.summary_line(provenance.records(out_dir)), "",
              "The whole configuration: " + ("`eval_config.yaml` (this re-evaluation's "
                                             "settings) and the training folder's "
                                             "`.hydra/config.yaml`."
                                             if (out_dir / io.EVAL_SETTINGS).exists() or
                                             not (out_dir / ".hydra").exists()
                                             else "`.hydra/config.yaml`."), ""]
    path = out_dir / NAME
    return io.atomic_write(path, lambda tmp: Path(tmp).write_text("\n".join(lines)))
