"""A user's own switching series from CSV or NPY files (task `csv`)."""

import glob
import os

import numpy as np

from moex.errors import ConfigError, check


def _read_one(path: str) -> list[np.ndarray]:
    if path.endswith(".npy"):
        array = np.load(path, allow_pickle=False)
        check(array.ndim in (2, 3), f"task.path: {path} must hold a (T, D) or (S, T, D) array, "
                                   f"got shape {array.shape}")
        return list(array) if array.ndim == 3 else [array]
    rows = []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            try:
                rows.append([float(v) for v in line.replace(",", " ").split()])
            except ValueError:
                raise ConfigError(f"task.path: {path} line {line_no} is not numeric") from None
            check(len(rows[-1]) == len(rows[0]),
                  f"task.path: {path} line {line_no} has {len(rows[-1])} columns, "
                  f"expected {len(rows[0])} (ragged rows)")
    check(len(rows) > 0, f"task.path: {path} holds no data rows")
    return [np.array(rows)]


def load_series(pattern: str, length: int, min_length: int) -> np.ndarray:
    """Series (S, T, D) from every file matching `pattern` (a file, a glob or a folder).

    Each CSV file (rows = time steps, columns = features) is one series; an NPY file holds one
    (T, D) series or a stack (S, T, D). `length` > 0 crops every series to its first `length`
    steps; otherwise all series must have equal length.
    """
    check(bool(pattern), "task.path is empty: name a CSV/NPY file, a glob or a folder")
    paths = sorted(glob.glob(os.path.join(pattern, "*")) if os.path.isdir(pattern)
                   else glob.glob(pattern))
    paths = [p for p in paths if p.endswith((".csv", ".txt", ".npy"))]
    check(len(paths) > 0, f"task.path={pattern} matches no .csv, .txt or .npy file")
    series = [s for p in paths for s in _read_one(p)]
    for p, s in zip(paths, series, strict=False):
        check(bool(np.isfinite(s).all()), f"task.path: {p} contains NaN or inf values")
        check(s.shape[1] == series[0].shape[1],
              f"task.path: {p} has {s.shape[1]} columns, expected {series[0].shape[1]}")
    lengths = {len(s) for s in series}
    if length > 0:
        check(min(lengths) >= length, f"task.length={length} exceeds the shortest series "
                                      f"({min(lengths)} steps)")
        series = [s[:length] for s in series]
    else:
        check(len(lengths) == 1, f"series lengths differ ({sorted(lengths)}); set task.length "
                                 f"to crop them to a common length")
    check(len(series[0]) >= min_length, f"task.path: series have {len(series[0])} steps, "
                                        f"need at least {min_length} (model.delay + 2)")
    return np.stack(series)
