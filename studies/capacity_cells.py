"""Figs. 14 and 16 cell by cell, at ρ² = 0, 10⁻⁴ and 10⁻³: the retrained grid and the NT 20 cells.

    python -m studies.capacity_cells grid REPORT_DIR      # REPORT_DIR/summary.csv, `moex report`'s
    python -m studies.capacity_cells add REPORT_DIR       # its new cells into that CSV
    python -m studies.capacity_cells nt20 EVAL_ROOT [LT]  # EVAL_ROOT/nc<NC>_noise<ρ²>/metrics.csv
    python -m studies.capacity_cells window WINDOW_ROOT   # <sweep>_<job>_noise<ρ²>/metrics.csv

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
`grid` and `nt20` print, per cell and ρ²: networks with λ_max > 0 (the paper's criterion for
"chaotic", used throughout), beyond twice its standard error over the samples, and above 10⁻⁴
(the sensitivity criterion: a limit cycle's finite-time exponent is 0 only up to a bias of order
1/steps that every sample shares, so the standard error alone does not bound it; `zero_band`
measures that bias on the networks whose every sample is periodic), the
switching probability, the networks that stay on one curve (< 0.02), the mean nonperiodic share
and the networks with a majority of nonperiodic samples, and E^closed.
"""

import re
import sys
from math import comb
from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown
from studies.common import DOCS
from studies.junction import spearman

COLUMNS = ["run", "E_closed", "max_lyapunov", "max_lyapunov_se", "switch_prob",
           "nonperiodic_fraction"]
CELL = ["context_size", "num_series", "length"]
# a `moex report` summary names the cell by config keys; this study's tables by short names
FROM_REPORT = {"model.gating.context_size": "context_size", "task.num_series": "num_series",
               "task.length": "length"}
NAMES = {"context_size": "NC", "num_series": "NT", "length": "LT", "noise_var": "ρ²"}
CHAOS = 0.0  # λ_max above this: chaotic, the paper's criterion (Tables 1-2)
SENSITIVITY = 1e-4  # the stated second criterion, beside it (see `zero_band`)
DRAWS = 20000  # relabellings of a permutation test
SAMPLES = 50  # closed-loop samples per network, from 50 random initial states (Sec. 3.2.1)
FIRST_TRAINING = ["capacity_summary.csv", "capacity_nc20_summary.csv"]
OUTCOMES = ["max_lyapunov", "switch_prob", "nonperiodic_fraction"]
STAY = 0.02  # switching probability below this: the network stays on one curve
SMALL = 1250  # NT·LT up to which a cell has the least data (NT 2 at LT ≤ 500, NT 5 at LT 250)
LARGE = 10_000  # NT·LT from which Fig. 14a's row counts the networks that still embed their data
# E^closed below this: the network replays its training series from its trained initial state
# (Sec. 4.2's "embedded in initial states"); per network the values cluster below 10⁻⁴ and near 0.1
EMBEDS = 1e-2
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


def read_report(path: Path) -> pd.DataFrame:
    """A `moex report` summary.csv with the cell's columns under this study's names."""
    return pd.read_csv(path).rename(columns=FROM_REPORT)


def collect_grid(report_dir: Path) -> pd.DataFrame:
    """The grid: `moex report`'s per-network table, one row per network, cell and ρ², with the
    NT 20 cells trained on their own (`NT20_CELLS`; their sample counts were not recorded)."""
    return merge_cells([read_report(report_dir / "summary.csv")]
                       + [pd.read_csv(DOCS / name).assign(num_series=20, length=length)
                          for name, length in NT20_CELLS.items()])


