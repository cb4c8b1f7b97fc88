"""The training core: the runs (networks) of one or more jobs trained as one batch, phase 1 then
phase 2 (paper Sec. 2.1). `moex train`, the packed launcher (`hydra/launcher=packed`) and `moex.fit`
all train through `train_jobs`.

A job is a config, its data set and, for the CLI, its run folder (a checkpoint every
`train.checkpoint_every` steps, resumed from there). Jobs trained together agree in everything
`packing_key` names (model, training, precision, backend, device) and in the shape of their
data; each job's runs are drawn from its own seed, train on its own series, and come back as if
the job had been trained alone (to rounding: the packing law of tests/test_train.py).
"""

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import checkpoint, io, provenance
from moex.config import Config
from moex.errors import check, never
from moex.evaluation import track_metrics
from moex.kernels import Backend, get_backend
from moex.model import init_experts, init_gating
from moex.tasks import Dataset
from moex.train import Hooks, phase2_targets, train_experts, train_gating

log = logging.getLogger(__name__)


@dataclass
class Job:
    """One job of a batch: its config, its data, and (CLI) its folder and checkpoint."""

    cfg: Config
    dataset: Dataset
    out_dir: Path | None = None  # None: nothing is written (the Python API)
    saved: checkpoint.Checkpoint | None = None  # an unfinished training to continue


def run_seeds(seed: int, num_runs: int) -> list[int]:
    """Seed of run r: a function of (seed, r) alone, so run r trains identically in any batch."""
    return [int(np.random.SeedSequence([seed, r]).generate_state(1)[0]) for r in range(num_runs)]


def run_generators(seed: int, num_runs: int, salt: int = 0) -> list[torch.Generator]:
    """A generator per run, run r's seeded by (seed, r) alone (and `salt`, which keeps apart the
    streams of different uses): what run r draws does not depend on the runs beside it."""
    return [torch.Generator().manual_seed(s ^ salt) for s in run_seeds(seed, num_runs)]


def initial_parameters(cfg: Config, num_series: int, num_features: int,
                       dtype: torch.dtype) -> tuple[dict, dict]:
    """The experts (none when D = 0) and the gating RNN of every run before training, run r
    drawn from a generator seeded by (seed, r) alone."""
    generators = run_generators(cfg.seed, cfg.num_runs)
    experts = (init_experts(cfg.model, num_series, num_features, generators, dtype)
               if num_features > 0 else {})
    return experts, init_gating(cfg.model, num_series, num_features, generators, dtype)


def packing_key(cfg: Config) -> str:
    """What jobs trained in one batch must share: everything that shapes a training step. The
    data, the seed and the number of runs may differ; a job that tracks metrics while training
    (`eval.every`) or caches phase 1 (`cache_dir`) trains alone."""
    shared = {k: dataclasses.asdict(cfg)[k] for k in ("model", "train", "precision", "device",
                                                      "backend")}
    alone = bool(cfg.eval.every or cfg.cache_dir)
    return json.dumps({**shared, "alone": alone}, sort_keys=True)


def phase1_cache(cfg: Config) -> Path | None:
    """Where phase 1 of this config is cached: it does not depend on the gating network, its
    phase or evaluation, so a sweep over those reuses one result per (task, seed)."""
    if not cfg.cache_dir:
        return None
    model = dataclasses.asdict(cfg.model)
    model.pop("gating")
    key = {"task": dataclasses.asdict(cfg.task), "model": model,
           "experts": dataclasses.asdict(cfg.train.experts),
           "adaptive": dataclasses.asdict(cfg.train.adaptive),
           "momentum_form": cfg.train.momentum_form, "seed": cfg.seed,
           "num_runs": cfg.num_runs, "precision": cfg.precision, "device": cfg.device}
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cfg.cache_dir) / f"phase1-{digest}.pt"


def _cpu(tree):
    if isinstance(tree, torch.Tensor):
        return tree.detach().cpu().clone()
    if isinstance(tree, dict):
        return {k: _cpu(v) for k, v in tree.items()}
    return tree


