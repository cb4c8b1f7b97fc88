"""The Python API: fit the mixture to your own arrays (in a notebook, say), without files or
Hydra. `fit` trains both phases (paper Sec. 2.1) and returns a `Fitted` whose `evaluate` and
`generate` run the closed loop (Sec. 2.2-4). Everything the CLI can set is a `Config` field.
`load(run_dir)` gives the same `Fitted` for a run folder of `moex train`; `Fitted.save(dir)`
writes a run folder that `moex evaluate` / `moex generate` accept."""

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import checkpoint, io, pilot, provenance
from moex.closed_loop import generate as run_closed_loop
from moex.closed_loop import trained_state
from moex.config import Config, RunFolder, check_prior_std
from moex.config.evaluation import EvalConfig
from moex.data import in_data_units, settled
from moex.errors import check
from moex.evaluation import evaluate
from moex.jobs import Job, run_generators, train_jobs
from moex.kernels import Backend, get_backend
from moex.model import gate_estimates, random_state
from moex.segment import METHODS, Segmentation, responsibilities, segmentation
from moex.tasks import Dataset, task_config, user_data
from moex.tasks.scaling import fit_scale
from moex.train import phase2_targets
from moex.verbs.train import evaluation_generators
from moex.verbs.trained import load_run


@dataclass
class Fitted:
    """A trained mixture of R runs.

    Attributes:
        config: everything it was trained with.
        experts, gating: parameters with a leading run axis R (as in `moex.model`).
        beta: (R, S, T, K) the gate logits of phase 1 (ĝ = softmax β, Eq. 9).
        history: one row per run and logged step of both phases (E, E_g, ...).
    """

    config: Config
    dataset: Dataset
    experts: dict[str, torch.Tensor]
    beta: torch.Tensor | None  # None for symbolic tasks (no experts)
    gating: dict[str, torch.Tensor]
    history: pd.DataFrame
    backend: Backend
    provenance: dict | None = None  # what trained it (versions, CPU/GPU, times); `save` writes it

    def __repr__(self) -> str:
        """One line, not the tensors: task, sizes, runs, backend and the last logged errors."""
        cfg, S, L, D = self.config, *self.dataset.series.shape
        last = self.history.groupby("phase").tail(1) if len(self.history) else self.history
        errors = ", ".join(f"{c} {last[c].dropna().mean():.3g}" for c in ("E", "E_g")
                           if c in last and last[c].notna().any())
        return (f"Fitted({cfg.num_runs} runs of task {cfg.task.name}: {S} series x {L} steps x "
                f"{D} features, {cfg.model.num_experts} experts, NC "
                f"{cfg.model.gating.context_size}, backend {self.backend.name}"
                f"{'; ' + errors if errors else ''})")

    def save(self, run_dir) -> Path:
        """Write a finished run folder (checkpoint.pt, history.csv) that `moex evaluate
        run_dir=...`, `moex generate` and `load` accept; refuses a folder that holds a run."""
        path = Path(run_dir)
        check(not (path / checkpoint.NAME).exists(),
              f"{path} already holds a run ({checkpoint.NAME}); save into another folder")
        path.mkdir(parents=True, exist_ok=True)
        R = self.config.num_runs
        failed = self.history.groupby("run")["failed"].any().reindex(range(R), fill_value=False)
        record = checkpoint.Checkpoint(
            dataclasses.asdict(self.config), "done", torch.as_tensor(self.dataset.series),
            torch.as_tensor(self.dataset.labels), experts=self.experts, beta=self.beta,
            gating=self.gating,
            experts_rows=self.history[self.history["phase"] == "experts"].to_dict("records"),
            gating_rows=self.history[self.history["phase"] == "gating"].to_dict("records"),
            failed=[bool(f) for f in failed],
            data_scale={k: torch.as_tensor(v) for k, v in self.dataset.scale.as_dict().items()})
        io.write_csv(path / io.HISTORY_CSV, self.history)
        record.save(path / checkpoint.NAME)
        if self.provenance is not None:
            provenance.save(path, self.provenance)
        return path

    def evaluate(self, quick: bool = False, **eval_settings) -> pd.DataFrame:
        """The metric table, one row per run: E, E^g, E^closed, the block KL of the closed loop
        from the trained initial states, λ_max from random initial states (paper Sec. 3-4).

        Args:
            quick: 4 samples × 5000 steps instead of the paper's 50 × 100 000.
            eval_settings: any `EvalConfig` field, e.g. noise_var=0.001.
        """
        sizes = dict(num_samples=4, lyapunov_steps=5000, transient=500) if quick else {}
        cfg = dataclasses.replace(self.config.eval, **{**sizes, **eval_settings})
        generators = evaluation_generators(self.config.seed, len(self.gating["w_out"]))
        result = evaluate(self.experts, self.beta, self.gating, self.dataset,
                          self.config.model.delay, cfg=cfg, generator=generators,
                          backend=self.backend,
                          target_temperature=self.config.train.gating.target_temperature,
                          sigma_min=self.config.model.sigma_min,
                          gate_prior_std=self.config.train.experts.gate_prior_std)
        return pd.DataFrame(result.rows)

    def segment(self, series: np.ndarray | None = None, labels: np.ndarray | None = None,
                method: str = "smooth", gate_prior_std: float | str = "auto") -> Segmentation:
        """Which expert explains which step of `series` ((S, T, D) or (T, D), in the data's own
        units; None: the training series): on new data by `method` (`smooth`: phase 1's
        estimate with the experts held fixed, ς = `gate_prior_std`: `auto` chosen per run by
        cross-validation on these data, 0 the run's own, or a number; `filter`:
        causal, the gating network's opening as the prior; see `moex.segment`), on the training
        series ĝ = softmax(β) of phase 1. Returns segments.csv's table (run, series, step, expert,
        label, gate_k) and, with labels ((S, T) or (T,) integers, -1 unknown; the training
        data's own for None), per-run scores: adjusted Rand index, normalised mutual
        information, accuracy after the best one-to-one matching of experts to labels."""
        delay = self.config.model.delay
        if series is None:
            check(self.beta is not None, "this task has no signal to segment")
            gates = gate_estimates(self.beta).numpy()
            labels = self.dataset.labels if labels is None else labels
        else:
            series = np.asarray(series, dtype=float)
            series = series[None] if series.ndim == 2 else series
            D = self.dataset.series.shape[-1]
            check(series.ndim == 3 and series.shape[-1] == D and series.shape[1] >= delay + 2,
                  f"series must be (S, T, {D}) or (T, {D}) with T >= {delay + 2}, got shape "
                  f"{series.shape}")
            check(method in METHODS, f"method={method!r}; choose one of {', '.join(METHODS)}")
            check_prior_std("gate_prior_std", gate_prior_std)
            gates = responsibilities(self.experts, self.gating,
                                     torch.as_tensor(self.dataset.scale.to_model(series)),
                                     delay, sigma_min=self.config.model.sigma_min, method=method,
                                     prior_std=(gate_prior_std
                                                or self.config.train.experts.gate_prior_std)
                                     ).gates.numpy()
        if labels is not None:
            labels = _labels(labels, (gates.shape[1], gates.shape[2] + delay))
        return segmentation(gates, labels, delay)

    def generate(self, steps: int = 1000, num_samples: int = 1, noise_var: float = 0.0,
                 from_series: int = -1, seed: int = 0) -> dict[str, np.ndarray]:
        """Closed-loop samples: outputs (R, N, steps, D), gates (R, N, steps, K) and gating
        potentials (R, N, steps, H), from random initial states or (`from_series` = k) the
        trained initial state of series k."""
        S, _, D = self.dataset.series.shape
        check(-1 <= from_series < S, f"from_series={from_series} is outside [-1, {S - 1}]")
        generator = run_generators(seed, len(self.gating["w_out"]))  # run r's: (seed, r) alone
        delay = self.config.model.delay
        if from_series < 0:
            state = random_state(self.experts, self.gating, num_samples, num_features=D,
                                 delay=delay, generator=generator)
        else:
            k = [from_series] * num_samples
            targets = phase2_targets(self.beta, self.dataset, self.config.num_runs,
                                     self.gating["w_out"].dtype,
                                     self.config.train.gating.target_temperature)
            state = trained_state(self.experts, self.gating, targets,
                                  torch.as_tensor(self.dataset.series), delay=delay, rows=k)
        with torch.no_grad():
            out = run_closed_loop(self.experts, self.gating, state, steps, noise_std=noise_var**0.5,
                                  generator=generator, backend=self.backend)
        return in_data_units({name: value.numpy() for name, value in out.items()}, self.dataset)


