"""`moex import`: networks trained by the authors' C tools (mregn) as one finished run folder,
evaluated as a training run is."""

import logging
from pathlib import Path

from moex import checkpoint, importer, progress, run_page
from moex.config import ImportConfig
from moex.data import load_task
from moex.errors import never
from moex.kernels import check_backend, get_backend
from moex.verbs.train import evaluate_run

log = logging.getLogger(__name__)

NAME, CONFIG = "import", "import"


def check(cfg: ImportConfig) -> None:
    """Before anything is written: the backend, the task's data and every source file read and
    matched."""
    check_backend(cfg.backend, cfg.device)
    importer.import_networks(cfg, load_task(cfg))


def run(cfg: ImportConfig, out_dir: Path, stop=never) -> checkpoint.Checkpoint:
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
