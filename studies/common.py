"""What every study shares: where the pages, CSVs and figures live."""

from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"  # the pages, their CSVs and figures