def _part(tree, runs: slice):
    """The runs `runs` of a batch: tensors sliced on their run axis, history rows filtered and
    renumbered from 0, other values (the step) as they are."""
    if isinstance(tree, torch.Tensor):
        return tree[runs]
    if isinstance(tree, dict):
        return {k: _part(v, runs) for k, v in tree.items()}
    if isinstance(tree, list):
        return [{**row, "run": row["run"] - runs.start} for row in tree
                if runs.start <= row["run"] < runs.stop]
    return tree


def _joined(parts: list, starts: list[int]):
    """The inverse of `_part`: the jobs' trees as one batch."""
    first = parts[0]
    if isinstance(first, torch.Tensor):
        return torch.cat(parts)
    if isinstance(first, dict):
        return {k: _joined([p[k] for p in parts], starts) for k in first}
    if isinstance(first, list):
        return [{**row, "run": row["run"] + start}
                for part, start in zip(parts, starts, strict=True) for row in part]
    return first


def saved_position(saved: checkpoint.Checkpoint | None) -> tuple:
    """Where a folder's training stands: (phase, step) of its checkpoint, (None,) when new."""
    return (None,) if saved is None else (saved.phase, (saved.train_state or {}).get("step"))


def train_jobs(jobs: list[Job], stop=never, backend: Backend | None = None
          ) -> list[checkpoint.Checkpoint]:
    """Train every job's networks in one batch; the jobs' finished records (phase `done`), each
    also saved in its folder.

    Args:
        jobs: one job, or jobs of one `packing_key` and data shape at the same saved step.
        stop: checked every step; when it says so, every job's state is saved and
            `TrainingInterrupted` raised (resume by calling again with the saved checkpoints).
        backend: where the time loops run (default: the first job's `backend` and `device`).
    """
    cfg = jobs[0].cfg
    shape = tuple(jobs[0].dataset.series.shape)
    for job in jobs[1:]:
        check(packing_key(job.cfg) == packing_key(cfg), "jobs trained in one batch must agree "
              "in model, train, precision, backend and device, and none may track or cache")
        check(tuple(job.dataset.series.shape) == shape,
              f"jobs trained in one batch need data of one shape, not {shape} and "
              f"{tuple(job.dataset.series.shape)}")
        check(saved_position(job.saved) == saved_position(jobs[0].saved),
              "jobs trained in one batch must stand at the same saved step")
    S, L, D = shape
    dtype = getattr(torch, cfg.precision)
    backend = backend or get_backend(cfg.backend, cfg.device)
    sizes = [job.cfg.num_runs for job in jobs]
    starts = np.cumsum([0] + sizes[:-1]).tolist()
    runs = [slice(a, a + n) for a, n in zip(starts, sizes, strict=True)]
    own = [torch.as_tensor(job.dataset.series, dtype=dtype) for job in jobs]
    series = own[0] if len(jobs) == 1 else torch.cat(
        [x.expand(n, S, L, D) for x, n in zip(own, sizes, strict=True)])  # (R, S, L, D)
    saved = jobs[0].saved
    if D > 0 and saved is None:
        K = cfg.model.num_experts  # the gating RNN's units, inputs (ĝ, x) and outputs
        backend.warm_up(cfg.precision, (cfg.model.gating.context_size, K + D, K))  # cpu:
        # compiles phase 2 etc. beside phase 1
    signal = f"{D} features" if D else f"{len(jobs[0].dataset.symbol_names)} symbols"
    packed = f" ({len(jobs)} jobs packed)" if len(jobs) > 1 else ""
    log.info("task %s: %d series x %d steps of %s; %d runs%s on %s/%s, %s backend",
             cfg.task.name, S, L, signal, sum(sizes), packed, cfg.device, cfg.precision,
             backend.name)
    # every draw happens on every start, so resumed and fresh runs see the same generators
    drawn = [initial_parameters(job.cfg, S, D, dtype) for job in jobs]
    experts, gating = (_joined([d[i] for d in drawn], starts) for i in (0, 1))
    track_rng = torch.Generator().manual_seed(run_seeds(cfg.seed, 1)[0] ^ 0x7AC)  # alone only
    records = [checkpoint.Checkpoint(
        dataclasses.asdict(job.cfg), "experts", x, torch.as_tensor(job.dataset.labels),
        data_scale={k: torch.as_tensor(v) for k, v in job.dataset.scale.as_dict().items()})
        for job, x in zip(jobs, own, strict=True)]

    def save_all():
        for job, record in zip(jobs, records, strict=True):
            if job.out_dir is not None:
                record.save(Path(job.out_dir) / checkpoint.NAME)

    def hooks(phase: str, **extra) -> Hooks:
        def save(state):
            for record, part in zip(records, runs, strict=True):
                record.phase, record.train_state = phase, _cpu(_part(state, part))
                record.track_rng = track_rng.get_state()
            save_all()

        resume = None
        if saved is not None and saved.phase == phase:
            resume = _joined([job.saved.train_state for job in jobs], starts)
            if saved.track_rng is not None:
                track_rng.set_state(saved.track_rng)
        return Hooks(save=save, save_every=cfg.train.checkpoint_every, stop=stop,
                     resume=resume, **extra)

    # ---- phase 1 (skipped for symbolic tasks, or when a checkpoint holds its result)
    beta = None
    if D > 0:  # symbolic tasks have no experts: their gates are the one-hot symbols
        cached = phase1_cache(cfg) if len(jobs) == 1 else None
        if saved is not None and saved.phase == "gating":
            experts = _joined([job.saved.experts for job in jobs], starts)
            beta = _joined([job.saved.beta for job in jobs], starts)
            rows = _joined([job.saved.experts_rows for job in jobs], starts)
        elif cached is not None and cached.exists():
            log.info("phase 1 reused from %s", cached)
            done = torch.load(cached, map_location="cpu", weights_only=True)
            experts, beta, rows = done["experts"], done["beta"], done["rows"]
        else:
            with provenance.part("phase 1"):
                experts, beta, rows = train_experts(experts, series, cfg.model, cfg.train.experts,
                                                    cfg.train, hooks=hooks("experts"),
                                                    backend=backend)
            if cached is not None:
                io.atomic_write(cached, lambda tmp: torch.save(
                    {"experts": _cpu(experts), "beta": _cpu(beta), "rows": rows}, tmp))
        for record, part in zip(records, runs, strict=True):
            record.experts, record.beta = _cpu(_part(experts, part)), _cpu(beta[part])
            record.experts_rows = _part(rows, part)
    # ---- phase 2: x_n aligned with ĝ_n (the whole series when D = 0)
    gating_inputs = series[..., :-cfg.model.delay, :] if D > 0 else series
    gate_targets = torch.cat([phase2_targets(None if beta is None else beta[part], job.dataset,
                                             job.cfg.num_runs, dtype,
                                             cfg.train.gating.target_temperature)
                              for job, part in zip(jobs, runs, strict=True)])
    monitor = None
    if cfg.eval.every:  # a job alone (packing_key)
        def monitor(gating_params):
            return track_metrics(experts, gate_targets, gating_params, series, cfg.model.delay,
                                 cfg=cfg.eval, generator=track_rng, backend=backend)

    with provenance.part("phase 2"):
        gating, gating_rows = train_gating(
            gating, gate_targets, gating_inputs, cfg.model, cfg.train.gating, rule=cfg.train,
            hooks=hooks("gating", monitor=monitor, monitor_every=cfg.eval.every,
                        monitor_from=cfg.eval.track_from),
            backend=backend,
            seeds=[s for job in jobs for s in run_seeds(job.cfg.seed, job.cfg.num_runs)])
    for record, part, n in zip(records, runs, sizes, strict=True):
        record.phase, record.gating, record.train_state = "done", _cpu(_part(gating, part)), None
        record.gating_rows = _part(gating_rows, part)
        history = pd.DataFrame(record.experts_rows + record.gating_rows)
        failed = history.groupby("run")["failed"].any().reindex(range(n), fill_value=False)
        record.failed = [bool(f) for f in failed]
    save_all()
    return records
