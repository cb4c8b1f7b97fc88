"""REPRODUCTION.md quotes the tables that scripts in docs/ recompute from the CSVs."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_verdict_table_is_the_one_the_csvs_give():
    verdicts = _script("verdicts")
    table = verdicts.markdown(verdicts.verdicts())
    assert len(table.splitlines()) == 2 + 4 * 5 + 3 * 3
    assert table in (ROOT / "REPRODUCTION.md").read_text()


def test_the_one_hot_tables_are_the_ones_the_csvs_give():
    onehot = _script("table2_onehot")
    rows, pairs = onehot.table()
    assert len(rows) == 2 * len(pairs) and set(rows["targets"]) == {"soft", "one-hot"}
    text = (ROOT / "REPRODUCTION.md").read_text()
    assert onehot.markdown(rows) in text and onehot.markdown(pairs) in text
