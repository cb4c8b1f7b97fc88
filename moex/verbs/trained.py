"""A finished run folder loaded for the verbs that read one (evaluate, generate, segment)."""

import dataclasses
from pathlib import Path

from moex import budget, checkpoint, provenance
from moex.config import (
    Config,
    EvaluateConfig,
    GenerateConfig,
    RunFolder,
    paper_eval_sizes,
)
from moex.config.evaluation import EvalConfig
from moex.data import held_out
from moex.errors import check
from moex.kernels import Backend, get_backend
from moex.resume import config_from_dict
from moex.tasks import Dataset, Scale, task_of_run


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
