"""`moex train`: train R runs of the mixture on the task (resumable), then write the run folder:
history, metrics, samples, figures and the run's page."""

import logging
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import checkpoint, io, pilot, plotting, progress, provenance, run_page, segment
from moex.config import Config
from moex.data import in_data_units, load_task, warn_ignored
from moex.errors import never
from moex.evaluation import evaluate
from moex.figures import numbered, plot_samples, write_segments
from moex.jobs import Job, run_generators, train_jobs
from moex.kernels import Backend, check_backend, get_backend
from moex.metrics.lyapunov import CHAOS_LABELS
from moex.metrics.table import LOGGED, METRICS
from moex.model import gate_estimates
from moex.resume import open_checkpoint
from moex.tasks import TASKS, Dataset

log = logging.getLogger(__name__)

NAME, CONFIG = "train", "config"  # the verb and its Hydra config


def check(cfg: Config) -> None:
    """Everything `run` refuses, before its folder is made: the backend, the task, its data."""
    check_backend(cfg.backend, cfg.device)
    pilot.check_pilot(cfg, load_task(cfg))


def run(cfg: Config, out_dir: Path, stop=never) -> checkpoint.Checkpoint:
    """Train R runs of the mixture on the task and write the run folder; resumable.

    A checkpoint already in `out_dir` (from the same config) is continued: a finished run is not
    redone, an interrupted phase resumes at its saved step with the same result as an
    uninterrupted run. Checkpoints are written every `train.checkpoint_every` steps and when
    `stop` reports a signal (then `TrainingInterrupted` is raised). A folder whose networks the
    packed launcher trained (phase `done`) only gets its outputs here.

    Args:
        cfg: the whole, validated config.
        out_dir: the run folder; receives checkpoint.pt, history.csv, metrics.csv, figures/.
        stop: the interruption request (`moex.stop.StopRequest`; signals are caught by the
            caller).

    Returns:
        the final `Checkpoint`.
    """
    out_dir = Path(out_dir)
    dataset = load_task(cfg)  # (first: it settles the data's defaults the checkpoint holds)
    backend = get_backend(cfg.backend, cfg.device)
    pilot.settle(cfg, dataset, out_dir, backend=backend)  # (so does gate_prior_std=auto)
    saved = open_checkpoint(cfg, out_dir)
    if saved is not None and saved.phase != "done":
        step = (saved.train_state or {}).get("step")
        log.info("resuming %s: %s phase from step %s", out_dir / checkpoint.NAME, saved.phase,
                 step if step is not None else "0 (its start)")
    provenance.note(backend=backend.name)
    warn_ignored(cfg, dataset)
    if saved is None or saved.phase != "done":
        [saved] = train_jobs([Job(cfg, dataset, out_dir, saved)], stop, backend)
    finish_run(cfg, dataset, saved, out_dir, backend=backend, stop=stop)
    return saved


def evaluation_generators(seed: int, num_runs: int) -> list[torch.Generator]:
    """One generator per run for an evaluation's random initial states, tangents and noise, run
    r's fixed by (seed, r) alone: a network's evaluation does not depend on how many are
    evaluated beside it (run 0's is the one generator every run shared before 2026-12-04)."""
    return run_generators(seed, num_runs, salt=0xE7A1)


def finish_run(cfg: Config, dataset: Dataset, saved: checkpoint.Checkpoint, out_dir: Path,
               *, backend: Backend, stop=never) -> None:
    """The outputs of a trained run that its folder lacks: history.csv and the learning curves,
    then metrics.csv, samples.npz and the figures (with `eval.enabled`) or the run's page."""
    history_written = False
    if not (out_dir / io.HISTORY_CSV).exists() and (saved.experts_rows or saved.gating_rows):
        history = pd.DataFrame(saved.experts_rows + saved.gating_rows)
        for r in np.flatnonzero(saved.failed):
            log.warning("run %d failed: its objective or parameters became non-finite; it was "
                        "frozen and its metrics are NaN", r)
        io.write_csv(out_dir / io.HISTORY_CSV, history)
        plotting.save_figure(plotting.plot_learning_curves(
            history, f"learning curves: task {cfg.task.name}, {numbered('run', cfg.num_runs)}"),
            out_dir / io.FIGURES / "learning_curves.png", cfg.plot.format)
        history_written = True
    if cfg.eval.enabled and not (out_dir / io.METRICS_CSV).exists():
        evaluate_run(cfg, dataset, saved.experts, saved.beta, gating=saved.gating, out_dir=out_dir,
                     failed=saved.failed, backend=backend, stop=stop)
    elif not cfg.eval.enabled and history_written:
        run_page.write(out_dir, cfg, None, f"moex run {out_dir.name}")


