"""How much the data realisation decides: the data-seed experiment's variance split, recomputed
from docs/data_seeds_summary.csv (written by `moex report` over the `data_seeds` sweep).

    python docs/data_seeds.py

One-way random-effects split of each metric over networks into a between-data-set part and a
within-data-set part (the same initial networks on every data set), the share of the variance
the data set explains (intraclass correlation), and a permutation p-value for "the data set
makes no difference" (data-set labels shuffled 20 000 times; no SciPy needed); then the same
split by initial network (the `run` index: network r starts from the same weights on every data
set), which asks whether the network, rather than the data, decides.
"""

from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown

DOCS = Path(__file__).resolve().parent
KEY = "task.data_seed"
STAYS = 0.03  # a network below this switching probability stays on one curve


def _f_statistic(values: np.ndarray, groups: np.ndarray) -> tuple[float, float, float]:
    """(F, between-set variance component, within-set variance) of a balanced one-way design."""
    labels = np.unique(groups)
    n = len(values) // len(labels)
    means = np.array([values[groups == g].mean() for g in labels])
    within = np.mean([values[groups == g].var(ddof=1) for g in labels])
    between = n * means.var(ddof=1)
    return between / within, max((between - within) / n, 0.0), within


def split(runs: pd.DataFrame, metric: str, key: str = KEY, permutations: int = 20000) -> dict:
    values, groups = runs[metric].to_numpy(float), runs[key].to_numpy()
    f, between, within = _f_statistic(values, groups)
    rng = np.random.default_rng(0)
    null = [_f_statistic(values, rng.permutation(groups))[0] for _ in range(permutations)]
    what = "data sets" if key == KEY else "initial networks"
    return {"metric": metric, "mean": values.mean(), f"sd between {what}": np.sqrt(between),
            "sd within": np.sqrt(within),
            f"share of variance from the {what}": between / (between + within),
            "permutation p": (1 + sum(x >= f for x in null)) / (1 + permutations)}


def main() -> None:
    runs = pd.read_csv(DOCS / "data_seeds_summary.csv")
    runs = runs[~runs["failed"].astype(bool)]
    per_set = runs.groupby(KEY).agg(
        networks=("run", "size"), switch_prob=("switch_prob", "mean"),
        switch_sd=("switch_prob", "std"), stay_on_one_curve=("switch_prob",
                                                             lambda x: int((x < STAYS).sum())),
        max_lyapunov=("max_lyapunov", "mean"), positive=("max_lyapunov",
                                                         lambda x: int((x > 0).sum())),
        data_switch_prob=("data_switch_prob", "first"))
    print(to_markdown(per_set.reset_index()))
    metrics = ("switch_prob", "max_lyapunov", "nonperiodic_fraction")
    print(to_markdown(pd.DataFrame([split(runs, m) for m in metrics])))
    per_network = runs.groupby("run").agg(
        data_sets=(KEY, "size"), switch_prob=("switch_prob", "mean"),
        switch_min=("switch_prob", "min"), switch_max=("switch_prob", "max"),
        stay_on_one_curve=("switch_prob", lambda x: int((x < STAYS).sum())))
    print(to_markdown(per_network.reset_index()))
    print(to_markdown(pd.DataFrame([split(runs, m, "run") for m in metrics])))


if __name__ == "__main__":
    main()
