"""The glue, testable without Hydra: task → model → phase 1 → phase 2 → checkpoint → CSV → plots."""

import dataclasses
import functools
import logging
import signal
import threading
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import torch

from moex import (
    budget,
    checkpoint,
    importer,
    io,
    plotting,
    progress,
    provenance,
    run_page,
    segment,
)
from moex.closed_loop import generate, trained_state
from moex.config import (
    Config,
    EvaluateConfig,
    GenerateConfig,
    ImportConfig,
    RunFolder,
    SegmentConfig,
    config_from_dict,
    paper_eval_sizes,
)
from moex.errors import ConfigError, check, never
from moex.evaluation import EvalConfig, evaluate
from moex.kernels import Backend, get_backend
from moex.metrics.lyapunov import CHAOS_LABELS
from moex.metrics.table import LOGGED, METRICS
from moex.model import ModelConfig, gate_estimates, random_state
from moex.run import Job, run_generators, train_jobs
from moex.tasks import Dataset, Scale, files, make_task, planned_shape, task_of_run
from moex.tasks.scaling import WINDOW, noise_floor
from moex.train import ExpertPhaseConfig, phase2_targets

log = logging.getLogger(__name__)


def evaluation_generators(seed: int, num_runs: int) -> list[torch.Generator]:
    """One generator per run for an evaluation's random initial states, tangents and noise, run
    r's fixed by (seed, r) alone: a network's evaluation does not depend on how many are
    evaluated beside it (run 0's is the one generator every run shared before 2026-12-04)."""
    return run_generators(seed, num_runs, salt=0xE7A1)


_BUILT: dict[tuple, Dataset] = {}  # generated data sets of this process by their settings, oldest
_BUILT_BYTES = 256 * 2**20  # first; the oldest go when their arrays exceed this


def _nbytes(dataset: Dataset | None) -> int:
    if dataset is None:
        return 0
    arrays = (dataset.series, dataset.labels, dataset.gate_targets)
    return sum(a.nbytes for a in arrays if a is not None) + _nbytes(dataset.test)


def _generated(cfg: Config) -> Dataset:
    """`make_task` for the config, built once per process when the task is generated (not read
    from files): `moex train` checks its config on the data (`cli.validate`) and then trains on
    the same data set; a packed sweep checks every job's and then trains them all. Nothing
    changes a `Dataset` in place."""
    if cfg.task.path:
        return make_task(cfg.task, cfg.seed, min_length=cfg.model.delay + 2)
    key = (repr(cfg.task), cfg.seed, cfg.model.delay)
    if key not in _BUILT:
        _BUILT[key] = make_task(cfg.task, cfg.seed, min_length=cfg.model.delay + 2)
        while len(_BUILT) > 1 and sum(map(_nbytes, _BUILT.values())) > _BUILT_BYTES:
            del _BUILT[next(iter(_BUILT))]
    return _BUILT[key]


def held_out(cfg: Config, dataset: Dataset) -> Dataset:
    """The dataset with `eval.test_series` held-out series in place of the task's own: the task
    drawn again with that many (it draws its held-out series first, one after another, so the
    first of them are the run's own; the training series of that draw are not used), built once
    a process as the task itself is (`_generated`)."""
    count = cfg.eval.test_series
    if not count or count == cfg.task.num_test_series:
        return dataset
    check(cfg.task.name != "csv", f"eval.test_series={count}: task {cfg.task.name} is a user's "
                                  f"files, which have no held-out series to draw more of")
    more = _generated(dataclasses.replace(cfg, task=dataclasses.replace(
        cfg.task, num_test_series=count)))
    return dataclasses.replace(dataset, test=more.test)


