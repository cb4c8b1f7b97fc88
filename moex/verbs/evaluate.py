"""`moex evaluate`: the evaluation of a finished run again, from its checkpoint (no retraining),
with other evaluation settings, into a folder of its own."""

import dataclasses
import logging
from pathlib import Path

import pandas as pd

from moex import io, progress
from moex.config import EvaluateConfig
from moex.errors import never
from moex.verbs.train import evaluate_run
from moex.verbs.trained import load_run

log = logging.getLogger(__name__)

NAME, CONFIG = "evaluate", "evaluate"
check = load_run


def run(tool: EvaluateConfig, out_dir: Path, stop=never) -> pd.DataFrame:
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
