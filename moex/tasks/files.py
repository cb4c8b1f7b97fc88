"""A user's own switching series from CSV or NPY files (task `csv`)."""

import glob
import io
import os
import re

import numpy as np
import pandas as pd

from moex.errors import ConfigError, check

SEPARATOR = r"\s*,\s*|\s+"  # commas or spaces


def _read_text(path: str, columns: list[str]) -> np.ndarray:
    """One (T, D) series from a CSV/TXT file: numbers separated by commas or spaces, `#`
    comments, an optional header row of column names (required to pick `columns` by name)."""
    try:
        with open(path, encoding="utf-8-sig") as f:  # a byte-order mark is not data
            text = f.read()
    except UnicodeDecodeError:
        raise ConfigError(f"task.path: {path} is not a text file (it does not decode as UTF-8); "
                          f"give a CSV/TXT file of numbers or an NPY array") from None
    lines = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    lines = [line for line in lines if line]
    check(len(lines) > 0, f"task.path: {path} holds no data rows")
    fields = [len([v for v in re.split(SEPARATOR, line) if v]) for line in lines]
    first = [v for v in re.split(SEPARATOR, lines[0]) if v]
    header = not all(_is_number(v) for v in first)
    ragged = [n for n, count in enumerate(fields) if count != fields[0]]
    check(not ragged, f"task.path: {path} has rows of different lengths (data row "
                      f"{ragged[0] + 1 - header if ragged else 0} has "
                      f"{fields[ragged[0]] if ragged else 0} values, expected {fields[0]})")
    frame = pd.read_csv(io.StringIO("\n".join(lines)), sep=SEPARATOR, engine="python",
                        header=0 if header else None)
    if columns:
        check(header, f"task.columns={list(columns)} needs a header row naming the columns "
                      f"in {path}")
        missing = [c for c in columns if c not in frame.columns]
        check(not missing, f"task.columns: {missing} not in {path}; its columns are "
                           f"{', '.join(map(str, frame.columns))}")
        frame = frame[list(columns)]
    values = frame.apply(pd.to_numeric, errors="coerce")
    bad = values.isna() & frame.notna()
    if bad.to_numpy().any():
        row = int(np.flatnonzero(bad.to_numpy().any(1))[0])
        raise ConfigError(f"task.path: {path} data row {row + 1} is not numeric "
                          f"({', '.join(map(str, frame.iloc[row].tolist()))})")
    return values.to_numpy(dtype=float)


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _read_one(path: str, columns: list[str]) -> list[np.ndarray]:
    if path.endswith(".npy"):
        check(not columns, f"task.columns selects CSV columns by name; {path} is an NPY array")
        try:
            array = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise ConfigError(f"task.path: {path} is not a readable NPY array ({exc})") from None
        check(array.ndim in (2, 3), f"task.path: {path} must hold a (T, D) or (S, T, D) array, "
                                   f"got shape {array.shape}")
        check(array.dtype.kind in "iuf", f"task.path: {path} holds {array.dtype} values; give "
                                         f"real numbers (integers or floats)")
        check(array.size > 0, f"task.path: {path} holds an empty array of shape {array.shape}; "
                              f"give at least one feature and one step")
        array = array.astype(float)
        return list(array) if array.ndim == 3 else [array]
    return [_read_text(path, columns)]


def load_series(pattern: str, length: int, min_length: int,
                columns: list[str] = ()) -> np.ndarray:
    """Series (S, T, D) from every file matching `pattern` (a file, a glob or a folder).

    Each CSV file (rows = time steps, columns = features, an optional header row) is one series;
    `columns` picks and orders its columns by header name. An NPY file holds one (T, D) series
    or a stack (S, T, D). `length` > 0 crops every series to its first `length` steps; otherwise
    all series must have equal length.
    """
    check(bool(pattern), "task.path is empty: name a CSV/NPY file, a glob or a folder")
    paths = sorted(glob.glob(os.path.join(pattern, "*")) if os.path.isdir(pattern)
                   else glob.glob(pattern))
    paths = [p for p in paths if p.endswith((".csv", ".txt", ".npy")) and not os.path.isdir(p)]
    check(len(paths) > 0, f"task.path={pattern} matches no .csv, .txt or .npy file")
    sources = [(p, i, s) for p in paths for i, s in enumerate(_read_one(p, list(columns)))]
    for p, i, s in sources:  # every series of a stack, named by its index
        where = f"{p} (series {i})" if p.endswith(".npy") else p
        bad = np.flatnonzero(~np.isfinite(s).all(1))
        check(not len(bad), f"task.path: {where} has NaN or inf values (first at step "
                            f"{bad[0] if len(bad) else 0}); remove or fill them")
        check(s.shape[1] == sources[0][2].shape[1],
              f"task.path: {where} has {s.shape[1]} columns, expected {sources[0][2].shape[1]}")
    series = [s for _, _, s in sources]
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
