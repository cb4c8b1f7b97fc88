"""How much the data realisation decides (open question 0): the data-seed experiments' variance
splits, recomputed from the per-network CSVs `moex report` wrote over each sweep.

    python -m studies.data_seeds            # every experiment: per-data-set tables and the splits
    python -m studies.data_seeds overview   # only the overview table REPRODUCTION.md quotes

Each experiment (EXPERIMENTS) trains the same initial networks (seed 0: Table 1's or Table 2's
networks 0, 1, ...) on several data sets (`task.data_seed`), a crossed design. For each metric:
- one-way random-effects splits, once by data set and once by initial network (the `run` index),
  each with the share of the variance it explains (intraclass correlation) and a permutation
  p-value (labels shuffled 20 000 times; no SciPy needed);
- the two-way additive split of the crossed design: variance components of the data set, the
  initial network and the rest (their interaction and round-off), with a restricted permutation
  test for the data set (data-set labels shuffled within each initial network, so the network's
  effect is held fixed).
"""

import sys

import numpy as np
import pandas as pd

from moex.report import to_markdown
from studies.common import DOCS

KEY = "task.data_seed"
STAYS = 0.03  # a network below this switching probability stays on one curve
PERMUTATIONS = 20000
LISSAJOUS = ("switch_prob", "max_lyapunov", "nonperiodic_fraction")
REBER = ("block_kl_test", "block_kl_train", "E_g", "max_lyapunov")
# name -> (per-network CSV in docs/, metrics)
EXPERIMENTS = {
    "Table 2, P = 0.5": ("data_seeds_p05_summary.csv", LISSAJOUS),
    "Table 2, P = 0.25": ("data_seeds_summary.csv", LISSAJOUS),
    "Table 2, P = 0.125": ("data_seeds_p0125_summary.csv", LISSAJOUS),
    "Table 1, NC = 20": ("data_seeds_reber_summary.csv", REBER),
}


def _f_statistic(values: np.ndarray, groups: np.ndarray) -> tuple[float, float, float]:
    """(F, between-group variance component, within-group variance) of a balanced one-way
    design."""
    labels = np.unique(groups)
    n = len(values) // len(labels)
    means = np.array([values[groups == g].mean() for g in labels])
    within = np.mean([values[groups == g].var(ddof=1) for g in labels])
    between = n * means.var(ddof=1)
    return between / within, max((between - within) / n, 0.0), within


def split(runs: pd.DataFrame, metric: str, key: str = KEY,
          permutations: int = PERMUTATIONS) -> dict:
    values, groups = runs[metric].to_numpy(float), runs[key].to_numpy()
    f, between, within = _f_statistic(values, groups)
    rng = np.random.default_rng(0)
    null = [_f_statistic(values, rng.permutation(groups))[0] for _ in range(permutations)]
    what = "data sets" if key == KEY else "initial networks"
    return {"metric": metric, "mean": values.mean(), f"sd between {what}": np.sqrt(between),
            "sd within": np.sqrt(within),
            f"share of variance from the {what}": between / (between + within),
            "permutation p": (1 + sum(x >= f for x in null)) / (1 + permutations)}


