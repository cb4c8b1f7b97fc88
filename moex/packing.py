"""Packed sweeps (`moex train -m ... hydra/launcher=packed`): the jobs of a sweep that can share
a batch are trained together, each group in one process as one batch of networks; then every
job runs as it would alone and finds its networks trained (its checkpoint says `done`), so it
only writes its outputs: history, figures, evaluation, status and provenance.

Jobs share a batch when `moex.jobs.packing_key` agrees (model, training, precision, backend,
device; no tracking, no phase-1 cache), their data have one shape and their folders stand at the
same saved step. Each job keeps its own data, seed and number of runs. A job that cannot share
(a lone job, a bad override, a finished folder) runs alone, exactly as without this launcher.
An interrupted group saves every job's checkpoint; the same command resumes it.
"""

import dataclasses
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from moex import budget, pilot, provenance
from moex.config import Config
from moex.data import load_task
from moex.errors import ConfigError, Interrupted
from moex.jobs import Job, packing_key, saved_position, train_jobs
from moex.resume import open_checkpoint
from moex.stop import StopRequest

log = logging.getLogger(__name__)
# seconds of a packed batch's training each job's share (its networks / the batch's), by job
# folder: its status.json adds them to its own time
SHARED_SECONDS: dict[Path, float] = {}


def shared_seconds(out_dir: Path) -> float:
    """A job's share of the packed training done for it in this process (0 where none)."""
    return SHARED_SECONDS.get(Path(out_dir).resolve(), 0.0)


@dataclass
class Planned:
    """A job of the sweep: its config and folder (the launcher's), its data and checkpoint."""

    cfg: Config
    out_dir: Path
    job: Job | None = None  # None: the job runs alone (it cannot be prepared here, or is done)


def prepare(cfg: Config, out_dir: Path) -> Planned:
    """A job ready to pack, or one left to run alone (its own run reports any error)."""
    try:
        dataset = load_task(cfg)  # (first: it settles the data's defaults, sigma_min=auto)
        pilot.settle(cfg, dataset, out_dir)
        saved = open_checkpoint(cfg, out_dir)
        if saved is not None and saved.phase == "done":
            return Planned(cfg, out_dir)
        return Planned(cfg, out_dir, Job(cfg, dataset, out_dir, saved))
    except ConfigError:
        return Planned(cfg, out_dir)


def groups(planned: list[Planned], max_runs: int = 0) -> list[list[Job]]:
    """The batches to train: jobs of one key, data shape and saved step, in sweep order, split
    where a batch would exceed `max_runs` networks (0: no limit); groups of one job are left to
    run alone."""
    by_key: dict[tuple, list[list[Job]]] = {}
    for item in planned:
        if item.job is None:
            continue
        job = item.job
        key = (packing_key(job.cfg), tuple(job.dataset.series.shape), saved_position(job.saved))
        batches = by_key.setdefault(key, [[]])
        if max_runs and batches[-1] and \
                sum(j.cfg.num_runs for j in batches[-1]) + job.cfg.num_runs > max_runs:
            batches.append([])
        batches[-1].append(job)
    return [batch for batches in by_key.values() for batch in batches if len(batch) > 1]


def train_group(jobs: list[Job], on_interrupt) -> None:
    """Train one batch (its networks' time and versions recorded in every job's provenance);
    an interruption saves every job's checkpoint, calls `on_interrupt(jobs, exc)` and ends the
    process; any other failure is logged and leaves the jobs to run alone."""
    total = sum(job.cfg.num_runs for job in jobs)
    folders = [job.out_dir for job in jobs]
    log.info("packed: %d jobs, %d networks in one batch (%s)", len(jobs), total,
             ", ".join(Path(f).name for f in folders))
    first = jobs[0].cfg
    try:
        budget.check_train(dataclasses.replace(first, num_runs=total),
                           *jobs[0].dataset.series.shape)
    except ConfigError as exc:
        log.warning("packed: %s; these jobs run one by one (or set hydra.launcher.max_runs)", exc)
        return
    with StopRequest() as stop:
        try:
            started = time.perf_counter()
            with provenance.recorded(folders, "train", first.backend, first.device,
                                     first.precision):
                provenance.note(packed={"jobs": [str(f) for f in folders], "networks": total})
                train_jobs(jobs, stop)
            took = time.perf_counter() - started
            for job in jobs:  # each job's share of the batch, by its networks
                SHARED_SECONDS[Path(job.out_dir).resolve()] = took * job.cfg.num_runs / total
        except Interrupted as exc:
            on_interrupt(jobs, exc)
            sys.exit(128 + (stop.signum or 2))
        except Exception:
            log.exception("packed training of %s failed; its jobs run one by one",
                          ", ".join(str(f) for f in folders))
