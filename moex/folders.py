"""A run folder's bookkeeping outside the run itself: the lock that keeps a second moex process
out (`claim`, `release`), the job's `status.json`, a sweep's `jobs.csv` and its closing summary
line, and the removal of a folder a failed `evaluate` or `generate` left empty."""

import contextlib
import fcntl
import json
import logging
import os
import shutil
from pathlib import Path

from omegaconf import OmegaConf

from moex import checkpoint
from moex.errors import ConfigError, check
from moex.io import atomic_write, write_csv
from moex.resume import check_same_training

LOCK = ".moex.lock"
JOBS_INDEX = "jobs.csv"
STATUS = "status.json"


def write_job_index(sweep_dir: Path) -> None:
    """`jobs.csv` at the sweep root: every job folder so far and its overrides. Each job
    rewrites it when it starts (atomically), so the last one to start lists them all."""
    rows = []
    for path in sorted(sweep_dir.glob("*/.hydra/overrides.yaml"),
                       key=lambda p: (len(p.parent.parent.name), p.parent.parent.name)):
        overrides = OmegaConf.to_container(OmegaConf.load(path))
        rows.append({"folder": path.parent.parent.name, "overrides": " ".join(overrides)})
    if rows:
        write_csv(sweep_dir / JOBS_INDEX, rows)


def write_status(out_dir: Path, **status) -> None:
    """The job's `status.json` (done, failed or interrupted, and why), written atomically."""
    text = json.dumps(status, indent=1)
    atomic_write(out_dir / STATUS, lambda tmp: Path(tmp).write_text(text))


def read_status(out_dir: Path) -> str:
    """A job folder's status (done, failed, interrupted), "" where none was written."""
    try:
        return str(json.loads((out_dir / STATUS).read_text()).get("status", ""))
    except (OSError, ValueError, AttributeError):
        return ""


def discard_if_empty(out_dir: Path, verb: str) -> bool:
    """After a failed `evaluate` or `generate`: remove its new folder when it holds nothing but
    Hydra's log (the run folder itself is never touched). True when removed."""
    if verb == "train" or not out_dir.is_dir():
        return False
    logging.shutdown()  # release the log file before removing it
    if {p.name for p in out_dir.iterdir()} - {f"{verb}.log", LOCK}:
        return False
    shutil.rmtree(out_dir)
    if out_dir.parent.name == verb and not any(out_dir.parent.iterdir()):
        out_dir.parent.rmdir()
    return True


def sweep_summary(sweep_dir: Path, verb: str) -> tuple[str, int]:
    """One line at the end of a sweep (where it is, how its jobs ended, what to run next) and
    how many of its jobs failed."""
    ended: dict[str, int] = {}
    seconds = 0.0
    for path in sweep_dir.glob(f"*/{STATUS}"):
        with contextlib.suppress(OSError, ValueError):
            status = json.loads(path.read_text())
            ended[status.get("status", "?")] = ended.get(status.get("status", "?"), 0) + 1
            seconds += float(status.get("seconds", 0.0))
    jobs = len(list(sweep_dir.glob("*/.hydra")))
    counts = ", ".join(f"{n} {state}" for state, n in sorted(ended.items())) or f"{jobs} jobs"
    hint = f"\nmoex: compare them with: moex report {sweep_dir}" if verb == "train" else ""
    return (f"moex: sweep folder {sweep_dir}: {jobs} jobs ({counts}, {seconds / 60:.1f} min)"
            f"{hint}", ended.get("failed", 0))


def named_folder(args: list[str], key: str) -> Path | None:
    """The folder an explicit `key=...` override names (the last one wins), else None."""
    values = [a.split("=", 1)[1] for a in args if a.startswith(f"{key}=")]
    return Path(values[-1]) if values else None


def claim(args: list[str], multirun: bool, verb: str, cfg) -> int | None:
    """Before Hydra writes anything: check the folder a command was pointed at (a run folder,
    an out_dir, a sweep folder) and lock it against a second moex process. A run folder that
    holds a checkpoint must hold a readable one from the same training config, so that a
    refused command never touches a finished run. Returns the lock's file descriptor."""
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    folder = named_folder(args, key)
    if folder is None:  # a new dated folder: nobody else writes it
        return None
    shown = "out_dir" if verb != "train" and not multirun else key
    check(not folder.exists() or folder.is_dir(), f"{shown}={folder} is a file, not a folder")
    if verb == "train" and not multirun and (folder / checkpoint.NAME).exists():
        check_same_training(checkpoint.load(folder / checkpoint.NAME).config, cfg,
                                     folder / checkpoint.NAME)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise ConfigError(f"{shown}={folder} cannot be written ({exc.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ConfigError(f"{shown}={folder} is being written by another moex process (pid "
                          f"{holder}); wait for it to finish or choose another folder") from None
    if not (folder / LOCK).exists() or os.stat(folder / LOCK).st_ino != os.fstat(fd).st_ino:
        os.close(fd)  # the holder removed the file as we opened it: claim the new one
        return claim(args, multirun, verb, cfg)
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


def release(fd: int, args: list[str], multirun: bool) -> None:
    """Remove the lock file (a finished folder keeps no trace of it), then unlock."""
    folder = named_folder(args, "hydra.sweep.dir" if multirun else "hydra.run.dir")
    with contextlib.suppress(OSError):
        (folder / LOCK).unlink()
    os.close(fd)
