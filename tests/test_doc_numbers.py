"""Every number the hand-written reproduction pages quote comes from a CSV, a script's output or
the paper: a guard that catches a number left behind when its CSV changed.

A decimal number of two or more significant digits (0.0093, 2.6·10⁻³, −0.036; not 5, not 0.5)
in REPRODUCTION.md, docs/verdicts.md, docs/mregn_control.md or a page of docs/reproduction/ must
equal, to the digits it prints, one of:
- a cell of a CSV the page names (docs/*.csv), or that a page it links to names, or the mean,
  median, SD, standard error, smallest or largest value of a column of such a CSV over all its
  rows or over the rows that share one or two of its settings or names (a column of text or a
  config key, or of integers with at most 12 values: a batch, a cell, a design);
- a number of a table the docs scripts compute from those CSVs (the verdict tables, the
  capacity grid's, the control's, ...) or of a table `moex report` wrote that the page names
  (docs/<name>.md);
- one of the paper's values (moex.tasks.paper, studies/fig15.py's PAPER_FLIP);
- an entry of `ELSEWHERE` below: a fact with no CSV (a version, a wall time, a value the paper
  prints in its text), named with its source.
A guard, not a proof: a stale number can still equal some other value by chance (the pages'
sources hold 10⁴-10⁵ values; when this test was written, a random change of one quoted number's
last digit was caught in 34 of 265 trials), and whole numbers (counts) are not checked here. The
blocks that matter most are held to their scripts exactly in test_docs.py (the verdict tables,
the tally, the control's counts and means).
"""

import bisect
import importlib.util
import re
from functools import cache
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from moex.tasks.paper import PAPER_TABLE1, PAPER_TABLE2

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
PAGES = [ROOT / "REPRODUCTION.md", DOCS / "verdicts.md", DOCS / "mregn_control.md",
         *sorted((DOCS / "reproduction").glob("*.md"))]
SUPERSCRIPT = str.maketrans("⁻⁰¹²³⁴⁵⁶⁷⁸⁹", "-0123456789")
NUMBER = re.compile(r"(?<![\w.·])[−-]?\d+\.\d+(?:e[+-]?\d+|·10[⁻⁰¹²³⁴⁵⁶⁷⁸⁹]+)?(?![\d.])")
SHARED = re.compile(r"\(([−-]?\d+\.\d+) ± (\d+\.\d+)\)(·10[⁻⁰¹²³⁴⁵⁶⁷⁸⁹]+)")  # (a ± b)·10ᵏ
REPORT = re.compile(r"docs/(\w+\.md)")
CSV = re.compile(r"([\w]+\.csv)")
LINK = re.compile(r"\]\(([^)#]+\.md)")

# page → {number as printed: where it comes from}; facts no CSV holds, and values derived in ways
# the summaries above do not cover (each recomputed by hand from its CSV when it was listed; the
# ones whose source is not kept say so)
ELSEWHERE = {
    "docs/verdicts.md": {
        "1.4826": "the normal law's ratio of SD to median absolute deviation (robust_sd)"},
    "docs/mregn_control.md": {
        "3.6·10³": "the C tools' training logs (mre.dat) of the default build's NC 20 "
                   "networks (not kept here: not rechecked)"},
    "docs/reproduction/capacity.md": {
        "0.0316": "the C code's σ floor, 10^-1.5, a constant of its source"},
    "docs/reproduction/data_seeds.md": {"10.2": "a wall time"},
    "docs/reproduction/learning_curves.md": {
        "2.36": "learning_curves_history.csv: mean block_kl_train at gating step 0, lissajous2"},
    "docs/reproduction/lissajous9.md": {
        "0.0072": "the 10 000-step evaluation of that run (out_dir n5_short, not kept)",
        "7.2·10⁻⁴": "a one-network run on the AMD VM (its metrics.csv, not kept)"},
    "docs/reproduction/table1.md": {
        "−0.0154": "table1_nc30_held_out.csv: mean paired difference, 40 against 4 series"},
    "docs/reproduction/table2_onehot.md": {
        "9.7": "median |E one-hot / E soft − 1| at P = 0.5, table2_onehot30_summary.csv "
                 "against table2_summary.csv"},
    "docs/reproduction/table2_own_data.md": {
        "0.00085": "the difference of the two means printed before it (0.00234 − 0.00149)"},
}