def load_task(cfg: Config) -> Dataset:
    """The task's data, checked against the model config and the memory a training on it needs
    (a `ConfigError` if they disagree, before generating data that could not be trained on).
    `model.sigma_min=auto` is replaced in `cfg` by the value the data give."""
    check(cfg.plot.run < cfg.num_runs,
          f"plot.run={cfg.plot.run} is outside [-1, {cfg.num_runs - 1}] (num_runs={cfg.num_runs})")
    shape = planned_shape(cfg.task)
    if shape is not None:
        budget.check_train(cfg, *shape)
    dataset = _generated(cfg)
    if shape is None:
        budget.check_train(cfg, *dataset.series.shape)
    K, names = cfg.model.num_experts, dataset.symbol_names
    cfg.model = settled(cfg.model, dataset.series)  # before anything trains on the data
    if dataset.gate_targets is not None:  # symbolic: one gate per symbol
        check(K == len(names), f"model.num_experts={K} must equal the {len(names)} symbols of "
                               f"task {cfg.task.name} ({', '.join(names)})")
    elif dataset.prototypes is not None:  # primitives: at least one expert each
        check(K >= len(names), f"model.num_experts={K} is fewer than the {len(names)} "
                               f"primitives of task {cfg.task.name} ({', '.join(names)}); use "
                               f"model.num_experts={len(names)} or more")
    return held_out(cfg, dataset)


def settled(model: ModelConfig, series: np.ndarray) -> ModelConfig:
    """`model` with `sigma_min=auto` replaced by the value the series (S, T, D) give, said in
    the log; `model` itself otherwise."""
    if model.sigma_min != "auto":
        return model
    model = dataclasses.replace(model, sigma_min=noise_floor(series))
    log.info("model.sigma_min=auto: σ̄ = %.4g (half the 10th percentile of the one-step "
             "change's RMS over %d-step windows)", model.sigma_min, WINDOW)
    return model


class StopRequest:
    """Turns SIGINT/SIGTERM into a flag that training checks each step (then saves and stops)."""

    def __init__(self):
        self.signum = 0

    def __call__(self) -> bool:
        return self.signum != 0

    def __enter__(self):
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        self.signum = signum

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def check_same_training(saved: dict, cfg: Config, path: Path) -> None:
    """A checkpoint may only be resumed by the config that wrote it (eval settings aside)."""
    now = dataclasses.asdict(cfg)
    saved = dataclasses.asdict(config_from_dict(saved))
    for key in ("task", "model", "train", "seed", "num_runs", "precision"):
        if saved[key] != now[key]:
            differ = _first_difference(saved[key], now[key], key)
            raise ConfigError(f"{path} was trained with {differ[0]}={differ[1]}, not "
                              f"{differ[2]}; use another output folder or the same overrides")


def _first_difference(then, now, key: str) -> tuple[str, object, object]:
    """The first dotted key whose value differs between two config trees, with both values."""
    if isinstance(then, dict) and isinstance(now, dict):
        for k in then:
            if then[k] != now.get(k):
                return _first_difference(then[k], now.get(k), f"{key}.{k}")
    return key, then, now


def open_checkpoint(cfg: Config, out_dir: Path) -> checkpoint.Checkpoint | None:
    """The checkpoint of a run folder, checked against the config that would continue it (a
    `ConfigError` if it was trained with another); None for a new folder."""
    path = Path(out_dir) / checkpoint.NAME
    if not path.exists():
        return None
    saved = checkpoint.load(path)
    check_same_training(saved.config, cfg, path)
    return saved


def run_train(cfg: Config, out_dir: Path,
              stop: StopRequest | None = None) -> checkpoint.Checkpoint:
    """Train R runs of the mixture on the task and write the run folder; resumable.

    A checkpoint already in `out_dir` (from the same config) is continued: a finished run is not
    redone, an interrupted phase resumes at its saved step with the same result as an
    uninterrupted run. Checkpoints are written every `train.checkpoint_every` steps and when
    `stop` reports a signal (then `TrainingInterrupted` is raised). A folder whose networks the
    packed launcher trained (phase `done`) only gets its outputs here.

    Args:
        cfg: the whole, validated config.
        out_dir: the run folder; receives checkpoint.pt, history.csv, metrics.csv, figures/.
        stop: the interruption flag (signals are caught by the caller).

    Returns:
        the final `Checkpoint`.
    """
    out_dir, stop = Path(out_dir), stop or StopRequest()
    dataset = load_task(cfg)  # (first: it settles the data's defaults the checkpoint holds)
    saved = open_checkpoint(cfg, out_dir)
    if saved is not None and saved.phase != "done":
        step = (saved.train_state or {}).get("step")
        log.info("resuming %s: %s phase from step %s", out_dir / checkpoint.NAME, saved.phase,
                 step if step is not None else "0 (its start)")
    backend = get_backend(cfg.backend, cfg.device)
    provenance.note(backend=backend.name)
    _warn_ignored(cfg, dataset)
    if saved is None or saved.phase != "done":
        [saved] = train_jobs([Job(cfg, dataset, out_dir, saved)], stop, backend)
    finish_run(cfg, dataset, saved, out_dir, backend=backend, stop=stop)
    return saved


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
                                 should_stop=stop, sigma_min=cfg.model.sigma_min,
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
    _plot_samples(samples, dataset, cfg, out_dir, metrics=metrics, noise_var=cfg.eval.noise_var)
    if beta is not None and dataset.series.shape[-1] > 0:  # which expert holds which stretch
        write_segments(out_dir, gate_estimates(beta).numpy(), dataset.labels, cfg=cfg,
                       what="training series, ĝ = softmax(β) of phase 1",
                       table=cfg.task.name == "csv", scores=False)
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