def zero_band(table: pd.DataFrame) -> float:
    """The largest noiseless λ_max of a network whose every sample was judged periodic and that
    switches between the curves: how far from 0 the estimator puts exponents that should be 0
    or negative (limit cycles). Only networks whose samples were all judged
    (`periodicity_samples` recorded and `SAMPLES`) count. A network that stays on one curve
    writes one symbol for ever, periodic whatever its dynamics, so it does not count: some of
    those are chaotic (λ_max up to 5·10⁻³ with an L/R sequence of one letter)."""
    periodic = table[(table.noise_var == 0) & (table.nonperiodic_fraction == 0)
                     & (table.periodicity_samples == SAMPLES) & (table.switch_prob >= STAY)]
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
            "λ_max > 10⁻⁴": int((cell.max_lyapunov > SENSITIVITY).sum()),
            "switching": f"{cell.switch_prob.mean():.3f} ± {cell.switch_prob.std():.3f}",
            "stay (< 0.02)": int((cell.switch_prob < STAY).sum()),
            "nonperiodic share": round(cell.nonperiodic_fraction.mean(), 3),
            "mostly nonperiodic": int((cell.nonperiodic_fraction > 0.5).sum()),
            "E^closed": round(cell.E_closed.mean(), 4)})
    return pd.DataFrame(rows)


def replication(table: pd.DataFrame) -> pd.DataFrame:
    """The retrained grid against its first training (the same seeds and commands, another CPU
    and kernel build; docs/capacity_summary.csv and capacity_nc20_summary.csv), network by
    network without noise: how far round-off alone moves a network's outcome."""
    first = pd.concat([read_report(DOCS / name) for name in FIRST_TRAINING])
    first = first[first["eval.noise_var"] == 0]
    keys = CELL + ["run"]
    pairs = table[table.noise_var == 0].merge(first[keys + OUTCOMES], on=keys,
                                              suffixes=("", "_first"))
    moved = (pairs.switch_prob - pairs.switch_prob_first).abs()
    now, then = pairs.max_lyapunov > CHAOS, pairs.max_lyapunov_first > CHAOS
    majority = (pairs.nonperiodic_fraction > 0.5) == (pairs.nonperiodic_fraction_first > 0.5)
    cells = [pairs[k] for k in CELL]
    cell_moves = (now.groupby(cells).sum() - then.groupby(cells).sum()).abs()
    return pd.DataFrame([{
        "networks paired": len(pairs),
        "cells whose count above 0 moved by 0-2 / 3-5 / more": (
            f"{(cell_moves <= 2).sum()} / {cell_moves.between(3, 5).sum()} / "
            f"{(cell_moves > 5).sum()}"),
        "λ_max bit-identical": int((pairs.max_lyapunov == pairs.max_lyapunov_first).sum()),
        "same sign": f"{(now == then).mean():.0%}",
        "switching moved, median (90 %)": f"{moved.median():.3f} ({moved.quantile(0.9):.3f})",
        "switching correlation": round(pairs.switch_prob.corr(pairs.switch_prob_first), 2),
        "same majority (nonperiodic or not)": f"{majority.mean():.0%}",
    }])


def mostly_nonperiodic(table: pd.DataFrame, noise: float) -> int | str:
    """Networks with a majority of nonperiodic samples at one noise level, "–" if not run;
    "n/m" where only m networks had a sample long enough to judge (100 laps)."""
    at = table.nonperiodic_fraction[table.noise_var == noise]
    if not len(at):
        return "–"
    count, judged = int((at > 0.5).sum()), int(at.notna().sum())
    return count if judged == len(at) else f"{count}/{judged}"


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
                f"{mostly_nonperiodic(full, noise)} → {mostly_nonperiodic(cell, noise)}")
        rows.append(row)
    return pd.DataFrame(rows)


def _e_closed(c: pd.DataFrame) -> str:
    return f"{c.E_closed.mean():.4f} ± {c.E_closed.std():.4f}"


def chaotic(c: pd.DataFrame) -> str:
    """Networks with λ_max > 0, in brackets those above the sensitivity criterion 10⁻⁴."""
    return f"{(c.max_lyapunov > CHAOS).sum()} ({(c.max_lyapunov > SENSITIVITY).sum()})"


