"""`moex segment`: each expert's responsibility per step on new data (or the run's held-out
series), by a finished run's networks (`moex.segment`), scored where labels are given."""

import functools
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from moex import errors, progress, segment
from moex.config import SegmentConfig
from moex.errors import ConfigError, never
from moex.figures import write_segments
from moex.tasks import files
from moex.verbs.trained import TrainedRun, load_run

log = logging.getLogger(__name__)

NAME, CONFIG = "segment", "segment"


def segment_input(tool: SegmentConfig) -> tuple[TrainedRun, np.ndarray, np.ndarray, str]:
    """The run, the series to segment in model units (S, T, D), their labels (S, T) and where
    they come from; every refusal of `moex segment` (also run before its folder is made)."""
    run = load_run(tool)
    cfg, dataset = run.cfg, run.dataset
    errors.check(dataset.series.shape[-1] > 0,
                 f"task {cfg.task.name} has no signal to segment (its gates are its symbols)")
    new = tool.task
    if not new.path:
        errors.check(dataset.test is not None,
                     f"run_dir={tool.run_dir} has no held-out series; give task.path=<new data>")
        return run, dataset.test.series, dataset.test.labels, "held-out series"
    read = functools.partial(files.load_series, new.path, new.length, cfg.model.delay + 2,
                             new.columns or getattr(cfg.task, "columns", []))
    try:  # the run's label column where the new files have it too
        series, labels = read(new.labels or _label_column(cfg.task))
    except ConfigError:
        if new.labels or not _label_column(cfg.task):
            raise
        series, labels = read("")
        log.info("no column %s in %s: the segmentation is not scored", _label_column(cfg.task),
                 new.path)
    errors.check(series.shape[-1] == dataset.series.shape[-1],
                 f"task.path={new.path} has {series.shape[-1]} features; the run was trained "
                 f"on {dataset.series.shape[-1]}")
    return run, dataset.scale.to_model(series), labels, new.path


def run(tool: SegmentConfig, out_dir: Path, stop=never) -> pd.DataFrame:
    """Each expert's responsibility per step on new data (`moex.segment`) into `out_dir`:
    segments.csv, segment_scores.csv where labels are given, figures/segments.png."""
    run, series, labels, source = segment_input(tool)
    cfg, saved = run.cfg, run.saved
    log.info("segmenting %s of %s (%d series x %d steps) with %s by %s", source, tool.run_dir,
             len(series), series.shape[1], progress.counted(cfg.num_runs, "run"), tool.method)
    if tool.method == "smooth" and tool.gate_prior_std == "auto":  # (no silent pause)
        log.info("gate_prior_std=auto: choosing ς by %d smoothing fits (one per ς and left-out "
                 "half, every run at once)", len(segment.PRIOR_GRID) * segment.FOLDS)
    found = segment.responsibilities(saved.experts, saved.gating, torch.as_tensor(series),
                                     cfg.model.delay, sigma_min=cfg.model.sigma_min,
                                     method=tool.method,
                                     prior_std=tool.gate_prior_std
                                     or cfg.train.experts.gate_prior_std,
                                     steps=tool.smooth_steps)
    how = "filtered with the gating network" if found.prior_std is None else "smoothed"
    if found.prior_std is not None and tool.gate_prior_std == "auto":
        log.info("ς per run, cross-validated on these data over %s: %s",
                 ", ".join(f"{s:g}" for s in segment.PRIOR_GRID),
                 ", ".join(f"{s:g}" for s in found.prior_std))
    result = write_segments(Path(out_dir), found.gates.numpy(), labels, cfg=cfg,
                            what=f"{source}, {how}", prior_std=found.prior_std)
    if len(result.scores):
        for line in progress.packed("scores against the labels (median over runs):", [
                f"{name} {result.scores[column].median():.3f}" for column, name in (
                    ("segment_ari", "adjusted Rand index"),
                    ("segment_nmi", "normalised mutual information"),
                    ("segment_accuracy", "accuracy after matching"))]):
            log.info("%s", line)
    return result.table


def _label_column(task) -> str:
    """The training data's label column, reused for new data (a label file is not; a task not
    read from files has none)."""
    labels = getattr(task, "labels", "")
    return labels if files.is_column_name(labels) else ""


check = segment_input  # every refusal of `moex segment`, before its folder is made