def _plot_samples(samples: dict, dataset: Dataset, cfg: Config, out_dir: Path,
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


def in_data_units(samples: dict, dataset: Dataset) -> dict:
    """Generated signals (outputs, closed_outputs) mapped back to the data's own units where
    the data was scaled (`task.scale=auto`); metrics stay in the model's units."""
    return {k: dataset.scale.to_data(v) if k in ("outputs", "closed_outputs") else v
            for k, v in samples.items()}


@dataclasses.dataclass
class TrainedRun:
    """A finished run folder: its config (with `eval` overrides), checkpoint, data and backend."""

    cfg: Config
    saved: checkpoint.Checkpoint
    dataset: Dataset
    backend: Backend


def load_run(tool: RunFolder) -> TrainedRun:
    """The config (with `eval` overrides), checkpoint and data of a finished run folder."""
    saved = checkpoint.load(Path(tool.run_dir))
    check(saved.phase == "done", f"run_dir={tool.run_dir} holds an unfinished training; "
                                 f"finish it with moex train first")
    cfg = config_from_dict(saved.config)
    if isinstance(tool, EvaluateConfig):  # explicit keys over eval=paper over the run's own
        overrides = {k: v for k, v in dataclasses.asdict(tool.eval).items() if v is not None}
        sizes = paper_eval_sizes(cfg.task.name) if tool.paper_sizes else {}
        cfg.eval = EvalConfig(**{**dataclasses.asdict(cfg.eval), **sizes, **overrides})
    if isinstance(tool, EvaluateConfig):
        budget.check_evaluate(cfg)
    if isinstance(tool, GenerateConfig):
        budget.check_generate(cfg, tool.steps, tool.num_samples)
        S = saved.series.shape[0]
        check(-1 <= tool.from_series < S, f"from_series={tool.from_series} is outside [-1, "
                                          f"{S - 1}]")
    backend = get_backend(cfg.backend, cfg.device)
    provenance.note(backend=backend.name, device=cfg.device, precision=cfg.precision,
                    run_dir=str(tool.run_dir))
    dataset = held_out(cfg, task_of_run(cfg.task, cfg.seed, saved.series.numpy(), scale=Scale(
        **saved.scale_arrays()), min_length=cfg.model.delay + 2, labels=saved.labels.numpy()))
    return TrainedRun(cfg, saved, dataset, backend)


def run_evaluate(tool: EvaluateConfig, out_dir: Path, stop=never) -> pd.DataFrame:
    """Re-run the evaluation of a finished run from its checkpoint (no retraining) into
    `out_dir`: metrics.csv, samples.npz, figures/ and the evaluation settings used."""
    run = load_run(tool)
    saved = run.saved
    networks = progress.counted(run.cfg.num_runs, "network")  # (how: evaluate_run's line)
    for line in progress.packed(f"re-evaluating {networks} of task {run.cfg.task.name}",
                                [f"from {tool.run_dir}", f"into {out_dir}"], sep=""):
        log.info("%s", line)
    metrics = evaluate_run(run.cfg, run.dataset, saved.experts, saved.beta, gating=saved.gating,
                           out_dir=Path(out_dir), failed=saved.failed, backend=run.backend,
                           stop=stop)
    io.write_yaml(Path(out_dir) / io.EVAL_SETTINGS, dataclasses.asdict(run.cfg.eval))
    return metrics


def write_segments(out_dir: Path, gates: np.ndarray, labels: np.ndarray | None, *, cfg: Config,
                   what: str, table: bool = True,
                   scores: bool = True) -> segment.Segmentation:
    """figures/segments.png of the run with the best adjusted Rand index (else run 0), with
    `table` segments.csv, with `scores` and labels segment_scores.csv (a training run has its
    scores in metrics.csv)."""
    result = segment.segmentation(gates, labels, cfg.model.delay)
    if table:
        io.write_csv(out_dir / io.SEGMENTS, result.table)
    run, matching, scored = 0, None, ""
    if len(result.scores):
        if scores:
            io.write_csv(out_dir / io.SEGMENT_SCORES, result.scores)
        best = result.scores.loc[result.scores["segment_ari"].idxmax()]
        run, matching = int(best["run"]), result.label_of_expert[int(best["run"])]
        scored = f"; ARI {best['segment_ari']:.3f}, accuracy {best['segment_accuracy']:.3f}"
    fig = plotting.plot_segments(gates[run], labels, cfg.model.delay, matching,
                                 f"winning expert per step, run {run}: {what}{scored}")
    plotting.save_figure(fig, out_dir / io.FIGURES / "segments.png", cfg.plot.format)
    return result


def segment_input(tool: SegmentConfig) -> tuple[TrainedRun, np.ndarray, np.ndarray, str]:
    """The run, the series to segment in model units (S, T, D), their labels (S, T) and where
    they come from; every refusal of `moex segment` (also run before its folder is made)."""
    run = load_run(tool)
    cfg, dataset = run.cfg, run.dataset
    check(dataset.series.shape[-1] > 0, f"task {cfg.task.name} has no signal to segment (its "
                                        f"gates are its symbols)")
    new = tool.task
    if not new.path:
        check(dataset.test is not None, f"run_dir={tool.run_dir} has no held-out series; give "
                                        f"task.path=<new data>")
        return run, dataset.test.series, dataset.test.labels, "held-out series"
    read = functools.partial(files.load_series, new.path, new.length, cfg.model.delay + 2,
                             new.columns or cfg.task.columns)
    try:  # the run's label column where the new files have it too
        series, labels = read(new.labels or _label_column(cfg.task))
    except ConfigError:
        if new.labels or not _label_column(cfg.task):
            raise
        series, labels = read("")
        log.info("no column %s in %s: the segmentation is not scored", cfg.task.labels, new.path)
    check(series.shape[-1] == dataset.series.shape[-1],
          f"task.path={new.path} has {series.shape[-1]} features; the run was trained on "
          f"{dataset.series.shape[-1]}")
    return run, dataset.scale.to_model(series), labels, new.path


def run_segment(tool: SegmentConfig, out_dir: Path, stop=never) -> pd.DataFrame:
    """Each expert's responsibility per step on new data (`moex.segment`) into `out_dir`:
    segments.csv, segment_scores.csv where labels are given, figures/segments.png."""
    run, series, labels, source = segment_input(tool)
    cfg, saved = run.cfg, run.saved
    log.info("segmenting %s of %s (%d series x %d steps) with %s by %s", source, tool.run_dir,
             len(series), series.shape[1], progress.counted(cfg.num_runs, "run"), tool.method)
    prior_std = tool.gate_prior_std or cfg.train.experts.gate_prior_std
    gates = segment.responsibilities(saved.experts, saved.gating, torch.as_tensor(series),
                                     cfg.model.delay, sigma_min=cfg.model.sigma_min,
                                     method=tool.method, prior_std=prior_std,
                                     steps=tool.smooth_steps).numpy()
    how = (f"smoothed (ς = {prior_std:g})" if tool.method == "smooth"
           else "filtered with the gating network")
    result = write_segments(Path(out_dir), gates, labels, cfg=cfg, what=f"{source}, {how}")
    if len(result.scores):
        for line in progress.packed("scores against the labels (median over runs):", [
                f"{name} {result.scores[column].median():.3f}" for column, name in (
                    ("segment_ari", "adjusted Rand index"),
                    ("segment_nmi", "normalised mutual information"),
                    ("segment_accuracy", "accuracy after matching"))]):
            log.info("%s", line)
    return result.table


def _label_column(task) -> str:
    """The training data's label column, reused for new data (a label file is not)."""
    return task.labels if files.is_column_name(task.labels) else ""


def run_generate(tool: GenerateConfig, out_dir: Path, stop=never) -> dict:
    """Closed-loop samples of every run from random initial states (or the trained state of
    series `from_series`) into `out_dir`: samples.npz and figures."""
    run = load_run(tool)
    cfg, saved, dataset = run.cfg, run.saved, run.dataset
    experts, gating = saved.experts, saved.gating
    generator = run_generators(tool.seed, len(gating["w_out"]))  # run r's samples: (seed, r)
    D = dataset.series.shape[2]
    if tool.from_series < 0:
        state = random_state(experts, gating, tool.num_samples, num_features=D,
                             delay=cfg.model.delay, generator=generator)
    else:  # the trained initial state of one series, repeated for every (noisy) sample
        estimates = phase2_targets(saved.beta, dataset, cfg.num_runs,
                                   gating["w_out"].dtype, cfg.train.gating.target_temperature)
        k = [tool.from_series] * tool.num_samples
        state = trained_state(experts, gating, estimates, saved.series, delay=cfg.model.delay,
                              rows=k)
    with torch.no_grad():
        out = generate(experts, gating, state, tool.steps, noise_std=tool.noise_var**0.5,
                       generator=generator, backend=run.backend, should_stop=stop)
    samples = {k: v.numpy() for k, v in out.items()}
    samples["symbols"] = dataset.symbolize(samples["outputs"], samples["gates"],
                                           run.backend.nearest_symbols)
    samples = in_data_units(samples, dataset)
    out_dir = Path(out_dir)
    io.save_arrays(out_dir / io.SAMPLES, samples)
    first = {k: v[:, 0] for k, v in samples.items()}
    _plot_samples(first, dataset, cfg, out_dir, noise_var=tool.noise_var)
    log.info("generated %d samples x %d steps per run (noise variance %g, from %s) into %s",
             tool.num_samples, tool.steps, tool.noise_var,
             "random states" if tool.from_series < 0 else f"series {tool.from_series}",
             out_dir / io.SAMPLES)
    return samples


def _warn_ignored(cfg: Config, dataset: Dataset) -> None:
    """Keys the task does not use are named as ignored, not silently dropped: task.num_series of
    a csv task (its files decide), and every train.experts key set away from its default where
    the task has no signal (Reber: symbols only; no experts, no phase 1)."""
    S = len(dataset.series)
    if cfg.task.name == "csv" and cfg.task.num_series not in (0, S):
        log.warning("task.num_series=%d ignored: task csv trains on every series its files hold "
                    "(%d)", cfg.task.num_series, S)
    if dataset.series.shape[-1] > 0:
        return
    default = dataclasses.asdict(ExpertPhaseConfig())
    changed = [f"train.experts.{k}={v}" for k, v in dataclasses.asdict(cfg.train.experts).items()
               if v != default[k]]
    if changed:
        log.warning("%s ignored: task %s has no signal for experts, so phase 1 does not run",
                    ", ".join(changed), cfg.task.name)


def check_import(cfg: ImportConfig) -> None:
    """Before anything is written: the task's data and every source file read and matched."""
    importer.import_networks(cfg, load_task(cfg))


def run_import(cfg: ImportConfig, out_dir: Path, stop=never) -> checkpoint.Checkpoint:
    """Networks trained by the authors' C tools as one finished run folder (checkpoint.pt,
    imported_from.csv), then evaluated as a training run is (unless eval.enabled=false)."""
    out_dir = Path(out_dir)
    dataset = load_task(cfg)
    run_cfg, record = importer.import_networks(cfg, dataset)
    folders = importer.network_folders(cfg.source)
    log.info("importing %s of the C tools (%s) on task %s into %s",
             progress.counted(run_cfg.num_runs, "network"),
             "gating network alone" if record.beta is None else "mixture", cfg.task.name, out_dir)
    record.save(out_dir / checkpoint.NAME)
    importer.write_sources(out_dir, folders)
    if run_cfg.eval.enabled:
        evaluate_run(run_cfg, dataset, record.experts, record.beta, gating=record.gating,
                     out_dir=out_dir, failed=record.failed,
                     backend=get_backend(run_cfg.backend, run_cfg.device), stop=stop)
    else:
        run_page.write(out_dir, run_cfg, None, f"moex import {out_dir.name}")
    return record
