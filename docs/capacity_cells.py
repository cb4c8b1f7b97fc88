"""Figs. 14 and 16 cell by cell, at ρ² = 0, 10⁻⁴ and 10⁻³: the retrained grid and the NT 20 cells.

    python docs/capacity_cells.py grid REPORT_DIR      # REPORT_DIR/summary.csv, `moex report`'s
    python docs/capacity_cells.py add REPORT_DIR       # its new cells into that CSV
    python docs/capacity_cells.py nt20 EVAL_ROOT [LT]  # EVAL_ROOT/nc<NC>_noise<ρ²>/metrics.csv
    python docs/capacity_cells.py window WINDOW_ROOT   # <sweep>_<job>_noise<ρ²>/metrics.csv

`grid` reads the per-network table `moex report` wrote for the grid's sweeps (each job trained,
then `moex evaluate run_dir=<job> eval.noise_var=<ρ²>` for ρ² > 0) and writes
docs/capacity_grid_summary.csv. `add` appends the cells of a later `moex report` (a sweep over
cells the CSV lacks, e.g. the LT 2000 column) to that CSV and refuses a network it already has,
so the grid grows without the earlier sweeps' folders. `nt20` reads one
`moex evaluate ... out_dir=` folder per NC and ρ² of an NT 20 cell and writes
docs/capacity_nt20_summary.csv (LT 1000, the default) or docs/capacity_nt20_lt<LT>_summary.csv.
`window` reads the grid's jobs evaluated again with periodicity judged on 10 000 closed-loop
steps per sample (`eval.lyapunov_steps=10000`, folders named after the sweep below
outputs/paper_capacity/, the job and ρ²), writes docs/capacity_window10k_summary.csv and prints
`window_table`.
`grid` and `nt20` print, per cell and ρ²: networks with λ_max > 0 by sign, beyond twice its
standard error over the samples, and above 10⁻⁴ (a limit cycle's finite-time exponent is 0 only
up to a bias of order 1/steps that every sample shares, so the standard error alone does not
bound it; `zero_band` measures that bias on the networks whose every sample is periodic), the
switching probability, the networks that stay on one curve (< 0.02), the mean nonperiodic share
and the networks with a majority of nonperiodic samples, and E^closed.
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
SAMPLES = 50  # closed-loop samples per network, from 50 random initial states (Sec. 3.2.1)
FIRST_TRAINING = ["capacity_summary.csv", "capacity_nc20_summary.csv"]
OUTCOMES = ["max_lyapunov", "switch_prob", "nonperiodic_fraction"]
# NT 20 cells trained before the grid's NT 20 sweeps, by `nt20` mode: file -> LT (NC 10, 20, 30
# at LT 1000; NC 10 at LT 250)
NT20_CELLS = {"capacity_nt20_summary.csv": 1000, "capacity_nt20_lt250_summary.csv": 250}


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


def merge_cells(parts: list[pd.DataFrame]) -> pd.DataFrame:
    """Per-network tables of disjoint cells as one, sorted; a network (cell, ρ², run) in two
    parts is an error, not a silent duplicate."""
    runs = pd.concat(parts, ignore_index=True)[CELL + ["noise_var"] + COLUMNS
                                               + ["periodicity_samples"]]
    twice = runs[runs.duplicated(CELL + ["noise_var", "run"], keep=False)]
    if len(twice):
        cells = sorted({tuple(int(v) for v in row) for row in twice[CELL].to_numpy()})
        raise ValueError(f"networks appear twice, cells (NC, NT, LT) {cells}")
    return runs.sort_values(CELL + ["noise_var", "run"], ignore_index=True)


def collect_grid(report_dir: Path) -> pd.DataFrame:
    """The grid: `moex report`'s per-network table, one row per network, cell and ρ², with the
    NT 20 cells trained on their own (`NT20_CELLS`; their sample counts were not recorded)."""
    return merge_cells([pd.read_csv(report_dir / "summary.csv")]
                       + [pd.read_csv(DOCS / name).assign(num_series=20, length=length)
                          for name, length in NT20_CELLS.items()])


def zero_band(table: pd.DataFrame) -> float:
    """The largest noiseless λ_max of a network whose every sample was judged periodic: how far
    from 0 the estimator puts exponents that should be 0 or negative (limit cycles). Only
    networks whose samples were all judged (`periodicity_samples` recorded and `SAMPLES`) count."""
    periodic = table[(table.noise_var == 0) & (table.nonperiodic_fraction == 0)
                     & (table.periodicity_samples == SAMPLES)]
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


def replication(table: pd.DataFrame) -> pd.DataFrame:
    """The retrained grid against its first training (the same seeds and commands, another CPU
    and kernel build; docs/capacity_summary.csv and capacity_nc20_summary.csv), network by
    network without noise: how far round-off alone moves a network's outcome."""
    first = pd.concat([pd.read_csv(DOCS / name) for name in FIRST_TRAINING])
    first = first[first.noise_var_setting == 0]
    keys = CELL + ["run"]
    pairs = table[table.noise_var == 0].merge(first[keys + OUTCOMES], on=keys,
                                              suffixes=("", "_first"))
    moved = (pairs.switch_prob - pairs.switch_prob_first).abs()
    now, then = pairs.max_lyapunov > THRESHOLD, pairs.max_lyapunov_first > THRESHOLD
    majority = (pairs.nonperiodic_fraction > 0.5) == (pairs.nonperiodic_fraction_first > 0.5)
    cells = [pairs[k] for k in CELL]
    cell_moves = (now.groupby(cells).sum() - then.groupby(cells).sum()).abs()
    return pd.DataFrame([{
        "networks paired": len(pairs),
        "cells whose count above 10⁻⁴ moved by 0-2 / 3-5 / more": (
            f"{(cell_moves <= 2).sum()} / {cell_moves.between(3, 5).sum()} / "
            f"{(cell_moves > 5).sum()}"),
        "λ_max bit-identical": int((pairs.max_lyapunov == pairs.max_lyapunov_first).sum()),
        "same side of 10⁻⁴": f"{(now == then).mean():.0%}",
        "switching moved, median (90 %)": f"{moved.median():.3f} ({moved.quantile(0.9):.3f})",
        "switching correlation": round(pairs.switch_prob.corr(pairs.switch_prob_first), 2),
        "same majority (nonperiodic or not)": f"{majority.mean():.0%}",
    }])


