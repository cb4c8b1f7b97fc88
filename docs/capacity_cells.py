"""Figs. 14 and 16 cell by cell, at ρ² = 0, 10⁻⁴ and 10⁻³: the retrained grid and the NT 20 cells.

    python docs/capacity_cells.py grid REPORT_DIR      # REPORT_DIR/summary.csv, `moex report`'s
    python docs/capacity_cells.py nt20 EVAL_ROOT [LT]  # EVAL_ROOT/nc<NC>_noise<ρ²>/metrics.csv

`grid` reads the per-network table `moex report` wrote for the grid's sweeps (each job trained,
then `moex evaluate run_dir=<job> eval.noise_var=<ρ²>` for ρ² > 0) and writes
docs/capacity_grid_summary.csv. `nt20` reads one `moex evaluate ... out_dir=` folder per NC and
ρ² of an NT 20 cell and writes docs/capacity_nt20_summary.csv (LT 1000, the default) or
docs/capacity_nt20_lt<LT>_summary.csv. Both print, per cell and ρ²: networks with λ_max > 0 by
sign, beyond twice its standard error over the samples, and above 10⁻⁴ (a limit cycle's
finite-time exponent is 0 only up to a bias of order 1/steps that every sample shares, so the
standard error alone does not bound it; `zero_band` measures that bias on the networks whose every
sample is periodic), the switching probability, the networks that stay on one curve (< 0.02),
the mean nonperiodic share and the networks with a majority of nonperiodic samples, and E^closed.
"""

import re
import sys
from pathlib import Path

import pandas as pd

from moex.report import to_markdown

DOCS = Path(__file__).resolve().parent
COLUMNS = ["run", "E_closed", "max_lyapunov", "max_lyapunov_se", "switch_prob",
           "nonperiodic_fraction"]
CELL = ["context_size", "num_series", "length"]
NAMES = {"context_size": "NC", "num_series": "NT", "length": "LT", "noise_var": "ρ²"}
THRESHOLD = 1e-4  # the grid tables' λ_max threshold for "chaotic"


def collect_evals(root: Path) -> pd.DataFrame:
    """One NT 20 cell: a folder of metrics per NC and ρ²."""
    parts = []
    for folder in sorted(root.glob("nc*_noise*")):
        nc, noise = re.fullmatch(r"nc(\d+)_noise([0-9.e-]+)", folder.name).groups()
        runs = pd.read_csv(folder / "metrics.csv")[COLUMNS]
        runs.insert(0, "noise_var", float(noise))
        runs.insert(0, "context_size", int(nc))
        parts.append(runs)
    return pd.concat(parts, ignore_index=True)


def collect_grid(report_dir: Path) -> pd.DataFrame:
    """The grid: `moex report`'s per-network table, one row per network, cell and ρ²."""
    runs = pd.read_csv(report_dir / "summary.csv")
    runs = runs[CELL + ["noise_var"] + COLUMNS + ["periodicity_samples"]]
    return runs.sort_values(CELL + ["noise_var", "run"], ignore_index=True)


def zero_band(table: pd.DataFrame) -> float:
    """The largest noiseless λ_max of a network whose every sample was judged periodic: how far
    from 0 the estimator puts exponents that should be 0 or negative (limit cycles)."""
    periodic = table[(table.noise_var == 0) & (table.nonperiodic_fraction == 0)]
    return float(periodic.max_lyapunov.max())


def summary(table: pd.DataFrame) -> pd.DataFrame:
    keys = [k for k in CELL if k in table] + ["noise_var"]
    rows = []
    for values, cell in table.groupby(keys):
        row = dict(zip([NAMES[k] for k in keys], values, strict=True))
        rows.append(row | {
            "networks": len(cell),
            "λ_max > 0": int((cell.max_lyapunov > 0).sum()),
            "λ_max > 2 s.e.": int((cell.max_lyapunov > 2 * cell.max_lyapunov_se).sum()),
            "λ_max > 10⁻⁴": int((cell.max_lyapunov > THRESHOLD).sum()),
            "switching": f"{cell.switch_prob.mean():.3f} ± {cell.switch_prob.std():.3f}",
            "stay (< 0.02)": int((cell.switch_prob < 0.02).sum()),
            "nonperiodic share": round(cell.nonperiodic_fraction.mean(), 3),
            "mostly nonperiodic": int((cell.nonperiodic_fraction > 0.5).sum()),
            "E^closed": round(cell.E_closed.mean(), 4)})
    return pd.DataFrame(rows)


if __name__ == "__main__":
    mode, source = sys.argv[1], Path(sys.argv[2])
    if mode == "grid":
        table, name = collect_grid(source), "capacity_grid_summary.csv"
        print(f"zero band (largest λ_max of an all-periodic network): {zero_band(table):.3g}")
    else:
        length = sys.argv[3] if len(sys.argv) > 3 else "1000"
        table = collect_evals(source)
        name = f"capacity_nt20{'' if length == '1000' else f'_lt{length}'}_summary.csv"
    table.to_csv(DOCS / name, index=False)
    print(to_markdown(summary(table)))