def _labels(labels, shape: tuple[int, int]) -> np.ndarray:
    """Per-step labels as (S, T), a (T,) array taken as one series; refused unless `shape`."""
    labels = np.asarray(labels)
    labels = labels[None] if labels.ndim == 1 else labels
    check(labels.shape == tuple(shape), f"labels must be (S, T) like the series {tuple(shape)}, "
                                        f"got {labels.shape}")
    return labels


def load(run_dir) -> Fitted:
    """A finished run folder (from `moex train` or `Fitted.save`) as the `Fitted` that `fit`
    returns: its config, data, parameters, learning history, backend and (the folder's last
    record) provenance."""
    run = load_run(RunFolder(run_dir=str(run_dir)))
    history_file = Path(run_dir) / io.HISTORY_CSV
    history = (pd.read_csv(history_file) if history_file.exists()
               else pd.DataFrame(run.saved.experts_rows + run.saved.gating_rows))
    records = provenance.read(Path(run_dir))
    return Fitted(run.cfg, run.dataset, run.saved.experts, run.saved.beta, run.saved.gating,
                  history, run.backend, records[-1] if records else None)


def fit(series: np.ndarray, *, num_experts: int = 2, expert_steps: int = 30000,
        gating_steps: int = 10000, num_runs: int = 1, seed: int = 0, scale: str = "none",
        config: Config | None = None, labels: np.ndarray | None = None) -> Fitted:
    """Train R mixtures of RNN experts on `series` (both phases, paper Sec. 2.1).

    Args:
        series: (S, T, D) or (T, D) signal within [-1, 1] (the outputs are tanh), or any range
            with `scale="auto"`, which maps each feature onto [-0.8, 0.8] for training and maps
            generated outputs back (E and the other metrics are in the scaled units).
        num_experts, expert_steps, gating_steps, num_runs, seed: the most used settings.
        config: a full `Config` for everything else (sizes, time constants, rates, backend,
            evaluation); the keyword settings above replace its values.
        labels: (S, T) or (T,) integer label of every step (-1 unknown), if you have them:
            `evaluate` and `segment` then score the segmentation against them.

    Returns:
        a `Fitted` with the parameters, the learning history, `evaluate` and `generate`.
    """
    series = np.asarray(series, dtype=float)
    series = series[None] if series.ndim == 2 else series
    check(series.ndim == 3 and series.shape[-1] >= 1,
          f"series must be (S, T, D) or (T, D), got shape {np.shape(series)}")
    check(bool(np.isfinite(series).all()), "series contains NaN or inf values")
    cfg = dataclasses.replace(config or Config(task=task_config("csv")), num_runs=num_runs,
                              seed=seed)
    cfg.model = dataclasses.replace(cfg.model, num_experts=num_experts)
    cfg.train = dataclasses.replace(  # replace() re-validates each config
        cfg.train, experts=dataclasses.replace(cfg.train.experts, steps=expert_steps),
        gating=dataclasses.replace(cfg.train.gating, steps=gating_steps))
    check(series.shape[1] >= cfg.model.delay + 2,
          f"series have {series.shape[1]} steps; need at least {cfg.model.delay + 2}")
    if labels is not None:
        labels = _labels(labels, series.shape[:2])
        check(np.issubdtype(labels.dtype, np.integer) and labels.min() >= -1,
              "labels must be integers >= 0 (-1: unknown)")
    dataset = user_data(*fit_scale(series, scale, "series"), labels)
    cfg.model = settled(cfg.model, dataset.series)
    backend = get_backend(cfg.backend, cfg.device)
    pilot.settle(cfg, dataset, backend=backend)
    with provenance.kept("fit", cfg.backend, cfg.device, cfg.precision) as record:
        provenance.note(backend=backend.name)
        [done] = train_jobs([Job(cfg, dataset)], backend=backend)  # the core `moex train` runs
    return Fitted(cfg, dataset, done.experts, done.beta, done.gating,
                  pd.DataFrame(done.experts_rows + done.gating_rows), backend, record)


__all__ = ["EvalConfig", "Fitted", "fit", "load"]
