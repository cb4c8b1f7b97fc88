"""A user's own switching series from CSV or NPY files (task `csv`)."""

import glob
import io
import os
import re
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd

from moex.errors import ConfigError, check
from moex.tasks.base import Dataset, Task, TaskConfig, user_data
from moex.tasks.scaling import SCALES, fit_scale

SEPARATOR = r"\s*,\s*|\s+"  # commas or spaces


def _read_text(path: str, columns: list[str], label: str = "") -> np.ndarray:
    """One (T, D) series from a CSV/TXT file: numbers separated by commas or spaces, `#`
    comments, an optional header row of column names (required to pick `columns` by name).
    `label` names a column of per-step labels: it is returned as the last column and never
    read as a feature."""
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
                        header=0 if header else None, dtype=str)  # parsed below, exactly
    if label:
        check(header and label in frame.columns,
              f"task.labels={label} is neither a column of {path} (its header: "
              f"{', '.join(map(str, frame.columns)) if header else 'none'}) nor a file")
        features = list(columns) or [c for c in frame.columns if c != label]
        check(label not in features, f"task.columns lists the label column {label}")
        columns = [*features, label]
    if columns:
        check(header, f"task.columns={list(columns)} needs a header row naming the columns "
                      f"in {path}")
        missing = [c for c in columns if c not in frame.columns]
        check(not missing, f"task.columns: {missing} not in {path}; its columns are "
                           f"{', '.join(map(str, frame.columns))}")
        frame = frame[list(columns)]
    cells = frame.fillna("nan").to_numpy(dtype=str)
    try:  # Python's own parsing: the nearest double to the written digits, on every pandas
        return cells.astype(float)
    except ValueError:
        row = next(i for i, r in enumerate(cells) if not all(map(_is_number, r)))
        raise ConfigError(f"task.path: {path} data row {row + 1} is not numeric "
                          f"({', '.join(frame.iloc[row].fillna('').tolist())})") from None


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _read_one(path: str, columns: list[str], label: str = "") -> list[np.ndarray]:
    if path.endswith(".npy"):
        check(not label, f"task.labels={label} names a CSV column; {path} is an NPY array "
                         f"(give the labels as a file)")
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
    return [_read_text(path, columns, label)]


def _paths(pattern: str) -> list[str]:
    paths = sorted(glob.glob(os.path.join(pattern, "*")) if os.path.isdir(pattern)
                   else glob.glob(pattern))
    return [p for p in paths if p.endswith((".csv", ".txt", ".npy")) and not os.path.isdir(p)]


def is_column_name(labels: str) -> bool:
    """Whether `task.labels` reads as a column name rather than a file, folder or glob."""
    return bool(labels) and not any(c in labels for c in "/*?[") and not labels.endswith(
        (".csv", ".txt", ".npy"))


def _integers(values: np.ndarray, where: str) -> np.ndarray:
    """Labels as integers >= -1 (-1: unknown), or a one-line refusal."""
    values = np.asarray(values, dtype=float)
    bad = np.flatnonzero(~np.isfinite(values) | (values != np.round(values)) | (values < -1))
    check(not len(bad), f"task.labels: {where} step {bad[0] if len(bad) else 0} has label "
                        f"{values[bad[0]] if len(bad) else 0}; labels are integers >= 0 "
                        f"(-1: unknown)")
    return values.astype(np.int64)


def load_labels(pattern: str, count: int) -> list[np.ndarray]:
    """Per-step labels (T,) of `count` series from every file matching `pattern`, in the
    series' order: a text file of one integer per row (an optional header) per series, or an
    NPY array (T,) or (S, T)."""
    paths = _paths(pattern)
    check(len(paths) > 0, f"task.labels={pattern} matches no .csv, .txt or .npy file (nor "
                          f"names a column of the series)")
    labels = []
    for path in paths:
        if path.endswith(".npy"):
            array = np.load(path, allow_pickle=False)
            check(array.ndim in (1, 2), f"task.labels: {path} must hold a (T,) or (S, T) array, "
                                        f"got shape {array.shape}")
            labels += list(array) if array.ndim == 2 else [array]
        else:
            table = _read_text(path, [])
            check(table.shape[1] == 1, f"task.labels: {path} has {table.shape[1]} columns; "
                                       f"give one label per row")
            labels.append(table[:, 0])
    check(len(labels) == count, f"task.labels={pattern} holds labels for {len(labels)} series; "
                                f"the data have {count}")
    return [_integers(v, f"series {i}") for i, v in enumerate(labels)]


