"""Every artefact a run reads or writes. Writes are atomic: a temporary file in the same folder is
renamed over the target, so a kill leaves the old file or the new one, never a truncated one."""

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

HISTORY_CSV = "history.csv"
METRICS_CSV = "metrics.csv"
SAMPLES = "samples.npz"
FIGURES = "figures"
SEGMENTS = "segments.csv"
SEGMENT_SCORES = "segment_scores.csv"
LABEL_STAYS = "label_stays.csv"
GATE_PRIOR = "gate_prior.csv"  # train.experts.gate_prior_std=auto: the pilot's choice (moex.pilot)
EVAL_SETTINGS = "eval_config.yaml"  # the evaluation settings `moex evaluate` used


def atomic_write(path: Path, write: Callable[[str], None]) -> Path:
    """Call `write(tmp_path)` and rename the result onto `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def write_csv(path: Path, rows: list[dict] | pd.DataFrame) -> Path:
    frame = rows if isinstance(rows, pd.DataFrame) else pd.DataFrame(rows)
    return atomic_write(path, lambda tmp: frame.to_csv(tmp, index=False))


def chosen_gate_prior(folder: Path) -> float | None:
    """The ς a pilot chose for the run folder (its GATE_PRIOR table's chosen row); None where
    no pilot ran."""
    path = Path(folder) / GATE_PRIOR
    if not path.is_file():
        return None
    table = pd.read_csv(path)
    return float(table.loc[table["chosen"], "gate_prior_std"].iloc[0])


def write_yaml(path: Path, data: dict) -> Path:
    text = yaml.safe_dump(data, sort_keys=False)
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def save_arrays(path: Path, arrays: dict) -> Path:
    """`samples.npz`: named numpy arrays, compressed."""
    return atomic_write(path, lambda tmp: np.savez_compressed(tmp, **arrays))