def _mean_squares(tables: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean squares (data set, network, residual) of data set × network tables without
    replication, additive model; the last two axes are rows (data sets) and columns (networks),
    any leading axes index tables of their own."""
    d, n = tables.shape[-2:]
    grand = tables.mean(axis=(-2, -1), keepdims=True)
    rows, cols = tables.mean(axis=-1, keepdims=True), tables.mean(axis=-2, keepdims=True)
    ms_data = n * ((rows - grand) ** 2).sum(axis=(-2, -1)) / (d - 1)
    ms_net = d * ((cols - grand) ** 2).sum(axis=(-2, -1)) / (n - 1)
    ms_res = ((tables - rows - cols + grand) ** 2).sum(axis=(-2, -1)) / ((d - 1) * (n - 1))
    return ms_data, ms_net, ms_res


def components(table: np.ndarray) -> tuple[float, float, float]:
    """Variance components (data set, network, rest) of one data set × network table."""
    d, n = table.shape
    ms_data, ms_net, ms_res = _mean_squares(table)
    return max((ms_data - ms_res) / n, 0.0), max((ms_net - ms_res) / d, 0.0), float(ms_res)


def two_way(runs: pd.DataFrame, metric: str, permutations: int = PERMUTATIONS) -> dict:
    table = runs.pivot(index=KEY, columns="run", values=metric).to_numpy(float)
    data, network, rest = components(table)
    ms_data, _, ms_res = _mean_squares(table)
    rng = np.random.default_rng(0)
    shuffled = rng.permuted(np.broadcast_to(table, (permutations, *table.shape)), axis=1)
    null_data, _, null_res = _mean_squares(shuffled)
    total = data + network + rest
    return {"metric": metric, "data sets × networks": f"{table.shape[0]} × {table.shape[1]}",
            "mean": table.mean(), "sd over all": np.sqrt(total),
            "share: data set": data / total, "share: initial network": network / total,
            "share: rest": rest / total,
            "data set p": (1 + int((null_data / null_res >= ms_data / ms_res).sum()))
                          / (1 + permutations)}


def load(csv: str) -> pd.DataFrame | None:
    """The experiment's finished networks; None while its CSV is not in docs/. Only data sets
    with every network are kept (the design must stay balanced)."""
    path = DOCS / csv
    if not path.is_file():
        return None
    runs = pd.read_csv(path)
    runs = runs[~runs["failed"].astype(bool)]
    full = runs.groupby(KEY)["run"].transform("size") == runs["run"].nunique()
    return runs[full]


def overview() -> pd.DataFrame:
    """One row per experiment and metric: the two-way split, rounded for REPRODUCTION.md."""
    rows = []
    for name, (csv, metrics) in EXPERIMENTS.items():
        runs = load(csv)
        if runs is None:
            continue
        for metric in metrics:
            row = two_way(runs, metric)
            rows.append({"experiment": name, "metric": metric,
                         "data sets × networks": row["data sets × networks"],
                         "mean ± sd": f"{row['mean']:.3g} ± {row['sd over all']:.2g}",
                         **{k: f"{row[k]:.0%}" for k in row if k.startswith("share")},
                         "data set p": f"{row['data set p']:.2g}"})
    return pd.DataFrame(rows)


def per_data_set(runs: pd.DataFrame) -> pd.DataFrame:
    if (runs["task.name"] == "lissajous2").all():
        agg = {"switch_prob": ("switch_prob", "mean"), "switch_sd": ("switch_prob", "std"),
               "stay_on_one_curve": ("switch_prob", lambda x: int((x < STAYS).sum())),
               "data_switch_prob": ("data_switch_prob", "first")}
    else:
        agg = {"E_g": ("E_g", "mean"), "block_kl_train": ("block_kl_train", "mean"),
               "block_kl_test": ("block_kl_test", "mean"),
               "block_kl_test_median": ("block_kl_test", "median")}
    agg |= {"networks": ("run", "size"), "max_lyapunov": ("max_lyapunov", "mean"),
            "positive": ("max_lyapunov", lambda x: int((x > 0).sum()))}
    return runs.groupby(KEY).agg(**agg).reset_index()


def main(argv: list[str]) -> None:
    if argv[1:] == ["overview"]:
        print(to_markdown(overview()))
        return
    for name, (csv, metrics) in EXPERIMENTS.items():
        runs = load(csv)
        if runs is None:
            print(f"## {name}: docs/{csv} not there (not run)\n")
            continue
        print(f"## {name} (docs/{csv})\n")
        print(to_markdown(per_data_set(runs)))
        print(to_markdown(pd.DataFrame([split(runs, m) for m in metrics])))
        print(to_markdown(pd.DataFrame([split(runs, m, "run") for m in metrics])))
        print(to_markdown(pd.DataFrame([two_way(runs, m) for m in metrics])))
    print("## Overview\n")
    print(to_markdown(overview()))


if __name__ == "__main__":
    main(sys.argv)