def load_series(pattern: str, length: int, min_length: int, columns: list[str] = (),
                labels: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Series (S, T, D) from every file matching `pattern` (a file, a glob or a folder).

    Each CSV file (rows = time steps, columns = features, an optional header row) is one series;
    `columns` picks and orders its columns by header name. An NPY file holds one (T, D) series
    or a stack (S, T, D). `length` > 0 crops every series to its first `length` steps; otherwise
    all series must have equal length.

    `labels`: a column of the CSV files, or files (see `load_labels`), of per-step integer
    labels (-1 unknown). Returns the series and their labels (S, T) (all -1 without labels).
    """
    check(bool(pattern), "task.path is empty: name a CSV/NPY file, a glob or a folder")
    paths = _paths(pattern)
    check(len(paths) > 0, f"task.path={pattern} matches no .csv, .txt or .npy file")
    column = labels if is_column_name(labels) and not _paths(labels) else ""
    sources = [(p, i, s) for p in paths
               for i, s in enumerate(_read_one(p, list(columns), column))]
    if column:  # the label column is the last one read
        given = [_integers(s[:, -1], p) for p, _, s in sources]
        sources = [(p, i, s[:, :-1]) for p, i, s in sources]
    elif labels:
        given = load_labels(labels, len(sources))
    else:
        given = [np.full(len(s), -1) for _, _, s in sources]
    for (p, i, s), lab in zip(sources, given, strict=True):
        check(len(lab) >= len(s), f"task.labels: series {i} of {p} has {len(s)} steps but "
                                  f"{len(lab)} labels")
    for p, i, s in sources:  # every series of a stack, named by its index
        where = f"{p} (series {i})" if p.endswith(".npy") else p
        bad = np.flatnonzero(~np.isfinite(s).all(1))
        check(not len(bad), f"task.path: {where} has NaN or inf values (first at step "
                            f"{bad[0] if len(bad) else 0}); remove or fill them")
        check(s.shape[1] == sources[0][2].shape[1],
              f"task.path: {where} has {s.shape[1]} columns, expected {sources[0][2].shape[1]}")
    series = [s for _, _, s in sources]
    given = [lab[:len(s)] for lab, s in zip(given, series, strict=True)]
    lengths = {len(s) for s in series}
    if length > 0:
        check(min(lengths) >= length, f"task.length={length} exceeds the shortest series "
                                      f"({min(lengths)} steps)")
        series, given = [s[:length] for s in series], [g[:length] for g in given]
    else:
        check(len(lengths) == 1, f"series lengths differ ({sorted(lengths)}); set task.length "
                                 f"to crop them to a common length")
    check(len(series[0]) >= min_length, f"task.path: series have {len(series[0])} steps, "
                                        f"need at least {min_length} (model.delay + 2)")
    return np.stack(series), np.stack(given)


@dataclass
class CsvConfig(TaskConfig):
    """Your own series (`load_series`); num_series and length 0: as the files hold them."""

    name: str = "csv"
    num_series: int = 0
    length: int = 0
    num_test_series: int = 0
    path: str = ""  # a file, glob or folder
    labels: str = ""  # a column of per-step integer labels, or files of them (scored)
    columns: list[str] = field(default_factory=list)  # by header name (all if [])
    scale: str = "none"  # none (data must lie in [-1, 1]) | auto (each feature linearly)
    FILES: ClassVar[bool] = True

    def __post_init__(self):
        super().__post_init__()
        check(self.scale in SCALES, f"task.scale={self.scale!r}; choose none or auto")


def _read(cfg: CsvConfig, rng, min_length) -> Dataset:
    series, labels = load_series(cfg.path, cfg.length, min_length, cfg.columns, cfg.labels)
    series, scale = fit_scale(series, cfg.scale, f"task.path={cfg.path}")
    return user_data(series, scale, labels)


TASKS = (Task(CsvConfig, _read),)
