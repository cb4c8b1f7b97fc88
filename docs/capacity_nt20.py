"""Figs. 14b and 16 with twice the grid's largest NT: the NT 20 cells (LT 1000 or another).

    python docs/capacity_nt20.py EVAL_ROOT [LT]   # folders EVAL_ROOT/nc<NC>_noise<ρ²>/metrics.csv

Each folder is `moex evaluate run_dir=<the cell's run> eval.noise_var=<ρ²>` (today's metrics,
among them λ_max's standard error over the 50 samples). Writes docs/capacity_nt20_summary.csv
(LT 1000, the default) or docs/capacity_nt20_lt<LT>_summary.csv (one row per network, NC and
ρ²) and prints per NC and ρ²: networks with λ_max > 0 by sign,
beyond twice its standard error over the samples, and above 10⁻⁴ (the grid tables' threshold: a
limit cycle's finite-time exponent is 0 only up to a bias of order 1/steps that every sample
shares, so the standard error alone does not bound it), the switching probability, the networks
that stay on one curve (< 0.02), the mean nonperiodic share and the networks with a majority of
nonperiodic samples, and E^closed.
"""

import re
import sys
from pathlib import Path

import pandas as pd

from moex.report import to_markdown

DOCS = Path(__file__).resolve().parent
COLUMNS = ["run", "E_closed", "max_lyapunov", "max_lyapunov_se", "switch_prob",
           "nonperiodic_fraction"]


def collect(root: Path) -> pd.DataFrame:
    parts = []
    for folder in sorted(root.glob("nc*_noise*")):
        nc, noise = re.fullmatch(r"nc(\d+)_noise([0-9.e-]+)", folder.name).groups()
        runs = pd.read_csv(folder / "metrics.csv")[COLUMNS]
        runs.insert(0, "noise_var", float(noise))
        runs.insert(0, "context_size", int(nc))
        parts.append(runs)
    return pd.concat(parts, ignore_index=True)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (nc, noise), cell in table.groupby(["context_size", "noise_var"]):
        n = len(cell)
        rows.append({
            "NC": nc, "ρ²": noise, "networks": n,
            "λ_max > 0": int((cell.max_lyapunov > 0).sum()),
            "λ_max > 2 s.e.": int((cell.max_lyapunov > 2 * cell.max_lyapunov_se).sum()),
            "λ_max > 10⁻⁴": int((cell.max_lyapunov > 1e-4).sum()),
            "switching": f"{cell.switch_prob.mean():.3f} ± {cell.switch_prob.std():.3f}",
            "stay (< 0.02)": int((cell.switch_prob < 0.02).sum()),
            "nonperiodic share": round(cell.nonperiodic_fraction.mean(), 3),
            "mostly nonperiodic": int((cell.nonperiodic_fraction > 0.5).sum()),
            "E^closed": round(cell.E_closed.mean(), 4)})
    return pd.DataFrame(rows)


if __name__ == "__main__":
    table = collect(Path(sys.argv[1]))
    length = sys.argv[2] if len(sys.argv) > 2 else "1000"
    name = f"capacity_nt20{'' if length == '1000' else f'_lt{length}'}_summary.csv"
    table.to_csv(DOCS / name, index=False)
    print(to_markdown(summary(table)))
