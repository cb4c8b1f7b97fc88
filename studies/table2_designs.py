"""Table 2 in two designs: 30 networks on one data set (Table 2 at full scale, seed 0) against
30 networks each on a data set of its own (`experiment=paper_table2_own_data`, seeds 100-129).

    python -m studies.table2_designs       # prints the Markdown table and the comparison

Reads docs/table2_summary.csv and docs/table2_own_data_summary.csv (`moex report` over the
own-data sweeps). The two designs share no seed, so they are compared unpaired: the difference
of the mean switching probability with its Welch standard error and a permutation p (design
labels shuffled), and the ratio of the variances with a permutation p. If networks on one data
set spread by the initialisation alone and networks on their own data sets by the
initialisation and the data, the variance the data adds is the difference of the two variances.
"stay" / "alternate" / "chaotic" as in studies/table2_onehot.py.
"""


import numpy as np
import pandas as pd

from moex.tasks.paper import PAPER_TABLE2
from studies.common import DOCS
from studies.table2_onehot import at_p, design_row, markdown

DRAWS = 20000


def _permutation_p(a: np.ndarray, b: np.ndarray, statistic) -> float:
    """Two-sided p of `statistic(a, b)` (0 under the null) with the labels of a and b shuffled;
    `statistic` works along the last axis."""
    both = np.concatenate([a, b])
    shuffled = np.random.default_rng(0).permuted(np.broadcast_to(both, (DRAWS, len(both))),
                                                 axis=1)
    null = np.abs(statistic(shuffled[:, :len(a)], shuffled[:, len(a):]))
    return float((1 + (null >= abs(statistic(a, b)) - 1e-15).sum()) / (DRAWS + 1))


def _mean_gap(a, b):
    return a.mean(axis=-1) - b.mean(axis=-1)


def _log_variance_ratio(a, b):
    return np.log(a.var(axis=-1, ddof=1) / b.var(axis=-1, ddof=1))


def table() -> tuple[pd.DataFrame, pd.DataFrame]:
    own = pd.read_csv(DOCS / "table2_own_data_summary.csv")
    one = pd.read_csv(DOCS / "table2_summary.csv")
    rows, tests = [], []
    for _, paper in PAPER_TABLE2.iterrows():
        p = paper["task.switch_prob"]
        mine, theirs = at_p(own, p), at_p(one, p)
        if mine.empty:
            continue
        for name, runs in (("one data set", theirs), ("a data set per network", mine)):
            rows.append({"P": p, "design": name, "paper": f"{paper['paper_switch_prob']:.3f}",
                         "data (mean)": f"{runs['data_switch_prob'].mean():.3f}",
                         **design_row(runs, paper["paper_switch_prob"])})
        a, b = mine["switch_prob"].to_numpy(), theirs["switch_prob"].to_numpy()
        se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
        added = a.var(ddof=1) - b.var(ddof=1)
        tests.append({
            "P": p, "networks (own / one)": f"{len(a)} / {len(b)}",
            "own − one, mean ± SE": f"{a.mean() - b.mean():+.3f} ± {se:.3f}",
            "permutation p (means)": f"{_permutation_p(a, b, _mean_gap):.2g}",
            "sd own / one": f"{a.std(ddof=1):.3f} / {b.std(ddof=1):.3f}",
            "permutation p (variances)": f"{_permutation_p(a, b, _log_variance_ratio):.2g}",
            "variance the data adds (share)": f"{added:+.4f} ({added / a.var(ddof=1):+.0%})",
            "λ_max own / one": f"{mine['max_lyapunov'].mean():.4f} / "
                               f"{theirs['max_lyapunov'].mean():.4f}",
        })
    return pd.DataFrame(rows), pd.DataFrame(tests)


if __name__ == "__main__":
    rows, tests = table()
    print(markdown(rows), "", markdown(tests), sep="\n")