def _script(name):
    """A study of the reproduction (`studies/`), imported as the package's module."""
    return importlib.import_module(f"studies.{name}")


def parse(text: str) -> tuple[float, float]:
    """The value a printed number stands for (2.6·10⁻³, 2.6e-03) and half its last digit."""
    mantissa, _, exponent = re.sub("·10|e", "^", text.replace("−", "-"), count=1).partition("^")
    scale = 10.0 ** int(exponent.translate(SUPERSCRIPT)) if exponent else 1.0
    return float(mantissa) * scale, 0.5 * 10.0 ** -len(mantissa.split(".")[1]) * scale


def significant(text: str) -> int:
    mantissa = re.sub("·10|e", "^", text).partition("^")[0]
    return len(mantissa.lstrip("−-").replace(".", "").lstrip("0"))


@cache
def csv_values(name: str) -> tuple[float, ...]:
    """Cells and summaries of docs/<name> (see the module's docstring)."""
    frame = pd.read_csv(DOCS / name)
    numbers = frame.apply(pd.to_numeric, errors="coerce").dropna(axis=1, how="all")
    text, whole = pd.api.types.is_string_dtype, pd.api.types.is_integer_dtype
    keys = [c for c in frame.columns  # settings and names, not metrics
            if 1 < frame[c].nunique() <= (40 if text(frame[c]) or "." in c
                                          else 12 if whole(frame[c]) else 0)]
    everything = [pd.Series(0, index=frame.index)]
    groupings = [everything, *([frame[a]] for a in keys),
                 *([frame[a], frame[b]] for i, a in enumerate(keys) for b in keys[i + 1:])]
    values = [numbers.to_numpy(float).ravel()]
    for by in groupings:  # each statistic by its own groupby method: .agg([...]) took 20 s
        groups = numbers.groupby(by)
        stats = {f: getattr(groups, f)().astype(float)
                 for f in ("mean", "median", "min", "max", "std", "count")}
        values += [stat.to_numpy().ravel() for stat in stats.values()]
        values.append((stats["std"] / np.sqrt(stats["count"])).to_numpy().ravel())
    values = np.concatenate(values).astype(float)
    return tuple(values[np.isfinite(values)])


def numbers(text: str) -> list[str]:
    """The decimal numbers of a text as printed, "(a ± b)·10ᵏ" read as a·10ᵏ and b·10ᵏ."""
    return NUMBER.findall(SHARED.sub(r"\1\3 ± \2\3", text))


def named_sources(page: Path) -> set[str]:
    """The CSVs and `moex report` tables (docs/<name>.md) a page names, and the CSVs the pages it
    links to name."""
    text = page.read_text()
    names = set(CSV.findall(text)) | set(REPORT.findall(text))
    for link in LINK.findall(text):
        target = (page.parent / link).resolve()
        if target.is_file():
            names |= set(CSV.findall(target.read_text()))
    return {name for name in names
            if (DOCS / name).is_file() and DOCS / name not in PAGES}


def source_values(name: str) -> tuple[float, ...]:
    if name.endswith(".md"):  # a report table kept as moex report wrote it
        return tuple(parse(n)[0] for n in numbers((DOCS / name).read_text()))
    return csv_values(name)


def numbers_in(*items) -> list[float]:
    """The numbers of tables and texts: numeric cells, and the numbers printed in text cells."""
    out = []
    for item in items:
        if isinstance(item, pd.DataFrame):
            cells = item.apply(pd.to_numeric, errors="coerce").to_numpy(float).ravel()
            out += list(cells[np.isfinite(cells)])
            item = item.astype(str).to_csv()
        out += [parse(n)[0] for n in numbers(str(item))]
    return out