def _mostly_nonperiodic(table: pd.DataFrame, noise: float) -> int | str:
    """Networks with a majority of nonperiodic samples at one noise level, "–" if not run."""
    at = table.nonperiodic_fraction[table.noise_var == noise]
    return int((at > 0.5).sum()) if len(at) else "–"


def collect_window(root: Path) -> pd.DataFrame:
    """The grid's jobs evaluated on 10 000 steps per sample, the cell read from each sweep's
    jobs.csv."""
    parts = []
    for folder in sorted(f.parent for f in root.glob("*_noise*/metrics.csv")):
        sweep, job, noise = re.fullmatch(r"(.+)_(\d+)_noise([0-9.e-]+)", folder.name).groups()
        jobs = pd.read_csv(root.parent / sweep / "jobs.csv", dtype=str).set_index("folder")
        cell = dict(kv.split("=") for kv in jobs.loc[job, "overrides"].split())
        runs = pd.read_csv(folder / "metrics.csv")[["run", "nonperiodic_fraction",
                                                    "periodicity_samples"]]
        for key, override in zip(CELL, ("model.gating.context_size", "task.num_series",
                                        "task.length"), strict=True):
            runs.insert(0, key, int(cell[override]))
        runs.insert(0, "noise_var", float(noise))
        parts.append(runs)
    return pd.concat(parts, ignore_index=True).sort_values(CELL + ["noise_var", "run"],
                                                           ignore_index=True)