def evaluate_run(cfg: Config, dataset: Dataset, experts, beta, *, gating, out_dir: Path,
                 failed: list[bool], backend: Backend, stop=never):
    """Run every metric, then write metrics.csv, samples.npz and the figures (nothing when
    `stop` interrupts it).

    Runs marked `failed` (non-finite during training) keep their row with NaN metrics.
    """
    R, ev = len(gating["w_out"]), cfg.eval
    generator = evaluation_generators(cfg.seed, R)
    for line in progress.packed(f"evaluating {progress.counted(R, 'run')}:", [
            "the closed loop from the trained states",
            f"λ_max and symbols over {ev.transient} + {ev.lyapunov_steps} steps from "
            f"{ev.num_samples} {ev.initial_states} states per run"
            + (f", noise ρ² = {ev.noise_var:g}" if ev.noise_var else "")]):
        log.info("%s", line)  # (no silent pause: at the paper's scale this takes minutes)
    with np.errstate(invalid="ignore"), provenance.part("evaluation"):
        rows, samples = evaluate(experts, beta, gating, dataset, cfg.model.delay, cfg=cfg.eval,
                                 generator=generator, backend=backend,
                                 target_temperature=cfg.train.gating.target_temperature,
                                 stop=stop, sigma_min=cfg.model.sigma_min,
                                 gate_prior_std=cfg.train.experts.gate_prior_std)
    metrics = pd.DataFrame(rows).astype({"lyapunov_positive": "boolean"})
    counts = metrics.select_dtypes("integer").columns  # stay integers beside a failed run's NaN
    metrics = metrics.astype({c: "Int64" for c in counts})
    metrics.loc[failed, metrics.columns.difference(["run"])] = np.nan
    metrics["failed"] = failed
    io.write_csv(out_dir / io.METRICS_CSV, metrics)
    samples = in_data_units(samples, dataset)
    io.save_arrays(out_dir / io.SAMPLES, samples)
    if "label_stays" in samples:  # the closed loop's residence per label beside the data's
        io.write_csv(out_dir / io.LABEL_STAYS, segment.label_stays_table(samples["label_stays"]))
    ok = metrics[~metrics["failed"]]
    plot_samples(samples, dataset, cfg, out_dir, metrics=metrics, noise_var=cfg.eval.noise_var)
    if beta is not None and dataset.series.shape[-1] > 0:  # which expert holds which stretch
        write_segments(out_dir, gate_estimates(beta).numpy(), dataset.labels, cfg=cfg,
                       what="training series, ĝ = softmax(β) of phase 1",
                       table=TASKS[cfg.task.name].files, scores=False)
    run_page.write(out_dir, cfg, metrics, f"moex run {out_dir.name}")
    for line in progress.packed(f"of {progress.counted(len(ok), 'run')}:",
                                chaos_parts(ok, cfg.eval), sep=";"):
        log.info("%s", line)
    for _, row in ok.iterrows():  # whole "name value" pairs per line, within the terminal
        parts = [f"{name} {row[column]:.4g}" for column, name in LOGGED_METRICS
                 if column in row and column != "max_lyapunov"]
        parts.append(f"λ_max {row['max_lyapunov']:.3g} ± {row['max_lyapunov_se']:.2g} "
                     f"({row['chaos']})" if row["lyapunov_samples"] > 1 else
                     f"λ_max {row['max_lyapunov']:.3g} (1 sample: no error; undetermined)")
        for line in progress.packed(f"run {row['run']}:", parts):
            log.info("%s", line)
    return metrics


def chaos_parts(ok: pd.DataFrame, ev) -> list[str]:
    """How many runs are chaotic, undetermined and not chaotic by the label with its error, and
    how many meet the paper's criterion (λ_max > 0) alone."""
    labels = ok["chaos"].value_counts()
    counts = ", ".join(f"{labels.get(name, 0)} {name}" for name in CHAOS_LABELS)
    return [f"{counts} (λ_max beyond {ev.chaos_z:g} s.e. and 1/{ev.lyapunov_steps} of 0)",
            f"λ_max > 0 (the paper's criterion) in {int((ok['max_lyapunov'] > 0).sum())}"]


LOGGED_METRICS = [(name, METRICS[name].text) for name in LOGGED]