@cache
def computed() -> tuple[float, ...]:
    """The paper's values and the numbers of the tables the docs scripts compute from the CSVs
    (the tables test_docs.py finds on the pages)."""
    read = lambda name: pd.read_csv(DOCS / name)  # noqa: E731
    verdicts, cells, length = _script("verdicts"), _script("capacity_cells"), \
        _script("lissajous9_length")
    control, arms = _script("mregn_control"), _script("table1_arms")
    grid, fig16 = read("capacity_grid_summary.csv"), read("fig16_arms.csv")
    embedding = cells.embedding(grid)
    counts = lambda cell: [int(x) for x in cell.split(" / ")]  # noqa: E731
    fisher = [cells.fisher_p(k, n - k, k2, n2 - k2)  # as if the networks were independent
              for (k, n), (k2, n2) in zip(map(counts, embedding["stay on one curve: do not"]),
                                          map(counts, embedding["stay on one curve: embed"]),
                                          strict=True)]
    frame, frames = verdicts.verdicts(), length.arms()
    tracking, history = _script("lissajous9_tracking"), read("lissajous9_history.csv")
    tables = [verdicts.markdown(frame, evidence=True), verdicts.tool_question(),
              cells.summary(grid), cells.replication(grid),
              cells.window_table(read("capacity_window10k_summary.csv"), grid),
              cells.cell_tables(grid), cells.embedding(grid), cells.chaos_against_data(grid),
              cells.figure_rows(grid, fig16), _script("fig16_arms").table(fig16),
              length.table(frames), length.differences(frames), length.resolution(frames),
              control.table(), control.labels_table(), *_script("table2_onehot").table(),
              *_script("table2_designs").table(), _script("data_seeds").overview(),
              _script("residence").table(read("table2_own_data_residence.csv")),
              _script("fig15").power_table(read("fig15_end_summary.csv")),
              _script("roundoff").summary(read("roundoff_pairs.csv")),
              *(arms.summary(read(f"table1_nc{nc}_arms.csv")) for nc in (10, 20)),
              tracking.table(history), tracking.judged(history)]
    paper = [*PAPER_TABLE1.to_numpy().ravel(), *PAPER_TABLE2.to_numpy().ravel(),
             *_script("fig15").PAPER_FLIP]
    return tuple(np.asarray([*paper, *fisher, *numbers_in(*tables)], float))


def found(text: str, values: list[float]) -> bool:
    value, half = parse(text)
    for target in (value, -value):  # a page may quote a magnitude or a difference's sign
        i = bisect.bisect_left(values, target - half * (1 + 1e-9))
        if i < len(values) and values[i] <= target + half * (1 + 1e-9):
            return True
    return False


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_number_a_page_quotes_has_a_source(page):
    values = sorted([*computed(), *(v for name in named_sources(page)
                                    for v in source_values(name))])
    known = ELSEWHERE.get(str(page.relative_to(ROOT)), {})
    missing = [(n, line.strip()[:100]) for line in page.read_text().splitlines()
               for n in numbers(line)
               if significant(n) >= 2 and n not in known and not found(n, values)]
    assert not missing, f"{len(missing)} numbers without a source: {missing}"


def test_the_guard_finds_a_number_no_csv_holds_and_accepts_its_summaries():
    """A law of the matcher: a column's mean to its printed digits is found, a value a digit
    beyond it is not."""
    values = sorted(csv_values("mregn_control_networks.csv"))
    column = pd.read_csv(DOCS / "mregn_control_networks.csv")["max_lyapunov"].dropna()
    assert found(f"{column.mean():.4f}", values)
    assert found(f"{column.median():.3g}".replace("-", "−"), values)
    assert not found("123.456", values)
    assert parse("2.6·10⁻³") == pytest.approx((2.6e-3, 0.5e-4))
    assert parse("4.28e-05") == pytest.approx((4.28e-5, 0.5e-7))
    assert numbers("(1.38 ± 0.18)·10⁻⁴") == ["1.38·10⁻⁴", "0.18·10⁻⁴"]
    assert significant("0.0093") == 2 and significant("0.5") == 1
