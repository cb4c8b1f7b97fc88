"""`provenance.json`: what produced a run folder — package versions, the CPU (and the flags that
change compiled code), the GPU, threads, backend, precision, moex's version and git commit, the
command line, and wall/CPU seconds per part. Appended once per command that writes the folder
(a resumed training adds a second record), shown on the run's page, compared by `moex report`.

Bit-identical reruns are promised on the same machine with the same versions: `EXACTNESS` are
the fields that must agree for two folders' numbers to be comparable bit for bit.
"""

import json
import os
import platform
import subprocess
import sys
import time
from contextlib import contextmanager
from contextvars import ContextVar
from importlib import metadata
from pathlib import Path

from moex.io import atomic_write

NAME = "provenance.json"
PACKAGES = ("moex", "numpy", "torch", "numba", "llvmlite", "triton", "hydra-core", "omegaconf")
FLAGS = ("avx2", "fma", "avx512f", "avx512dq", "avx512vl")  # what numba/LLVM compile for
EXACTNESS = ("versions", "cpu", "cpu_flags", "gpu", "backend", "precision")


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def _cpu() -> tuple[str, list[str]]:
    """The model name and the compile-relevant flags of the first processor."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine(), []
    first = {}
    for line in text.splitlines():
        if not line.strip():
            break  # the end of the first processor's block
        key, _, value = line.partition(":")
        first[key.strip()] = value.strip()
    flags = first.get("flags", "").split()
    return first.get("model name", platform.machine()), [f for f in FLAGS if f in flags]


def _git() -> dict:
    """The commit of the checkout moex runs from (None when installed from a wheel), and
    whether it had uncommitted changes."""
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"],
                                capture_output=True, text=True, timeout=5)
        if commit.returncode:
            return {"commit": None, "dirty": None}
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--", "."],
                               capture_output=True, text=True, timeout=5)
        return {"commit": commit.stdout.strip(), "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def collect(verb: str, backend: str | None, device: str | None, precision: str | None) -> dict:
    """This process's record (everything but the times)."""
    import numba
    import torch

    model, flags = _cpu()
    gpu = None
    if (device or "").startswith("cuda") and torch.cuda.is_available():
        gpu = {"name": torch.cuda.get_device_name(), "cuda": torch.version.cuda}
    return {"verb": verb, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            "host": platform.node(), "python": platform.python_version(),
            "versions": {p: _version(p) for p in PACKAGES}, "git": _git(),
            "cpu": model, "cpu_flags": flags, "cores": os.cpu_count(), "gpu": gpu,
            "threads": {"numba": numba.get_num_threads(), "torch": torch.get_num_threads()},
            "backend": backend, "device": device, "precision": precision, "seconds": {}}


def read(folder: Path) -> list[dict]:
    """The records of a folder (oldest first); [] when it has none (or an unreadable file)."""
    try:
        records = json.loads((Path(folder) / NAME).read_text())
    except (OSError, ValueError):
        return []
    return records if isinstance(records, list) else []


_CURRENT: ContextVar[dict | None] = ContextVar("provenance", default=None)


@contextmanager
def recorded(out_dir: Path | list[Path], verb: str, backend: str | None, device: str | None,
             precision: str | None):
    """Append this command's record to `out_dir`/provenance.json (to each folder of a list: the
    jobs of a packed batch) when it ends: on success, and for `train` also when it fails or is
    interrupted (its folder stays); a refused or failed evaluate/generate/import leaves nothing.
    Parts are timed with `part(name)` meanwhile."""
    record = collect(verb, backend, device, precision)
    folders = out_dir if isinstance(out_dir, list) else [out_dir]
    token = _CURRENT.set(record)
    try:
        yield record
    except BaseException:
        if verb == "train":
            for folder in folders:
                save(folder, record)
        raise
    else:
        for folder in folders:
            save(folder, record)
    finally:
        _CURRENT.reset(token)


@contextmanager
def kept(verb: str, backend: str | None, device: str | None, precision: str | None):
    """This process's record for work that writes no folder yet (`moex.fit`): parts are timed
    into it; the caller keeps it and writes it with `save` (`Fitted.save`)."""
    record = collect(verb, backend, device, precision)
    token = _CURRENT.set(record)
    try:
        yield record
    finally:
        _CURRENT.reset(token)


def save(out_dir: Path, record: dict) -> None:
    """Append a record (a kept one, or the running command's) to `out_dir`/provenance.json."""
    text = json.dumps(read(out_dir) + [record], indent=1)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    atomic_write(Path(out_dir) / NAME, lambda tmp: Path(tmp).write_text(text))


@contextmanager
def part(name: str):
    """Time a part of the current command (wall and CPU seconds); nothing outside a command."""
    record = _CURRENT.get()
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        if record is not None:
            record["seconds"][name] = {"wall": round(time.perf_counter() - wall, 3),
                                       "cpu": round(time.process_time() - cpu, 3)}


def note(**fields) -> None:
    """Set fields of the current command's record (e.g. the backend once it is chosen)."""
    record = _CURRENT.get()
    if record is not None:
        record.update(fields)


def records(folder: Path) -> list[dict]:
    """The folder's records, with the running command's record last where there is one."""
    current = _CURRENT.get()
    return read(folder) + ([current] if current is not None else [])


def exactness_key(records: list[dict]) -> str:
    """The fields of `EXACTNESS` of a folder's last record, as one comparable string ("" when
    the folder has no record)."""
    if not records:
        return ""
    last = records[-1]
    return json.dumps({k: last.get(k) for k in EXACTNESS}, sort_keys=True)


def summary_line(records: list[dict]) -> str:
    """One line for a run's page."""
    if not records:
        return "Provenance: not recorded (written before moex recorded it)."
    r = records[-1]
    v = r.get("versions", {})
    git = r.get("git") or {}
    commit = (git.get("commit") or "")[:10] + (" (uncommitted changes)" if git.get("dirty")
                                               else "")
    return (f"Provenance (`{NAME}`, {len(records)} command(s)): moex {v.get('moex')}"
            f"{' at ' + commit if commit else ''}; Python {r.get('python')}, torch "
            f"{v.get('torch')}, numba {v.get('numba')}, triton {v.get('triton')}; CPU "
            f"{r.get('cpu')} ({', '.join(r.get('cpu_flags', [])) or 'no AVX'}), "
            f"{(r.get('gpu') or {}).get('name', 'no GPU')}; {r.get('threads', {}).get('numba')} "
            f"numba thread(s); backend {r.get('backend')}, {r.get('precision')}; "
            f"`{r.get('command')}`.")
