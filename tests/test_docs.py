"""REPRODUCTION.md quotes the verdict table that docs/verdicts.py recomputes from the CSVs."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_verdict_table_is_the_one_the_csvs_give():
    spec = importlib.util.spec_from_file_location("verdicts", ROOT / "docs" / "verdicts.py")
    verdicts = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(verdicts)
    table = verdicts.markdown(verdicts.verdicts())
    assert len(table.splitlines()) == 2 + 4 * 5 + 3 * 3
    assert table in (ROOT / "REPRODUCTION.md").read_text()