def window_table(window: pd.DataFrame, grid: pd.DataFrame) -> pd.DataFrame:
    """Networks with a majority of nonperiodic samples, judged on 100 000 (the grid) and on
    10 000 steps per sample, per cell at ρ² = 0 and 10⁻³."""
    rows = []
    for values, cell in window.groupby(CELL):
        full = grid.merge(pd.DataFrame([dict(zip(CELL, values, strict=True))]))
        row = dict(zip(["NC", "NT", "LT"], values, strict=True))
        for noise in (0, 1e-3):
            row[f"ρ² = {noise:g}: 100 000 → 10 000 steps"] = (
                f"{_mostly_nonperiodic(full, noise)} → {_mostly_nonperiodic(cell, noise)}")
        rows.append(row)
    return pd.DataFrame(rows)


def _e_closed(c: pd.DataFrame) -> str:
    return f"{c.E_closed.mean():.4f} ± {c.E_closed.std():.4f}"


def _chaotic(c: pd.DataFrame) -> str:
    return f"{(c.max_lyapunov > THRESHOLD).sum()} ({(c.max_lyapunov > 0).sum()})"


def _switching(c: pd.DataFrame) -> str:
    return f"{c.switch_prob.mean():.2f} ± {c.switch_prob.std():.2f}"


def _nonperiodic(c: pd.DataFrame) -> str:
    return " → ".join(str(_mostly_nonperiodic(c, v)) for v in (0, 1e-4, 1e-3))


# title -> (which evaluations, the cell's entry): Fig. 14's quantities without noise, Fig. 16's
CELL_TABLES = {
    "E^closed, mean ± sd": (True, _e_closed),
    "λ_max > 10⁻⁴ (in brackets > 0), of 10": (True, _chaotic),
    "switching probability, mean ± sd (data 0.5)": (True, _switching),
    "mostly nonperiodic at ρ² = 0 → 10⁻⁴ → 10⁻³, of 10": (False, _nonperiodic),
}


def cell_tables(table: pd.DataFrame) -> str:
    """The grid's pivot tables REPRODUCTION.md quotes, one per quantity (rows NC × NT)."""
    parts = []
    for title, (noiseless, value) in CELL_TABLES.items():
        rows = table[table.noise_var == 0] if noiseless else table
        lengths = sorted(rows.length.unique())
        frame = pd.DataFrame([
            {"NC": nc, "NT \\\\ LT": nt,
             **{str(lt): value(cell[cell.length == lt]) if (cell.length == lt).any() else "–"
                for lt in lengths}}
            for (nc, nt), cell in rows.groupby(["context_size", "num_series"])])
        parts.append(f"{title}:\n\n{to_markdown(frame)}")
    return "\n".join(parts)


if __name__ == "__main__":
    mode, source = sys.argv[1], Path(sys.argv[2])
    if mode == "window":
        table = collect_window(source)
        table.to_csv(DOCS / "capacity_window10k_summary.csv", index=False)
        print(to_markdown(window_table(table, pd.read_csv(DOCS / "capacity_grid_summary.csv"))))
        sys.exit()
    if mode in ("grid", "add"):
        name = "capacity_grid_summary.csv"
        table = (collect_grid(source) if mode == "grid" else
                 merge_cells([pd.read_csv(DOCS / name), pd.read_csv(source / "summary.csv")]))
        print(f"zero band (largest λ_max of an all-periodic network): {zero_band(table):.3g}")
        print(cell_tables(table))
        print(to_markdown(replication(table)))
    else:
        length = sys.argv[3] if len(sys.argv) > 3 else "1000"
        table = collect_evals(source)
        name = f"capacity_nt20{'' if length == '1000' else f'_lt{length}'}_summary.csv"
    table.to_csv(DOCS / name, index=False)
    print(to_markdown(summary(table)))