def _switching(c: pd.DataFrame) -> str:
    return f"{c.switch_prob.mean():.2f} ± {c.switch_prob.std():.2f}"


def _nonperiodic(c: pd.DataFrame) -> str:
    return " → ".join(str(mostly_nonperiodic(c, v)) for v in (0, 1e-4, 1e-3))


# title -> (which evaluations, the cell's entry): Fig. 14's quantities without noise, Fig. 16's
CELL_TABLES = {
    "E^closed, mean ± sd": (True, _e_closed),
    "λ_max > 0 (in brackets > 10⁻⁴), of 10": (True, chaotic),
    "switching probability, mean ± sd (data 0.5)": (True, _switching),
    "mostly nonperiodic at ρ² = 0 → 10⁻⁴ → 10⁻³, of 10 (n/m: of the m networks with a sample "
    "long enough to judge)": (False, _nonperiodic),
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


def fisher_p(a: int, b: int, c: int, d: int) -> float:
    """Fisher's exact test, two-sided, of the 2 × 2 table [[a, b], [c, d]]: the probability,
    with the margins fixed, of a table no more likely than this one."""
    row, col, n = a + b, a + c, a + b + c + d

    def prob(x: int) -> float:
        return comb(col, x) * comb(n - col, row - x) / comb(n, row)

    observed = prob(a)
    return min(1.0, sum(prob(x) for x in range(max(0, row + col - n), min(row, col) + 1)
                        if prob(x) <= observed * (1 + 1e-9)))


def cell_permutation_p(flags: pd.Series, embeds: pd.Series, cells: pd.Series) -> float:
    """Two-sided p of the difference between the share of `flags` among the networks that embed
    their data and among those that do not, from a permutation at the level of the cell: the
    cells' sets of embed labels are shuffled among the cells of equal size (a cell's networks
    share their data and experts, so they move together; `DRAWS` relabellings, the observed one
    counted)."""
    frame = pd.DataFrame({"flag": flags.to_numpy(), "embeds": embeds.to_numpy(),
                          "cell": cells.to_numpy()})

    def gap(e: np.ndarray, f: np.ndarray) -> np.ndarray:  # rows: relabellings
        n_e = e.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (e * f).sum(-1) / n_e - ((1 - e) * f).sum(-1) / (e.shape[-1] - n_e)

    rng, e_parts, f_parts = np.random.default_rng(0), [], []
    for _, same in frame.groupby(frame.groupby("cell").cell.transform("size")):
        labels = np.stack([c.embeds.to_numpy(float) for _, c in same.groupby("cell")])
        outcomes = np.stack([c.flag.to_numpy(float) for _, c in same.groupby("cell")])
        order = np.argsort(rng.random((DRAWS, len(labels))), axis=1)
        e_parts.append(labels[order].reshape(DRAWS, -1))
        f_parts.append(np.broadcast_to(outcomes.reshape(-1), (DRAWS, outcomes.size)))
    observed = gap(frame.embeds.to_numpy(float), frame.flag.to_numpy(float))
    null = gap(np.concatenate(e_parts, axis=1), np.concatenate(f_parts, axis=1))
    return float(((np.abs(null) >= abs(observed) - 1e-12).sum() + 1) / (DRAWS + 1))


def embedding(table: pd.DataFrame) -> pd.DataFrame:
    """Per NC, the networks without noise split by whether they embed their training data
    (E^closed < `EMBEDS`): how many are chaotic (λ_max > 0; in brackets > 10⁻⁴) and how many
    stay on one curve (switching < 0.02), with the permutation p over cells
    (`cell_permutation_p`) of the difference between the two groups."""
    quiet = table[table.noise_var == 0]
    rows = []
    for nc, part in quiet.groupby("context_size"):
        embeds = part.E_closed < EMBEDS
        cells = part[CELL].astype(str).agg("/".join, axis=1)
        row = {"NC": int(nc)}
        for name, flags, second in (
                ("chaotic", part.max_lyapunov > CHAOS, part.max_lyapunov > SENSITIVITY),
                ("stay on one curve", part.switch_prob < STAY, None)):
            for side, where in (("embed", embeds), ("do not", ~embeds)):
                extra = f" ({int(second[where].sum())})" if second is not None else ""
                row[f"{name}: {side}"] = f"{int(flags[where].sum())}{extra} / {int(where.sum())}"
            row[f"{name}: p over cells"] = f"{cell_permutation_p(flags, embeds, cells):.2g}"
        rows.append(row)
    return pd.DataFrame(rows)


def cell_means(table: pd.DataFrame) -> pd.DataFrame:
    """One row per cell without noise: its data NT·LT, mean E^closed, and the shares of its
    networks that are chaotic (λ_max > 0; `chaotic_sensitivity`: > 10⁻⁴) and that stay on one
    curve (switching < 0.02)."""
    quiet = table[table.noise_var == 0]
    cells = quiet.groupby(CELL).agg(
        E_closed=("E_closed", "mean"),
        chaotic=("max_lyapunov", lambda v: (v > CHAOS).mean()),
        chaotic_sensitivity=("max_lyapunov", lambda v: (v > SENSITIVITY).mean()),
        stay=("switch_prob", lambda v: (v < STAY).mean())).reset_index()
    cells["data"] = cells.num_series * cells.length
    return cells


def data_trend(cells: pd.DataFrame, column: str) -> dict[int, tuple[float, float]]:
    """Per NC: Spearman's ρ between the cells' `column` and their data NT·LT, with a permutation
    p over cells (cells, not networks, are the units: a cell's networks share their data and
    experts)."""
    return {int(nc): spearman(part.data.to_numpy(), part[column].to_numpy())
            for nc, part in cells.groupby("context_size")}


def _least_data(table: pd.DataFrame) -> dict[int, pd.DataFrame]:
    """Per NC, the networks without noise of the cells with the least data (NT·LT ≤ `SMALL`)."""
    quiet = table[table.noise_var == 0]
    return {int(nc): c for nc, c in quiet[quiet.num_series * quiet.length <= SMALL]
            .groupby("context_size")}


def chaos_against_data(table: pd.DataFrame) -> pd.DataFrame:
    """Per NC, Fig. 14b's two trends: networks chaotic (λ_max > 0; in brackets > 10⁻⁴) in the
    cells with the least data (NT·LT ≤ `SMALL`), and Spearman's ρ of a cell's chaotic share
    against NT·LT over the cells that embed their data (mean E^closed < `EMBEDS`) and over those
    that do not, under each criterion."""
    few_by_nc = _least_data(table)
    rows = []
    for nc, part in cell_means(table).groupby("context_size"):
        few = few_by_nc[int(nc)]
        sides = {"embed": part.E_closed < EMBEDS, "do not": part.E_closed >= EMBEDS}
        row = {"NC": int(nc), f"chaotic, NT·LT ≤ {SMALL}": f"{chaotic(few)} of {len(few)}",
               "cells that embed / do not": " / ".join(str(s.sum()) for s in sides.values())}
        for name, side in sides.items():
            trends = [spearman(part.data[side].to_numpy(), part[column][side].to_numpy())
                      for column in ("chaotic", "chaotic_sensitivity")]
            row[f"ρ over cells that {name}"] = "{:+.2f}, p {:.2g} ({:+.2f}, p {:.2g})".format(
                *trends[0], *trends[1])
        rows.append(row)
    return pd.DataFrame(rows)


def _per_nc(stats: dict, fmt, unit: str = "") -> str:
    return (" / ".join(fmt(v) for v in stats.values()) + unit + " at NC "
            + " / ".join(map(str, stats)))


def _trend(stats: dict) -> str:
    return _per_nc(stats, lambda v: f"{v[0]:+.2f} (p {v[1]:.2g})")


def _fig14a(table: pd.DataFrame, cells: pd.DataFrame, most: dict) -> dict:
    trend = data_trend(cells, "E_closed")
    quiet = table[table.noise_var == 0]
    large = quiet[quiet.num_series * quiet.length >= LARGE]
    embed = {int(nc): p for nc, p in large.groupby("context_size")}
    embedded = [int((p.E_closed < EMBEDS).sum()) for p in embed.values()]
    # grows with the data at every NC, and more networks embed the large data as NC grows
    reproduced = all(rho > 0 and p < 0.05 for rho, p in trend.values()) and \
        embedded == sorted(embedded) and embedded[0] < embedded[-1]
    return {"paper": "Fig. 14a", "claim": "E^closed grows with NT and LT and falls with NC",
            "moex": f"E^closed against NT·LT over cells, Spearman ρ {_trend(trend)}; networks "
                    f"that embed their data (E^closed < 10⁻²) among the "
                    f"{len(next(iter(embed.values())))} with NT·LT ≥ {LARGE}: "
                    + _per_nc(embed, lambda p: f"{(p.E_closed < EMBEDS).sum()}")
                    + f"; with the most data (NT {most['nt']}, LT {most['lt']}) E^closed "
                    + _per_nc(most["cells"], lambda c: f"{c.E_closed.mean():.3f}"),
            "verdict": "reproduced" if reproduced else "differs, cause open"}


def _fig14b(table: pd.DataFrame, cells: pd.DataFrame, most: dict) -> dict:
    split = embedding(table).set_index("NC")
    stays = "; ".join(
        f"NC {nc}: {r['stay on one curve: do not'].replace(' / ', ' of ')} against "
        f"{r['stay on one curve: embed'].replace(' / ', ' of ')} that embed it "
        f"(p {r['stay on one curve: p over cells']} over cells)" for nc, r in split.iterrows())
    chaos = data_trend(cells[cells.E_closed < EMBEDS], "chaotic")
    rising = [nc for nc, (rho, p) in chaos.items() if rho > 0 and p < 0.05]
    quiet = table[table.noise_var == 0]
    much = quiet[(quiet.context_size == 10) & (quiet.num_series >= 10) & (quiet.length >= 1000)]
    by_cell = much.groupby(["num_series", "length"])
    nc10 = {name: by_cell.max_lyapunov.apply(lambda v, t=t: int((v > t).sum()))
            for name, t in (("paper", CHAOS), ("sensitivity", SENSITIVITY))}
    nc10_stay = much.switch_prob < STAY
    few = _least_data(table)
    few_cells = cells[cells.data <= SMALL]
    few_rho, few_p = spearman(few_cells.context_size.to_numpy(), few_cells.chaotic.to_numpy())
    few_chaotic = [int((c.max_lyapunov > CHAOS).sum()) for c in few.values()]
    larger_nc_needs_more = few_chaotic == sorted(few_chaotic, reverse=True) and \
        few_chaotic[0] > few_chaotic[-1]
    stays_mostly = (nc10_stay.groupby([much.num_series, much.length]).mean() >= 0.5).any()
    if nc10["paper"].max() <= 3:
        nc10_text = "NC = 10 stays non-chaotic with much data"
    elif nc10["sensitivity"].max() <= 3:
        nc10_text = (f"NC = 10 with much data: {nc10_stay.sum()} of {len(much)} on one curve, but "
                     f"λ_max > 0 in up to {nc10['paper'].max()} of 10 (non-chaotic only above "
                     f"10⁻⁴)")
    else:
        nc10_text = "NC = 10 with much data is chaotic"
    growth = ("chaos growing with the data while it is embedded: significant at NC "
              + ", ".join(f"{nc} (p {chaos[nc][1]:.2g}; {chaos[nc][1] * len(chaos):.2g} for "
                          f"{len(chaos)} NCs)" for nc in rising) + " only" if rising else
              "chaos growing with the data: not significant at any NC")
    more = ("more data needed at larger NC: the paper's direction with the least data, "
            + ("" if few_p < 0.05 else "not significant ")
            + f"(ρ {few_rho:+.2f} over {len(few_cells)} cells, p {few_p:.2g})"
            if larger_nc_needs_more else "more data needed at larger NC: not seen")
    return {"paper": "Fig. 14b", "claim": "chaos appears as NT and LT grow, with more data needed "
                                         "at larger NC; with NC = 10 networks stay non-chaotic "
                                         "even with much data",
            "moex": "NC = 10 with NT ≥ 10 and LT ≥ 1000: λ_max > 0 in "
                    + ", ".join(map(str, nc10["paper"])) + " of 10 networks (> 10⁻⁴: "
                    + ", ".join(map(str, nc10["sensitivity"])) + f"), {nc10_stay.sum()} of "
                    f"{len(much)} stay on one curve; with the most data (NT {most['nt']}, LT "
                    f"{most['lt']}) chaotic "
                    + _per_nc(most["cells"], chaotic, " of 10")
                    + ", on one curve "
                    + _per_nc(most["cells"], lambda c: f"{(c.switch_prob < STAY).sum()}", " of 10")
                    + f". Networks that do not embed their data (E^closed ≥ 10⁻²) stay on one "
                    f"curve: {stays}. The share with λ_max > 0 against NT·LT, Spearman ρ over "
                    f"the cells whose mean E^closed is below 10⁻²: {_trend(chaos)}; over the "
                    f"others: {_trend(data_trend(cells[cells.E_closed >= EMBEDS], 'chaotic'))}. "
                    f"With the least data (NT·LT ≤ {SMALL}) chaotic "
                    + _per_nc(few, chaotic, f" of {len(next(iter(few.values())))}")
                    + f"; the share against NC over those cells: ρ {few_rho:+.2f} (p "
                    f"{few_p:.2g}). λ_max > 0 is the paper's criterion, > 10⁻⁴ in brackets",
            "verdict": (f"partly reproduced: {nc10_text}; a network whose data outgrows its "
                        f"memory stays on one curve at every NC; {growth}; {more}")
            if stays_mostly else "differs, cause open"}


# docs/fig16_arms.csv's arms (conf/p05_arm/), as the Fig. 16 row names them
ARMS = {"init_mregn": "the C code's initialisation", "learned_tau": "learned τ",
        "attraction": "u₀ attraction", "sigma_c": "the C code's σ floor",
        "c_code": "all of the C code's choices together",
        "targets_onehot": "one-hot phase-2 targets"}


def arms_at_noise(arms: pd.DataFrame, noise: float = 1e-3) -> pd.DataFrame:
    """docs/fig16_arms.csv per NC and arm: networks, those mostly nonperiodic at `noise`, and
    Fisher's exact p of that count against the same NC's baseline."""
    at = arms[arms.noise_var == noise]
    counts = at.groupby(["context_size", "arm"]).agg(
        networks=("run", "size"),
        mostly=("nonperiodic_fraction", lambda v: int((v > 0.5).sum()))).reset_index()
    base = counts[counts.arm == "baseline"].set_index("context_size")
    counts["p"] = [fisher_p(r.mostly, r.networks - r.mostly, base.mostly[r.context_size],
                            base.networks[r.context_size] - base.mostly[r.context_size])
                   for r in counts.itertuples()]
    return counts


def _fig16(table: pd.DataFrame, arms: pd.DataFrame) -> dict:
    smallest = table[(table.num_series == table.num_series.min())
                     & (table.length == table.length.min())]
    small = {int(nc): c for nc, c in smallest.groupby("context_size")}
    per_cell = [(mostly_nonperiodic(c, 1e-3), mostly_nonperiodic(c, 0))
                for _, c in table.groupby(CELL)]
    per_cell = [pair for pair in per_cell if all(isinstance(n, int) for n in pair)]
    raised = sum(after >= before for after, before in per_cell)
    contradicted = all(mostly_nonperiodic(c, 1e-3) > 5 for c in small.values())
    counts = arms_at_noise(arms)
    changed = counts[counts.arm != "baseline"]
    base = counts[counts.arm == "baseline"]
    return {"paper": "Fig. 16", "claim": "noise makes well-trained networks nonperiodic; "
                                        "small-data networks stay periodic",
            "moex": f"ρ² = 10⁻³ raises or keeps the count of mostly nonperiodic networks in "
                    f"{raised} of the {len(per_cell)} cells whose every network could be judged "
                    f"at both levels; in the smallest cell (NT "
                    f"{int(smallest.num_series.iloc[0])}, LT {int(smallest.length.iloc[0])}) "
                    + _per_nc(small, lambda c: f"{mostly_nonperiodic(c, 0)} → "
                                               f"{mostly_nonperiodic(c, 1e-3)}", " of 10")
                    + "; the same on 10 000 instead of 100 000 steps per sample; that cell "
                    "retrained on the same seeds with one change each ("
                    + ", ".join(ARMS[a] for a in sorted(changed.arm.unique())) + ") at NC "
                    + " and ".join(map(str, base.context_size))
                    + f": {changed.mostly.min()}-{changed.mostly.max()} of 10 mostly "
                    f"nonperiodic at 10⁻³ against the baseline's "
                    + " and ".join(map(str, base.mostly)) + f" (Fisher p ≥ {changed.p.min():.2g})",
            "verdict": ("first half reproduced; second **contradicted** at every NC, under both "
                        "periodicity rules, both window lengths and six changes to the model "
                        "or its training, cause open") if contradicted
            else "reproduced"}


def figure_rows(table: pd.DataFrame, arms: pd.DataFrame) -> pd.DataFrame:
    """The verdict rows of Figs. 14a, 14b and 16 (REPRODUCTION.md's figure table), from the
    grid's per-network table and the smallest cell's arms (docs/fig16_arms.csv)."""
    cells = cell_means(table)
    top = cells[cells.data == cells.data.max()].iloc[0]
    quiet = table[table.noise_var == 0]
    most = {"nt": int(top.num_series), "lt": int(top.length),
            "cells": {int(nc): c for nc, c in quiet[
                (quiet.num_series == top.num_series) & (quiet.length == top.length)]
                .groupby("context_size")}}
    return pd.DataFrame([_fig14a(table, cells, most), _fig14b(table, cells, most),
                         _fig16(table, arms)])


def main(mode: str, source: Path) -> None:
    if mode == "window":
        table = collect_window(source)
        table.to_csv(DOCS / "capacity_window10k_summary.csv", index=False)
        print(to_markdown(window_table(table, pd.read_csv(DOCS / "capacity_grid_summary.csv"))))
        return
    if mode in ("grid", "add"):
        name = "capacity_grid_summary.csv"
        table = (collect_grid(source) if mode == "grid" else
                 merge_cells([pd.read_csv(DOCS / name), read_report(source / "summary.csv")]))
        print(f"zero band (largest λ_max of an all-periodic network): {zero_band(table):.3g}")
        print(cell_tables(table))
        print(to_markdown(replication(table)))
    else:
        length = sys.argv[3] if len(sys.argv) > 3 else "1000"
        table = collect_evals(source)
        name = f"capacity_nt20{'' if length == '1000' else f'_lt{length}'}_summary.csv"
    table.to_csv(DOCS / name, index=False)
    print(to_markdown(summary(table)))


if __name__ == "__main__":
    try:
        main(sys.argv[1], Path(sys.argv[2]))
    except (FileNotFoundError, ValueError) as error:  # a missing folder, a network twice
        print(f"capacity_cells.py {sys.argv[1]}: {error}", file=sys.stderr)
        sys.exit(2)
